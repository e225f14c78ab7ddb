"""The source files the tests read as code (``ast``), each parsed once per test process: the
package's layers, its one-place-for-each-idea checks, its declared imports and its ROS-free core
read the same ~100 modules (0.7 CPU-s a parse of them all)."""
import ast
import functools
import pathlib

ROOT = pathlib.Path(__file__).resolve().parents[1]
PKG = ROOT / "inclinometer_calib"


def files(folder: pathlib.Path = PKG) -> list:
    """The ``*.py`` files under ``folder`` (compiled caches left out), in a stable order."""
    return sorted(p for p in folder.rglob("*.py") if "__pycache__" not in p.parts)


@functools.lru_cache(maxsize=None)
def _parsed(path: str) -> ast.Module:
    with open(path, encoding="utf-8") as fh:
        return ast.parse(fh.read(), path)


def parse(path) -> ast.Module:
    """The parsed source of ``path`` (shared: do not change the tree)."""
    return _parsed(str(pathlib.Path(path).resolve()))
