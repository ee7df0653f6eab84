"""``raytraced``: the ground truth, real shadow rays toward the light sample (no map)."""
from __future__ import annotations

import math
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

from ..light_views import emitter_kind
from ..light_views.base import emitter_frame, opaque_point
from ..methods import Method, Prop
from ..rays import is_infinite, on_cylinder, spawn_shadow_ray
from .common import Lookup, RayTracedLight


def raytraced(smap: RayTracedLight, lk: Lookup, opts, active=True) -> mi.Float:
    """Ground truth: one shadow ray from the shading point to the light sample.

    The ray is spawned by :func:`mi_shadowmap.rays.spawn_shadow_ray` (an origin
    offset and an end shortening relative to the coordinates involved), not by
    Mitsuba's ``si.spawn_ray_to``, whose offset has an absolute floor and makes
    the reference drift with the scene's scale.

    With ``light_sample='independent'`` the ray goes to a second light sample of the
    same emitter, drawn independently of the one that is shaded: the expected
    contribution is then ``E[L] * E[V]``, the unshadowed light times the fraction of
    the light that is visible. That is the quantity every shadow-map method
    estimates (its visibility does not depend on which point of an area light was
    sampled), so this is their ideal: the difference between the two settings is
    the error of treating visibility as a factor, which no map can remove. For
    delta lights (point, spot, directional) both settings are the same. A map sees
    no horizon, so the second sample is drawn from the part of the light above the
    receiver's horizon (see :func:`_independent_target`).

    A delta light given a size (``light_size`` for point, spot and projector lights,
    ``angular_diameter`` for directional ones; see :func:`sized_shape`) is shaded as
    before, from its own sample, but each shadow ray goes to a point of the sized
    light drawn above the receiver's horizon (:func:`_sized_target`): the visibility,
    averaged over ``shadow_rays``, is the fraction of that light the point sees.
    """
    target, n_target = lk.ds.p, lk.ds.n
    shape = sized_shape(smap.emitter, opts)
    if shape is not None:     # (a delta light: its ray ends short by rounding alone)
        target = _sized_target(lk, active, shape, opts.shadow_rays)
    elif opts.light_sample == "independent":
        target, n_target = _independent_target(lk, active, smap.emitter)
    ray = spawn_shadow_ray(lk.si, target, smap.scene, is_infinite(smap.emitter),
                           getattr(smap, "p_surface", None), smap.emitter, n_target)
    occluded = smap.occlusion(ray, active,     # not ray_test alone: spheres, cylinders
                              on_cylinder(lk.si, smap.scene), lk.si)
    return dr.select(occluded, 0.0, 1.0)


#: Draws of :func:`_independent_target` (rejection of samples below the horizon).
HORIZON_TRIES = 8


def _independent_target(lk: Lookup, active, emitter) -> tuple:
    """A light point drawn independently of the shaded sample ``lk.ds``, from the part
    of its emitter on the viewer's side of the receiver's surface (where the shaded
    sample lies, as it is shaded): the first of :data:`HORIZON_TRIES` draws that is
    there, else the shaded sample's point (only where the light barely clears the
    horizon). Rejection makes it a sample of the visible part of the light, so the
    visibility estimated is the fraction of *that* part left unoccluded, which is
    what a shadow map's compare measures (it does not count the horizon). The draw
    must also face the receiver, as the shaded sample does (an area light emits from
    its front only): a point on the back of a closed light (a ``cube``) is hidden by
    the light itself, which made the image 37 % too dark under a cube light.
    ``emitter`` is the light's own object, called directly: through the samples'
    emitter pointer every live emitter of the process was traced, and one on a shape
    Mitsuba cannot sample (a curve) in another scene made the render fail. Returns the
    point and the light's normal there (``ds.n``, for the ray's end)."""
    si = lk.si
    infinite = is_infinite(emitter)
    viewer = dr.sign(si.wi.z)
    target, normal, found = mi.Point3f(lk.ds.p), mi.Vector3f(lk.ds.n), mi.Bool(False)
    for _ in range(HORIZON_TRIES):   # unrolled: the draws stay outside any loop
        ds, _ = emitter.sample_direction(si, lk.sampler.next_2d(active), active)
        ok = active & ~found & (ds.pdf > 0) & (si.to_local(ds.d).z * viewer > 0)
        if not infinite:     # the emitter's front (Mitsuba's area lights are one-sided)
            ok &= dr.dot(ds.d, ds.n) < 0
        target = dr.select(ok, ds.p, target)
        normal = dr.select(ok, ds.n, normal)
        found |= ok
    return target, normal


# ------------------------------------------------------------ delta lights given a size
@dataclass(frozen=True)
class SizedShape:
    """What a delta light stands for when given a size (as ``multiview`` and ``pcss``
    read ``light_size`` and ``angular_diameter``): ``kind`` ``'sphere'`` (a point light:
    ``size`` its diameter), ``'square'`` (a spot or projector: ``size`` its side, across
    the light's axis; ``axes`` the emitter frame's x and y in the world, the frame of
    :func:`~mi_shadowmap.light_views.base.emitter_frame`, which its views use) or
    ``'cone'`` (a directional light: ``size`` its angular diameter in degrees)."""
    kind: str
    size: float
    axes: tuple = ()


def sized_shape(emitter, opts) -> SizedShape | None:
    """The extent ``opts`` gives ``emitter`` (a point, spot or projector light with
    ``light_size`` > 0, a directional one with ``angular_diameter`` > 0), else None:
    the light keeps no extent (area lights keep their own shape: ``light_size`` does
    not act on them, and a render warns where it acts on none of a scene's lights)."""
    if emitter is None:
        return None
    kind = emitter_kind(emitter)
    size = float(getattr(opts, "light_size", None) or 0.0)
    if kind == "point" and size > 0.0:
        return SizedShape("sphere", size)
    if kind in ("spot", "projector") and size > 0.0:
        frame = emitter_frame(emitter.world_transform(), (0.0, 0.0, 0.0)).matrix
        rows = [tuple(float(frame[i][j]) for j in range(3)) for i in range(2)]
        return SizedShape("square", size, tuple(rows))
    angle = float(getattr(opts, "angular_diameter", 0.0) or 0.0)
    if kind == "directional" and angle > 0.0:
        return SizedShape("cone", angle)
    return None


def cone_direction(u: mi.Point2f, one_minus_cos) -> mi.Vector3f:
    """A direction uniform in solid angle in the cone about ``+z`` of half-angle ``a``,
    given ``one_minus_cos`` = ``1 - cos(a)`` (``u`` in ``[0, 1)^2``): Mitsuba's
    ``warp.square_to_uniform_cone``, but from ``1 - cos(a)`` itself, which float32 keeps
    for tiny cones (``cos(a)`` rounds to 1 below a = 3.5e-4 rad: every direction was the
    axis, a sun of 0.02 degrees or a sphere light seen 3000 radii away gave hard
    shadows)."""
    disk = mi.warp.square_to_uniform_disk_concentric(u)
    r2 = dr.squared_norm(disk)
    xy = disk * dr.safe_sqrt(one_minus_cos * (2.0 - one_minus_cos * r2))
    return mi.Vector3f(xy.x, xy.y, 1.0 - one_minus_cos * r2)


def sphere_point(p_world: mi.Point3f, centre: mi.Point3f, radius, u: mi.Point2f):
    """A point of the sphere ``(centre, radius)`` drawn as Mitsuba draws a sphere light's
    sample from ``p_world``: uniform in solid angle in the cone the sphere subtends, on
    the near side (no point behind its silhouette). The point is ``centre`` plus an
    offset of length ``radius`` computed from the drawn direction's sine (no difference
    of distances: a light 1e4 from the receiver keeps its millimetres). Inside the
    sphere (no cone) it is ``centre``: the light's own position."""
    to_centre = centre - p_world
    d2 = dr.squared_norm(to_centre)
    r2 = radius * radius
    outside = d2 > r2
    inv_d = dr.rsqrt(dr.maximum(d2, dr.smallest(mi.Float)))
    sin2_max = dr.minimum(r2 / dr.maximum(d2, dr.smallest(mi.Float)), 1.0)
    v = cone_direction(u, sin2_max / (1.0 + dr.safe_sqrt(1.0 - sin2_max)))
    sin2 = v.x * v.x + v.y * v.y
    t = d2 * inv_d * v.z - dr.safe_sqrt(r2 - d2 * sin2)      # distance to the near hit
    offset = mi.Vector3f(t * v.x, t * v.y, -dr.safe_sqrt(r2 - t * t * sin2))
    q = centre + mi.Frame3f(to_centre * inv_d).to_world(offset)
    return dr.select(outside, q, centre)


def sized_point(lk: Lookup, shape: SizedShape, u: mi.Point2f) -> mi.Point3f:
    """The point of ``shape`` (a delta light given a size, :func:`sized_shape`) that
    sample ``u`` draws, seen from ``lk``: the sphere in the cone it subtends
    (:func:`sphere_point`), the square uniformly by area, the sun's cone uniformly in
    solid angle, as a point ``lk.ds.dist`` away (where Mitsuba puts the sun's sample;
    :func:`~mi_shadowmap.rays.spawn_shadow_ray` reaches past the scene anyway)."""
    centre = mi.Point3f(lk.ds.p)      # a point, spot or projector light's position
    if shape.kind == "sphere":
        return sphere_point(lk.si.p, centre, 0.5 * shape.size, u)
    if shape.kind == "square":
        x, y = (mi.Vector3f(opaque_point(a)) for a in shape.axes)
        return centre + (x * (u.x - 0.5) + y * (u.y - 0.5)) * shape.size
    half = 0.5 * math.radians(shape.size)
    d = mi.Frame3f(lk.ds.d).to_world(cone_direction(u, 2.0 * math.sin(0.5 * half) ** 2))
    return lk.si.p + d * lk.ds.dist


def _sized_target(lk: Lookup, active, shape: SizedShape, n: int) -> mi.Point3f:
    """A point of the sized light ``shape`` (:func:`sized_point`) on the viewer's side
    of the receiver's surface, as :func:`_independent_target` draws an area light's: the
    first of :data:`HORIZON_TRIES` draws there, else the light's own sample (only where
    the light barely clears the horizon). So the shadow rays estimate the fraction of
    the light's part above the horizon that is unoccluded, the quantity a map's compare
    measures; the light's own sample, which is shaded, is above it where it counts.

    The first draw is in the stratum of ``lk.u_light``, the integrator's stratified
    light sample (a delta light's own point does not use it; :func:`_in_stratum`), so the
    ``shadow_rays`` points are stratified over the light: on the default scene (64^2,
    4 spp, a point light of size 1, RMSE to 4096 rays at 16 / 64 / 256 rays) 0.0152 /
    0.0079 / 0.0040 with independent draws (1 / sqrt(rays)) fell to 0.0111 / 0.0039 /
    0.0015, about 1 / rays^(3/4) (benchmarks/RESULTS.md, forty-seventh session, helper
    H). Without it (None:
    a gradient render's ``pixel_centre`` runs) the first draw is the sampler's. Later
    draws, for the few lanes whose first is below the horizon, are the sampler's, in a
    ``dr.while_loop`` a lane leaves at its first draw above the horizon: unrolled as in
    :func:`_independent_target`, the eight draws made 64 sized shadow rays 2.0x (point)
    and 2.1x (sun) the time of 64 hard ones on the default scene at 64^2, the loop 1.2x
    and 1.3x."""
    si = lk.si
    viewer = dr.sign(si.wi.z)
    active = mi.Bool(active)

    def above(q):
        return si.to_local(q - si.p).z * viewer > 0

    if lk.u_light is None:
        tries, found, target = mi.UInt32(0), mi.Bool(False), mi.Point3f(lk.ds.p)
    else:
        q = sized_point(lk, shape, _in_stratum(lk.u_light, n, lk.sampler.next_2d(active)))
        found = active & above(q)
        tries, target = mi.UInt32(1), dr.select(found, q, mi.Point3f(lk.ds.p))

    def cond(i, found, target, sampler):
        return active & ~found & (i < HORIZON_TRIES)

    def body(i, found, target, sampler):
        q = sized_point(lk, shape, sampler.next_2d(active & ~found))
        ok = ~found & above(q)
        return i + 1, found | ok, dr.select(ok, q, target), sampler

    _, _, target, _ = dr.while_loop((tries, found, target, lk.sampler), cond, body,
                                    labels=("i", "found", "target", "sampler"),
                                    label="raytraced sized light draws")
    return target


def _in_stratum(u_light, n: int, u_jitter: mi.Point2f) -> mi.Point2f:
    """A point uniform in the stratum of ``u_light``, the integrator's light sample: a
    point of :func:`~mi_shadowmap.filters.common.shifted_grid_point`'s grid of ``n``
    (``ceil(sqrt(n))`` columns, ``ceil(n / cols)`` rows of cells, their centres shifted
    together), moved by ``u_jitter`` (uniform in ``[0, 1)^2``) within its cell, wrapped
    on the unit torus. The grid's points alone, shifted as one, kept the error of a
    penumbra near 1 / sqrt(n) (16 -> 256 rays: 4.8x, the lattice resonating with an
    edge); jittered in their cells, 7.7x (about 1 / n^(3/4)). Whatever the grid, the
    point is uniform in ``[0, 1)^2`` (``u_light`` is, and the move is independent of it),
    so a grid other than this one would cost stratification, never bias."""
    cols = math.ceil(math.sqrt(n))
    rows = math.ceil(n / cols)
    u = mi.Point2f(u_light) + mi.Point2f((u_jitter.x - 0.5) / cols, (u_jitter.y - 0.5) / rows)
    return u - dr.floor(u)


METHOD = Method(
    name="raytraced",
    lookup=raytraced,
    summary="shadow rays toward each light sample: the ground truth (matches Mitsuba's "
            "'direct')",
    properties=(Prop("shadow_rays", "int", 1,
                     "Shadow rays per camera sample per emitter (stratified light samples).",
                     lo=1, hi=65536),
                Prop("light_sample", "str", "shared",
                     "'shared': the shadow ray goes to the light sample that is shaded "
                     "(Mitsuba's 'direct'; the ground truth). 'independent': to a second, "
                     "independent sample of the same light, so visibility is a factor of "
                     "the unshadowed light, as in every shadow-map method: the ideal those "
                     "methods approximate (differs from 'shared' only for area lights).",
                     choices=("shared", "independent")),
                Prop("light_size", "float", None,
                     "Point, spot and projector lights: their width in world units, as in "
                     "'multiview' (point: a sphere of that diameter, its shadow rays drawn "
                     "in the cone it subtends; spot, projector: a square across the axis). "
                     "Each shadow ray goes to a point of it, so visibility is the fraction "
                     "of it the point sees; the shading is the light's own. Default 0: the "
                     "light itself (hard shadows). Area lights keep their shape.", lo=0.0,
                     lights=("point", "spot", "projector")),
                Prop("angular_diameter", "float", 0.0,
                     "Apparent diameter of a directional light in degrees; > 0: shadow rays "
                     "in that cone of directions, uniform in solid angle (0: hard shadows).",
                     lo=0.0, hi=30.0, lights=("directional",))),
    uses_map=False,
    shadow_rays="shadow_rays",
    builtin=True,
)
