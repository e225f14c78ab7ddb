"""User-defined effects (plug-ins) loaded from the user's own Python file.

A plug-in file defines one or more subclasses of :class:`inclinometer_calib.effects.Effect` with a
unique ``name``, the ``stage`` it acts at (``tool``, ``axes``, ``gain`` or ``output``), the
``sensors`` it applies to, its parameters (``specs``: name, unit and typical magnitude per sensor)
and ``_apply(self, v, ctx)``, which changes the (N, 3) signal ``v`` in place using
``self.values[...]`` (one value per acted-on axis) and ``ctx.temperature_c`` / ``ctx.time_s``.
Loading the file registers every such class, after which the effect can be simulated, fitted,
ranked by the diagnosis and named on the command line like a catalogue effect::

    from inclinometer_calib.effects import Effect, ParamSpec, T_REF_C

    class QuadraticTemperatureBias(Effect):
        name = "temperature_bias_quadratic"
        stage = "output"
        specs = (ParamSpec("c2", {"acc": "m/s^2/degC^2", "mag": "nT/degC^2"},
                           {"acc": 1e-5, "mag": 0.1}),)

        def _apply(self, v, ctx):
            v[:, self._idx()] += self.values["c2"] * ((ctx.temperature_c - T_REF_C) ** 2)[:, None]

See ``docs/model_lab.md`` and ``examples/plugins/quadratic_temperature.py``.
"""
from __future__ import annotations

import hashlib
import importlib.util
import inspect
import os
import sys

from .. import effects as fx


class PluginError(ValueError):
    """A plug-in file could not be loaded or defines no usable effect."""


def load_plugin(path) -> list:
    """Import ``path`` and register the Effect subclasses it defines.  Returns their names."""
    path = os.path.abspath(os.fspath(path))
    if not os.path.isfile(path):
        raise PluginError(f"plug-in file {path} does not exist")
    modname = "inclinometer_calib_plugin_" + hashlib.sha1(path.encode()).hexdigest()[:10]
    if modname in sys.modules:
        module = sys.modules[modname]
    else:
        spec = importlib.util.spec_from_file_location(modname, path)
        module = importlib.util.module_from_spec(spec)
        sys.modules[modname] = module
        try:
            spec.loader.exec_module(module)
        except Exception as exc:  # the user's code: report whatever it raised, with the file
            del sys.modules[modname]
            raise PluginError(f"plug-in {path} failed to import: {type(exc).__name__}: {exc}") from exc
    names = []
    for _, cls in inspect.getmembers(module, inspect.isclass):
        if issubclass(cls, fx.Effect) and cls.__module__ == module.__name__ and cls.name:
            try:
                fx.register(cls)
            except (TypeError, ValueError) as exc:
                raise PluginError(f"plug-in {path}: {exc}") from None
            names.append(cls.name)
    if not names:
        raise PluginError(f"plug-in {path} defines no subclass of inclinometer_calib.effects.Effect with a name")
    return names
