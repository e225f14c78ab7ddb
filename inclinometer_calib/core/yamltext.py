"""YAML text in and out, the one place the package parses and writes it.

PyYAML's libyaml bindings (``CSafeLoader``/``CSafeDumper``) when PyYAML was built with them, else
its pure-Python ``SafeLoader``/``SafeDumper``: the same safe subset either way (plain data, no
Python objects), the C pair about seven times faster (a calibration record: 16 ms → 2.4 ms to
read). The data read are the same; the text written may fold long strings at other places, which
YAML reads back to the same values.
"""
from __future__ import annotations

import yaml

#: the loader and dumper of every YAML text the package reads and writes
SafeLoader = getattr(yaml, "CSafeLoader", yaml.SafeLoader)
SafeDumper = getattr(yaml, "CSafeDumper", yaml.SafeDumper)
#: what a text that is not YAML raises
YAMLError = yaml.YAMLError


def load(stream):
    """The data of one YAML document (a ``str``, ``bytes`` or an open file); ``yaml.safe_load``'s."""
    return yaml.load(stream, Loader=SafeLoader)


def dump(data, stream=None, **kwds):
    """``data`` as YAML text (or written to ``stream``); ``yaml.safe_dump``'s keywords."""
    return yaml.dump_all([data], stream, Dumper=SafeDumper, **kwds)
