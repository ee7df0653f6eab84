"""The physical pages of one emitter's virtual map: the page pool (one array per layer),
the page table lookups read, and the ray casts that fill pages.
"""
from __future__ import annotations

import warnings

import drjit as dr
import mitsuba as mi
import numpy as np

from ..depth_maps import first_hit, second_depth_along
# what a page holds is the method's (methods.py: options and map_manager read it too)
from ..methods import casts_first_depth, page_bytes, page_layers, page_pools  # noqa: F401
from ..light_views.base import TEXEL_SAMPLE
from .layout import (MAX_TABLE, MAX_TABLE_SIDE, INVALID_SLOT, VirtualLayout, key_fields,
                     padded_array, page_key)

#: Marks of different keys a store remembers (:meth:`PageStore.recall_mark`): methods of
#: different margins rendered in turn on one store, still camera.
MARK_MEMO = 4
#: What a store's page tables other than the latest may hold together (bytes): a few are
#: kept for those renders (:meth:`PageStore.table`).
KEPT_TABLE_BYTES = 32 << 20


def _recall(entries: list, key):
    """The entry of ``entries`` (tuples, ``key`` first; the latest last) whose key is
    ``key``, moved to the end as the latest; None if none is."""
    for k, entry in enumerate(entries):
        if entry[0] == key:
            entries.append(entries.pop(k))
            return entry
    return None


class PageStore:
    """The physical pages of one emitter's virtual map, kept across renders.

    ``slots``: page key -> slot (a view of the built pages, kept as two arrays); the
    pool of each layer (``pools``, :func:`page_pools`: no ``depth`` pool where the
    pages cast no first depth) holds ``capacity``
    pages of ``page_size^2`` float32 texels; ``slot_frame``: the frame each slot was
    last read in (least recently used pages are evicted first).
    """

    def __init__(self, layout: VirtualLayout, layers: tuple):
        self.layout = layout
        self.layers = tuple(layers)
        # the built pages: key and slot, in the order they were built
        self._keys = np.zeros(0, np.uint64)
        self._slot_of = np.zeros(0, np.int64)
        self.free: list = []
        self.capacity = 0
        # whether the pages' first depths are ray-cast (not for a method that reads its
        # second depths alone: casts_first_depth); the pools are the layers held, no
        # first-depth pool without (page_pools)
        self.casts_depth = casts_first_depth(self.layers)
        self.pools = {name: mi.Float() for name in page_pools(self.layers)}
        # nearest finite depth per slot and tile (its tiles ray-cast so far; +inf else;
        # the second depths where no first depth is cast)
        self.tile_min = np.zeros((0, layout.tiles_per_side ** 2), np.float64)
        self.page_face = np.zeros(0, np.int64)
        self.slot_frame = np.zeros(0, np.int64)      # frame each slot was last read
        self.slot_mask = np.zeros(0, np.int64)       # tiles built per slot (bit per tile)
        self.pages_cast = 0                          # pages the last build cast tiles of
        self.cast_seconds = 0.0                      # all builds' ray casting ...
        self.cast_pages = 0                          # ... and the pages they cast
        self.frame = 0
        self.version = 0                             # changes whenever pages do
        self._sorted = None
        self._looked = None       # the last lookup: (version, keys, present, slots)
        # the last build's ``(keys, slots)``: every key's slot, once built (the planner
        # reads its pages' slots there, not from a lookup after the build)
        self.built_slots = None
        # the last MARK_MEMO tables, (token, arrays, bytes), latest last
        self._tables = []
        self.lit_faces = None                        # faces a one-sided light shines through
        # the planner's last (marks, coarsest keys, tiles, pages) and (marks, tiles, budget,
        # fit): a still camera's frame plans from them (planner.prepare_virtual)
        self.plan_memo = None
        self.fit_memo = None
        self.dark_memo = None      # planner._dark's watch of the light's emitted values
        self.coarse_keys = None                      # their coarsest pages' keys
        # slot 0 is never allocated: an empty page (+inf, lit). Slot f + 1 is reserved for
        # face f's coarsest page (always built where the light shines; empty where a
        # one-sided light does not), so a lookup finds it without a gather
        self.next_slot = 1 + layout.view.n_faces
        # the last MARK_MEMO marks of different keys, the latest last (last_mark): each
        # ((camera state, margin, coarse_res, lod_bias, reach), marked tile keys, those of
        # them only coarser-level kernels read)
        self.recent_marks = []
        # the last render's (last_mark, budget, version, needed keys, their slots, level
        # histogram, pages degraded): a render with the same three reuses the rest
        self.settled = None
        self.max_pages = 1 << 62      # the memory budget's pages (set per render)

    def recall_mark(self, key) -> bool:
        """Make the remembered mark of ``key`` (camera state, margin, coarse_res,
        lod_bias, reach) :attr:`last_mark`; False if none is remembered. A mark depends on
        its key, the light's view and the scene's shapes alone (a store is keyed by the
        latter two), so methods of different margins sharing this store (``hard`` and
        ``pcf`` hold the same layers) each keep theirs: rendered in turn with a still
        camera, each re-marked every frame before (a mark pass: 4 kernels and the camera
        hits, a few ms at 256^2)."""
        return _recall(self.recent_marks, key) is not None

    def remember_mark(self, mark) -> None:
        """:attr:`last_mark` = ``mark``, remembered among the last :data:`MARK_MEMO`."""
        self.recent_marks = [m for m in self.recent_marks if m[0] != mark[0]][
            -(MARK_MEMO - 1):] + [mark]

    @property
    def last_mark(self):
        """The latest mark (:meth:`recall_mark`, :meth:`remember_mark`), or None."""
        return self.recent_marks[-1] if self.recent_marks else None

    @property
    def n_pages(self) -> int:
        return len(self._keys)

    @property
    def slots(self) -> dict:
        """Page key -> slot of every built page."""
        return dict(zip(self._keys.tolist(), self._slot_of.tolist()))

    @property
    def texels_per_page(self) -> int:
        return self.layout.page_size ** 2

    @property
    def nbytes(self) -> int:
        return self.capacity * self.texels_per_page * 4 * len(self.pools)

    @property
    def n_slots(self) -> int:
        """Slots in use or reserved (the pages, the freed slots, the empty page and the
        coarsest page's slot of every face, built or not)."""
        return self.next_slot

    def _grow(self, need: int) -> None:
        if need <= self.capacity:
            return
        cap = max(2 * need, 2 * self.capacity, 16)   # growth is rare (and compiles once)
        cap = max(min(cap, self.max_pages), need)
        n_old = self.capacity * self.texels_per_page
        for name, pool in self.pools.items():
            new = dr.full(mi.Float, dr.inf, cap * self.texels_per_page)
            if n_old:
                dr.scatter(new, pool, dr.arange(mi.UInt32, n_old))
            self.pools[name] = new
        self.tile_min = np.concatenate([self.tile_min, np.full(
            (cap - self.capacity, self.tile_min.shape[1]), np.inf)])
        self.page_face = np.concatenate([self.page_face, np.zeros(cap - self.capacity, np.int64)])
        self.slot_frame = np.concatenate([self.slot_frame, np.zeros(cap - self.capacity, np.int64)])
        self.slot_mask = np.concatenate([self.slot_mask, np.zeros(cap - self.capacity, np.int64)])
        self.capacity = cap
        dr.eval(*self.pools.values())

    def shrink(self, max_slots: int) -> None:
        """Reallocate the pools to ``max_slots`` slots (a later render's smaller
        ``memory_budget``, or this map's smaller share of it): pages in slots from
        ``max_slots`` on move to unused slots below it (the caller evicted enough pages
        first). Without this a pool kept the largest size any render gave it."""
        fixed = 1 + self.layout.view.n_faces     # the empty page, the coarsest pages
        max_slots = max(int(max_slots), fixed)
        if self.capacity <= max_slots:
            return
        high = self._slot_of >= max_slots
        used = np.zeros(max_slots, bool)
        used[:fixed] = True
        used[self._slot_of[~high]] = True
        holes = np.flatnonzero(~used)
        n_high = int(high.sum())
        if n_high > len(holes):
            raise RuntimeError(f"shadowmap: virtual map '{self.layout.view.label}': "
                               f"{self.n_pages} pages do not fit {max_slots} slots")
        src = np.arange(max_slots, dtype=np.int64)      # new slot -> old slot
        src[holes[:n_high]] = self._slot_of[high]
        tpp = self.texels_per_page
        idx = dr.arange(mi.UInt32, max_slots * tpp)
        slot = idx // tpp
        old = dr.gather(mi.UInt32, padded_array(mi.UInt32, src.astype(np.uint32)), slot)
        old = old * tpp + (idx - slot * tpp)
        for name, pool in self.pools.items():
            self.pools[name] = dr.gather(mi.Float, pool, old)
        dr.eval(*self.pools.values())
        self.tile_min = self.tile_min[src]
        self.page_face = self.page_face[src]
        self.slot_frame = self.slot_frame[src]
        self.slot_mask = self.slot_mask[src]
        self._slot_of = self._slot_of.copy()
        self._slot_of[high] = holes[:n_high]
        used[holes[:n_high]] = True
        self.next_slot = int(np.flatnonzero(used).max()) + 1
        self.free = np.flatnonzero(~used[:self.next_slot]).tolist()
        self.capacity = max_slots
        self.version += 1
        self.settled = None

    def _index(self):
        """``(keys, slots)`` sorted by key, rebuilt when the pages change."""
        if self._sorted is None or self._sorted[0] != self.version:
            order = np.argsort(self._keys)
            self._sorted = (self.version, self._keys[order], self._slot_of[order])
        return self._sorted[1], self._sorted[2]

    def lookup(self, keys: np.ndarray):
        """``(present, slot)`` of each of ``keys`` (slot -1 where absent); the same arrays
        again for the same ``keys`` object while the pages have not changed (a camera
        move looks its pages up before evicting, then in the build: one lookup where
        no page was evicted). Read-only: copy before writing to them."""
        hit = self._looked
        if hit is not None and hit[0] == self.version and hit[1] is keys:
            return hit[2], hit[3]
        k, sl = self._index()
        if len(k) == 0:
            out = np.zeros(len(keys), bool), np.full(len(keys), -1, np.int64)
        else:
            pos = np.clip(np.searchsorted(k, keys), 0, len(k) - 1)
            present = k[pos] == keys
            out = present, np.where(present, sl[pos], -1)
        self._looked = (self.version, keys, *out)
        return out

    def evict(self, keep: np.ndarray, n: int) -> int:
        """Free up to ``n`` slots of pages not in ``keep`` and not of the coarsest level
        (least recently used first)."""
        k, sl = self._index()
        coarse = ((k >> np.uint64(54)) & np.uint64(31)) == np.uint64(self.layout.coarsest)
        cand = ~np.isin(k, keep) & ~coarse
        order = np.argsort(self.slot_frame[sl[cand]], kind="stable")[:n]
        victims = k[cand][order]
        self.free.extend(sl[cand][order].tolist())
        kept = ~np.isin(self._keys, victims)
        self._keys, self._slot_of = self._keys[kept], self._slot_of[kept]
        self.version += 1
        return len(victims)

    def build(self, scene, keys: np.ndarray, masks: np.ndarray | None = None) -> int:
        """Ray-cast the tiles ``masks`` (a bit per tile, :attr:`VirtualLayout.tile_size`;
        default: every tile) of the pages ``keys`` that are not built yet; pages not in
        the store get free slots, and their other tiles the coarsest level's depths (what
        a tap beyond the lookup's 2 x 2 pages reads). Returns the texels ray-cast.
        (:meth:`plan_build`, :func:`cast_tiles` and :meth:`finish_build`: the planner
        casts every light's tiles of a render in one kernel.)"""
        job = self.plan_build(keys, masks)
        cast_tiles(scene, [job])
        return self.finish_build(job)

    def plan_build(self, keys: np.ndarray, masks: np.ndarray | None = None) -> "TileCast":
        """The first part of :meth:`build`: slots for the pages ``keys`` not in the store,
        and the tiles to cast (a :class:`TileCast` for :func:`cast_tiles`)."""
        self.pages_cast = 0
        self.built_slots = None
        job = TileCast(self)
        if len(keys) == 0:
            self.built_slots = (keys, np.zeros(0, np.int64))
            return job
        lay = self.layout
        S = lay.tiles_per_side
        keys = np.asarray(keys, np.uint64)
        masks = (np.full(len(keys), lay.full_mask, np.int64) if masks is None
                 else np.asarray(masks, np.int64))
        coarse = ((keys >> np.uint64(54)) & np.uint64(31)) == np.uint64(lay.coarsest)
        masks = np.where(coarse, lay.full_mask, masks)     # the coarsest pages: whole
        present, slot_ids = self.lookup(keys)
        slot_ids = slot_ids.copy()      # (the lookup's, kept for the same keys)
        new = ~present
        new_fine = new & ~coarse
        n_fine = int(new_fine.sum())
        reuse = [self.free.pop() for _ in range(min(n_fine, len(self.free)))]
        first = self.next_slot
        fresh = list(range(first, first + n_fine - len(reuse)))
        self.next_slot += len(fresh)
        self._grow(self.next_slot)
        slot_ids[new & coarse] = (keys[new & coarse] >> np.uint64(59)).astype(np.int64) + 1
        slot_ids[new_fine] = np.array(reuse + fresh, dtype=np.int64)
        if new.any():
            self._keys = np.concatenate([self._keys, keys[new]])
            self._slot_of = np.concatenate([self._slot_of, slot_ids[new]])
            self.slot_mask[slot_ids[new]] = 0
            self.tile_min[slot_ids[new]] = np.inf
            self.page_face[slot_ids[new]] = (keys[new] >> np.uint64(59)).astype(np.int64)
        # every key has its slot now (kept for the caller: no lookup after the build)
        self.built_slots = (keys, slot_ids)
        cast = masks & ~self.slot_mask[slot_ids]
        # the tiles to cast: tile keys (page_key in tile units) and their slots
        bit = np.arange(S * S)
        sel = (cast[:, None] >> bit[None, :]) & 1 == 1
        page_i, tile_b = np.nonzero(sel)
        n_tiles = len(page_i)
        self.pages_cast = int(sel.any(axis=1).sum())
        if n_tiles == 0 and not new_fine.any():
            return job
        self.version += 1
        job.keys, job.masks, job.slot_ids, job.new_fine = keys, masks, slot_ids, new_fine
        if n_tiles:
            f, lv, px, py = key_fields(keys[page_i])
            tx = px * np.uint64(S) + (tile_b % S).astype(np.uint64)
            ty = py * np.uint64(S) + (tile_b // S).astype(np.uint64)
            # cast near tiles together, whatever their level (cast_order)
            order = cast_order(f, lv, tx, ty)
            job.tkeys = page_key(f[order], lv[order], tx[order], ty[order])
            job.tslots, job.tile_b = slot_ids[page_i][order], tile_b[order]
        return job

    def finish_build(self, job: "TileCast", fill: bool = True) -> int:
        """The last part of :meth:`build`, once :func:`cast_tiles` cast ``job``: the tiles'
        minima, the pages' masks, the new pages' other tiles (``fill``; else by
        :func:`fill_new_pages`, every store's at once); the texels ray-cast."""
        if job.keys is None:
            return 0
        built = 0
        if job.n_tiles:
            np.minimum.at(self.tile_min, (job.tslots, job.tile_b), job.minima)
            tpt = self.layout.tile_size ** 2
            # the depths ray-cast: a first and a second one a texel, or either alone
            built = job.n_tiles * tpt * (self.casts_depth + ("second_depth" in self.pools))
        self.slot_mask[job.slot_ids] |= job.masks
        nf = job.new_fine
        if fill and nf.any():
            self._fill_from_coarsest(job.keys[nf], job.slot_ids[nf], job.masks[nf])
        return built

    def _tile_rays(self, tkeys, tslots, lane, active=True) -> tuple:
        """``(o, d, dst)`` of lane ``lane`` of a cast of tiles ``tkeys`` into slots
        ``tslots`` (``tile_size^2`` lanes a tile): the texel's ray (from ``t0`` along it,
        :attr:`VirtualLayout.t0`) and where its depth goes in the pools."""
        lay = self.layout
        P, T = lay.page_size, lay.tile_size
        tpt = T * T
        tile = lane // tpt
        local = lane - tile * tpt
        ti, tj = morton_xy(local, T)   # 4 x 2 blocks of neighbours per vector
        # one upload of the tile keys (decoded in the kernel) and one of the slots
        f_l, lev, tx, ty = key_fields(dr.gather(mi.UInt64, padded_array(mi.UInt64, tkeys),
                                                tile, active))
        gx, gy = tx * T + ti, ty * T + tj
        res = mi.Float64(mi.UInt32(lay.res0) >> lev)
        uv = mi.Point2d((mi.Float64(gx) + TEXEL_SAMPLE[0]) / res,
                        (mi.Float64(gy) + TEXEL_SAMPLE[1]) / res)
        o64, d64 = lay.view.ray_through_f64(f_l, uv)
        # start near the scene: float32 stays exact (t0 opaque, as the lookups'
        # depth_origin: a moved far light compiles no new kernel)
        o = mi.Point3f(o64 + d64 * dr.opaque(mi.Float64, float(lay.t0))
                       if lay.t0 > 0.0 else o64)
        d = dr.normalize(mi.Vector3f(d64))
        slot = dr.gather(mi.UInt32, padded_array(mi.UInt32, tslots.astype(np.uint32)), tile,
                         active)
        dst = slot * (P * P) + (gy & (P - 1)) * P + (gx & (P - 1))
        return o, d, dst

    def _fill_from_coarsest(self, keys, slots, masks) -> None:
        """The tiles of new pages that were not cast: the coarsest level's texel over
        each (its page of face ``f`` is in slot ``f + 1``), as :meth:`BoundVirtualMap.
        fetch` reads beyond a lookup's 2 x 2 pages."""
        if self.layout.tiles_per_side == 1:
            return
        lane = dr.arange(mi.UInt32, len(keys) * self.layout.page_size ** 2)
        src, dst, empty = self._fill_lanes(keys, slots, masks, lane)
        values = {name: dr.gather(mi.Float, pool, src, empty)
                  for name, pool in self.pools.items()}
        dr.eval(*values.values())     # read before the scatters write the same pools
        for name, v in values.items():
            dr.scatter(self.pools[name], v, dst, empty)
        dr.eval(*self.pools.values())

    def _fill_lanes(self, keys, slots, masks, lane, active=True) -> tuple:
        """``(src, dst, empty)`` of lane ``lane`` of :meth:`_fill_from_coarsest` of pages
        ``keys`` (``page_size^2`` lanes a page): the coarsest level's texel it reads,
        the texel it writes, and whether that texel's tile is one not cast."""
        lay = self.layout
        P, T, S = lay.page_size, lay.tile_size, lay.tiles_per_side
        tpp = P * P
        page = lane // tpp
        local = lane - page * tpp
        ti, tj = local % P, local // P
        face, lev, px, py = key_fields(dr.gather(mi.UInt64, padded_array(mi.UInt64, keys), page,
                                                 active))
        mask = dr.gather(mi.UInt32, padded_array(mi.UInt32, masks.astype(np.uint32)), page,
                         active)
        slot = dr.gather(mi.UInt32, padded_array(mi.UInt32, slots.astype(np.uint32)), page,
                         active)
        gx, gy = px * P + ti, py * P + tj
        shift = mi.UInt32(lay.coarsest) - lev
        src = (face + 1) * tpp + (gy >> shift) * P + (gx >> shift)
        b = (ti // T) + (tj // T) * S
        empty = ((mask >> b) & 1) == 0
        return src, slot * tpp + local, empty

    def table(self, frame: tuple | None = None):
        """The page table as Dr.Jit arrays ``(header, dense, face_near, tile_masks,
        dense_tiles)``,
        rebuilt when pages change (``face_near``: the nearest depth per face, PCSS's
        blocker-search bound; ``tile_masks``: which tiles of each slot are ray-cast).

        ``frame``: ``(keys, slots, masks)`` of the pages one render reads (sorted keys,
        their slots, their marked tiles): the table then holds only those pages and
        tiles, and ``face_near`` is over those tiles, so a render reads what its own marks
        asked for, whatever earlier renders (other camera poses, another integrator
        sharing the store, pages a smaller ``memory_budget`` would not hold) left in the
        pool: the same image as a fresh integrator's. (Pages left by earlier renders made
        a pose rendered again differ from its first render on up to 4 % of pixels under
        a small ``memory_budget``, 0.6 % with PCSS's wide kernels on pages of 8^2, 7 %
        through PCSS's near depth.) A tap in a tile outside the marks (beyond the kernel
        margin of every pixel centre; a walked ``hard`` read beside its point's tile)
        reads the coarsest level's texel there (``dense_tiles``,
        :meth:`~mi_shadowmap.virtual.lookup.BoundVirtualMap._index`), as a fresh pool
        holds it, not a depth an earlier render cast into that tile.
        Default: every built page, every cast tile.

        Per (face, level) -- entry ``face * n_levels + level`` -- ``header`` holds
        two 64-bit words, ``(x0 - 1) | (y0 - 1) << 32`` and ``W | H << 16 | base << 32``
        (32-bit fields, the first two signed): the grid of 2 x 2 blocks
        whose lower-left page is in ``[x0 - 1, x0 + w - 1] x [y0 - 1, y0 + h - 1]``,
        ``(x0, y0, w, h)`` the bounding rectangle of that level's built pages (in
        pages), ``W = w + 1``, ``H = h + 1``, and where its ``W x H`` entries start
        in ``dense``. Each entry of ``dense`` holds the block's 4 slots (pages
        ``(bx, by)``, ``(bx + 1, by)``, ``(bx, by + 1)``, ``(bx + 1, by + 1)``;
        ``INVALID_SLOT`` where none is built), so a lookup reads its block with no loop.
        A level whose grid would exceed :data:`MAX_TABLE` entries or
        :data:`MAX_TABLE_SIDE` per side keeps its pages out of the table (lookups
        there walk to another level). The coarsest page of face ``f`` is in slot
        ``f + 1`` (:class:`PageStore`), so it needs no table. The fourth array holds
        each slot's tile mask (which of its tiles are ray-cast), the fifth the tile mask
        of each entry of ``dense`` (0 where none is built): read with its slot, not after.
        With ``frame`` both are of the frame's tiles alone (the slot's ray-cast tiles
        among its marks; 0 for a slot the frame does not read), so ``bind``'s walk, which
        reads the fourth by slot, and the taps, which read the fifth by entry, see the
        same tiles (``tests/test_page_cache_paths.py``); a walk reading every tile the
        slot ever had cast made a long-lived integrator's frame differ from a fresh one's
        (6 pixels of ``pcf`` on room_two_points along a camera path, a scratch run).
        """
        token = (self.version,) if frame is None else (
            self.version, hash(frame[0].tobytes()), hash(frame[2].tobytes()))
        # a few tables kept (methods of different margins rendered in turn, each its own
        # frame: one kept table rebuilt both every frame, 2.8 ms of a 256^2 large_world
        # frame); tables of an older pool version are dropped
        kept = _recall(self._tables, token)
        if kept is not None:
            return kept[1]
        lay = self.layout
        L = lay.n_levels
        if frame is None:
            keys, slots = self._index()
            slot_mask = self.slot_mask
        else:
            keys, slots, masks = frame
            coarse = ((keys >> np.uint64(54)) & np.uint64(31)) == np.uint64(lay.coarsest)
            slot_mask = np.zeros_like(self.slot_mask)
            slot_mask[slots] = self.slot_mask[slots] & np.where(coarse, lay.full_mask, masks)
        face, level, px, py = (f.astype(np.int64) for f in key_fields(keys))
        group = face * L + level
        # keys are sorted, so each (face, level) group is one run: its bounding rectangle
        # by reduceat, then every page is one of the 4 corners of 4 blocks (vectorised)
        first = np.empty(len(keys), bool)
        first[:1] = True
        np.not_equal(group[1:], group[:-1], out=first[1:])
        starts = np.flatnonzero(first)
        run = np.cumsum(first) - 1                  # each page's group
        groups = group[starts]
        if len(keys):
            x0, y0 = np.minimum.reduceat(px, starts), np.minimum.reduceat(py, starts)
            w = np.maximum.reduceat(px, starts) - x0 + 1
            h = np.maximum.reduceat(py, starts) - y0 + 1
        else:
            x0 = y0 = w = h = starts
        W, H = w + 1, h + 1
        fits = (W * H <= MAX_TABLE) & (np.maximum(W, H) <= MAX_TABLE_SIDE)
        every = bool(fits.all())
        if not every:       # one warning a table (six a frame of three lights before)
            spans = "; ".join(f"face {g // L} level {g % L}: {ww} x {hh}" for g, ww, hh in
                              zip(groups[~fits], w[~fits], h[~fits]))
            warnings.warn(f"shadowmap: virtual map '{lay.view.label}': pages spanning more "
                          f"than the page table holds ({spans} pages); their lookups use "
                          "other levels", RuntimeWarning)
        entries = np.where(fits, W * H, 0)
        base = np.cumsum(entries) - entries
        total = int(entries.sum())
        # per (face, level): two words, (x0 - 1) | (y0 - 1) << 32 and W | H << 16 |
        # base << 32, each field its low 32 bits (W = H = 0: no block)
        m32 = np.uint64(0xFFFFFFFF)
        low = lambda a: a.view(np.uint64) & m32    # noqa: E731  (int64: two's complement)
        words = np.zeros((lay.view.n_faces * L, 2), np.uint64)
        if len(keys):       # (one row per (face, level): a few dozen)
            words[groups[fits], 0] = (low((x0 - 1)[fits])
                                      | (low((y0 - 1)[fits]) << np.uint64(32)))
            words[groups[fits], 1] = (low((W | (H << 16))[fits])
                                      | (low(base[fits]) << np.uint64(32)))
        dense = np.full(4 * total + 4, INVALID_SLOT, np.uint32)   # + 4: one empty entry
        page_tiles = slot_mask[slots].astype(np.uint32)
        slots_in = slots           # the pages in the table (a level too wide keeps out)
        if not every:
            keep = fits[run]
            px, py, run, page_tiles = px[keep], py[keep], run[keep], page_tiles[keep]
            slots_in = slots[keep]
        # page (px, py) is corner k of block (px - (k & 1), py - (k >> 1)): entry
        # 4 (block's index) + k, the block's index (bx - x0 + 1) + W (by - y0 + 1)
        Wr = 4 * W[run]
        at0 = 4 * base[run] + (py - (y0[run] - 1)) * Wr + 4 * (px - (x0[run] - 1))
        at = np.concatenate([at0, at0 - 3, at0 - Wr + 2, at0 - Wr - 1])
        slots32 = slots_in.astype(np.uint32)
        dense[at] = np.concatenate([slots32] * 4)
        # each entry's tile mask written with its slot (a gather over every entry of
        # dense, most of them empty, took 0.14 ms of a large_world camera move's 0.69)
        dense_tiles = np.zeros(len(dense), np.uint32)
        dense_tiles[at] = np.concatenate([page_tiles] * 4)
        table = (padded_array(mi.UInt64, words.reshape(-1)),
                 padded_array(mi.UInt32, dense),
                 padded_array(mi.Float, self.face_near(lay.view.n_faces, slots_in,
                                                       slot_mask[slots_in])),
                 padded_array(mi.UInt32, slot_mask[:max(self.next_slot, 1)].astype(np.uint32)),
                 padded_array(mi.UInt32, dense_tiles))
        # older ones kept while they hold at most KEPT_TABLE_BYTES together
        size = 4 * 2 * len(dense) + words.nbytes
        kept, held = [], 0
        for t in reversed([t for t in self._tables if t[0][0] == self.version][
                -(MARK_MEMO - 1):]):
            held += t[2]
            if held > KEPT_TABLE_BYTES:
                break
            kept.insert(0, t)
        self._tables = kept + [(token, table, size)]
        return table

    def face_near(self, n_faces: int, slots: np.ndarray | None = None,
                  masks: np.ndarray | None = None) -> np.ndarray:
        """Nearest finite depth per face over the tiles ``masks`` of the pages in
        ``slots`` (default: every built page, every tile ray-cast; +inf for a face with
        none). Per tile, not per page: a tile an earlier render cast into a page this
        render reads, but outside its marks, moved PCSS's blocker-search bound (7 % of
        a re-rendered pose's pixels changed)."""
        out = np.full(n_faces, np.inf)
        if slots is None:
            slots = self._index()[1]
            masks = self.slot_mask[slots]
        slots = np.asarray(slots, np.int64)
        if len(slots):
            bits = (np.asarray(masks, np.int64)[:, None]
                    >> np.arange(self.tile_min.shape[1])[None, :]) & 1
            near = np.where(bits == 1, self.tile_min[slots], np.inf).min(axis=1)
            np.minimum.at(out, self.page_face[slots], near)
        return out.astype(np.float32)


class TileCast:
    """One store's part of a build (:meth:`PageStore.plan_build`): its pages, their slots
    and masks, the tiles to ray-cast (tile keys, slots, bit in the page), and the tiles'
    nearest depths once cast (:func:`cast_tiles`). ``keys`` None: nothing to build.
    ``cast``: its tiles' depths until their minima are read (:func:`read_minima`):
    ``(depth, start, texels, texels a tile)``, its range of the cast's depths."""

    __slots__ = ("store", "keys", "masks", "slot_ids", "new_fine", "tkeys", "tslots",
                 "tile_b", "minima", "cast")

    def __init__(self, store):
        self.store = store
        self.keys = self.masks = self.slot_ids = self.new_fine = None
        self.tkeys = self.tslots = self.tile_b = self.minima = self.cast = None

    @property
    def n_tiles(self) -> int:
        return 0 if self.tkeys is None else len(self.tkeys)


def cast_tiles(scene, jobs: list, minima: bool = True) -> None:
    """Ray-cast the tiles of ``jobs`` (:class:`TileCast`, one per store), setting each
    one's ``minima`` (``minima`` False: left to :func:`read_minima`, so that the host
    waits for the cast once, after more kernels are launched): the stores whose lights
    skip no shape of their own and keep the same layers, together in one kernel (a lane
    range each, from opaque offsets: the kernel is the same whatever each range's size,
    an empty one included, so that a camera move compiles nothing); a store alone, as it
    always was.

    The two point lights of room_two_points cast their tiles in one kernel, not two, on a
    camera move: the rays' and the tracing's Python (``first_hit``'s loop, the pages'
    rays) once, one kernel launch. A lane's ray, depth and texel are its store's own
    (its range's values, selected), so the pages are bit-identical."""
    groups = {}
    for job in jobs:
        st = job.store
        shape = st.layout.view.ignore_shape
        key = (None if shape is None else id(shape), "second_depth" in st.pools,
               st.casts_depth)
        groups.setdefault(key, []).append(job)
    for (shape, second, first), group in groups.items():
        if shape is not None or len(group) == 1:
            for job in group:
                if job.n_tiles:
                    _cast_alone(scene, job, second, first)
            continue
        # (a store with nothing to cast: an empty range; but none for a store that never
        # built a page: its pools are empty, and Dr.Jit refuses a scatter to an empty
        # array even with every lane masked off)
        live = [j for j in group if _has_pool(j)]
        tpts = [j.store.layout.tile_size ** 2 for j in live]
        counts = [j.n_tiles * t for j, t in zip(live, tpts)]
        total = sum(counts)
        if total == 0:
            continue
        lane = dr.arange(mi.UInt32, total)
        o = d = None
        parts = []
        at = 0
        for job, n in zip(live, counts):
            lo = dr.opaque(mi.UInt32, at)
            inside = (lane >= lo) & (lane < dr.opaque(mi.UInt32, at + n))
            tk = job.tkeys if job.tkeys is not None else np.zeros(0, np.uint64)
            ts = job.tslots if job.tslots is not None else np.zeros(0, np.int64)
            o_j, d_j, dst = job.store._tile_rays(tk, ts, lane - lo, inside)
            o = o_j if o is None else dr.select(inside, o_j, o)
            d = d_j if d is None else dr.select(inside, d_j, d)
            parts.append((job, inside, dst, at, n))
            at += n
        depth = _cast_rays(scene, live[0].store.layout.view, o, d, second,
                           [(job.store, dst, inside) for job, inside, dst, _, _ in parts],
                           first)
        for (job, _, _, at, n), tpt in zip(parts, tpts):
            if n:
                job.cast = (depth, at, n, tpt)
    if minima:
        read_minima(jobs)


def read_minima(jobs: list) -> None:
    """Each cast job's ``minima`` from its depths (:func:`cast_tiles` with ``minima``
    False): the nearest finite depth of each tile it cast (:func:`page_minima`). The
    stores cast together share one read of their kernel's depths on the CPU backend."""
    read = {}
    for job in jobs:
        if job.cast is None:
            continue
        depth, at, n, tpt = job.cast
        job.cast = None
        if dr.backend_v(depth) != dr.JitBackend.LLVM:
            job.minima = page_minima(depth if at == 0 and n == dr.width(depth) else
                                     dr.gather(mi.Float, depth, dr.arange(mi.UInt32, n)
                                               + dr.opaque(mi.UInt32, at)), tpt)
            continue
        if id(depth) not in read:
            read[id(depth)] = (depth, depth.numpy())
        job.minima = page_minima(read[id(depth)][1][at:at + n], tpt)


def fill_new_pages(jobs: list) -> None:
    """:meth:`PageStore._fill_from_coarsest` of every new page of ``jobs`` (cast by
    :func:`cast_tiles`): the stores with the same layers together, in one kernel that
    reads the coarsest texels and one that writes them (a lane range per store from
    opaque offsets, an empty one where a store has no new page: the same kernels every
    camera move), not two kernels per light; a store alone as before. Each lane reads
    and writes its own store's pools, so the pages are bit-identical."""
    groups = {}
    for job in jobs:        # (a store with nothing to build: an empty range)
        st = job.store
        if st.layout.tiles_per_side > 1:
            groups.setdefault(tuple(st.pools), []).append(job)
    for names, group in groups.items():
        group = [j for j in group if _has_pool(j)]     # (as cast_tiles: no empty pools)
        if len(group) == 1:
            job = group[0]
            nf = job.new_fine
            if nf is not None and nf.any():
                job.store._fill_from_coarsest(job.keys[nf], job.slot_ids[nf], job.masks[nf])
            continue
        counts = [0 if j.keys is None else
                  int(j.new_fine.sum()) * j.store.layout.page_size ** 2 for j in group]
        total = sum(counts)
        if total == 0:
            continue
        lane = dr.arange(mi.UInt32, total)
        values = dict.fromkeys(names)
        parts = []
        at = 0
        for job, n in zip(group, counts):
            lo = dr.opaque(mi.UInt32, at)
            inside = (lane >= lo) & (lane < dr.opaque(mi.UInt32, at + n))
            nf = (job.new_fine if job.keys is not None else np.zeros(0, bool))
            keys, slots, masks = ((np.zeros(0, np.uint64), np.zeros(0, np.int64),
                                   np.zeros(0, np.int64)) if job.keys is None else
                                  (job.keys[nf], job.slot_ids[nf], job.masks[nf]))
            src, dst, empty = job.store._fill_lanes(keys, slots, masks, lane - lo, inside)
            act = inside & empty
            for name in names:
                # (no reference to a gather left past the loop: a pool read by a pending
                # gather is copied whole before a scatter writes it, 1.5 MB here)
                values[name] = (dr.gather(mi.Float, job.store.pools[name], src, act)
                                if values[name] is None else
                                dr.select(inside, dr.gather(mi.Float, job.store.pools[name],
                                                            src, act), values[name]))
            parts.append((job, act, dst))
            at += n
        dr.eval(*values.values())     # read before the scatters write the same pools
        for job, act, dst in parts:
            for name in names:
                dr.scatter(job.store.pools[name], values[name], dst, act)
        dr.eval(*(job.store.pools[name] for job in group for name in names))


def _has_pool(job) -> bool:
    """Whether ``job``'s store has pools to gather from and scatter to: not a store that
    built no page yet, whose lane range is empty (its build's keys none: a plan grows
    the pools before any page is cast)."""
    return dr.width(next(iter(job.store.pools.values()))) > 0


def _cast_alone(scene, job, second: bool, first: bool = True) -> None:
    """:func:`cast_tiles` of one store's tiles in a kernel of its own."""
    st = job.store
    tpt = st.layout.tile_size ** 2
    lane = dr.arange(mi.UInt32, job.n_tiles * tpt)
    o, d, dst = st._tile_rays(job.tkeys, job.tslots, lane)
    depth = _cast_rays(scene, st.layout.view, o, d, second, [(st, dst, True)], first)
    job.cast = (depth, 0, dr.width(depth), tpt)


def _cast_rays(scene, view, o, d, second: bool, writes: list, first: bool = True):
    """The depths along the rays ``(o, d)`` of ``view``'s texels (from ``t0`` along them,
    :attr:`VirtualLayout.t0`), and the second depths with ``second``, scattered into each
    ``(store, dst, active)`` of ``writes``: one kernel, evaluated (the tile minima read the
    depths, returned). ``first`` False (with ``second``): no first depth is cast (the
    stores have no ``depth`` pool: :func:`casts_first_depth`) and the second depths
    are returned (the tile minima then bound the second depths)."""
    depth = first_hit(scene, view, o, d) if first else None
    sd = second_depth_along(scene, view, o, d) if second else None
    for st, dst, active in writes:
        if first:
            dr.scatter(st.pools["depth"], depth, dst, active)
        if second:
            dr.scatter(st.pools["second_depth"], sd, dst, active)
    out = depth if first else sd
    dr.eval(out)
    return out


def page_minima(depth, tpp: int, on_host: bool | None = None) -> np.ndarray:
    """Nearest finite depth of each page of ``depth`` (evaluated, ``tpp`` texels a page;
    +inf for a page with none), as numpy. ``on_host`` (default: on the CPU backend, which
    reads the depths in place): numpy; else a block reduction on the device, so that a
    GPU copies one value a page instead of the pages."""
    if isinstance(depth, np.ndarray):       # read already (cast_tiles)
        on_host, d = True, depth
    elif on_host is None:
        on_host = dr.backend_v(depth) == dr.JitBackend.LLVM
    if on_host:
        d = depth if isinstance(depth, np.ndarray) else depth.numpy()
        if len(d) == 0:
            return np.zeros(0, d.dtype)
        # the plain minimum first (np.minimum.reduceat over the pages' runs), the finite
        # one wherever it is finite or +inf: a NaN or -inf would have won it; only the
        # pages where it is not are masked (masking every texel was 2.6 ms for the 656 k
        # texels of a 1M-triangle first frame; 1.0 ms now)
        out = np.minimum.reduceat(d, np.arange(0, len(d), tpp))
        bad = np.isnan(out) | (out == -np.inf)
        if bad.any():
            b = d.reshape(-1, tpp)[bad]
            out[bad] = np.where(np.isfinite(b), b, np.inf).min(axis=1)
        return out
    finite = dr.select(dr.isfinite(depth), depth, dr.inf)
    return dr.block_reduce(dr.ReduceOp.Min, finite, tpp).numpy()


def cast_order(face, level, tx, ty) -> np.ndarray:
    """The order in which a build casts tiles ``(face, level, tx, ty)`` (numpy, tile
    units of their level): by face, then in Morton (Z) order of each tile's corner in
    level 0's tile units, the levels mixed, so that the tiles of one region of the map,
    whatever their level, are cast one after another, while the BVH nodes their rays
    visit are still in the caches. In the keys' order (level by level) every level
    swept the whole region again: the first frame's cast on the 1M-triangle mesh (385 k
    rays over ten levels) was 11 % slower, one thread. The depths do not depend on the
    order."""
    lv = np.asarray(level, np.uint64)
    code = (_spread_bits(np.asarray(tx, np.uint64) << lv)
            | (_spread_bits(np.asarray(ty, np.uint64) << lv) << np.uint64(1)))
    return np.lexsort((code, np.asarray(face, np.uint64)))


def _spread_bits(x: np.ndarray) -> np.ndarray:
    """The low 32 bits of ``x`` (``np.uint64``) moved to the even bits (a Morton code's
    half)."""
    x = x & np.uint64(0xFFFFFFFF)
    for shift, mask in ((16, 0x0000FFFF0000FFFF), (8, 0x00FF00FF00FF00FF),
                        (4, 0x0F0F0F0F0F0F0F0F), (2, 0x3333333333333333),
                        (1, 0x5555555555555555)):
        x = (x | (x << np.uint64(shift))) & np.uint64(mask)
    return x


def morton_xy(local, T: int) -> tuple:
    """``(i, j)`` of texel ``local`` (``mi.UInt32``) of a ``T`` x ``T`` tile (``T`` a
    power of two) in Morton (Z) order: its even bits are ``i``'s, its odd bits
    ``j``'s. A page build casts each tile's rays in this order, so an 8-wide vector holds
    a 4 x 2 block of texels rather than a row of 8, which a BVH traverses together
    (the build's ray casts 12 % faster on a 1M-triangle mesh than in rows)."""
    i, j = mi.UInt32(0), mi.UInt32(0)
    b = 0
    while (1 << b) < T:
        i |= ((local >> (2 * b)) & 1) << b
        j |= ((local >> (2 * b + 1)) & 1) << b
        b += 1
    return i, j
