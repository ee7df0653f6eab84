"""``hard``: Williams (1978), one nearest-texel depth comparison."""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from ..methods import Method
from .common import Lookup, receiver


def hard(smap, lk: Lookup, opts, active=True) -> mi.Float:
    """Williams (1978): one nearest-texel depth comparison.

    The texel is ``floor(uv * resolution)`` of the face the (normal-offset)
    point projects into. Points outside the map are lit (Reeves 1987).
    """
    r = receiver(smap, lk, opts)
    z_map = dr.gather(mi.Float, smap.depth, smap.texel_index(r.face, r.uv), active & r.inside)
    return dr.select(~r.inside | (r.depth <= z_map), 1.0, 0.0)


METHOD = Method(name="hard", lookup=hard,
                summary="Williams 1978: one nearest-texel depth comparison", virtual=True,
                virtual_per_tap=True, builtin=True)
