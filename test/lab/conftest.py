"""Simulated data sets for the lab tests (made once per session, by the CLI)."""
import contextlib
import io
import json

import pytest

from inclinometer_calib.apps.cli import main
from inclinometer_calib.core.frames import Site
from inclinometer_calib.lab import load_logs


def simulate(out, seed, effects=(), plugins=()):
    args = ["simulate", "--out", str(out), "--seed", str(seed)]
    for p in plugins:
        args += ["--plugin", str(p)]
    for e in effects:
        args += ["--effect", e]
    with contextlib.redirect_stdout(io.StringIO()):
        assert main(args) == 0
    truth = json.loads((out / "truth.json").read_text())
    return load_logs(out / "cal.csv", out / "val.csv"), truth, Site(**truth["site"])


@pytest.fixture(scope="session")
def sim_factory(tmp_path_factory):
    cache = {}

    def make(seed, effects=(), plugins=()):
        key = (seed, tuple(effects), tuple(map(str, plugins)))
        if key not in cache:
            cache[key] = simulate(tmp_path_factory.mktemp("lab"), seed, effects, plugins)
        return cache[key]
    return make
