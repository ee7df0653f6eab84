"""Variance shadow maps: Donnelly & Lauritzen, "Variance Shadow Maps", I3D 2006
(``method="vsm"``), with the light-bleeding reduction of Lauritzen, "Summed-Area
Variance Shadow Maps", GPU Gems 3, chapter 8 (2007).

Filter first, compare second: the map stores the first two moments of the
depth, ``z`` and ``z^2``, which (unlike depths) may be averaged over any
region; a lookup reads their means over the pixel's footprint and bounds the
fraction of that region which does not occlude the receiver with the one-sided
Chebyshev (Cantelli) inequality. Prefiltered with summed-area tables, a lookup
costs O(1) whatever the footprint.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from ..depth_maps import box_mean, summed_area_table
from ..methods import Method, Prop
from .common import (Lookup, antialiased, box_means_of_depths, has_layers,
                     narrow_to_face, normalized_depth, prefilter_box, receiver, span_layer, span_of,
                     virtual_depth_scale, virtual_variance_factor)

#: The layers of a full map (virtual maps build none: see :func:`vsm_moments`).
LAYERS = ("vsm_m1", "vsm_m2", "vsm_span")


#: The variance never goes below this (normalised depth squared: sigma = 1e-7, 2e-7 of the
#: map's depth span, at most the float32 resolution of a stored depth), so that the
#: round-off of the float64 box means (~1e-16) cannot shadow a receiver level with the map
#: (e.g. ``t = 1`` in a box of empty texels) even with ``min_variance = 0``.
VARIANCE_FLOOR = 1e-14


def chebyshev_upper_bound(m1, m2, t, min_variance: float = 0.0,
                          light_bleeding: float = 0.0):
    """Donnelly & Lauritzen's lit fraction from the moments ``m1 = E[z]``,
    ``m2 = E[z^2]`` of a region and the receiver depth ``t`` (same units).

    ``sigma^2 = max(m2 - m1^2, min_variance)``; ``p_max = sigma^2 / (sigma^2 +
    (t - m1)^2)`` for ``t > m1`` (the one-sided Chebyshev bound on
    ``P(z >= t)``), 1 for ``t <= m1``; then Lauritzen's light-bleeding reduction
    ``clamp((p - amount) / (1 - amount), 0, 1)``. Works on any Dr.Jit float type
    (the lookup passes ``mi.Float64``: the variance is a difference of nearly
    equal means).
    """
    var = dr.maximum(m2 - m1 * m1, dr.maximum(min_variance, VARIANCE_FLOOR))
    d = t - m1
    p_max = var / (var + d * d)
    p = dr.select(t <= m1, 1.0, p_max)
    if light_bleeding > 0.0:
        p = dr.clip((p - light_bleeding) / (1.0 - light_bleeding), 0.0, 1.0)
    return p


def vsm_moments(smap, lk: Lookup, r, filter_size, active=True):
    """``(m1, m2, t, floor)``: the means of ``z`` and ``z^2`` over the lookup's filter box
    (:func:`~.common.prefilter_box`: the pixel footprint, at least
    ``filter_size`` texels, narrowed symmetrically to the receiver's face) and the receiver's
    biased depth ``t``, all in normalised depth (``mi.Float64``), and the factor on
    ``min_variance`` (1 on full maps; :func:`~.common.virtual_variance_factor` on
    virtual maps)."""
    res = smap.resolution
    # narrowed symmetrically at a face border: a box clipped on one side shadowed
    # inclined receivers along every cube seam (see narrow_to_face)
    lo, hi = narrow_to_face(smap, r, *prefilter_box(smap, lk, r, filter_size))
    if not has_layers(smap, LAYERS):
        # virtual maps: the box's texels summed here, normalised over the scene's depth
        # span (virtual_depth_scale; the map's own extremes change with the pages built)
        d_lo, scale = virtual_depth_scale(smap)

        def per_texel(d):
            z = dr.select(dr.isfinite(d), (mi.Float64(d) - d_lo) * scale, 1.0)
            return z, z * z

        (m1, m2), _ = box_means_of_depths(smap, r.face, lo, hi, per_texel, 2, active)
        return (m1, m2, dr.minimum((mi.Float64(r.depth) - d_lo) * scale, 1.0),
                virtual_variance_factor(r, scale))
    m1 = box_mean(smap.extra["vsm_m1"], res, r.face, lo, hi, active)
    m2 = box_mean(smap.extra["vsm_m2"], res, r.face, lo, hi, active)
    d_lo, scale = span_of(smap.extra["vsm_span"], dr.width(r.depth))
    # Clamped at 1, the value of empty texels: they stay "behind every receiver" even
    # for a receiver twice the map's depth span behind its nearest texel (e.g. a map too
    # coarse to hold any surface). A receiver nearer than every texel has t < 0: lit.
    t = dr.minimum((mi.Float64(r.depth) - d_lo) * scale, 1.0)
    return m1, m2, t, 1.0


def vsm(smap, lk: Lookup, opts, active=True) -> mi.Float:
    r"""Donnelly & Lauritzen 2006, with summed-area tables (Lauritzen 2007).

    **Map.** The depth is normalised over the map's own finite depth span, ``z =
    (depth - d_lo) / (2 (d_hi - d_lo))`` (:func:`~.common.normalized_depth`: the
    nearest texel at 0, the deepest at 1/2, empty texels ``z = 1``), and the layers
    ``vsm_m1``, ``vsm_m2`` are float64 summed-area tables of ``z`` and ``z^2`` per face
    (:func:`~mi_shadowmap.depth_maps.summed_area_table`), built once per map and cached
    with it; ``vsm_span`` holds ``(d_lo, 1 / (2 (d_hi - d_lo)))`` (two values).

    **Filter region.** A box centred on the receiver's (normal-offset)
    projection whose width per axis is the camera pixel's footprint in
    texels or ``filter_size`` texels, whichever is larger
    (:func:`~.common.prefilter_box`), narrowed symmetrically about the receiver
    where it would cross the face's border (:func:`~.common.narrow_to_face`: a box cut
    on one side has a mean depth off the receiver's on an inclined plane, which
    shadowed open walls along cube seams). Its means
    ``M1 = E[z]`` and ``M2 = E[z^2]`` come from 16 gathers per table
    (:func:`~mi_shadowmap.depth_maps.box_mean`; texels count by their covered
    fraction): O(1) whatever the box size.

    **Visibility.** With the receiver's biased depth ``t`` (normalised over the
    same span, clamped at 1; a receiver nearer than every texel has ``t < 0``),
    ``sigma^2 = max(M2 - M1^2, min_variance)`` and

    .. math:: p_{max}(t) = \frac{\sigma^2}{\sigma^2 + (t - M_1)^2}
              \quad (t > M_1), \qquad 1 \quad (t \le M_1),

    the one-sided Chebyshev inequality's upper bound on ``P(z >= t)``, the lit
    fraction of the box. It is exact when the box holds one occluder depth and
    the receiver's own depth (a shadow edge on a flat receiver facing the
    light: ``p = 1 -`` occluded fraction, the box-filtered PCF result); where
    two occluders at different depths share the box, ``p_max`` overestimates
    (light bleeding). Light-bleeding reduction (``light_bleeding = a``,
    Lauritzen 2007): ``p' = clamp((p_max - a) / (1 - a), 0, 1)`` cuts the
    tail below ``a``. Points outside the map are lit.

    **Properties and defaults** (measured on the six repository scenes at
    1024^2 and at the automatic resolution, 64^2 images, 4 spp, and on six
    scenes not in the repository: the built-in scene under spot, point,
    directional and area lights scaled by 3 and seen from another camera,
    ``mi.cornell_box()`` with a point light, and a plate half covering a box
    -- two overlapping occluders, the classic bleeding case):

    * ``filter_size = 2`` texels: the minimum box, the footprint of 2x2
      hardware filtering. 1, 2 and 4 are equal at 1024^2 (the pixel footprint,
      ~16 texels, is wider); at the automatic resolution 2 has the lowest
      visibility RMSE (0.046 against 0.048 and 0.049 for 1 and 4) while 4 raises the
      worst false lit from 0.56 % to 0.88 % (8 without reduction: 3.8 %).
    * ``light_bleeding = 0.2``: worst false lit over all twelve scenes
      0.88 % / 0.71 % / 0.56 % / 0.54 % for ``a`` = 0 / 0.1 / 0.2 / 0.3 at the
      automatic resolution (0.42 / 0.37 / 0.29 / 0.22 % at 1024^2), at the cost
      of false shadow along shadow edges (the 0.5 level moves ``a/2`` of the
      box width into the lit side: mean misclassified 0.67 / 0.70 / 0.77 /
      0.88 %; 0.3 reaches 3.03 % on ``contact_hardening``). 0.2 keeps the worst
      false lit at half the 1 % acceptance; it removes the bleeding streak of
      the plate-and-box scene. **For gradients use 0**: the reduction's
      clamp makes the visibility's derivative jump where ``p_max = a``, and
      a Monte Carlo pixel integral of a jumping derivative is noisy.
      Measured (``benchmarks/bench_gradients.py``, area scene, 128^2, 16 spp,
      ``multijitter`` sampler, an occluder moved sideways, ``filter_size =
      4``): standard deviation of the gradient over seeds 1.2e-5 at 0.2,
      4.6e-6 at 0 (``direct_projective``: 3.4e-5); mean within 0.3 % of
      ray-traced finite differences at 0 (3 % at 0.2).
    * ``min_variance = 1e-7`` (normalised depth squared: ``sigma_min =
      2 sqrt(1e-7) (d_hi - d_lo) ~ 6.3e-4`` of the depth span the light sees,
      below half a texel's depth at 1024^2 in the repository scenes, so
      contact shadows keep their length). With the biases on, 0 to 1e-5 give
      the same classification on every scene (float64 moments leave no
      round-off to hide); without biases, a plane facing the light has zero
      variance and with ``min_variance = 0`` darkens by 12 % on average, any
      value >= 1e-9 removes that. 1e-4 starts to add false lit
      (directional_mesh 0.29 -> 0.44 %). (Re-measured when the full maps'
      normalisation became their depth span instead of twice their largest
      depth, the 9 repository scenes at 1024^2, 64^2, 4 spp: 0, 1e-7 and 1e-5
      give the same classification before and after; at 1e-4
      directional_mesh's false lit was 0.51 %.)

    **Bias.** The Chebyshev test is already soft: a receiver plane tilted
    against the light spreads its own depth over the box as variance, and its
    mean is the depth at the box centre, so it does not shadow itself (the
    grazing-light tests of ``tests/test_stability.py`` give 0 % acne at 60 to
    89.9 degrees). The receiver still gets the package's biases
    (:func:`~.common.receiver`), at half the compare-based defaults:
    ``slope_bias = 0.5``, ``normal_bias = 0.25`` texels. Measured
    (``benchmarks/bench_prefiltered_bias.py``: the 9 repository scenes, 128^2,
    16 spp, on the reference's camera samples, 2026-12-06; mean misclassified /
    mean false lit on virtual maps, the default; full 1024^2 maps in brackets):
    no bias 0.61 % / 0.07 % (1.18 % / 0.74 %); (0.5, 0.25) 0.54 % / 0.10 %
    (1.14 % / 0.75 %); the package's (1, 0.5) 0.55 % / 0.15 % (1.13 % /
    0.76 %). The biases remove false shadow and add false lit (they move shadow
    edges towards the occluder); half the package's defaults keep the first at
    less of the second. (The full maps' means include far_point and
    large_world, whose shadows full maps lose.)

    Deviations from the paper, and why:

    * *Summed-area tables, not mipmaps.* The I3D paper filters the moments
      with hardware mipmapping / anisotropic filtering (and a separable blur);
      we use summed-area tables, as Lauritzen's GPU Gems 3 chapter does: an
      exact box of any width and aspect at O(1), no mip-level blending. They
      are float64 (the chapter uses fp32 with an offset, or integers) so that
      ``M2 - M1^2`` keeps its precision on 1024^2 and larger maps; the
      Chebyshev bound is evaluated in float64 too.
    * *Depth.* The paper stores the light-space distance; we store it
      normalised over the map's own finite depth span, ``[d_lo, d_hi]`` to
      ``[0, 1/2]`` (at least :data:`~.common.MIN_SPAN` of the depth wide), so
      the moments are bounded and ``min_variance`` is relative to the depths
      the light sees, independent of the scene's scale and of the light's
      distance. (Divided by twice the largest depth instead, as before, the
      floor grew with the distance: a spot 1e4 away over an 8-unit scene had
      ``sigma_min`` = 6 units and lost every shadow, 1.90 % misclassified
      against ``hard``'s 0.20 %; 0.20 % now.) Empty texels read ``z = 1`` and
      the receiver depth is clamped at 1, so empty texels never occlude, even
      a receiver far behind the map's deepest texel (a map too coarse to hold
      any surface, e.g. a light 1e6 units away: lit, as ``hard`` is); a
      receiver nearer than every texel has ``t < 0`` and is lit.
    * *Variance floor.* Besides ``min_variance`` the variance is never below
      :data:`VARIANCE_FLOOR` (1e-14, ``sigma = 1e-7``: 2e-7 of the depth span,
      at most the float32 resolution of a stored depth), so that round-off of
      the float64 box means cannot shadow a receiver level with the map when
      ``min_variance = 0``.
    * *Filter region.* The paper filters what the hardware's texture
      footprint covers; we filter the camera pixel's ray-differential
      footprint (as ``pcf`` does), never less than ``filter_size`` texels.
      Every camera sample filters the whole pixel, so at ``spp > 1`` edges
      are blurred over about two pixels (see ``pcf``).
    * *Cube maps* (point/area lights) are not in the paper: the box is
      clipped at the face's seams (its mean is taken over the part on the
      receiver's face), so near a seam the filter is narrower on one side.
    * *Biases.* The paper relies on ``min_variance`` alone for self-shadowing;
      the receiver additionally gets the package's scale-invariant slope and
      normal-offset biases (see above).
    * *Area lights* are treated as their centre point, as ``hard`` and ``pcf``
      do (VSM itself has no light size).
    * *Virtual maps* (``virtual=true``, the default): pages hold depths only, and the
      moments' box means are summed over the box's texels at lookup time (the same
      coverage-weighted means a summed-area table gives; the box is a few texels wide,
      as the level matches the pixel footprint). Depths are normalised over the scene's
      depth span as the light sees it (:func:`~.common.virtual_depth_scale`: ``z =
      (depth - d_lo) / (2 (d_hi - d_lo))``), not over the built pages' own span (which
      would change as camera moves build pages), and ``min_variance`` is scaled per
      texel
      (:func:`~.common.virtual_variance_factor`): at most the floor a 1024^2 map across
      the scene's depth span has per texel, smaller on finer levels (far_point, 1e5
      away over a 5e4-unit ground: 3.06 % misclassified with the span-relative floor,
      full maps 3.08 %).

    Known limitation (inherent to VSM): a receiver that is not level with the
    light inside a wide box (a tilted floor under a pixel footprint of many
    texels) has part of its own surface nearer the light than ``t``; where
    the box also holds an occluder, that part counts as occluding and the
    shadow edge moves a fraction of the box into the lit side (most of the
    false shadow above).
    """
    r = receiver(smap, lk, opts)
    act = mi.Bool(active) & r.inside
    m1, m2, t, floor = vsm_moments(smap, lk, r, opts.filter_size, act)
    p = chebyshev_upper_bound(m1, m2, t, opts.min_variance * floor, opts.light_bleeding)
    return dr.select(r.inside, mi.Float(p), 1.0)


# ------------------------------------------------------------------ layers
def moment_layer(smap, power: int) -> mi.Float64:
    """Summed-area table of ``z**power`` (``z``: :func:`~.common.normalized_depth`)."""
    z = normalized_depth(smap)[0]
    return summed_area_table(antialiased(smap, z if power == 1 else z * z),
                             smap.view.n_faces, smap.resolution)


METHOD = Method(
    name="vsm",
    lookup=vsm,
    summary="Donnelly & Lauritzen 2006 variance shadow maps: Chebyshev bound on "
            "summed-area-table moments of the pixel footprint",
    properties=(
        Prop("filter_size", "float", 2.0,
             "Minimum width of the filter box in texels per axis; the camera pixel's "
             "footprint widens it (O(1) lookups through summed-area tables on full maps; "
             "virtual maps sum the box's texels, at most 64 per side).", lo=0.0),
        Prop("min_variance", "float", 1e-7,
             "Lower clamp of the variance, in normalised depth squared (the depth span "
             "the light sees mapped to [0, 1/2]: sigma_min = 2 sqrt(min_variance) times "
             "the span; virtual maps scale it per texel).",
             lo=0.0, hi=1.0),
        Prop("light_bleeding", "float", 0.2,
             "Light-bleeding reduction amount a (Lauritzen 2007): "
             "p' = clamp((p - a) / (1 - a), 0, 1); 0 = the plain Chebyshev bound.",
             lo=0.0, hi=0.99),
    ),
    layers={"vsm_m1": lambda scene, smap: moment_layer(smap, 1),
            "vsm_m2": lambda scene, smap: moment_layer(smap, 2),
            "vsm_span": lambda scene, smap: span_layer(smap)},
    layers_for=lambda o: () if getattr(o, "virtual", False) else LAYERS,
    # the box: the pixel footprint (at most about 6 texels of a virtual level) or
    # filter_size, centred on the receiver; plus the nearest-texel margin
    virtual_margin=lambda o: 2.0 + 0.5 * max(o.filter_size, 6.0),
    virtual=True,
    layer_cost={"vsm_m1": 2.0, "vsm_m2": 2.0, "vsm_span": 0.0},   # float64 tables; 2 values
    needs_footprint=True,
    bias_defaults={"slope_bias": 0.5, "normal_bias": 0.25},
    builtin=True,
)
