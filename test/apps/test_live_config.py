"""The live view's configuration files, without ROS:

* ``config/foxglove_layout.json`` is a Foxglove layout in the format Foxglove imports from a file
  (``configById``, the mosaic ``layout`` tree, ``globalVariables``, ``userNodes``,
  ``playbackConfig``): every panel of the tree is configured and every configured panel is in the
  tree; panel types are built-in ones (the panel catalogue of the open-source Foxglove Studio
  fork, lichtblick-suite/lichtblick ``packages/suite-base/src/panels/index.ts``: ``3D``, ``Plot``,
  ``Table``, ``RawMessages``, ``DiagnosticSummary``, ``DiagnosticStatusPanel``, ``RosOut``); each
  panel's settings are ones the panel knows (the foxglove-sdk's own layout model,
  ``foxglove.layouts``, lists them); and every topic (and field) the layout reads is one the live
  node sends (:data:`liveview.CHANNELS`, the payloads of :class:`liveview.LiveView`).
* ``config/diagnostic_aggregator.yaml`` is a diagnostic_aggregator analyzer configuration (ROS 2)
  in which every DiagnosticStatus name our nodes publish (read from their source) is matched by
  exactly one analyzer, with the GenericAnalyzer's matching rules.
* the launcher's ``--foxglove-port`` starts the live node on that port.
"""
import ast
import glob
import json
import os
import re

import pytest
import yaml

import pysource

from inclinometer_calib.apps import launcher
from inclinometer_calib.rig import liveview as lv

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
CONFIG = os.path.join(ROOT, "config")


# ---------------------------------------------------------------------------------------------
# Foxglove layout

@pytest.fixture(scope="module")
def layout():
    with open(os.path.join(CONFIG, "foxglove_layout.json"), encoding="utf-8") as fh:
        return json.load(fh)


def _leaves(node):
    if isinstance(node, str):
        return [node]
    assert set(node) <= {"direction", "first", "second", "splitPercentage"}, node
    assert node["direction"] in ("row", "column") and 0 < node.get("splitPercentage", 50) < 100, node
    return _leaves(node["first"]) + _leaves(node["second"])


#: built-in panel type (classic layout id prefix) -> the foxglove-sdk layout model's config class
PANEL_CONFIGS = {"3D": "ThreeDeeConfig", "Plot": "PlotConfig", "Table": "TableConfig",
                 "RawMessages": "RawMessagesConfig", "DiagnosticSummary": "DiagnosticsSummaryConfig",
                 "DiagnosticStatusPanel": "DiagnosticsDetailConfig", "RosOut": "LogConfig"}


def _topic_paths(panel_type, cfg):
    """The message paths (topic + field path) a panel reads."""
    if panel_type == "Plot":
        yield from (p["value"] for p in cfg["paths"])
        if cfg.get("xAxisPath"):
            yield cfg["xAxisPath"]["value"]
    elif panel_type in ("Table", "RawMessages"):
        yield cfg["topicPath"]
    elif panel_type in ("DiagnosticSummary", "DiagnosticStatusPanel", "RosOut"):
        yield cfg["topicToRender"]
    elif panel_type == "3D":
        yield from cfg["topics"]


def _split(path):
    m = re.fullmatch(r"(/[\w/]+)((?:\.\w+|\[:?\])*)", path)
    assert m, f"not a message path: {path!r}"
    return m.group(1), re.findall(r"\.(\w+)", m.group(2))


def test_layout_has_the_file_format_and_a_consistent_tree(layout):
    assert {"configById", "layout", "globalVariables", "userNodes", "playbackConfig"} <= set(layout)
    leaves = _leaves(layout["layout"])
    assert sorted(leaves) == sorted(layout["configById"]), "panels in the tree and configured panels differ"
    assert len(set(leaves)) == len(leaves)
    for pid in leaves:
        assert re.fullmatch(r"[\w ]+![\w-]+", pid), pid
        assert pid.split("!")[0] in PANEL_CONFIGS, f"{pid}: not a built-in panel type"


def test_layout_panels_use_only_settings_the_panels_know(layout):
    fl = pytest.importorskip("foxglove.layouts")
    for pid, cfg in layout["configById"].items():
        ptype = pid.split("!")[0]
        known = set(getattr(fl, PANEL_CONFIGS[ptype])()._to_dict()) | {"title"}
        assert set(cfg) <= known, f"{pid}: unknown settings {sorted(set(cfg) - known)}"
        if ptype == "Plot":
            series = set(fl.PlotSeries()._to_dict())
            for p in cfg["paths"]:
                assert set(p) <= series, f"{pid}: unknown series settings {sorted(set(p) - series)}"
            assert cfg["xAxisVal"] in ("timestamp", "index", "custom", "currentCustom")


def test_layout_reads_only_what_the_live_node_sends(layout):
    view = lv.LiveView()
    view.add({"station_id": 1, "stamp": 1.0, "coefficients_id": "x", "status": 0, "measured_depth_m": 500.0,
              "delta_g_mps2": 0.0, "delta_b_nt": 0.0, "delta_dip_deg": 0.0, "drift_deg": 1.0, "azimuth_deg": 2.0,
              "toolface_deg": 3.0, "temperature_c": 20.0, "warnings": []})
    payload_keys = {lv.TOPIC_RESIDUALS: set(view.residuals()), lv.TOPIC_TABLE: set(view.table())}
    read = set()
    for pid, cfg in layout["configById"].items():
        for path in _topic_paths(pid.split("!")[0], cfg):
            topic, fields = _split(path)
            assert topic in lv.CHANNELS, f"{pid} reads {topic}, which the live node does not send"
            read.add(topic)
            if fields and topic in payload_keys:
                assert fields[0] in payload_keys[topic], f"{pid}: {path}: no field {fields[0]}"
    # the panels the live view is for: the residuals, the station, the trajectory, the diagnostics
    plotted = {_split(p["value"])[1][0] for pid, c in layout["configById"].items() if pid.startswith("Plot!")
               for p in c["paths"]}
    assert set(lv.SERIES) <= plotted
    assert {lv.TOPIC_STATION, lv.TOPIC_TABLE, lv.TOPIC_TRAJECTORY, lv.TOPIC_FRAMES, lv.TOPIC_DIAGNOSTICS} <= read
    three_d = next(c for pid, c in layout["configById"].items() if pid.startswith("3D!"))
    assert three_d["followTf"] == lv.FRAME_DISPLAY


# ---------------------------------------------------------------------------------------------
# diagnostic_aggregator analyzers

#: Parameters a GenericAnalyzer reads (ros/diagnostics, diagnostic_aggregator/src/generic_analyzer.cpp,
#: GenericAnalyzer::init) besides ``type``.
GENERIC_PARAMS = {"path": str, "find_and_remove_prefix": list, "remove_prefix": list, "startswith": list,
                  "contains": list, "expected": list, "regex": list, "timeout": float, "num_items": int,
                  "discard_stale": bool}
MATCHERS = ("find_and_remove_prefix", "startswith", "contains", "regex")


def generic_analyzer_matches(cfg, name) -> bool:
    """GenericAnalyzer::match (generic_analyzer.cpp): true when ``name`` fully matches a ``regex``
    (std::regex_match), or starts with one of ``startswith`` (``name.find(s) == 0``) — to which
    ``find_and_remove_prefix`` is copied in init() — or contains one of ``contains``.  (``expected``
    names are added as items in init() but not matched here: the config does not use them.)"""
    starts = list(cfg.get("startswith", [])) + list(cfg.get("find_and_remove_prefix", []))
    return (any(re.fullmatch(r, name) for r in cfg.get("regex", []))
            or any(name.startswith(s) for s in starts)
            or any(c in name for c in cfg.get("contains", [])))


def _generic_analyzers(analyzers, where=""):
    """(path, config) of every GenericAnalyzer, through AnalyzerGroups (analyzer_group.cpp: a
    group's ``analyzers`` parameters; AnalyzerGroup::match hands a status to *every* analyzer that
    matches it, so a name matched twice is reported twice)."""
    for key, cfg in analyzers.items():
        if not isinstance(cfg, dict):
            continue
        kind = cfg.get("type")
        assert kind in ("diagnostic_aggregator/GenericAnalyzer", "diagnostic_aggregator/AnalyzerGroup"), (key, kind)
        assert isinstance(cfg.get("path"), str) and cfg["path"], f"{key}: no path"
        if kind.endswith("AnalyzerGroup"):
            assert set(cfg) == {"type", "path", "analyzers"}, key
            yield from _generic_analyzers(cfg["analyzers"], f"{where}/{cfg['path']}")
            continue
        for param, value in cfg.items():
            if param == "type":
                continue
            assert param in GENERIC_PARAMS, f"{key}: {param} is not a GenericAnalyzer parameter"
            assert isinstance(value, GENERIC_PARAMS[param]), f"{key}.{param}: {value!r}"
            if GENERIC_PARAMS[param] is list:
                assert value and all(isinstance(v, str) and v for v in value), f"{key}.{param}"
        assert "expected" not in cfg, f"{key}: use startswith (expected names are not matched, see above)"
        # init() refuses an analyzer with no way of checking diagnostics
        assert any(m in cfg for m in MATCHERS), f"{key}: no startswith/contains/regex/find_and_remove_prefix"
        yield f"{where}/{cfg['path']}", cfg


def published_diagnostic_names():
    """Every DiagnosticStatus name the nodes publish, read from their source: ``name=`` of each
    ``DiagnosticStatus(...)``; an f-string name whose placeholder is a parameter of the function
    it is in takes each constant that function is called with."""
    names = set()
    for path in glob.glob(os.path.join(ROOT, "inclinometer_calib", "nodes", "*.py")):
        tree = pysource.parse(path)
        parents = {child: node for node in ast.walk(tree) for child in ast.iter_child_nodes(node)}
        for call in ast.walk(tree):
            if not (isinstance(call, ast.Call) and getattr(call.func, "id", None) == "DiagnosticStatus"):
                continue
            name = next((k.value for k in call.keywords if k.arg == "name"), None)
            if name is None:
                continue
            if isinstance(name, ast.Constant):
                names.add(name.value)
                continue
            assert isinstance(name, ast.JoinedStr), f"{path}:{call.lineno}: a name the test cannot read"
            fn = call
            while not isinstance(fn, ast.FunctionDef):
                fn = parents[fn]
            holes = [v.value.id for v in name.values if isinstance(v, ast.FormattedValue)]
            assert len(holes) == 1, f"{path}:{call.lineno}"
            index = [a.arg for a in fn.args.args].index(holes[0])
            calls = [c for c in ast.walk(tree) if isinstance(c, ast.Call) and getattr(c.func, "id", None) == fn.name]
            assert calls, f"{path}: {fn.name} is never called"
            for c in calls:
                arg = c.args[index]
                assert isinstance(arg, ast.Constant), f"{path}:{c.lineno}: a name the test cannot read"
                names.add("".join(v.value if isinstance(v, ast.Constant) else str(arg.value) for v in name.values))
    return names


def test_every_published_diagnostic_is_grouped_by_exactly_one_analyzer():
    with open(os.path.join(CONFIG, "diagnostic_aggregator.yaml"), encoding="utf-8") as fh:
        doc = yaml.safe_load(fh)
    assert set(doc) == {"analyzers"} and set(doc["analyzers"]) == {"ros__parameters"}
    params = doc["analyzers"]["ros__parameters"]
    assert isinstance(params.get("path", ""), str)
    analyzers = list(_generic_analyzers(params))
    assert len(analyzers) >= 3
    names = published_diagnostic_names()
    assert {"inclinometer_calib: station", "inclinometer_calib: total field", "inclinometer_calib: model",
            "inclinometer_calib: site reference"} <= names, names
    for name in sorted(names):
        matched = [path for path, cfg in analyzers if generic_analyzer_matches(cfg, name)]
        assert len(matched) == 1, f"{name!r} is matched by {matched or 'no analyzer'}"
    # and each analyzer groups something
    for path, cfg in analyzers:
        assert any(generic_analyzer_matches(cfg, n) for n in names), f"{path} matches none of our diagnostics"


def test_the_matching_rules_emulated():
    cfg = {"startswith": ["a: b"], "contains": ["xyz"], "regex": ["q+"], "find_and_remove_prefix": ["p: "]}
    assert all(generic_analyzer_matches(cfg, n) for n in ("a: bc", "0xyz1", "qqq", "p: r"))
    assert not any(generic_analyzer_matches(cfg, n) for n in ("x a: b", "qqqr", "xy", "p:"))


# ---------------------------------------------------------------------------------------------
# launcher

def test_launcher_foxglove_port_starts_the_live_node_on_loopback():
    args = launcher.parse_args(["--foxglove-port", "8765"])
    params = launcher.build_params(args, "/tmp/run")
    assert params["live"] == {"port": 8765}
    with open(os.path.join(CONFIG, "live.yaml"), encoding="utf-8") as fh:
        assert yaml.safe_load(fh)["live"]["ros__parameters"]["host"] == "127.0.0.1"
    assert launcher.build_params(launcher.parse_args([]), "/tmp/run")["live"] == {}
    with pytest.raises(SystemExit, match="1..65535"):
        launcher.build_params(launcher.parse_args(["--foxglove-port", "70000"]), "/tmp/run")


def test_launcher_plugin_is_the_nodes_plugins_parameter_and_is_not_executed(tmp_path, monkeypatch):
    from inclinometer_calib.core import plugins

    monkeypatch.setattr(plugins, "_NAMED", {}, raising=False)
    plug = tmp_path / "p.py"
    plug.write_text("open(__file__ + '.ran', 'w').close()\n")
    monkeypatch.chdir(tmp_path)
    params = launcher.build_params(launcher.parse_args(["--plugin", "p.py"]), "/tmp/run")
    assert params["correction"]["plugins"] == params["calibration"]["plugins"] == [str(plug)]
    assert not (tmp_path / "p.py.ran").exists()
    with pytest.raises(SystemExit, match="--plugin: plug-in file .*nope.py does not exist"):
        launcher.build_params(launcher.parse_args(["--plugin", "nope.py"]), "/tmp/run")


def test_table_status_is_the_run_reports_wording():
    s = {"coefficients_id": "", "status": 0}
    assert lv.status_text(s) == lv.station_label(s)
    assert lv.station_color(s) == lv.UNCORRECTED_COLOR
    assert lv.station_color({"coefficients_id": "x", "status": 1}) == lv.STATUS_COLORS[1]
