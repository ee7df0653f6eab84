"""``unshadowed``: visibility 1, the cost baseline of the benchmarks (no map)."""
from __future__ import annotations

import mitsuba as mi

from ..methods import Method
from .common import Lookup


def unshadowed(smap, lk: Lookup, opts, active=True) -> mi.Float:
    """No shadows (visibility 1): the baseline for cost ratios."""
    return mi.Float(1.0)


METHOD = Method(name="unshadowed", lookup=unshadowed, uses_map=False,
                summary="no shadows (visibility 1): the cost baseline of benchmarks",
                builtin=True)
