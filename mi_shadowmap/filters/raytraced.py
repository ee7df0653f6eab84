"""``raytraced``: the ground truth, real shadow rays toward the light sample (no map)."""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from ..methods import Method, Prop
from ..rays import spawn_shadow_ray
from .common import Lookup, RayTracedLight


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


METHOD = Method(
    name="raytraced",
    lookup=raytraced,
    summary="shadow rays toward each light sample: the ground truth (matches Mitsuba's "
            "'direct' with emitter_samples=1, bsdf_samples=0)",
    properties=(Prop("shadow_rays", "int", 1,
                     "Shadow rays per camera sample per emitter (stratified light samples).",
                     lo=1, hi=65536),),
    uses_map=False,
    shadow_rays="shadow_rays",
    builtin=True,
)
