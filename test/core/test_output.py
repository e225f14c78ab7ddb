"""Output files are whole or absent, and a refusal is one line (inclinometer_calib.core.output).

The full disk is real: a tmpfs mounted in a mount namespace of the command's own
(``unshare --mount``, which needs root or CAP_SYS_ADMIN; without it those tests are skipped and
say what is missing), filled before the command runs (``full_disk``, test/conftest.py).  A missing
folder needs nothing."""
import errno
import os
import re
import subprocess
import sys

import pytest

from inclinometer_calib.apps import cli
from inclinometer_calib.core.output import (OutputError, atomic_write_text, check_output, output_folder,
                                       output_path)


# ---- the module ---------------------------------------------------------------------------------

def test_a_write_into_a_missing_folder_names_the_folder_and_is_an_os_error(tmp_path):
    with pytest.raises(OutputError) as info:
        atomic_write_text(tmp_path / "nowhere" / "x.yaml", "a: 1\n")
    assert str(info.value) == f"cannot write {tmp_path / 'nowhere' / 'x.yaml'}: the folder {tmp_path / 'nowhere'} " \
                              "does not exist"
    assert isinstance(info.value, OSError)
    with pytest.raises(OutputError, match="it is a folder"):
        check_output(tmp_path)


def test_a_writer_that_fails_leaves_neither_the_file_nor_its_temporary(tmp_path):
    target = tmp_path / "run.mcap"
    with pytest.raises(OutputError, match=re.escape(f"cannot write {target}: no space left on the device (ENOSPC)")):
        with output_path(target) as tmp:
            assert tmp.parent == tmp_path and tmp.suffix == ".mcap" and tmp.name.startswith(".run.part-")
            tmp.write_bytes(b"partial")
            raise OSError(errno.ENOSPC, "No space left on device")
    assert list(tmp_path.iterdir()) == []
    with output_path(target) as tmp:
        tmp.write_bytes(b"whole")
    assert target.read_bytes() == b"whole" and list(tmp_path.iterdir()) == [target]
    with pytest.raises(FileExistsError, match="refusing to overwrite"):
        with output_path(target):
            pass


def test_a_new_folder_of_several_files_appears_whole_or_not_at_all(tmp_path):
    with pytest.raises(OutputError, match=re.escape(f"cannot write {tmp_path / 'sim' / 'b.csv'}: the disk is full")):
        with output_folder(tmp_path / "sim") as out:
            atomic_write_text(out / "a.csv", "1\n")
            raise OutputError(out / "b.csv", "the disk is full", errno.ENOSPC)
    assert list(tmp_path.iterdir()) == []
    with output_folder(tmp_path / "sim") as out:
        atomic_write_text(out / "a.csv", "1\n")
    assert [p.name for p in tmp_path.iterdir()] == ["sim"] and (tmp_path / "sim" / "a.csv").read_text() == "1\n"


def test_an_inputs_error_inside_the_block_keeps_its_own_words_and_is_not_said_of_the_output(tmp_path):
    missing = FileNotFoundError(f"{tmp_path / 'in.mcap'}: no such bag file or directory")   # io.bag's, no errno
    refused = PermissionError(errno.EACCES, "Permission denied", str(tmp_path / "in.mcap"))  # the OS's, naming it
    for exc in (missing, refused):
        with pytest.raises(type(exc)) as info:
            with output_path(tmp_path / "out.mcap") as tmp:
                tmp.write_bytes(b"partial")
                raise exc
        assert info.value is exc and not isinstance(info.value, OutputError)
        with pytest.raises(type(exc)) as info:
            with output_folder(tmp_path / "sim") as out:
                atomic_write_text(out / "a.csv", "1\n")
                raise exc
        assert info.value is exc and not isinstance(info.value, OutputError)
        assert list(tmp_path.iterdir()) == []            # and still no partial output
    # a refusal naming the output (or naming no file: a writer's full disk) is the output's
    with pytest.raises(OutputError, match=re.escape(f"cannot write {tmp_path / 'out.mcap'}: permission denied")):
        with output_path(tmp_path / "out.mcap") as tmp:
            raise PermissionError(errno.EACCES, "Permission denied", str(tmp))
    with pytest.raises(OutputError, match=re.escape(f"cannot write {tmp_path / 'sim'}: no space left")):
        with output_folder(tmp_path / "sim") as out:
            raise OSError(errno.ENOSPC, "No space left on device", str(out / "a.csv"))
    assert list(tmp_path.iterdir()) == []


def test_a_refusal_said_in_words_only_gets_no_errno_name():
    from inclinometer_calib.core.output import refused_write_words

    assert refused_write_words(OSError("the writer gave up")) == ("the writer gave up", "the writer gave up")
    assert refused_write_words(OSError(errno.ENOSPC, "No space left on device"))[1] == \
        "no space left on the device (ENOSPC)"


def test_an_existing_output_is_refused_in_plain_words_without_errno_text(tmp_path):
    target = tmp_path / "run.mcap"
    target.write_bytes(b"earlier")
    with pytest.raises(FileExistsError) as info:
        with output_path(target):
            pass
    assert str(info.value) == f"{target} already exists; refusing to overwrite it (choose another output name)"
    assert info.value.errno == errno.EEXIST and info.value.filename == str(target)
    assert target.read_bytes() == b"earlier" and list(tmp_path.iterdir()) == [target]


# ---- the commands ----------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def logs(tmp_path_factory):
    d = tmp_path_factory.mktemp("logs")
    assert cli.main(["simulate", "--out", str(d / "sim"), "--seed", "2", "--station-seconds", "0.6", "--rate", "25"]) == 0
    assert cli.main(["twelve-position", str(d / "sim" / "cal.csv"), "-o", str(d / "coeffs.yaml")]) == 0
    assert cli.main(["bag", "from-csv", str(d / "sim" / "val.csv"), "-o", str(d / "val.mcap")]) == 0
    return d


def _commands(d):
    """Each command that writes, with its output named ``OUT`` (a file or, for simulate, a folder)."""
    return {
        "simulate": ["simulate", "--out", "OUT", "--seed", "2", "--station-seconds", "0.6", "--rate", "25"],
        "twelve-position": ["twelve-position", d / "sim" / "cal.csv", "-o", "OUT"],
        "correct": ["correct", d / "sim" / "val.csv", "--coeffs", d / "coeffs.yaml", "-o", "OUT"],
        "bag from-csv": ["bag", "from-csv", d / "sim" / "val.csv", "-o", "OUT"],
        "reprocess": ["reprocess", d / "val.mcap", "--coeffs", d / "coeffs.yaml", "-o", "OUT"],
        "lab report": ["lab", "report", "--cal", d / "sim" / "cal.csv", "--val", d / "sim" / "val.csv", "-o", "OUT",
                       "--quiet", "--max-steps", "1"],
    }


OUTPUT_NAME = {"simulate": "sim", "twelve-position": "c.yaml", "correct": "s.csv", "bag from-csv": "v.mcap",
               "reprocess": "r.mcap", "lab report": "r.html"}


def _argv(args, out):
    return [str(out) if a == "OUT" else str(a) for a in args]


def _assert_one_line(r, expected):
    assert r.returncode == 2, f"exit {r.returncode}\n{r.stdout}\n{r.stderr}"
    assert "Traceback" not in r.stderr, r.stderr
    errors = [line for line in r.stderr.splitlines() if line.startswith("error:")]
    assert errors == [expected], r.stderr


@pytest.mark.parametrize("name", list(OUTPUT_NAME))
def test_an_output_in_a_missing_folder_is_one_line_and_nothing_is_written(logs, tmp_path, name):
    out = tmp_path / "missing" / OUTPUT_NAME[name]
    r = subprocess.run([sys.executable, "-m", "inclinometer_calib.apps.cli", *_argv(_commands(logs)[name], out)],
                       cwd=tmp_path, capture_output=True, text=True, timeout=120)
    _assert_one_line(r, f"error: cannot write {out}: the folder {tmp_path / 'missing'} does not exist")
    assert list(tmp_path.iterdir()) == []


def _cli(argv):
    return [sys.executable, "-m", "inclinometer_calib.apps.cli", *argv]


@pytest.mark.parametrize("name", list(OUTPUT_NAME))
def test_a_full_disk_is_one_line_and_leaves_no_partial_file(logs, full_disk, name):
    argv = _argv(_commands(logs)[name], OUTPUT_NAME[name])
    r = full_disk.run(_cli(argv))
    assert r.returncode != 97, r.stderr
    first = OUTPUT_NAME[name] + ("/cal.csv" if name == "simulate" else "")
    _assert_one_line(r, f"error: cannot write {first}: no space left on the device (ENOSPC)")
    assert r.stderr.strip().splitlines()[-1] == "LEFT:", r.stderr      # nothing under the name, no temporary
    assert not os.listdir(full_disk.mnt)                                  # (the namespace's mount is gone)


@pytest.mark.parametrize("name", list(OUTPUT_NAME))
def test_a_read_only_folder_is_said_before_the_work(logs, full_disk, name):
    argv = _argv(_commands(logs)[name], OUTPUT_NAME[name])
    r = full_disk.run(_cli(argv), ro=True)
    assert r.returncode != 97, r.stderr
    _assert_one_line(r, f"error: cannot write {OUTPUT_NAME[name]}: the file system is read-only (EROFS)")
    assert r.stderr.strip().splitlines()[-1] == "LEFT:", r.stderr
