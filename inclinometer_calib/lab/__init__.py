"""The model lab: compare a probe model with measurements, see where it fails, find the missing
physical effect, add it, and watch the error fall.

Python API (the CLI ``inclinometer-calib lab ...`` is a thin layer over it)::

    from inclinometer_calib import lab
    from inclinometer_calib.frames import Site

    data = lab.load_logs("cal.csv", "val.csv")               # stations with roles cal / val
    dg = lab.diagnose(data, site=Site())                      # ranked candidate effects
    print(dg.verdict)
    model = lab.LabModel.base(Site()).with_effect(lab.effect("axial_interference", "mag", "z"), "val")
    result = lab.fit(model, data)                             # parameters ± 1σ, identifiability
    steps = lab.ladder(data, Site())                          # effect ladder
    lab.write_report("report.html", data, Site())             # self-contained HTML
"""
import importlib

#: Where each name of the API lives: imported on first use (PEP 562), so that a module that needs
#: one part of the lab (the correction node's field monitor: ``lab.field`` and ``lab.stats``) does
#: not pay for scipy's optimizers at start-up.
_WHERE = {
    "PluginError": "..plugins", "load_plugin": "..plugins",
    "load_bag": ".data", "load_logs": ".data",
    "Diagnosis": ".diagnose", "cross_validate": ".diagnose", "diagnose": ".diagnose", "field_fit": ".diagnose",
    "ladder": ".diagnose", "val_metrics": ".diagnose", "validation": ".diagnose",
    "FitResult": ".fit", "fit": ".fit",
    "LabModel": ".model",
    "build_model": ".spec", "effect": ".spec", "model_from_truth": ".spec", "uncorrected_metrics": ".spec",
    "write_report": ".spec",
}

__all__ = ["load_logs", "load_bag", "Diagnosis", "cross_validate", "diagnose", "field_fit", "ladder",
           "val_metrics", "validation", "FitResult", "fit",
           "LabModel", "PluginError", "load_plugin", "effect", "build_model", "uncorrected_metrics", "write_report",
           "model_from_truth"]


def __getattr__(name):
    where = _WHERE.get(name)
    if where is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(where, __name__), name)
    globals()[name] = value
    return value


def __dir__():
    return sorted(set(globals()) | set(__all__))
