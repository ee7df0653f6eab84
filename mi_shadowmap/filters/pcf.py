"""Percentage-closer filtering: Reeves, Salesin & Cook, "Rendering Antialiased
Shadows with Depth Maps", SIGGRAPH 1987 (``method="pcf"``).

Compare first, filter second: the shaded area's footprint is mapped into the
depth map, ``num_samples`` texels of that region are compared with the
receiver's depth, and the fraction that passes is the visibility.
"""
from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi

from ..methods import Method, Prop
from .common import Lookup, ReceiverPlane, Receiver, footprint_texels, own_texel, \
    plane_z_at, receiver, receiver_plane, smooth_taps, soft_compare_width, soft_tap, \
    tap_depths, tap_lit


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
             center_texel: mi.Point2f | None = None, active=True,
             soft_width=None) -> mi.Float:
    """Fraction of lit taps in a rectangle of the map (percentage-closer filtering).

    The rectangle is ``center_texel +- half_size`` (texels; default centre:
    the receiver, ``r.uv * resolution``) on the receiver's face, sampled by
    ``ns x nt`` taps (per-lane ``UInt32`` or ints) placed as in Reeves et al.
    1987, Figure 3:

    * ``'jitter'`` (c): one uniformly jittered tap per cell of an ``ns x nt``
      grid (stratified);
    * ``'regular'``: one tap at the centre of each cell (deterministic);
    * ``'uniform'`` (a): taps uniform over the whole rectangle;
    * ``'gaussian'`` (b): a normal distribution centred on the rectangle with
      ``sigma = half_size / 2``, truncated at the rectangle (+-2 sigma).

    ``bias_range = (bias0, bias1)``: each tap subtracts its own bias, uniform
    in that range (world units), from the receiver depth (Reeves' stochastic
    bias). Each tap is a :func:`tap_lit` comparison (off-map taps lit). The
    random numbers come from :func:`lane_rng` seeded by ``u_seed`` (one
    sampler draw per lookup). All taps run in one ``dr.while_loop``: one
    kernel whatever the sample count.

    ``soft_width`` (world depth, per lane; :func:`~.common.soft_compare_width`):
    each tap is the smooth :func:`~.common.soft_tap_lit` instead of the step,
    so the result is differentiable in the map and receiver depths; None:
    the step (:func:`~.common.tap_lit`), exactly as without it.
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

    col, row = mi.UInt32(0), mi.UInt32(0)   # tap k's cell, wrapped by hand (see below)

    def cond(k, col, row, rng, n_lit):
        return active & (k < n_taps)

    def body(k, col, row, rng, n_lit):
        xi = mi.Point2f(rng.next_float32(), rng.next_float32())
        if sampling == "jitter" or sampling == "regular":
            off = xi if sampling == "jitter" else mi.Point2f(0.5, 0.5)
            xy = lo + mi.Point2f(mi.Float(col) + off.x, mi.Float(row) + off.y) * cell
        elif sampling == "uniform":
            xy = lo + xi * (2.0 * half)
        else:
            z = dr.erfinv((2.0 * xi - 1.0) * _ERF_SQRT2) * math.sqrt(2.0)   # in [-2, 2]
            xy = center + z * (0.5 * half)
        bias = 0.0
        if bias_range is not None:
            bias = b0 + rng.next_float32() * (b1 - b0) if b1 > b0 else b0
        if soft_width is None:
            # own: a tap beyond the plane's near clamp takes the receiver's own texel's
            lit = tap_lit(smap, r, face, xy, plane, bias, active, own)
            n_lit = dr.select(lit, n_lit + 1, n_lit)
        else:
            z_map, z, inside = tap_depths(smap, r, face, xy, plane, active)
            # a tap moved by the light's pose compares each neighbour with its own plane
            # depth; for an occluder's motion the tap's depth gives the same gradient
            # (measured) in 7 % less time
            z_at = (plane_z_at(smap, plane, r, offset=bias)
                    if getattr(smap, "pose", None) is not None else None)
            n_lit = n_lit + soft_tap(smap, z_map, z - bias, inside, soft_width, face, xy,
                                     active, z_at=z_at, smooth=smooth)
        # k % ns and k // ns without an integer division by the per-lane ns: Dr.Jit 1.5's
        # LLVM backend divides the padding lanes of a vector too, by 0 (SIGFPE)
        last = col + 1 >= ns
        return k + 1, dr.select(last, 0, col + 1), dr.select(last, row + 1, row), rng, n_lit

    own = None     # the receiver's own texel: (z_map, inside), for a near_fallback plane
    if plane is not None and plane.near_fallback and soft_width is None:
        own = own_texel(smap, r, face, active)
    smooth = smooth_taps(smap, soft_width)   # continuous in the receiver's position
    if soft_width is not None:
        n_lit = mi.Float(0.0)
        # a sum of taps: Dr.Jit's sum-style reverse mode differentiates the symbolic
        # loop in place (no per-iteration state stored, no evaluated loop)
        k, col, row, rng, n_lit = dr.while_loop((k, col, row, rng, n_lit), cond, body,
                                                max_iterations=-1)
    else:
        k, col, row, rng, n_lit = dr.while_loop((k, col, row, rng, n_lit), cond, body)
    return mi.Float(n_lit) / mi.Float(dr.maximum(n_taps, 1))


def pcf(smap, lk: Lookup, opts, active=True) -> mi.Float:
    r"""Reeves et al. 1987, Figure 4 (``SampleShadow``), vectorised over lanes.

    **Region.** The shaded area is the camera pixel's footprint on the surface,
    ``p +- dp_dx/2 +- dp_dy/2``, where ``dp_dx``/``dp_dy`` come from Mitsuba's
    ray differentials intersected with the tangent plane at ``p`` and scaled
    by the integrator to *one whole pixel* (Mitsuba scales them by
    ``1/sqrt(spp)``; the integrator undoes that). Its four corners are
    projected onto the receiver's map face and the bounding box of their
    ``uv`` gives the region's widths in texels
    (:func:`~.common.footprint_texels`). Each width is multiplied by
    ``res_factor`` (Reeves' ``ResFactor``) and raised to at least ``min_size``
    texels (``MinSize``); the region is centred on the receiver's ``uv``.

    **Samples.** ``ns x nt`` samples per axis are chosen exactly as in Figure 4
    from ``num_samples`` and ``min_samples`` (:func:`~.common.reeves_sample_counts`):
    about one per texel for regions smaller than ``num_samples`` texels, else
    ``ns * nt ~ num_samples`` split in proportion to the region's aspect.
    ``sampling`` places them as in Figure 3: ``jitter`` (c, stratified: one
    jittered sample per cell, the default and the paper's choice),
    ``uniform`` (a) or ``gaussian`` (b). ``regular`` (not in the paper, which
    trades aliasing for noise with jitter) puts each sample at its cell's
    centre, the fixed grid of real-time PCF: the lookup is then deterministic,
    which is what a gradient wants. Measured on ``benchmarks/bench_gradients.py``'s
    area scene (``soft_compare`` 2, ``multijitter`` sampler), the standard
    deviation of a shadow gradient over seeds halves against ``jitter``
    (1.1e-4 to 5.1e-5); with the ``independent`` sampler the pixel positions'
    noise dominates and it does not change. Each sample compares its
    nearest texel with the receiver depth (:func:`~.common.tap_lit`); samples
    outside the map count as lit ("regions outside the light source's field
    of view are not considered to be in shadow"); the result is the fraction
    of lit samples, so it has at most ``ns * nt + 1`` levels.

    **Bias.** The receiver depth carries the package's biases (``bias``,
    ``slope_bias``, ``normal_bias``, see :func:`~.common.receiver`). With
    ``bias_range = (bias0, bias1)`` every sample additionally subtracts its
    own bias drawn uniformly from that range (Reeves' stochastic bias).

    **Randomness.** One ``sampler.next_2d()`` per lookup seeds a PCG32 stream
    per lane (:func:`~.common.lane_rng`); jitter offsets and stochastic biases
    are drawn from it inside the loop. All samples run in one
    ``dr.while_loop`` (one kernel for any ``num_samples``).

    Deviations from the paper, and why:

    * *Region from ray differentials.* The paper maps the shaded region
      (a micropolygon or pixel) into light space with the light's matrix; we
      map the pixel's ray-differential footprint on the tangent plane, which
      is the same region for a planar surface and what a ray tracer has.
    * *Region size.* Figure 4 samples ``s +- sres`` although its text calls
      ``sres`` the size of the rectangle and ``MinSize`` "the size in pixels
      of each dimension" ("MinSize 2 ... samples from at least four pixels").
      We follow the text: the region is ``res_factor * footprint`` texels
      wide (``sres`` = half of it), so ``res_factor=1`` filters exactly one
      pixel's footprint.
    * *Jitter.* The printed code adds ``Rand()*js`` (half a cell, one-sided)
      to each cell centre, which leaves half of every cell unsampled and
      shifts the pattern by a quarter cell; we jitter over the whole cell,
      as the text describes ("partition the bounding box into subregions and
      sample each one with jitter").
    * *Gaussian.* The paper gives no width; we use ``sigma = half-width / 2``,
      truncated to the region (+-2 sigma).
    * *Bias units and composition.* ``bias_range`` is in world units (the
      paper's were too, "(0.3, 0.4) in worlds of 100 units"); it is added to
      the package's texel-scaled slope/normal biases (set ``slope_bias=0,
      normal_bias=0`` for the paper's bias alone).
    * *Receiver plane* (``receiver_plane``, default on). The paper compares
      every sample with the single depth ``z`` of the shaded point, so a
      sloped receiver shadows itself over a wide region unless the bias is
      large. By default each sample is instead compared with the depth of the
      receiver's tangent plane along that texel's ray (clamped at
      ``max_tan_slope``); ``receiver_plane=false`` gives the paper's
      comparison. A tap whose ray meets the plane nearer than the clamp allows
      (``depth0 - lateral max_tan_slope``) takes the paper's comparison at the
      receiver's own texel (``hard``'s, with the tap's stochastic bias; the smooth
      compare keeps the clamp). Such a tap stands for the plane more than
      ``max_tan_slope`` times its distance away, beyond what the plane is trusted for,
      and the clamped depth, a point behind the plane, let surfaces behind it shadow
      it: where the light grazes a wall (``n . l`` < 0.05) the wall lies within a texel
      or two of its line in the map, and a kernel a texel wide (``min_size``) read the
      wall's own roof there. Measured against ``raytraced`` (128^2, 16 spp, virtual
      maps): 20 terrain worlds (``random_terrain_world``, seeds 0-29 with the sun 2-5
      or 80-89.5 degrees high) 3.11 -> 2.83 % misclassified summed, none worse (a tower
      under a sun 86 degrees high 0.18 -> 0.08 %, 355 -> 30 lit pixels below 0.9; one
      3 degrees high 0.24 -> 0.17 %; at 256^2 one of six 0.26 -> 0.27 %); the
      repository's scenes and random large worlds as before (a few pixels' values;
      ``benchmarks/RESULTS.md``, forty-fifth session). Time: as before. On a
      4096^2 full map the first tower's wall under its ledge, truly shadowed, is now lit
      like ``hard``'s (false lit 2.68 -> 2.92 %; ``hard`` 4.93 %): the clamp's false
      shadow had covered ``hard``'s miss there.
    * *Several samples per pixel.* Every camera sample filters a whole pixel's
      footprint, and the film then averages the samples over the pixel, so at
      ``spp > 1`` the shadow edge is blurred over about two pixels. Measured
      (spot_sphere_box-like default scene, 64^2 at 16 spp, 1024^2 map,
      visibility RMSE against 16-spp ray tracing): 0.028 with
      ``res_factor=1`` against 0.011 with ``res_factor=0.25 = 1/sqrt(spp)``
      (each sample filtering its own share of the pixel; ``hard``: 0.011).
      The default keeps Reeves' region (the pixel) as the issue specifies.
    * *Bounding box of finite depths* (a storage/culling optimisation) is not
      needed: texels with no surface hold ``+inf`` and are lit.
    * *Cube maps* (point/area lights) are not in the paper: on a full map samples
      that leave a cube face continue on the neighbouring face; on a virtual map they
      are clamped to their face (:func:`~.common.taps_cross_seams`), as ``pcss``'s
      are: the marks build each point's pages on its own face only, and a sample
      across the seam read the coarsest level there, a texel 4 times as wide whose
      depth lies in front of the receiver's plane (cbox_area's back wall beside the
      side walls, 81 pixels: 0.140 against ``raytraced``; clamped 0.061, full maps
      0.070). A clamped sample reads its face's border texel: an occluder seen only
      across the seam within the region is missed, an error bounded by the share of
      samples beyond the edge (a rod whose shadow lies just across a seam, 32^2 pixels
      0.03 wide: its lit side's pixels 0.007 off ``raytraced`` on average, at most
      0.036; crossing 0.002, at most 0.017; ``benchmarks/RESULTS.md``, fifty-third
      session, helper E).
    * *Smooth compare* (``soft_compare``, default 0 = the paper's step,
      bit-identical). With ``soft_compare = s > 0`` each sample is lit by
      ``smoothstep(1 + (z_map - z_receiver) / w)`` with
      ``w = s * texel_world`` (the world width of one map texel at the
      receiver, the unit of ``slope_bias``/``normal_bias``): fully lit where
      the step says lit, fully shadowed where the map is nearer than the
      receiver by ``w`` or more, a C1 ramp in between
      (:func:`~.common.soft_tap_lit`). It makes the visibility
      differentiable in the map's and the receiver's depths (issue 13,
      differentiable shadows), at the price of light leaking under
      occluders closer than ``w`` to the receiver (contact shadows lighten).
      A *silhouette's* motion across texels reaches the gradient through
      the map's antialiasing (property ``antialias``,
      :mod:`mi_shadowmap.antialias`): on such a map each tap blends the
      compares against its texel's surface and its neighbours' by their
      coverage (:func:`~.common.soft_tap`), and when the light's pose has
      gradients a tap's motion across texels is differentiated through the
      bilinear interpolation of its four texels' compares (values stay the
      nearest texel's). In a gradient render (the map in the AD graph) every
      tap's whole derivative is that bilinear one, so it is continuous in the
      receiver's position: the integrator's ``gradient_at='pixel_centre'``
      samples it at the pixels' centres, where the nearest texel's
      derivative aliased against the texel grid (regular taps: 12 % off).
    """
    res = smap.resolution
    r = receiver(smap, lk, opts)
    width = footprint_texels(smap, lk, r) * opts.res_factor
    width = dr.maximum(width, opts.min_size)
    ns, nt = reeves_sample_counts(width.x, width.y, opts.num_samples, opts.min_samples)
    u_seed = lk.sampler.next_2d(active)
    plane = (receiver_plane(smap, lk, r, opts, near_fallback=opts.soft_compare <= 0.0)
             if opts.receiver_plane else None)
    lit = pcf_taps(smap, r, 0.5 * width, ns, nt, u_seed, opts.sampling, opts.bias_range,
                   plane, r.uv * res, active & r.inside,
                   soft_compare_width(r, opts.soft_compare))
    return dr.select(r.inside, lit, 1.0)


def _finalize(values: dict, given) -> None:
    """Reeves' CLAMP(n, MinSamples, NumSamples): ``min_samples <= num_samples``; the
    default MinSamples (2) never exceeds NumSamples."""
    from ..options import OptionError
    if "min_samples" in given:
        if values["min_samples"] > values["num_samples"]:
            raise OptionError(f"shadowmap: property 'min_samples' = {values['min_samples']} "
                              f"must be <= 'num_samples' = {values['num_samples']}")
    else:
        values["min_samples"] = min(values["min_samples"], values["num_samples"])


def _virtual_margin(opts) -> float:
    """How far from a receiver's texel, at its pixel footprint's level, the taps of its
    region reach (the mark pass's margin, :mod:`mi_shadowmap.virtual`): ``hard``'s 2
    texels (the nearest texel, the normal offset), half of ``min_size`` and half the
    region, ``res_factor`` times the footprint's longer side. A level's texel is over
    ``2^(lod_bias - 1)`` of the footprint's shorter side, or of half its longer one if
    that is more (:meth:`~mi_shadowmap.virtual.VirtualShadowMap.level_for`, ``ANISO``
    2; at level 0 the footprint is under ``2^(1 - lod_bias)`` texels too), so the longer
    side spans under ``2^(2 - lod_bias)`` texels there: half the region is under
    ``res_factor 2^(1 - lod_bias)`` texels, 2.83 at the default ``lod_bias`` -0.5
    (``4 res_factor`` before: 1.4x that at the default, short of it at a ``lod_bias``
    finer than -1; ``lod_bias`` as :func:`~mi_shadowmap.virtual.lookup.
    effective_lod_bias` reads it). The camera samples' offsets within a pixel are the
    mark pass's (:func:`mi_shadowmap.virtual.marks._margins`): beside a pixel's centre
    the neighbouring pixels' marks reach as far, and a film-border pixel's marks reach
    half its footprint farther (``virtual_footprint``). A level the receiver biases chose
    finer than the footprint's is marked from the footprint's box there (``spread``),
    with the region ``res_factor`` times that box
    (:func:`~mi_shadowmap.virtual.marks._tile_range`).
    With the kept points' rings only where a neighbour reads their level,
    ``random_terrain_world(22)`` at 256^2: 8.48 -> 7.91 texels a film pixel, 123: 9.45 ->
    8.62, misclassified as before but for one pixel at 0.5 (``benchmarks/RESULTS.md``,
    the forty-ninth session, helper A)."""
    from ..virtual.lookup import effective_lod_bias
    lod_bias = effective_lod_bias(opts.lod_bias, opts.page_size)
    return 2.0 + opts.res_factor * 2.0 ** (1.0 - lod_bias) + 0.5 * opts.min_size


SOFT_COMPARE = Prop(
    "soft_compare", "float", 0.0,
    "Smooth depth compare for gradients (issue 13): 0 = the step (exactly as without it); "
    "s > 0: a tap whose map depth is nearer than the receiver by d is lit by "
    "smoothstep(1 - d / w), w = s x the world width of one map texel at the receiver "
    "(the unit of slope_bias), so visibility is differentiable in map and receiver "
    "depths; occluders within w of the receiver leak light.", lo=0.0, hi=1e6)

RECEIVER_PLANE = Prop(
    "receiver_plane", "bool", True,
    "Compare each PCF tap against the receiver's tangent plane at that texel instead of "
    "the shading point's single depth (receiver-plane depth bias; not in Reeves 1987 or "
    "Brabec & Seidel; false gives their single-depth comparison).")

METHOD = Method(
    name="pcf",
    lookup=pcf,
    summary="Reeves et al. 1987 percentage-closer filtering of the pixel footprint",
    properties=(
        Prop("num_samples", "int", 16, "Samples of the PCF region (Reeves' NumSamples).",
             lo=1, hi=4096),
        Prop("min_samples", "int", 2, "Minimum samples per axis (Reeves' MinSamples); at "
             "most num_samples (the default is min(2, num_samples)).", lo=1, hi=64),
        Prop("res_factor", "float", 1.0, "Scale of the pixel footprint (Reeves' ResFactor).",
             lo=0.0, lo_open=True),
        Prop("min_size", "float", 1.0,
             "Minimum region size in texels per axis (Reeves' MinSize).", lo=0.0),
        Prop("sampling", "str", "jitter", "Sample placement in the region (Reeves Fig. 3; "
             "'regular': cell centres, deterministic).",
             choices=("jitter", "regular", "uniform", "gaussian")),
        Prop("bias_range", "pair", None,
             "Stochastic bias [bias0, bias1] in world units, drawn per sample (Reeves).",
             lo=0.0),
        RECEIVER_PLANE,
        SOFT_COMPARE,
    ),
    needs_footprint=True,
    needs_curvature=True,      # the receiver plane's bend on concave receivers
    finalize=_finalize,
    virtual_margin=_virtual_margin,
    virtual_footprint=lambda o: o.res_factor,     # the region: res_factor footprints
    virtual=True, builtin=True,
)
