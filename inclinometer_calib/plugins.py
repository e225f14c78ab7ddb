"""User-defined effects (plug-ins): loaded from the user's own Python file or module.

A plug-in defines one or more subclasses of :class:`inclinometer_calib.effects.Effect` with a
unique ``name``, the ``stage`` it acts at (``tool``, ``axes``, ``gain`` or ``output``), the
``sensors`` it applies to, its parameters (``specs``: name, unit and typical magnitude per sensor)
and ``_apply(self, v, ctx)``, which changes the (N, 3) signal ``v`` in place using
``self.values[...]`` (one value per acted-on axis) and ``ctx.temperature_c`` / ``ctx.time_s``.
It may declare the rest of an effect's metadata (``needs``, ``signature``, ``field_regressors``,
``iscwsa``, ``survey_only``); what it does not declare is found out (``Effect.context_needs``) or
left empty.  Loading registers every such class, after which the effect can be simulated, fitted,
ranked by the diagnosis, named on the command line and carried by a calibration record like a
catalogue effect::

    from inclinometer_calib.effects import Effect, ParamSpec, T_REF_C

    class QuadraticTemperatureBias(Effect):
        name = "temperature_bias_quadratic"
        stage = "output"
        specs = (ParamSpec("c2", {"acc": "m/s^2/degC^2", "mag": "nT/degC^2"},
                           {"acc": 1e-5, "mag": 0.1}),)

        def _apply(self, v, ctx):
            v[:, self._idx()] += self.values["c2"] * ((ctx.temperature_c - T_REF_C) ** 2)[:, None]

A record that uses a plug-in effect names it by file (or module) and the SHA-256 of its source
(:func:`reference`); loading the record loads the plug-in and refuses one that is missing or
whose source changed (:func:`require_plugin`), so a record never means other numbers than the
ones it was fitted with.  See ``docs/model_lab.md`` and ``examples/plugins/quadratic_temperature.py``.
"""
from __future__ import annotations

import hashlib
import importlib
import importlib.util
import inspect
import os
import sys

from . import effects as fx


class PluginError(ValueError):
    """A plug-in could not be loaded, defines no usable effect, or is not the one a record names."""


def _sha256(path) -> str:
    with open(path, "rb") as fh:
        return hashlib.sha256(fh.read()).hexdigest()


def _is_module_name(spec: str) -> bool:
    return not spec.endswith(".py") and os.sep not in spec and "/" not in spec and all(
        part.isidentifier() for part in spec.split("."))


def load_plugin(spec) -> list:
    """Import the plug-in ``spec`` — a ``.py`` file, or a dotted module name on the Python path —
    and register the Effect subclasses it defines.  Returns their names.

    Each class gets ``plugin = {"file": <absolute path>}`` (or ``{"module": <name>}``) and
    ``"sha256"`` of its source, which a record written with it keeps."""
    spec = os.fspath(spec)
    if _is_module_name(spec) and not os.path.exists(spec):
        try:
            module = importlib.import_module(spec)
        except Exception as exc:  # the user's code: report whatever it raised
            raise PluginError(f"plug-in module {spec} failed to import: {type(exc).__name__}: {exc}") from exc
        source = inspect.getsourcefile(module)
        ref = {"module": spec}
    else:
        path = os.path.abspath(spec)
        if not os.path.isfile(path):
            raise PluginError(f"plug-in file {path} does not exist")
        modname = "inclinometer_calib_plugin_" + hashlib.sha1(path.encode()).hexdigest()[:10]
        if modname in sys.modules:
            module = sys.modules[modname]
        else:
            mspec = importlib.util.spec_from_file_location(modname, path)
            module = importlib.util.module_from_spec(mspec)
            sys.modules[modname] = module
            try:
                mspec.loader.exec_module(module)
            except Exception as exc:  # the user's code: report whatever it raised, with the file
                del sys.modules[modname]
                raise PluginError(f"plug-in {path} failed to import: {type(exc).__name__}: {exc}") from exc
        source = path
        ref = {"file": path}
    ref["sha256"] = _sha256(source)
    names = []
    for _, cls in inspect.getmembers(module, inspect.isclass):
        if issubclass(cls, fx.Effect) and cls.__module__ == module.__name__ and cls.name:
            try:
                fx.register(cls)
            except (TypeError, ValueError) as exc:
                raise PluginError(f"plug-in {spec}: {exc}") from None
            cls.plugin = dict(ref)
            names.append(cls.name)
    if not names:
        raise PluginError(f"plug-in {spec} defines no subclass of inclinometer_calib.effects.Effect with a name")
    return names


def reference(cls) -> dict | None:
    """How a record names the plug-in an effect class comes from (None for catalogue effects)."""
    return dict(cls.plugin) if cls.plugin else None


def require_plugin(name: str, ref: dict, base_dir: str = ".", source: str = "<record>") -> None:
    """Make sure effect ``name`` is registered from exactly the plug-in ``ref`` names.

    Loads it when it is not registered yet (a relative file is taken relative to ``base_dir``,
    the record's folder).  Raises :class:`PluginError` when the plug-in is missing, does not
    define ``name``, or its source no longer has the SHA-256 the record was written with."""
    want = ref.get("sha256", "")
    cls = fx.CATALOGUE.get(name)
    if cls is None:
        if "module" in ref:
            spec = ref["module"]
        else:
            spec = ref.get("file", "")
            if spec and not os.path.isabs(spec):
                spec = os.path.join(base_dir, spec)
            if not spec or not os.path.isfile(spec):
                raise PluginError(f"{source}: effect {name!r} comes from the plug-in {ref.get('file')!r}, which does "
                                  "not exist here: load it with --plugin, or put the file back")
        try:
            load_plugin(spec)
        except PluginError as exc:
            raise PluginError(f"{source}: effect {name!r} needs its plug-in: {exc}") from None
        cls = fx.CATALOGUE.get(name)
        if cls is None:
            raise PluginError(f"{source}: the plug-in {spec} does not define effect {name!r}")
    have = (cls.plugin or {}).get("sha256")
    if have is None:
        raise PluginError(f"{source}: effect {name!r} is a plug-in effect of the record, but {name!r} is registered "
                          "here as a built-in effect")
    if want and have != want:
        where = (cls.plugin or {}).get("file") or (cls.plugin or {}).get("module")
        raise PluginError(f"{source}: the plug-in of effect {name!r} ({where}) changed since the record was written "
                          f"(sha256 {have[:12]}…, the record was fitted with {want[:12]}…): refit the model, or "
                          "restore the plug-in the record was made with")
