"""One place for each idea: the copies the pipeline replaced are gone, and every path uses the one left.

Read from the source (``ast``), so that a copy coming back fails here whatever it is called by:
one station type (:mod:`station`), one correction path (:meth:`model.ProbeModel.correct` through
:meth:`coeffs.Calibration.correct` and :func:`station.correct_stations`), the specific-force
sign flip in :mod:`frames` only, effect metadata on the effect classes, one effect grammar.
"""
import ast
import pathlib

import pytest

PKG = pathlib.Path(__file__).resolve().parents[2] / "inclinometer_calib"
MODULES = {p.relative_to(PKG).as_posix(): ast.parse(p.read_text()) for p in PKG.rglob("*.py")
           if "__pycache__" not in p.parts}


def _classes(tree):
    return {n.name for n in ast.walk(tree) if isinstance(n, ast.ClassDef)}


def _functions(tree):
    return {n.name for n in ast.walk(tree) if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef))}


def _imports(tree):
    """(module, name) of every ``from X import name`` (the module's last name: ``..core.station``
    and ``.station`` are ``station``)."""
    out = set()
    for n in ast.walk(tree):
        if isinstance(n, ast.ImportFrom):
            for a in n.names:
                out.add(((n.module or "").rsplit(".", 1)[-1], a.name))
    return out


def _calls(tree, attr):
    return [n for n in ast.walk(tree) if isinstance(n, ast.Call) and isinstance(n.func, ast.Attribute)
            and n.func.attr == attr]


@pytest.mark.parametrize("name", ["StaticSegment", "Capture", "LabData", "StationRecord", "Stationary",
                                  "FastCorrection", "ProbeModel", "Station", "Stations"])
def test_each_station_and_model_type_is_defined_once(name):
    where = [m for m, t in MODULES.items() if name in _classes(t)]
    home = {"Station": ["core/station.py"], "Stations": ["core/station.py"], "ProbeModel": ["core/model.py"]}.get(name, [])
    assert where == home, f"class {name} defined in {where}"


def test_the_paths_import_the_one_station_type_and_the_one_correction_path():
    uses = {
        "apps/cli/survey.py": {("pipeline", "evaluate_log")},
        "correct/reprocess.py": {("pipeline", "SurveyProcessor")},
        "nodes/correction.py": {("pipeline", "SurveyProcessor")},
        "calibrate/labmodel.py": {("model", "ProbeModel")},
        "lab/data.py": {("station", "Stations")},
        "calibrate/capture.py": {("station", "Station")},
        "correct/pipeline.py": {("station", "Station"), ("station", "correct_stations")},
        "lab/loop.py": {("compare", "*")},
    }
    for module, need in uses.items():
        have = _imports(MODULES[module])
        if ("compare", "*") in need:
            assert ("", "compare") in have, module
            continue
        assert need <= have, f"{module} imports {sorted(have)}"


def test_only_the_model_inverts_a_triad_and_only_the_pipeline_feeds_it_stations():
    # TriadModel.inverse: the model's correction (model.py) and the twelve-position solver's own triad
    callers = sorted(m for m, t in MODULES.items() if _calls(t, "inverse"))
    assert callers == ["calibrate/twelve_position.py", "core/model.py"], callers
    # .correct(...): Calibration -> ProbeModel (coeffs, model), of stations (station.correct_stations), of
    # samples (the batch path, survey.py), the lab's model, fit, wander smoother and predicted uncertainty
    # (LabModel.correct -> ProbeModel.correct; the fit one triad at a time, correct_triad)
    callers = sorted(m for m, t in MODULES.items()
                     if (_calls(t, "correct") or _calls(t, "correct_triad")) and m != "correct/axial.py")
    assert callers == ["calibrate/fit.py", "calibrate/labmodel.py", "calibrate/wander.py", "core/coeffs.py", "core/model.py",
                       "core/station.py", "core/survey.py", "lab/uncertainty.py"], callers


def test_the_specific_force_sign_flip_lives_in_frames_only():
    defs = [m for m, t in MODULES.items() if {"gravity_from_specific_force", "specific_force_from_gravity"}
            & _functions(t)]
    assert defs == ["core/frames.py"]
    for module in ("detect/streaming.py", "core/survey.py", "nodes/correction.py", "nodes/calibration.py",
                   "calibrate/simulate.py", "core/coeffs.py"):
        names = {n for _, n in _imports(MODULES[module])}
        assert names & {"gravity_from_specific_force", "specific_force_from_gravity"}, module


def test_effect_metadata_is_asked_of_the_classes_not_keyed_by_name_elsewhere():
    from inclinometer_calib.core import effects as fx

    # the base model's names are also the record's parameter fields (bias_x, scale_x ...): the others
    names = set(fx.CATALOGUE) - set(fx.BASE)
    for module, tree in MODULES.items():
        if module == "core/effects.py":
            continue
        docstrings = {id(n.body[0].value) for n in ast.walk(tree)
                      if isinstance(n, (ast.Module, ast.ClassDef, ast.FunctionDef)) and n.body
                      and isinstance(n.body[0], ast.Expr) and isinstance(n.body[0].value, ast.Constant)}
        literals = {n.value for n in ast.walk(tree) if isinstance(n, ast.Constant) and isinstance(n.value, str)
                    and id(n) not in docstrings}
        assert not literals & names, f"{module} names effects {sorted(literals & names)} in its code"


def test_one_grammar_parses_effect_specifications():
    parsers = [(m, f) for m, t in MODULES.items() for f in _functions(t) if f.startswith("parse_effect")]
    assert parsers == [("core/effects.py", "parse_effects")], parsers


def test_the_nodes_and_reprocess_drive_the_one_stream_engine():
    """Samples to stations, what a station waits for, its gates, the session and the record in
    force: ``engine.StreamEngine`` — the calibration and correction nodes and ``reprocess`` drive
    it; nothing else pairs the streams or holds stations back."""
    for module in ("correct/reprocess.py", "nodes/correction.py", "nodes/calibration.py"):
        assert ("engine", "StreamEngine") in _imports(MODULES[module]), module
    pairers = sorted(m for m, t in MODULES.items() if any(
        isinstance(n, ast.Call) and getattr(n.func, "id", getattr(n.func, "attr", "")) == "StreamPairer"
        for n in ast.walk(t)))
    assert pairers == ["correct/engine.py"], pairers
    # the tracks a station waits on are the engine's alone
    tracks = sorted(m for m, t in MODULES.items() if any(
        isinstance(n, ast.Call) and getattr(n.func, "id", getattr(n.func, "attr", "")) == "ReferenceTrack"
        for n in ast.walk(t)))
    assert tracks == ["correct/engine.py"], tracks


def test_a_stations_status_is_decided_in_one_place():
    """``pipeline.station_status``: the nodes' and reprocess's fields (``station_fields``) and
    ``correct``'s table and figures."""
    callers = sorted(m for m, t in MODULES.items() if any(
        isinstance(n, ast.Call) and getattr(n.func, "id", "") == "station_status" for n in ast.walk(t)))
    assert callers == ["correct/pipeline.py"], callers
