"""Progress bars for the commands that may run longer than a few seconds (tqdm, on standard error).

One place for how they look: shown only on a terminal (a log file or a test's captured output
gets none, so that its lines stay the command's own), cleared when done, counts in thousands
shown as such.  A bar that is not shown costs a comparison per update.
"""
from __future__ import annotations

import sys


def progress_bar(total: int, unit: str, desc: str, enabled: bool = True):
    """A tqdm bar of ``total`` ``unit`` (``None``: unknown) named ``desc``; ``enabled=False`` or
    standard error not a terminal: none shown."""
    from tqdm import tqdm

    return tqdm(total=total, unit=unit, desc=desc, disable=None if enabled else True, smoothing=0.1,
                unit_scale=True, leave=False, file=sys.stderr, dynamic_ncols=True)
