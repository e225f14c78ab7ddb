"""Writing output files: whole or not at all, and a refusal said in one line.

Every file a command writes goes through here.  A file is written under a temporary name beside
it and renamed into place once complete (:func:`atomic_write_text`, :func:`atomic_write_bytes`;
:func:`output_path` for a writer that writes by name, such as a bag's; :func:`output_folder` for a
command's several files): a full disk or a refused
write never leaves a half-written file under the name asked for.  What the file system
refuses becomes an :class:`OutputError` naming the path and the cause in words — a missing
folder, a folder that may not be written, a full disk — which the CLI prints as one line
(``error: cannot write out/stations.csv: no space left on the device (ENOSPC)``) with exit status 2.
:func:`check_output` says it before a long computation, not after.
"""
from __future__ import annotations

import errno
import os
import re
import shutil
import tempfile
from contextlib import contextmanager
from pathlib import Path

#: A refusal of the OS in words: errno → (short reason, description).
_WORDS = {
    errno.ENOSPC: ("disk full", "no space left on the device"),
    errno.EDQUOT: ("disk quota exceeded", "the disk quota is exceeded"),
    errno.EFBIG: ("file too large", "the file is larger than the file system or a limit allows"),
    errno.EIO: ("I/O error", "the disk reported an input/output error"),
    errno.EACCES: ("permission denied", "permission denied"),
    errno.EPERM: ("permission denied", "the operation is not permitted"),
    errno.EROFS: ("read-only", "the file system is read-only"),
    errno.EISDIR: ("a folder", "it is a folder"),
    errno.ENOTDIR: ("not a folder", "a part of the path is not a folder"),
    errno.ENAMETOOLONG: ("name too long", "the name is too long"),
}


def refused_write_words(exc: OSError):
    """(short reason, one-line description) of a write the OS refused, for people:
    ``("disk full", "no space left on the device (ENOSPC)")``; others by strerror and errno name."""
    text = exc.strerror or str(exc)
    short, long = _WORDS.get(exc.errno, (text, text))
    if exc.errno is None:          # a refusal said in words only: no errno name to add
        return short, long
    return short, f"{long} ({errno.errorcode.get(exc.errno, str(exc.errno))})"


class OutputError(OSError):
    """An output file that cannot be written: the path and the cause, in one line.  An
    ``OSError`` (with the refusal's ``errno``, None when found out beforehand), so that code that
    handles the OS's refusals handles it too."""

    def __init__(self, path, cause: str, errno_: int | None = None):
        super().__init__(f"cannot write {os.fspath(path)}: {cause}")
        self.path = os.fspath(path)
        self.cause = cause
        self.errno = errno_

    def __str__(self) -> str:
        return self.args[0]

    @classmethod
    def from_os(cls, path, exc: OSError) -> "OutputError":
        if isinstance(exc, OutputError):
            return exc
        folder = os.path.dirname(os.path.abspath(os.fspath(path)))
        if exc.errno == errno.ENOENT and not os.path.isdir(folder):
            cause = f"the folder {folder} does not exist"
        else:
            cause = refused_write_words(exc)[1]
        return cls(path, cause, exc.errno)


class OutputExistsError(FileExistsError):
    """An output that exists already (the writers here never replace one), said in words:
    ``x.mcap already exists; refusing to overwrite it (choose another output name)``, the
    wording of :class:`io.bag.BagWriter`'s refusal.  ``errno`` EEXIST, ``filename`` the path."""

    def __init__(self, path, text: str | None = None):
        p = os.fspath(path)
        super().__init__(errno.EEXIST, text or exists_words(p), p)

    def __str__(self) -> str:
        return self.strerror


def exists_words(path) -> str:
    """The one line for an output that exists already."""
    return f"{os.fspath(path)} already exists; refusing to overwrite it (choose another output name)"


def _names_output(exc: OSError, *paths) -> bool:
    """Whether ``exc`` is a refusal of writing the output at ``paths`` (a file, or a folder and
    what is in it): it names one of them, or names no file and carries the OS's error number (a
    writer's refusal: a full disk, a stale NFS handle...).  Anything else raised while the output
    is written (an input that does not exist or is refused, named; the package's own words without
    an error number) is the input's error and keeps its own words."""
    named = [os.fsdecode(f) for f in (exc.filename, exc.filename2) if isinstance(f, (str, bytes, os.PathLike))]
    if not named:
        return exc.errno is not None
    outs = [os.path.abspath(os.fspath(p)) for p in paths]
    return any(f == o or f.startswith(o + os.sep) for f in map(os.path.abspath, named) for o in outs)


def check_output(path, *, folder: bool = False) -> None:
    """Raise :class:`OutputError` when ``path`` cannot be written: its folder missing or not
    writable, or ``path`` an existing folder (a file asked for) or file (``folder``: a folder
    asked for).  Said before the work, so that a long run does not end in a refusal."""
    p = os.fspath(path)
    parent = os.path.dirname(os.path.abspath(p))
    if not os.path.isdir(parent):
        raise OutputError(p, f"the folder {parent} does not exist")
    if not os.access(parent, os.W_OK | os.X_OK):
        if os.statvfs(parent).f_flag & os.ST_RDONLY:
            raise OutputError(p, "the file system is read-only (EROFS)", errno.EROFS)
        raise OutputError(p, f"the folder {parent} may not be written: permission denied (EACCES)", errno.EACCES)
    if not folder and os.path.isdir(p):
        raise OutputError(p, "it is a folder")
    if folder and os.path.exists(p) and not os.path.isdir(p):
        raise OutputError(p, "a file of that name exists")


def _ordinary_permissions(path) -> None:
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(path, 0o666 & ~umask)        # mkstemp creates 0600


def atomic_write_bytes(path, data: bytes) -> None:
    """Write ``data`` to ``path`` through a temporary file in the same folder and a rename: the
    file is whole or absent (the temporary one removed).  :class:`OutputError` when refused."""
    p = os.fspath(path)
    try:
        fd, tmp = tempfile.mkstemp(prefix=".tmp-", dir=os.path.dirname(os.path.abspath(p)))
    except OSError as exc:
        raise OutputError.from_os(p, exc) from None
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
            fh.flush()
            os.fsync(fh.fileno())
        _ordinary_permissions(tmp)
        os.replace(tmp, p)
    except BaseException as exc:
        if os.path.exists(tmp):
            os.unlink(tmp)
        if isinstance(exc, OSError) and not isinstance(exc, OutputError):
            raise OutputError.from_os(p, exc) from None
        raise


def atomic_write_text(path, text: str) -> None:
    """:func:`atomic_write_bytes` of ``text`` in UTF-8."""
    atomic_write_bytes(path, text.encode("utf-8"))


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    else:
        path.unlink(missing_ok=True)


_PART = re.compile(r"^\.(?P<stem>.+)\.part-\d+(?P<suffix>\.[^.]*)?$")


def final_name(path) -> Path:
    """The name a file written under :func:`output_path`'s temporary name (``.x.part-<pid>.mcap``)
    will have (``x.mcap``); any other path unchanged.  What a file records of its own name (a
    bag's rosbag2 metadata) is this, not the temporary name."""
    p = Path(path)
    m = _PART.match(p.name)
    return p.with_name(m["stem"] + (m["suffix"] or "")) if m else p


@contextmanager
def output_path(path):
    """A name for a writer that writes by name (a bag), ``path`` must not exist (the writers here
    never replace an output).  A file (``x.mcap``): ``.x.part-<pid>.mcap`` beside it, renamed to
    ``path`` when the block ends, removed when it raises.  A folder (a rosbag2 directory, whose
    files are named after it): ``path`` itself, removed with what it holds when the block raises.
    A refusal of the OS to write the output (inside the block or at the rename) becomes
    :class:`OutputError` naming ``path``; any other error of the block (an input's) is raised as
    it is.  An existing ``path``: :class:`OutputExistsError`."""
    p = Path(path)
    folder = p.suffix == ""
    if p.exists():
        raise OutputExistsError(p)
    check_output(p, folder=folder)
    tmp = p if folder else p.with_name(f".{p.stem}.part-{os.getpid()}{p.suffix}")
    if not folder:
        _remove(tmp)
    try:
        yield tmp
        if not folder:
            if p.exists():
                raise OutputExistsError(p, f"{p} appeared while it was written; refusing to overwrite it "
                                           "(choose another output name)")
            os.rename(tmp, p)
    except BaseException as exc:
        _remove(tmp)
        if isinstance(exc, OSError) and not isinstance(exc, (FileExistsError, OutputError)) \
                and _names_output(exc, p, tmp):
            raise OutputError.from_os(p, exc) from None
        raise


@contextmanager
def output_folder(path):
    """A folder for a command's several files.  A new one is made under a temporary name beside it
    (``.<name>.part-<pid>``) and renamed into place when the block ends, removed with what it holds
    when the block raises: all the files or none.  An existing folder is used as it is (each file
    in it written whole).  A refusal of the OS to write in it becomes :class:`OutputError` naming
    ``path``; any other error of the block (an input's) is raised as it is."""
    p = Path(path)
    check_output(p, folder=True)
    existing = p.exists()
    tmp = p if existing else p.with_name(f".{p.name}.part-{os.getpid()}")
    try:
        if not existing:
            _remove(tmp)
            tmp.mkdir()
        yield tmp
        if not existing:
            os.rename(tmp, p)
    except BaseException as exc:
        if not existing:
            _remove(tmp)
        if isinstance(exc, OutputError) and not existing:   # said of the folder's own name
            raise OutputError(exc.path.replace(os.fspath(tmp), os.fspath(p), 1), exc.cause, exc.errno) from None
        if isinstance(exc, OSError) and not isinstance(exc, OutputError) and _names_output(exc, p, tmp):
            raise OutputError.from_os(p, exc) from None
        raise
