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
    texel = view.texel_world_size(res, view.depth_of(p), p)   # p: cascaded maps
    if opts.normal_bias_texels > 0:
        p = p + n_towards * (opts.normal_bias_texels * texel)
    face, uv, depth, inside = view.project(p)
    z = depth - opts.bias_world - opts.slope_bias_texels * texel * tan_theta
    return Receiver(face, uv, z, inside, texel, tan_theta)


def shifted_grid_point(k, n: int, shift: mi.Point2f) -> mi.Point2f:
    """Point ``k`` (int or ``mi.UInt32``) of ``n`` on a stratified grid in
    [0, 1)^2, toroidally shifted by ``shift``.

    The grid has ``cols = ceil(sqrt(n))`` columns and ``ceil(n / cols)`` rows
    of cell centres. With ``shift`` uniform in [0, 1)^2 (one per camera
    sample) every point is uniformly distributed, so averages over the
    pattern are unbiased for any ``n``, while the points stay stratified.
    Used for the integrator's light samples and PCSS's ``'stratified'`` taps
    (:func:`tap_offset`).
    """
    cols = math.ceil(math.sqrt(n))
    rows = math.ceil(n / cols)
    u = mi.Point2f((mi.Float(k % cols) + 0.5) / cols, (mi.Float(k // cols) + 0.5) / rows) + shift
    return u - dr.floor(u)


# ------------------------------------------------------------------ tap patterns
def _poisson_disk(n: int, seed: int = 7) -> list:
    """``n`` points of a Poisson disk in the unit disk (deterministic dart throwing).

    Pure Python, run once per ``n`` at set-up; the minimum distance starts at
    ``1.5 / sqrt(n)`` and shrinks whenever 1000 darts in a row fail.
    """
    import random
    rng = random.Random(seed)
    r_min = 1.5 / math.sqrt(n)
    pts, fails = [], 0
    while len(pts) < n:
        x, y = rng.uniform(-1, 1), rng.uniform(-1, 1)
        if x * x + y * y > 1.0:
            continue
        if all((x - a) ** 2 + (y - b) ** 2 >= r_min * r_min for a, b in pts):
            pts.append((x, y))
            fails = 0
        else:
            fails += 1
            if fails > 1000:
                r_min *= 0.9
                fails = 0
    return pts


#: ``(variant, n) -> (x, y)`` Poisson-disk tap arrays (of that variant's ``mi.Float``).
_POISSON_CACHE: dict = {}


def tap_offset(k, n: int, pattern: str, rnd: mi.Point2f) -> mi.Point2f:
    """Offset of tap ``k`` (``mi.UInt32``) of ``n``, in units of the kernel half-width.

    * ``'stratified'``: the ``shifted_grid_point`` grid over the square
      ``[-1, 1]^2``, toroidally shifted by ``rnd`` (uniform per camera sample);
    * ``'poisson'``: a fixed Poisson disk in the unit disk, rotated by the
      angle ``2 pi rnd.x``.
    """
    if pattern == "stratified":
        return shifted_grid_point(k, n, rnd) * 2.0 - 1.0
    key = (mi.variant(), n)   # the arrays belong to the variant active when built
    if key not in _POISSON_CACHE:
        pts = _poisson_disk(n)
        _POISSON_CACHE[key] = (mi.Float([p[0] for p in pts]), mi.Float([p[1] for p in pts]))
    px, py = _POISSON_CACHE[key]
    x = dr.gather(mi.Float, px, k)
    y = dr.gather(mi.Float, py, k)
    s, c = dr.sincos(2.0 * math.pi * rnd.x)
    return mi.Point2f(c * x - s * y, s * x + c * y)


# ------------------------------------------------------- receiver-plane depth
@dataclass
class ReceiverPlane:
    """The receiver's tangent plane, for per-tap depth comparisons.

    Comparing every tap of a wide kernel with the single receiver depth
    makes a tilted receiver shadow itself; instead each tap's texel is
    compared with the depth at which that texel's light ray meets the
    receiver's tangent plane ("receiver-plane depth bias"), minus the
    receiver's own bias (:func:`receiver`).
    """
    p_world: mi.Point3f
    n_world: mi.Vector3f
    depth0: mi.Float             # unbiased map depth of p_world
    offset: mi.Float             # depth0 - biased receiver depth (>= the receiver's bias)
    max_tan: float
    light_front: tuple | None = None   # emitting normal of a planar one-sided light, or None


def receiver_plane(smap, lk: Lookup, r: Receiver, opts, light_front: bool = False
                   ) -> ReceiverPlane:
    """The receiver's tangent plane; with ``light_front`` and a planar one-sided
    area light (``view.extra['light_normal']``), texels whose ray leaves the
    light's centre behind its emitting plane can neither block nor shadow
    (:func:`plane_depth_at` returns -inf for them)."""
    depth0 = smap.view.depth_of(lk.p_world)
    front = smap.view.extra.get("light_normal") if light_front else None
    return ReceiverPlane(lk.p_world, lk.n_world, depth0, depth0 - r.depth, opts.max_tan_slope,
                         front)


def plane_depth_at(smap, plane: ReceiverPlane, face, uv_light: mi.Point2f, lateral_world):
    """Biased receiver depth to compare with the texel at ``uv_light``.

    The depth where the texel's ray meets the tangent plane, clamped to
    ``depth0 +- lateral_world * max_tan_slope`` (``lateral_world``: the tap's
    distance from the receiver, in world units at the receiver), so that
    grazing planes stay finite; minus ``plane.offset``.
    """
    o, d = smap.view.ray_through(face, uv_light)
    denom = dr.dot(plane.n_world, d)
    t = dr.dot(plane.n_world, plane.p_world - o) / dr.select(dr.abs(denom) > 1e-12, denom, 1e-12)
    lim = lateral_world * plane.max_tan
    t = dr.clip(t, plane.depth0 - lim, plane.depth0 + lim)
    if plane.light_front is not None:   # behind a one-sided light: cannot occlude it
        t = dr.select(dr.dot(d, mi.Vector3f(*plane.light_front)) > 0, t, -dr.inf)
    return t - plane.offset


def blocker_search(smap, lk: Lookup, r: Receiver, plane: ReceiverPlane, half_texels: mi.Float,
                   n: int, pattern: str, rnd: mi.Point2f, active):
    """PCSS step 1 (Fernando 2005): mean depth of the blockers in a search region.

    ``n`` taps (``tap_offset`` pattern) over the region of half-width
    ``half_texels`` around the receiver; a texel is a blocker when its depth
    is below the receiver plane's depth there (:func:`tap_depths`: taps off
    a perspective/orthographic map are not blockers; cube taps are clamped to
    the receiver's face, see :mod:`.pcss`).

    Returns ``(sum of blocker depths, number of blockers)``; one
    ``dr.while_loop``.
    """
    k = mi.UInt32(0)
    z_sum = mi.Float(0.0)
    count = mi.Float(0.0)
    active = mi.Bool(active)

    def cond(k, z_sum, count):
        return active & (k < n)

    centre = r.uv * smap.resolution

    def body(k, z_sum, count):
        off = tap_offset(k, n, pattern, rnd) * half_texels
        z_map, z, inside = tap_depths(smap, r, r.face, centre + off, plane, active,
                                      cross_seams=False, lateral_texels=dr.norm(off))
        blocked = inside & (z_map < z)
        z_sum = dr.select(blocked, z_sum + z_map, z_sum)
        count = dr.select(blocked, count + 1.0, count)
        return k + 1, z_sum, count

    k, z_sum, count = dr.while_loop((k, z_sum, count), cond, body)
    return z_sum, count


def pcf_plane(smap, lk: Lookup, r: Receiver, plane: ReceiverPlane, half_texels: mi.Float,
              n: int, pattern: str, rnd: mi.Point2f, active) -> mi.Float:
    """Percentage-closer filtering with receiver-plane depths (PCSS step 3).

    Fraction of ``n`` taps (``tap_offset`` pattern, half-width
    ``half_texels``) that are lit (:func:`tap_depths` against the receiver
    plane's depth; off-map taps lit, cube taps clamped to the receiver's
    face as in :func:`blocker_search`); one ``dr.while_loop``.
    """
    k = mi.UInt32(0)
    lit = mi.Float(0.0)
    active = mi.Bool(active)

    def cond(k, lit):
        return active & (k < n)

    centre = r.uv * smap.resolution

    def body(k, lit):
        off = tap_offset(k, n, pattern, rnd) * half_texels
        z_map, z, inside = tap_depths(smap, r, r.face, centre + off, plane, active,
                                      cross_seams=False, lateral_texels=dr.norm(off))
        return k + 1, dr.select(~inside | (z <= z_map), lit + 1.0, lit)

    k, lit = dr.while_loop((k, lit), cond, body)
    return lit / n

# ------------------------------------------------------------------ PCF taps
# Helpers shared by every percentage-closer filter (Reeves 1987 ``pcf``, the
# fixed-footprint ``bilinear`` of Brabec & Seidel, PCSS): taps are addressed
# by *continuous texel coordinates* ``xy_texel = uv_light * resolution`` on a
# face (texel ``(i, j)`` covers ``[i, i+1) x [j, j+1)``, centre at ``+0.5``).


def uv_on_face(view, face, p_world: mi.Point3f) -> mi.Point2f:
    """``uv_light`` of ``p_world`` on a *given* face (cube faces: even off that face).

    :meth:`LightView.project` picks the face itself; footprints need the
    projection onto the receiver's face, so that ``p + dp`` across a cube
    seam does not jump to another face, nor ``p + dp`` across a cascade
    split to another cascade's rectangle (cascaded views: the uv is taken in
    ``face``'s own rectangle). Perspective and orthographic views have one face.
    """
    if view.projection == "cascaded":
        p_light = mi.Transform4f(view.light_from_world) @ mi.Point3f(p_world)
        cx, cy, hx, hy = view._cascade(mi.UInt32(face))
        return mi.Point2f(0.5 * ((p_light.x - cx) / hx + 1.0),
                          0.5 * ((p_light.y - cy) / hy + 1.0))
    if view.projection != "cube":
        return view.project(p_world)[1]
    d = mi.Point3f(p_world) - mi.Point3f(view.position)
    face = mi.UInt32(face)
    axis = face // 2
    sign = dr.select((face & 1) == 0, 1.0, -1.0)
    major = sign * dr.select(axis == 0, d.x, dr.select(axis == 1, d.y, d.z))
    u_comp = dr.select(axis == 0, d.y, dr.select(axis == 1, d.z, d.x))
    v_comp = dr.select(axis == 0, d.z, dr.select(axis == 1, d.x, d.y))
    inv = dr.rcp(dr.maximum(major, 1e-30))
    return mi.Point2f(0.5 * (u_comp * inv + 1.0), 0.5 * (v_comp * inv + 1.0))


def footprint_texels(smap, lk: Lookup, r: Receiver) -> mi.Point2f:
    """Width in texels, per map axis, of the camera pixel's footprint.

    The pixel's footprint on the surface is the parallelogram
    ``p +- dp_dx/2 +- dp_dy/2`` (``lk.dp_dx``/``dp_dy``: one whole pixel, from
    ray differentials, see the integrator); its corners are projected onto the
    receiver's face and the axis-aligned bounding box of the result is
    returned as full widths ``(w_s, w_t)`` (Reeves' ``2*sres``, ``2*tres`` in
    texels). Non-finite widths (grazing views, no differentials) become 0 and
    widths are capped at the map resolution.
    """
    view, res = smap.view, smap.resolution
    uv0 = uv_on_face(view, r.face, lk.p_world)
    du_x = uv_on_face(view, r.face, lk.p_world + lk.dp_dx) - uv0
    du_y = uv_on_face(view, r.face, lk.p_world + lk.dp_dy) - uv0
    w = (dr.abs(du_x) + dr.abs(du_y)) * res
    w = mi.Point2f(dr.select(dr.isfinite(w.x), w.x, 0.0), dr.select(dr.isfinite(w.y), w.y, 0.0))
    return dr.minimum(w, float(res))


def tap_face_texel(smap, face, xy_texel: mi.Point2f, cross_seams: bool = True):
    """Texel hit by a tap at continuous texel coordinates ``xy_texel`` of ``face``.

    Returns ``(face, i, j, inside)``. Perspective and orthographic maps: a tap
    off the map has ``inside`` False (lit, Reeves 1987). Cube maps: a tap off
    its face continues on the neighbouring face (its direction is
    re-projected), so cube seams do not leak light; with ``cross_seams``
    False it is clamped to the face's border texel instead (PCSS, see
    :mod:`.pcss`).
    """
    res = smap.resolution
    ij = mi.Point2i(dr.floor(xy_texel))
    in_face = (ij.x >= 0) & (ij.x < res) & (ij.y >= 0) & (ij.y < res)
    face = mi.UInt32(face)
    if smap.view.projection != "cube":
        return face, ij.x, ij.y, in_face
    if not cross_seams:
        ij = dr.clip(ij, 0, res - 1)
        return face, ij.x, ij.y, mi.Bool(True)
    from ..light_views import _cube_dir, _cube_face
    st = xy_texel * (2.0 / res) - 1.0
    f2, s2, t2, _ = _cube_face(_cube_dir(face, st.x, st.y))
    ij2 = dr.clip(mi.Point2i(dr.floor(mi.Point2f(s2 + 1.0, t2 + 1.0) * (0.5 * res))), 0, res - 1)
    return (dr.select(in_face, face, f2), dr.select(in_face, ij.x, ij2.x),
            dr.select(in_face, ij.y, ij2.y), mi.Bool(True))


def tap_depths(smap, r: Receiver, face, xy_texel: mi.Point2f,
               plane: ReceiverPlane | None = None, active=True, cross_seams: bool = True,
               lateral_texels=None):
    """The one tap helper of every percentage-closer filter (pcf, bilinear, pcss).

    Returns ``(z_map, z_receiver, inside)`` for a tap at continuous texel
    coordinates ``xy_texel`` of ``face``: ``z_map`` is the depth of the texel
    it hits (:func:`tap_face_texel`: off a perspective/orthographic map
    ``inside`` is False -- such a tap is lit and blocks nothing; cube taps
    continue on the neighbouring face, or with ``cross_seams`` False are
    clamped to the face); ``z_receiver`` is ``r.depth`` (biases applied) or,
    with ``plane``, the receiver plane's depth along that texel's ray through
    its centre (:func:`plane_depth_at`, same biases, clamped by the tap's
    lateral distance from the receiver: ``lateral_texels``, default the
    texel centre's distance).
    """
    f2, i, j, inside = tap_face_texel(smap, face, xy_texel, cross_seams)
    z_map = smap.fetch(smap.depth, f2, i, j, active & inside)
    if plane is not None:
        res = smap.resolution
        uv_c = (mi.Point2f(i, j) + 0.5) * (1.0 / res)
        if lateral_texels is None:
            lateral_texels = dr.norm(dr.floor(xy_texel) + 0.5 - r.uv * res)
        z = plane_depth_at(smap, plane, f2, uv_c, lateral_texels * r.texel_world)
    else:
        z = r.depth
    return z_map, z, inside


def tap_lit(smap, r: Receiver, face, xy_texel: mi.Point2f, plane: ReceiverPlane | None = None,
            extra_bias=0.0, active=True) -> mi.Bool:
    """One percentage-closer comparison (:func:`tap_depths`): lit when the tap is
    off the map or ``z_receiver - extra_bias <= z_map`` (``extra_bias``: e.g.
    Reeves' stochastic bias)."""
    z_map, z, inside = tap_depths(smap, r, face, xy_texel, plane, active)
    return ~inside | (z - extra_bias <= z_map)


def reeves_sample_counts(width_s, width_t, num_samples: int, min_samples: int):
    """Samples per axis ``(ns, nt)`` for a region of ``width_s x width_t`` texels.

    Reeves, Salesin & Cook 1987, Figure 4 (with ``sres = width_s / 2``): a
    region of fewer than ``num_samples`` texels gets about one sample per
    texel and axis; a larger one gets ``ns * nt ~ num_samples`` with
    ``nt / ns ~ width_t / width_s``. Each count is rounded (``+.5``, truncated)
    and clamped to ``[min_samples, num_samples]`` (``min_samples`` wins, as in
    the paper's CLAMP).
    """
    width_s, width_t = mi.Float(width_s), mi.Float(width_t)

    def clamp(x):
        return dr.select(x < min_samples, min_samples, dr.select(x > num_samples, num_samples, x))

    small = width_s * width_t < num_samples
    ns_small = clamp(dr.floor(width_s + 0.5))
    nt_small = clamp(dr.floor(width_t + 0.5))
    ratio = width_t * num_samples / dr.maximum(width_s, 1e-30)
    nt_big = clamp(dr.floor(dr.sqrt(ratio) + 0.5))
    ns_big = clamp(dr.floor(num_samples / nt_big + 0.5))
    return (mi.UInt32(dr.select(small, ns_small, ns_big)),
            mi.UInt32(dr.select(small, nt_small, nt_big)))


def lane_rng(u_seed: mi.Point2f) -> mi.PCG32:
    """A PCG32 stream per lane, seeded from one sampler draw ``u_seed``.

    The float bits of ``u_seed.x`` pick the state and those of ``u_seed.y``
    the stream, so the per-tap numbers are a deterministic function of the
    camera sample's own random numbers (reproducible for a given sampler
    seed), and independent between lanes.
    """
    bx = dr.reinterpret_array(mi.UInt32, mi.Float(u_seed.x))
    by = dr.reinterpret_array(mi.UInt32, mi.Float(u_seed.y))
    return mi.PCG32(size=dr.width(bx), initstate=mi.UInt64(bx),
                    initseq=mi.UInt64(by) + mi.UInt64(0x9E3779B9))


#: erf(sqrt(2)): the truncation of the ``gaussian`` sampling at +-2 sigma.
_ERF_SQRT2 = math.erf(math.sqrt(2.0))


def pcf_taps(smap, r: Receiver, half_size: mi.Point2f, ns, nt, u_seed: mi.Point2f,
             sampling: str = "jitter", bias_range=None, plane: ReceiverPlane | None = None,
             center_texel: mi.Point2f | None = None, active=True) -> mi.Float:
    """Fraction of lit taps in a rectangle of the map (percentage-closer filtering).

    The rectangle is ``center_texel +- half_size`` (texels; default centre:
    the receiver, ``r.uv * resolution``) on the receiver's face, sampled by
    ``ns x nt`` taps (per-lane ``UInt32`` or ints) placed as in Reeves et al.
    1987, Figure 3:

    * ``'jitter'`` (c): one uniformly jittered tap per cell of an ``ns x nt``
      grid (stratified);
    * ``'uniform'`` (a): taps uniform over the whole rectangle;
    * ``'gaussian'`` (b): a normal distribution centred on the rectangle with
      ``sigma = half_size / 2``, truncated at the rectangle (+-2 sigma).

    ``bias_range = (bias0, bias1)``: each tap subtracts its own bias, uniform
    in that range (world units), from the receiver depth (Reeves' stochastic
    bias). Each tap is a :func:`tap_lit` comparison (off-map taps lit). The
    random numbers come from :func:`lane_rng` seeded by ``u_seed`` (one
    sampler draw per lookup). All taps run in one ``dr.while_loop``: one
    kernel whatever the sample count.
    """
    res = smap.resolution
    center = r.uv * res if center_texel is None else mi.Point2f(center_texel)
    half = mi.Point2f(half_size)
    ns, nt = mi.UInt32(ns), mi.UInt32(nt)
    n_taps = ns * nt
    cell = mi.Point2f(2.0 * half.x / mi.Float(ns), 2.0 * half.y / mi.Float(nt))
    lo = center - half
    face = mi.UInt32(r.face)
    rng = lane_rng(u_seed)
    k = mi.UInt32(0)
    n_lit = mi.UInt32(0)
    active = mi.Bool(active)
    b0, b1 = (0.0, 0.0) if bias_range is None else (float(bias_range[0]), float(bias_range[1]))

    def cond(k, rng, n_lit):
        return active & (k < n_taps)

    def body(k, rng, n_lit):
        xi = mi.Point2f(rng.next_float32(), rng.next_float32())
        if sampling == "jitter":
            col = k % ns
            row = k // ns
            xy = lo + mi.Point2f(mi.Float(col) + xi.x, mi.Float(row) + xi.y) * cell
        elif sampling == "uniform":
            xy = lo + xi * (2.0 * half)
        else:
            z = dr.erfinv((2.0 * xi - 1.0) * _ERF_SQRT2) * math.sqrt(2.0)   # in [-2, 2]
            xy = center + z * (0.5 * half)
        bias = 0.0
        if bias_range is not None:
            bias = b0 + rng.next_float32() * (b1 - b0) if b1 > b0 else b0
        lit = tap_lit(smap, r, face, xy, plane, bias, active)
        n_lit = dr.select(lit, n_lit + 1, n_lit)
        return k + 1, rng, n_lit

    k, rng, n_lit = dr.while_loop((k, rng, n_lit), cond, body)
    return mi.Float(n_lit) / mi.Float(dr.maximum(n_taps, 1))


# ------------------------------------------------ fixed texel blocks (W&M, MDSM)
def nearest_block(smap, lk: Lookup, opts, default_samples: int, active=True):
    """The receiver and the block of the ``k = pcf_samples`` (default
    ``default_samples``) nearest texels that second_depth and mdsm filter.

    Returns ``(r, active, k, side, i0)``: the :class:`Receiver`, ``active``
    restricted to points inside the map, the tap count, the block side
    ``sqrt(k)`` and the block's first texel (:func:`block_origin`).
    """
    k = opts.pcf_samples or default_samples
    side = math.isqrt(k)
    r = receiver(smap, lk, opts)
    return r, mi.Bool(active) & r.inside, k, side, block_origin(r.uv, smap.resolution, side)


def block_origin(uv_light: mi.Point2f, res: int, side: int) -> mi.Point2i:
    """First texel ``(i0, j0)`` of the ``side x side`` texels whose centres are
    nearest ``uv_light`` (texel centres at ``(i + 0.5) / res``)."""
    return mi.Point2i(dr.floor(uv_light * res - 0.5 * side + 0.5))


def virtual_sample_depth(view, face, ij: mi.Point2i, res: int, p_world: mi.Point3f,
                         n_world: mi.Vector3f, max_tan: float):
    """Depth of the virtual sample at texel ``ij`` (Wang & Molnar 1994): where the
    ray through that texel's centre meets the plane through ``p_world`` with
    normal ``n_world``.

    Returns ``(depth, ok)``; ``ok`` is False where the plane is within
    ``atan(max_tan)`` of parallel to the ray (the paper's ``c_L -> 0``) or meets
    it behind the light. Used by ``second_depth`` and ``mdsm``.
    """
    uv = (mi.Point2f(ij) + 0.5) * (1.0 / res)
    o, d = view.ray_through(face, uv)
    c = dr.dot(n_world, d)
    cos_min = 1.0 / math.sqrt(1.0 + max_tan * max_tan)
    ok = dr.abs(c) >= cos_min
    t = dr.dot(n_world, p_world - o) / dr.select(ok, c, 1.0)
    ok &= dr.isfinite(t) & (t > 0)
    return t, ok


def taps_loop(k: int, body_fn, init, active):
    """Run ``body_fn(tap, *state) -> state`` for taps 0..k-1 in one ``dr.while_loop``."""
    tap = mi.UInt32(0)
    active = mi.Bool(active)

    def cond(tap, *state):
        return active & (tap < k)

    def body(tap, *state):
        return (tap + 1, *body_fn(tap, *state))

    out = dr.while_loop((tap, *init), cond, body)
    return out[1:]
