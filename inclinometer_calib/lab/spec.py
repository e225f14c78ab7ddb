"""Models as users name them (the package's one effect grammar), and the report entry point."""
from __future__ import annotations

import numpy as np

from ..core import effects as fx
from ..core.output import atomic_write_text, check_output
from ..core.survey import evaluate, summarize
from ..calibrate.labmodel import LabModel


def effect(name: str, sensor: str | None = None, axes: str | None = None) -> fx.Effect:
    """A catalogue or plug-in effect with zero parameters (to be fitted)."""
    return fx.make_effect(name, sensor, axes)


def build_model(site, effects_text=None, **kw) -> LabModel:
    """The paper's base model plus the effects named in the package's grammar
    (:func:`effects.parse_effects`; values given there are the starting point of a fit), the
    stand's pose errors and the heading offset among them (:meth:`LabModel.with_named`)."""
    return LabModel.base(site, **kw).with_named(effects_text)


def uncorrected_metrics(data, site) -> dict:
    """Validation angle errors of the raw (uncorrected) sensors (azimuths + the site declination)."""
    has = np.all(np.isfinite(data.ref), axis=1)
    if not has.any():
        return {"stations": 0}
    d = data.subset(has)
    return summarize(evaluate(d.g, d.b, site, ref=d.ref))


def write_report(path, data, site, effects_text: str | None = None, max_steps: int = 4, progress=None,
                 candidates=None, methods=None) -> list:
    """Run the effect ladder from the base model (plus ``effects_text``) and write the HTML report.

    ``methods``: rows of :func:`lab.methods.compare` (the seed methods side by side) for a section.

    Raises :class:`deps.MissingDependency` before any fitting if matplotlib is not installed."""
    from ..core.deps import require
    from .diagnose import ladder
    from .report import render

    require("matplotlib", "report", "lab report")  # the plots; checked before the minutes of fitting
    check_output(path)                             # and where the report goes
    steps = ladder(data, site, max_steps=max_steps, progress=progress, candidates=candidates,
                   start=build_model(site, effects_text))
    # the last rung's diagnosis field-fitted its model already (Diagnosis.base_fit; its model is
    # that fit's, unchanged since): fitting it again from its own optimum only repeated the work
    final_fit = steps[-1].base_fit
    html = render(steps, data, uncorrected_metrics(data, site), final_fit, methods=methods)
    atomic_write_text(path, html)
    return steps


def model_from_truth(truth: dict) -> LabModel:
    """The simulator's true probe (``truth.json`` of ``inclinometer-calib simulate``) as a LabModel.

    Gives the 'true-model' figures: the validation errors a perfect model reaches on the same data.
    """
    from ..core.frames import Site
    from ..calibrate.simulate import SimulatedProbe

    return LabModel(site=Site(**truth["site"]), probe=SimulatedProbe.from_dict(truth["probe"]).model)
