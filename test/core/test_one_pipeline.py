"""One place for each idea: the copies the pipeline replaced are gone, and every path uses the one left.

Read from the source (``ast``), so that a copy coming back fails here whatever it is called by:
one station type (:mod:`station`), one correction path (:meth:`model.ProbeModel.correct` through
:meth:`coeffs.Calibration.correct` and :func:`station.correct_stations`), the specific-force
sign flip only where samples enter and leave (through :mod:`frames`), effect metadata on the effect
classes, one effect grammar.
"""
import ast
import functools
import re

import pytest

import pysource
from pysource import PKG


@functools.lru_cache(maxsize=1)
def modules() -> dict:
    """module path -> its parsed source (read when a test first asks, not while tests are collected)."""
    return {p.relative_to(PKG).as_posix(): pysource.parse(p) for p in pysource.files()}


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
    where = [m for m, t in modules().items() if name in _classes(t)]
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
        have = _imports(modules()[module])
        if ("compare", "*") in need:
            assert ("", "compare") in have, module
            continue
        assert need <= have, f"{module} imports {sorted(have)}"


def test_only_the_model_inverts_a_triad_and_only_the_pipeline_feeds_it_stations():
    # TriadModel.inverse: the model's correction (model.py) and the twelve-position solver's own triad
    callers = sorted(m for m, t in modules().items() if _calls(t, "inverse"))
    assert callers == ["calibrate/twelve_position.py", "core/model.py"], callers
    # .correct(...): Calibration -> ProbeModel (coeffs, model), of stations (station.correct_stations), of
    # samples (the batch path, survey.py), the lab's model, fit, wander smoother and predicted uncertainty
    # (LabModel.correct -> ProbeModel.correct; the fit one triad at a time, correct_triad)
    callers = sorted(m for m, t in modules().items()
                     if (_calls(t, "correct") or _calls(t, "correct_triad")) and m != "correct/axial.py")
    assert callers == ["calibrate/fit.py", "calibrate/labmodel.py", "calibrate/wander.py", "core/coeffs.py", "core/model.py",
                       "core/station.py", "core/survey.py", "lab/uncertainty.py"], callers


#: Where REP-145 specific force becomes the core's gravity vector (the only callers of
#: frames.gravity_from_specific_force): a probe log's rows, the CDR bytes of an Imu (a bag, the
#: nodes' raw subscriptions), a Python Imu message.
ENTRIES = {"io/probelog.py", "io/cdr.py", "nodes/common.py"}
#: Where a gravity vector goes out as specific force (frames.specific_force_from_gravity): an Imu
#: message, a coefficients message's accelerometer fields, the simulator's probe output, and two
#: messages that quote the probe's own values (an implausible sample, a stuck level).
EXITS = {"nodes/common.py", "core/coeffs.py", "calibrate/simulate.py", "correct/engine.py", "detect/gates.py"}
#: Names an accelerometer array goes by in the package (a sign flip of one of these is the flip again).
ACCEL = re.compile(r"(f|fs|f_flat|h|acc\w*|accel\w*|specific_force\w*|sf|linear_acceleration|la|imu\w*)$")


def _callee(node):
    f = node.func
    return f.id if isinstance(f, ast.Name) else f.attr if isinstance(f, ast.Attribute) else None


def _array_name(node):
    """The variable an expression reads an array from (``f``, ``f[s:e]``, ``log.acc``,
    ``np.asarray(f)``), or None."""
    while True:
        if isinstance(node, ast.Name):
            return node.id
        if isinstance(node, ast.Attribute):
            return node.attr
        if isinstance(node, ast.Subscript):
            node = node.value
        elif isinstance(node, ast.Call) and _callee(node) in ("asarray", "array", "ascontiguousarray", "tuple",
                                                                "float") and node.args:
            node = node.args[0]
        else:
            return None


def _negations(nodes):
    """Line numbers where an accelerometer-named array is negated among ``nodes`` (those of
    ``ast.walk``): ``-f``, ``np.negative(acc)``, ``-1 * f`` / ``f * -1``."""
    out = []
    for n in nodes:
        if isinstance(n, ast.UnaryOp) and isinstance(n.op, ast.USub):
            operand = n.operand
        elif isinstance(n, ast.Call) and _callee(n) == "negative" and n.args:
            operand = n.args[0]
        elif isinstance(n, ast.BinOp) and isinstance(n.op, ast.Mult):
            minus_one = [x for x in (n.left, n.right) if isinstance(x, ast.UnaryOp) and isinstance(x.op, ast.USub)
                         and isinstance(x.operand, ast.Constant) and x.operand.value == 1]
            operand = (n.right if minus_one[0] is n.left else n.left) if minus_one else None
        else:
            continue
        name = _array_name(operand) if operand is not None else None
        if name is not None and ACCEL.fullmatch(name):
            out.append(n.lineno)
    return out


def test_the_specific_force_sign_flip_happens_at_the_entries_only():
    defs = [m for m, t in modules().items() if {"gravity_from_specific_force", "specific_force_from_gravity"}
            & _functions(t)]
    assert defs == ["core/frames.py"]
    # used: called or passed on (coeffs picks it per sensor), not merely imported or named in a docstring
    names = ("gravity_from_specific_force", "specific_force_from_gravity")
    calls = {name: [] for name in names}
    flips = {}
    for m, t in modules().items():
        nodes = list(ast.walk(t))       # one walk per module: the whole package costs about a second
        used = {n.id if isinstance(n, ast.Name) else n.attr for n in nodes if isinstance(n, (ast.Name, ast.Attribute))}
        for name in names:
            if name in used:
                calls[name].append(m)
        if m != "core/frames.py" and _negations(nodes):
            flips[m] = _negations(nodes)
    assert set(calls["gravity_from_specific_force"]) == ENTRIES, calls
    assert set(calls["specific_force_from_gravity"]) == EXITS, calls
    assert flips == {}, "negates an accelerometer array: convert where samples enter, with frames"


def test_the_negation_finder_sees_each_form_of_the_flip():
    # the rule above is only as good as this finder: each way the flip was (or could be) written
    for src in ("g = -f", "g = -f[s:e]", "g = -np.asarray(log.acc[i0:i1])", "x = (-f[0], -f[1], -f[2])",
                "np.negative(acc, out=t)", "g = f * -1", "g = -1 * specific_force",
                "hx = -f[3 * i + 0] if negate else f[3 * i + 0]"):
        assert _negations(ast.walk(ast.parse(src))), src
    for src in ("g = -b", "x = -np.asarray(spacing_s)", "y = a - f", "t = -gx", "jb = [c, -a]"):
        assert not _negations(ast.walk(ast.parse(src))), src


def test_the_core_apis_take_the_gravity_vector():
    """The entry points of the core name their accelerometer argument ``g`` (the docstrings say
    gravity vector): a caller reading the signature cannot mistake it for specific force."""
    first = {("detect/streaming.py", "StaticDetector.update"): 1, ("detect/streaming.py", "StaticDetector.run"): 1,
             ("detect/streaming.py", "StreamPairer.add_imu"): 1, ("correct/engine.py", "StreamEngine.imu"): 1,
             ("correct/engine.py", "StreamEngine.samples"): 1, ("correct/engine.py", "implausible"): 0,
             ("core/survey.py", "correct_samples"): 0, ("core/batchkernel.py", "fused"): 0,
             ("core/_batch_numba.py", "fused"): 0, ("nodes/stream.py", "StreamDriver.feed"): 1}
    for (module, func), k in first.items():
        body = modules()[module].body
        *cls, name = func.split(".")
        if cls:
            body = next(n.body for n in body if isinstance(n, ast.ClassDef) and n.name == cls[0])
        defs = [n for n in body if isinstance(n, ast.FunctionDef) and n.name == name]
        assert len(defs) == 1, (module, func)
        for d in defs:
            args = [a.arg for a in d.args.args if a.arg != "self"]
            assert args[k] == "g" and "negate" not in args, (module, func, args)


def test_effect_metadata_is_asked_of_the_classes_not_keyed_by_name_elsewhere():
    from inclinometer_calib.core import effects as fx

    # the base model's names are also the record's parameter fields (bias_x, scale_x ...): the others
    names = set(fx.CATALOGUE) - set(fx.BASE)
    for module, tree in modules().items():
        if module == "core/effects.py":
            continue
        docstrings = {id(n.body[0].value) for n in ast.walk(tree)
                      if isinstance(n, (ast.Module, ast.ClassDef, ast.FunctionDef)) and n.body
                      and isinstance(n.body[0], ast.Expr) and isinstance(n.body[0].value, ast.Constant)}
        literals = {n.value for n in ast.walk(tree) if isinstance(n, ast.Constant) and isinstance(n.value, str)
                    and id(n) not in docstrings}
        assert not literals & names, f"{module} names effects {sorted(literals & names)} in its code"


def test_one_grammar_parses_effect_specifications():
    parsers = [(m, f) for m, t in modules().items() for f in _functions(t) if f.startswith("parse_effect")]
    assert parsers == [("core/effects.py", "parse_effects")], parsers


def test_the_nodes_and_reprocess_drive_the_one_stream_engine():
    """Samples to stations, what a station waits for, its gates, the session and the record in
    force: ``engine.StreamEngine`` — the calibration and correction nodes and ``reprocess`` drive
    it; nothing else pairs the streams or holds stations back."""
    for module in ("correct/reprocess.py", "nodes/correction.py", "nodes/calibration.py"):
        assert ("engine", "StreamEngine") in _imports(modules()[module]), module
    pairers = sorted(m for m, t in modules().items() if any(
        isinstance(n, ast.Call) and getattr(n.func, "id", getattr(n.func, "attr", "")) == "StreamPairer"
        for n in ast.walk(t)))
    assert pairers == ["correct/engine.py"], pairers
    # the tracks a station waits on are the engine's alone
    tracks = sorted(m for m, t in modules().items() if any(
        isinstance(n, ast.Call) and getattr(n.func, "id", getattr(n.func, "attr", "")) == "ReferenceTrack"
        for n in ast.walk(t)))
    assert tracks == ["correct/engine.py"], tracks


def test_a_stations_status_is_decided_in_one_place():
    """``pipeline.station_status``: the nodes' and reprocess's fields (``station_fields``) and
    ``correct``'s table and figures."""
    callers = sorted(m for m, t in modules().items() if any(
        isinstance(n, ast.Call) and getattr(n.func, "id", "") == "station_status" for n in ast.walk(t)))
    assert callers == ["correct/pipeline.py"], callers


#: Arc tangents, arc sines, norms and degrees outside formulas.py in the modules that apply the survey's
#: formulas: other ideas (a rotation matrix's angles, the angle between two vectors) and the kernel's
#: arc tangent, a primitive formulas.bind compiles the formulas against.
TRIG_ELSEWHERE = {"core/frames.py": {"attitude_angles", "angle_between_deg"},
                  "core/_batch_numba.py": {"_atan2", "_primitives"}}


def _own_call(node, names) -> bool:
    """A call of one of ``names`` that is not ``formulas.<name>``."""
    if not isinstance(node, ast.Call) or _callee(node) not in names:
        return False
    f = node.func
    return not (isinstance(f, ast.Attribute) and isinstance(f.value, ast.Name) and f.value.id == "formulas")


def test_the_survey_formulas_are_written_once():
    """The correction v = C·(h − B), drift, azimuth, toolface, dip, |G|, |B|, the QC and the status are
    formulas.py's: frames, survey, the models and the batch kernel call them, none computes an angle
    or a norm of its own (a copy kept in line by bit-equality tests alone is what this replaced)."""
    trig = {"arctan2", "atan2", "arcsin", "asin", "_atan2_core", "degrees", "hypot", "norm"}
    found = {}
    for module in ("core/frames.py", "core/survey.py", "core/errormodel.py", "core/model.py", "core/batchkernel.py",
                   "core/_batch_numba.py"):
        for top in modules()[module].body:
            defs = top.body if isinstance(top, ast.ClassDef) else [top]
            for d in defs:
                if isinstance(d, ast.FunctionDef) and any(_own_call(n, trig) for n in ast.walk(d)):
                    found.setdefault(module, set()).add(d.name)
    assert found == TRIG_ELSEWHERE, found


def test_every_dip_of_corrected_vectors_is_the_formulas():
    """The lab's fits, the field monitor, the twelve-position check of the site and the MSA report
    their dip through :func:`formulas.dip_of` (the same bits as the survey's): no asin of a clipped
    g·b/(|g||B|) written elsewhere (the dogleg's asin of a chord is another formula)."""
    import pathlib
    import re

    pkg = pathlib.Path(__file__).resolve().parents[2] / "inclinometer_calib"
    own = re.compile(r"arcsin\(np\.clip\(")
    found = sorted(str(p.relative_to(pkg)) for p in pkg.rglob("*.py") if own.search(p.read_text())
                   and p.name != "formulas.py")
    assert found == ["correct/trajectory.py"], found
