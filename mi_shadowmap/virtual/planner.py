"""The first pass with ``virtual=true``: for every emitter, plan the pages (marks, memory
budget) and build those missing; the page cache that keeps them across renders.
"""
from __future__ import annotations

import collections
import math
import time
import warnings

import drjit as dr
import mitsuba as mi
import numpy as np

from ..control_flow import if_stmt
from ..methods import virtual_coarse_res_of, virtual_margin_of
from .camera import camera_frame, camera_state, clear_camera_states
from .layout import (VirtualLayout, key_fields, layout_for, page_key, sorted_unique,
                     with_keys)
from ..filters.common import BiasReach
from .lookup import KEEP_CENTRE, KEEP_OTHERS, KEEP_SHAPE, VirtualShadowMap
from .marks import (Marker, _kept_by_biases, block_axis, block_tiles, camera_hits,
                    camera_pixels, dedupe_many, dilate_tiles, kept_axes, kept_tiles,
                    mark_blocks, mark_coarser, marked_points, shape_bits, tile_pages)
from .store import (PageStore, TileCast, cast_tiles, fill_new_pages, page_bytes,
                    page_layers, read_minima)


#: Most lanes of one environment mark kernel (regions x camera hits): an environment's
#: regions are marked in batches of ``MARK_LANES // hits`` regions (at least one).
MARK_LANES = 1 << 19


class _Hits:
    """Camera hits gathered per mark lane: the position and the normal facing the camera
    (all that marking reads of a surface interaction)."""

    def __init__(self, p, n):
        self.p, self.n = p, n


# ----------------------------------------------------------------------- the cache
class PageCache:
    """Page stores kept across renders: per scene (latest state only) and emitter view."""

    def __init__(self, max_scenes: int = 4):
        self.max_scenes = max_scenes
        # id(scene) -> [scene, state, {key: store, ("layout", ...): layout}]
        self._scenes = collections.OrderedDict()
        self._fingerprints = collections.OrderedDict()   # id(view) -> (view, fingerprint)

    def store(self, scene, state, key, make):
        from ..map_manager import scene_slot
        slot = scene_slot(self._scenes, scene, state, self.max_scenes)
        if key not in slot[2]:
            slot[2][key] = make()
        return slot[2][key]

    def fingerprint(self, view) -> tuple:
        """:func:`~mi_shadowmap.map_manager.view_fingerprint` of ``view``, kept per view
        object (views are frozen, and the integrator keeps its views while the scene's
        state is unchanged)."""
        hit = self._fingerprints.get(id(view))
        if hit is None or hit[0] is not view:
            from ..map_manager import view_fingerprint
            hit = self._fingerprints[id(view)] = (view, view_fingerprint(view))
            while len(self._fingerprints) > 64:
                self._fingerprints.popitem(last=False)
        return hit[1]

    def layout(self, scene, state, view, fingerprint, opts) -> "VirtualLayout":
        """:func:`layout_for`, kept with the scene's stores (``state`` None: computed)."""
        if state is None:
            return layout_for(view, scene, opts)
        from ..map_manager import scene_slot
        slot = scene_slot(self._scenes, scene, state, self.max_scenes)
        key = ("layout", fingerprint, opts.page_size, opts.resolution)
        if key not in slot[2]:
            slot[2][key] = layout_for(view, scene, opts)
        return slot[2][key]

    def retire(self, scene, state, label, fingerprint) -> None:
        """Keep one fingerprint's store and layout for ``label``'s view: when it changes
        (a moved light, cascades following the camera), the stores and layouts of the
        previous one are dropped, so a light or camera path does not pile up page
        pools."""
        if state is None:
            return
        from ..map_manager import scene_slot
        entries = scene_slot(self._scenes, scene, state, self.max_scenes)[2]
        group = ("view of", label)
        old = entries.get(group)
        if old is not None and old != fingerprint:
            for k in [k for k in entries if k != group and (
                    k[0] == old or k[0] == "layout" and k[1] == old)]:
                del entries[k]
        entries[group] = fingerprint

    def clear(self):
        self._scenes.clear()
        self._fingerprints.clear()
        clear_camera_states()


#: The page cache of every ``shadowmap`` integrator (``PAGE_CACHE.clear()`` empties it).
PAGE_CACHE = PageCache()


def prepare_virtual(scene, sensor, opts, views, stats, params=None,
                    budget_bytes: int | None = None, pixels: bool = False,
                    camera=None) -> list:
    """First pass with ``virtual=true``: mark, build missing pages, return one
    :class:`VirtualShadowMap` per emitter whose view supports it (None elsewhere).

    ``params``: the scene's ``mi.traverse`` where the caller has it (else traversed
    here). Updates ``stats`` (a :class:`~mi_shadowmap.map_manager.MapStats`): pages marked,
    built, reused, the level histogram of the marked pages and ``texels_built``.
    ``budget_bytes``: what the virtual maps' pools may hold together (default
    ``memory_budget``; less what the render's full maps hold), shared by need
    (:func:`share_pages`); every pool is resized to its share, smaller ones too. Maps
    whose marked pages do not fit are degraded (finest levels replaced by coarser ones)
    with one warning naming them.
    ``pixels``: the render's lookups know their film pixel (``Lookup.pixel``: the
    integrator's own render through a ``perspective`` camera); its marks then decide per
    pixel whether the receiver biases' level applies (:func:`~.marks.probe_keeps`), and
    the maps carry that decision (:meth:`VirtualShadowMap.keeps`). Else it applies
    wherever the biases ask for it.
    ``camera``: ``sensor``'s :func:`~.camera.camera_state` where the caller read it in
    this render (the integrator's first pass, which shares it with the render's pinhole
    frame: one read of every camera parameter a render, not two); default: read here.

    The steps, in order (each a method of :class:`_FirstPass`, which holds what they
    share): the views' stores, the mark pass, the memory plan, the build, and the maps
    published with the render's stats.
    """
    run = _FirstPass(scene, sensor, opts, stats, pixels, camera)
    run.open_stores(views, params)
    run.mark()
    run.plan_memory(budget_bytes)
    run.build()
    return run.publish(views)


class _FirstPass:
    """One render's first pass with ``virtual=true`` (:func:`prepare_virtual`), its steps
    in the order they run. Per view ``i`` of the render (those that support virtual
    maps): ``stores[i]`` (views of one light share a store), ``margins[i]``,
    ``coarse[i]``, ``reach[i]``, ``mark_key[i]`` (what its remembered marks are keyed
    by) and ``dark[i]`` (its light lights no sample); ``uniq``: one view per store, which
    plans and builds it; ``plans[i]``, ``fits[i]``, ``budgets[i]``, ``builds[i]``: the
    memory plan's and the build's per store."""

    def __init__(self, scene, sensor, opts, stats, pixels, camera):
        self.scene, self.sensor, self.opts, self.stats = scene, sensor, opts, stats
        self.pixels, self.camera = pixels, camera

    # ------------------------------------------------------------ 1. the stores
    def open_stores(self, views, params) -> None:
        """The stores of this render's views from the page cache (their layouts kept
        with them), each view's margin, coarse levels, reach and mark key, and which
        lights are dark. Reads the views and the scene's state; writes ``cam``,
        ``pinhole``, ``probe``, ``stores``, ``margins``, ``coarse``, ``reach``, ``mark_key``,
        ``dark``."""
        from ..map_manager import MAP_CACHE
        from ..light_views import is_pinhole
        scene, sensor, opts = self.scene, self.sensor, self.opts
        camera = self.camera
        layer_names = page_layers(opts)
        # the shapes' state: a store is keyed by its light's view too, so a moved light (new
        # view) rebuilds its own pages and keeps every other light's (retired below)
        state = (MAP_CACHE.scene_state(scene, params, shapes_only=True) if opts.cache_maps
                 else None)
        cam = (camera if camera is not None else camera_state(sensor)) if sensor is not None \
            else None
        margins, coarse, stores = {}, {}, {}
        for i, view in enumerate(views):
            if view is None or not getattr(view, "supports_virtual", False):
                continue
            fingerprint = PAGE_CACHE.fingerprint(view)
            # one view's stores per light (a light moved every frame, cascades following the
            # camera: the previous view's pages are dropped, not piled up)
            # (per kind of view: integrators whose options give one light other views --
            # cascades, an environment's region count -- do not drop each other's)
            PAGE_CACHE.retire(scene, state, (view.label, type(view).__name__, view.n_faces),
                              fingerprint)
            layout = PAGE_CACHE.layout(scene, state, view, fingerprint, opts)
            key = (fingerprint, layout.res0, layout.page_size, layer_names)
            store = (PAGE_CACHE.store(scene, state, key, lambda: PageStore(layout, layer_names))
                     if state is not None else PageStore(layout, layer_names))
            store.frame += 1
            stores[i] = store
            margins[i] = virtual_margin_of(opts.record, opts, view)
            coarse[i] = virtual_coarse_res_of(opts.record, opts, view)
        reach = {i: reach_of(opts, stores[i].layout.view) for i in stores}
        # per-pixel decisions of the biases' level: a perspective camera's pixels (one camera
        # hit a pixel, whose lane the lookups find from their point: Lookup.pixel)
        pinhole = sensor is not None and is_pinhole(sensor)
        probe = bool(self.pixels) and pinhole
        mark_key = {i: (cam, margins[i], coarse[i], opts.lod_bias, reach[i], probe)
                    for i in stores}
        # a light whose radiance is exactly 0 lights no sample, so no lookup of its map
        # reaches the image or its visibility AOV (both 0 where it does not contribute);
        # its map keeps the coarsest level only (no marks), until it is lit again
        emitters = scene.emitters()
        dark = {i: len(emitters) == len(views) and _dark(emitters[i], stores[i])
                for i in stores}
        dark = {i: all(dark[j] for j in stores if stores[j] is stores[i]) for i in stores}
        self.cam, self.pinhole, self.probe, self.stores = cam, pinhole, probe, stores
        self.margins, self.coarse, self.reach = margins, coarse, reach
        self.mark_key, self.dark = mark_key, dark

    # ------------------------------------------------------------ 2. the mark pass
    def mark(self) -> None:
        """The mark pass: every light whose marks are stale, from one set of camera hits
        (their own kernel, then one kernel for all the marks; a still camera reuses its
        marks). Reads the stores and their mark keys; writes each stale store's mark
        (:meth:`PageStore.remember_mark`, through :meth:`_settle`)."""
        stores, dark, cam = self.stores, self.dark, self.cam
        stale = [i for i, st in stores.items() if cam is not None and not dark[i]
                 and not st.recall_mark(self.mark_key[i])]
        stale = [i for k, i in enumerate(stale)         # views sharing a store: marked once
                 if all(stores[j] is not stores[i] for j in stale[:k])]
        if not stale:
            return
        # lights marked from their own view: all in one pass; an environment's regions
        # (mark_lanes): in one pass too, a lane per region and hit, from hits evaluated
        # once (and whether each hit's BSDF transmits: light reaches it from behind too)
        plain = [i for i in stale if not hasattr(stores[i].layout.view, "mark_views")]
        multi = [i for i in stale if i not in plain]
        # every lit light marked from its own view (a first frame, a camera move): one
        # kernel for all of them, dark lights included (their marks are dropped), so
        # that the kernel is the same whichever lights are dark (one kernel per light
        # there launched 36-41 kernels a camera move, not 11-16, for 8 lights one of
        # them dark); some of them only (a light moved, or lit again): one kernel per
        # light, so which lights are stale does not shape a kernel (fused, each new set
        # of stale lights -- one point light, two, a point and a spot -- compiled its own)
        every = [i for k, i in enumerate(stores)
                 if not hasattr(stores[i].layout.view, "mark_views")
                 and all(stores[j] is not stores[i] for j in list(stores)[:k])]
        fused = plain == [i for i in every if not dark[i]]
        # the camera hits in a kernel of their own, launched before the marks are traced
        # (an environment's below, with whether each hit transmits): Dr.Jit launches it
        # on its thread pool and returns, so with two threads the pool runs the hits
        # while this thread traces every light's marks (about 2 ms of room_two_points'
        # camera move), where traced into the mark kernel they ran only after it (a
        # moved frame's first pass 1-2 ms shorter on a quiet machine, 16/16 and 18/24
        # paired, for +0.4 ms of kernel work; none with the second core taken or with
        # one thread; benchmarks/RESULTS.md, fifty-sixth session). Not through a lens:
        # its marks trace 3 x 3 lens points a pixel (marks.LENS_GRID), whose stored hits
        # raised a 1024^2 thinlens frame's peak memory 1.78 -> 2.22 GiB (helper E), for a
        # gain measured on pinholes only; they are traced into the marks' kernel, as before
        lens = fused and not self.pinhole
        hits = camera_hits(self.scene, self.sensor, evaluate=not (multi or lens), state=cam)
        through = None
        if multi:
            si_m, valid_m = hits[0], hits[3]
            through = valid_m & mi.has_flag(si_m.bsdf().flags(), mi.BSDFFlags.Transmission)
            # the hits and whether each one's BSDF transmits in one kernel (two kernels
            # before: 2.0 + 0.9 ms at 256^2 under sky_sun)
            dr.eval(si_m.p, si_m.n, hits[1], hits[2], valid_m, through)
        self.hits = hits
        self.shapes = {}    # per light: mark_blocks' (per_axis, bits), for block_tiles
        # a kernel of so many footprints (Method.virtual_footprint: pcf's region), or None
        self.footprints = (None if self.opts.record.virtual_footprint is None
                           else float(self.opts.record.virtual_footprint(self.opts)))
        self._mark_own_views(plain, every, fused)
        self._mark_regions(multi, through)

    def _mark_own_views(self, plain, every, fused) -> None:
        """The stale lights ``plain`` marked from their own views: ``every`` such light in
        one batch where ``fused``, else one batch a light; settles each lit one's
        mark."""
        sensor, opts, stores, hits = self.sensor, self.opts, self.stores, self.hits
        probe, reach, footprints = self.probe, self.reach, self.footprints
        # every light's marked points first (one kernel after the camera hits'), then the
        # candidate tiles from them in each dedupe round (a few integer operations)
        # the pinhole the probes' corners are seen from (marks.probe_keeps)
        eye = camera_frame(sensor, self.cam)[0] if probe else None
        for batch in ([every] if fused and plain else [[i] for i in plain]):
            markers = [Marker(stores[i].layout, opts.lod_bias, reach=reach[i],
                              scene=self.scene if probe and reach[i] is not None else None,
                              eye=eye)
                       for i in batch]
            points = [marked_points(mk, *hits) for mk in markers]
            # each probed light's centres' words, scattered in the same kernel, then
            # their neighbours' (_pixel_keeps) in the dedupe's second round
            centres = {i: _centre_words(sensor, pt[5], pt[6], hits[0].shape)
                       for i, mk, pt in zip(batch, markers, points) if mk.scene is not None}
            edge = _film_border(sensor, dr.width(hits[3])) if footprints is not None \
                else None
            axes = {}
            groups = [self._marks(i, mk, pt, edge, axes)
                      for i, mk, pt in zip(batch, markers, points)]
            keeps, read = {}, {}

            def neighbours():
                keeps.update((i, _pixel_keeps(sensor, c)) for i, c in centres.items())
                # the kept points that a neighbour reads through its word (_kept_read),
                # from the centres' words the first kernel scattered
                read.update((i, _kept_read(sensor, centres[i], points[batch.index(i)][6]))
                            for i in axes)
                return [k[0] for k in keeps.values()] + list(read.values())

            # the points (and the kept points' footprints' sides) evaluated in the
            # dedupe's first kernel, which scatters their keys (one kernel, not two), the
            # pixels' words in its second (not their own): a moved frame's kernels 11 -> 9
            found = dedupe_many([g for gs in groups for g in gs],
                                first=[x for pt in points for x in pt] + list(centres.values())
                                + [x for ax in axes.values() for x in ax],
                                second=neighbours)
            film = (tuple(int(x) for x in sensor.film().crop_size())
                    if edge is not None else None)
            for i, mk, pt, gs in zip(batch, markers, points, groups):
                mine, found = found[:len(gs)], found[len(gs):]
                if not self.dark[i]:
                    kept = (kept_tiles(mk, pt, axes[i], read[i], self.margins[i],
                                       footprints or 0.0, film) if i in axes else None)
                    self._settle(i, [self._tiles(i, mine, kept)], keeps.get(i))

    def _mark_regions(self, multi, through) -> None:
        """The stale environments ``multi`` marked by regions: every (region, camera hit)
        pair a lane, as many regions a kernel as ``MARK_LANES`` lanes hold (``through``:
        whether each hit's BSDF transmits); settles each one's mark."""
        sensor, opts, stores, hits = self.sensor, self.opts, self.stores, self.hits
        # an environment's regions: every (region, camera hit) pair a lane, as many
        # regions a kernel as MARK_LANES lanes hold (16 regions of a 128^2 film: one
        # kernel, where one per region launched 48 kernels and 900 table memsets a
        # camera move); each region keeps its own hash slots (dedupe_many's parts)
        n_pts = dr.width(hits[3])
        edge_m = (_film_border(sensor, n_pts) if multi and self.footprints is not None
                  else None)
        for i in multi:
            view = stores[i].layout.view
            n_regions = view.n_views
            per = max(1, min(n_regions, MARK_LANES // max(n_pts, 1)))
            parts = []
            for k0 in range(0, n_regions, per):
                nk = min(per, n_regions - k0)
                lane = dr.arange(mi.UInt32, nk * n_pts)
                width = dr.opaque(mi.UInt32, n_pts)
                local = lane // width
                pt = lane - local * width
                pts = (_Hits(*(dr.gather(type(a), a, pt) for a in (hits[0].p, hits[0].n))),
                       *(dr.gather(type(a), a, pt) for a in hits[1:]))
                thr = dr.gather(mi.Bool, through, pt)
                mark_view, mark_active = view.mark_lanes(local + dr.opaque(mi.UInt32, k0))
                marker = Marker(stores[i].layout, opts.lod_bias, mark_view, self.reach[i])
                points = marked_points(marker, *pts,
                                       active=lambda p, n, f=mark_active, t=thr: f(p, n, t))
                dr.eval(*points)
                # (a region's marker has no scene: no point is kept apart, axes unused)
                gs = self._marks(i, marker, points,
                                 None if edge_m is None else dr.gather(mi.Bool, edge_m, pt),
                                 {})
                parts.append(self._tiles(i, dedupe_many(gs, parts=[(local, nk)] * len(gs))))
            self._settle(i, parts)

    def _marks(self, i, marker, points, border, axes) -> list:
        """The candidate lists of light ``i`` (its own levels', then the coarser
        levels' its kernels may filter, :func:`mark_coarser`) from its evaluated
        :func:`marked_points` ``points``; its kept points' footprints' sides
        (:func:`kept_axes`) into ``axes[i]`` where the biases' level is decided per
        pixel."""
        # its own levels' tiles as blocks (mark_blocks): one group, the blocks' shapes
        # in their keys (else one group per block shape); the points that kept the
        # biases' level (where the marks decide it per pixel) marked on the host
        # (kept_tiles), from their footprints' sides evaluated with the points
        margin, coarse = self.margins[i], self.coarse[i]
        per_axis = block_axis(marker, margin, border is not None)
        self.shapes[i] = (per_axis, shape_bits(marker.layout, per_axis))
        apart = marker.scene is not None and _kept_by_biases(marker)
        if apart:
            axes[i] = kept_axes(marker, *self.hits[:3], points)
        keys, oks = mark_blocks(marker, points, margin=margin, bits=self.shapes[i][1],
                                border=border, footprints=self.footprints or 0.0,
                                host_kept=apart)
        out = [([k], [ok]) for k, ok in zip(keys, oks)]
        if coarse:
            out.append(mark_coarser(marker, None, None, None, None,
                                    coarse_res=coarse, points=points))
        return out

    def _tiles(self, i, found, kept=None) -> tuple:
        """Light ``i``'s tile keys from its :meth:`_marks` groups' keys (and its kept
        points' tiles, :func:`kept_tiles`): ``(own levels', coarser levels')`` (the
        latter empty without ``virtual_coarse_res``)."""
        coarse = self.coarse[i]
        n = len(found) - bool(coarse)
        own = block_tiles(found[:n], *self.shapes[i])
        if kept is not None and len(kept):
            own = sorted_unique(np.concatenate([own, kept]))
        extra = (dilate_tiles(found[n], self.stores[i].layout, self.margins[i]) if coarse
                 else np.zeros(0, np.uint64))
        return own, extra

    def _settle(self, i, parts, keep=None) -> None:
        """Light ``i``'s mark: every tile, and those only the coarser levels' kernels
        read (a full budget drops them first), and its pixels' ``keep``
        (:meth:`VirtualShadowMap.keeps`; None: no probe)."""
        # (each part's own tiles sorted and distinct already: block_tiles)
        own = (parts[0][0] if len(parts) == 1 else
               sorted_unique(np.concatenate([p[0] for p in parts])))
        extra = sorted_unique(np.concatenate([p[1] for p in parts]))
        optional = np.setdiff1d(extra, own, assume_unique=True)
        self.stores[i].remember_mark((self.mark_key[i], with_keys(own, optional), optional,
                                      keep))

    # ------------------------------------------------------------ 3. the memory plan
    def plan_memory(self, budget_bytes) -> None:
        """The budget's pages shared by need (:func:`share_pages`), then the pages each
        map's marks keep (:func:`_fit_marks`); a degraded map's unused pages go to the
        next degraded one. Reads the stores' marks; writes ``per_page``,
        ``budget_bytes``, ``uniq``, ``plans[i]`` (``[mark, tiles, fixed slots,
        pages]``), ``fits[i]`` (``_fit_marks``'), ``budgets[i]`` (pages)."""
        stores, opts = self.stores, self.opts
        per_page = page_bytes(opts)
        budget_bytes = opts.budget_bytes if budget_bytes is None else int(budget_bytes)
        uniq = [i for i in stores if all(stores[j] is not stores[i] for j in stores if j < i)]
        plans = {}
        for i in uniq:
            store = stores[i]
            layout = store.layout
            view = layout.view      # the emitter's view, or one face aimed at a far scene
            if store.lit_faces is None:
                store.lit_faces = _lit_faces(view)
                store.coarse_keys = np.sort(np.array([page_key(f, layout.coarsest, 0, 0)
                                                      for f in store.lit_faces],
                                                     np.uint64).reshape(-1))
            mark = store.last_mark if self.cam is not None and not self.dark[i] else None
            memo = store.plan_memo      # the same marks as the last render: the same tiles
            if memo is not None and memo[0] is mark and memo[1] is store.coarse_keys:
                tiles, n_pages = memo[2], memo[3]
            else:
                marked = mark[1] if mark is not None else np.zeros(0, np.uint64)
                tiles = with_keys(marked, store.coarse_keys)
                # the pages and their tile masks (what the build reads when the tiles fit the
                # budget; their count is the plan's), computed once: _fit_marks and the build
                # take them from the memo (one tile_pages, where two _n_pages and a
                # tile_pages of the same tiles took 0.31 ms a camera move on large_world)
                pages = tile_pages(tiles, layout)
                n_pages = len(pages[0])
                store.plan_memo = (mark, store.coarse_keys, tiles, n_pages, pages)
            # slots: the empty page (slot 0) and unlit faces' reserved coarsest slots (empty
            # pages) besides the pages
            fixed = 1 + view.n_faces - len(store.lit_faces)
            plans[i] = [mark, tiles, fixed, n_pages]
        alloc = share_pages(budget_bytes // per_page,
                            [plans[i][2] + len(stores[i].lit_faces) for i in uniq],
                            [plans[i][2] + plans[i][3] for i in uniq],
                            [stores[i].capacity for i in uniq])
        fits = {}
        for i, slots in zip(uniq, alloc):
            fits[i] = _fit_marks(stores[i], plans[i][0], plans[i][1], slots - plans[i][2])
        spare = budget_bytes // per_page - sum(alloc)
        for k, i in enumerate(uniq):        # degraded maps keep the pages they use ...
            if fits[i][1]:
                spare += alloc[k] - plans[i][2] - fits[i][2]
                alloc[k] = plans[i][2] + fits[i][2]
        for k, i in enumerate(uniq):        # ... and the next take what is left, in turn
            if fits[i][1] and spare > 0:
                fits[i] = _fit_marks(stores[i], plans[i][0], plans[i][1],
                                     alloc[k] + spare - plans[i][2])
                spare -= plans[i][2] + fits[i][2] - alloc[k]
                alloc[k] = plans[i][2] + fits[i][2]
        self.per_page, self.budget_bytes, self.uniq = per_page, budget_bytes, uniq
        self.plans, self.fits = plans, fits
        self.budgets = {i: alloc[k] - plans[i][2] for k, i in enumerate(uniq)}

    # ------------------------------------------------------------ 4. the build
    def build(self) -> None:
        """Every store whose pages changed: its pages planned (evictions, slots, the tiles
        to cast), then every light's tiles cast together (:func:`cast_tiles`: one kernel
        where the lights allow it, on a camera move of room_two_points one for its two
        point lights), the new pages filled and the tiles' minima read. Reads the memory
        plan; writes ``builds[i]`` (``(job, needed, masks, degraded, seconds)``, stores
        whose pages did not change have none), ``cast_dt`` and ``cast_n``."""
        stores, plans, budgets = self.stores, self.plans, self.budgets
        builds = {}
        for i in self.uniq:
            store = stores[i]
            mark, budget_pages = plans[i][0], budgets[i]
            store.max_pages = budget_pages + plans[i][2]
            settled = store.settled
            if (settled is not None and settled[0] is mark and settled[1] == budget_pages
                    and settled[2] == store.version):
                continue
            tiles, degraded, _ = self.fits[i]
            needed, masks = _tile_pages(store, tiles)
            have, _ = store.lookup(needed)
            over = store.n_pages + int((~have).sum()) - budget_pages
            if over > 0:
                store.evict(needed, over)
            store.shrink(store.max_pages)   # a smaller budget, or share of it, than before
            t0 = time.perf_counter()
            builds[i] = (store.plan_build(needed, masks), needed, masks, degraded,
                         time.perf_counter() - t0)
        # (every store a range, an empty one where its pages did not change: which lights
        # build -- a camera move: all lit ones; a moved light: some -- shapes no kernel)
        jobs = [builds[i][0] if i in builds else TileCast(stores[i]) for i in self.uniq]
        t0 = time.perf_counter()
        # the new pages' fills launched behind the cast before the host reads the cast's
        # depths (the tiles' minima): one wait for both, not one for the cast and another
        # for the fills (the fills read no minimum)
        cast_tiles(self.scene, jobs, minima=False)
        fill_new_pages(jobs)
        read_minima(jobs)
        dr.sync_thread()
        self.cast_dt = time.perf_counter() - t0
        self.cast_n = sum(b[0].n_tiles for b in builds.values())
        self.builds = builds

    # ------------------------------------------------------------ 5. publishing
    def publish(self, views) -> list:
        """One :class:`VirtualShadowMap` per view of ``views`` (None where it has no
        store): each store's build finished (or, where its marks, budget and pages are
        the last render's, its pages' last use recorded), the render's ``stats``
        updated, and one warning naming the degraded maps."""
        stores, plans, budgets, stats = self.stores, self.plans, self.budgets, self.stats
        degraded_maps = []
        out = []
        # a probed render's light without a mark (dark): no pixel keeps the biases' level,
        # through bits of the same types (the render kernel is the one a lit light compiles)
        no_keep = ((dr.zeros(mi.UInt32, 1), dr.opaque(mi.UInt32, 0), dr.opaque(mi.UInt32, 0))
                   if self.probe else None)
        for i, view in enumerate(views):
            if i not in stores:
                out.append(None)
                continue
            store = stores[i]
            layout = store.layout
            view = layout.view
            first = i in budgets
            if not first:        # a store another view of this render shares: planned there
                i0 = next(j for j in self.uniq if stores[j] is store)
                mark, fixed, budget_pages = plans[i0][0], plans[i0][2], budgets[i0]
            else:
                mark, fixed, budget_pages = plans[i][0], plans[i][2], budgets[i]
            store.max_pages = budget_pages + fixed
            settled = store.settled
            if (settled is not None and settled[0] is mark and settled[1] == budget_pages
                    and settled[2] == store.version):
                # the same marks, budget and pages as the last render (a still camera): every
                # needed page is built; only their last use is recorded
                needed, slots, masks, hist, degraded = settled[3:]
                n_cast = 0
                dt = 0.0
                store.slot_frame[slots] = store.frame
            else:
                job, needed, masks, degraded, dt = self.builds[i if first else i0]
                t0 = time.perf_counter()
                stats.texels_built += store.finish_build(job, fill=False)
                n_cast = store.pages_cast
                store._grow(store.next_slot)   # never an empty pool: slot 0, the empty page
                dr.sync_thread()
                # its time: planning and finishing its build, and its share of the cast
                dt += (time.perf_counter() - t0
                       + self.cast_dt * job.n_tiles / max(self.cast_n, 1))
                store.cast_seconds += dt
                store.cast_pages += n_cast
                # every needed page is built now, in the slot the build gave it (a lookup
                # after the build found the same, all of them present)
                built = store.built_slots
                if built is not None and built[0] is needed:
                    slots = built[1]
                else:
                    present, slots = store.lookup(needed)
                    needed, slots, masks = needed[present], slots[present], masks[present]
                store.slot_frame[slots] = store.frame
                levels = ((needed >> np.uint64(54)) & np.uint64(31)).astype(int)
                hist = np.bincount(levels, minlength=layout.n_levels)
                store.settled = (mark, budget_pages, store.version, needed, slots, masks,
                                 hist, degraded)
            if degraded and first:
                degraded_maps.append((view.label, degraded))
            stats.pages_marked += int(len(needed))
            stats.pages_built += int(n_cast)
            stats.pages_reused += int(len(needed) - n_cast)
            stats.level_histogram = _add_hist(stats.level_histogram, hist)
            stats.maps_built += int(n_cast > 0)
            stats.maps_reused += int(n_cast == 0)
            # casting every page read from scratch: this frame's casts, and the reused pages
            # at the store's mean time a page
            stats.naive_build_seconds += dt + (len(needed) - n_cast) * (
                store.cast_seconds / max(store.cast_pages, 1))
            keep = mark[3] if mark is not None else None
            if keep is None and self.probe and self.reach[i] is not None \
                    and not hasattr(view, "mark_views"):
                keep = no_keep
            out.append(VirtualShadowMap(store, {"pages": int(len(needed)), "new": int(n_cast)},
                                        self.opts.lod_bias, self.margins[i],
                                        self.coarse.get(i), frame=(needed, slots, masks),
                                        reach=self.reach[i], keep=keep))
        if degraded_maps:
            self._warn_degraded(degraded_maps)
        return out

    def _warn_degraded(self, degraded_maps) -> None:
        """The one warning a render, whatever the number of lights, naming the maps whose
        marked pages were replaced by coarser ones (``(label, pages)``) and the budget
        that would hold every marked page."""
        opts, per_page, uniq, plans = self.opts, self.per_page, self.uniq, self.plans
        budget_bytes = self.budget_bytes
        need = sum(plans[i][2] + plans[i][3] for i in uniq) * per_page + (
            opts.budget_bytes - budget_bytes)
        names = ", ".join(f"'{name}' ({n})" for name, n in degraded_maps[:4]) + (
            f", and {len(degraded_maps) - 4} more" if len(degraded_maps) > 4 else "")
        # stacklevel: this method, publish, prepare_virtual, then its caller's caller
        warnings.warn(f"shadowmap: memory_budget = {opts.memory_budget:g} MiB holds "
                      f"{budget_bytes // per_page} pages of {opts.page_size}^2 for "
                      f"{len(uniq)} virtual map(s); {len(degraded_maps)} of them had marked "
                      f"pages replaced by coarser ones (pages): {names}; memory_budget = "
                      f"{math.ceil(need / 2 ** 20 * 100) / 100:g} MiB would hold every "
                      "marked page", RuntimeWarning, stacklevel=5)


def reach_of(opts, view):
    """The receiver biases a virtual map's levels account for
    (:meth:`VirtualShadowMap.level_for`): ``opts``' (:class:`BiasReach`), except on an
    environment's regions (None: the footprint's level). A region's map stands for a
    patch of sky by one direction, an error far larger than the texel's (on sky_sun at
    64^2, 16 regions, ``hard``: capped, 45 % more texels for a visibility AOV 2 % further
    from 256 shadow rays, 0.0241 against 0.0237; full maps 0.0234)."""
    if getattr(view, "kind", None) == "environment":
        return None
    return BiasReach.of(opts)


def share_pages(total: int, least: list, need: list, held: list) -> list:
    """Slots of ``total`` for each virtual map, by need: each map asks for ``need[k]``
    slots (its marked pages, its coarsest pages, the empty page and unlit faces'
    reserved slots) and gets at least ``least[k]`` (the same without marked pages).

    Everything fits: each map gets its need, then what is left keeps cached pages -- up to
    the slots a map holds already (``held``, so a pool need not shrink), in order, then
    evenly. It does not: the maps below a common level get their need, the others the
    level (the largest whose sum fits; the remainder one slot each, in order), so no slot
    stays unused while a map degrades (the pages of a level a map then does not fill
    are passed on by the caller). Deterministic: the same arguments, the same shares."""
    n = len(need)
    need = [max(a, b) for a, b in zip(need, least)]
    if sum(need) <= total:
        out = list(need)
        left = total - sum(out)
        for k in range(n):
            add = min(left, max(int(held[k]) - out[k], 0))
            out[k] += add
            left -= add
        for k in range(n):
            out[k] += left // n + (k < left % n)
        return out
    clamp = lambda lv: [min(max(lv, a), b) for a, b in zip(least, need)]  # noqa: E731
    lo, hi = 0, max(need)
    while lo < hi:                          # the largest level whose shares fit
        mid = (lo + hi + 1) // 2
        if sum(clamp(mid)) <= total:
            lo = mid
        else:
            hi = mid - 1
    out = clamp(lo)
    left = total - sum(out)
    for k in range(n):
        if left > 0 and out[k] < need[k]:
            out[k] += 1
            left -= 1
    return out


def _fit_marks(store, mark, tiles, budget_pages) -> tuple:
    """The tiles of ``store``'s marks (``tiles``: the marked ones and the coarsest pages)
    that fit ``budget_pages`` pages: over it, first without the tiles only coarser-level
    kernels read (their lookups walk to a coarser level built), then the finest levels
    replaced by their parents (:func:`_fit_budget`). ``(tiles, pages replaced, pages)``."""
    memo = store.fit_memo            # the same marks' tiles and budget as the last render
    if (memo is not None and memo[0] is mark and memo[1] is tiles
            and memo[2] == budget_pages):
        return memo[3]
    memo_tiles = tiles
    layout = store.layout
    dropped = 0
    if mark is not None and len(mark[2]) and _count_pages(store, tiles) > budget_pages:
        kept = with_keys(np.setdiff1d(mark[1], mark[2], assume_unique=True),
                         store.coarse_keys)
        dropped = _count_pages(store, tiles) - _n_pages(kept, layout)
        tiles = kept
    fitted, degraded = _fit_budget(tiles, budget_pages, layout)
    out = (fitted, degraded + dropped, _count_pages(store, fitted))
    store.fit_memo = (mark, memo_tiles, budget_pages, out)
    return out


def _dark(emitter, store=None) -> bool:
    """Whether ``emitter`` emits nothing: its ``intensity``, ``radiance`` or
    ``irradiance`` is a uniform value of exactly 0 (a texture, or an environment: not
    known to be, False). A 0 with gradients enabled (``dr.grad_enabled``, whatever the
    AD scope) is not dark: the gradient image it lights reads its map's marked pages.

    ``store``: the light's :class:`PageStore`, which keeps the emitter's watched values
    (:class:`~mi_shadowmap.map_manager.ParamWatch`) in ``dark_memo``, so a still scene
    reads no parameter again (a ``mi.traverse`` per emitter and frame cost 0.2 ms each).
    The memo holds neither the emitter nor its ``mi.traverse`` (only the getters of its
    emitted values, whose nodes are its textures), and lives with the store, a light's
    in one scene: a first version kept emitters in a module-level memo, past their
    scenes, and an area emitter outliving its shape made Mitsuba's later kernels, which
    dispatch over every live emitter, crash (``direct`` on the next scene of a test
    module: a segmentation fault)."""
    if mi.has_flag(emitter.flags(), mi.EmitterFlags.Infinite) and not mi.has_flag(
            emitter.flags(), mi.EmitterFlags.DeltaDirection):
        return False
    slot = store.dark_memo if store is not None else None
    if slot is None or slot[0] != id(emitter):
        from ..map_manager import ParamWatch
        params = mi.traverse(emitter)
        keys = [k for k in params.keys()
                if k.split(".")[0] in ("intensity", "radiance", "irradiance")]
        uniform = bool(keys) and all(len(k.split(".")) == 2 and k.endswith(".value")
                                     for k in keys)
        watch = ParamWatch(params, keys) if uniform else None
        if watch is not None:
            watch.params = None          # the getters only: not the emitter
        slot = [id(emitter), watch, None, None, False]
        if store is not None:
            store.dark_memo = slot
    watch = slot[1]
    if watch is None:
        return False
    token, values = watch.read()
    if token != slot[2]:
        slot[2], slot[3] = token, watch.held(values)
        slot[4] = all(not np.any(np.asarray(v) != 0) for v in values)
    if slot[4]:
        # a 0 whose gradient is tracked lights the derivative image (the shading's
        # derivative wrt the intensity is the unshadowed light times the visibility):
        # its pages are marked as any lit light's, in the primal render too (run under
        # dr.suspend_grad() by mi.render(scene, params)), so both see the same maps
        with dr.resume_grad():
            if any(dr.grad_enabled(v) for v in values):
                return False
    return slot[4]


def _lit_faces(view) -> list:
    """The faces a light can shine through: all, but for a one-sided planar area light
    only those with a corner ray in front of its emitting plane (a face's directions
    form a convex cone, so its corners bound ``dot(d, n)``)."""
    if view.light_normal is None:
        return list(range(view.n_faces))
    n = np.array(view.light_normal, np.float64)
    out = []
    for f in range(view.n_faces):
        uv = mi.Point2d([0.0, 1.0, 0.0, 1.0], [0.0, 0.0, 1.0, 1.0])
        _, d = view.ray_through_f64(mi.UInt32(f), uv)
        dots = d.x.numpy() * n[0] + d.y.numpy() * n[1] + d.z.numpy() * n[2]
        if np.any(dots > 1e-9):
            out.append(f)
    return out


def _add_hist(old, hist):
    old = list(old or [])
    n = max(len(old), len(hist))
    old += [0] * (n - len(old))
    return [int(a + (hist[i] if i < len(hist) else 0)) for i, a in enumerate(old)]


def _tile_pages(store, tiles: np.ndarray) -> tuple:
    """:func:`tile_pages` of ``tiles``: the plan's (``store.plan_memo``) where they are
    the plan's tiles (they fit the budget), else computed."""
    memo = store.plan_memo
    if memo is not None and memo[2] is tiles:
        return memo[4]
    return tile_pages(tiles, store.layout)


def _count_pages(store, tiles: np.ndarray) -> int:
    """:func:`_n_pages` of ``tiles``: the plan's count where they are the plan's tiles."""
    memo = store.plan_memo
    if memo is not None and memo[2] is tiles:
        return memo[3]
    return _n_pages(tiles, store.layout)


def _n_pages(tiles: np.ndarray, layout) -> int:
    """How many pages hold ``tiles`` (sorted tile keys)."""
    S = np.uint64(layout.tiles_per_side)
    face, level, tx, ty = key_fields(tiles)
    return len(sorted_unique(page_key(face, level, tx // S, ty // S)))


def _fit_budget(tiles: np.ndarray, budget_pages: int, layout) -> tuple:
    """Replace the finest level's tiles by their parents (the tiles under them one level
    coarser) until the pages of ``tiles`` fit the budget; ``(tiles, pages replaced)``."""
    degraded = 0
    if len(tiles) <= budget_pages:      # never more pages than tiles
        return tiles, degraded
    S = np.uint64(layout.tiles_per_side)
    while True:
        face, level, tx, ty = key_fields(tiles)
        pages = page_key(face, level, tx // S, ty // S)
        if len(sorted_unique(pages)) <= budget_pages:
            break
        levels = level.astype(int)
        finest = levels.min()
        if finest >= layout.coarsest:
            break
        sel = levels == finest
        k = tiles[sel]
        parents = page_key(face[sel], finest + 1, tx[sel] >> np.uint64(1),
                           ty[sel] >> np.uint64(1)) if len(k) else k
        degraded += len(sorted_unique(pages[sel]))
        tiles = sorted_unique(np.concatenate([tiles[~sel], parents.astype(np.uint64)]))
    return tiles, degraded


def _centre_words(sensor, dropped, kept, shape):
    """Each film pixel's centre's word (``x + width y``, unevaluated: a scatter), from a
    mark pass's points (:func:`~.marks.marked_points`: which dropped the biases' level
    after its probe, which kept it) and the hits' ``shape`` (the hits of
    :func:`~.marks.camera_hits` through a pinhole: one a pixel, in
    :func:`~mi_shadowmap.light_views.pixel_centres`' blocks, whose filler lanes repeat
    a pixel with the same values): its shape, ``KEEP_CENTRE`` where it kept the level
    and (here) ``KEEP_OTHERS`` where it dropped it: either bit, the biases capped it.
    Scattered in the mark kernel: evaluated apart, it traced the camera rays and their
    probes again (9.9 ms of a moved 256^2 large_world frame)."""
    w, h = (int(x) for x in sensor.film().crop_size())
    pixel = camera_pixels(sensor)
    ids = dr.reinterpret_array(mi.UInt32, shape) & KEEP_SHAPE
    centre = dr.zeros(mi.UInt32, w * h)
    zero = mi.UInt32(0)
    dr.scatter(centre, ids | dr.select(kept, mi.UInt32(KEEP_CENTRE), zero)
               | dr.select(dropped, mi.UInt32(KEEP_OTHERS), zero),
               (pixel & 0xFFFF) + (pixel >> 16) * w)
    return centre


def _pixel_keeps(sensor, centre) -> tuple:
    """``(words, width, count)`` (:meth:`VirtualShadowMap.keeps`) from the centres'
    words (:func:`_centre_words`, evaluated): per film pixel (``x +
    width y``, unevaluated) a word of ``KEEP_SHAPE`` (the centre's shape id, its
    ``ShapePtr`` as ``mi.UInt32``), ``KEEP_CENTRE`` (its mark kept the biases' level;
    or the biases did not cap the centre and one of the 8 neighbouring pixels whose
    centre is on its shape kept it) and ``KEEP_OTHERS`` (:mod:`.lookup`): one of the 8
    neighbouring pixels whose centre is on another shape kept it. A sample whose own
    centre says nothing of its level (uncapped, or on another shape: a silhouette's
    pixel) reads beside its neighbours' marks: where they kept the biases' level it
    keeps it too (built by their footprints' boxes), else it reads the level without
    it, which they built. (Uncapped centres' samples keeping it always wanted a level
    their neighbours had dropped and read what wider marks would build: ``pcf`` on the
    point light of ``tests/test_filters_pcf.py``, 2 pixels of 4096 moved with wider
    marks; dropping it always lit 4 floor pixels of the boxed light of
    ``tests/test_virtual.py`` under ``mdsm`` where the cap's region begins, bound 2.)
    And the film's width and pixel count as opaque values. One more kernel (the
    neighbours' words, 0.2 ms at 256^2) a mark pass."""
    w, h = (int(x) for x in sensor.film().crop_size())
    zero = mi.UInt32(0)
    idx = dr.arange(mi.UInt32, w * h)
    y = idx // w
    x = idx - y * w
    own = dr.gather(mi.UInt32, centre, idx)
    others_keep = same_keep = mi.Bool(False)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            if dx == 0 and dy == 0:
                continue
            nx, ny = mi.Int32(x) + dx, mi.Int32(y) + dy
            ok = (nx >= 0) & (ny >= 0) & (nx < w) & (ny < h)
            n = dr.gather(mi.UInt32, centre, mi.UInt32(ny * w + nx), ok)
            n_kept = ok & ((n & KEEP_CENTRE) != 0)
            same = (n & KEEP_SHAPE) == (own & KEEP_SHAPE)
            others_keep |= n_kept & ~same
            same_keep |= n_kept & same
    capped = (own & (KEEP_CENTRE | KEEP_OTHERS)) != 0
    keep_own = ((own & KEEP_CENTRE) != 0) | (~capped & same_keep)
    words = (own & KEEP_SHAPE) | dr.select(keep_own, mi.UInt32(KEEP_CENTRE), zero) \
        | dr.select(others_keep, mi.UInt32(KEEP_OTHERS), zero)
    return words, dr.opaque(mi.UInt32, w), dr.opaque(mi.UInt32, w * h)


def _kept_read(sensor, centre, kept) -> mi.Bool:
    """Per camera hit of a mark pass (:func:`~.marks.camera_hits` through a pinhole, one
    a pixel), whether it kept the biases' level (``kept``, :func:`~.marks.marked_points`)
    and a neighbouring pixel's samples read that level through their word
    (:func:`_pixel_keeps`, :meth:`VirtualShadowMap.keeps`): one of the 8 neighbours'
    centres (``centre``, :func:`_centre_words`, evaluated) is on another shape (its
    samples on the kept point's shape read ``KEEP_OTHERS``), or on the same shape and
    uncapped (its ``KEEP_CENTRE`` comes from its kept neighbours). Only there does a kept
    point's band hold its neighbours' centres with the kernel around them
    (:func:`~.marks.kept_tiles`; the ring ``m + 2 spread`` bounds them); elsewhere its
    own samples' (the box ``m + spread`` bounds them, with ``pcf``'s region at that
    level). On ``random_terrain_world(123)`` at 64^2, 99 of 203 kept points have such a
    neighbour; at 256^2 the ring where read took ``pcf`` 9.45 -> 8.62 texels a film pixel
    with the images those of every ring (``benchmarks/RESULTS.md``, the forty-ninth
    session, helper A). Unevaluated: 8 gathers on the kept lanes, in the dedupe's second
    kernel (:func:`prepare_virtual`); read on the host."""
    w, h = (int(x) for x in sensor.film().crop_size())
    kept = mi.Bool(kept)

    def neighbours(pixel, kept):
        x, y = mi.Int32(pixel & 0xFFFF), mi.Int32(pixel >> 16)
        own = dr.gather(mi.UInt32, centre, mi.UInt32(x + y * w), kept) & KEEP_SHAPE
        read = mi.Bool(False)
        for dy in (-1, 0, 1):
            for dx in (-1, 0, 1):
                if dx == 0 and dy == 0:
                    continue
                nx, ny = x + dx, y + dy
                ok = kept & (nx >= 0) & (ny >= 0) & (nx < w) & (ny < h)
                n = dr.gather(mi.UInt32, centre, mi.UInt32(ny * w + nx), ok)
                uncapped = (n & (KEEP_CENTRE | KEEP_OTHERS)) == 0
                read |= ok & (((n & KEEP_SHAPE) != own) | uncapped)
        return read

    # in a conditional: the packets without a kept lane (most: 2-8 % of the points keep
    # the level, in blocks of the film) skip the gathers
    return if_stmt((camera_pixels(sensor), kept), kept, neighbours,
                   lambda pixel, kept: mi.Bool(False),
                   label="virtual marks: the kept points' reading neighbours")


def _film_border(sensor, n: int) -> mi.Bool:
    """Whether each of the ``n`` camera hits of :func:`~.marks.camera_hits` is in a
    pixel on the film's border (:func:`~.marks._margins`' ``m_edge``): one hit a pixel,
    or ``LENS_GRID``^2 through a lens, pixel after pixel's set (unevaluated)."""
    w, h = (int(x) for x in sensor.film().crop_size())
    pixel = camera_pixels(sensor)
    if n != dr.width(pixel):
        pixel = dr.gather(mi.UInt32, pixel, dr.arange(mi.UInt32, n) % dr.width(pixel))
    x, y = pixel & 0xFFFF, pixel >> 16
    return (x == 0) | (y == 0) | (x == w - 1) | (y == h - 1)
