"""``multiview``: accumulated multi-view shadow maps, after Heckbert & Herf (1997).

The soft-shadow literature's reference ("the average of 1024 hard shadows",
Guennebaud et al. 2006): a soft shadow is the fraction of the light's points
that see the receiver. The map manager builds, through the record's
``view_for`` hook, one :class:`~mi_shadowmap.light_views.multi.MultiView` per
emitter: ``views`` (K) depth maps rendered from K stratified, fixed points of
the light (area lights: the emitter's own position sampling -- by area, or through
the texture's importance sampling for a textured radiance, as Mitsuba samples it;
point and spot lights: a sphere / square of side ``light_size``; directional lights:
K directions inside ``angular_diameter``), all in one tensor, built in one pass
of ray queries and cached like every map. Each view covers what it must: cube
maps, one perspective face per view for a planar light whose scene fits a
frustum, the spot's cone, or the scene's bounds (directional). A light without
extent (``light_size`` / ``angular_diameter`` 0) keeps its ordinary map: one
view, i.e. ``hard``.

**The lookup.** Each camera sample looks up ``lookups`` of the K views
(``0`` or ``>= K``: all of them) in one ``dr.while_loop`` -- one kernel for any
K. With fewer than K, a per-camera-sample Cranley--Patterson shift ``s`` in
[0, 1) selects views ``floor((j + s) K / lookups)``, ``j < lookups``: one per
run of ``K / lookups`` consecutive views, and the views are ordered along a
Hilbert curve over the light
(:func:`~mi_shadowmap.light_views.multi.stratified_points`), so every camera
sample sees a stratified subset and the fixed light points give noise instead
of banding; every view is chosen with probability ``lookups / K``, so the
average (the visibility AOV) is unbiased for the K-view one. A sphere light sampled
in its cone (``MultiView.cone``) instead draws its ``lookups`` points in that cone, as
Mitsuba draws its light samples, each testing the view of its point's stratum
(:meth:`~mi_shadowmap.light_views.multi.MultiView.cone_view`; ``_cone_subset``). The light sample's
weight, ``visible / above``, is the subset's ratio; where the subset holds no
point above the receiver's horizon (or none facing it) while the light sample is
above the horizon, uniformly drawn views are tested until one is (at most K),
whose visibility is an unbiased estimate of it (rejection sampling). Each lookup is
a ``hard`` nearest-texel test or (``filter='bilinear'``) a 2x2 bilinear PCF
with receiver-plane depths (``bilinear`` with ``kernel=2``), with the usual
receiver biases of that view; their defaults differ from ``hard``'s
(``normal_bias`` 0, ``slope_bias`` 2: see the record). With ``hard``'s biases,
a light without extent is bit-identical to ``hard``.

**Visibility** is defined exactly as by the converged reference
(:mod:`mi_shadowmap.reference`): a light point is lit where it emits towards the
receiver (front side of an area light, radiance > 0 there; the spot's cone, from
the emitter's own sample), lies above the receiver's horizon (the BSDF towards it is
not 0: evaluated once towards the light's centre, and again only for views on the
other side of the shading plane -- BSDFs are zero or not per hemisphere -- and for
every view where the BSDF tilts its frame per point, ``normalmap`` or ``bumpmap``,
whose horizon is not the shading plane's: ``Lookup.tilted``) and is not
occluded (a light point behind the geometric face of a solid's outside is, by the
solid itself, as Mitsuba's shadow ray is there: ``Lookup.solid_back``). The points are distributed as the reference's light samples are, and the
fraction is over the points those samples could be: all K for lights Mitsuba samples
by area or through their texture (a point on the back of a cube or a cylinder light,
or on a black square of a ``checkerboard`` radiance, which samples uniformly, counts as
shadowed, as a light sample drawn there does; a ``bitmap`` radiance puts its points
only on its bright texels, as many as their share of its brightness), the emitting
ones for a uniform sphere, which Mitsuba samples uniformly in the cone it subtends
(:attr:`~mi_shadowmap.light_views.multi.MultiView.count_all`) -- each of them counted
for the solid angle it stands for, ``cos(theta) / d^2`` at the receiver
(:attr:`~mi_shadowmap.light_views.multi.MultiView.cone`; an unweighted average over
the sphere's facing cap over-weights its rim). The
lookup returns ``(visible, above)``, the fractions of those points that are lit and
that are above the horizon (the record's ``whole_light``), and with ``lookups`` < K
a third value, the light sample's weight (an estimate of ``visible / above``, see
above): the integrator reports ``visible`` as the AOV at every shaded point, and
weights its one light sample's radiance by ``visible / above`` (or that weight). (A one-sample AOV would be
``above``-probability noise where the light straddles the horizon, and could
not converge to the reference there.)

It converges to the reference as K grows (up to the maps' resolution and
biases); K, the resolution and ``lookups`` trade speed for accuracy. Memory:
K x (faces of one view) x resolution^2 texels, which the planner checks
against ``memory_budget``; the automatic resolution is lowered so that all K
views fit (see the README). Built: all of them but, under a one-sided planar
area light seen through cube maps, the texels behind its plane, which no lookup
reads (it tests a view only where its point emits towards the receiver; the
margin is the lookup's reach, ``_views``): the face looking behind it and half
of each side face, about half the texels
(:meth:`~mi_shadowmap.light_views.multi.MultiView.built_texels`).
"""
from __future__ import annotations

import dataclasses
import math

import drjit as dr
import mitsuba as mi
import numpy as np

from ..variants import bsdf_eval_reaches, unpolarized
from ..light_views.multi import as_multi_view, multi_view, stratified_points
from ..methods import Method, Prop
from .common import Lookup, largest_normal_offset, receiver, receiver_plane, tap_lit
from .hard import hard


def bilinear2(smap, lk: Lookup, opts, active=True) -> mi.Float:
    """2x2 bilinear percentage-closer test (``bilinear`` with ``kernel=2`` and
    ``receiver_plane``): the four texels around the receiver, compared with its
    tangent plane's depth along each texel's ray, weighted bilinearly.

    A receiver that rises off its tangent plane towards the light (concave as the light
    sees it: a frosted bulb's shell or a room lit from inside) lies in front of that
    plane by the plane's bend, which no bias here covers: ``normal_bias`` defaults to 0
    (see the record) and the slope bias vanishes where the light is along the normal.
    So each tap's plane depth is lowered by that bend along its ray (the record's
    ``needs_curvature`` gives :func:`~.common.receiver_plane` the receiver's curvature,
    :func:`~.common.plane_depth_at` applies second_depth's
    :func:`~.common.bend_along_ray`; 0 on planes and convex receivers). Without
    it a point light at the centre of a rough-glass sphere (radius 0.3) shadowed its
    whole shell: a 64^2 image 0.019 against ``raytraced``'s 0.392."""
    res = smap.resolution
    r = receiver(smap, lk, opts)
    plane = receiver_plane(smap, lk, r, opts)
    a = r.uv * res - 0.5
    i0 = dr.floor(a)
    f = a - i0
    act = mi.Bool(active) & r.inside
    face = mi.UInt32(r.face)
    vis = mi.Float(0.0)
    for dx, dy in ((0, 0), (1, 0), (0, 1), (1, 1)):
        w = (f.x if dx else 1.0 - f.x) * (f.y if dy else 1.0 - f.y)
        lit = tap_lit(smap, r, face, i0 + mi.Point2f(dx + 0.5, dy + 0.5), plane, 0.0, act)
        vis += dr.select(lit, w, 0.0)
    return dr.select(r.inside, dr.clip(vis, 0.0, 1.0), 1.0)


_TESTS = {"hard": hard, "bilinear": bilinear2}


def multiview(smap, lk: Lookup, opts, active=True):
    """Accumulated multi-view visibility; see the module docstring.

    Returns ``(visible, above)`` (``mi.Float`` each): over the looked-up light
    points (all of them, or those that emit towards the shading point: ``count_all``),
    the fraction that is above its horizon and unoccluded, and the fraction that is
    above its horizon (both 0 where no point emits towards it); a sphere's points are
    weighted by their solid angle (``MultiView.cone``). With ``lookups`` < K, a third
    value: the light sample's weight, ``visible / above`` of the subset or, where the
    subset has no point above the horizon, of views drawn until one is.
    """
    view = as_multi_view(smap.view)
    K = view.n_views
    L = K if opts.lookups == 0 else min(int(opts.lookups), K)
    act = mi.Bool(active)
    si = lk.si
    p = lk.p_world
    bsdf = si.bsdf()
    ctx = mi.BSDFContext()
    test = _TESTS[opts.filter]
    # Delta lights (point, spot, directional): whether the emitter itself lights p
    # (the spot's cone), from its own sample; area lights: per point, emits_towards.
    # The emitter shaded (lk.emitter), called directly: through the sample's pointer
    # (lk.ds.emitter) the call traced every live emitter of the process, and an area
    # light on a curve anywhere (Shape::sample_position not implemented) raised here.
    # Where the light's weight tracks gradients, the views are looked up wherever the
    # light sample is valid, whatever the weight's value (a point light of intensity
    # exactly 0 has weight 0 everywhere, and gating by it cut the derivative wrt the
    # intensity to 0: 0 against 14.2 at intensity 1, and an area light's: 4.1); the
    # visibility AOV (``visible``, ``above``) still counts only where the weight is
    # non-zero.
    emitter = lk.emitter
    emitting = mi.Bool(True)
    tracked = view.dark     # an area light of radiance 0 that tracks gradients
    if emitter is not None and mi.has_flag(emitter.flags(), mi.EmitterFlags.Delta):
        ds0, w0 = emitter.sample_direction(si, mi.Point2f(0.5, 0.5), act)
        emitting = (ds0.pdf > 0) & (dr.max(unpolarized(w0)) > 0)
        tracked = tracked or dr.grad_enabled(w0)
        act &= (ds0.pdf > 0) if tracked else emitting
    if view.dark:
        emitting = mi.Bool(False)
    cone_subset = L < K and view.cone and bool(view.sphere)
    if cone_subset:
        shift2 = lk.sampler.next_2d(act)
        shift = shift2.x
    else:
        shift = lk.sampler.next_1d(act) if L < K else mi.Float(0.0)
    subset_shift = shift    # the retry's seed below (``shift`` is rebound for a sphere's
    #                         fallback loop, whose body reads it)
    step = K / L
    # The horizon test: the BSDF towards the light's centre, evaluated once; a view on
    # the same side of the shading plane gets the same answer (BSDFs are zero or not per
    # hemisphere), only views across it evaluate the BSDF themselves.
    wo_c = si.to_local(smap.view.direction_to_light(p))
    # An environment region (one view) is no light point: the environment's shading
    # tests the horizon of the direction it draws and of the region; its axis can lie
    # below a horizon most of the region is above (a floor under a sky lost 4 % of its
    # light when such regions read as shadowed).
    if getattr(smap.view, "caller_tests_horizon", False):
        above_c = mi.Bool(True)
    else:
        above_c = bsdf_eval_reaches(bsdf, ctx, si, wo_c, act)[1]
    side_c = mi.Frame3f.cos_theta(wo_c) > 0
    # a BSDF that tilts its frame per point (normalmap, bumpmap) is zero below the tilted
    # frame's horizon too: every view evaluates it there (lk.tilted)
    tilted = mi.Bool(False) if lk.tilted is None else mi.Bool(lk.tilted)
    # the outside of a solid whose light points behind the hit's geometric face are
    # occluded by the solid itself (a smooth shading frame reflects them near the
    # terminator; Lookup.solid_back): such a view is above the horizon but not lit
    solid_back = None if lk.solid_back is None else mi.Bool(lk.solid_back)
    n_geo = dr.detach(mi.Vector3f(lk.n_world))

    def seen(above, d_world):
        """``above`` but for a light point in direction ``d_world`` behind a solid's face."""
        if solid_back is None:
            return above
        return above & ~(solid_back & (dr.dot(n_geo, d_world) < 0))

    def point(k):
        """View ``k``'s sub-map; whether its light point emits towards ``p``, whether it
        is above the horizon too, and whether it may be lit there (not behind a solid's
        face: ``seen``); its weight there (1, or its solid angle: ``cone``)."""
        sub = dataclasses.replace(smap, view=view.sub_view(k))
        emits = act & view.emits_towards(k, p)
        d = sub.view.direction_to_light(p)
        wo = si.to_local(d)
        across = emits & (((mi.Frame3f.cos_theta(wo) > 0) != side_c) | tilted)
        above = emits & dr.select(across, bsdf_eval_reaches(bsdf, ctx, si, wo, across)[1],
                                  above_c)
        w = dr.select(emits, view.weight(k, p), 0.0) if view.cone else mi.Float(1.0)
        return sub, emits, above, seen(above, d), w

    if cone_subset:
        visible, above, ratio = _cone_subset(view, smap, lk, opts, act, L, shift2, test, si,
                                             bsdf, ctx, above_c, side_c, tilted, seen)
        if tracked:   # the weight is the geometric one; the AOV counts emitting lanes only
            return dr.select(emitting, visible, 0.0), dr.select(emitting, above, 0.0), ratio
        return visible, above, ratio

    def cond(j, n_emit, n_above, n_lit):
        return act & (j < L)

    def body(j, n_emit, n_above, n_lit):
        k = dr.minimum(mi.UInt32(dr.floor((mi.Float(j) + shift) * step)), K - 1)
        sub, emits, above, lit, w = point(k)
        vis = dr.select(lit, test(sub, lk, opts, lit), 0.0)
        if not view.cone:
            return (j + 1, dr.select(emits, n_emit + 1.0, n_emit),
                    dr.select(above, n_above + 1.0, n_above), n_lit + vis)
        # a sphere sampled in its cone: each point counts for its solid angle
        return (j + 1, n_emit + w, dr.select(above, n_above + w, n_above), n_lit + w * vis)

    z = mi.Float(0.0)
    _, n_emit, n_above, n_lit = dr.while_loop((mi.UInt32(0), z, z, z), cond, body)
    if L < K and not view.count_all:
        # A subset of a sphere light's views none of which emits towards the point (all
        # on the sphere's far side) says nothing about its visibility, and read 0: those
        # lanes look all K views up (sphere light, K=256, unoccluded ground: 0.966 with
        # lookups=4, 0.437 with 1; images 4 % and 41 % too dark against direct).
        act_all = act & (n_emit <= 0)
        step = 1.0
        shift = mi.Float(0.0)

        def cond_all(j, n_emit, n_above, n_lit):
            return act_all & (j < K)

        _, n_emit, n_above, n_lit = dr.while_loop((mi.UInt32(0), n_emit, n_above, n_lit),
                                                  cond_all, body)
    # the reference's denominator: every point looked up for a light sampled by area
    # (or by its texture), the emitting ones -- weighted by their solid angle -- for a
    # sphere sampled in its cone (see MultiView.count_all, MultiView.cone)
    total = mi.Float(L) if view.count_all else n_emit
    if view.cone:
        inv = dr.select(n_emit > 0, dr.rcp(total), 0.0)
    else:
        inv = dr.select(n_emit > 0, dr.rcp(dr.maximum(total, 1.0)), 0.0)
    if L >= K:
        if tracked:   # the weight is the geometric one; the AOV counts emitting lanes only
            return (dr.select(emitting, n_lit * inv, 0.0), dr.select(emitting, n_above * inv, 0.0),
                    dr.select(n_above > 0, n_lit / dr.maximum(n_above, 1e-30), 0.0))
        return n_lit * inv, n_above * inv
    # The light sample's weight, visible / above: where the subset holds no point above
    # the horizon (a cube light's far faces, a light straddling the receiver's horizon)
    # it says nothing about it, and read 0 -- a cube light over a ground, 256 views:
    # images 0.908 of direct at lookups=1 and 0.972 at 4 (1.005 with all views). There,
    # where the light sample itself is above the horizon (elsewhere the weight is not
    # used), uniformly drawn views (hashed from the shift: independent of the subset)
    # are tested until one is above the horizon, at most K: the first one's visibility
    # is then an unbiased estimate of visible / above (rejection sampling). The AOV
    # keeps the subset's unbiased estimate.
    ratio = dr.select(n_above > 0, n_lit / dr.maximum(n_above, 1e-30), 0.0)
    wo_s = si.to_local(lk.ds.d)
    sample_above = bsdf_eval_reaches(bsdf, ctx, si, wo_s, act)[1]
    retry = sample_above & (n_above <= 0)
    seed = dr.reinterpret_array(mi.UInt32, subset_shift)

    def cond_r(r, found, v):
        return retry & ~found & (r < K)

    def body_r(r, found, v):
        u = mi.sample_tea_float32(seed, r)
        k = dr.minimum(mi.UInt32(dr.floor(u * K)), K - 1)
        sub, _, above, lit, _ = point(k)
        vis = dr.select(lit, test(sub, lk, opts, lit), 0.0)
        return r + 1, found | above, dr.select(above, vis, v)

    _, found, v = dr.while_loop((mi.UInt32(0), mi.Bool(False), mi.Float(0.0)),
                                cond_r, body_r)
    ratio = dr.select(retry & found, v, ratio)
    if tracked:
        return dr.select(emitting, n_lit * inv, 0.0), dr.select(emitting, n_above * inv, 0.0), ratio
    return n_lit * inv, n_above * inv, ratio


def _cone_subset(view, smap, lk, opts, act, L, shift2, test, si, bsdf, ctx, above_c,
                 side_c, tilted, seen):
    """``lookups`` L < K on a sphere light sampled in its cone (``MultiView.cone``):
    ``(visible, above, weight)`` from L points drawn as Mitsuba draws the sphere's light
    samples -- uniformly in the cone it subtends from the receiver, at a stratified
    pattern of L points shifted per camera sample -- each testing the view of its
    stratum (``MultiView.cone_view``), so each counts 1 / L. A subset of the K views
    weighted by their solid angle (its ratio sum(w v) / sum(w)) was biased where few of
    its points face the receiver, their weights cancelling (a sphere of radius 0.3 at
    0.6 over a ground, K=256: the AOV +0.0125 at lookups=4, at 16 and 64 spp alike).
    The weight (visible / above) is the drawn points' ratio; where none is above the
    horizon but the light sample is, points drawn from a hash of the shift are tested
    until one is (rejection sampling, as for the other lights)."""
    p = lk.p_world
    base = stratified_points(L)
    base = mi.Point2f(mi.Float(base[:, 0].astype(np.float32)),
                      mi.Float(base[:, 1].astype(np.float32)))
    dr.make_opaque(base)
    _, _, outside = view.cone_view(p, mi.Point2f(0.5, 0.5))
    act = act & outside

    def draw(u, active):
        """The view of the point drawn at ``u``, whether it is above the horizon, and its
        hard shadow's visibility (0 below the horizon)."""
        k, d, _ = view.cone_view(p, u)
        sub = dataclasses.replace(smap, view=view.sub_view(k))
        wo = si.to_local(d)
        across = active & (((mi.Frame3f.cos_theta(wo) > 0) != side_c) | tilted)
        above = active & dr.select(across, bsdf_eval_reaches(bsdf, ctx, si, wo, across)[1],
                                   above_c)
        lit = seen(above, d)
        return above, dr.select(lit, test(sub, lk, opts, lit), 0.0)

    def cond(j, n_above, n_lit):
        return act & (j < L)

    def body(j, n_above, n_lit):
        u = dr.gather(mi.Point2f, base, j) + shift2
        u = u - dr.floor(u)
        above, vis = draw(dr.minimum(u, 0.99999994), act)
        return j + 1, dr.select(above, n_above + 1.0, n_above), n_lit + vis

    z = mi.Float(0.0)
    _, n_above, n_lit = dr.while_loop((mi.UInt32(0), z, z), cond, body)
    ratio = dr.select(n_above > 0, n_lit / dr.maximum(n_above, 1e-30), 0.0)
    sample_above = bsdf_eval_reaches(bsdf, ctx, si, si.to_local(lk.ds.d), act)[1]
    retry = sample_above & (n_above <= 0)
    seed = dr.reinterpret_array(mi.UInt32, shift2.x)
    K = view.n_views

    def cond_r(r, found, v):
        return retry & ~found & (r < K)

    def body_r(r, found, v):
        u = mi.sample_tea_float32(seed, 2 * r)
        w = mi.sample_tea_float32(seed, 2 * r + 1)
        above, vis = draw(mi.Point2f(u, w), retry & ~found)
        return r + 1, found | above, dr.select(above, vis, v)

    _, found, v = dr.while_loop((mi.UInt32(0), mi.Bool(False), z), cond_r, body_r)
    ratio = dr.select(retry & found, v, ratio)
    return n_lit / L, n_above / L, ratio


#: How far beyond the receiver's nearest texel each test's taps reach, in texels
#: (``bilinear2``: the 2x2 texel centres around it, within one texel on each axis).
_TAP_REACH = {"hard": 0.0, "bilinear": math.sqrt(2.0)}


def _views(view, emitter, scene, opts):
    """The record's ``view_for``: K views of the light in one map (None: no extent). A
    one-sided light's build skips the texels behind it, which no lookup here reads: the
    lookups' reach (``MultiView.lookup_reach``) is the normal offset of ``receiver`` and
    the test's taps."""
    return multi_view(view, emitter, scene, opts.views, opts.light_size, opts.angular_diameter,
                      lookup_reach=(largest_normal_offset(opts), _TAP_REACH[opts.filter]))


METHOD = Method(
    name="multiview",
    lookup=multiview,
    summary="Heckbert & Herf 1997 accumulated multi-view maps: K hard shadows from "
            "stratified light points, averaged (converges to the reference)",
    properties=(
        Prop("views", "int", 32,
             "multiview: number K of light points, each with its own depth map (all in one "
             "tensor: K x the faces of the light's ordinary map).", lo=1, hi=1024),
        Prop("lookups", "int", 0,
             "multiview: views looked up per camera sample, 0 (or >= views) = all K; fewer "
             "pick a stratified subset shifted per camera sample (noise instead of "
             "banding).", lo=0, hi=1024),
        Prop("filter", "str", "hard",
             "multiview: test of each view, 'hard' (nearest texel) or 'bilinear' (2x2 "
             "bilinear PCF with receiver-plane depths).", choices=("hard", "bilinear")),
        Prop("light_size", "float", None,
             "Point, spot and projector lights: light width in world units (point: a sphere "
             "of that diameter; spot, projector: a square across its axis). Default 0: "
             "one view (hard shadows). Area lights use their shape.", lo=0.0,
             lights=("point", "spot", "projector")),
        Prop("angular_diameter", "float", 0.0,
             "Apparent diameter of a directional light in degrees; > 0 spreads the views "
             "over that cone of directions (0: one view, hard shadows).", lo=0.0, hi=30.0,
             lights=("directional",)),
    ),
    # No normal offset: it moves every view's lookup the same way, a systematic shift of
    # the averaged penumbra that K views cannot average out; the depth-only slope bias
    # does not move edges, and one view's acne is averaged with K - 1 others. Measured
    # (512^2, 1 spp, visibility RMSE): cbox_area K=128 at 256^2 0.0071 -> 0.0058,
    # contact_hardening K=128 at 512^2 0.0107 -> 0.0084, the built-in area scene K=64 at
    # 512^2 0.0116 -> 0.0061 (normal_bias 0.5 / slope_bias 1 -> 0 / 2).
    bias_defaults={"normal_bias": 0.0, "slope_bias": 2.0},
    view_for=_views,
    view_properties=("views", "lookups"),
    whole_light=True,
    needs_curvature=True,      # filter='bilinear': the receiver plane's bend
    builtin=True,
)
