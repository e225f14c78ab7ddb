"""Example plug-in: a bias that grows with the square of the temperature offset.

Not in the catalogue (whose ``temperature_bias`` is linear).  Use it with::

    inclinometer-calib simulate --out sim --plugin examples/plugins/quadratic_temperature.py \
        --effect temperature_bias_quadratic:mag=0.2
    inclinometer-calib lab diagnose --cal sim/cal.csv --val sim/val.csv \
        --plugin examples/plugins/quadratic_temperature.py
"""
from inclinometer_calib.core.effects import T_REF_C, Effect, ParamSpec


class QuadraticTemperatureBias(Effect):
    """Bias b(T) = c2·(T − T_ref)² per axis (e.g. a fluxgate's excitation drifting with heat)."""

    name = "temperature_bias_quadratic"
    stage = "output"
    specs = (ParamSpec("c2", {"acc": "m/s^2/degC^2", "mag": "nT/degC^2"}, {"acc": 1e-5, "mag": 0.1},
                       "quadratic temperature coefficient of the bias"),)

    def _apply(self, v, ctx):
        v[:, self._idx()] += self.values["c2"] * ((ctx.temperature_c - T_REF_C) ** 2)[:, None]
