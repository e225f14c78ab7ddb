"""What the commands share: the user's input error (printed without a traceback) and the readers
of the files every command takes (a site reference, a calibration record)."""
from __future__ import annotations

import yaml

from ..core.coeffs import Calibration, CoefficientError
from ..core.frames import Site
from ..core.geomag import site_from_config


class UserError(Exception):
    """An error in the user's input: printed without a traceback."""


def load_site(path) -> Site:
    if path is None:
        return Site()
    try:
        with open(path, encoding="utf-8") as fh:
            d = yaml.safe_load(fh)
        return site_from_config(d.get("site", d) if isinstance(d, dict) else {})
    except (OSError, yaml.YAMLError, ValueError, TypeError) as exc:
        raise UserError(f"{path}: cannot read site reference: {exc}") from None


def load_calibration(spec):
    if spec is None or str(spec).lower() == "none":
        return None
    try:
        return Calibration.load(spec)
    except OSError as exc:
        raise UserError(f"{spec}: {exc.strerror}") from None
    except CoefficientError as exc:
        raise UserError(str(exc)) from None
