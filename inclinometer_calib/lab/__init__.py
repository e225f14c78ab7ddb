"""The model lab: compare a probe model with measurements, see where it fails, find the missing
physical effect, add it, and watch the error fall.

Python API (the CLI ``inclinometer-calib lab ...`` is a thin layer over it)::

    from inclinometer_calib import lab
    from inclinometer_calib.core.frames import Site

    data = lab.load_logs("cal.csv", "val.csv")               # stations with roles cal / val
    dg = lab.diagnose(data, site=Site())                      # ranked candidate effects
    print(dg.verdict)
    model = lab.LabModel.base(Site()).with_effect(lab.effect("axial_interference", "mag", "z"), "val")
    result = lab.fit(model, data)                             # parameters ± 1σ, identifiability
    steps = lab.ladder(data, Site())                          # effect ladder
    lab.write_report("report.html", data, Site())             # self-contained HTML

Lives here: the lab's data, diagnosis, discovery, field validation, the model loop, the
comparison of runs (``compare``), noise models and reports; its fit and model are
``calibrate.fit`` and ``calibrate.labmodel`` (a capture session fits with them too).

May import: ``core``, ``detect``, ``io``, ``calibrate``, ``correct``, ``rig``.
"""
from ..core.plugins import PluginError, load_plugin
from .data import load_bag, load_logs
from .diagnose import Diagnosis, cross_validate, diagnose, field_fit, ladder, val_metrics, validation
from ..calibrate.fit import FitResult, fit
from ..calibrate.labmodel import LabModel
from .spec import build_model, effect, model_from_truth, uncorrected_metrics, write_report

__all__ = ["load_logs", "load_bag", "Diagnosis", "cross_validate", "diagnose", "field_fit", "ladder",
           "val_metrics", "validation", "FitResult", "fit",
           "LabModel", "PluginError", "load_plugin", "effect", "build_model", "uncorrected_metrics", "write_report",
           "model_from_truth"]
