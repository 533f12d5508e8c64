"""A small bounded most-recently-used cache for the simulator's expensive, pure objects
(renderers, FEM models)."""

from __future__ import annotations

from collections import OrderedDict
from typing import Callable, Hashable, TypeVar

T = TypeVar("T")


def cached(cache: OrderedDict[Hashable, T], key: Hashable, make: Callable[[], T],
           limit: int) -> T:
    """``cache[key]``, made with ``make()`` on a miss; keeps the ``limit`` most recently used."""
    value = cache.get(key)
    if value is None:
        value = cache[key] = make()
        while len(cache) > limit:
            cache.popitem(last=False)
    else:
        cache.move_to_end(key)
    return value
