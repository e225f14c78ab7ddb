"""What the commands share: the user's input error (printed without a traceback) and the readers
of the files every command takes (a site reference, a calibration record)."""
from __future__ import annotations

from ..core.coeffs import Calibration, CoefficientError
from ..core.frames import Site
from ..core.geomag import load_site_file


class UserError(Exception):
    """An error in the user's input: printed without a traceback."""


def load_site(path) -> Site:
    """The site of a ``--site`` file (:func:`geomag.load_site_file`; None: the default site); a bad
    one is a :class:`UserError` line naming the file and the key."""
    if path is None:
        return Site()
    try:
        return load_site_file(path)
    except ValueError as exc:
        raise UserError(str(exc)) from None


def load_calibration(spec):
    if spec is None or str(spec).lower() == "none":
        return None
    try:
        return Calibration.load(spec)
    except OSError as exc:
        raise UserError(f"{spec}: {exc.strerror}") from None
    except CoefficientError as exc:
        raise UserError(str(exc)) from None
