"""The reference and baseline lookups: ``raytraced``, ``hard``, ``unshadowed``."""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from ..rays import spawn_shadow_ray
from .common import Lookup, RayTracedLight, receiver


def raytraced(smap: RayTracedLight, lk: Lookup, opts, active=True) -> mi.Float:
    """Ground truth: one shadow ray from the shading point to the light sample.

    The ray is spawned by :func:`mi_shadowmap.rays.spawn_shadow_ray` (an origin
    offset and an end shortening relative to the coordinates involved), not by
    Mitsuba's ``si.spawn_ray_to``, whose offset has an absolute floor and makes
    the reference drift with the scene's scale.
    """
    ray = spawn_shadow_ray(lk.si, lk.ds.p, smap.scene)
    occluded = smap.scene.ray_test(ray, active)
    return dr.select(occluded, 0.0, 1.0)


def hard(smap, lk: Lookup, opts, active=True) -> mi.Float:
    """Williams (1978): one nearest-texel depth comparison.

    The texel is ``floor(uv * resolution)`` of the face the (normal-offset)
    point projects into. Points outside the map are lit (Reeves 1987).
    """
    r = receiver(smap, lk, opts)
    z_map = dr.gather(mi.Float, smap.depth, smap.texel_index(r.face, r.uv), active & r.inside)
    return dr.select(~r.inside | (r.depth <= z_map), 1.0, 0.0)


def unshadowed(smap, lk: Lookup, opts, active=True) -> mi.Float:
    """No shadows (visibility 1): the baseline for cost ratios."""
    return mi.Float(1.0)


FILTERS = {"unshadowed": unshadowed, "raytraced": raytraced, "hard": hard}
