"""Shared pieces of every lookup: the call's inputs and the helpers written once.

(See :mod:`mi_shadowmap.filters` for the call shape.)

Visibility lookups: (map, world point, normal, footprint) -> visibility in [0, 1].

Every method is a function ``fn(smap, lk, opts, active) -> mi.Float`` where

* ``smap`` is the emitter's :class:`~mi_shadowmap.depth_maps.ShadowMap`
  (or, for ``raytraced``, a :class:`RayTracedLight`);
* ``lk`` is a :class:`Lookup`: the shading point ``p_world``, its geometric
  normal ``n_world``, the camera pixel footprint ``dp_dx``/``dp_dy`` on the
  surface, the light sample ``ds`` and the ``sampler``;
* ``opts`` are the validated :class:`~mi_shadowmap.options.Options`.

The registry :data:`FILTERS` maps method names to these functions. Shared
helpers (receiver depth with biases, off-map handling) are written once
here.

Depth comparisons happen in the map's depth space (world distance from the
light, see :mod:`mi_shadowmap.light_views`): a receiver at biased depth
``z_r`` is lit by a texel of depth ``z_map`` when ``z_r <= z_map``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi


@dataclass
class Lookup:
    """Inputs shared by every lookup at a batch of shading points."""
    p_world: mi.Point3f
    n_world: mi.Vector3f          # geometric normal (any orientation)
    dp_dx: mi.Vector3f            # pixel footprint on the surface (world)
    dp_dy: mi.Vector3f
    si: object                    # mi.SurfaceInteraction3f (for spawning rays)
    ds: object                    # mi.DirectionSample3f of the light sample
    sampler: object


@dataclass
class RayTracedLight:
    """The 'map' of the ray-traced reference: the scene itself."""
    scene: mi.Scene


@dataclass
class Receiver:
    """A shading point expressed in a light's map, biases applied."""
    face: mi.UInt32
    uv: mi.Point2f
    depth: mi.Float              # biased receiver depth (compare with z_map)
    inside: mi.Bool              # False: outside every face -> lit
    texel_world: mi.Float        # world width of a texel at the receiver
    tan_theta: mi.Float          # tan(angle between normal and light), clamped


def receiver(smap, lk: Lookup, opts) -> Receiver:
    """Project a shading point into ``smap`` with the configured biases.

    * ``normal_bias`` (texels): the point is moved along its normal (turned
      towards the light) by that many texel widths before projection;
    * ``slope_bias`` (texels): ``slope_bias * texel_width * tan(theta)`` is
      subtracted from the receiver depth, ``theta`` being the angle between
      the normal and the direction to the light (``tan`` clamped at
      ``max_tan_slope``);
    * ``bias`` (world units): subtracted from the receiver depth.

    The texel biases scale with the map's texel size, hence with the scene:
    the automatic default is scale-invariant.
    """
    view, res = smap.view, smap.resolution
    p = lk.p_world
    w_light = view.direction_to_light(p)
    cos_nl = dr.dot(lk.n_world, w_light)
    n_towards = dr.select(cos_nl < 0, -lk.n_world, lk.n_world)
    cos_nl = dr.clip(dr.abs(cos_nl), 1e-6, 1.0)
    tan_theta = dr.minimum(dr.safe_sqrt(1.0 - cos_nl * cos_nl) / cos_nl, opts.max_tan_slope)
    texel = view.texel_world_size(res, view.depth_of(p))
    if opts.normal_bias_texels > 0:
        p = p + n_towards * (opts.normal_bias_texels * texel)
    face, uv, depth, inside = view.project(p)
    z = depth - opts.bias_world - opts.slope_bias_texels * texel * tan_theta
    return Receiver(face, uv, z, inside, texel, tan_theta)


def shifted_grid_point(k: int, n: int, shift: mi.Point2f) -> mi.Point2f:
    """Point ``k`` of ``n`` on a stratified grid, toroidally shifted by ``shift``.

    The grid has ``cols = ceil(sqrt(n))`` columns and ``ceil(n / cols)`` rows
    of cell centres. With ``shift`` uniform in [0, 1)^2 (one per camera
    sample) every point is uniformly distributed, so averages over the
    pattern are unbiased for any ``n``, while the points stay stratified.
    """
    cols = math.ceil(math.sqrt(n))
    rows = math.ceil(n / cols)
    u = mi.Point2f(((k % cols) + 0.5) / cols, ((k // cols) + 0.5) / rows) + shift
    return u - dr.floor(u)


