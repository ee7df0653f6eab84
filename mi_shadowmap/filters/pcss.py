"""Percentage-closer soft shadows (``pcss``): Fernando 2005, after the PCSS thesis.

Source: the PCSS thesis (``papers/002_3c13a5335145be05.txt``, sec. 2.1.5,
4.3 and 5.1) describing R. Fernando, "Percentage-Closer Soft Shadows"
(NVIDIA, 2005). Three steps per shading point:

1. **Blocker search.** ``blocker_samples`` taps over a region of the map
   whose size comes from the light size and the receiver depth by similar
   triangles: a blocker at depth ``d`` can only shadow the receiver (depth
   ``d_r``) if it lies within ``w_light (d_r - d) / (2 d)`` of it, measured
   in world units on the receiver's plane; the region uses the nearest
   depth ``d_near`` of the receiver's map face (Fernando uses the light's
   near plane). Texels nearer than the receiver (plane) are blockers; their
   depths are averaged into ``d_blocker``.
2. **Penumbra estimate.** ``w = (d_r - d_blocker) * w_light / d_blocker``
   (thesis eq. 2), with ``d_blocker`` clamped to ``>= 1e-3 d_r`` (the guard
   for ``d_blocker -> 0``). No blocker found: the point is lit and the
   filter is not run (its loop is inactive for that lane).
3. **Filtering.** PCF (Reeves 1987) over a kernel of width ``w`` (in texels:
   ``w`` divided by the world size of a texel at the receiver, measured
   parallel to the map plane, i.e. at the receiver's axial depth), with
   ``filter_samples`` taps, capped as below ("Kernel cap").

Light size ``w_light``: the ``light_size`` property when given (a square of that
width), otherwise, for a planar area light (a rectangle, a disk, a planar mesh), the
light's own parallelogram as each receiver sees it across its map face
(:func:`_light_shape`, see "Light shape" below), and for any other area light the size
derived from its shape (:func:`~mi_shadowmap.light_views.area_light_size`); point and spot lights
have size 0 unless ``light_size`` > 0 (then they are treated as a square
light of that width at their position, like Godot's light size).
Directional lights use ``angular_diameter`` (degrees): with ``s = 2
tan(angular_diameter / 2)`` the formulas become ``w = (d_r - d_blocker) s``
and the search half-width ``(d_r - d_near) s / 2`` (depths from the map
plane). With a light size of 0, PCSS degenerates to one-tap hard shadows.

Tap patterns (``pattern``): ``'stratified'`` -- a square grid of
``ceil(sqrt(n))`` columns over the square kernel, toroidally shifted by a
per-camera-sample random offset (each tap is uniform, the set stays
stratified); ``'poisson'`` -- a fixed Poisson disk (dart throwing) over the
inscribed disk, rotated per camera sample. Both loops are ``dr.while_loop``.

Deviations from the paper and why:

* **Receiver-plane depth bias.** Each tap is compared with the depth at
  which its texel's light ray meets the receiver's tangent plane (clamped to
  ``max_tan_slope`` times the tap's lateral distance), not with the single
  receiver depth: with kernels tens of texels wide, the single depth makes
  tilted receivers shadow themselves (RMSE 0.11 vs 0.025 in the project's
  prototype). The receiver's usual biases are kept on top. A tap whose ray meets
  the plane nearer than the clamp allows (``depth0 - lateral max_tan_slope``) takes,
  in both steps, the paper's compare at the receiver's own texel (as in ``pcf``,
  :attr:`~.common.ReceiverPlane.near_fallback`; the smooth compare keeps the clamp):
  the clamped depth, a point behind the plane, made surfaces behind the receiver's
  plane, which cannot occlude it from the light's side, blockers and shadowing taps;
  where a sun grazes a wall (``n . l`` < 0.05) the search region and the kernel reach
  the texels of the wall's own roof. Measured against ``raytraced`` (a point sun: the
  only reference at hand; 128^2, 16 spp, ``angular_diameter`` 0.53): a tower under a
  sun 86 degrees high (``random_terrain_world(17)``) 471 -> 24 lit pixels below 0.9
  but 0.35 -> 0.39 % misclassified (false lit 0.08 -> 0.37: the wall under the
  tower's ledge, in its shadow, lit like ``hard``'s, 0.40: the false shadow had
  covered ``hard``'s miss there, as in ``pcf``); 8 terrain worlds summed 1.08 -> 1.09 %
  (virtual), 19.07 -> 19.18 % (full 4096^2); ``benchmarks/RESULTS.md``, forty-fifth
  session, helper D. At ``angular_diameter`` 0 (the default) PCSS is ``hard``. Not
  for an environment's regions, which keep the clamp: sky_sun (128^2, virtual) came
  out RMSE 0.0698 -> 0.0715 against ``raytraced``, mean visibility 0.6845 -> 0.6891
  (the reference's 0.6778), misclassified unchanged, 9881 pixels' values changed.
* **Search-region near depth** is the nearest depth stored in the
  receiver's map face (a per-face ``d_near``, the map layer ``pcss_near``),
  not a user near plane: this keeps the region as small as the scene allows
  without a new parameter.
* **Kernel cap.** The thesis' GLSL clamps both kernels by a fixed range table;
  Fernando's uv-space kernels are not clamped. Here the search region and the
  filter kernel keep their world width up to ``max_kernel`` texels of the map or
  ``max_kernel / 512`` of the face's width (:data:`KERNEL_REF_RES`), whichever is
  wider: a cap in texels alone shrinks in world units as the map gets denser (a
  bigger ``resolution``, or a virtual map's finer level under a larger film or a
  closer camera), and a penumbra many pixels wide came out as ``hard``. Below
  ``KERNEL_REF_RES`` texels a face the cap is still ``max_kernel`` texels, a larger share
  of the face, so it halves in world units from 256 to 512 texels: a fence 1.8 high under a
  1.6-wide rectangle light 3 above the ground (64^2, 16 spp, 2 seeds) has RMSE
  0.025 at 256 and 0.047 at 512-1024 (its penumbrae span 1/4 of the face; ``max_kernel``
  128: 0.025). Not changed: ``KERNEL_REF_RES`` 256 gives that scene 0.024 but raises
  a ball under a square light from 0.023 to 0.027 and cbox_area from 0.041 to 0.048
  (PCSS's overestimated penumbrae, which the tighter cap trims). A filter
  kernel wider than ``max_kernel`` texels (on a virtual map: than ``min(max_kernel,
  page_size)`` texels, what a level's marks reach) is filtered, with the same taps, on
  a virtual map at the level ``2^k`` times coarser where it fits (the
  mark pass builds those levels' tiles around each point, down to 512 texels a face,
  at most 8 levels: ``virtual_coarse_res``; not for an environment's regions, whose
  wide kernels the plain cap regularises better: they keep their own level, capped at
  ``page_size / 2 - 1`` texels, within the 2 x 2 pages a lookup binds, whose tiles the
  mark pass builds), on a full map with its taps spread
  over it (the same ``filter_samples``, strided across the texels). A virtual map's
  blocker search reads at most one level coarser than the receiver's
  (:data:`SEARCH_COARSER`): a region sized from the face's nearest depth can be far
  wider than any penumbra, and coarser levels lose thin blockers (large_world with the
  sun's angular diameter, 96^2: RMSE 0.120 on its own level, 0.124 one level coarser,
  0.149 up to 8). The cap in face
  width keeps ``max_kernel``'s regularising role on wide search regions: searching
  a whole face (the region of a receiver whose face holds a blocker next to the
  light, e.g. cbox_area's walls under the ceiling) finds false blockers (cbox_area,
  64^2, 1024^2 map, 3 seeds: RMSE 0.0567 without a cap, 0.0505 with it, 0.0518
  before with 64 texels). Measured (64^2, 16 spp, RMSE
  against the converged reference): contact_hardening zoomed onto plate B's
  penumbra 2x/4x/8x, virtual maps 0.069/0.160/0.093 before, 0.024/0.025/0.026 now
  (multiview 0.023-0.026); full maps of 1024-4096 texels 0.044/0.108/0.142 before,
  0.027-0.028 now (512: 0.027).
  On a virtual map under a light with extent (not a directional light's angular
  diameter, not an environment's regions) the filter kernel's cap is at least half the
  light's width ``w_light`` on the receiver's plane (:func:`_light_width_cap`): the
  penumbra of a blocker halfway between the receiver and the light, what the light's
  size produces rather than a share of the face. A kernel beyond the face-width cap
  reads the coarser levels, down to :data:`LIGHT_COARSE_RES` texels a face, whose tile
  under its point this frame's marks built (:func:`_built_beyond`; the levels the mark
  pass builds for other points, their own and their kernels'); the mark pass builds no
  level for it. A virtual map's levels are always
  :data:`KERNEL_REF_RES` or more texels a face, so the face-width cap alone (1/16 of a
  face) filtered a disk light 4 wide 5.6 over the ground (``bench_unseen``'s ``area``
  seed 7, 128^2, 4 spp, against 16-ray ``raytraced``) as a near-hard shadow: 5.98 %
  misclassified, now 1.76 % (256^2: 5.88 -> 1.66 %, 512^2: 5.58 -> 1.35 %), with the
  texels built unchanged. Marking the
  coarser levels for these kernels cost every area light's ``pcss`` 10-25 % more texels
  around every point (``wip/pcss-light-cap-51H``), 8-23 % per point from the light's
  width (``wip/pcss-light-levels-51I``), 0-4.4 % per point from the blockers five rays
  to the light find (``wip/pcss-blocker-marks-52D``), for the same accuracy
  (``benchmarks/RESULTS.md``, fifty-first and fifty-second sessions). The cost: where
  PCSS overestimates the penumbra (rectangle lights 3 wide over a ball, ``area`` seeds 1
  and 13) the face-width cap had trimmed it; at 256^2 they misclassify 0.4-0.5 points
  more (false lit), within their seed noise at 128^2. Full maps keep the face-width
  cap: there the light-width cap fixed that scene (1024^2: 5.80 -> 1.65 %)
  but raised a 3-wide rectangle light 2.9 over a 1.3-wide ball (``area`` seed 1, where
  PCSS overestimates the penumbra and the cap trims it) 1.41 -> 2.36 % at 256^2 (its
  seed noise 0.4; fifty-first session, helper H).
  A widened kernel whose level is not built under its point keeps its world width at the
  coarsest level that is (:data:`KEEP_KERNEL_WIDTH`; its taps beyond the tiles marked
  there read what any far tap reads: the neighbouring points' pages, else the coarsest
  level), not ``max_kernel`` texels of it, which had made the penumbra near-hard wherever
  the levels are fine (64^2, 4 spp: ``lod_bias`` -4 3.37 -> 1.59 % misclassified, 2.54 ->
  0.20 % false shadow; ``max_kernel`` 1 5.96 -> 1.59 %; 128^2: ``lod_bias`` -4 5.72 ->
  1.46 %, ``page_size`` 16 2.21 -> 1.70 %, 256^2 3.95 -> 1.79 %; the texels built equal;
  ``benchmarks/RESULTS.md``, fifty-third session, helper B). The light's width these
  kernels' estimate takes is at most twice the receiver's distance from it, the width a
  cube face spans there (:func:`_light_seen`): a rectangle light 1200 wide 8 above a
  12-wide ground (100 times it) gave a blocker 1 unit tall a penumbra ~170 units wide and
  left the ground nearly unshadowed, 8.06 % misclassified (RMSE 0.1785) against 6.71 %
  (0.1414) with the face-width cap alone, now 6.79 % (0.1491) at 64^2 (128^2: 7.67 -> 6.84
  %, cap off 6.19 %; 256^2: 6.85 -> 6.87 %, 6.22 %; RMSE 0.1748 -> 0.1612 and 0.1670 ->
  0.1553, cap off 0.1490 and 0.1469): not all the way back: 13.6 % of its filter taps
  (128^2) read the coarsest level, no finer one being built there (marking the levels down
  to 64 texels a face, 12 % more texels: 6.20 %); lights no wider than twice their
  distance (every other light measured) are unchanged.
* **Map borders.** Taps use the PCF tap helper
  (:func:`~.common.tap_depths`): taps off a spot/directional map are lit and
  are not blockers, as in ``pcf``. Unlike ``pcf`` on a full map, taps beyond a *cube* face
  are clamped to the receiver's face instead of continuing on the
  neighbouring face: crossing the seams was measured slightly worse
  (cbox_area, 64^2, 256^2 maps, 4 seeds: RMSE 0.09690 vs 0.09678 against the
  converged reference; the 17 changed pixels are concave wall corners lying
  on a seam, where the neighbouring wall lies in front of the receiver's
  extended tangent plane and becomes a false blocker -- the single receiver
  plane's concave-corner artefact, which clamping happens to hide there).
* **Sample pattern.** Fernando's fixed Poisson disk is the ``'poisson'``
  option; the default ``'stratified'`` pattern gave lower error in the
  project's measurements (see mitsuba-facts.md).
* **Behind the light.** For a planar one-sided area light, texels whose
  ray leaves the light's centre behind its emitting plane are neither
  blockers nor shadowing taps (nothing behind the light can occlude it):
  this removes false blockers where walls meet a ceiling the light hangs
  under. Not in the paper, which has no light geometry beyond its width.
* **Light shape.** Fernando's light is a square parallel to the map, one ``w_light``. A
  planar area light here is its own parallelogram (:func:`_light_shape`): both steps'
  taps are mapped from the square pattern onto the light's two half-axes as the receiver
  sees them across its map face (each light point's offset across the face minus its
  offset along the face's axis times the receiver's tangent coordinates, the similar
  triangles with the light point off the map's plane), scaled by the same
  similar-triangles ratio: an anisotropic kernel, where the paper's is square. Why: the
  square of the light's area (0.35 for a strip 6 x 0.02) gave a strip's penumbra far too
  narrow along it and far too wide across it, on every face alike, also those that see
  the light edge-on. Measured (``benchmarks/RESULTS.md``, fifty-fifth session, helper A;
  128^2, 64 spp, 2 render seeds, RMSE against ``raytraced`` with 64 shadow rays, virtual
  / full): strip 6 x 0.02 0.116 -> 0.071 / 0.116 -> 0.067, strip 4 x 0.08 0.078 -> 0.053
  / 0.078 -> 0.048, rectangle 4:1 0.049 -> 0.046 / 0.049 -> 0.041, the strip turned 45
  degrees 0.152 -> 0.083 / 0.152 -> 0.072, a square 0.027 -> 0.026 / 0.026 -> 0.025,
  cbox_area and contact_hardening unchanged to 1e-4. Misclassified at 0.5 falls with
  them (strip 6 x 0.02 1.64 -> 1.50 / 1.58 -> 1.42 %) but for the turned strip on a
  virtual map, 1.91 -> 2.03 % (full 1.83 -> 1.44 %: false light where PCSS's one blocker
  depth shrinks the umbrae of a ball and a plate, which the near-hard square kept dark).
  The parallelogram's bounding box (no shear) and the light's axes projected on the face
  without the axial term were worse (virtual maps, misclassified on the square / the
  strip 6 x 0.02: 0.99 / 1.88 % and 0.63 / 1.83 %, against 0.62 / 1.50 % with both).
* **Light geometry.** The depth map is rendered from the light's centre, so
  penumbrae are estimated from one view (the usual PCSS assumption): the
  blocker average takes occluders' front faces, which shrinks umbrae.
* **Smooth compare** (``soft_compare``, default 0 = the step, bit-identical;
  issue 13). With ``soft_compare = s > 0`` every tap of both steps is smooth,
  with ``w = s * texel_world`` (the world width of one map texel at the
  receiver, the unit of ``slope_bias``), so the visibility is differentiable in
  the map's depths, the receiver's and the occluder's outline:

  - a *filtering* tap (step 3) is lit by ``smoothstep(1 + (z_map - z_plane) /
    w)``, as in ``pcf`` (:func:`~.common.soft_tap_lit`);
  - a *blocker-search* tap (step 1) counts as a blocker by ``1 -`` that
    (:func:`~.common.soft_blocker`). On an antialiased map each surface in the
    texel counts with its coverage and its own depth, so a silhouette texel
    enters the average with the occluder's depth and a weight growing from 0.
    Counts are then fractional: ``d_blocker`` is the weighted mean, and with
    less than one blocker's worth found the shadow is scaled by the count
    (``1 - (1 - V) n``), so visibility is continuous as the first blocker
    enters the region;
  - taps that move (the search region follows the face's nearest depth, the
    kernel the blocker depth) are differentiated through their bilinear
    neighbours (:func:`~.common.soft_tap`).

  Measured (``benchmarks/RESULTS.md``, area scene, 128^2, 16 spp): the
  sideways gradient's mean is 0.4 % off the ray-traced derivative, and its AD
  matches PCSS's own central differences (cosine 0.998-0.999 over the
  occluder's corners, sideways and along the light). Along the light PCSS's
  own derivative is small and positive where ray tracing's is small and
  negative (+1.2e-5 against -2.7e-5, 1/500 of the sideways one), like the
  exact derivative of any visibility factor (``raytraced`` with
  ``light_sample='independent'``: +1.2e-5): not its gradient's error. Before
  the smooth blocker search the AD
  came out 4x too large there and disagreed with the differences: a
  silhouette texel entered the blocker average at once, with the blended
  depth of occluder and ground. A light of size 0 stays ``hard`` (no smooth
  compare). Occluders within ``w`` of the receiver leak light; a silhouette's
  motion across texels reaches the gradient through the map's antialiasing
  (property ``antialias``).
"""
from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi

from ..methods import Method, Prop
from .common import (Lookup, Receiver, ReceiverPlane, own_texel, plane_z_at, receiver,
                     receiver_plane,
                     shifted_grid_point, smooth_taps, soft_blocker, soft_compare_width, soft_tap,
                     tap_depths)
from .hard import hard
from .pcf import SOFT_COMPARE


def face_near_layer(scene, smap) -> mi.Float:
    """Layer ``pcss_near``: the nearest depth of each face (``n_faces`` entries, one
    per face, not per texel; ``+inf`` for an empty face): the per-face near depth
    of the blocker-search region."""
    return dr.block_reduce(dr.ReduceOp.Min, smap.depth, smap.resolution * smap.resolution)


def face_near_depth(smap) -> mi.Float:
    """Nearest finite depth of each face of ``smap`` (``n_faces`` entries).

    The map layer ``pcss_near`` (built and cached by the map manager like every
    layer of the record); computed on the spot for a map built without it
    (e.g. by :func:`~mi_shadowmap.depth_maps.build_depth_map` alone).
    """
    near = smap.extra.get("pcss_near")
    return face_near_layer(None, smap) if near is None else near


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


def _own_texel(smap, r: Receiver, plane: ReceiverPlane, active, soft_width):
    """:func:`~.common.own_texel` for a step compare with a ``near_fallback`` plane
    (what its taps beyond the near clamp compare), else None."""
    if soft_width is not None or plane is None or not plane.near_fallback:
        return None
    return own_texel(smap, r, r.face, active)


def blocker_search(smap, lk: Lookup, r: Receiver, plane: ReceiverPlane, half_texels: mi.Float,
                   n: int, pattern: str, rnd: mi.Point2f, active, soft_width=None,
                   shape=None):
    """PCSS step 1 (Fernando 2005): mean depth of the blockers in a search region.

    ``n`` taps (``tap_offset`` pattern) over the region of half-width
    ``half_texels`` around the receiver; a texel is a blocker when its depth
    is below the receiver plane's depth there (:func:`tap_depths`: taps off
    a perspective/orthographic map are not blockers; cube taps are clamped to
    the receiver's face, see :mod:`.pcss`).

    Returns ``(sum of blocker depths, number of blockers)``; one
    ``dr.while_loop``. ``soft_width``: each tap counts as ``1 -`` its smooth
    compare, coverage-blended on an antialiased map (:func:`~.common.soft_blocker`),
    so both sums are continuous; None: the step. ``shape``: the light's shape
    (:func:`_light_shape`) that maps each tap's offset, else the square.
    """
    k = mi.UInt32(0)
    z_sum = mi.Float(0.0)
    count = mi.Float(0.0)
    active = mi.Bool(active)

    def cond(k, z_sum, count):
        return active & (k < n)

    centre = r.uv * smap.resolution
    own = _own_texel(smap, r, plane, active, soft_width)

    def body(k, z_sum, count):
        off = _shaped(tap_offset(k, n, pattern, rnd), shape) * half_texels
        z_map, z, inside = tap_depths(smap, r, r.face, centre + off, plane, active,
                                      cross_seams=False, lateral_texels=dr.norm(off))
        if soft_width is not None:
            b, bz = soft_blocker(smap, z_map, z, inside, soft_width, r.face, centre + off,
                                 active, cross_seams=False,
                                 z_at=plane_z_at(smap, plane, r, dr.norm(off)))
            return k + 1, z_sum + bz, count + b
        blocked = inside & (z_map < z)
        if own is not None:     # beyond the plane's near clamp: the receiver's own texel
            beyond = dr.isnan(z)
            blocked = dr.select(beyond, own[1] & (own[0] < r.depth), blocked)
            z_map = dr.select(beyond, own[0], z_map)
        return k + 1, z_sum + dr.select(blocked, z_map, 0.0), count + dr.select(blocked, 1.0, 0.0)

    # sums of taps: Dr.Jit's sum-style reverse mode differentiates the symbolic loop in
    # place (the integrator's SYMBOLIC_BACKWARD)
    k, z_sum, count = dr.while_loop((k, z_sum, count), cond, body, max_iterations=-1)
    return z_sum, count


def pcf_plane(smap, lk: Lookup, r: Receiver, plane: ReceiverPlane, half_texels: mi.Float,
              n: int, pattern: str, rnd: mi.Point2f, active, soft_width=None,
              shape=None) -> mi.Float:
    """Percentage-closer filtering with receiver-plane depths (PCSS step 3).

    Fraction of ``n`` taps (``tap_offset`` pattern, half-width
    ``half_texels``) that are lit (:func:`tap_depths` against the receiver
    plane's depth; off-map taps lit, cube taps clamped to the receiver's
    face as in :func:`blocker_search`); one ``dr.while_loop``. ``soft_width``:
    smooth taps (:func:`~.common.soft_tap_lit`), None: the step. ``shape``: as in
    :func:`blocker_search`.
    """
    k = mi.UInt32(0)
    lit = mi.Float(0.0)
    active = mi.Bool(active)
    smooth = smooth_taps(smap, soft_width)   # continuous in the receiver's position

    def cond(k, lit):
        return active & (k < n)

    centre = r.uv * smap.resolution

    own = _own_texel(smap, r, plane, active, soft_width)

    def body(k, lit):
        off = _shaped(tap_offset(k, n, pattern, rnd), shape) * half_texels
        z_map, z, inside = tap_depths(smap, r, r.face, centre + off, plane, active,
                                      cross_seams=False, lateral_texels=dr.norm(off))
        if soft_width is not None:
            return k + 1, lit + soft_tap(smap, z_map, z, inside, soft_width, r.face,
                                         centre + off, active, cross_seams=False,
                                         z_at=plane_z_at(smap, plane, r, dr.norm(off)),
                                         smooth=smooth)
        hit = ~inside | (z <= z_map)
        if own is not None:     # beyond the plane's near clamp: the receiver's own texel
            hit = dr.select(dr.isnan(z), ~own[1] | (r.depth <= own[0]), hit)
        return k + 1, lit + dr.select(hit, 1.0, 0.0)

    k, lit = dr.while_loop((k, lit), cond, body, max_iterations=-1)   # a sum, as above
    return lit / n


def _shaped(offset: mi.Point2f, shape) -> mi.Point2f:
    """A tap's ``offset`` (units of the kernel's half-width) mapped through the light's
    ``shape`` (:func:`_light_shape`: its two columns), or kept (``shape`` None: the
    square)."""
    if shape is None:
        return offset
    a, b = shape
    return mi.Point2f(a.x * offset.x + b.x * offset.y, a.y * offset.x + b.y * offset.y)


def _light_shape(smap, r: Receiver, p_world, texel):
    """``(w_light, shape, fit)`` of a planar area light seen from the receiver, per lane, or
    None (the square of :func:`~mi_shadowmap.light_views.area_light_size`: a light
    that is not planar, or not an area light).

    The light's half-axes ``e_1, e_2`` (:func:`~mi_shadowmap.light_views.
    area_light_axes`) as the receiver sees them across the map face's plane: each
    light point ``c + L`` moves the receiver's blocker region by ``L_perp - uv L_axial``
    (``uv`` the receiver's tangent coordinates on the face, ``L_axial`` along the face's
    axis: the similar triangles of the module docstring with the light point off the
    map's plane, to first order in ``L / d``), which is the map's
    :meth:`~mi_shadowmap.light_views.base.LightView.uv_differential` of ``L`` at the
    receiver, in world units there (``res`` texels of width ``texel``). ``w_light`` is
    twice the larger of that parallelogram's half-extents along the face's two axes, so
    every cap, level and mark sized from it still holds the kernel (they are PCSS's
    scalar light width); ``shape`` its two columns over that half-width (per-axis
    extents at most 1), which :func:`_shaped` applies to every tap; ``fit``, that
    half-width over the longer half-axis (per lane), by which a full map's kernel cap
    grows, so that it bounds the light's longer half-axis as it bounded the square's
    half-side, whatever the light's turn on the face: capping the half-extent instead
    shrank a tilted disk 4 wide's penumbrae (``bench_unseen``'s ``area`` seed 7, full
    256^2, 4 spp: 2.14 % misclassified with the square, 5.13 % so, 1.99 % with ``fit``;
    with ``max_kernel`` 256, no cap reached, 2.15 % and 2.04 %). A virtual map's cap
    grows by no more than 1 (``fit`` < 1 only trims it: a strip along a face's diagonal,
    128^2, 64 spp, 2.37 -> 2.03 %): its marks and levels hold the half-extent's reach.

    Deviation from Fernando 2005, whose light is a square parallel to the map (one
    ``w_light``; this module read every area light as the square of its area): the
    search region and the filter kernel take the light's own parallelogram, scaled by
    the same similar-triangles ratio along both axes. A strip light 6 x 0.02 read as a
    0.35 square had a penumbra far too narrow along the strip and far too wide across it
    (``pcss`` 1.10 % misclassified, as ``hard``; a face that sees the light edge-on saw
    the same square). A square light seen face-on gives ``w_light`` its side and the
    identity shape (to rounding: ``sqrt(area)`` before)."""
    view = smap.view
    axes = getattr(view, "light_axes", None) if getattr(view, "kind", None) == "area" \
        else None
    if axes is None:
        return None
    from ..light_views.base import opaque_point
    res = smap.resolution if isinstance(smap.resolution, int) else mi.Float(smap.resolution)
    cols = [view.uv_differential(r.face, p_world, mi.Vector3f(opaque_point(e))) * res * texel
            for e in axes]
    a, b = (mi.Point2f(c) for c in cols)
    half = dr.maximum(dr.maximum(dr.abs(a.x) + dr.abs(b.x), dr.abs(a.y) + dr.abs(b.y)), 1e-30)
    inv = dr.rcp(half)
    fit = half / dr.maximum(dr.maximum(dr.norm(a), dr.norm(b)), 1e-30)
    return 2.0 * half, (a * inv, b * inv), fit


#: Whether ``pcss`` reads a planar area light's own shape (:func:`_light_shape`) rather
#: than the square of its area.
LIGHT_SHAPE = True


def _spread(d_r, d, w_light, angular, depth_origin=0.0):
    """World width on the receiver's plane of the light seen past depth ``d``; depths
    as the map measures them, ``depth_origin`` short of the light (a far light's
    virtual map, :attr:`~mi_shadowmap.light_views.base.LightView.depth_origin`): the
    difference stays exact, the ratio takes the distance from the light."""
    if angular:
        return (d_r - d) * w_light
    if isinstance(depth_origin, float) and depth_origin == 0.0:
        return (d_r - d) * w_light / d
    return (d_r - d) * w_light / (d + depth_origin)


def _texel_parallel(smap, r, p_world):
    """World width of a texel at the receiver, measured parallel to the map plane
    (``mi.Float``; a ``mi.Point2f``, per map axis, on a rectangular face, whose
    kernels are then as many texels along each axis as its world width spans there).

    PCSS's similar triangles hold between planes parallel to the light (and to
    the map's image plane): a width ``w`` there spans ``w / z`` in tan units,
    ``z`` being the receiver's *axial* depth along the face's view axis (not
    its Euclidean distance, which would shrink off-axis kernels by cos theta).
    """
    xy = getattr(smap.view, "texel_parallel_xy", None)
    xy = None if xy is None else xy(smap.resolution, r.face, p_world, r.texel_world)
    if xy is not None:
        # a rectangular face (a far light's, a sun's fitted map): the kernel's world
        # width is as many texels along each axis as that axis's texel width gives (one
        # width for both, the one along the receiver's depth gradient, made the kernels
        # on a ground under a light 8 degrees high several times too wide across the
        # light's direction: a square area light 1e5 away, 2.3 degrees wide, RMSE
        # against raytraced 0.156, 0.040 with the square face it had before, now 0.038;
        # a sun of that angular diameter 0.167, now 0.034, on a full map 0.164 -> 0.023;
        # 64^2, 16 spp)
        return mi.Point2f(xy[0], xy[1])
    return smap.view.texel_parallel_size(smap.resolution, r.face, p_world, r.texel_world)


#: The face resolution at which ``max_kernel`` texels also cap a kernel's share of the
#: face: a kernel is at most ``max_kernel`` texels of the map, or ``max_kernel /
#: KERNEL_REF_RES`` of the face's width on a denser map (or virtual level), whichever is
#: wider, so that the cap does not shrink in world units as the map gets denser.
KERNEL_REF_RES = 512


def _kernel_cap(smap, half_max):
    """Largest kernel half-width, in texels of ``smap`` (per lane on a virtual map):
    ``half_max``, or ``half_max`` texels of a :data:`KERNEL_REF_RES`-texel face on a
    denser map. On a virtual map, that many texels of the coarsest level it may read
    (:func:`~mi_shadowmap.virtual.coarser_levels`: at most
    :data:`~mi_shadowmap.virtual.MAX_COARSER` levels coarser, never beyond the coarsest),
    the levels the mark pass builds."""
    vmap = getattr(smap, "vmap", None)
    if vmap is None:
        return half_max * max(smap.resolution / KERNEL_REF_RES, 1.0)
    if vmap.coarse_res is None:     # no coarser level marked (an environment's regions):
        # what the marks built around the point on its own level, page_size / 2 texels
        # less the camera sample's texel; a tap beyond read the coarsest level where no
        # neighbouring point had built its page, whose texels, far wider, stood in front
        # of the receiver plane (an open ground seen through a 0.5-degree lens under a
        # uniform sky: visibility 0.34 against raytraced's 0.49)
        return min(half_max, 0.5 * vmap.layout.page_size - 1.0)
    from ..virtual import coarser_levels
    k = coarser_levels(vmap.layout, smap.level, vmap.coarse_res)
    return half_max * mi.Float(mi.UInt32(1) << k)


#: Whether a virtual map's filter kernels under a light with extent are capped at no
#: less than the light's own width (:func:`_light_width_cap`).
LIGHT_WIDTH_CAP = True

#: Face resolution down to which a virtual map's filter kernel under a light with extent
#: may read coarser levels (:func:`_built_beyond`): a kernel as wide as the light spans
#: up to half a face seen from a receiver one light width away.
LIGHT_COARSE_RES = 64


#: Whether the light's width a virtual map's widened kernels (:func:`_light_width_cap`)
#: take is at most what a cube face spans at the receiver (:func:`_light_seen`).
LIGHT_SEEN = True

#: Whether a widened kernel whose level is not built under its point keeps its width at
#: the coarsest level that is (:func:`_built_beyond`) instead of ``max_kernel`` texels.
KEEP_KERNEL_WIDTH = True


def _light_width_cap(smap, angular, w_light, texel, half_cap, d_light) -> tuple:
    """``(cap, widened, w_seen)``: the filter kernel's largest half-width, in texels of
    ``smap``: ``half_cap`` (:func:`_kernel_cap`) or, on a virtual map under a light with
    extent (not a directional light's angular diameter, not an environment's regions),
    half the light's width on the receiver's plane, whichever is wider: the penumbra of a
    blocker halfway between the receiver and the light; whether the light's width
    applies (a Python bool); and that width, ``w_seen`` (world units, per lane:
    :func:`_light_seen` of the receiver's axial distance ``d_light`` from the light;
    ``w_light`` where the light's width does not apply)."""
    vmap = getattr(smap, "vmap", None)
    if not LIGHT_WIDTH_CAP or angular or vmap is None or vmap.coarse_res is None:
        return half_cap, False, w_light
    w_seen = _light_seen(w_light, d_light) if LIGHT_SEEN else w_light
    return dr.maximum(half_cap, 0.5 * w_seen / texel), True, w_seen


def _light_seen(w_light, d_light) -> mi.Float:
    """The light's width PCSS's estimate takes on a widened kernel: ``w_light``, at most
    ``2 d_light``, the width a cube face (90 degrees) spans at the receiver's axial
    distance ``d_light`` from the light: the part of the light within 45 degrees of the
    receiver's line to its centre. In Fernando's terms, the light's size in a 90-degree
    map's uv at the receiver's depth (``LIGHT_SIZE_UV * NEAR_PLANE / z_receiver``) is at
    most the whole map. A light point further off is seen from the receiver along a
    grazing ray, whose occluders no compare at the blocker's depth through the light's
    centre reads: a rectangle 1200 wide 8 above a 12-wide ground (100 times it) gave a
    blocker 1 unit tall a penumbra ~170 units wide and left the ground nearly unshadowed
    (``benchmarks/RESULTS.md``, fifty-third session, helper B). Not the width of the
    receiver's own face: a far light's face is aimed at the scene alone, a fraction of a
    degree wide, narrower than the light (2.3 degrees seen from the ground), whose whole
    width is its penumbra's (``test_kernels_on_a_rectangular_face_keep_their_world_width``
    with the face's width: RMSE 0.063 against ``raytraced``, 0.047 without)."""
    return dr.minimum(w_light, 2.0 * d_light)


#: Levels coarser than the receiver's a virtual map's blocker search may read (the filter
#: kernel: as many as :func:`_kernel_cap` allows). The search region is sized from the
#: face's nearest depth, which can be far wider than any penumbra, and coarser levels
#: lose thin blockers. Measured (96^2, 4 spp, RMSE against 256 light samples), 0 / 1 /
#: 2 / 3 / 8 levels: large_world with the sun's angular diameter 0.120 / 0.124 / 0.124 /
#: 0.137 / 0.149, contact_hardening 0.042 / 0.037 / 0.037 / 0.037 / 0.037.
SEARCH_COARSER = 1


def _level_for_kernel(smap, lk: Lookup, opts, r, plane, texel, half, half_max, active,
                      max_coarser=None, light_width=False):
    """``(map, receiver, plane, texel)`` to filter a kernel ``half`` texels of ``smap``
    wide (half-width) with: ``smap`` itself on a full map (its taps spread over the
    kernel, ``filter_samples`` of them whatever its width); on a virtual map, the
    map bound again at the level ``2^k`` times coarser (``k = 0``: its own level; ``k
    = ceil(log2(half / h))``, ``h = min(half_max, page_size / 2)``: the
    texels a level's marks reach around the point; at most the levels
    :func:`_kernel_cap` allows; with ``light_width``, a kernel beyond that cap at most
    the levels built under its point, :func:`_built_beyond`), with the receiver and its
    plane there (its biases in that level's texels). (Coarsening from ``half_max``
    instead left kernels of 16-32 texels to the neighbouring points' tiles: on a 96 x 12
    film of a ground strip under a 2-unit light, RMSE 0.022 against 0.013 before the
    kernel cap changed; 0.013 now.)"""
    vmap = getattr(smap, "vmap", None)
    if vmap is None or vmap.coarse_res is None:
        return smap, r, plane, texel
    from ..virtual import coarser_levels
    # the level's own marks reach page_size / 2 texels around the point
    fits = min(half_max, 0.5 * vmap.layout.page_size)
    if dr.size_v(half) == 2:     # per axis (a rectangular face): the wider fits
        half = dr.maximum(half[0], half[1])
    k = mi.UInt32(dr.maximum(dr.ceil(dr.log2(dr.maximum(half / fits, 1.0))), 0.0))
    # down to virtual_coarse_res (KERNEL_REF_RES) texels a face; a kernel beyond that cap
    # (a light's own width, _light_width_cap) down to the coarsest level built under it
    k_ref = coarser_levels(vmap.layout, smap.level, vmap.coarse_res)
    if light_width:
        beyond = mi.Bool(active) & (half > half_max * mi.Float(mi.UInt32(1) << k_ref))
        k_ref = dr.select(beyond, _built_beyond(smap, k_ref, k, beyond), k_ref)
    k = dr.minimum(k, k_ref)
    if max_coarser is not None:
        k = dr.minimum(k, mi.UInt32(max_coarser))
    coarse = vmap.bind(lk, active, level=smap.level + k)
    r2 = receiver(coarse, lk, opts)
    plane2 = receiver_plane(coarse, lk, r2, opts, light_front=True,
                            near_fallback=plane.near_fallback)
    texel2 = dr.maximum(_texel_parallel(coarse, r2, lk.p_world), 1e-30)
    return coarse, r2, plane2, texel2


def _built_beyond(smap, k_ref, k_want, active) -> mi.UInt32:
    """Levels coarser than ``smap``'s (a bound virtual map) that a filter kernel beyond
    the face-width cap (:func:`_light_width_cap`) filters: up to ``k_want``, down to
    :data:`LIGHT_COARSE_RES` texels a face, those whose tile under the point this frame's
    marks built, every level from ``k_ref`` on
    (:meth:`~mi_shadowmap.virtual.lookup.VirtualShadowMap.tile_marked`): ``k_ref`` where
    the next coarser one is not built. The mark pass builds
    no level for these kernels: the levels coarser than ``virtual_coarse_res``'s it builds
    for other points (their own levels, their kernels' levels) hold them."""
    from ..virtual import coarser_levels
    lay = smap.vmap.layout
    face, uv64 = smap.projected[:2]
    k_top = dr.minimum(k_want, coarser_levels(lay, smap.level, LIGHT_COARSE_RES))
    k, go = mi.UInt32(k_ref), mi.Bool(active)
    for j in range(1, int(math.log2(KERNEL_REF_RES // LIGHT_COARSE_RES)) + 1):
        go &= k_ref + j <= k_top
        go &= smap.vmap.tile_marked(face, uv64,
                                    dr.minimum(smap.level + k_ref + j, lay.coarsest), go)
        k = dr.select(go, k_ref + j, k)
    return k


def pcss(smap, lk: Lookup, opts, active=True) -> mi.Float:
    """Percentage-closer soft shadows; see the module docstring."""
    w_light, angular = smap.view.light_width(opts.light_size, opts.angular_diameter)
    if isinstance(w_light, (int, float)) and w_light <= 0.0:   # size 0: hard (one compare)
        return hard(smap, lk, opts, active)
    r = receiver(smap, lk, opts)
    active = mi.Bool(active) & r.inside
    # not an environment's regions (see the module docstring: sky_sun measured worse)
    fallback = opts.soft_compare <= 0.0 and getattr(smap.view, "kind", None) != "environment"
    plane = receiver_plane(smap, lk, r, opts, light_front=True, near_fallback=fallback)
    d_r = plane.depth0
    origin = smap.view.depth_origin     # 0.0 but for a far light's virtual map
    # blockers no nearer than 1e-3 of the receiver's distance from the light
    guard = 1e-3 * d_r if isinstance(origin, float) else 1e-3 * (d_r + origin) - origin
    half_max = 0.5 * opts.max_kernel
    half_cap = _kernel_cap(smap, half_max)
    texel = dr.maximum(_texel_parallel(smap, r, lk.p_world), 1e-30)
    # a planar area light's own shape (not a user's light_size: the square it means)
    shaped = None if angular or opts.light_size is not None or not LIGHT_SHAPE else \
        _light_shape(smap, r, lk.p_world, texel)
    shape = None
    if shaped is not None:
        w_light, shape, fit = shaped
        # the cap bounds the light's longer half-axis, as it bounded the square's
        # half-side (the same world width at every turn of the light); on a virtual map
        # never beyond the half-extent, which its marks and levels hold
        virtual_map = getattr(smap, "vmap", None) is not None
        half_cap = half_cap * (dr.minimum(fit, 1.0) if virtual_map else fit)

    # 1. blocker search over the similar-triangles region
    near = dr.gather(mi.Float, face_near_depth(smap), r.face, active)
    near = dr.clip(near, guard, d_r)
    # a virtual map's search: at most SEARCH_COARSER levels coarser (thin blockers)
    virtual = getattr(smap, "vmap", None) is not None
    search_cap = half_max * 2 ** SEARCH_COARSER if virtual else half_cap
    region = 0.5 * _spread(d_r, near, w_light, angular, origin)     # world half-width
    search_half = dr.clip(region / texel, 0.5, dr.minimum(search_cap, half_cap))
    smap_b, r_b, plane_b, texel_b = _level_for_kernel(smap, lk, opts, r, plane, texel,
                                                      search_half, half_max, active,
                                                      SEARCH_COARSER)
    if smap_b is not smap:     # a coarser level: the same world width, in its texels
        search_half = dr.clip(search_half * texel / texel_b, 0.5, half_max)
    soft_width = soft_compare_width(r_b, opts.soft_compare)
    rnd_b = lk.sampler.next_2d(active)
    z_sum, n_block = blocker_search(smap_b, lk, r_b, plane_b, search_half,
                                    opts.blocker_samples, opts.pattern, rnd_b, active,
                                    soft_width, shape)
    has_blocker = n_block > 0

    # 2. penumbra estimate (thesis eq. 2), guarded for d_blocker -> 0
    # a fractional count (soft_compare's blocker weights) divides too; soft counts
    # below 1e-6 (their shadow is scaled by the count below) keep the division sane
    n_div = n_block if soft_width is None else dr.maximum(n_block, 1e-6)
    d_blocker = dr.maximum(z_sum / dr.select(has_blocker, n_div, 1.0), guard)
    d_light = d_r + origin     # the receiver's axial distance from the light
    filter_cap, widened, w_seen = _light_width_cap(smap, angular, w_light, texel, half_cap,
                                                   d_light)
    w_penumbra = dr.maximum(_spread(d_r, d_blocker, w_seen, angular, origin), 0.0)
    filter_half = dr.clip(0.5 * w_penumbra / texel, 1e-3, filter_cap)

    # 3. PCF with a kernel proportional to w, only where blockers were found
    smap_f, r_f, plane_f, texel_f = _level_for_kernel(smap, lk, opts, r, plane, texel,
                                                      filter_half, half_max,
                                                      active & has_blocker,
                                                      light_width=widened)
    if smap_f is not smap:     # the same world width, in its texels
        # at most max_kernel texels there; a widened kernel whose level is not built
        # under its point keeps its width at the coarsest level that is (_built_beyond)
        keep = widened and KEEP_KERNEL_WIDTH
        filter_half = dr.maximum(filter_half * texel / texel_f, 1e-3)
        filter_half = filter_half if keep else dr.minimum(filter_half, half_max)
        soft_width = soft_compare_width(r_f, opts.soft_compare)
    rnd_f = lk.sampler.next_2d(active)
    vis = pcf_plane(smap_f, lk, r_f, plane_f, filter_half, opts.filter_samples, opts.pattern,
                    rnd_f, active & has_blocker, soft_width, shape)
    if soft_width is not None:
        # Less than one blocker tap's worth found: the shadow scaled by it, so that
        # visibility is continuous as the first blocker enters the search.
        vis = 1.0 - (1.0 - vis) * dr.minimum(n_block, 1.0)
    return dr.select(active & has_blocker, vis, 1.0)


def _size_zero(view, opts) -> bool:
    """A light PCSS reads as hard shadows (size 0: a point or spot light without
    ``light_size``, a directional one without ``angular_diameter``): its lookups read
    one texel, so the mark pass builds ``hard``'s margin, not the kernel's. Not an
    environment: its regions' widths are per lane (:class:`~mi_shadowmap.environment.
    RegionView`), not the width the whole view reports (0, a directional light's
    without ``angular_diameter``), which marked ``hard``'s margin around each point
    for kernels up to ``max_kernel`` texels wide."""
    if getattr(view, "kind", None) == "environment":
        return False
    w_light, _ = view.light_width(opts.light_size, opts.angular_diameter)
    return isinstance(w_light, (int, float)) and w_light <= 0.0


def _virtual_margin(view, opts) -> float:
    """Texels the mark pass builds around each point: ``hard``'s for a light of size 0,
    else the kernels' half-width (:func:`_kernel_cap`: an environment's regions, which
    read no coarser level, keep their kernels within the 2 x 2 pages a lookup binds)."""
    if _size_zero(view, opts):
        return 2.0
    if getattr(view, "kind", None) == "environment":
        return 2.0 + min(0.5 * opts.max_kernel, 0.5 * opts.page_size - 3.0)
    return 2.0 + 0.5 * opts.max_kernel


METHOD = Method(
    name="pcss",
    lookup=pcss,
    summary="Fernando 2005 percentage-closer soft shadows: blocker search, penumbra "
            "estimate, variable PCF kernel",
    properties=(
        Prop("blocker_samples", "int", 16, "PCSS blocker-search taps (Fernando's "
             "BLOCKER_SEARCH_NUM_SAMPLES).", lo=1, hi=4096),
        Prop("filter_samples", "int", 16, "PCSS filtering (PCF) taps (Fernando's "
             "PCF_NUM_SAMPLES).", lo=1, hi=4096),
        Prop("light_size", "float", None,
             "Light width in world units for PCSS (a square of that width). Default: a "
             "planar area emitter's own shape (rectangle, disk, planar mesh: its "
             "parallelogram as each receiver sees it), another area emitter's side of the "
             "square of equal projected area (see light_views), 0 for "
             "point, spot and projector lights (hard shadows); > 0 gives them a PCSS "
             "penumbra.", lo=0.0, lights=("point", "spot", "projector", "area")),
        Prop("max_kernel", "float", 64.0,
             "PCSS blocker-search and filter kernels are at most max_kernel texels wide "
             "or max_kernel / 512 of the face's width, whichever is wider (so the cap "
             "does not shrink as the map gets denser; a virtual map's filter kernel under "
             "a light with extent: at least the light's width, at most twice its distance); "
             "a kernel wider than max_kernel "
             "texels (virtual maps: min(max_kernel, page_size)) filters a coarser level "
             "(virtual maps) or spreads its taps over the map's texels (full maps).",
             lo=1.0, hi=4096.0),
        Prop("pattern", "str", "stratified",
             "PCSS tap pattern: 'stratified' (square grid, shifted per camera sample) or "
             "'poisson' (a Poisson disk, rotated per camera sample).",
             choices=("stratified", "poisson")),
        Prop("angular_diameter", "float", 0.0,
             "Apparent diameter of a directional light (sun: about 0.53), in degrees; > 0 "
             "gives directional lights a PCSS penumbra.", lo=0.0, hi=30.0,
             lights=("directional",)),
        SOFT_COMPARE,
    ),
    #: ``pcss_near``: one value per face (not a per-texel layer), see face_near_depth.
    layers={"pcss_near": face_near_layer},
    layer_cost={"pcss_near": 0.0},
    virtual_margin=lambda o, view: _virtual_margin(view, o),
    # kernels wider than max_kernel texels filter coarser levels, down to KERNEL_REF_RES;
    # not an environment's regions (their wide kernels are better regularised by the cap:
    # sky_sun zoomed, RMSE 0.052 -> 0.069 with coarser levels)
    virtual_coarse_res=lambda o, view: (None if _size_zero(view, o)
                                        or getattr(view, "kind", None) == "environment"
                                        else KERNEL_REF_RES),
    virtual=True, builtin=True,
)
