"""Multiple-depth shadow maps (Pagot, Comba & Oliveira 2004).

C. A. Pagot, J. L. D. Comba, M. M. de Oliveira, "Multiple-Depth Shadow
Maps", SIBGRAPI 2004 (``shared/papers/004``).

* **The map (n-SM).** Each cell stores ``n = depths`` values: the standard
  depth ``Z``; for ``n >= 2`` also the **maximum**, for ``n = 3`` also the
  **minimum**, of the base map over the ``search x search`` texels around
  the cell (q = search^2 samples; the paper's "maximum or minimum (or
  both)" selection, with its 3 x 3 default). The 3 x 3 minimum and maximum
  are map layers ``mdsm_min`` / ``mdsm_max`` built only for this method
  (the ``layers`` of its record, :data:`METHOD`).
* **The n-shadow test (n-ST).** A receiver at depth ``d`` is shadowed by
  ``s`` of the cell's ``n`` depths (``Z_i < d``); the shadow coverage is
  ``s / n`` -- one of ``n + 1`` equally spaced values.
* **PCF(k, n).** The n-ST of each of the ``k = pcf_samples`` texels nearest
  the lookup point (a ``sqrt(k) x sqrt(k)`` block, default 9 = 3 x 3) is
  averaged (unweighted): up to ``n k + 1`` distinct outcomes (Table 1).
  Visibility is ``1 - mean(s) / n``.
* **Thinner shadows with n = 2** (the paper's method, not a deviation: "the
  same transition using the 2-SM is thinner", Section 5). The maximum is in
  front of a receiver only where the whole search square is, so its test's
  shadow edge lies ``(search-1)/2`` texels inside the standard depth's, and
  their average ``(search-1)/4`` texels inside: every shadow edge moves that
  far into the shadow (half a texel at ``search = 3``; integrated over a
  straight edge: exactly 0.5 / 1.0 texel of added light for search 3 / 5, 0
  for n = 1 and n = 3, whose minimum moves the edge back as far). The added
  light scales with the texel, so virtual maps (texels 0.35-0.7 of the pixel
  footprint) show it more than a finer full map; it is not a leak through
  walls (see the README's "Thinner shadows with mdsm depths=2").

Deviations from the paper, and why:

* **Reading of the n-ST formula.** The printed rule ("sc = 1 if d > Z_n,
  otherwise (i-1)/n, Z_i the largest Z smaller than d") is garbled in our
  copy (taken literally it is not monotone in d); we use the reading its
  text and Figure 4 describe: ``sc`` = fraction of the n depths in front of
  the receiver.
* **Which extra depth for n = 2.** The paper allows the maximum or the
  minimum; we use the maximum (it softens the shadow side of an edge). The
  minimum of a tilted receiver's own neighbourhood always lies in front of
  it, so a 2-SM with the minimum would need a bias of the search radius
  everywhere.
* **Biases** (not discussed by the paper). Each tap's texel is compared with
  the receiver's tangent plane at that texel's centre (receiver-plane depth,
  the same construction as Wang & Molnar's virtual samples, see
  :func:`.common.virtual_sample_depth`; where the plane is within
  ``atan(max_tan_slope)`` of the light ray the shading point's depth is
  used), minus the usual ``bias``/``slope_bias``/``normal_bias`` of
  :func:`~.common.receiver`. The **minimum** is compared with the plane's
  depth lowered by ``(search-1)/2 * (|dz/di| + |dz/dj|)`` (the plane's depth
  change over the search radius, clamped by ``max_tan_slope``): the
  smallest depth of a plane over the search square, so that a tilted
  receiver does not shadow itself through its own neighbourhood minimum.
* **search > 3** composes the stored 3 x 3 layers at lookup time (the
  minimum / maximum of 4 or 9 stored windows that tile the larger square):
  layers are cached by name independently of the options, so one pair of
  layers serves every ``search``. ``search = 1`` uses the base depth (the
  n-SM then equals a standard map).
* Taps are clamped to the receiver's face (cube-map seams are not
  crossed); lookups outside the map are lit. A block cut by the face's border reads
  the border's texels again, and unlike ``second_depth``'s (whose compares of the
  point's own depth against those texels all shadowed an open floor: no evidence,
  see its module doc) each clamped tap here is a sound compare: the texel it reads
  against the receiver's plane at that same texel. Its vote only counts twice, as a
  box filter's weights do at an edge. Measured (forty-seventh session, 128^2, 16
  spp; a floor, box, ball and post under a point light 4 or 0.3 over the floor, full
  maps of 1-16 texels a face and virtual maps): 0.00-0.06 % false shadow (every bias
  0: 0.01-0.23 % at 2-16 texels, 0.6 / 6.4 % at 1, where the face's one texel sees an
  occluder; the 2.5-11 % false light of those maps is under-sampling, as ``hard``'s);
  counting only the distinct in-face taps changed misclassified pixels by at most 0.14
  points (none at 1 texel), and cbox_area, room_two_points and spectral_point
  (virtual, 256, 1024) by none (RMSE identical to 4 digits).
* Only the layers the options read are built (the record's ``layers_for``,
  :meth:`mi_shadowmap.methods.Method.layer_names`): none for ``depths = 1`` or
  ``search = 1``, ``mdsm_max`` for ``depths = 2``, both for ``depths = 3``.
* **Virtual maps** (``virtual=true``, :mod:`mi_shadowmap.virtual`) store no extra
  depths: their pages hold the base depth only, and a page's 3 x 3 extremes at its
  border would need its neighbours' texels, which may not be built. The lookup
  computes each stored value it would read from the base depths instead (the same
  clamped 3 x 3 windows: the same visibility as a full map of the level's
  resolution). Where the taps' squares lie inside the face the lookup reads their
  union once, ``(side + search - 1)^2`` depths (25 at the defaults, against 9 depths
  and 9 stored maxima of a full map); near the face's border it visits each tap's
  clamped windows (9 depths a window). The mark pass builds the pages within the taps' windows
  (``virtual_margin``); a window beyond the lookup's 2 x 2 pages reads its own pages
  through the page table, as every virtual tap does.
* **Stored window.** The layer builders (the record's ``layers``, ``mdsm_min`` /
  ``mdsm_max``) always store the 3 x 3 (q = 9, the paper's default)
  minimum / maximum, clamped at the face border, whatever ``search`` is;
  other sizes are composed from it at lookup (above).
"""
from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi

from ..control_flow import if_stmt
from ..methods import Method, Prop
from .common import Lookup, has_layers, nearest_block, taps_loop, virtual_sample_depth


def _window_offsets(search: int) -> list:
    """Centres (per axis) of stored 3 x 3 windows tiling ``[-r, r]``, r = (search-1)/2."""
    r = (search - 1) // 2
    if r <= 1:
        return [0]
    m = math.ceil((2 * r + 1) / 3)
    return sorted({round(-(r - 1) + k * (2 * (r - 1)) / (m - 1)) for k in range(m)})


_REDUCE = {"mdsm_min": dr.minimum, "mdsm_max": dr.maximum}


def neighbourhood_depth(smap, layer: str, face, ij: mi.Point2i, search: int, active):
    """Min (``layer='mdsm_min'``) or max (``'mdsm_max'``) of the base map over the
    ``search x search`` texels around ``ij``."""
    return neighbourhood_depths(smap, (layer,), face, ij, search, active)[layer]


def neighbourhood_depths(smap, layers: tuple, face, ij: mi.Point2i, search: int,
                         active) -> dict:
    """:func:`neighbourhood_depth` of each of ``layers`` (``'mdsm_min'``,
    ``'mdsm_max'``): the stored 3 x 3 windows tiling the search square, read from the
    map's layers, or, on a map without them (virtual maps, which build no such layer),
    computed from the same base depths here (the stored value at the window's clamped
    centre: the extreme of its 3 x 3 clamped neighbours), the fetches shared between
    the minimum and the maximum."""
    if search == 1:
        z = smap.fetch(smap.depth, face, ij.x, ij.y, active)
        return {name: z for name in layers}
    out = {name: None for name in layers}
    stored = has_layers(smap, layers)
    for dj in _window_offsets(search):
        for di in _window_offsets(search):
            if stored:
                zs = {name: smap.fetch(smap.extra[name], face, ij.x + di, ij.y + dj, active)
                      for name in layers}
            else:
                c = smap.clamp_texel(mi.Point2i(ij.x + di, ij.y + dj))
                zs = {name: None for name in layers}
                for ej in (-1, 0, 1):
                    for ei in (-1, 0, 1):
                        z = smap.fetch(smap.depth, face, c.x + ei, c.y + ej, active)
                        zs = {name: z if v is None else _REDUCE[name](v, z)
                              for name, v in zs.items()}
            out = {name: zs[name] if v is None else _REDUCE[name](v, zs[name])
                   for name, v in out.items()}
    return out


def mdsm(smap, lk: Lookup, opts, active=True) -> mi.Float:
    """PCF(k, n) over an n-depth shadow map (Pagot et al. 2004)."""
    r, active, k, side, i0 = nearest_block(smap, lk, opts, active)
    n_depths = opts.depths
    search = opts.search
    res = smap.resolution
    view = smap.view
    p = mi.Point3f(lk.p_world)
    n = dr.normalize(mi.Vector3f(lk.n_world))
    offset = view.depth_of(p) - r.depth          # bias, slope bias (texels), normal offset
    max_tan = opts.max_tan_slope

    def plane_depth(ij):
        z, ok = virtual_sample_depth(view, r.face, ij, res, p, n, max_tan)
        return dr.select(ok, z - offset, r.depth), ok

    if n_depths == 3 and search > 1:
        # the plane's depth change per texel along i and j (for the minimum's bias)
        z00, ok0 = plane_depth(i0)
        z10, ok1 = plane_depth(i0 + mi.Point2i(1, 0))
        z01, ok2 = plane_depth(i0 + mi.Point2i(0, 1))
        lim = max_tan * r.texel_world
        grad = dr.minimum(dr.abs(z10 - z00), lim) + dr.minimum(dr.abs(z01 - z00), lim)
        min_drop = dr.select(ok0 & ok1 & ok2, grad, 2.0 * lim) * ((search - 1) // 2)
    else:
        min_drop = mi.Float(0.0)

    names = ("mdsm_max",) if n_depths == 2 else ("mdsm_max", "mdsm_min")

    def body(tap, n_shadow):
        ij = smap.clamp_texel(mi.Point2i(i0.x + mi.Int32(tap % side),
                                         i0.y + mi.Int32(tap // side)))
        z_rec, _ = plane_depth(ij)
        z = smap.fetch(smap.depth, r.face, ij.x, ij.y, active)
        one, zero = mi.UInt32(1), mi.UInt32(0)
        s = dr.select(z < z_rec, one, zero)
        if n_depths >= 2:
            ext = neighbourhood_depths(smap, names, r.face, ij, search, active)
            s += dr.select(ext["mdsm_max"] < z_rec, one, zero)
        if n_depths == 3:
            s += dr.select(ext["mdsm_min"] < z_rec - min_drop, one, zero)
        return (n_shadow + s,)

    def all_taps(face, i0):
        (n_shadow,) = taps_loop(k, body, (mi.UInt32(0),), active)
        return n_shadow

    if n_depths == 1 or search == 1 or has_layers(smap, names):
        n_shadow = all_taps(r.face, i0)
    else:
        # no stored extremes (virtual maps): the taps' search squares overlap, so read
        # their union once (an unrolled block of (side + search - 1)^2 depths instead of
        # k (1 + 9 windows) fetches) where it lies inside the face; lanes near the
        # face's border, whose clamped windows differ from a square, take the loop
        rs = (search - 1) // 2
        lo_c = mi.Point2i(i0.x - rs, i0.y - rs)
        hi_c = mi.Point2i(i0.x + side - 1 + rs, i0.y + side - 1 + rs)
        interior = (dr.all(smap.clamp_texel(lo_c) == lo_c)
                & dr.all(smap.clamp_texel(hi_c) == hi_c))

        def union_block(face, i0):
            u = side + 2 * rs
            block = [[smap.fetch(smap.depth, face, i0.x - rs + a, i0.y - rs + b, active)
                      for a in range(u)] for b in range(u)]
            one, zero = mi.UInt32(1), mi.UInt32(0)
            total = mi.UInt32(0)
            for tap in range(k):
                ti, tj = tap % side, tap // side
                z_rec, _ = plane_depth(mi.Point2i(i0.x + ti, i0.y + tj))
                window = [block[tj + b][ti + a] for b in range(2 * rs + 1)
                          for a in range(2 * rs + 1)]
                total += dr.select(block[tj + rs][ti + rs] < z_rec, one, zero)
                z_max = window[0]
                for z in window[1:]:
                    z_max = dr.maximum(z_max, z)
                total += dr.select(z_max < z_rec, one, zero)
                if n_depths == 3:
                    z_min = window[0]
                    for z in window[1:]:
                        z_min = dr.minimum(z_min, z)
                    total += dr.select(z_min < z_rec - min_drop, one, zero)
            return total

        n_shadow = if_stmt((mi.UInt32(r.face), mi.Point2i(i0)), interior, union_block,
                           all_taps, holds_loops=True)
    vis = 1.0 - mi.Float(n_shadow) / float(n_depths * k)
    return dr.select(r.inside, vis, 1.0)


def neighbourhood_extreme(smap, reduce) -> mi.Float:
    """``reduce`` (dr.minimum / dr.maximum) of the base depths over the 3 x 3 texels
    around every texel (clamped at the face border): Pagot et al. (2004)'s
    extra depths of a multiple-depth map, with q = 9."""
    res = smap.resolution
    idx = dr.arange(mi.UInt32, smap.n_texels)
    face = idx // (res * res)
    rem = idx - face * (res * res)
    j = mi.Int32(rem // res)
    i = mi.Int32(rem - (rem // res) * res)
    out = smap.fetch(smap.depth, face, i, j)
    for dj in (-1, 0, 1):
        for di in (-1, 0, 1):
            if di or dj:
                out = reduce(out, smap.fetch(smap.depth, face, i + di, j + dj))
    return out


def _layers_used(opts) -> tuple:
    """The layers :func:`mdsm` reads with ``opts``: none for ``depths = 1`` or
    ``search = 1`` (base depth only), ``mdsm_max`` for ``depths = 2``, both for 3."""
    if opts.depths == 1 or opts.search == 1 or getattr(opts, "virtual", False):
        return ()   # virtual maps: the lookup computes them from the base depths
    return ("mdsm_max",) if opts.depths == 2 else ("mdsm_min", "mdsm_max")


METHOD = Method(
    name="mdsm",
    lookup=mdsm,
    summary="Pagot et al. 2004 multiple-depth shadow maps",
    properties=(
        Prop("pcf_samples", "int", 9,
             "Percentage-closer taps k (PCF(k, n) of Pagot et al.): one compare per texel of "
             "the sqrt(k) x sqrt(k) texels nearest the lookup point (9: the paper's "
             "PCF(9, n)).", choices=(1, 4, 9, 16, 25)),
        Prop("depths", "int", 2,
             "Depths n per cell of the multiple-depth map: 1 = standard map, 2 = plus the "
             "maximum, 3 = plus maximum and minimum over the 'search' neighbourhood.",
             choices=(1, 2, 3)),
        Prop("search", "int", 3,
             "Side (texels) of the square neighbourhood of the base map searched for the "
             "extra depths of mdsm (q = search^2 samples; the paper's 3 x 3).",
             choices=(1, 3, 5, 7, 9)),
    ),
    layers={"mdsm_min": lambda scene, smap: neighbourhood_extreme(smap, dr.minimum),
            "mdsm_max": lambda scene, smap: neighbourhood_extreme(smap, dr.maximum)},
    layers_for=_layers_used,
    # taps reach (side - 1) / 2 texels, their windows (search - 1) / 2 more, plus the
    # nearest-texel margin (normal offset, camera samples within a pixel)
    virtual_margin=lambda o: 2.0 + 0.5 * math.isqrt(o.pcf_samples) + (o.search - 1) // 2,
    virtual=True,
    builtin=True,
)
