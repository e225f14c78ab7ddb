"""The noise model of the lab's data: per sensor axis the IEEE figures (:mod:`allan`) from the
stations' samples, and the random walk across the calibration's station sequence.

* the **holds**: every station's samples (the lab keeps them, :attr:`station.Stations.samples`)
  are static segments; their pooled Allan deviation gives the white noise ``N``, the bias
  instability ``B`` and, when the holds are long enough to see it, the random walk ``K``;
* the **sequence**: the calibration stations' residuals against ``model`` (its stochastic
  effects' paths left out: the wander is what is measured), consecutive in each log, give ``K``
  by maximum likelihood (:func:`allan.sequence_walk`) — used when the holds cannot resolve it.
  A slow misfit the model lacks (a temperature effect not in it) looks like a wander here: the lab
  tries the deterministic effects first (:mod:`lab.diagnose`).

A bag keeps no samples (the stations' means only): the holds then give nothing and say so.
"""
from __future__ import annotations

import copy

import numpy as np

from ..detect.allan import SensorNoise, sensor_noise
from ..calibrate.wander import clear_paths

#: Columns of a station's samples (time, gravity vector, field) per sensor.
COLUMNS = {"acc": [0, 1, 2, 3], "mag": [0, 4, 5, 6]}


def noise_model(model, data) -> dict:
    """``{"acc": SensorNoise, "mag": SensorNoise}`` of ``data`` (the lab's :class:`station.Stations`)
    with the residuals of ``model`` (a :class:`calibrate.labmodel.LabModel`) for the sequence."""
    samples = holds(data)
    m = copy.deepcopy(model)
    clear_paths(m)
    seq = {}
    sel = data.oriented & (data.role == "cal")
    if sel.sum() >= 5:
        d = data.subset(sel)
        g_t, b_t = m.true_vectors(d)
        h_g, h_b = m.forward(d, g_t, b_t)
        dur = np.array([np.ptp(x[:, 0]) if x is not None and len(x) else 0.0 for x in d.samples])
        seq = {"acc": (d.time_s, d.g - h_g, d.g_sigma, d.source, dur),
               "mag": (d.time_s, d.b - h_b, d.b_sigma, d.source, dur)}
    return {s: sensor_noise(s, [np.asarray(x)[:, COLUMNS[s]] for x in samples], seq.get(s))
            for s in ("acc", "mag")}


#: Two abutting stations whose mean directions differ by less than this are one hold cut in two.
SAME_ATTITUDE_DEG = 0.2


def _angle_deg(u, v) -> float:
    c = float(np.dot(u, v) / (np.linalg.norm(u) * np.linalg.norm(v) + 1e-300))
    return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))


def holds(data) -> list:
    """The static holds' samples: each station's, stations of one log that follow one another
    without a gap at the same attitude (a long hold the detector cut at its maximum duration)
    joined into one — the Allan deviation then reaches a third of the whole hold."""
    out, src = [], []
    for x, source in zip([] if data.samples is None else data.samples, data.source):
        if x is None or not len(x):
            continue
        x = np.asarray(x, dtype=float)
        if out and src[-1] == source and len(out[-1]) > 1:
            prev = out[-1]
            dt = float(np.median(np.diff(prev[:, 0])))
            # the same attitude: both triads' mean directions within SAME_ATTITUDE_DEG (a move turns
            # them by degrees; noise and a wander by thousandths)
            same = all(_angle_deg(prev[:, c].mean(axis=0), x[:, c].mean(axis=0)) <= SAME_ATTITUDE_DEG
                       for c in (slice(1, 4), slice(4, 7)))
            if 0 < x[0, 0] - prev[-1, 0] <= 1.5 * dt and same:
                out[-1] = np.vstack([prev, x])
                continue
        out.append(x)
        src.append(source)
    return out


def walk_axes(noise: SensorNoise) -> tuple:
    """``(axes, densities)``: the axes whose random walk the noise model resolves, and ``K`` of each."""
    k = noise.walk_density()
    axes = "".join(a for a, v in zip("xyz", k) if v > 0)
    return axes, np.array([v for v in k if v > 0])


def noise_json(models: dict) -> dict:
    return {s: m.to_json() for s, m in models.items()}
