"""Effect specifications as users write them, and the report entry point."""
from __future__ import annotations

import numpy as np

from .. import effects as fx
from ..probelog import atomic_write_text
from ..survey import evaluate, summarize
from .model import LabModel

#: Effects whose default scope is the validation/survey logs only.
SURVEY_ONLY = ("axial_interference",)


def effect(name: str, sensor: str | None = None, axes: str | None = None) -> fx.Effect:
    """A catalogue or plug-in effect with zero parameters (to be fitted)."""
    cls = fx.CATALOGUE.get(name)
    if cls is None:
        raise ValueError(f"unknown effect {name!r}; known: {', '.join(sorted(fx.CATALOGUE))} "
                         f"(or load a plug-in with --plugin)")
    return cls(sensor=sensor or cls.sensors[0], axes=axes or cls.default_axes)


def parse_effects(text: str | None) -> list:
    """``NAME[:sensor[:axes]][@scope],...`` → [(Effect, scope)].  No sensor: every sensor it acts on."""
    out = []
    if not text:
        return out
    for item in (s.strip() for s in text.split(",")):
        if not item:
            continue
        spec, _, scope = item.partition("@")
        parts = spec.split(":")
        if len(parts) > 3 or not parts[0]:
            raise ValueError(f"effect {item!r}: expected NAME[:sensor[:axes]][@scope]")
        name = parts[0]
        cls = fx.CATALOGUE.get(name)
        if cls is None:
            raise ValueError(f"unknown effect {name!r}; known: {', '.join(sorted(fx.CATALOGUE))}")
        sensors = [parts[1]] if len(parts) > 1 and parts[1] else list(cls.sensors)
        axes = parts[2] if len(parts) > 2 and parts[2] else None
        scope = scope or ("val" if name in SURVEY_ONLY else "all")
        if scope not in ("all", "cal", "val"):
            raise ValueError(f"effect {item!r}: scope must be all, cal or val")
        for s in sensors:
            out.append((effect(name, s, axes), scope))
    return out


def build_model(site, effects_text: str | None = None, **kw) -> LabModel:
    model = LabModel.base(site, **kw)
    for eff, scope in parse_effects(effects_text):
        model = model.with_effect(eff, scope)
    return model


def uncorrected_metrics(data, site) -> dict:
    """Validation angle errors of the raw (uncorrected) sensors (azimuths + the site declination)."""
    has = np.all(np.isfinite(data.ref), axis=1)
    if not has.any():
        return {"stations": 0}
    d = data.subset(has)
    return summarize(evaluate(d.g, d.b, site, ref=d.ref))


def write_report(path, data, site, effects_text: str | None = None, max_steps: int = 4, progress=None,
                 candidates=None) -> list:
    """Run the effect ladder from the base model (plus ``effects_text``) and write the HTML report.

    Raises :class:`deps.MissingDependency` before any fitting if matplotlib is not installed."""
    from ..deps import require
    from .diagnose import ladder
    from .fit import fit
    from .report import render

    require("matplotlib", "report", "lab report")  # the plots; checked before the minutes of fitting
    steps = ladder(data, site, max_steps=max_steps, progress=progress, candidates=candidates,
                   start=build_model(site, effects_text))
    final_fit = fit(steps[-1].model, data)
    html = render(steps, data, uncorrected_metrics(data, site), final_fit)
    atomic_write_text(path, html)
    return steps


def model_from_truth(truth: dict) -> LabModel:
    """The simulator's true probe (``truth.json`` of ``inclinometer-calib simulate``) as a LabModel.

    Gives the 'true-model' figures: the validation errors a perfect model reaches on the same data.
    """
    from ..errormodel import TriadModel
    from ..frames import Site

    probe = truth["probe"]
    model = LabModel.base(Site(**truth["site"]), TriadModel.from_parameters(probe["acc"]),
                          TriadModel.from_parameters(probe["mag"]))
    for e in probe["effects"]:
        cls = fx.CATALOGUE.get(e["name"])
        if cls is None:
            raise ValueError(f"truth names effect {e['name']!r}, which is not registered (load its plug-in)")
        eff = cls(sensor=e["sensor"], axes=e["axes"], values={k: np.asarray(v) for k, v in e["values"].items()})
        model = model.with_effect(eff, "val" if e["name"] in probe.get("survey_only", ()) else "all")
    return model
