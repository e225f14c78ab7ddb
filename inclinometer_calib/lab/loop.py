"""The model loop of a recorded run: from the live record, through the lab, to a better record.

After a run (the launcher's summary, or anyone with a bag and the record the graph applied):

1. **the lab's data**: the bag replayed through the graph's own steps
   (:func:`data.load_bag`): the twelve-position captures (``cal``) and the survey stations with
   a reference attitude (``val``);
2. **the lab's finding**: :func:`diagnose.diagnose` from the live record's model — the missing
   effect it recommends (fitted as for a survey: the references never fitted), with the field
   error it gains;
3. **the lab's record**: the recommended effect added and the model fitted to everything the run
   has, its reference stations too (:func:`fit.fit`) — the best record for the next run; its
   figures in the ladder below are therefore in-sample, and the ladder says so — written as a calibration record (``lab_model.yaml``);
4. **the field effect ladder**: the bag replayed through each record — uncorrected, the live
   record, the lab's record and, for a simulated probe, the simulator's truth — by
   :func:`compare.compare`: the same stations, only the model differs.

ROS-free; plots need matplotlib (the ``report`` extra).
"""
from __future__ import annotations

import copy
import os
from dataclasses import dataclass, field

from ..core import effects as fx


@dataclass
class LoopResult:
    """What the loop found: the lab's diagnosis, the lab's record (None when the lab found nothing
    to add), the ladder's runs (:class:`compare.ModelRun`), and what it says, line by line."""

    diagnosis: object = None
    record: object = None
    runs: list = field(default_factory=list)
    lines: list = field(default_factory=list)
    skipped: str = ""


def run_loop(bag, live, out_dir, *, truth=None, warn=None, progress=None) -> LoopResult:
    """The loop of the module docstring on ``bag`` with the live record ``live``; writes
    ``out_dir/lab_model.yaml`` and ``out_dir/compare/``.  ``truth``: the simulator's true record."""
    from . import compare
    from .data import load_bag
    from .diagnose import HEADING, diagnose
    from ..calibrate.fit import fit
    from ..calibrate.labmodel import LabModel

    res = LoopResult()
    data, _ = load_bag(bag, warn=warn)
    n_val = int(((data.role == "val") & (data.kind == "ref")).sum())
    n_cal = int((data.role == "cal").sum())
    if n_val < 8:
        res.skipped = (f"the lab needs survey stations with a reference attitude to find a missing effect: the run "
                       f"has {n_val} (and {n_cal} captures)")
    else:
        start = LabModel.from_calibration(live)
        dg = diagnose(data, start, progress=progress)
        res.diagnosis = dg
        rec = dg.recommended
        res.lines.append(f"lab, on the run's {n_cal} captures and {n_val} stations with a reference (start: the live "
                         f"record {live.id}, {live.model.describe()}):")
        res.lines += ["  " + ln for ln in dg.verdict.splitlines()]
        if rec is not None and rec.effect != HEADING:
            if rec.effect in fx.MODEL_OPTIONS:     # the stand's pose errors: an option of the fit, not an effect
                model = dg.model.with_named(rec.effect)
            else:
                model = copy.deepcopy(dg.model).with_effect(fx.make_effect(rec.effect, rec.sensor, rec.axes),
                                                            rec.scope)
            result = fit(model, data)    # the best record: every station of the run, references too
            res.record = model.record(probe_id=live.probe_id, site_source=live.site_source,
                                      not_identifiable=result.not_identifiable,
                                      fit_stats={"chi2": result.chi2, "dof": result.dof, "z_rms": result.z_rms,
                                                 "stations": len(data), "data": data.describe()},
                                      method=f"lab fit of {model.describe()} to the run's captures and "
                                             f"reference stations, from the live record {live.id}")
            path = os.path.join(out_dir, "lab_model.yaml")
            res.record.save(path)
            res.lines.append(f"lab record {res.record.id} ({res.record.model.describe()}) written to {path}")
            for row in result.parameter_table(extras_only=True):
                if not row["name"].startswith("site."):
                    res.lines.append(f"  {row['name']} = {row['value']:.4g} ± {row['std']:.2g} {row['unit']}")
        elif rec is not None:
            res.lines.append("the lab's finding is a heading offset of the stand, not a probe effect: no new record")
    models = [("uncorrected", None), ("live record", live)]
    if res.record is not None:
        models.append(("lab model", res.record))
    if truth is not None:
        models.append(("simulator truth", truth))
    res.runs = compare.compare(bag, [(name.replace(" ", "_"), cal) for name, cal in models],
                               os.path.join(out_dir, "compare"), site=live.site, warn=warn)
    res.lines += compare.describe(res.runs, os.path.basename(str(bag)))
    if res.record is not None:
        res.lines.append("  (the lab model was fitted on this run's stations, references included: its figures above are "
                         "in-sample; the lab's field figure is in its verdict)")
    return res
