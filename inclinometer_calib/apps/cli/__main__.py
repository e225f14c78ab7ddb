"""``python -m inclinometer_calib.apps.cli``: the command line without the console script."""
import sys

from . import main

sys.exit(main())
