"""What two or more methods share: the lookup's inputs and the helpers written once.

(See :mod:`mi_shadowmap.filters` for the call shape.) Helpers used by one
method live in that method's module.

* :class:`Lookup`, :class:`Receiver`, :func:`receiver` (every map method);
  :class:`RayTracedLight` (the methods that read no map);
* :func:`shifted_grid_point` (the integrator's light samples, PCSS taps);
* the receiver plane and the percentage-closer tap (``pcf``, ``bilinear``,
  ``pcss``), the pixel footprint in texels (``pcf``, the prefiltered methods);
* the k-texel blocks and virtual samples (``second_depth``, ``mdsm``).

Depth comparisons happen in the map's depth space (world distance from the
light, see :mod:`mi_shadowmap.light_views`): a receiver at biased depth
``z_r`` is lit by a texel of depth ``z_map`` when ``z_r <= z_map``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

from ..light_views.base import texel_sample_uv


@dataclass
class Lookup:
    """Inputs shared by every lookup at a batch of shading points.

    In a gradient render with the integrator's ``gradient_at='pixel_centre'`` (the
    default) a lookup runs twice: for the value at the sample's point (gradients
    suspended) and for the derivative at its pixel's centre. The second run's
    ``sampler`` gives ``next_1d``/``next_2d`` numbers of the pixel (a stream seeded
    by the film pixel and the emitter: the same for every sample and seed of that
    pixel, so random taps add no spread over seeds; with a camera other than
    ``perspective`` it replays the first run's numbers, and a lookup must then draw
    the same way in both runs). Either way a lookup draws them outside symbolic
    loops (``dr.while_loop`` bodies); other sampler attributes are the real
    sampler's.

    ``centre`` is True in that second run only: its value is not used, and its
    derivative stands for the pixel's average derivative. A lookup whose kernel is
    narrower than the pixel's footprint (``dp_dx``, ``dp_dy``) may widen it there to
    the pixel's (``bilinear`` does), or the derivative at the centre aliases against
    the texel grid."""
    p_world: mi.Point3f
    n_world: mi.Vector3f          # geometric normal (any orientation)
    dp_dx: mi.Vector3f            # pixel footprint on the surface (world)
    dp_dy: mi.Vector3f
    si: object                    # mi.SurfaceInteraction3f (for spawning rays)
    ds: object                    # mi.DirectionSample3f of the light sample
    sampler: object
    centre: bool = False          # the pixel-centre derivative run (see above)
    #: the emitter shaded (its Python object, called directly), or None where unknown; a
    #: lookup that needs the light calls this, never ``ds.emitter``: a call through the
    #: sample's emitter pointer traces every live emitter of the process, and one on a
    #: shape without position sampling (a curve's, in any scene) raises there
    emitter: object = None
    #: ``mi.Bool``: where the hit's BSDF tilts its shading frame per point (Mitsuba's
    #: ``normalmap``, ``bumpmap``, nested anywhere), so that whether it reflects light
    #: from a direction is not the same over a hemisphere of the shading frame (it is
    #: zero below the tilted frame's horizon too); a lookup that tests the horizon of
    #: several light points must then evaluate the BSDF for each. None: nowhere.
    tilted: object = None
    #: ``mi.Bool``: where the hit is on the outside of a solid (a closed, outward mesh
    #: part) that occludes light arriving from behind its geometric face -- Mitsuba's
    #: shadow ray leaves the face on the light's side, inside the solid -- which a smooth
    #: shading frame reflects near the terminator. The integrator gives light samples
    #: behind the face (``dot(n_world, d) < 0``) visibility 0 there; a ``whole_light``
    #: lookup must count its light points behind the face as occluded itself. None:
    #: nowhere. For a lookup that is not ``whole_light`` the integrator computes it only
    #: where ``ds`` lies behind the geometric face (False elsewhere, where it decides
    #: nothing): such a lookup should not read it in front of the face.
    solid_back: object = None
    #: ``mi.UInt32``: the film pixel of the camera sample (``x + 65536 y`` in the crop;
    #: a ``perspective`` camera's, in the integrator's own render or nested in another
    #: integrator's whose sensor it knows), or None: unknown. A virtual map reads there
    #: whether its mark kept the receiver biases' level for that pixel
    #: (:meth:`~mi_shadowmap.virtual.VirtualShadowMap.keeps`).
    pixel: object = None
    #: ``mi.Point2f``: the 2D sample the integrator drew the light sample ``ds`` from
    #: (one point of a stratified grid over ``shadow_rays``), or None: unknown (a
    #: gradient render's ``pixel_centre`` runs, an environment's regions). A delta
    #: light's sample does not use it; ``raytraced`` draws a sized delta light's first
    #: point from it, so its shadow rays are stratified as the light samples are.
    u_light: object = None


@dataclass
class RayTracedLight:
    """The 'map' of the ray-traced reference: the scene itself, and the emitter shaded
    (None: unknown; it says whether its samples are at infinity)."""
    scene: mi.Scene
    emitter: object = None
    #: the scene's shadow-ray query (:func:`mi_shadowmap.rays.occlusion`), prepared here,
    #: outside the symbolic loops that call it
    occlusion: object = None
    #: the shading point's :func:`~mi_shadowmap.rays.surface_point`, computed once for all
    #: its light samples (None: per shadow ray)
    p_surface: object = None

    def __post_init__(self):
        if self.occlusion is None:
            from ..rays import occlusion
            self.occlusion = occlusion(self.scene)


@dataclass
class Receiver:
    """A shading point expressed in a light's map, biases applied."""
    face: mi.UInt32
    uv: mi.Point2f
    depth: mi.Float              # biased receiver depth (compare with z_map)
    inside: mi.Bool              # False: outside every face -> lit
    texel_world: mi.Float        # world width of a texel at the receiver
    tan_theta: mi.Float          # tan(angle between normal and light), clamped


#: The receiver depth's margin for rounding, relative to the depth (4-8 float32 ulps): a
#: plane facing the light has no slope bias, and without a normal offset (``multiview``'s
#: default, or ``normal_bias`` 0) its camera hits and the map's texels agree only up to
#: rounding (``tests/test_stability.py``'s box top under a sun straight down: 21 of 1024
#: pixels shadowed with no margin on one machine, 0 with a margin of 1e-6 units).
DEPTH_ULPS = 4.0 * 2.0 ** -23


#: Texels of normal offset a receiver with a slope bias gets at least where its slope
#: bias is clamped (``tan(theta) > max_tan_slope``), whatever ``normal_bias`` is: half a
#: texel's depth change there, the margin the clamp takes away. Without it a small or
#: zero ``normal_bias`` shadowed a plane 89.9 degrees from a sun (``multiview``'s
#: defaults 25 %, ``hard`` with ``normal_bias`` 0.01 27 %). (Without a slope bias, as
#: ``second_depth``'s defaults, nothing is clamped: an offset there moved grazing
#: lookups onto their neighbours' depths.)
GRAZING_OFFSET = 0.5


@dataclass(frozen=True)
class BiasReach:
    """The texel-scaled receiver biases of :func:`receiver` (texels), for what they hide:
    ``normal`` (``normal_bias``), ``slope`` (``slope_bias``), ``grazing`` (the normal
    offset where the slope bias is clamped) and ``max_tan`` (``max_tan_slope``); and
    ``edge``, the method's ``virtual_edge`` (texels; 0 without one): how far across the
    light's rays its compares may misplace an occluder's edge on the receiver."""
    normal: float
    slope: float
    grazing: float
    max_tan: float
    edge: float = 0.0

    @staticmethod
    def of(opts) -> "BiasReach | None":
        """The biases ``opts`` give :func:`receiver` and its method's ``virtual_edge``;
        None where neither scales with the texel (then nothing is lost that a finer level
        would keep)."""
        nb, sb = float(opts.normal_bias_texels), float(opts.slope_bias_texels)
        fn = getattr(getattr(opts, "record", None), "virtual_edge", None)
        edge = max(float(fn(opts)), 0.0) if fn is not None else 0.0
        if nb <= 0.0 and sb <= 0.0 and edge <= 0.0:
            return None
        return BiasReach(nb, sb, max(nb, GRAZING_OFFSET) if sb > 0 else nb,
                         float(opts.max_tan_slope), edge)

    def texels(self, cos_nl, sin_nl):
        """How far along the receiver (in texels of the lookup's level) the biases of
        :func:`receiver` may lose an occluder's shadow, where the light meets the
        receiver at ``cos_nl``, ``sin_nl`` (of the angle to its normal).

        The normal offset lifts the point ``normal cos(theta)`` texels off the surface
        (``grazing`` where ``tan(theta) > max_tan``): an occluder that low over the
        receiver is not seen. Its shadow falls ``tan(theta)`` times its height further
        along the receiver, away from the light: that many texels of receiver are wrongly
        lit behind it (``tan`` clamped at ``max_tan``, as the bias is). The slope bias,
        ``slope tan(theta)`` texels of depth along the light's ray, ``slope sin(theta)``
        more (``slope max_tan cos(theta)`` where clamped): an occluder's edge up to that
        height is not seen either, and its shadow is counted the same way. Where the
        slope bias is clamped, a slab overhanging the receiver by more than the offset
        (a ledge over a wall) is lost over the slope bias's ``slope max_tan`` texels of
        depth along the ray, ``slope max_tan sin(theta)`` texels along the receiver
        whatever ``tan(theta)``: the longer of the two counts. Without it the count
        shrank to the offset's ``grazing max_tan`` as the light grazed the receiver
        (10.2 texels on ``random_terrain_world(17)``'s tower wall, ``n . l`` = 0.0006,
        where the ledge's shadow was lost over 20), and ``hard`` lit the wall up to 4
        pixels under the ledge (0.40 % of the view falsely lit at 128^2, 0.14 % now:
        0-0.7 units under it, within ``REACH_PIXELS``; at 256^2 0.14 % -> 0).
        Their sum (the edge's count with ``tan`` clamped for the offset's share only,
        30 texels there) put ``pcf`` on ``random_terrain_world(0)`` at 256^2 at 8.50
        texels per film pixel, over issue 11's 8 (7.46 before); the slab's alone
        (``max(grazing, slope sin(theta)) max_tan``) was coarser than before near the
        clamp and lit terrain 26's tower wall (``n . l`` = 0.041: 16 pixels at 128^2).
        The constant ``bias`` (world units) is not counted: no level makes it smaller.

        ``edge`` texels across the light's rays are ``edge / cos(theta)`` texels along the
        receiver (``tan`` clamped at ``max_tan`` here too: a receiver the light grazes
        closer gets the level of ``max_tan``): a lookup whose compares place an
        occluder's edge within ``edge`` texels of the map (``second_depth``: the lit
        fraction of its virtual samples, Wang & Molnar 1994, sec. 3.2, crosses 1/2 within
        half a texel of it) moves that shadow's edge over as much of the receiver, and
        loses a lit gap between an occluder and the receiver narrower than that (the
        paper's under-sampling, sec. 5: "the only solution is to increase the size of the
        depth map"; this is how much larger where the light grazes)."""
        tan = sin_nl / dr.maximum(cos_nl, 1e-6)
        clamped = tan > self.max_tan
        tan_c = dr.minimum(tan, self.max_tan)
        height = dr.select(clamped, self.grazing + self.slope * self.max_tan * cos_nl,
                           self.normal * cos_nl + self.slope * sin_nl)
        r = height * tan_c
        # where clamped: a slab overhanging by more than the offset, lost over the slope
        # bias's depth along the receiver whatever tan(theta) (see above)
        r = dr.select(clamped, dr.maximum(r, self.slope * self.max_tan * sin_nl), r)
        if self.edge > 0.0:
            r += self.edge * dr.sqrt(1.0 + tan_c * tan_c)
        return r

    def height(self, cos_nl, sin_nl):
        """How high over the receiver (texels of the lookup's level, along its normal) an
        occluder may be and still be hidden by the biases (:meth:`texels`' ``height``):
        ``normal cos(theta) + slope sin(theta)``, ``grazing + slope max_tan cos(theta)``
        where ``tan(theta) > max_tan``."""
        clamped = sin_nl / dr.maximum(cos_nl, 1e-6) > self.max_tan
        return dr.select(clamped, self.grazing + self.slope * self.max_tan * cos_nl,
                         self.normal * cos_nl + self.slope * sin_nl)


def largest_normal_offset(opts) -> float:
    """The largest normal offset :func:`receiver` gives a point, in texels of its
    view's :meth:`~mi_shadowmap.light_views.LightView.texel_world_size` there: the
    full ``normal_bias`` where the slope bias is clamped, and with a slope bias at
    least :data:`GRAZING_OFFSET` texels (the margin the clamp takes away); elsewhere
    ``normal_bias`` times ``cos(theta)``, less."""
    nb = opts.normal_bias_texels
    return max(nb, GRAZING_OFFSET) if opts.slope_bias_texels > 0 else nb


def receiver(smap, lk: Lookup, opts, coordinate_margin: bool = True) -> Receiver:
    """Project a shading point into ``smap`` with the configured biases.

    * ``normal_bias`` (texels): the point is moved along its normal (turned
      towards the light) by ``normal_bias * cos(theta)`` texel widths before it
      is projected, and by the full ``normal_bias`` where ``tan(theta)`` exceeds
      ``max_tan_slope`` (see below);
    * ``slope_bias`` (texels): ``slope_bias * texel_width * tan(theta)`` is
      subtracted from the receiver depth, ``theta`` being the angle between
      the normal and the direction to the light (``tan`` clamped at
      ``max_tan_slope``);
    * ``bias`` (world units): subtracted from the receiver depth;
    * and :data:`DEPTH_ULPS` of the depth, and of the point's largest coordinate
      (``coordinate_margin``): float32 depths agree only up to rounding.
      ``second_depth`` leaves the coordinate out: its layer stores a surface that is its
      own second surface raised by 16 ulps of its coordinates already, and needs none
      against a solid's back face; with it a unit scene 1e6 from the origin (where 4
      ulps of the coordinates are 0.48 units) lost a band of every solid's shadow
      behind it: 6.6 / 4.3 % of a view misclassified against ``raytraced`` at the
      origin (spot_sphere_box / room_two_points), 2.1 / 1.6 % without (``hard``, which
      needs it, 1.8 / 1.3 %).

    The texel biases scale with the map's texel size, hence with the scene:
    the automatic default is scale-invariant.

    Why the normal offset is scaled by ``cos(theta)`` (a deviation from the usual
    normal offset, a constant distance or one that grows towards grazing light): an
    offset ``d`` along the normal moves the point ``d sin(theta)`` sideways in the
    light's view, and a sideways shift ``s`` in the light's view is ``s / cos(theta)``
    on the receiver, so the shadow edges falling on a surface the light grazes moved
    by ``d tan(theta)``: a half-texel offset at ``tan(theta) = 8.3`` (a thin post's
    side under a low sun) shifted a neighbour's shadow on it by 3 pixels. Scaled, the
    sideways shift is ``d sin(theta) cos(theta) <= d / 2`` and vanishes at grazing
    light, while on a plane the offset still adds a depth margin of ``d`` along the
    light ray to the slope bias's. Where the slope bias is clamped the full offset
    makes up for it (a plane's margin ``d / cos(theta)``), at least
    :data:`GRAZING_OFFSET` texels with a slope bias (at ``tan(theta) > 20``, by default:
    a receiver the light grazes). Measured against the
    unscaled offset (``benchmarks/RESULTS.md``, 2026-12-02): random large worlds at
    256^2 misclassify at most 0.40 % instead of 0.75 % (``hard``); on the repository's
    nine scenes at their own films 43 of 45 (scene, method) pairs of ``hard``, ``pcf``,
    ``pcss``, ``bilinear`` and ``mdsm`` misclassify as often or less (``pcf`` on
    cbox_area 1.76 -> 1.46 %), false shadow rising by at most 0.05 points.
    """
    view, res = smap.view, smap.resolution
    p = lk.p_world
    w_light = view.direction_to_light(p)
    cos_nl = dr.dot(lk.n_world, w_light)
    n_towards = dr.select(cos_nl < 0, -lk.n_world, lk.n_world)
    cos_nl = dr.clip(dr.abs(cos_nl), 1e-6, 1.0)
    sin_nl = dr.safe_sqrt(1.0 - cos_nl * cos_nl)
    tan_theta = dr.minimum(sin_nl / cos_nl, opts.max_tan_slope)
    # p: cascaded maps; the normal: the width along its depth gradient on stretched faces
    texel = view.texel_world_size(res, view.depth_of(p), p, lk.n_world)
    clamped = sin_nl > opts.max_tan_slope * cos_nl
    nb = opts.normal_bias_texels
    full = largest_normal_offset(opts)
    if full > 0:
        # times cos(theta) elsewhere (see above)
        scale = dr.select(clamped, full, nb * cos_nl)
        p = p + n_towards * (texel * scale)
    face, uv, depth, inside = view.project(p)
    # the margin for rounding: of the depth, and of the receiver's own world position
    # (a camera hit far from the origin but near the light: see DEPTH_ULPS)
    p0 = dr.detach(mi.Point3f(lk.p_world))
    scale = dr.maximum(dr.abs(depth), dr.max(dr.abs(p0))) if coordinate_margin \
        else dr.abs(depth)
    z = depth - opts.bias_world - opts.slope_bias_texels * texel * tan_theta \
        - DEPTH_ULPS * scale
    return Receiver(face, uv, z, inside, texel, tan_theta)


def shifted_grid_point(k, n: int, shift: mi.Point2f) -> mi.Point2f:
    """Point ``k`` (int or ``mi.UInt32``) of ``n`` on a stratified grid in
    [0, 1)^2, toroidally shifted by ``shift``.

    The grid has ``cols = ceil(sqrt(n))`` columns and ``ceil(n / cols)`` rows
    of cell centres. With ``shift`` uniform in [0, 1)^2 (one per camera
    sample) every point is uniformly distributed, so averages over the
    pattern are unbiased for any ``n``, while the points stay stratified.
    Used for the integrator's light samples and PCSS's ``'stratified'`` taps.
    """
    cols = math.ceil(math.sqrt(n))
    rows = math.ceil(n / cols)
    u = mi.Point2f((mi.Float(k % cols) + 0.5) / cols, (mi.Float(k // cols) + 0.5) / rows) + shift
    return u - dr.floor(u)


# ------------------------------------------------------- receiver-plane depth
#: Virtual samples (a receiver's tangent plane, ``second_depth``) are unusable only where
#: ``tan`` of the angle between the plane's normal and the texel's ray exceeds this (the
#: plane within 1e-4 rad of the ray).
PARALLEL_TAN = 1e4


def concavity(lk: Lookup, to_light) -> mi.Float:
    """How fast the receiver bends towards the light (1 / world units): the largest
    normal curvature of the shading normal (``si.dn_du``, ``si.dn_dv`` against
    ``si.dp_du``, ``si.dp_dv``) with which the surface rises off its tangent plane on
    the light's side, 0 where it only falls away from it. The inside of a sphere of
    radius r lit from within: 1 / r; its outside, a plane, a flat-shaded mesh, or no
    surface interaction: 0. Only the rise puts the surface in front of its tangent plane
    as the light sees it, i.e. virtual samples behind it."""
    si = lk.si
    if si is None or not hasattr(si, "dn_du"):
        return mi.Float(0.0)
    toward = dr.select(dr.dot(si.sh_frame.n, to_light) >= 0, 1.0, -1.0)
    # dot(dn, dp) / |dp|^2 > 0: the normal turns outwards, the surface falls away from it
    ku = dr.dot(si.dn_du, si.dp_du) / dr.maximum(dr.squared_norm(si.dp_du), 1e-30)
    kv = dr.dot(si.dn_dv, si.dp_dv) / dr.maximum(dr.squared_norm(si.dp_dv), 1e-30)
    k = dr.detach(dr.maximum(dr.maximum(-toward * ku, -toward * kv), 0.0))
    return dr.select(dr.isfinite(k), k, 0.0)


def bend_along_ray(kappa, qp, d, n) -> mi.Float:
    """How far back along the unit ray ``d`` (pointing away from the light) from the
    point ``p + qp`` of the tangent plane (normal ``n``, ``qp`` in the plane) the ray
    meets the osculating sphere of curvature ``kappa`` that touches the plane at ``p``
    on the light's side: the allowance a virtual sample's compare makes for a surface
    that rises towards the light. With ``c = |n . d|``, ``D = |qp|`` and
    ``B = c + kappa (d . qp)`` that is ``kappa D^2 / (B + sqrt(B^2 - kappa^2 D^2))``,
    ``kappa D^2 / (2c)`` to first order (the ray along the normal). The slant term
    ``kappa (d . qp)`` matters where the ray runs towards the shading point (going
    back from the plane it moves away from ``p``, where the sphere has bent further):
    without it a light 0.1 off the centre of a sphere of radius 0.3 had texels 0.017
    wide fall short by ~1e-6, past the compare's tolerance, and shadowed the shell.
    Where the ray does not meet the sphere (``B`` <= 0, ``c`` <= ``kappa D``; a tap as
    far off as the radius times ``c``) the first-order ``kappa D^2 / (2c)``; 0 where
    ``kappa`` is 0."""
    c = dr.maximum(dr.abs(dr.dot(n, d)), 1.0 / PARALLEL_TAN)
    kd2 = kappa * dr.squared_norm(qp)
    b = c + kappa * dr.dot(d, qp)
    disc = dr.maximum(b * b - kappa * kd2, 0.0)
    exact = kd2 / dr.maximum(b + dr.safe_sqrt(disc), 1e-30)
    return dr.select(b > 0, exact, 0.5 * kd2 / c)


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
    #: the receiver's curvature towards the light (:func:`concavity`), for methods
    #: with ``needs_curvature``; None: the plane itself
    kappa: object = None
    #: where the plane's depth along a texel's ray is nearer than the clamp allows
    #: (``depth0 - lateral max_tan``), :func:`plane_depth_at` returns NaN instead of the
    #: clamped depth, and the caller compares that tap otherwise (``pcf``, ``bilinear``,
    #: ``pcss``: with the receiver's own texel, :func:`own_texel`); False: the clamped
    #: depth
    near_fallback: bool = False


def receiver_plane(smap, lk: Lookup, r: Receiver, opts, light_front: bool = False,
                   near_fallback: bool = False) -> ReceiverPlane:
    """The receiver's tangent plane; with ``light_front`` and a planar one-sided
    area light (``view.light_normal``), texels whose ray leaves the
    light's centre behind its emitting plane can neither block nor shadow
    (:func:`plane_depth_at` returns -inf for them). ``near_fallback``: see
    :attr:`ReceiverPlane.near_fallback`."""
    depth0 = smap.view.depth_of(lk.p_world)
    front = smap.view.light_normal if light_front else None
    kappa = None
    record = getattr(opts, "record", None)
    if record is not None and record.needs_curvature:
        kappa = concavity(lk, smap.view.direction_to_light(lk.p_world))
    return ReceiverPlane(lk.p_world, lk.n_world, depth0, depth0 - r.depth, opts.max_tan_slope,
                         front, kappa, near_fallback)


def plane_depth_at(smap, plane: ReceiverPlane, face, uv_light: mi.Point2f, lateral_world):
    """Biased receiver depth to compare with the texel at ``uv_light``.

    The depth where the texel's ray meets the tangent plane, clamped to
    ``depth0 +- lateral_world * max_tan_slope`` (``lateral_world``: the tap's
    distance from the receiver, in world units at the receiver), so that
    grazing planes stay finite; minus ``plane.offset``. A ray from a point light
    (:attr:`~mi_shadowmap.light_views.base.LightView.rays_from_point`) that meets the
    plane behind the light never reaches it: the plane says nothing there, and the tap
    is compared with the receiver's own depth (PCSS's plain compare). (It came out
    negative: a receiver a light grazes, 0.15 above the ground and 5 away, read every
    tap ray pointing above the ground's horizon, blockers included, as lit; PCSS's
    search regions reach there on virtual maps, whose texels follow the pixel: 14 % of
    such a scene's pixels lit in the umbrae of a sphere light. Reading the plane as
    infinitely far there made walls behind the receiver blockers.)

    The clamp's near side (``depth0 - lateral max_tan``) compares a tap with a point
    behind the plane, so a surface behind the plane can shadow it: ``pcf``'s kernel, a
    texel wide (``min_size``), read a grazed wall's own roof in the texels of the
    wall's line in the map (``n . l`` < 0.05; 273 of a lit tower wall's 470 pixels
    below 0.9, ``random_terrain_world(17)`` at 128^2; of the view's lit pixels,
    ``hard`` 33 below 0.9, ``bilinear``'s 2x2 footprint 307, ``pcss`` under a sun 0.53
    degrees wide 471). With ``plane.near_fallback`` (``pcf``, ``bilinear``, ``pcss``;
    not the smooth compare) such a tap gets NaN, and the caller compares it otherwise
    (the receiver's own texel, :func:`own_texel`); a texel behind a one-sided light
    keeps -inf. Not the plane's
    own depth there: a tap a texel across such a line stands for the plane
    ``tan(theta)`` texels away, and answered for the plane past a contact shadow's end
    (a block beside a tower under a sun 3 degrees high, ``random_terrain_world(15)``:
    0.24 -> 0.49 % misclassified at 128^2). The far side keeps its clamp, which keeps
    concave corners (the ground at a wall's foot) lit: unclamped, a grazed tower's
    view misclassified 12.0 % instead of 0.09 % (``benchmarks/RESULTS.md``, forty-second
    and forty-fifth sessions).
    """
    t_hit, _ = smap.view.ray_plane(face, uv_light, plane.p_world, plane.n_world, 1e-12)
    lim = lateral_world * plane.max_tan
    t = dr.clip(t_hit, plane.depth0 - lim, plane.depth0 + lim)
    near = t_hit < plane.depth0 - lim if plane.near_fallback else None
    if smap.view.rays_from_point:        # the plane behind the light along this ray
        t = dr.select(t_hit + smap.view.depth_origin > 0.0, t, plane.depth0)
        if near is not None:
            near &= t_hit + smap.view.depth_origin > 0.0
    if plane.light_front is not None:   # behind a one-sided light: cannot occlude it
        d = smap.view.ray_through(face, uv_light)[1]
        front = dr.dot(d, mi.Vector3f(*plane.light_front)) > 0
        t = dr.select(front, t, -dr.inf)
        if near is not None:            # -inf wins: neither blocker nor shadowing tap
            near &= front
    if plane.kappa is not None:
        # a receiver that rises towards the light (concave as the light sees it) lies in
        # front of its tangent plane by the plane's bend along the ray
        # (bend_along_ray): without it a kernel as wide as the pixel (pcf)
        # shadowed a frosted bulb's shell lit from inside, 57 % of its light at 256^2
        o, d = smap.view.ray_through(face, uv_light)
        n = dr.normalize(mi.Vector3f(plane.n_world))
        bend = bend_along_ray(plane.kappa, o + d * t_hit - mi.Point3f(plane.p_world), d, n)
        t = dr.select((plane.kappa > 0) & dr.isfinite(bend), t - bend, t)
    if near is not None:
        return dr.select(near, dr.nan, t - plane.offset)
    return t - plane.offset


# ------------------------------------------------------------------ PCF taps
# Helpers shared by the percentage-closer filters (Reeves 1987 ``pcf``, the
# fixed-footprint ``bilinear`` of Brabec & Seidel, PCSS): taps are addressed
# by *continuous texel coordinates* ``xy_texel = uv_light * resolution`` on a
# face (texel ``(i, j)`` covers ``[i, i+1) x [j, j+1)``, centre at ``+0.5``).


def footprint_texels(smap, lk: Lookup, r: Receiver, equal_variance: bool = False) -> mi.Point2f:
    """Width in texels, per map axis, of the camera pixel's footprint.

    The pixel's footprint on the surface is the parallelogram
    ``p +- dp_dx/2 +- dp_dy/2`` (``lk.dp_dx``/``dp_dy``: one whole pixel, from
    ray differentials, see the integrator); its corners are projected onto the
    receiver's face and the axis-aligned bounding box of the result is
    returned as full widths ``(w_s, w_t)`` (Reeves' ``2*sres``, ``2*tres`` in
    texels). ``equal_variance``: instead, the width of the box with the same
    variance as the projected parallelogram, ``sqrt(e1^2 + e2^2)`` of its edges'
    components (the same for an axis-aligned footprint; for a turned one narrower
    than the bounding box: at 45 degrees the side, not the diagonal). Non-finite
    widths (grazing views, no differentials) become 0 and widths are capped at the
    map resolution.
    """
    view, res = smap.view, smap.resolution
    uv0 = view.uv_on_face(r.face, lk.p_world)
    du_x = view.uv_on_face(r.face, lk.p_world + lk.dp_dx) - uv0
    du_y = view.uv_on_face(r.face, lk.p_world + lk.dp_dy) - uv0
    if equal_variance:
        e1, e2 = du_x * res, du_y * res
        w = dr.sqrt(e1 * e1 + e2 * e2)
    else:
        w = (dr.abs(du_x) + dr.abs(du_y)) * res
    w = mi.Point2f(dr.select(dr.isfinite(w.x), w.x, 0.0), dr.select(dr.isfinite(w.y), w.y, 0.0))
    return dr.minimum(w, mi.Float(res))   # res: per lane on virtual maps


def taps_cross_seams(smap, cross_seams: bool = True) -> bool:
    """Whether a tap on ``smap`` off its face continues on the neighbouring face (a
    cube map's seam): ``cross_seams`` (the filter's wish) unless the map's view says
    its taps cannot cross (``view.taps_cross_seams`` False: a virtual cube map's
    :class:`~mi_shadowmap.light_views.local.LocalView`, whose taps are clamped to their
    face's border texel). Full maps cross. Every tap helper here asks it, so a user
    method's taps get the same answer.

    A clamped tap reads the border texel: an occluder seen only across the seam
    within the kernel is missed, a partial error bounded by the share of taps beyond
    the edge; where the neighbouring face's pages are not built (the marks build a
    point's own face) a crossing tap read the coarsest level, a wider error
    (``benchmarks/RESULTS.md``, fifty-third session, helper E)."""
    return bool(cross_seams) and getattr(smap.view, "taps_cross_seams", True)


def tap_depths(smap, r: Receiver, face, xy_texel: mi.Point2f,
               plane: ReceiverPlane | None = None, active=True, cross_seams: bool = True,
               lateral_texels=None):
    """The one tap helper of every percentage-closer filter (pcf, bilinear, pcss).

    Returns ``(z_map, z_receiver, inside)`` for a tap at continuous texel
    coordinates ``xy_texel`` of ``face``: ``z_map`` is the depth of the texel
    it hits (the view's :meth:`~mi_shadowmap.light_views.LightView.tap_texel`: off a
    perspective/orthographic map
    ``inside`` is False -- such a tap is lit and blocks nothing; cube taps
    continue on the neighbouring face, or with ``cross_seams`` False or on a map
    whose taps cannot cross (:func:`taps_cross_seams`: virtual maps) are
    clamped to the face); ``z_receiver`` is ``r.depth`` (biases applied) or,
    with ``plane``, the receiver plane's depth along that texel's ray through
    its centre (:func:`plane_depth_at`, same biases, clamped by the tap's
    lateral distance from the receiver: ``lateral_texels``, default the
    texel centre's distance). On a virtual map a tap whose page is not built reads
    the coarsest level, whose texel holds the depth along its own ray: it is compared
    with the nearer of the plane's depths at the tap's texel and at that ray's point.
    """
    f2, i, j, inside = smap.view.tap_texel(face, xy_texel, smap.resolution,
                                           taps_cross_seams(smap, cross_seams))
    centre = None
    if plane is not None and hasattr(smap, "fetch_centre"):
        # a virtual map: a tap whose page is not built reads the coarsest level, whose
        # texel (2^k of this level's wide) holds the depth along its own centre's ray;
        # the plane through the tap's texel put an open wall in false shadow along
        # cube seams and page borders (pcf, 64^2, lod_bias -4: 2105 of 4096 pixels)
        z_map, centre = smap.fetch_centre(smap.depth, f2, i, j, active & inside)
    else:
        z_map = smap.fetch(smap.depth, f2, i, j, active & inside)
    if plane is not None:
        res = smap.resolution
        uv_c = texel_sample_uv(mi.Point2f(i, j), res)
        if lateral_texels is None:
            lateral_texels = dr.norm(dr.floor(xy_texel) + 0.5 - r.uv * res)
        z = plane_depth_at(smap, plane, f2, uv_c, lateral_texels * r.texel_world)
        if centre is not None:
            # the nearer of the plane's depths at the tap and where the read texel's ray
            # crossed it: an open wall is lit, and so is a concave corner the plane at the
            # coarse texel's point alone put in shadow
            zc = plane_depth_at(smap, plane, f2, centre * (1.0 / res),
                                lateral_texels * r.texel_world)
            if plane.near_fallback:     # either beyond the near clamp: the nearer is
                z = dr.select(dr.isnan(zc), zc, dr.select(dr.isnan(z), z, dr.select(
                    dr.isfinite(zc), dr.minimum(z, zc), z)))
            else:
                z = dr.select(dr.isfinite(zc), dr.minimum(z, zc), z)
    else:
        z = r.depth
    return z_map, z, inside


def plane_z_at(smap, plane: ReceiverPlane | None, r: Receiver, lateral_texels=None,
               offset=0.0):
    """``z_at`` for :func:`soft_tap` / :func:`soft_blocker`: the receiver depth
    :func:`tap_depths` would compare texel ``(face, i, j)`` with (the receiver plane's
    depth through its centre, minus ``offset``), so a moving or smooth tap's
    neighbours are each compared with their own plane depth. ``lateral_texels``: the
    clamp's lateral distance (default: the texel centre's distance from the
    receiver, as :func:`tap_depths`). None without a plane."""
    if plane is None:
        return None
    res = smap.resolution

    def z_at(face, i, j):
        centre = mi.Point2f(i, j) + 0.5
        lateral = (dr.norm(centre - r.uv * res) if lateral_texels is None
                   else dr.detach(lateral_texels))
        return plane_depth_at(smap, plane, face, centre * (1.0 / res),
                              lateral * r.texel_world) - offset
    return z_at


def own_texel(smap, r: Receiver, face, active=True):
    """``(z_map, inside)`` of the receiver's own texel (the nearest to ``r.uv``): what
    a tap beyond a :attr:`ReceiverPlane.near_fallback` plane's near clamp (its plane
    depth NaN) is compared with, ``r.depth`` against it (:func:`tap_lit`'s ``own``)."""
    z_own, _, in_own = tap_depths(smap, r, face, r.uv * smap.resolution, None, active)
    return z_own, in_own


def tap_lit(smap, r: Receiver, face, xy_texel: mi.Point2f, plane: ReceiverPlane | None = None,
            extra_bias=0.0, active=True, own=None) -> mi.Bool:
    """One percentage-closer comparison (:func:`tap_depths`): lit when the tap is
    off the map or ``z_receiver - extra_bias <= z_map`` (``extra_bias``: e.g.
    Reeves' stochastic bias). ``own`` (:func:`own_texel`, with a ``near_fallback``
    plane): a tap whose plane depth is NaN (beyond the near clamp) takes the receiver's
    own texel's compare, ``r.depth - extra_bias`` against it."""
    z_map, z, inside = tap_depths(smap, r, face, xy_texel, plane, active)
    lit = ~inside | (z - extra_bias <= z_map)
    if own is None:
        return lit
    return dr.select(dr.isnan(z), ~own[1] | (r.depth - extra_bias <= own[0]), lit)


def soft_compare_width(r: Receiver, soft_compare: float):
    """World depth width of the smooth compare (:func:`soft_tap_lit`):
    ``soft_compare * r.texel_world``, the world width of one map texel at the
    receiver (the unit of ``slope_bias`` and ``normal_bias``), so it scales with
    the map and the scene. Detached: the width is a filter setting, not a
    quantity to differentiate. None for ``soft_compare <= 0`` (the step)."""
    if soft_compare <= 0.0:
        return None
    return dr.detach(dr.maximum(soft_compare * r.texel_world, 1e-30))


def soft_tap_lit(z_map, z, inside, width) -> mi.Float:
    """Smooth percentage-closer comparison (issue 13, ``soft_compare``): lit
    fraction ``smoothstep(1 + (z_map - z) / width)`` (``smoothstep(x) = 3x^2 -
    2x^3`` on ``[0, 1]``, clamped), i.e. 1 where ``z <= z_map`` as in
    :func:`tap_lit`, 0 where the map is nearer than the receiver by ``width`` or
    more, a C1 ramp in between. One-sided on purpose: every tap today's step
    calls lit stays fully lit (no new acne), only occluders within ``width`` of
    the receiver are softened, and its derivative reaches both ``z_map`` and
    the receiver depth ``z``. Off-map taps, empty texels (``+inf``) and
    receivers at ``-inf`` keep the step's answer (no derivative)."""
    d = z_map - z
    ok = inside & dr.isfinite(d)
    x = dr.clip(1.0 + dr.select(ok, d, 0.0) / width, 0.0, 1.0)
    step = dr.select(~inside | (z <= z_map), 1.0, 0.0)
    return dr.select(ok, x * x * (3.0 - 2.0 * x), step)


def soft_tap(smap, z_map, z, inside, width, face, xy_texel, active=True,
             cross_seams: bool = True, z_at=None, smooth: bool = False) -> mi.Float:
    """:func:`soft_tap_lit` of one tap, on any map. On a silhouette-antialiased map
    (``smap.coverage``, :mod:`mi_shadowmap.antialias`) the tap's texel is a mix of
    its own surface and its neighbours' (weights ``alpha_s``), and the lit
    fraction is mixed the same way: ``lit(own) + sum_s alpha_s (lit(z_s) -
    lit(own))`` -- the compares are blended, not the depths, so the result is
    linear in the coverage (an outline moving by ``dx`` texels changes the
    lit fraction by ``dx`` times the compare step, as the shadow's area does).
    ``z_at(face, i, j)``: the receiver depth to compare texel ``(i, j)`` with in the
    moving tap's derivative (a receiver plane's depth there); None: ``z``.
    ``smooth`` (gradient renders of ``pcf`` and ``pcss``): the tap's whole derivative,
    the map's included, is the bilinear interpolation's of its four texels, so it is
    continuous in the receiver's position; the value stays the nearest texel's.
    (Measured, ``pcf`` with regular taps and ``gradient_at='pixel_centre'``: the
    nearest texel's derivative sampled at the pixels' centres aliased against the
    texel grid, 12 % off the mean; 2 % with this.)"""
    moving = dr.grad_enabled(xy_texel) or smooth
    if getattr(smap, "coverage", None) is None and not moving:
        return soft_tap_lit(z_map, z, inside, width)
    res = smap.resolution
    f2, i, j, _ = smap.view.tap_texel(face, dr.detach(xy_texel) if smooth else xy_texel, res,
                                      taps_cross_seams(smap, cross_seams))
    lit = _covered_tap(smap, f2, i, j, z, inside, width, active)
    if not moving:
        return lit
    # The light's pose moves the tap across the texels (xy_texel carries its
    # derivatives): the nearest texel's value, the bilinear interpolation's
    # derivative (each neighbour on the tap's face, clamped at its edges).
    # A tap that crossed a cube seam lies on another face, whose texels are not the
    # neighbours of its coordinates: it keeps its nearest texel's derivative.
    crossed = f2 != mi.UInt32(face)
    bil = mi.Float(0.0)
    for w, ii, jj in _bilinear_texels(xy_texel, res):
        z_n = z if z_at is None else z_at(f2, ii, jj)
        c = _covered_tap(smap, f2, ii, jj, z_n, inside, width, active & ~crossed)
        bil += w * (c if smooth else dr.detach(c))
    if smooth:   # the derivative of the bilinear interpolation, in the map too
        return dr.replace_grad(lit, dr.select(crossed, lit, bil))
    return dr.replace_grad(lit, lit + dr.select(crossed, 0.0, bil - dr.detach(bil)))


def smooth_taps(smap, soft_width) -> bool:
    """``soft_tap``'s ``smooth``: smooth compares in a gradient render (the map in the
    AD graph), where each tap's derivative is its four texels' bilinear one."""
    return soft_width is not None and dr.grad_enabled(getattr(smap, "depth", None))


def soft_blocker(smap, z_map, z, inside, width, face, xy_texel, active=True,
                 cross_seams: bool = True, z_at=None):
    """A blocker-search tap with smooth, coverage-blended compares (PCSS step 1 with
    ``soft_compare``): ``(weight, weight * depth)`` with ``weight = 1 -``
    :func:`soft_tap_lit`, the tap's degree of being a blocker. On an antialiased map
    (``smap.coverage``) the texel's own surface and its neighbours' are weighted by
    their coverage, each with its *own* depth: a silhouette texel enters the blocker
    average with the occluder's depth and a weight that grows from 0 with the
    coverage, not (as the blended ``smap.depth``) with a depth that slides from the
    receiver's to the occluder's. A tap that moves (the search region follows the
    occluder's depth) is differentiated through its bilinear neighbours, as
    :func:`soft_tap`. Both sums are then continuous in the occluder's motion, so
    their derivatives match finite differences (issue 13)."""
    moving = dr.grad_enabled(xy_texel)
    if getattr(smap, "coverage", None) is None and not moving:
        return _blocker_weight(z_map, z, inside, width)
    res = smap.resolution
    f2, i, j, _ = smap.view.tap_texel(face, dr.detach(xy_texel), res,
                                      taps_cross_seams(smap, cross_seams))
    b, bz = _covered_blocker(smap, f2, i, j, z, inside, width, active)
    if not moving:
        return b, bz
    bil_b, bil_bz = mi.Float(0.0), mi.Float(0.0)
    for w, ii, jj in _bilinear_texels(xy_texel, res):
        z_n = z if z_at is None else z_at(f2, ii, jj)
        nb, nbz = _covered_blocker(smap, f2, ii, jj, z_n, inside, width, active)
        bil_b += w * dr.detach(nb)
        bil_bz += w * dr.detach(nbz)
    return (dr.replace_grad(b, b + bil_b - dr.detach(bil_b)),
            dr.replace_grad(bz, bz + bil_bz - dr.detach(bil_bz)))


def _blocker_weight(z_k, z, inside, width):
    """``(b, b * z_k)``, ``b = 1 -`` :func:`soft_tap_lit` (0 for an empty texel)."""
    b = 1.0 - soft_tap_lit(z_k, z, inside, width)
    return b, b * dr.select(b > 0, z_k, 0.0)


def _covered_blocker(smap, f2, i, j, z, inside, width, active):
    """:func:`_blocker_weight` at texel ``(f2, i, j)``, coverage-blended on an
    antialiased map (each surface with its own depth)."""
    return _coverage_mix(smap, f2, i, j, active & inside,
                         lambda z_k: _blocker_weight(z_k, z, inside, width))


def _covered_tap(smap, f2, i, j, z, inside, width, active):
    """The smooth compare at texel ``(f2, i, j)``, coverage-blended on an antialiased map."""
    return _coverage_mix(smap, f2, i, j, active & inside,
                         lambda z_k: (soft_tap_lit(z_k, z, inside, width),))[0]


def _coverage_mix(smap, f2, i, j, ok, fn) -> tuple:
    """``fn(z)`` (a tuple of values) at texel ``(f2, i, j)``: of its depth, or on an
    antialiased map (``smap.coverage``) of its own surface's depth mixed with its
    neighbours' by their coverage, ``v + sum_s alpha_s (v_s - v)``."""
    if getattr(smap, "coverage", None) is None:
        return fn(smap.fetch(smap.depth, f2, i, j, ok))
    from ..antialias import STEPS
    res = smap.resolution
    own = fn(smap.fetch(smap.raw_depth, f2, i, j, ok))
    out = list(own)
    k = mi.UInt32(f2) * (res * res) + mi.UInt32(dr.clip(j, 0, res - 1)) * res \
        + mi.UInt32(dr.clip(i, 0, res - 1))
    for s, (di, dj) in enumerate(STEPS):
        alpha = dr.gather(mi.Float, smap.coverage, 4 * k + s, ok)
        near = fn(smap.fetch(smap.raw_depth, f2, i + di, j + dj, ok & (alpha > 0)))
        out = [dr.select(alpha > 0, o + alpha * (v_n - v), o)
               for o, v, v_n in zip(out, own, near)]
    return tuple(out)


def _bilinear_texels(xy_texel, res: int):
    """The four texels around the continuous tap ``xy_texel`` (clamped to the face)
    and their bilinear weights, attached to ``xy_texel``: ``[(w, i, j)]``."""
    xy = mi.Point2f(xy_texel)
    fx = xy.x - 0.5 - dr.floor(dr.detach(xy.x) - 0.5)
    fy = xy.y - 0.5 - dr.floor(dr.detach(xy.y) - 0.5)
    i0 = mi.Int32(dr.floor(dr.detach(xy.x) - 0.5))
    j0 = mi.Int32(dr.floor(dr.detach(xy.y) - 0.5))
    return [((fx if di else 1.0 - fx) * (fy if dj else 1.0 - fy),
             dr.clip(i0 + di, 0, res - 1), dr.clip(j0 + dj, 0, res - 1))
            for dj in (0, 1) for di in (0, 1)]


# ------------------------------------------------ fixed texel blocks (W&M, MDSM)
def nearest_block(smap, lk: Lookup, opts, active=True, coordinate_margin: bool = True):
    """The receiver (``coordinate_margin``: see :func:`receiver`) and the block of the
    ``k = pcf_samples`` nearest texels that second_depth and mdsm filter.

    Returns ``(r, active, k, side, i0)``: the :class:`Receiver`, ``active``
    restricted to points inside the map, the tap count, the block side
    ``sqrt(k)`` and the block's first texel (:func:`block_origin`).
    """
    k = opts.pcf_samples
    side = math.isqrt(k)
    r = receiver(smap, lk, opts, coordinate_margin)
    return r, mi.Bool(active) & r.inside, k, side, block_origin(r.uv, smap.resolution, side)


def block_origin(uv_light: mi.Point2f, res: int, side: int) -> mi.Point2i:
    """First texel ``(i0, j0)`` of the ``side x side`` texels whose centres are
    nearest ``uv_light`` (texel centres at ``(i + 0.5) / res``)."""
    return mi.Point2i(dr.floor(uv_light * res - 0.5 * side + 0.5))


def virtual_sample_depth(view, face, ij: mi.Point2i, res: int, p_world: mi.Point3f,
                         n_world: mi.Vector3f, max_tan: float):
    """Depth of the virtual sample at texel ``ij`` (Wang & Molnar 1994): where the
    texel's own ray (through its centre moved by ``base.TEXEL_SAMPLE``, as the map
    was built) meets the plane through ``p_world`` with normal ``n_world``.

    Returns ``(depth, ok)``; ``ok`` is False where the plane is within
    ``atan(max_tan)`` of parallel to the ray (the paper's ``c_L -> 0``) or meets
    it behind the light. Used by ``second_depth`` and ``mdsm``.
    """
    uv = texel_sample_uv(ij, res)
    cos_min = 1.0 / math.sqrt(1.0 + max_tan * max_tan)
    t, c = view.ray_plane(face, uv, p_world, n_world, cos_min)
    ok = dr.abs(c) >= cos_min
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


# ------------------------------------------- prefiltered moments (vsm, evsm, msm)
#: Narrowest depth span a full map is normalised over (:func:`normalized_depth`), relative
#: to its largest depth: 16 times :data:`DEPTH_ULPS`, so that a map whose depths are all
#: equal up to float32 rounding (a sun straight down on a flat ground) does not stretch
#: that rounding over the whole normalised range, while any span a scene's surfaces have
#: (a unit scene under a spot 1e5 away: a span of 1e-5 of the depth) is kept.
MIN_SPAN = 16.0 * DEPTH_ULPS


def normalized_depth(smap):
    """``(z, d_lo, scale)``: a full map's depths normalised over the map's own finite
    depth span, ``z = (depth - d_lo) scale`` per texel (``mi.Float64``), with ``d_lo``,
    ``d_hi`` its smallest and largest finite depths and ``scale = 1 / (2 (d_hi -
    d_lo))``: ``[d_lo, d_hi]`` maps to ``[0, 1/2]``, the convention of virtual maps
    (:func:`virtual_depth_scale`). Empty texels (``+inf``: nothing along the ray) become
    1, i.e. "far behind every receiver", so they filter as unoccluded. Shared by the
    prefiltered methods, whose moments (z, z^2, exp(c z), ...) need bounded depths, and
    whose ``min_variance`` / ``moment_bias`` are in these units: relative to the depths
    the map holds, whatever the light's distance (dividing by twice the largest depth
    instead put ``sigma_min`` at 6 world units for a spot 1e4 away over an 8-unit
    scene, and every shadow was lost).

    The span is at least :data:`MIN_SPAN` of the largest depth (a map whose depths are
    all equal); an empty map gets ``d_lo = 0``, ``scale = 1/2``. A receiver is
    normalised the same way (:func:`span_of`); one nearer than ``d_lo`` gets ``z < 0``,
    in front of every texel. In a map attached to the AD graph ``d_lo`` and ``d_hi``
    carry the mean derivative of the texels at that depth (:func:`_extreme`)."""
    depth = texel_depths(smap)
    finite = dr.isfinite(depth)
    d = mi.Float64(depth)
    d_lo = _extreme(d, finite, lowest=True)
    d_hi = _extreme(d, finite, lowest=False)
    empty = ~(d_lo <= d_hi)
    d_lo = dr.select(empty, 0.0, d_lo)
    d_hi = dr.select(empty, 1.0, d_hi)
    floor = dr.maximum(MIN_SPAN * dr.maximum(dr.abs(d_lo), dr.abs(d_hi)), 2.0 ** -100)
    scale = 0.5 / dr.maximum(d_hi - d_lo, floor)
    return dr.select(finite, (d - d_lo) * scale, 1.0), d_lo, scale


def _extreme(d, finite, lowest: bool):
    """The smallest (``lowest``) or largest finite value of ``d`` (one lane); attached to
    the AD graph, its derivative is the mean of the texels holding that value (Dr.Jit's
    ``min`` / ``max`` reductions hand every tied texel the whole derivative: an occluder
    of 128 texels facing the light moved the span 128 times over, and ``msm``'s
    derivative came out -15 against +4.5 by finite differences)."""
    inf = dr.inf if lowest else -dr.inf
    v = dr.detach(d)
    ext = dr.min(dr.select(finite, v, inf)) if lowest else dr.max(dr.select(finite, v, inf))
    if not dr.grad_enabled(d):
        return ext
    at = finite & (v == ext)
    mean = dr.sum(dr.select(at, d, 0.0)) / dr.maximum(dr.sum(dr.select(at, 1.0, 0.0)), 1.0)
    return dr.replace_grad(ext, mean)


def span_layer(smap) -> mi.Float64:
    """The layer a full map's prefiltered method keeps its normalisation in: two values,
    ``(d_lo, scale)`` of :func:`normalized_depth` (``mi.Float64``)."""
    _, d_lo, scale = normalized_depth(smap)
    out = dr.zeros(mi.Float64, 2)
    dr.scatter(out, d_lo, mi.UInt32(0))
    dr.scatter(out, scale, mi.UInt32(1))
    return out


def span_of(layer, width) -> tuple:
    """``(d_lo, scale)`` (``mi.Float64``, ``width`` lanes) from a :func:`span_layer`:
    a receiver's depth normalises as ``(depth - d_lo) scale``."""
    zero = dr.zeros(mi.UInt32, width)
    return dr.gather(mi.Float64, layer, zero), dr.gather(mi.Float64, layer, zero + 1)


def texel_depths(smap):
    """The map's depths before silhouette antialiasing (``smap.depth`` when the map
    is not antialiased, :mod:`mi_shadowmap.antialias`)."""
    return smap.raw_depth if getattr(smap, "raw_depth", None) is not None else smap.depth


def antialiased(smap, values):
    """Per-texel ``values`` (e.g. a moment of the depth) blended across the map's
    silhouettes (:func:`mi_shadowmap.antialias.blend`); unchanged when the map is
    not antialiased. Prefiltered methods blend each moment, not the depth."""
    if getattr(smap, "coverage", None) is None:
        return values
    from ..antialias import blend
    return blend(values, smap.coverage, smap.view.n_faces, smap.resolution)


def prefilter_box(smap, lk: Lookup, r: Receiver, filter_size):
    """``(lo, hi)``: the filter box of a prefiltered lookup, in continuous texel
    coordinates of the receiver's face, centred on the receiver.

    Its width per axis is the camera pixel's footprint (:func:`footprint_texels`)
    or ``filter_size`` texels, whichever is larger, so a lookup filters what
    the pixel covers and never less than ``filter_size``; with a summed-area
    table (:func:`~mi_shadowmap.depth_maps.box_mean`) the cost is O(1) whatever
    the width.
    """
    width = dr.maximum(footprint_texels(smap, lk, r), filter_size)
    centre = r.uv * smap.resolution
    return centre - 0.5 * width, centre + 0.5 * width


#: Largest side, in texels, of a filter box summed texel by texel
#: (:func:`box_means_of_depths`); wider boxes are narrowed about their centre.
MAX_DIRECT_BOX = 64


def has_layers(smap, names) -> bool:
    """Whether the map carries the layers ``names``: full maps build a method's layers;
    virtual maps build none derived from the whole face (``mdsm``'s extremes, the
    prefiltered methods' tables), whose lookups compute them from the depths instead."""
    return all(name in smap.extra for name in names)


def virtual_depth_scale(smap):
    """``(d_lo, scale)`` (``mi.Float64``, per lane): how the prefiltered methods
    normalise the depths of a map without their layers (virtual maps), ``z = (depth -
    d_lo) scale`` with ``scale = 1 / (2 (d_hi - d_lo))``: the scene's depth span as the
    light sees it (:attr:`mi_shadowmap.virtual.VirtualLayout.depth_range`) maps to
    ``[0, 1/2]``, as a full map's own finite depth span does (:func:`normalized_depth`).
    The span does not grow with the light's distance, so ``min_variance`` stays relative
    to the scene's depths for a light far away (twice the largest depth instead would put
    ``sigma_min`` at 60 units for a light 1e5 away), and it does not change as camera
    moves build pages."""
    b = getattr(smap, "depth_bounds", None)
    if b is None:
        raise ValueError(f"shadowmap: the map of emitter '{smap.view.label}' has neither the "
                         "prefiltered method's layers (a full map builds them through "
                         "methods.get(name).layers) nor a virtual map's depth bounds")
    zero = dr.zeros(mi.UInt32, 1)
    d_lo, d_hi = dr.gather(mi.Float64, b, zero), dr.gather(mi.Float64, b, zero + 1)
    return d_lo, 0.5 / (d_hi - d_lo)


#: A virtual map's variance floors are those of a full map with this many texels across
#: twice the scene's depth span (a 1024^2 map across the span), per texel of the
#: lookup's level (:func:`virtual_variance_factor`).
FLOOR_TEXELS = 2048.0


def virtual_variance_factor(r: Receiver, scale):
    """Factor on a prefiltered method's variance floor (``min_variance``, in normalised
    depth squared) for a virtual map normalised with ``scale``
    (:func:`virtual_depth_scale`): ``min(1, FLOOR_TEXELS texel_world scale)^2``. The
    floor ``sqrt(min_variance)`` of normalised depth is then at most the one a full map
    of :data:`FLOOR_TEXELS` texels across the normalised range would have per texel:
    the same as a 1024^2 full map's where the level is that coarse, and proportionally
    smaller on finer levels, so a scene whose depth span is far larger than the shadows
    it casts (a light 1e5 away over a wide ground) keeps them."""
    f = dr.minimum(mi.Float64(FLOOR_TEXELS) * mi.Float64(r.texel_world) * scale, 1.0)
    return f * f


def narrow_to_face(smap, r: Receiver, lo: mi.Point2f, hi: mi.Point2f,
                   min_half: float = 0.5) -> tuple:
    """``(lo, hi)`` narrowed symmetrically about the receiver's projection so that the
    box stays on the receiver's face (keeping at least ``min_half`` texels on each side
    of the receiver, then clipped to the face).

    A box clipped to the face on one side only is not centred on the receiver: on a
    receiver inclined to the light its mean depth is then nearer (or farther) than the
    receiver's own, and a prefiltered method's Chebyshev bound shadows an unoccluded
    plane along every cube-face seam (``vsm``: 384 of 4096 pixels of an open wall under a
    point light below 0.99 with 1024^2 maps, lines that widened as ``resolution`` grew).
    The mean of a plane over a box symmetric about the receiver is the receiver's depth.
    """
    centre = r.uv * smap.resolution
    f_lo, f_hi = face_rect(smap)         # [0, res] on a full map
    border = dr.maximum(dr.minimum(centre - f_lo, f_hi - centre), min_half)
    half = dr.minimum(0.5 * (hi - lo), border)
    return dr.clip(centre - half, f_lo, f_hi), dr.clip(centre + half, f_lo, f_hi)


def face_rect(smap) -> tuple:
    """``(lo, hi)``: the receiver's face in the continuous texel coordinates the map's
    view gives (``[0, res]`` on a full map; shifted by the lookup's origin on a bound
    virtual map), from ``smap.clamp_texel``."""
    big = mi.Point2i(1 << 30)
    return mi.Point2f(smap.clamp_texel(-big)), mi.Point2f(smap.clamp_texel(big)) + 1.0


def box_means_of_depths(smap, face, lo: mi.Point2f, hi: mi.Point2f, per_texel,
                        n_values: int, active=True) -> tuple:
    """Means over the box ``[lo, hi]`` (continuous texel coordinates of ``face`` as the
    map's view gives them) of ``per_texel(depth)`` (a tuple of ``n_values``
    ``mi.Float64``), each
    texel counted by its covered fraction: the value :func:`~mi_shadowmap.depth_maps.box_mean`
    reads from a summed-area table, computed by visiting the box's texels (one
    ``dr.while_loop``, as many iterations as the box covers texels in each lane). For
    maps without the tables (virtual maps, whose page set grows with the camera).

    The box is clipped to the face (as ``box_mean`` clips it) and made at least
    ``1e-3`` texels wide; a box wider than :data:`MAX_DIRECT_BOX` texels is narrowed to
    that about its centre. Texels are read through ``smap.fetch``.
    """
    f_lo, f_hi = face_rect(smap)
    wide = (hi - lo) > MAX_DIRECT_BOX
    centre = 0.5 * (lo + hi)
    lo = dr.clip(dr.select(wide, centre - 0.5 * MAX_DIRECT_BOX, lo), f_lo, f_hi)
    hi = dr.clip(dr.select(wide, centre + 0.5 * MAX_DIRECT_BOX, hi), f_lo, f_hi)
    hi = dr.maximum(hi, dr.minimum(lo + 1e-3, f_hi))
    lo = dr.minimum(lo, hi - 1e-3)
    i0 = mi.Point2i(dr.floor(lo))
    n = dr.maximum(mi.Point2i(dr.ceil(hi)) - i0, 1)
    count = mi.UInt32(n.x * n.y)
    active = mi.Bool(active)
    Float64 = mi.Float64
    lo64, hi64 = mi.Point2d(lo), mi.Point2d(hi)
    tap = mi.UInt32(0)
    sums = tuple(dr.zeros(Float64, dr.width(count)) for _ in range(n_values))

    def cond(tap, *sums):
        return active & (tap < count)

    def body(tap, *sums):
        dj = mi.Int32(tap) // n.x
        di = mi.Int32(tap) - dj * n.x
        i, j = i0.x + di, i0.y + dj
        # covered fractions in float64: exact (float32 would round 1 - 0.13)
        wx = dr.minimum(hi64.x, Float64(i + 1)) - dr.maximum(lo64.x, Float64(i))
        wy = dr.minimum(hi64.y, Float64(j + 1)) - dr.maximum(lo64.y, Float64(j))
        w = wx * wy
        z = smap.fetch(smap.depth, face, i, j, active)
        vals = per_texel(z)
        return (tap + 1,) + tuple(s + w * v for s, v in zip(sums, vals))

    # a sum: reverse-mode differentiates it in place (the integrator's SYMBOLIC_BACKWARD)
    state = dr.while_loop((tap,) + sums, cond, body, max_iterations=-1)
    area = Float64(hi.x - lo.x) * Float64(hi.y - lo.y)
    return tuple(s / area for s in state[1:]), count
