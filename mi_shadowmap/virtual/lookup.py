"""What filters read: an emitter's virtual map (:class:`VirtualShadowMap`) and the map
bound to one batch of lookups (:class:`BoundVirtualMap`).
"""
from __future__ import annotations

import copy
import dataclasses
import math

import drjit as dr
import mitsuba as mi
import numpy as np

from ..control_flow import if_stmt
from ..methods import MethodError
from ..light_views.local import LocalView
from ..light_views.base import TEXEL_SAMPLE
from .layout import ANISO, INVALID_SLOT, key_fields, padded_array
from .store import PageStore
from ..filters.common import BiasReach


#: How many pixel footprints the receiver's texel-scaled biases may lose an occluder's
#: shadow over along the receiver (:meth:`VirtualShadowMap.level_for` picks a finer level
#: where the footprint's would lose more).
REACH_PIXELS = 2.0


def effective_lod_bias(lod_bias: float, page_size: int) -> float:
    """The ``lod_bias`` the level choice uses: at least ``1 - log2(page_size)`` (-4 for
    pages of 32^2). Finer, a pixel spans more than ``page_size`` texels of its level, and
    the mark pass (from pixel centres, up to ``page_size / 2`` texels around each) leaves
    many of the pixel's samples (and their kernels' taps) without a page there: they
    walked to coarse levels (``lod_bias`` -8 on pages of 32^2 rendered as the coarsest
    level alone, 0.66 % misclassified against 0.10 % at the default; at -5 ``pcf`` and
    ``vsm`` were 3-8x the default's visibility RMSE). A ``resolution`` given reads level
    0 where the footprint is finer than that anyway."""
    return max(float(lod_bias), 1.0 - math.log2(int(page_size)))


#: The fields of a film pixel's word of :meth:`VirtualShadowMap.keeps`
#: (:func:`~mi_shadowmap.virtual.planner._pixel_keeps`): the centre's shape id in the low
#: bits, whether the centre's mark kept the biases' level, and whether samples on other
#: shapes than the centre's (a silhouette's pixel) keep it.
KEEP_SHAPE, KEEP_CENTRE, KEEP_OTHERS = (1 << 29) - 1, 1 << 30, 1 << 31


class VirtualShadowMap:
    """One emitter's virtual map for one render: the page pool and its table.

    What a filter reads is :meth:`bind`'s :class:`BoundVirtualMap`; this object is
    what ``integrator.maps`` holds (``view``, ``layout``, ``store``, ``stats``).
    ``frame``: the render's own pages (:meth:`PageStore.table`); default: every page
    the store holds.
    """

    def __init__(self, store: PageStore, stats: dict, lod_bias: float = -0.5,
                 margin: float = 2.0, coarse_res: int | None = None,
                 frame: tuple | None = None, reach: BiasReach | None = None,
                 keep: tuple | None = None):
        self.lod_bias = float(lod_bias)
        # per film pixel, where its lookups read the biases' level (:meth:`keeps`):
        # ``(words, width, count)``, a word per pixel (``x + width y``; KEEP_SHAPE,
        # KEEP_CENTRE, KEEP_OTHERS), the film's width and pixel count (opaque); None:
        # the biases' level everywhere
        self.keep = keep
        # the method's receiver biases (level_for keeps the shadows they lose within
        # REACH_PIXELS footprints); None: the footprint alone
        self.reach = reach
        # the method's virtual_coarse_res: the coarser levels its marks built, which its
        # wide kernels may filter (None: its own level only)
        self.coarse_res = coarse_res
        # the lookups' taps reach beyond the 2 x 2 pages they bind (margin: the method's
        # kernel half-width, texels): those taps read their own pages through the table
        # (BoundVirtualMap._index); narrower kernels skip that code
        self.far_taps = float(margin) + 1.0 > 0.5 * store.layout.page_size
        self.store = store
        self.layout = store.layout
        self.view = store.layout.view
        self.header, self.dense, self.face_near, self.tile_masks, self.dense_tiles = \
            store.table(frame)
        self.depth_bounds = padded_array(mi.Float64, self.layout.depth_range)
        # where the pages' depths start (a far light's, VirtualLayout.t0): an opaque
        # variable, not a kernel literal (a moved light would compile a new lookup)
        t0 = float(self.layout.t0)
        self.depth_origin = dr.opaque(mi.Float64, t0) if t0 > 0.0 else None
        self.stats = stats

    # The texel-counting interface of ShadowMap, for the harness and reports.
    @property
    def resolution(self) -> int:
        return self.layout.res0

    @property
    def depth(self):
        return self.store.pools["depth"]

    @property
    def extra(self) -> dict:
        return {k: v for k, v in self.store.pools.items() if k != "depth"}

    @property
    def n_texels(self) -> int:
        return self.store.n_pages * self.store.texels_per_page

    @property
    def nbytes(self) -> int:
        return self.store.nbytes

    def layers(self) -> list:
        return list(self.store.pools)

    def page_records(self) -> dict:
        """The built pages as numpy arrays: ``face``, ``level``, ``px``, ``py`` (page
        coordinates in the level), ``slot`` (in the pool), ``res`` (the level's
        resolution) and the page's ``uv`` rectangle on its face (``u0, v0, u1, v1``)."""
        keys, slots = self.store._index()
        P = self.layout.page_size
        rec = {name: f.astype(np.int64)
               for name, f in zip(("face", "level", "px", "py"), key_fields(keys))}
        rec["slot"] = slots
        rec["res"] = self.layout.res0 >> rec["level"]
        for name, c, off in (("u0", "px", 0), ("v0", "py", 0), ("u1", "px", 1), ("v1", "py", 1)):
            rec[name] = (rec[c] + off) * P / rec["res"].astype(np.float64)
        return rec

    def pages_numpy(self, layer: str = "depth") -> np.ndarray:
        """Layer ``layer`` of every built page, ``(n_pages, page_size, page_size)``, in
        the order of :meth:`page_records` (row j, column i of each page)."""
        P = self.layout.page_size
        data = self.store.pools[layer].numpy().reshape(-1, P, P)
        return data[self.store._index()[1]]

    def to_numpy(self, layer: str = "depth", level: int | None = None) -> np.ndarray:
        """Level ``level`` of layer ``layer`` as a dense ``(n_faces, res, res)`` float32
        array (row j, column i; ``res`` the level's resolution), like a full map's
        :meth:`~mi_shadowmap.depth_maps.ShadowMap.to_numpy`: the ray-cast tiles of the
        built pages in place, NaN where none was cast at that level (lookups read another
        level there).
        Default ``level``: the coarsest, one page per face, always built. A level of
        more than 2^26 texels is refused: read :meth:`pages_numpy` and
        :meth:`page_records` (or render with ``virtual=false`` for a full map)."""
        lay, P = self.layout, self.layout.page_size
        level = lay.coarsest if level is None else int(level)
        if not 0 <= level <= lay.coarsest:
            raise ValueError(f"shadowmap: virtual map '{lay.view.label}': level {level} "
                             f"does not exist; levels are 0 to {lay.coarsest}")
        if layer not in self.store.pools:
            raise KeyError(f"layer '{layer}' was not built for emitter '{lay.view.label}'; "
                           f"built: {', '.join(self.layers())}")
        res = lay.res0 >> level
        n_faces = lay.view.n_faces
        if n_faces * res * res > 2 ** 26:
            raise ValueError(
                f"shadowmap: virtual map '{lay.view.label}': level {level} is {n_faces} x "
                f"{res}^2 texels, more than 2^26 as one array; pick a coarser level (up to "
                f"{lay.coarsest}), or read pages_numpy() and page_records()")
        out = np.full((n_faces, res, res), np.nan, np.float32)
        rec = self.page_records()
        pages = self.pages_numpy(layer)
        T, S = lay.tile_size, lay.tiles_per_side
        for k in np.flatnonzero(rec["level"] == level):
            f, x, y = int(rec["face"][k]), int(rec["px"][k]) * P, int(rec["py"][k]) * P
            mask = int(self.store.slot_mask[rec["slot"][k]])
            for t in range(S * S):
                if (mask >> t) & 1:
                    i, j = (t % S) * T, (t // S) * T
                    out[f, y + j:y + j + T, x + i:x + i + T] = pages[k][j:j + T, i:i + T]
        return out

    # ----------------------------------------------------------- levels
    def level_for(self, face, p64, dp_dx, dp_dy, n=None, p=None, pixel=None,
                  shape=None) -> mi.UInt32:
        """Level whose texel matches the pixel footprint ``dp_dx``, ``dp_dy`` at
        ``p64`` on ``face``: ``floor(log2(w) + lod_bias)`` clamped to the levels,
        ``w`` the footprint in level-0 texels: the shorter side of its bounding box
        in the map's axes (``|du/dx| + |du/dy|`` and the same in ``v``), or 1/ANISO of
        the longer side if larger (not the footprint ellipse's minor axis: a footprint
        turned to the map's axes reads a level up to sqrt(2) coarser; the minor axis,
        probed, bought about what ``lod_bias`` buys for the same texels); at
        ``lod_bias = -0.5`` a texel is 0.35-0.7 of that. No footprint (no ray
        differentials): level 0, and the lookup walks to the finest level built.

        With the receiver's normal ``n`` and the method's receiver biases
        (``self.reach``, a :class:`~mi_shadowmap.filters.common.BiasReach`), no coarser
        than the level at which the biases lose an occluder's shadow over at most
        :data:`REACH_PIXELS` pixel footprints along the receiver (:meth:`_levels`). The
        biases scale with the texel, and where the light grazes the receiver they hide
        occluders up to about a texel above it, whose shadows fall ``tan(theta)`` times
        as far along it: at the footprint's level alone a point light in a box floating
        0.1 over a floor lit 2.4 % of a 64^2 image under ``hard`` (the coarsest level,
        its slope bias 1.6 units against the box wall 1.2-1.6 units in front of the
        floor; full maps of 64^2 texels a face: 0). ``pixel``, ``shape``: the lookups'
        film pixels (``Lookup.pixel``) and shapes, whose mark may have dropped the
        biases' level (:meth:`keeps`); None: the biases' level wherever it applies."""
        keep = None if pixel is None else VirtualShadowMap.keeps(self, pixel, shape)
        return self._levels(face, p64, dp_dx, dp_dy, n, p, keep=keep)[0]

    def _levels(self, face, p64, dp_dx, dp_dy, n=None, p=None, keep=None,
                probe: bool = False, active=None) -> tuple:
        """``(level, spread)``: :meth:`level_for`'s level, and where the biases chose it
        finer than the footprint's, half the footprint's bounding box in its texels
        (``mi.Point2f``, else 0): how far from the pixel's centre the pixel's samples
        read there, which the mark pass marks (:func:`~mi_shadowmap.virtual.marks._tile_range`).

        The biases' level: ``floor(log2(REACH_PIXELS f / (r t0)) + max(lod_bias + 1/2, 0))``,
        ``r`` how many texels along the receiver the biases may lose a shadow over
        (:meth:`~mi_shadowmap.filters.common.BiasReach.texels`, 0 for a receiver facing
        the light), ``f`` the footprint's length along the receiver's direction towards
        the light (the way a lost shadow runs) and ``t0`` a level-0 texel's world width
        at the point; a ``lod_bias`` coarser than the default -0.5 moves it as it moves the
        footprint's level (``2^(lod_bias + 1/2)`` times the footprints), a finer one does
        not: its footprint's level is finer already, and a cap moved with it chose levels
        up to 5 finer than that, on which a pixel spans hundreds of texels, far more than
        the mark pass builds around its centre (at ``lod_bias`` -4 on the boxed light of
        ``tests/test_virtual.py`` 16 % of the floor's lookups walked to the coarsest
        level, ``hard`` lit 458 pixels of 4096, 3 without the cap; now 3). ``p``: ``p64`` in
        float32 where the caller has it (:meth:`bind`: the lookup's point).

        ``keep`` (``mi.Bool`` per lane; None: everywhere): where the biases' level applies
        (with the method's ``virtual_edge``); elsewhere the footprint's level
        (``fallback``). The mark pass decides it per film pixel
        (:func:`~mi_shadowmap.virtual.marks.probe_keeps`) and the lookups read that
        pixel's decision (:meth:`bind`, ``keep``). With ``probe``: ``(level, spread,
        fallback, fallback_spread, length, edge)``, ``level`` and ``spread`` the biases'
        (``keep`` ignored), ``length`` where ``level`` is finer than ``fallback``: how far
        (world units) along the ray towards the light an occluder may lie and be hidden by
        the biases at ``fallback`` (0 elsewhere), and ``edge`` where the ``virtual_edge``
        alone chooses a level finer than ``fallback``: how far (world units) along the
        receiver its compares may move an occluder's edge at ``fallback`` (0 elsewhere;
        :func:`~mi_shadowmap.virtual.marks.marked_points` probes that far for an edge).

        The edge's level was the fallback, unprobed, until the forty-eighth session: where
        the light grazes the receiver (``tan(theta)`` up to ``max_tan_slope`` 20) it is up
        to 3 levels finer than the footprint's everywhere, edge or not, and
        ``second_depth`` built 27.5 texels a film pixel on ``random_terrain_world(15)`` at
        256^2 (sun 2-5 degrees; the footprint's level alone: 2.4; probed: 5.6); see
        ``benchmarks/RESULTS.md``, the forty-seventh session, helper F, and the
        forty-eighth, helper A. ``active``
        (``mi.Bool``; None: every lane): the lanes whose level is read; elsewhere any
        level may be returned (see the conditional below)."""
        view, lay = self.view, self.layout
        # the lookup's own point: the variable the receiver's biases read, so that Dr.Jit
        # computes the direction to the light once (the same value as from p64)
        p = mi.Point3f(p64) if p is None else p
        du_x = view.uv_differential(face, p, dp_dx)
        du_y = view.uv_differential(face, p, dp_dy)
        w = (dr.abs(du_x) + dr.abs(du_y)) * float(lay.res0)
        w_eff = dr.maximum(dr.minimum(w.x, w.y), dr.maximum(w.x, w.y) * (1.0 / ANISO))
        w_eff = dr.select(dr.isfinite(w_eff) & (w_eff > 1.0), w_eff, 1.0)
        # floor(log2(w) + lod_bias) is the binary exponent of w 2^lod_bias, a normal float
        # or +inf (w >= 1, |lod_bias| <= 8): read from its bits, not through a log2
        # polynomial (about 1 ns of a lookup's 6-13)
        lod_bias = effective_lod_bias(self.lod_bias, lay.page_size)
        scaled = w_eff * float(2.0 ** lod_bias)
        level = mi.Int32(dr.reinterpret_array(mi.UInt32, scaled) >> 23) - 127
        spread = mi.Point2f(0.0)
        fallback, fb_spread, length = level, spread, mi.Float(0.0)
        edge = mi.Float(0.0)
        reach = getattr(self, "reach", None)
        if n is not None and reach is not None:
            def biased(footprint):
                """``(level, spread, capped, cos_nl, sin_nl, t0, capped_level)``: the
                biases' level and spread, where they cap ``footprint`` (the footprint's
                level), and what the fallback and the probe read."""
                nn = dr.normalize(mi.Vector3f(n))
                to_light = view.direction_to_light(p)
                c = dr.dot(nn, to_light)
                along = to_light - nn * c            # towards the light along the receiver
                sin_nl = dr.norm(along)
                cos_nl = dr.clip(dr.abs(c), 1e-6, 1.0)
                f = (dr.abs(dr.dot(dp_dx, along)) + dr.abs(dr.dot(dp_dy, along))) \
                    / dr.maximum(sin_nl, 1e-30)
                t0 = view.texel_world_size(lay.res0, view.depth_of(p), p, nn)
                scale = REACH_PIXELS * 2.0 ** max(lod_bias + 0.5, 0.0)

                def capped_level(r, base):
                    """``(level, spread, capped)`` where a reach of ``r`` texels caps
                    ``base``, the level without it."""
                    # level-0 texels a texel may span (the same exponent trick)
                    allowed = scale * f / (r * t0)
                    cap = mi.Int32(dr.reinterpret_array(mi.UInt32, dr.maximum(allowed, 1.0))
                                   >> 23) - 127
                    capped = dr.isfinite(allowed) & (f > 0) & (cap < base)
                    lev = dr.select(capped, cap, base)
                    span = w * dr.exp2(-mi.Float(dr.clip(lev, 0, lay.coarsest)))
                    sp = dr.select(capped & dr.isfinite(span.x) & dr.isfinite(span.y),
                                   0.5 * span, mi.Point2f(0.0))
                    return lev, sp, capped

                lev, sp, capped = capped_level(reach.texels(cos_nl, sin_nl), footprint)
                return lev, sp, capped, cos_nl, sin_nl, t0, capped_level

            footprint = level
            if (keep is not None and not probe
                    and not dr.grad_enabled(n, p, dp_dx, dp_dy)):
                # The fallback is the footprint's level, and the biases'
                # level is computed in a conditional that only the vector packets with an
                # active lane that keeps it enter (0-0.4 % of the pixels of the
                # repository's scenes keep it; at 16 spp a packet of 16 lanes is one
                # pixel's samples). An inactive lane's level is never read (its reads are
                # masked, its result unused); ``keeps`` has such lanes keep, and with them
                # every packet holding a background sample entered. Computed for every
                # lane (a normal, a square root, 3 divisions) and thrown away nearly
                # everywhere, it cost the render kernel of ``hard`` at 256^2, 16 spp
                # (2 threads, medians of 16 alternated frames) 1.0 of far_point's 6.4 ms
                # over the unshadowed kernel, 1.1 of large_world's 8.0, 1.5 of
                # spot_sphere_box's 13; isolated lookups (one thread) 13-21 % of their time.
                cond = mi.Bool(keep) if active is None else mi.Bool(keep) & active
                level, spread = if_stmt(
                    (footprint, spread), cond,
                    lambda lev, sp: biased(lev)[:2], lambda lev, sp: (lev, sp),
                    label="virtual map: the receiver biases' level")
            else:
                level, spread, capped, cos_nl, sin_nl, t0, _ = biased(footprint)
                if probe:
                    fb = dr.clip(fallback, 0, lay.coarsest)
                    finer = capped & (dr.clip(level, 0, lay.coarsest) < fb)
                    t_fb = t0 * dr.exp2(mi.Float(fb))
                    # the height the biases hide at the fallback, as a distance along
                    # the ray towards the light
                    length = dr.select(finer, reach.height(cos_nl, sin_nl) * t_fb / cos_nl,
                                       0.0)
                    if reach.edge > 0.0:
                        # how far the edge's compares move a shadow's edge along the
                        # receiver at the fallback (``edge / cos(theta)`` texels: not
                        # clamped at ``max_tan`` as the level is), in world units
                        edge = dr.select(finer, reach.edge * t_fb / cos_nl, 0.0)
                elif keep is not None:
                    keep = mi.Bool(keep)
                    level = dr.select(keep, level, fallback)
                    spread = dr.select(keep, spread, fb_spread)
        out = (mi.UInt32(dr.clip(level, 0, lay.coarsest)), spread)
        if probe:
            out += (mi.UInt32(dr.clip(fallback, 0, lay.coarsest)), fb_spread, length, edge)
        return out

    def keeps(self, pixel, shape=None, active=True):
        """Where lookups on ``shape`` (``si.shape``; None: unknown) in film pixels
        ``pixel`` (``x + 65536 y``, :attr:`~mi_shadowmap.filters.common.Lookup.pixel`)
        read the biases' level (:meth:`_levels`' ``keep``), from the mark pass's word for
        the pixel (``self.keep``, :func:`~mi_shadowmap.virtual.planner._pixel_keeps`): on
        the shape of the pixel's centre where the centre's mark kept it after its probe
        (:func:`~mi_shadowmap.virtual.marks.probe_keeps`), or where the biases did not
        cap the centre and a neighbouring pixel on its shape kept it; on another shape
        (a silhouette's pixel) where a neighbouring pixel on another shape kept it.
        Marks and lookups then agree per pixel: a lookup wants a level its own pixel's
        mark, or those of the neighbours its decision came from, built (the
        forty-fourth session in ``benchmarks/RESULTS.md`` has the cases each rule
        fixed). None (the biases' level everywhere) without a pixel or without the
        mark's words; a pixel outside the film the mark saw keeps it."""
        if pixel is None or getattr(self, "keep", None) is None:
            return None
        words, width, count = self.keep
        pixel = mi.UInt32(pixel)
        x, y = pixel & 0xFFFF, pixel >> 16
        idx = x + y * width
        known = mi.Bool(active) & (x < width) & (idx < count)
        word = dr.gather(mi.UInt32, words, idx, known)
        if shape is None:
            return ~known | ((word & KEEP_CENTRE) != 0)
        same = (word & KEEP_SHAPE) == (dr.reinterpret_array(mi.UInt32, shape) & KEEP_SHAPE)
        return ~known | ((word & dr.select(same, mi.UInt32(KEEP_CENTRE),
                                           mi.UInt32(KEEP_OTHERS))) != 0)

    def _block_entry(self, face, level, bx, by, active):
        """``(e, ok)``: where in ``dense`` the 2 x 2 pages whose lower-left page is
        ``(bx, by)`` at ``(face, level)`` have their 4 slots (``e`` to ``e + 3``), and
        whether the table has that block: the level's header (two 64-bit words, see
        :meth:`PageStore.table`), then plain arithmetic. Plain gathers: Dr.Jit's packet
        gathers (``mi.Vector4u``) were as fast here but made the render kernel depend on
        the table's size, so a camera move compiled a new kernel."""
        h = (mi.UInt32(face) * self.layout.n_levels + mi.UInt32(level)) * 2
        w0 = dr.gather(mi.UInt64, self.header, h, active)
        w1 = dr.gather(mi.UInt64, self.header, h + 1, active)
        x0 = dr.reinterpret_array(mi.Int32, mi.UInt32(w0))
        y0 = dr.reinterpret_array(mi.Int32, mi.UInt32(w0 >> 32))
        wh = mi.UInt32(w1)
        W, H = mi.Int32(wh & 0xFFFF), mi.Int32(wh >> 16)
        lx, ly = bx - x0, by - y0
        ok = mi.Bool(active) & (lx >= 0) & (ly >= 0) & (lx < W) & (ly < H)
        e = (mi.UInt32(w1 >> 32) + mi.UInt32(ly * W + lx)) * 4
        return e, ok

    def _block_at(self, face, level, uv64, active):
        """``(res, xy, bx, by, e, eok)``: the resolution of ``level`` (per lane), ``uv64``
        (float64 uv of ``face``) in its texels, the lower-left page ``(bx, by)`` of the
        2 x 2 pages around the point, and their entry in the table
        (:meth:`_block_entry`)."""
        P = self.layout.page_size
        res = mi.Int32(mi.UInt32(self.layout.res0) >> level)
        xy = uv64 * mi.Float64(res)
        bx = mi.Int32(dr.floor((xy.x - 0.5 * P) / P))
        by = mi.Int32(dr.floor((xy.y - 0.5 * P) / P))
        e, eok = self._block_entry(face, level, bx, by, active)
        return res, xy, bx, by, e, eok

    def _own_page(self, xy, bx, by):
        """Which of the 2 x 2 pages whose lower-left page is ``(bx, by)`` holds the texel
        at ``xy`` (:meth:`_block_at`): 0-3, the offset of its slot from the entry."""
        P = self.layout.page_size
        cx = mi.Int32(dr.floor(xy.x / P)) > bx
        cy = mi.Int32(dr.floor(xy.y / P)) > by
        return mi.UInt32(dr.select(cx, 1, 0) + dr.select(cy, 2, 0))

    def _tile_bit(self, xy):
        """The bit of the tile holding the texel at ``xy`` in its page's tile word."""
        lay = self.layout
        P, T = lay.page_size, lay.tile_size
        ix = mi.UInt32(mi.Int32(dr.floor(xy.x)) & (P - 1)) // T
        iy = mi.UInt32(mi.Int32(dr.floor(xy.y)) & (P - 1)) // T
        return ix + iy * lay.tiles_per_side

    def _built_at(self, xy, bx, by, e, eok):
        """Whether the page holding the texel at ``xy`` among the 2 x 2 pages of table
        entry ``e`` (:meth:`_block_at`) is built, and with tiles, the tile under it
        ray-cast (not the coarsest level's fill): this frame's tiles alone
        (:meth:`tile_marked`)."""
        own = dr.gather(mi.UInt32, self.dense, e + self._own_page(xy, bx, by), eok)
        built = eok & (own != INVALID_SLOT)
        if self.layout.tiles_per_side > 1:
            tiles = dr.gather(mi.UInt32, self.tile_masks, own, built)
            built &= ((tiles >> self._tile_bit(xy)) & 1) != 0
        return built

    def tile_marked(self, face, uv64, level, active=True):
        """Whether this frame's marks built the tile under the points at ``uv64`` of
        ``face`` (float64 uv, per lane) at ``level`` (per lane; ``mi.Bool``): its page in
        the frame's page table and the tile among the frame's marked tiles, what a tap
        there reads (:meth:`BoundVirtualMap._index`; elsewhere it reads the coarsest
        level). The page table holds this frame's tiles alone (:meth:`PageStore.table`
        with a frame; ``bind``'s walk reads the same tiles by slot), not every tile an
        earlier view built: a kernel choosing its level by those would make the image
        depend on earlier views (``tests/test_page_cache_paths.py``)."""
        _, xy, bx, by, e, ok = self._block_at(face, mi.UInt32(level), uv64, active)
        return self._built_at(xy, bx, by, e, ok)

    def with_view(self, view) -> "VirtualShadowMap":
        """This map read through ``view``, a view of some of its faces with the same
        float64 interface (an environment's region ``k``, per lane: its shading loop)."""
        out = copy.copy(self)
        out.view = view
        return out

    def bind(self, lk, active=True, per_tap: bool = False,
             walk: bool = True, level=None, projected=None) -> "BoundVirtualMap":
        """The map as one batch of lookups reads it (see the module doc). With
        ``per_tap`` every read gathers its own page's slot (cheapest for lookups that
        read a texel or two: ``hard``); else the 2 x 2 pages' four slots are gathered
        here, once per lookup (wide kernels). With ``walk`` False (``per_tap`` only) every
        lane stays at its wanted level and each read checks that its own page and tile
        are built there, collecting the lanes where one is not in the result's
        ``missed`` (:meth:`visibility` runs those again, walked; what such a read gives
        is no texel's depth, and must not be used). ``level`` (per lane,
        clamped to the coarsest): the level wanted instead of the pixel footprint's (a
        PCSS kernel wider than ``max_kernel`` texels filters a coarser level); the walk
        is the same. ``projected``: ``(face, uv64, depth64, inside)``, the float64
        projection of ``lk.p_world`` an earlier bind of the same point made
        (:attr:`BoundVirtualMap.projected`), not traced again (:meth:`visibility`'s second
        run: inside its conditional Dr.Jit does not merge repeated operations: 48 of the
        1725 of far_point's render kernel of ``hard``; LLVM merged most of them in the
        machine code already, so what this saves is the trace and Dr.Jit's code
        generation of every frame)."""
        lay = self.layout
        p64 = mi.Point3d(lk.p_world) if projected is None or level is None else None
        face, uv64, depth64, inside = (self.view.project_f64(p64) if projected is None
                                       else projected)
        active = mi.Bool(active) & inside
        want = (self._levels(face, p64, lk.dp_dx, lk.dp_dy, lk.n_world, lk.p_world,
                             keep=self.keeps(getattr(lk, "pixel", None),
                                             getattr(lk.si, "shape", None), active),
                             active=active)[0]
                if level is None
                else dr.minimum(mi.UInt32(level), mi.UInt32(lay.coarsest)))

        def block(level, act, walked: bool = True):
            """The 2 x 2 pages around the point at ``level`` (their table entry), and
            whether the page under it is built (None unless ``walked``: only the walk
            reads it; unread, its two gathers were no part of the kernel, but were traced
            every frame)."""
            res, xy, bx, by, e, eok = self._block_at(face, level, uv64, act)
            if not walked:
                return res, bx, by, e, eok, None
            return res, bx, by, e, eok, self._built_at(xy, bx, by, e, eok)

        # the wanted level (nearly every lookup); else the next finer, else the nearest
        # coarser level built there, one level at a time up to the coarsest (always
        # built). The biases scale with the texel, so the nearest coarser level is the
        # one that hides the least: where the marks had not built the wanted level under
        # a sample (a pixel's footprint longer than the marks' MAX_SPREAD at the biases'
        # level: a tower wall the sun grazes, ``random_terrain_world(15)``), the walk
        # skipped the levels 2 to 12 coarser that its neighbours had built and read the
        # coarsest, whose slope bias (3 km there) lit occluded samples: 5 pixels of that
        # wall shadowed in both references read 0.25-0.63. The fallbacks run in a loop
        # that only lanes whose page is missing enter: most vector packets skip it.
        res, bx, by, e, eok, ok = block(want, active, walk)
        level = mi.UInt32(want)
        if not walk:
            if not per_tap:
                raise ValueError("VirtualShadowMap.bind: walk=False needs per_tap=True")
            return self._bound(lk, face, uv64, depth64, inside, res, level, bx, by, e, eok,
                               per_tap, check_reads=True)
        step = mi.UInt32(0)
        want_i = mi.Int32(want)

        def cond(step, level, res, bx, by, e, eok, ok):
            return active & ~ok

        def body(step, level, res, bx, by, e, eok, ok):
            # step 0: the next finer level; step k > 0: k levels coarser
            lev = dr.select(step == 0, dr.maximum(want_i - 1, 0),
                            dr.minimum(want_i + mi.Int32(step), lay.coarsest))
            r2, bx2, by2, e2, eok2, ok2 = block(mi.UInt32(lev), mi.Bool(True))
            take = ok2 | (lev == lay.coarsest)
            return (step + 1, dr.select(take, mi.UInt32(lev), level),
                    dr.select(take, r2, res), dr.select(take, bx2, bx),
                    dr.select(take, by2, by), dr.select(take, e2, e),
                    dr.select(take, eok2, eok), ok | take)

        state = dr.while_loop((step, level, res, bx, by, e, eok, ok), cond, body)
        _, level, res, bx, by, e, eok, _ = state
        return self._bound(lk, face, uv64, depth64, inside, res, level, bx, by, e, eok,
                           per_tap)

    def _bound(self, lk, face, uv64, depth64, inside, res, level, bx, by, e, eok, per_tap,
               check_reads=False) -> "BoundVirtualMap":
        P = self.layout.page_size
        slots = tile_words = None
        if not per_tap:
            slots = [dr.select(eok, dr.gather(mi.UInt32, self.dense, e + k, eok), INVALID_SLOT)
                     for k in range(4)]
            if self.layout.tiles_per_side > 1 and not check_reads:
                tile_words = [dr.gather(mi.UInt32, self.dense_tiles, e + k, eok)
                              for k in range(4)]
        origin = mi.Point2i(bx * P, by * P)
        local = LocalView(self.view, face, res, origin, (lk.p_world, uv64, depth64, inside),
                          depth_origin=self.depth_origin, lazy_frame=per_tap)
        return BoundVirtualMap(self, local, res, level, (e, eok), slots, check_reads, inside,
                               tile_words, projected=(face, uv64, depth64, inside))

    def visibility(self, lookup, lk, opts, active=True, per_tap: bool = False) -> mi.Float:
        """``lookup(bound, lk, opts, active)`` (a method's lookup) on this map.

        With ``per_tap`` (``hard``) the lookup first runs at every lane's wanted level,
        each read checking its own page and tile (gathered with its slot), and a symbolic
        ``dr.if_stmt`` runs it again, :meth:`bind`'s walk included, for the lanes where a
        read found one missing (a vector packet without such a lane skips it). A lane
        whose texel is built at its wanted level reads it there; every other lane gets
        what the walk gives. The bound point's own page and tile are then not read
        before the texel's address: 2 of a ``hard`` lookup's 6 gathers (1-1.5 ns of
        5-12 ns on ``bench_virtual_lookup.py``'s hits). The second run must not draw
        random numbers (its lanes would draw twice): a per-tap lookup that calls
        ``lk.sampler`` gets a :class:`~mi_shadowmap.methods.MethodError` there. In a
        render with gradients (``lk``'s point or normal tracking them) and for the other
        methods, the lookup runs once, walked.

        The integrator runs all of it (projection, level, page table, reads, a per-tap
        lookup's second run) only in the vector packets with an active lane
        (:func:`mi_shadowmap.packets.in_lit_packets`, as for full maps)."""
        if dr.grad_enabled(lk.p_world, lk.n_world):
            return lookup(self.bind(lk, active, per_tap), lk, opts, active)
        if per_tap:         # draws nothing (see above)
            return self._per_tap_visibility(lookup, lk, opts, active)
        return mi.Float(lookup(self.bind(lk, active, False), lk, opts, active))

    def _per_tap_visibility(self, lookup, lk, opts, active) -> mi.Float:
        """:meth:`visibility` of a per-tap lookup: unwalked at every lane's wanted level,
        then walked, in a conditional, for the lanes whose read found its page or tile
        missing."""
        first = self.bind(lk, active, True, walk=False)
        vis = mi.Float(lookup(first, lk, opts, active))
        if first.missed is None:       # the lookup read no texel
            return vis
        retry = mi.Bool(active) & first.inside & first.missed
        again = dataclasses.replace(lk, sampler=None if lk.sampler is None
                                    else _NoDraws(lk.sampler))

        def walked(vis):
            # the first run's wanted level (its level, unwalked): level_for is not traced
            # again inside the conditional (Dr.Jit does not share values across it: the
            # footprint and the biases' cap, about 180 of a hard lookup's 2000 operations)
            # nor the point's projection (the same point: the same float64 values)
            return mi.Float(lookup(self.bind(again, retry, True, level=first.level,
                                             projected=first.projected), again, opts, retry))

        return if_stmt((vis,), retry, walked, lambda vis: vis,
                       label="virtual map: lookups whose page is missing", holds_loops=True)


class _NoDraws:
    """A sampler for :meth:`VirtualShadowMap.visibility`'s second run of a per-tap
    lookup: drawing from it is an error; other attributes are the sampler's."""

    def __init__(self, sampler):
        self._sampler = sampler

    def _refuse(self, *args, **kwargs):
        raise MethodError("shadowmap: a lookup with virtual_per_tap=True runs again for "
                          "lanes whose virtual page is missing and must not draw random "
                          "numbers (lk.sampler.next_1d/next_2d); register it with "
                          "virtual_per_tap=False")

    next_1d = next_2d = _refuse

    def __getattr__(self, name):
        return getattr(self._sampler, name)


class BoundVirtualMap:
    """A :class:`VirtualShadowMap` bound to one batch of lookups: what filters read.

    ``resolution`` is the per-lane level resolution (``mi.Int32``), ``view`` a
    :class:`~mi_shadowmap.light_views.local.LocalView`, ``depth`` and ``extra``
    the physical pools; :meth:`fetch` and :meth:`texel_index` translate local
    texels into pool indices.
    """

    def __init__(self, vmap: VirtualShadowMap, view: LocalView, res, level, entry,
                 slots=None, check_reads: bool = False, inside=True, tile_words=None,
                 projected=None):
        self.vmap = vmap
        # (face, uv64, depth64, inside): the bound point's float64 projection (for
        # VirtualShadowMap.bind's ``projected``)
        self.projected = projected
        self.view = view
        self.resolution = res
        self.level = level
        self.entry = entry      # (where the 2 x 2 pages' slots are in the table, valid)
        self.slots = slots      # their 4 slots, or None: gathered per read
        self.inside = inside    # the point projects into the map (else read as lit)
        # bound unwalked (VirtualShadowMap.visibility): reads check their page and tile,
        # and ``missed`` collects the lanes where one is missing (None before a read)
        self.check_reads = check_reads
        self.missed = None
        # the 2 x 2 pages' tile masks of this frame (VirtualShadowMap._bound, with
        # ``slots``), or None: gathered per read
        self.tile_words = tile_words
        self._scope = dr.flag(dr.JitFlag.SymbolicScope)
        pools = vmap.store.pools
        self.depth = pools.get("depth", mi.Float())   # (none: read, an error as traced)
        self.extra = {k: v for k, v in pools.items() if k != "depth"}
        self.extra["pcss_near"] = vmap.face_near if vmap.store.casts_depth else mi.Float()
        self.depth_bounds = vmap.depth_bounds

    @property
    def second_depth(self):
        return self.extra.get("second_depth")

    def _index(self, face, i, j):
        """Pool index of local texel ``(i, j)`` of ``face`` (clamped to the face)."""
        lay, P = self.vmap.layout, self.vmap.layout.page_size
        v = self.view
        res = self.resolution
        gx = dr.clip(mi.Int32(i) + v.origin.x, 0, res - 1)
        gy = dr.clip(mi.Int32(j) + v.origin.y, 0, res - 1)
        li, lj = gx - v.origin.x, gy - v.origin.y
        in_block = (mi.UInt32(face) == v.face) & (li >= 0) & (lj >= 0) & (li < 2 * P) \
            & (lj < 2 * P)
        q = dr.select(li >= P, 1, 0) + dr.select(lj >= P, 2, 0)
        e, eok = self.entry
        m = eok & in_block              # the table has the block (read per tap only)
        if self.slots is None:
            s = dr.select(m, dr.gather(mi.UInt32, self.vmap.dense, e + mi.UInt32(q), m),
                          INVALID_SLOT)
        else:
            s = _pick(self.slots, q)
        fine = in_block & (s != INVALID_SLOT)
        if self.check_reads:     # and its tile ray-cast; else this lane runs again, walked
            if dr.flag(dr.JitFlag.SymbolicScope) and not self._scope:
                raise MethodError("shadowmap: a lookup with virtual_per_tap=True must read "
                                  "the map outside symbolic loops and conditionals "
                                  "(dr.while_loop, dr.if_stmt: its reads decide which lanes "
                                  "run again, walked); register it with "
                                  "virtual_per_tap=False")
            tiles = dr.gather(mi.UInt32, self.vmap.dense_tiles, e + mi.UInt32(q), m)
            S = lay.tiles_per_side
            t = mi.UInt32(li & (P - 1)) // lay.tile_size \
                + mi.UInt32(lj & (P - 1)) // lay.tile_size * S
            fine &= ((tiles >> t) & 1) != 0
            self.missed = ~fine if self.missed is None else self.missed | ~fine
        if self.vmap.far_taps and not self.check_reads:
            # a tap beyond the bound 2 x 2 pages (a wide kernel: PCSS's blocker search, a
            # PCF region): its own page at this level, through the page table, where the
            # neighbouring points had it built; else the coarsest level. Reading the
            # coarsest level for every such tap compared texels 4-16 times as wide with
            # the receiver plane along the tap's own ray: PCSS on contact_hardening
            # misclassified 1.69 % of a 128^2 image, 1.07 % now (full maps: 1.06 %)
            far = ~in_block
            e2, ok2 = self.vmap._block_entry(face, self.level, gx // P, gy // P, far)
            s2 = dr.gather(mi.UInt32, self.vmap.dense, e2, ok2)   # corner 0: that page
            s = dr.select(far, dr.select(ok2, s2, INVALID_SLOT), s)
            fine = dr.select(far, s != INVALID_SLOT, fine)
        fine_idx = s * (P * P) + mi.UInt32(lj & (P - 1)) * P + mi.UInt32(li & (P - 1))
        # where the texel read was cast (fetch_centre), for the read fetch_centre makes:
        # traced there only (hard never asks)
        self._read_at = (fine, li, lj, gx, gy)
        if self.check_reads:
            # a lane whose read is not here runs again, walked, and only that run's value
            # is used (VirtualShadowMap.visibility): no coarsest-level index for it (10
            # operations every packet ran); texel 0 of the pool, a valid address, instead
            return dr.select(fine, fine_idx, 0)
        # elsewhere: the coarsest level (one page per face, always built, in slot
        # face + 1; an empty page where a one-sided light does not shine)
        shift = mi.Int32(lay.coarsest) - mi.Int32(self.level)
        cx, cy = gx >> shift, gy >> shift
        coarse_idx = (mi.UInt32(face) + 1) * (P * P) + mi.UInt32(cy) * P + mi.UInt32(cx)
        cast = fine
        if not self.check_reads and lay.tiles_per_side > 1:
            # a tile this frame did not mark reads the coarsest level's texel over it,
            # what a new page holds there (PageStore._fill_from_coarsest), at its own
            # texel's centre: not what an earlier frame may have cast into the slot (a
            # ``pcf`` kernel reaching past the tiles its point marked read depths cast
            # for another camera; a camera moved and put back changed pixels)
            if self.tile_words is None:
                tw = dr.gather(mi.UInt32, self.vmap.dense_tiles, e + mi.UInt32(q), m)
            else:
                tw = _pick(self.tile_words, q)
            if self.vmap.far_taps:
                tw = dr.select(far, dr.gather(mi.UInt32, self.vmap.dense_tiles, e2, ok2), tw)
            S, T = lay.tiles_per_side, lay.tile_size
            t = mi.UInt32(gx & (P - 1)) // T + mi.UInt32(gy & (P - 1)) // T * S
            cast = fine & (((tw >> t) & 1) != 0)
        return dr.select(cast, fine_idx, coarse_idx)

    def fetch(self, layer, face, i, j, active=True):
        return dr.gather(mi.Float, layer, self._index(face, i, j), active)

    def fetch_centre(self, layer, face, i, j, active=True):
        """``(value, point)``: :meth:`fetch` and the point, in this lookup's local
        texel coordinates, whose ray gave the texel it read (``TEXEL_SAMPLE``): in the
        texel itself where its page is built, else in the coarsest level's texel that
        holds it (2^k texels wide)."""
        z = self.fetch(layer, face, i, j, active)
        fine, li, lj, gx, gy = self._read_at
        shift = mi.Int32(self.vmap.layout.coarsest) - mi.Int32(self.level)
        cx, cy = gx >> shift, gy >> shift
        ts = mi.Point2f(*TEXEL_SAMPLE)           # where each texel's ray crosses it
        return z, dr.select(
            fine, mi.Point2f(li, lj) + ts,
            (mi.Point2f(cx, cy) + ts) * dr.power(2.0, mi.Float(shift))
            - mi.Point2f(self.view.origin))

    def texel_index(self, face, uv):
        ij = mi.Point2i(dr.floor(uv * self.resolution))
        return self._index(face, ij.x, ij.y)

    def clamp_texel(self, ij):
        v = self.view
        g = dr.clip(mi.Point2i(ij) + v.origin, 0, self.resolution - 1)
        return g - v.origin


def _pick(words: list, q):
    """``words[q]`` per lane, for the 2 x 2 pages' four words (``q`` 0-3)."""
    return dr.select(q == 0, words[0], dr.select(q == 1, words[1],
                     dr.select(q == 2, words[2], words[3])))
