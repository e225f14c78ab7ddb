"""A few last results by key, handed out as copies: the one memo of the package.

For work a process repeats on the same input — the noise model of the same holds in every step of
a diagnosis (:func:`detect.allan.allan_curve`), the same logs read by a diagnosis, its fit and its
report (:func:`lab.data.load_logs`).  Values go in and come out as deep copies, so what a caller
changes in its result is never what the next caller gets.
"""
from __future__ import annotations

import copy
from collections import OrderedDict


class CopyMemo:
    """The last ``size`` values by key (least recently used out first)."""

    def __init__(self, size: int):
        self.size = int(size)
        self._items: OrderedDict = OrderedDict()

    def __contains__(self, key) -> bool:
        return key in self._items

    def __len__(self) -> int:
        return len(self._items)

    def keys(self) -> list:
        return list(self._items)

    def get(self, key, default=None):
        """A copy of the value kept under ``key``, else ``default``."""
        if key not in self._items:
            return default
        self._items.move_to_end(key)
        return copy.deepcopy(self._items[key])

    def put(self, key, value) -> None:
        """Keep a copy of ``value`` under ``key``."""
        self._items[key] = copy.deepcopy(value)
        self._items.move_to_end(key)
        while len(self._items) > self.size:
            self._items.popitem(last=False)

    def clear(self) -> None:
        self._items.clear()
