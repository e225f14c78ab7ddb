"""User-defined effects (plug-ins): executed only from a Python file or module the user named.

A plug-in defines one or more subclasses of :class:`inclinometer_calib.core.effects.Effect` with a
unique ``name``, the ``stage`` it acts at (``tool``, ``axes``, ``gain`` or ``output``), the
``sensors`` it applies to, its parameters (``specs``: name, unit and typical magnitude per sensor)
and ``_apply(self, v, ctx)``, which changes the (N, 3) signal ``v`` in place using
``self.values[...]`` (one value per acted-on axis) and ``ctx.temperature_c`` / ``ctx.time_s``.
It may declare the rest of an effect's metadata (``needs``, ``signature``, ``field_regressors``,
``iscwsa``, ``survey_only``); what it does not declare is found out (``Effect.context_needs``) or
left empty.  Loading registers every such class, after which the effect can be simulated, fitted,
ranked by the diagnosis, named on the command line and carried by a calibration record like a
catalogue effect::

    from inclinometer_calib.core.effects import Effect, ParamSpec, T_REF_C

    class QuadraticTemperatureBias(Effect):
        name = "temperature_bias_quadratic"
        stage = "output"
        specs = (ParamSpec("c2", {"acc": "m/s^2/degC^2", "mag": "nT/degC^2"},
                           {"acc": 1e-5, "mag": 0.1}),)

        def _apply(self, v, ctx):
            v[:, self._idx()] += self.values["c2"] * ((ctx.temperature_c - T_REF_C) ** 2)[:, None]

**Code comes from the user, never from data.**  A plug-in is Python code; a calibration record
is data (it arrives in files, on ``/calibration/coefficients``, from bags and registries).  So:

* the user *names* plug-ins — ``--plugin PATH|MODULE`` on the command line, the ``plugins``
  parameter of a node — and :func:`name_plugin` keeps each in this process's registry of named
  sources with the SHA-256 of its source file, read when it is named; naming executes nothing;
* a command that needs the effects themselves (``simulate``, ``twelve-position``, the lab's fit,
  diagnosis and report, ``reprocess --calibrate --effects``) executes what the user named at once
  (:func:`load_plugin`): that is what the user asked for;
* a record that uses a plug-in effect names it by file (or module) and the SHA-256 of its source
  (:func:`reference`).  Loading the record (:func:`require_plugin`) never imports the file or
  module the record names: it executes a *named* source whose SHA-256 (of the bytes read now,
  which are the bytes executed) equals the record's, and refuses the record otherwise, in one line
  that names the effect, the record's plug-in and its hash, and how to allow it.  A named source
  whose content is not the record's is refused without being executed, and an effect already
  loaded from another source is refused too, so a record never means other numbers than the ones
  it was fitted with.

The SHA-256 covers the plug-in's own source file, not what it imports.  A dotted module name
``pkg.mod`` is located with :func:`importlib.util.find_spec`, which imports (executes) the parent
package(s) ``pkg`` — code the user named by naming the module, never something a record can
cause; name the file instead to have nothing executed before the hash is compared.  See
``docs/model_lab.md`` and ``examples/plugins/quadratic_temperature.py``.
"""
from __future__ import annotations

import hashlib
import importlib.util
import inspect
import os
import re
import sys

from . import effects as fx


class PluginError(ValueError):
    """A plug-in could not be named or loaded, defines no usable effect, or is not the one a record names."""


#: The plug-in sources the user named in this process: source file (absolute) -> entry with
#: ``ref`` (``{"file": path}`` or ``{"module": name}``), ``sha256`` (read when named) and
#: ``spec`` (a module's import spec).  Only these are ever executed.
_NAMED: dict = {}

_SHA256 = re.compile(r"[0-9a-f]{64}")
#: The description of the nodes' ``plugins`` parameter (a read-only string array).
NODE_PARAMETER = ("Python files (or modules) defining plug-in effects that records may use; a record's plug-in is "
                  "loaded only from these, after its SHA-256 matches")
#: How the user allows a record's plug-in, said in every refusal.
_HOW_TO_NAME = "--plugin PATH on the command line, the plugins parameter on a node"


def _is_module_name(spec: str) -> bool:
    return not spec.endswith(".py") and os.sep not in spec and "/" not in spec and all(
        part.isidentifier() for part in spec.split("."))


def _read(path) -> tuple[bytes, str]:
    """The bytes of a source file and their SHA-256 (hashed before anything executes them)."""
    try:
        with open(path, "rb") as fh:
            data = fh.read()
    except OSError as exc:
        raise PluginError(f"plug-in {path}: {exc.strerror}") from None
    return data, hashlib.sha256(data).hexdigest()


def name_plugin(spec) -> dict:
    """Name ``spec`` — a ``.py`` file, or a module name on the Python path — as a plug-in source the
    user allows, without executing it (see the module docstring: a dotted name imports its parent
    packages to be found).  Returns its reference (``{"file": <absolute path>}`` or
    ``{"module": <name>}``, and ``"sha256"`` of the source read now); naming the same source again
    reads it again."""
    entry = _name(spec)
    return dict(entry["ref"], sha256=entry["sha256"])


def name_plugins(specs) -> list:
    """:func:`name_plugin` for each of ``specs`` (None: none); the references, in order."""
    return [name_plugin(s) for s in specs or ()]


def _name(spec) -> dict:
    spec = os.fspath(spec)
    mspec = None
    if _is_module_name(spec) and not os.path.exists(spec):
        try:
            mspec = importlib.util.find_spec(spec)
        except Exception as exc:  # a parent package (the user's code) failed to import: report what it raised
            raise PluginError(f"plug-in module {spec} cannot be found: {type(exc).__name__}: {exc}") from None
        if mspec is None:
            raise PluginError(f"plug-in module {spec} is not on the Python path")
        if not mspec.has_location or not str(mspec.origin).endswith(".py") or not os.path.isfile(mspec.origin):
            raise PluginError(f"plug-in module {spec} has no Python source file to check ({mspec.origin})")
        path, ref = os.path.abspath(mspec.origin), {"module": spec}
    else:
        path = os.path.abspath(spec)
        if not os.path.isfile(path):
            raise PluginError(f"plug-in file {path} does not exist")
        ref = {"file": path}
    _, sha = _read(path)
    entry = {"path": path, "ref": ref, "sha256": sha, "spec": mspec}
    _NAMED[path] = entry
    return entry


def _execute(entry, want: str) -> list:
    """Execute the named source ``entry`` if its bytes, read now, have the SHA-256 ``want`` (those
    very bytes are executed), and register the Effect subclasses it defines; their names.

    Each class gets ``plugin = {"file": <absolute path>}`` (or ``{"module": <name>}``) and the
    ``"sha256"`` of the source executed, which a record written with it keeps.  A source already
    executed (same file, same content) is not executed again."""
    path, ref = entry["path"], entry["ref"]
    where = ref.get("module") or path
    data, sha = _read(path)
    if sha != want:
        raise PluginError(f"plug-in {where} changed since it was named (sha256 {sha[:12]}…, was {want[:12]}…): "
                          "not loaded")
    if "module" in ref:
        modname = ref["module"]
    else:
        modname = ("inclinometer_calib_plugin_" + hashlib.sha1(path.encode()).hexdigest()[:10] + "_" + sha[:10])
    module = sys.modules.get(modname)   # executed before here, or a module the user's program imported itself
    if module is not None and getattr(module, "__plugin_sha256__", sha) != sha:
        raise PluginError(f"plug-in {where}: another version of it (sha256 {module.__plugin_sha256__[:12]}…) is "
                          f"already loaded in this process, not this one (sha256 {sha[:12]}…): start again")
    if module is None:
        mspec = entry["spec"] or importlib.util.spec_from_file_location(modname, path)
        module = importlib.util.module_from_spec(mspec)
        code = compile(data, path, "exec", dont_inherit=True)
        module.__plugin_sha256__ = sha
        sys.modules[modname] = module
        try:
            exec(code, module.__dict__)  # noqa: S102 - the bytes hashed above, of a source the user named
        except Exception as exc:  # the user's code: report whatever it raised, with the file
            del sys.modules[modname]
            raise PluginError(f"plug-in {where} failed to import: {type(exc).__name__}: {exc}") from exc
        parent, _, child = modname.rpartition(".")
        if parent in sys.modules:
            setattr(sys.modules[parent], child, module)
    names = []
    for _, cls in inspect.getmembers(module, inspect.isclass):
        if issubclass(cls, fx.Effect) and cls.__module__ == module.__name__ and cls.name:
            try:
                fx.register(cls)
            except (TypeError, ValueError) as exc:
                raise PluginError(f"plug-in {where}: {exc}") from None
            cls.plugin = dict(ref, sha256=sha)
            names.append(cls.name)
    if not names:
        raise PluginError(f"plug-in {where} defines no subclass of inclinometer_calib.core.effects.Effect with a name")
    return names


def load_plugin(spec) -> list:
    """Name the plug-in ``spec`` (:func:`name_plugin`) and execute it now: for a command that needs
    its effects (simulate, fit, diagnose).  Returns the names of the effects it registers."""
    entry = _name(spec)
    return _execute(entry, entry["sha256"])


def reference(cls) -> dict | None:
    """How a record names the plug-in an effect class comes from (None for catalogue effects)."""
    return dict(cls.plugin) if cls.plugin else None


def _label(ref: dict) -> str:
    return f"module {ref['module']!r}" if ref.get("module") else f"file {ref.get('file')!r}"


def _same_source(entry, ref: dict, base_dir: str) -> bool:
    """Whether the named ``entry`` is the plug-in ``ref`` names (by module name, path or file name)."""
    if ref.get("module"):
        return entry["ref"].get("module") == ref["module"]
    f = ref.get("file")
    if not isinstance(f, str) or not f:
        return False
    path = f if os.path.isabs(f) else os.path.join(base_dir, f)
    return os.path.abspath(path) == entry["path"] or os.path.basename(f) == os.path.basename(entry["path"])


def require_plugin(name: str, ref, base_dir: str = ".", source: str = "<record>") -> None:
    """Make sure effect ``name``, which a record says comes from the plug-in ``ref`` (``file`` or
    ``module``, and ``sha256``), is registered from a source with exactly that SHA-256.

    Never imports what ``ref`` names: when ``name`` is not registered yet, the source executed is a
    user-named one (:func:`name_plugin`) whose bytes have the record's SHA-256.  ``base_dir`` (the
    record's folder) only tells whether a named file is the one a relative ``file`` means, for the
    message.  Raises :class:`PluginError` (one line) when no named source matches, the effect is
    registered from another source (or is a built-in), or the matching source does not define it."""
    if not isinstance(ref, dict) or not (ref.get("file") or ref.get("module")):
        raise PluginError(f"{source}: effect {name!r}: its plug-in reference {ref!r} names no file or module")
    want = ref.get("sha256")
    label = _label(ref)
    if not isinstance(want, str) or not _SHA256.fullmatch(want):
        raise PluginError(f"{source}: effect {name!r} comes from the plug-in {label} with no valid sha256 "
                          f"({want!r}): the record cannot say which source it was fitted with: refit the model")
    cls = fx.CATALOGUE.get(name)
    if cls is None:
        entry = next((e for e in _NAMED.values() if e["sha256"] == want), None)
        if entry is None:
            head = f"{source}: effect {name!r} comes from the plug-in {label} (sha256 {want[:12]}…)"
            same = [e for e in _NAMED.values() if _same_source(e, ref, base_dir)]
            if same:
                e = same[0]
                raise PluginError(f"{head}, but the named {e['ref'].get('module') or e['path']} has sha256 "
                                  f"{e['sha256'][:12]}…: it changed since the record was written and is not loaded: "
                                  f"refit the model, or name the file the record was made with ({_HOW_TO_NAME})")
            named = ", ".join(e["ref"].get("module") or os.path.basename(e["path"]) for e in _NAMED.values())
            others = f" (the named {named}: other sources)" if named else ""
            raise PluginError(f"{head}, which is not named{others}: a record never loads code by itself; to allow "
                              f"it, name it: {_HOW_TO_NAME}")
        try:
            _execute(entry, want)
        except PluginError as exc:
            raise PluginError(f"{source}: effect {name!r} needs its plug-in: {exc}") from None
        cls = fx.CATALOGUE.get(name)
        if cls is None:
            raise PluginError(f"{source}: the plug-in {entry['ref'].get('module') or entry['path']} (the sha256 "
                              f"the record names) does not define effect {name!r}")
    have = (cls.plugin or {}).get("sha256")
    if have is None:
        raise PluginError(f"{source}: effect {name!r} is a plug-in effect of the record, but {name!r} is registered "
                          "here as a built-in effect")
    if have != want:
        where = (cls.plugin or {}).get("file") or (cls.plugin or {}).get("module")
        raise PluginError(f"{source}: the plug-in of effect {name!r} ({where}) changed since the record was written "
                          f"(sha256 {have[:12]}…, the record was fitted with {want[:12]}…): refit the model, or "
                          "restore the plug-in the record was made with")
