"""Exponential variance shadow maps: Lauritzen & McCool, "Layered Variance Shadow
Maps", Graphics Interface 2008 (``method="evsm"``).

Filter first, compare second, as in variance shadow maps (Donnelly &
Lauritzen 2006, ``vsm``), but on two *exponentially warped* depths, the
paper's answer to VSM's light bleeding. The map stores the first two moments
of ``w+ = exp(c+ u)`` and of ``w- = -exp(-c- u)``, ``u`` being the depth
mapped to [-1, 1]; a lookup averages them over a filter box, bounds the lit
fraction of the box with the one-sided Chebyshev inequality in each warped
space and returns the smaller bound.

**Why it works.** Both warps are increasing, so ``P(w(z) >= w(t)) = P(z >=
t)``: each bound is still an upper bound of the box's lit fraction, and the
smaller one is the tighter. Chebyshev on the plain depth leaks light where
a box holds two occluders far apart in depth over a receiver just behind the
deeper one (their spread dominates the receiver's distance behind the
mean); ``exp(c+ u)`` squeezes every depth in front of the receiver towards 0
relative to the receiver's own value, so the bound falls off like
``exp(-2 c+ (t - z_b))``, ``z_b`` being the occluder depth nearest the
receiver (all in ``u``). The
negative warp ``-exp(-c- u)`` does the same from the other side: it stays
tight where depths *behind* the receiver (a far background next to a ledge)
inflate the positive warp's mean.

**Algorithm.**

1. *Map* (per map, built and cached by the map manager). ``z =``
   :func:`~.common.normalized_depth` (``z = (depth - d_lo) / (2 (d_hi - d_lo))``
   over the map's finite depths ``[d_lo, d_hi]``, at least
   :data:`~.common.MIN_SPAN` of the depth wide; empty texels 1); the warp input
   ``u = 4 z - 1``, clipped to [-1, 1], maps that span onto [-1, 1] (empty
   texels: ``u = 1``). Layers: ``evsm_span`` (``d_lo`` and ``1 / (2 (d_hi -
   d_lo))``, float64) and float64 summed-area
   tables (:func:`~mi_shadowmap.depth_maps.summed_area_table`, per face) of
   ``w+``, ``w+^2``, ``w-``, ``w-^2``, named after the
   exponent they hold (``evsm_p1_6p0``, ``evsm_p2_6p0``, ``evsm_n1_6p0``,
   ``evsm_n2_6p0`` for the defaults; :func:`moment_layer_names`): a render
   builds the pair for its exponents, and tables of other exponents stay
   cached under their own names.
2. *Filter box*, centred on the receiver's (normal-offset) projection, as
   wide per axis as the camera pixel's footprint in texels or
   ``filter_size``, whichever is larger, and at least one texel
   (:func:`~.common.prefilter_box`); narrowed symmetrically at a face border.
3. *Moments* ``M1 = E[w]``, ``M2 = E[w^2]`` of each warp over the box:
   :func:`~mi_shadowmap.depth_maps.box_mean` (16 gathers per table, partial
   texels by their covered fraction), O(1) whatever the width.
4. *Bounds.* The receiver's biased depth is normalised over the same span and
   warped (``t = w(u_r)``; a receiver nearer than every texel has ``u_r = -1``,
   at or below every texel's warp: lit); ``sigma^2 = max(M2 - M1^2,
   sigma_min^2)``, ``p = sigma^2 / (sigma^2 + (t - M1)^2)`` if ``t > M1``
   else 1, where ``sigma_min^2 = min_variance * (dw/dz)^2`` at the receiver
   (the paper's minimum variance scaled by the warp's derivative, so it is
   the same depth spread in both warps); then the light-bleeding reduction
   ``p' = clamp((p - a) / (1 - a), 0, 1)``, ``a = light_bleeding``.
5. *Visibility* ``min(p'+, p'-)``; points outside the map are lit.

**Defaults** (measured on every scene of ``scenes_xml/`` and, off the
repository, the built-in scene with each light type from another camera,
the Cornell box with a point light and a spot over two stacked plates; 64^2
images on 1024^2 maps, 128^2 on the automatic resolution, 256^2 on 256^2):

* ``exponent = negative_exponent = 6``: the largest exponents a float64
  summed-area table resolves over the whole depth range of a 4096^2 face
  (see the deviations). Over 24 random depth triples of two occluders over
  a receiver (1024^2 map, far texels first in the table's scan), the leaked
  light where the truth is 0 is 0.028 on average (max 0.34) against 0.165
  (max 0.46) for plain Chebyshev on the depth; 5: 0.037, 8: 0.026 at 1024^2
  but 0.048 at 2048^2, 10: 0.14, 12: 0.18. On the scenes the exponents below
  10 change nothing measurable; at 20 / 20 the tables lose both warps over
  part of the range (default_directional from the other camera: 9 % false
  lit) and the concave negative warp, whose mean over a tilted receiver's own
  depths lies below the receiver's warped depth, shadows such receivers
  (cbox_area: 3.7 % false shadow).
* ``filter_size = 1`` texel (bilinear filtering of the moments, the paper's
  texture lookup): against 2 it lowers the visibility RMSE at 256^2 maps
  (0.053 vs 0.055) and the grazing-spot acne of ``tests/test_stability.py``
  (0 vs 0.2 %), with no difference where the footprint is wider.
* ``min_variance = 1e-7`` (``vsm``'s value and unit): no measurable effect
  between 0 and 1e-5; 1e-4 leaks (mean false lit 0.14 -> 0.18 % at 128^2); it
  cannot replace the biases (without them cbox_area has 1.3 % false shadow,
  0.8 % with them; virtual maps, 128^2).
* ``light_bleeding = 0``: the plain bounds. 0.1 trades false lit for false
  shadow (128^2: mean false lit 0.14 -> 0.11 %, largest false shadow
  1.7 -> 1.8 %; 64^2: mean misclassified 0.57 -> 0.67 %).
* ``slope_bias = 0.5``, ``normal_bias = 0.25`` texels (``vsm``'s): against the
  shared 1.0 / 0.5 they lower the mean false lit from 0.21 to 0.16 %
  (peter-panning) and the mean misclassified from 0.55 to 0.51 %
  (``benchmarks/bench_prefiltered_bias.py``: 9 repository scenes, 128^2,
  16 spp, virtual maps, on the reference's camera samples, 2026-12-06), at
  equal acne (none at 60-89.9 degrees). Without biases the mean is 0.59 %.

Deviations from the paper, and why:

* *Summed-area tables, not mipmaps.* The paper filters the warped moments
  with fp32 mipmaps and hardware (anisotropic) filtering; we use per-face
  float64 summed-area tables, as ``vsm`` and ``msm`` do: an exact box of any
  width and aspect at O(1).
* *Exponent clamp* (:data:`MAX_EXPONENT` = 42, the paper's fp32 limit, also
  used by the common implementations): with ``u`` in [-1, 1] the second
  moment ``exp(2 c u)`` must stay below FLT_MAX = 3.4e38, i.e. ``2 c <=
  88.7``; 42 leaves a factor ``e^4.7`` of headroom so that the moments can
  still be stored, exported or mip-filtered in float32. Larger exponents are
  an ``OptionError`` naming the range.
* *In a summed-area table the usable exponent is far smaller than the
  clamp.* A box mean is a difference of prefix sums over the face, so its
  rounding error scales with the prefix sum ``S`` at the box's far corner,
  not with the box's own values as in a mipmap: measured at most
  ``29.2 * 2^-52 |S|`` (random boxes on 256^2 .. 4096^2 maps; tables of
  constants and of ``exp(40 u)``). With ``c = 40`` the sums of
  ``exp(2 c u)`` reach ``N e^80`` while the values near the light are
  ``e^-80``, and the unguarded bounds were noise: 42.7 % of the pixels of
  contact_hardening and 18.5 % of spot_sphere_box were false shadow (``c+ =
  20``: 9.3 % on contact_hardening). Each box mean therefore carries an
  error bound ``E = SAT_ERROR * 2^-52 * |S(far corner)| / area`` (one more
  gather per table; :data:`SAT_ERROR` = 64, twice the largest measured
  ratio), and each Chebyshev bound is evaluated with its moments moved by
  ``E`` in the lit direction (variance plus its error bound, ``t - M1``
  minus ``E``): a warp the table cannot resolve reads 1 and the other warp
  decides. It never adds noise or acne (it only raises a bound); at the
  defaults it raises 0.3 % of the measured scenes' visibility pixels by at
  most 0.017 (4 of 53248 pixels change side of 0.5 at 64^2 / 1024^2 maps,
  none at 128^2). With exponents near the clamp both warps are lost over
  much of the range and light leaks (42 / 42: up to 14 % false lit).
* *Depth range.* The paper warps the light's [near, far] range mapped to
  [-1, 1]; we map the map's own finite depth range there (``d_lo``,
  ``d_hi``), so the exponent acts over the depths that occur and neither a
  far margin nor the empty texels take part of it. ``min_variance`` is in
  normalised depth squared, ``((depth - d_lo) / (2 (d_hi - d_lo)))^2``, as for
  ``vsm``: relative to the scene's depths whatever the light's distance. (In
  units of twice the largest depth, as before, it grew with the distance: a spot
  1e4 away over an 8-unit scene lost every shadow, 1.90 % misclassified against
  ``hard``'s 0.20 %; 0.15 % now. The warp's range was the map's span already.)
* *Precision.* Moments, variance, warps and bounds are float64 (the paper:
  fp32, hence its larger minimum variance).
* *Filter region.* The paper filters the hardware's texture footprint; we
  filter the camera pixel's ray-differential footprint (as ``pcf`` and
  ``vsm``), never less than ``filter_size`` texels nor one texel (a narrower
  box of a summed-area table is a difference of nearly equal sums).
* *Face borders and cube maps* (not in the paper). Boxes do not continue
  across cube-face seams; at a face border the box is narrowed
  symmetrically (keeping at least half a texel on each side) rather than
  clipped on one side, since a one-sided box on a tilted receiver has a
  mean depth away from the receiver's, which Chebyshev reads as shadow
  (64^2 images on 1024^2 maps, wide footprints: cbox_area false shadow
  1.37 -> 1.20 %, spot_sphere_box 0.27 -> 0.22 %; no change at 128^2).
* *Biases.* The receiver also gets the package's scale-invariant slope and
  normal-offset biases (smaller defaults than ``hard``, see above).
* *Area lights* are treated as their centre point, like ``hard``, ``pcf``
  and ``vsm``.
* *Virtual maps* (``virtual=true``, the default): pages hold depths only; the warps'
  box means are summed over the box's texels at lookup time (the values the tables
  give, with a rounding bound of their own instead of the tables'), and the warped
  range is the scene's depth span as the light sees it
  (:func:`~.common.virtual_depth_scale`) instead of the built map's, which would change
  as camera moves build pages: where the scene's box is much deeper than its surfaces
  the warps spread over a wider range than with full maps. ``min_variance`` is in that
  span's normalised depth squared, scaled per texel as for ``vsm``
  (:func:`~.common.virtual_variance_factor`).
"""
from __future__ import annotations

import functools
import re

import drjit as dr
import mitsuba as mi

from ..depth_maps import box_mean, summed_area_table
from ..methods import Method, Prop
from .common import Lookup, Receiver, antialiased, box_means_of_depths, \
    has_layers, narrow_to_face, normalized_depth, prefilter_box, receiver, span_layer, \
    span_of, virtual_depth_scale, virtual_variance_factor

#: Largest allowed exponent: exp(2 c) of u = 1 stays a finite float32 (2 c <= 88.7).
MAX_EXPONENT = 42.0
#: Default exponents (c+, c-); see the module doc and the record.
EXPONENTS = (6.0, 6.0)
#: The layer holding the map's depth normalisation ``(d_lo, scale)`` (float64,
#: :func:`~.common.span_layer`).
SPAN_LAYER = "evsm_span"
#: The normalised depths the warps map to [-1, 1]: a map's finite depths span
#: ``[0, 1/2]`` (:func:`~.common.normalized_depth`, :func:`~.common.virtual_depth_scale`).
Z_LO, Z_HI = 0.0, 0.5
#: Narrowest filter box, in texels.
MIN_BOX = 1.0
#: Bound on the rounding error of a box sum, in units of 2^-52 |S(far corner)|.
SAT_ERROR = 64.0
_EPS64 = 2.0 ** -52


# ------------------------------------------------------------------ layers
def _tag(c: float) -> str:
    """The exponent in a layer name: ``repr`` with '.' -> 'p', '-' -> 'm'."""
    return repr(float(c)).replace(".", "p").replace("-", "m").replace("+", "")


def _untag(tag: str) -> float:
    return float(tag.replace("p", ".").replace("m", "-"))


def moment_layer_names(exponent: float, negative_exponent: float) -> tuple:
    """The four moment layers ``(w+, w+^2, w-, w-^2)`` for these exponents."""
    cp, cn = _tag(exponent), _tag(negative_exponent)
    return (f"evsm_p1_{cp}", f"evsm_p2_{cp}", f"evsm_n1_{cn}", f"evsm_n2_{cn}")


def warp_input(z, z_lo, z_hi):
    """``u = 2 (z - z_lo) / (z_hi - z_lo) - 1`` clipped to [-1, 1], in float64."""
    Float64 = mi.Float64
    z_lo = Float64(z_lo)
    u = 2.0 * (Float64(z) - z_lo) / (Float64(z_hi) - z_lo) - 1.0
    return dr.clip(u, -1.0, 1.0)


def warp(u, c: float, positive: bool):
    """The paper's warps: ``exp(c u)`` (positive) or ``-exp(-c u)`` (negative)."""
    return dr.exp(c * u) if positive else -dr.exp(-c * u)


def range_layer(scene, smap):
    """``evsm_span``: ``(d_lo, scale)`` of :func:`~.common.normalized_depth` (float64)."""
    return span_layer(smap)


def moment_layer(smap, positive: bool, power: int, c: float):
    """Summed-area table of ``w^power``, ``w`` = the warp of exponent ``c`` of the
    normalised depth (:func:`~.common.normalized_depth`; empty texels ``u = 1``)."""
    z = normalized_depth(smap)[0]
    w = warp(warp_input(z, Z_LO, Z_HI), c, positive)
    return summed_area_table(antialiased(smap, w if power == 1 else w * w),
                             smap.view.n_faces, smap.resolution)


@functools.lru_cache(maxsize=None)
def _moment_builder(positive: bool, power: int, c: float):
    """One builder per layer (the map cache keys layers by their builder too)."""
    def build(scene, smap):
        return moment_layer(smap, positive, power, c)
    build.__name__ = build.__qualname__ = "evsm_moment_layer"
    return build


class _Layers(dict):
    """``{name: builder}`` of the record: the range layer and the default exponents'
    moment layers, plus a builder for the moment layers of any other exponents
    (looked up by name, :func:`moment_layer_names`)."""

    def __missing__(self, name):
        m = re.fullmatch(r"evsm_([pn])([12])_([0-9pem]+)", name)
        if m is None:
            raise KeyError(name)
        return _moment_builder(m.group(1) == "p", int(m.group(2)), _untag(m.group(3)))


class _Costs(dict):
    """Memory of each layer in float32 arrays of a face (:attr:`Method.layer_cost`): 2 for
    every float64 moment table (whatever its exponent), 0 for the 2-value span layer."""

    def get(self, name, default=None):
        if name == SPAN_LAYER:
            return 0.0
        return 2.0 if name.startswith("evsm_") else default


def _layers_for(opts) -> tuple:
    if getattr(opts, "virtual", False):
        return ()      # virtual maps: the lookup sums the box's texels (_summed_moments)
    return (SPAN_LAYER,) + moment_layer_names(opts.exponent, opts.negative_exponent)


# ------------------------------------------------------------------ lookup
def chebyshev(m1, m2, t, min_var, light_bleeding: float = 0.0, err1=0.0, err2=0.0):
    """One-sided Chebyshev bound on ``P(w >= t)`` from ``m1 = E[w]``, ``m2 = E[w^2]``,
    with the error bounds ``err1``, ``err2`` of ``m1``, ``m2`` taken in the lit direction
    (the variance's upper bound, the distance's lower bound), then the light-bleeding
    reduction ``clamp((p - a) / (1 - a), 0, 1)``."""
    var = m2 - m1 * m1 + err2 + 2.0 * dr.abs(m1) * err1 + err1 * err1
    var = dr.maximum(var, min_var)
    d = t - m1 - err1
    p = var / (var + d * d)
    if light_bleeding > 0.0:
        p = dr.clip((p - light_bleeding) / (1.0 - light_bleeding), 0.0, 1.0)
    return dr.select(d > 0.0, p, 1.0)


def filter_box(smap, lk: Lookup, r: Receiver, filter_size: float):
    """``(lo, hi)`` in continuous texel coordinates: :func:`~.common.prefilter_box`
    (at least :data:`MIN_BOX` wide), narrowed symmetrically at the face border
    (keeping at least half a texel on each side of the receiver)."""
    lo, hi = prefilter_box(smap, lk, r, max(float(filter_size), MIN_BOX))
    return narrow_to_face(smap, r, lo, hi, 0.5 * MIN_BOX)


def evsm_bounds(smap, lk: Lookup, opts, active=True):
    """``(p+, p-, inside)``: the two Chebyshev bounds (float64) of a lookup."""
    r = receiver(smap, lk, opts)
    active = mi.Bool(active) & r.inside
    lo, hi = filter_box(smap, lk, r, opts.filter_size)
    names = moment_layer_names(opts.exponent, opts.negative_exponent)
    if has_layers(smap, (SPAN_LAYER,) + names):
        u, dudz, moments, floor = _table_moments(smap, r, lo, hi, names, active)
    else:
        u, dudz, moments, floor = _summed_moments(smap, r, lo, hi, opts, active)
    bounds = []
    for (positive, c), (m1, m2, err1, err2) in zip(
            ((True, opts.exponent), (False, opts.negative_exponent)), moments):
        t = warp(u, c, positive)
        min_var = opts.min_variance * floor * dr.square(c * t * dudz)      # (dw/dz)^2
        bounds.append(chebyshev(m1, m2, t, min_var, opts.light_bleeding, err1, err2))
    return bounds[0], bounds[1], r.inside


def _table_moments(smap, r: Receiver, lo, hi, names, active):
    """``(u, du/dz, [(m1, m2, err1, err2)] per warp, floor factor)`` from a full map's
    summed-area tables, each mean with its tables' error bound."""
    Float64 = mi.Float64
    res = smap.resolution
    d_lo, scale = span_of(smap.extra[SPAN_LAYER], dr.width(r.depth))
    # a receiver nearer than every texel: z < 0, u clipped to -1, lit (t <= M1)
    u = warp_input((Float64(r.depth) - d_lo) * scale, Z_LO, Z_HI)
    dudz = 2.0 / (Z_HI - Z_LO)
    area = dr.maximum(Float64(hi.x - lo.x), 1e-3) * dr.maximum(Float64(hi.y - lo.y), 1e-3)
    ci = mi.UInt32(dr.clip(mi.Int32(dr.ceil(hi.x)), 1, res) - 1)
    cj = mi.UInt32(dr.clip(mi.Int32(dr.ceil(hi.y)), 1, res) - 1)
    corner = mi.UInt32(r.face) * (res * res) + cj * res + ci
    scale = SAT_ERROR * _EPS64 / area
    moments = []
    for k in range(2):
        sat1, sat2 = smap.extra[names[2 * k]], smap.extra[names[2 * k + 1]]
        moments.append((box_mean(sat1, res, r.face, lo, hi, active),
                        box_mean(sat2, res, r.face, lo, hi, active),
                        scale * dr.abs(dr.gather(Float64, sat1, corner, active)),
                        scale * dr.abs(dr.gather(Float64, sat2, corner, active))))
    return u, dudz, moments, 1.0


def _summed_moments(smap, r: Receiver, lo, hi, opts, active):
    """:func:`_table_moments` on a map without the tables (virtual maps): the warps' box
    means summed over the box's texels, depths normalised over the scene's depth span
    (:func:`~.common.virtual_depth_scale`: ``z`` in ``[0, 1/2]``, the warps' range),
    each mean with a rounding bound of 4 x (texels summed) x 2^-52 of its magnitude,
    and the floor scaled per texel as for ``vsm``."""
    Float64 = mi.Float64
    d_lo, scale = virtual_depth_scale(smap)
    z_lo, z_hi = Z_LO, Z_HI
    c_pos, c_neg = opts.exponent, opts.negative_exponent

    def per_texel(d):
        z = dr.select(dr.isfinite(d), (Float64(d) - d_lo) * scale, 1.0)
        u = warp_input(z, z_lo, z_hi)
        wp, wn = warp(u, c_pos, True), warp(u, c_neg, False)
        return wp, wp * wp, wn, wn * wn

    means, count = box_means_of_depths(smap, r.face, lo, hi, per_texel, 4, active)
    u = warp_input((Float64(r.depth) - d_lo) * scale, z_lo, z_hi)
    rel = 4.0 * Float64(count) * _EPS64
    moments = [(m1, m2, rel * dr.abs(m1), rel * dr.abs(m2))
               for m1, m2 in (means[:2], means[2:])]
    return u, 2.0 / (z_hi - z_lo), moments, virtual_variance_factor(r, scale)


def evsm(smap, lk: Lookup, opts, active=True) -> mi.Float:
    """Lauritzen & McCool 2008 exponential variance shadow maps (see the module doc)."""
    p_pos, p_neg, inside = evsm_bounds(smap, lk, opts, active)
    return dr.select(inside, mi.Float(dr.minimum(p_pos, p_neg)), 1.0)


_LAYERS = _Layers({SPAN_LAYER: range_layer})
for _name in moment_layer_names(*EXPONENTS):
    _LAYERS[_name] = _LAYERS[_name]      # the defaults' builders, listed in the record

METHOD = Method(
    name="evsm",
    lookup=evsm,
    summary="Lauritzen & McCool 2008 exponential variance shadow maps: Chebyshev bounds "
            "on two exponentially warped depths' summed-area-table moments, the minimum",
    properties=(
        Prop("filter_size", "float", 1.0,
             "evsm: minimum width of the filter box in texels per axis (at least 1); the "
             "camera pixel's footprint widens it (O(1) lookups through summed-area "
             "tables on full maps; virtual maps sum the box's texels, at most 64 per "
             "side).", lo=0.0),
        Prop("exponent", "float", EXPONENTS[0],
             "evsm: exponent c+ of the positive warp exp(c+ u), u = the depth mapped to "
             "[-1, 1] over the map's depth range; at most 42, the float32 limit of "
             "exp(2 c+). Above ~8 the float64 summed-area tables cannot resolve the "
             "warp over the whole range; there its bound reads 1 (light may leak).",
             lo=0.0, lo_open=True, hi=MAX_EXPONENT),
        Prop("negative_exponent", "float", EXPONENTS[1],
             "evsm: exponent c- of the negative warp -exp(-c- u); at most 42 (as exponent).",
             lo=0.0, lo_open=True, hi=MAX_EXPONENT),
        Prop("min_variance", "float", 1e-7,
             "evsm: lower clamp of the variance, in normalised depth squared (the depth "
             "span the light sees mapped to [0, 1/2], as vsm), mapped into each warp by "
             "its derivative.", lo=0.0, hi=1.0),
        Prop("light_bleeding", "float", 0.0,
             "evsm: light-bleeding reduction amount a applied to each warp's bound: "
             "p' = clamp((p - a) / (1 - a), 0, 1); 0 = the plain bounds.",
             lo=0.0, hi=0.99),
    ),
    layers=_LAYERS,
    layers_for=_layers_for,
    layer_cost=_Costs({name: 0.0 if name == SPAN_LAYER else 2.0 for name in _LAYERS}),
    needs_footprint=True,
    bias_defaults={"slope_bias": 0.5, "normal_bias": 0.25},
    virtual_margin=lambda o: 2.0 + 0.5 * max(o.filter_size, 6.0),
    virtual=True,
    builtin=True,
)
