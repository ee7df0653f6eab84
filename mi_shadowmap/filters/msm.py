"""Moment shadow mapping: Peters & Klein, "Moment Shadow Mapping", I3D 2015
(``method="msm"``).

Filter first, compare second: every texel stores the first four powers of
its depth, ``b = (z, z^2, z^3, z^4)``; a lookup averages them over a filter
box (a linear filter commutes with the powers, so the averages are the first
four *moments* of the depth distribution under the box) and asks how much of
a distribution with these moments must lie in front of the receiver.

**Reconstruction** (the paper's "Hamburger 4MSM" algorithm; ``c = (c1, c2,
c3)`` as in the paper):

1. *Moment bias.* ``b' = (1 - a) b + a b*``: a small convex step (``a`` =
   ``moment_bias``) towards the moments ``b*`` of a fixed distribution, which
   makes the Hankel matrix ``B = [[1, b1, b2], [b1, b2, b3], [b2, b3, b4]]``
   positive definite (a box of one or two depths has a singular ``B``) and
   absorbs the rounding of the stored moments.
2. *Cholesky solve* of ``B c = (1, z_f, z_f^2)`` for the receiver depth
   ``z_f`` (``B = L D L^T`` written out for 3 x 3).
3. *Roots* ``z_2 <= z_3`` of ``c3 z^2 + c2 z + c1``: with ``z_f`` they are the
   support of the canonical three-atom representation of ``b'`` that puts
   an atom on the receiver.
4. *Shadow intensity* ``G`` = the weight of the atoms in front of the
   receiver, the sharpest lower bound on the occluded fraction over all
   distributions with these moments:

   * ``z_f <= z_2``: ``G = 0``;
   * ``z_2 < z_f <= z_3``: ``G = (z_f z_3 - b1 (z_f + z_3) + b2) /
     ((z_3 - z_2) (z_f - z_2))``;
   * ``z_3 < z_f``: ``G = 1 - (z_2 z_3 - b1 (z_2 + z_3) + b2) /
     ((z_f - z_2) (z_f - z_3))``.

   Visibility is ``1 - G``. For a box holding one or two distinct depths (an
   occluder's edge over a flat receiver) the four moments determine the
   distribution and ``G`` is the exact fraction in front of the receiver up
   to the bias, where Chebyshev's two-moment bound (VSM) leaks light
   (``tests/test_msm.py``).

**Filtering.** The box of :func:`~.common.prefilter_box`: the camera pixel's
footprint in the map (ray differentials), at least ``filter_size`` texels
wide per axis, centred on the receiver. The moments are box means of
summed-area tables (:func:`~mi_shadowmap.depth_maps.box_mean`: 16 gathers per
moment, O(1) whatever the width, partial texels weighted by their covered
fraction, so a 1-texel box is bilinear filtering). Points outside the map
are lit.

**Layers.** ``msm_b1`` .. ``msm_b4``: float64 summed-area tables (per face)
of ``u^k``, where ``u = 2 z - 1`` maps the normalised depth ``z = (depth -
d_lo) / (2 (d_hi - d_lo))`` of :func:`~.common.normalized_depth` (the map's
finite depths ``[d_lo, d_hi]`` to ``[0, 1/2]``; empty texels ``z = 1``) to
``[-1, 1]``; ``msm_span``: ``d_lo`` and ``1 / (2 (d_hi - d_lo))`` (two values),
with which the receiver depth is normalised. Built once per map by the map
manager, cached with it, read from ``smap.extra``.

**Defaults** (measured on every scene of ``scenes_xml/`` at 1024^2 maps and,
out of the repository, on the built-in scene with each light type seen from
another camera at 3x scale, the Cornell box with a point light, and 256^2
images on 256^2 / 512^2 maps, where the footprint is below a texel):

* ``filter_size = 1``: bilinear filtering of the moments, the paper's
  texture lookup. It matters only where the pixel footprint is smaller;
  there the visibility RMSE against ray tracing was lowest at 1 texel in 4
  of 6 cases (2 texels in the other two, by 2-4 %) and grew by up to 18 %
  at 3 texels and 41 % at 4 (a wider blur of hard shadows). (``vsm`` needs
  a wider minimum for its variance; MSM does not.)
* ``moment_bias = 1e-7``: the bias must dominate the rounding of the SAT
  box means (measured: at most 1.3e-11 at 1024^2, 2.1e-10 at 4096^2 and
  9e-10 at 8192^2, the largest map), and costs depth resolution ~
  ``sqrt(a)``. 1e-7 is the smallest power of ten at which the rounding moves
  ``G`` by less than 0.01 everywhere (max 0.004 at 8192^2, 6e-5 at 1024^2,
  20 000 random boxes of 1..16 texels on a map of curved surfaces and
  occluders; 0.03 at 1e-8). A receiver behind a single depth is then half
  shadowed 1.2e-4 of the map's depth span behind it (3.9e-4 at 1e-6,
  2.1e-3 at the paper's 3e-5; ``u`` units, in which the span is 1), and
  boxes of two depths are resolved far better (a receiver 0.01 behind depths
  0.1 apart: ``G`` = 0.81 against 0.44 at 1e-6, exact 1). Misclassification on the test scenes moved by at
  most 0.12 % between 1e-8 and 3e-5 (directional_mesh's visibility RMSE:
  0.060 at 1e-7, 0.063 at 1e-6, 0.067 at 3e-5).
* ``light_bleeding = 0``: at 0.1 the reduction lowered false lit (0.44 ->
  0.39 % on directional_mesh) and the visibility RMSE on 8 of 11 scenes (by
  up to 9 %), but raised false shadow more, so the misclassified fraction
  grew on 5 of 6 repository scenes; off by default.
* ``receiver_plane = true`` (see below): without it cbox_area misclassified
  3.9 % instead of 1.1 %, the Cornell box's visibility RMSE was 2.6 times
  higher, and 10 of 11 scenes misclassified more (the other: equal).
* The shared texel biases keep their defaults (``slope_bias`` 1,
  ``normal_bias`` 0.5). On virtual maps (``benchmarks/bench_prefiltered_bias.py``:
  9 repository scenes, 128^2, 16 spp, on the reference's camera samples,
  2026-12-06) ``vsm``'s halves give a mean misclassified of 0.52 % against
  0.55 % and false lit 0.17 % against 0.21 %; both at 0: 0.55 % / 0.13 %
  (more false shadow, e.g. on cbox_area; an earlier run on other camera
  samples: its false shadow 0.78 -> 1.18 %).

Deviations from the paper, and why:

* *Summed-area tables instead of a blurred, mip-mapped moment texture.* The
  paper renders the moments with MSAA, blurs them with a small fixed kernel
  and samples them with the texture unit. Here the box is the pixel's own
  footprint (or ``filter_size``), read in O(1) from SATs as Peters et al.
  do for moment soft shadows (JCGT 2017). A box is not a Gaussian: shadow
  edges are linear ramps over the footprint.
* *No optimised 16-bit quantisation.* The paper stores the moments in four
  16-bit channels (an optimised affine transform) and uses ``a = 3e-5`` to
  hide their rounding. Here the moments are float64 sums and the
  reconstruction runs in float64, so the default ``moment_bias`` is 300
  times smaller (see Defaults): sharper contact shadows, less leaking. A
  float32 reconstruction from the same moments was measured too: its ``G``
  differed from float64 by up to 0.99 at ``a <= 1e-7`` and 0.03 at 1e-6
  (0.0035 at 1e-5; 200 000 random boxes on a 1024^2 map), hence float64.
* *Depth in [-1, 1] and bias target.* The 2015 algorithm takes depth in
  ``[0, 1]`` and biases towards ``(0.5, 0.5, 0.5, 0.5)`` (atoms at 0 and 1,
  a singular ``B``); we use ``[-1, 1]`` and ``b* = (0, 0.375, 0, 0.375)``
  (atoms -1, 0, 1 with weights 3/16, 5/8, 3/16: positive definite ``B``),
  the convention of Peters et al.'s later moment shadow maps. Geometry lies
  in ``u in [-1, 0]`` (the map's nearest texel at -1, its deepest at 0) and
  empty texels at ``u = 1``, behind every receiver; a receiver nearer than
  every texel (``u < -1``) is in front of every atom and is lit. (With ``u =
  depth / d_hi - 1`` before, a scene under a far light shrank into a sliver
  below 0 that ``moment_bias`` blurred away: a spot 1e4 away over an 8-unit
  scene, 1.90 % misclassified against ``hard``'s 0.20 %; 0.17 % now.)
* *Depth bias.* The paper subtracts a constant depth bias. Here the receiver
  carries the package's biases (:func:`~.common.receiver`: ``bias``,
  ``slope_bias``, ``normal_bias``, their shared defaults) and, with
  ``receiver_plane`` (default), is lowered by half the drop of its tangent
  plane from the box's centre to its lowest corner (clamped by
  ``max_tan_slope``). A box ``w`` texels wide on a receiver tilted by
  ``theta`` holds the receiver's own depths spread over ``w texel
  tan(theta)``; for a uniform spread with the receiver at its centre the
  lower bound is 5/18 = 0.28 of shadow from the receiver alone, a quarter of
  the way down 0.14, half-way down at most 0.004 (any spread, default
  bias): half-way is about the least lowering that removes the self-shadow,
  and it halves the contact-shadow loss of going all the way
  (directional_mesh at ``a = 1e-6``: RMSE 0.063 instead of 0.070, false lit
  0.51 % instead of 0.66 %).
* *Degenerate moments* (``moment_bias = 0`` on a box of one or two depths,
  where ``B`` is singular): the receiver is compared with the box's mean
  depth instead of returning NaN.
* *Cube maps* (point and area lights): each face has its own tables; the box
  is narrowed symmetrically about the receiver at the face's border (it does not
  continue across seams; :func:`~.common.narrow_to_face`: clipped on one side, its
  mean left an inclined receiver's, and with ``receiver_plane = false`` an open wall
  under a point light read below 0.9 along the seams, 49 of 48^2 pixels at 512^2).
* *Build.* The tables are :func:`~mi_shadowmap.depth_maps.summed_area_table`'s
  (float64, O(texels)).
* *Virtual maps* (``virtual=true``, the default): pages hold depths only; the four
  moments' box means are summed over the box's texels at lookup time (the values the
  tables give; the box is a few texels wide, as the level matches the pixel
  footprint), and depths are normalised over the scene's depth span as the light sees
  it (:func:`~.common.virtual_depth_scale`: geometry in ``u in [-1, 0]`` as with full
  maps) instead of the built map's own span, which changes as camera moves build
  pages.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from ..depth_maps import box_mean, summed_area_table
from ..methods import Method, Prop
from .common import Lookup, antialiased, box_means_of_depths, has_layers, \
    narrow_to_face, normalized_depth, plane_depth_at, prefilter_box, receiver, receiver_plane, \
    span_layer, span_of, virtual_depth_scale, virtual_variance_factor

#: The four moment layers (summed-area tables of u^1 .. u^4).
MOMENT_LAYERS = ("msm_b1", "msm_b2", "msm_b3", "msm_b4")
#: Two values: the ``(d_lo, scale)`` of :func:`~.common.normalized_depth` the moments were
#: built with (:func:`~.common.span_layer`).
SPAN_LAYER = "msm_span"
#: Moments of the bias target in the [-1, 1] depth convention (Peters et al. 2017).
BIAS_TARGET = (0.0, 0.375, 0.0, 0.375)
#: Default moment bias (float64 moments and reconstruction; the paper's 16-bit
#: value is 3e-5). See the module documentation for the measurements.
MOMENT_BIAS = 1e-7
#: Default minimum filter width, in texels.
FILTER_SIZE = 1.0
#: ``receiver_plane``: how far the receiver is lowered towards its tangent plane's
#: minimum over the box (0: not at all, 1: all the way).
PLANE_FRACTION = 0.5


# ------------------------------------------------------------------- layers
def moment_depth(smap):
    """``(u, d_lo, scale)``: the map's depths as ``u = 2 z - 1`` (float64), ``z`` the
    depth normalised over the map's finite depth span (:func:`~.common.normalized_depth`,
    whose ``d_lo`` and ``scale`` follow): geometry in ``[-1, 0]``, empty texels ``u =
    1``."""
    z, d_lo, scale = normalized_depth(smap)
    return 2.0 * z - 1.0, d_lo, scale


def _moment_layer(k: int):
    def build(scene, smap):
        u = moment_depth(smap)[0]
        return summed_area_table(antialiased(smap, u ** k), smap.view.n_faces, smap.resolution)
    build.__name__ = build.__qualname__ = f"msm_b{k}_layer"
    build.__doc__ = f"Summed-area table of u^{k} (see :func:`moment_depth`)."
    return build


def span_layer_of(scene, smap) -> mi.Float64:
    """``(d_lo, scale)`` of :func:`~.common.normalized_depth` (two values)."""
    return span_layer(smap)


LAYERS = {**{name: _moment_layer(k + 1) for k, name in enumerate(MOMENT_LAYERS)},
          SPAN_LAYER: span_layer_of}


# ----------------------------------------------------------- reconstruction
def bias_moments(b, alpha):
    """``(1 - alpha) b + alpha b*`` with ``b* =`` :data:`BIAS_TARGET`."""
    return tuple((1.0 - alpha) * bk + alpha * tk for bk, tk in zip(b, BIAS_TARGET))


def hamburger(b1, b2, b3, b4, zf):
    """Shadow intensity ``G`` of the Hamburger 4MSM (Peters & Klein 2015).

    ``b1..b4``: (already biased) moments, ``zf``: receiver depth, all of one
    Dr.Jit float type (e.g. ``mi.Float64``). Returns ``(G, ok)``: ``G`` in
    ``[0, 1]`` (clamped), ``ok`` False where the moments are not strictly
    positive definite or the result is not finite (``G`` is then 0 there).
    """
    # LDL^T of the Hankel matrix B (D11 = 1, L21 = b1, L31 = b2).
    d22 = b2 - b1 * b1
    l32d22 = b3 - b1 * b2
    d33d22 = (b4 - b2 * b2) * d22 - l32d22 * l32d22
    ok = (d22 > 0) & (d33d22 > 0)
    d22s = dr.select(ok, d22, 1.0)
    d33d22s = dr.select(ok, d33d22, 1.0)
    l32 = l32d22 / d22s
    # Solve B c = (1, zf, zf^2): forward substitution, scaling, back substitution
    # (c0, c1, c2 here are the paper's c1, c2, c3).
    c1 = zf - b1
    c2 = zf * zf - b2 - l32 * c1
    c1 = c1 / d22s
    c2 = c2 * (d22s / d33d22s)
    c1 = c1 - l32 * c2
    c0 = 1.0 - b1 * c1 - b2 * c2
    # Roots of c2 z^2 + c1 z + c0 (the numerically stable pair of formulas).
    disc = dr.maximum(c1 * c1 - 4.0 * c2 * c0, 0.0)
    s = dr.sqrt(disc)
    qq = -0.5 * (c1 + dr.select(c1 >= 0, s, -s))
    ra = qq / c2
    rb = c0 / qq
    z2 = dr.minimum(ra, rb)
    z3 = dr.maximum(ra, rb)
    # Sum of the weights of the atoms in front of the receiver.
    g_mid = (zf * z3 - b1 * (zf + z3) + b2) / ((z3 - z2) * (zf - z2))
    g_far = 1.0 - (z2 * z3 - b1 * (z2 + z3) + b2) / ((zf - z2) * (zf - z3))
    g = dr.select(zf <= z2, 0.0, dr.select(zf <= z3, g_mid, g_far))
    ok &= dr.isfinite(g)
    return dr.select(ok, dr.clip(g, 0.0, 1.0), 0.0), ok


def shadow_intensity(b, zf, alpha):
    """``G`` for raw moments ``b = (b1, b2, b3, b4)`` and receiver depth ``zf`` (one
    float type): :func:`bias_moments`, then :func:`hamburger`; where the biased
    moments are degenerate, 1 if ``zf`` is behind their mean, else 0."""
    bb = bias_moments(b, alpha)
    g, ok = hamburger(*bb, zf)
    return dr.select(ok, g, dr.select(zf > bb[0], 1.0, 0.0))


def reduce_light_bleeding(vis, amount: float):
    """Lauritzen's light-bleeding reduction (as for VSM): ``clip((vis - amount) /
    (1 - amount), 0, 1)`` for ``0 <= amount < 1``."""
    if amount <= 0:
        return vis
    return dr.clip((vis - amount) / (1.0 - amount), 0.0, 1.0)


# ------------------------------------------------------------------- lookup
def receiver_depth(smap, lk: Lookup, r, opts, lo, hi):
    """The receiver depth the moments are compared with (world units, biases
    applied): ``r.depth``, or with ``receiver_plane`` ``r.depth`` lowered by
    :data:`PLANE_FRACTION` of the drop of the receiver's tangent plane from the
    box's centre to its lowest corner (:func:`~.common.plane_depth_at`, clamped
    by ``max_tan_slope``)."""
    if not opts.receiver_plane:
        return r.depth
    res = smap.resolution
    plane = receiver_plane(smap, lk, r, opts)
    centre = r.uv * res
    z = mi.Float(r.depth)
    for cx, cy in ((lo.x, lo.y), (hi.x, lo.y), (lo.x, hi.y), (hi.x, hi.y)):
        corner = mi.Point2f(cx, cy)
        lateral = dr.norm(corner - centre) * r.texel_world
        zc = plane_depth_at(smap, plane, r.face, corner * (1.0 / res), lateral)
        z = dr.minimum(z, dr.select(dr.isfinite(zc), zc, z))
    return r.depth + PLANE_FRACTION * (z - r.depth)


def msm(smap, lk: Lookup, opts, active=True) -> mi.Float:
    """Peters & Klein (2015) moment shadow mapping over the pixel's footprint.

    The box of :func:`~.common.prefilter_box` (the footprint, at least
    ``filter_size`` texels wide, narrowed symmetrically to the face), four float64 SAT
    box means of the moments, the receiver depth normalised as the map's (and lowered half-way
    to its tangent plane's minimum over the box with ``receiver_plane``), then the
    Hamburger reconstruction with ``moment_bias`` (see the module
    documentation). Visibility ``1 - G``; points outside the map are lit.
    """
    res = smap.resolution
    r = receiver(smap, lk, opts)
    act = mi.Bool(active) & r.inside
    lo, hi = narrow_to_face(smap, r, *prefilter_box(smap, lk, r, opts.filter_size))
    full = has_layers(smap, MOMENT_LAYERS + (SPAN_LAYER,))
    # full maps: normalised over the map's own depth span (its layer); virtual maps: over
    # the scene's depth span (virtual_depth_scale), their box's texels summed here
    d_lo, scale = (span_of(smap.extra[SPAN_LAYER], dr.width(r.depth)) if full
                   else virtual_depth_scale(smap))

    def to_u(z):
        return 2.0 * (mi.Float64(z) - d_lo) * scale - 1.0

    if full:
        b = tuple(box_mean(smap.extra[name], res, r.face, lo, hi, act)
                  for name in MOMENT_LAYERS)
        alpha = opts.moment_bias
    else:
        def per_texel(d):
            u = dr.select(dr.isfinite(d), to_u(d), 1.0)
            u2 = u * u
            return u, u2, u2 * u, u2 * u2

        b, _ = box_means_of_depths(smap, r.face, lo, hi, per_texel, 4, act)
        # the moment bias adds variance like vsm's floor: scaled per texel the same way
        alpha = opts.moment_bias * virtual_variance_factor(r, scale)
    z = receiver_depth(smap, lk, r, opts, lo, hi)
    # Receivers deeper than every texel stay in front of the empty texels (u = 1).
    # Receivers nearer than every texel (u < -1) are in front of the geometry and of the
    # bias target's atoms: G = 0 (tests/test_msm.py, down to u = -1e4).
    zf = dr.minimum(to_u(z), 1.0 - 1e-6)
    g = shadow_intensity(b, zf, alpha)
    vis = reduce_light_bleeding(mi.Float(1.0 - g), opts.light_bleeding)
    return dr.select(act, vis, 1.0)


METHOD = Method(
    name="msm",
    lookup=msm,
    summary="Peters & Klein 2015 moment shadow maps: four filtered depth moments, "
            "Hamburger reconstruction (O(1) summed-area-table filtering of the pixel "
            "footprint)",
    properties=(
        Prop("filter_size", "float", FILTER_SIZE,
             "Minimum filter width in texels per axis; the camera pixel's footprint "
             "widens it (1 = bilinear filtering of the moments).", lo=0.0),
        Prop("moment_bias", "float", MOMENT_BIAS,
             "Moment bias alpha: the filtered moments (depth in [-1, 1], the map's depth "
             "span in [-1, 0]) are blended "
             "with (0, 0.375, 0, 0.375) by this weight before the reconstruction "
             "(larger: more robust, softer, more light leaking; the paper's 16-bit "
             "value is 3e-5).", lo=0.0, hi=0.99),
        Prop("light_bleeding", "float", 0.0,
             "Light-bleeding reduction as for VSM: visibility v becomes "
             "clip((v - amount) / (1 - amount), 0, 1); 0 = off.", lo=0.0, hi=0.99),
        Prop("receiver_plane", "bool", True,
             "Lower the receiver depth by half the drop of its tangent plane over the "
             "filter box, so a tilted receiver does not shadow itself (false: the "
             "receiver's own depth, as in the paper)."),
    ),
    layers=LAYERS,
    layers_for=lambda o: () if getattr(o, "virtual", False) else tuple(LAYERS),
    virtual_margin=lambda o: 2.0 + 0.5 * max(o.filter_size, 6.0),
    virtual=True,
    #: four float64 tables (2 float32 arrays each) and two values
    layer_cost={**{name: 2.0 for name in MOMENT_LAYERS}, SPAN_LAYER: 0.0},
    needs_footprint=True,
    builtin=True,
)
