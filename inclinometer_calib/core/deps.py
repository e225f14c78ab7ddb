"""Optional dependencies: import them where they are needed, or say in one line how to get them.

``pip install .`` installs the core only: numpy, scipy, PyYAML and what the core's own commands
need (the site's field and projection — pygeomag, ppigrf, pyproj —, WITSML's lxml, threadpoolctl,
tqdm).  The rest comes with extras declared in
``setup.py``:

=========  ==========================================  =============================================
extra      distributions                               needed by
=========  ==========================================  =============================================
report     matplotlib                                  ``lab report`` (:mod:`.lab.report`), reports'
                                                       plots
bag        mcap, zstandard, lz4, rosbags               ``reprocess``, writing bags (:mod:`.bag`,
                                                       :mod:`.reprocess`), the launcher's summary
lab        scikit-learn                                the lab's discovery beyond the catalogue
fleet      sqlalchemy, alembic, psycopg, dask,         ``fleet ...`` (:mod:`.fleet`): the registry,
           distributed, pyarrow                        reprocessing on Dask into Parquet
live       foxglove-sdk                                the live view (``--foxglove-port``)
fast       numba, pyarrow                              the fused batch kernel and the column-wise
                                                       probe-log reader (each has a fallback: the
                                                       numpy path, the row reader)
all        every one of them
=========  ==========================================  =============================================

:func:`require` imports a module of one of them and, when it is missing, raises
:class:`MissingDependency` whose message names the purpose, the missing distribution and the pip
command; the CLI prints it as ``error: <message>`` (exit status 2, no traceback).
"""
from __future__ import annotations

import importlib
import importlib.util
from types import ModuleType

#: The pip requirement that installs this package with an extra (quoted for the shell).
PIP_TARGET = "inclinometer_calib[{extra}]"


class MissingDependency(ImportError):
    """An optional dependency is not installed; the message says which extra provides it."""

    def __init__(self, module: str, extra: str, purpose: str):
        self.module = module
        self.extra = extra
        self.purpose = purpose
        super().__init__(f"{purpose} needs {module}, which is not installed: "
                         f"pip install '{PIP_TARGET.format(extra=extra)}'", name=module)


def require(module: str, extra: str, purpose: str) -> ModuleType:
    """Import ``module`` (e.g. ``"matplotlib"``, ``"rosbags.typesys"``) and return it.

    Raises :class:`MissingDependency` if it (or a module it imports) is not installed; the
    message names the missing top-level module (for our optional dependencies the same as the
    PyPI distribution), ``purpose`` (what the user was doing, e.g. ``"lab report"``) and the
    ``pip install 'inclinometer_calib[<extra>]'`` that provides it.  Other import errors (an
    installed package that is broken or too old) propagate unchanged.
    """
    try:
        return importlib.import_module(module)
    except ModuleNotFoundError as exc:
        missing = (exc.name or module).split(".")[0]
        raise MissingDependency(missing, extra, purpose) from exc


def installed(module: str) -> bool:
    """Whether ``module`` can be imported (found, not imported: the choice between a fast path and
    its fallback, made without the import's cost)."""
    try:
        return importlib.util.find_spec(module) is not None
    except (ImportError, ValueError):
        return False
