"""Virtual shadow maps: build only the texels the image reads, at the density it needs.

After Unreal Engine 5's virtual shadow maps (and Olsson et al. 2014's virtual
cube maps, Lauritzen et al. 2010's sample distribution): every face of an
emitter's :class:`~mi_shadowmap.light_views.LightView` is a very large
*virtual* map (``res0`` texels per side, up to ``2^30``) with a mip chain of
levels (level ``l`` has ``res0 >> l`` texels per side; the last level is one
page). Levels are split into pages of ``page_size^2`` texels anchored in
light space. Only the pages that camera-visible points read are built,
into one physical page pool (one ``mi.Float`` per layer) with a page table, and of
those only the *tiles* (:data:`TILE_SIZE`^2 texels, at most 4 x 4 a page) the points
read are ray-cast.

**Mark pass** (:func:`mark_candidates`): one camera ray through every pixel centre
(with its ray differentials, one pixel wide; a camera with a lens: :data:`LENS_GRID`^2
rays through points of its lens). Each hit that can receive the
light picks the level whose texel matches its pixel footprint projected into
the light (:meth:`VirtualShadowMap.level_for`: ``floor(log2(w) + lod_bias)``
for a footprint ``w`` level-0 texels wide; at the default ``lod_bias = -0.5``
a texel is 0.35-0.7 footprint wide) and marks the tiles its lookup reads: those
within the method's ``virtual_margin`` (its kernel's half-width) plus one texel
(camera samples off the pixel centre) of it. Kernels up to ``page_size / 2``
texels stay inside the 2 x 2 pages a lookup binds (below); the taps of a wider kernel
read their own pages through the page table (:attr:`VirtualShadowMap.far_taps`). A
method whose kernels may filter coarser levels (``virtual_coarse_res``: a PCSS penumbra
wider than ``max_kernel`` texels) also marks, on each of those levels, the tile under
the point (:func:`mark_coarser`) and, on the host, the tiles within its margin of those
(:func:`dilate_tiles`; not capped at ``page_size / 2``: such levels hold few tiles). A
render whose camera state (:func:`camera_state`) equals the previous one's reuses its
marks.

**Tiles**: a page is the unit of the pool and the page table; a tile is the unit of
ray casting. A page's marked tiles are ray-cast, its others hold the coarsest level's
texel over them (a copy, no ray), and a per-slot tile mask records which is which; a
camera move casts the newly marked tiles of pages already built. Objects smaller than a
page (thin posts, far boxes) and the rim of what the camera sees read a corner of a
page: on ten random large worlds at a 256^2 film, whole 32^2 pages cast 5.4-9.5 texels
per film pixel for ``hard``, 8^2 tiles 3.1-6.5, with the same misclassified pixels
(``benchmarks/RESULTS.md``).

**Lookups** (:meth:`VirtualShadowMap.bind`): the integrator binds the map to
each batch of lookups. The level is chosen per lane the same way; if the
page under the receiver is missing at that level, or its tile there is not ray-cast
(a camera sample off the pixel centre) it takes the next finer level, else the next coarser one, else
the coarsest level (one page per face), which is always built, so no point is
lit for want of a page (a loop that only lanes with a missing page enter). The
lookup of a method with ``virtual_per_tap`` (``hard``) does not wait for that walk: it
reads at its wanted level, each read checking its own page and tile, and only the lanes
where one is missing run again, walked (:meth:`VirtualShadowMap.visibility`). The
2 x 2 pages around the receiver are found in the page table once per lookup (per
face and level, a grid over the bounding rectangle of its built pages whose entry
holds the 2 x 2 block's four slots: no loop). The filter's taps then read through
:meth:`BoundVirtualMap.fetch`: a tap inside those pages reads its page's slot (the
four gathered once per lookup, or, for a method with ``virtual_per_tap`` such as
``hard``, each tap's own slot gathered when it reads), a tap outside them (a wide
kernel, a cube seam) the coarsest level, whose page of face ``f`` is always in slot
``f + 1`` (no gather). Filters see a
:class:`~mi_shadowmap.light_views.local.LocalView`: coordinates local to
the lookup, so float32 stays exact at any level.

**Derived layers**: pages hold depths (and ``second_depth``, ray-cast per tile). A
method whose full maps carry layers derived from the whole face -- ``mdsm``'s 3 x 3
extremes, the prefiltered methods' summed-area tables -- computes what it reads from
the pages' depths at lookup time instead (see those modules); the prefiltered methods
normalise depths by the layout's ``depth_range`` (the scene's bounding box as the light
sees it), which does not change as pages are built.

**Environment lights**: an :class:`~mi_shadowmap.environment.EnvironmentView`'s K
median-cut regions are the K faces of one virtual map (orthographic faces, like a
directional light's), marked per region for the points it can light
(``mark_views``) and read through the region of the shading loop
(:meth:`VirtualShadowMap.with_view`); see :mod:`mi_shadowmap.environment`.

**Cascades** (``virtual=true`` with ``cascades`` > 1): a directional light's view is
its :class:`~mi_shadowmap.light_views.CascadedView`, fitted to the camera as for full
maps, and each cascade is a virtual face, plus one face for the whole rectangle, read by
points outside their cascade's (camera samples off the pixel centres, towards the
horizon). Cascades follow the camera, so a moved camera gets new faces and their pages
are built anew (:meth:`PageCache.retire` drops the old ones); the automatic virtual maps
need no cascades.

**Caching** (:data:`PAGE_CACHE`): pages live in light space, so a camera move
builds only the pages that were never built; the cache is dropped when the
scene's shapes or emitters change (the map cache's scene state). Every
camera-dependent value is data (page tables, levels, slots), never a kernel
literal, so moving the camera compiles no new kernel.

**Memory** (``memory_budget``): the pool holds at most the budget's pages
(all layers). Cached pages the frame does not read are evicted first; if the
frame's own pages do not fit, the finest marked pages are replaced by their
parents (coarser, never missing) with a warning.

**Gradients**: pages are built detached; with ``virtual`` automatic (left out), a
render whose shape or emitter parameters have gradients enabled gets full maps,
built in the AD graph (issue 13); with ``virtual=true`` given it is refused.

Deviations from UE5, and why:

* One mechanism for every light: a mip chain over the whole (scene-fitted)
  face, addressed sparsely through per-level page grids, instead of UE5's clipmaps
  around the camera for directional lights. Levels chosen from the pixel
  footprint give the same density falloff as clipmaps, and pages anchored to
  the scene-fitted face never move with the camera.
* The mark pass traces its own camera ray per pixel centre instead of reading
  the render's primary hits (Mitsuba's ``render()`` traces those inside one
  kernel with the shading); it is one ray per pixel against the frame's spp.
* Taps that leave the receiver's 2 x 2 pages read the coarsest level rather
  than the finest built one (a fixed slot instead of a walk per tap); so do taps
  beyond the marked kernel in a tile that was not ray-cast (its copy of the coarsest
  level; the lookup checks only the receiver's own tile).
* Pages are ray-cast in tiles (UE5 renders whole pages of 128^2): the
  texels-per-pixel budget of issue 11 (8 at a 256^2 film) is spent on what lookups
  read rather than on the rest of pages a thin object or the view's rim touches.
"""
from __future__ import annotations

import collections
import copy
import dataclasses
import math
import time
import warnings

import drjit as dr
import mitsuba as mi
import numpy as np

from . import depth_maps
from .depth_maps import first_hit, second_depth_along
from .methods import (VIRTUAL_LAYERS, MethodError,  # noqa: F401  (VIRTUAL_LAYERS: built here)
                      virtual_coarse_res_of, virtual_margin_of)
from .light_views import (pinhole_footprint, pinhole_frame, pixel_centres,
                          pixel_ray_differentials)
from .light_views.base import TEXEL_SAMPLE, opaque_point, scene_bounds
from .light_views.local import LocalView
from .light_views import box_view

#: Largest virtual resolution per face side (texel coordinates stay in an Int32).
MAX_VIRTUAL_RES = 2 ** 30
#: Default virtual resolution: 2^24 texels across the scene's extent as the light sees it.
#: Levels are chosen by pixel footprint, so a finer level 0 costs nothing where pixels do
#: not need it (the repository scenes build the same texels as with 2^20); 2^20 was
#: about 1 unit a texel on a world 1e6 wide, which lost 1-unit posts' shadows under a
#: low sun (0.96 % misclassified at 128^2; 0.34 % now, as with any finer level).
SCENE_TEXELS = 2 ** 24
#: Pages are ray-cast in tiles of this many texels per side (at most 4 x 4 tiles a page):
#: a page holds the tiles its lookups read, the rest hold the coarsest level's depths.
TILE_SIZE = 8
#: Footprint anisotropy kept: a level's texel is at least 1/ANISO of the footprint's
#: longer side (grazing views would otherwise ask for the finest level everywhere).
ANISO = 2.0

_INVALID = 0xFFFFFFFF
#: Never a page key (its level, 31, is beyond any layout's): an empty slot of the mark
#: pass's hash table.
_NO_KEY = 0xFFFFFFFFFFFFFFFF
#: Largest page grid of one (face, level) in the page table (entries of 4 slots).
MAX_TABLE = 1 << 22
#: Largest page grid side (the header packs width and height into 32 bits of one uint64).
MAX_TABLE_SIDE = (1 << 15) - 1
#: Coarser levels the mark pass builds at most, beyond a point's own, for a method whose
#: kernel may filter a coarser level (``virtual_coarse_res``: PCSS's kernels wider than
#: ``max_kernel`` texels): up to 2^8 times its footprint level's texel.
MAX_COARSER = 8


def _array(cls, values):
    """A Dr.Jit array of ``values`` that is never a kernel literal: a one-entry array
    would be one (a new kernel whenever its value changes), so it is padded."""
    values = np.asarray(values)
    if len(values) < 2:
        values = np.concatenate([values, np.zeros(2 - len(values), values.dtype)])
    return cls(values)


def page_key(face, level, px, py):
    """64-bit key of a page: face (5 bits: at most 32 faces), level (5 bits), px and py
    (27 bits each);
    numpy or Dr.Jit integers."""
    if isinstance(px, np.ndarray) or isinstance(face, (int, np.integer)):
        return ((np.uint64(face) << np.uint64(59)) | (np.uint64(level) << np.uint64(54))
                | (np.asarray(px, np.uint64) << np.uint64(27)) | np.asarray(py, np.uint64))
    U = mi.UInt64
    return ((U(face) << 59) | (U(level) << 54) | (U(mi.UInt32(px)) << 27)
            | U(mi.UInt32(py)))


def key_fields(keys):
    """``(face, level, px, py)`` of page (or tile) keys, the inverse of :func:`page_key`:
    ``np.uint64`` arrays for numpy keys, ``mi.UInt32`` for ``mi.UInt64`` keys."""
    M = (1 << 27) - 1
    if isinstance(keys, np.ndarray):
        k = keys.astype(np.uint64, copy=False)
        return (k >> np.uint64(59), (k >> np.uint64(54)) & np.uint64(31),
                (k >> np.uint64(27)) & np.uint64(M), k & np.uint64(M))
    return (mi.UInt32(keys >> 59), mi.UInt32(keys >> 54) & 31,
            mi.UInt32(keys >> 27) & M, mi.UInt32(keys) & M)


@dataclasses.dataclass
class VirtualLayout:
    """The fixed (camera-independent) shape of one emitter's virtual map."""
    #: the emitter's view, or for a light far from the scene one face aimed at it
    #: (:func:`~mi_shadowmap.light_views.perspective.box_view`, see :func:`layout_for`)
    view: object
    page_size: int
    res0: int
    #: texel rays start this far along (near the scene), in float64; the pages' depths
    #: are measured from there (``t0`` less than the light's distance): float32 keeps
    #: them to a scene-sized precision for a light at any distance, where the distance
    #: from the light itself would round to 64 units at 1e9 (lookups subtract ``t0``
    #: from the receiver's float64 depth the same way, :class:`LocalView`)
    t0: float
    #: ``(d_lo, d_hi)``: bounds of the depths the map can hold, from the scene's bounding
    #: box as the light sees it, measured from ``t0`` (what the prefiltered methods
    #: normalise by)
    depth_range: tuple = (0.0, 1.0)

    @property
    def n_levels(self) -> int:
        return int(math.log2(self.res0 // self.page_size)) + 1

    @property
    def coarsest(self) -> int:
        return self.n_levels - 1

    def pages_per_side(self, level: int) -> int:
        return max((self.res0 >> level) // self.page_size, 1)

    @property
    def tile_size(self) -> int:
        """Side of a tile, the unit pages are ray-cast in: :data:`TILE_SIZE` texels, or
        ``page_size / 4`` for pages wider than 32 (at most 4 x 4 tiles a page, one bit
        each in the page's tile mask)."""
        return max(min(TILE_SIZE, self.page_size), self.page_size // 4)

    @property
    def tiles_per_side(self) -> int:
        """Tiles per page side."""
        return self.page_size // self.tile_size

    @property
    def full_mask(self) -> int:
        """The tile mask of a page whose every tile is built."""
        return (1 << self.tiles_per_side ** 2) - 1


def layout_for(view, scene, opts) -> VirtualLayout:
    """The virtual layout of ``view``: ``res0`` is ``resolution`` if given, else the
    power of two that puts :data:`SCENE_TEXELS` texels across the scene's bounding
    box as the light sees it (at least :data:`SCENE_TEXELS`, at most :data:`MAX_VIRTUAL_RES`);
    ``t0`` is the distance from the light to the scene's bounding box less the box's
    diagonal when that is more than the diagonal (else 0, and 0 for directional maps,
    which start at their near plane). The scene is what the light shadows: every shape
    but an area light's own (a large far light would otherwise widen the box to itself).
    Without ``resolution``, a light so far that ``res0`` would be capped gets one face
    aimed at the box (:func:`~mi_shadowmap.light_views.perspective.box_view`) as the
    layout's view: a cube face's capped finest level has texels 1.9 units wide 1e9 away,
    coarser than a 10-unit scene's casters."""
    P = opts.page_size
    # scene.bbox() misses merged meshes
    bounds = scene_bounds(scene, exclude=getattr(view, "ignore_shape", None))
    lo, hi = bounds if bounds is not None else (-np.ones(3), np.ones(3))
    diam = float(np.linalg.norm(hi - lo)) or 1.0
    pos = np.array([float(c) for c in view.position])
    dist = float(np.linalg.norm(np.maximum(np.maximum(lo - pos, 0.0), pos - hi)))
    centre = 0.5 * (lo + hi)
    if view.kind in ("directional", "environment"):    # orthographic faces
        t0 = 0.0
    else:
        # rays start near the scene only for a light far from it, one box diagonal before
        # the box (float32 positions stay exact there, and the depths the pages hold,
        # measured from there, stay within a few diagonals whatever the distance); a
        # light next to the scene starts them at the light, as full maps do (a blocker
        # right at the light would otherwise fall within first_hit's skip)
        t0 = dist - diam if dist > diam else 0.0

        def face_width(view):
            return 2.0 * float(getattr(view, "tan_half", 1.0)) * max(
                float(np.linalg.norm(centre - pos)), 1e-30)
        # a light so far that the finest level would be capped (about 32 box diagonals
        # away for a cube): one face aimed at the box instead (box_view), whose texels
        # all fall on the scene; the layout's view is then that face
        if (opts.resolution is None and bounds is not None
                and SCENE_TEXELS * face_width(view) / diam > MAX_VIRTUAL_RES):
            fitted = box_view(view, lo, hi)
            if fitted is not None and fitted.tan_half < float(getattr(view, "tan_half", 1.0)):
                view = fitted
    if opts.resolution is not None:
        res0 = int(opts.resolution)
    else:
        width = (2.0 * max(view.half_extent) if view.kind in ("directional", "environment")
                 else face_width(view))
        want = max(SCENE_TEXELS * width / diam, SCENE_TEXELS)
        res0 = 1 << max(int(math.ceil(math.log2(want))), 0)
        res0 = min(max(res0, P), MAX_VIRTUAL_RES)
    d_lo, d_hi = _depth_range(view, lo, hi, dist)
    if t0 > 0.0:     # the far light's depths, measured from t0 (see VirtualLayout)
        d_lo, d_hi = dist - t0, d_hi - t0
    return VirtualLayout(view, P, res0, t0, (d_lo, d_hi))


def _depth_range(view, lo, hi, dist) -> tuple:
    """``(d_lo, d_hi)``: the depths of the box ``[lo, hi]`` as ``view`` measures them
    (a directional map's along its direction from its near plane; the others' at most
    the distance from the light), d_hi > d_lo >= 0."""
    corners = np.array([[(lo, hi)[k >> a & 1][a] for a in range(3)] for k in range(8)])
    if view.kind == "environment":     # every region's orthographic face
        d_lo, d_hi = view.depth_range64(corners)
        d_lo = max(d_lo, 0.0)
    elif view.kind == "directional":
        # from lists: Dr.Jit copies them into its own (aligned) memory, while numpy
        # arrays may be read in place, and their alignment would enter the kernel's hash
        # (a kernel compiled per layout: with cascades, per camera move)
        p = mi.Point3d(*(mi.Float64(corners[:, a].tolist()) for a in range(3)))
        depth = np.asarray(view.project_f64(p)[2].numpy(), np.float64)
        d_lo, d_hi = max(float(depth.min()), 0.0), float(depth.max())
    else:
        pos = np.array([float(c) for c in view.position])
        d_lo, d_hi = dist, float(np.linalg.norm(corners - pos, axis=1).max())
    if not (math.isfinite(d_hi) and d_hi > 0.0):
        d_lo, d_hi = 0.0, 1.0
    return (min(d_lo, 0.5 * d_hi), d_hi)


# ---------------------------------------------------------------- the page store
class PageStore:
    """The physical pages of one emitter's virtual map, kept across renders.

    ``slots``: page key -> slot (a view of the built pages, kept as two arrays); the
    pool of each layer holds ``capacity``
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
        self.pools = {name: mi.Float() for name in ("depth",) + self.layers}
        self.page_min = np.zeros(0, np.float64)     # nearest finite depth per slot
        self.page_face = np.zeros(0, np.int64)
        self.slot_frame = np.zeros(0, np.int64)      # frame each slot was last read
        self.slot_mask = np.zeros(0, np.int64)       # tiles built per slot (bit per tile)
        self.pages_cast = 0                          # pages the last build cast tiles of
        self.cast_seconds = 0.0                      # all builds' ray casting ...
        self.cast_pages = 0                          # ... and the pages they cast
        self.frame = 0
        self.version = 0                             # changes whenever pages do
        self._sorted = None
        self._table = None
        self.lit_faces = None                        # faces a one-sided light shines through
        self.coarse_keys = None                      # their coarsest pages' keys
        # slot 0 is never allocated: an empty page (+inf, lit). Slot f + 1 is reserved for
        # face f's coarsest page (always built where the light shines; empty where a
        # one-sided light does not), so a lookup finds it without a gather
        self.next_slot = 1 + layout.view.n_faces
        # ((camera state, margin, coarse_res, lod_bias), marked tile keys, those of them
        # only coarser-level kernels read)
        self.last_mark = None
        # the last render's (last_mark, budget, version, needed keys, their slots, level
        # histogram, pages degraded): a render with the same three reuses the rest
        self.settled = None
        self.max_pages = 1 << 62      # the memory budget's pages (set per render)

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
        self.page_min = np.concatenate([self.page_min, np.full(cap - self.capacity, np.inf)])
        self.page_face = np.concatenate([self.page_face, np.zeros(cap - self.capacity, np.int64)])
        self.slot_frame = np.concatenate([self.slot_frame, np.zeros(cap - self.capacity, np.int64)])
        self.slot_mask = np.concatenate([self.slot_mask, np.zeros(cap - self.capacity, np.int64)])
        self.capacity = cap
        dr.eval(*self.pools.values())

    def _index(self):
        """``(keys, slots)`` sorted by key, rebuilt when the pages change."""
        if self._sorted is None or self._sorted[0] != self.version:
            order = np.argsort(self._keys)
            self._sorted = (self.version, self._keys[order], self._slot_of[order])
        return self._sorted[1], self._sorted[2]

    def lookup(self, keys: np.ndarray):
        """``(present, slot)`` of each of ``keys`` (slot -1 where absent)."""
        k, sl = self._index()
        if len(k) == 0:
            return np.zeros(len(keys), bool), np.full(len(keys), -1, np.int64)
        pos = np.clip(np.searchsorted(k, keys), 0, len(k) - 1)
        present = k[pos] == keys
        return present, np.where(present, sl[pos], -1)

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
        a tap beyond the lookup's 2 x 2 pages reads). Returns the texels ray-cast."""
        self.pages_cast = 0
        if len(keys) == 0:
            return 0
        lay = self.layout
        P, T, S = lay.page_size, lay.tile_size, lay.tiles_per_side
        keys = np.asarray(keys, np.uint64)
        masks = (np.full(len(keys), lay.full_mask, np.int64) if masks is None
                 else np.asarray(masks, np.int64))
        coarse = ((keys >> np.uint64(54)) & np.uint64(31)) == np.uint64(lay.coarsest)
        masks = np.where(coarse, lay.full_mask, masks)     # the coarsest pages: whole
        present, slot_ids = self.lookup(keys)
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
            self.page_min[slot_ids[new]] = np.inf
            self.page_face[slot_ids[new]] = (keys[new] >> np.uint64(59)).astype(np.int64)
        cast = masks & ~self.slot_mask[slot_ids]
        # the tiles to cast: tile keys (page_key in tile units) and their slots
        bit = np.arange(S * S)
        sel = (cast[:, None] >> bit[None, :]) & 1 == 1
        page_i, tile_b = np.nonzero(sel)
        n_tiles = len(page_i)
        self.pages_cast = int(sel.any(axis=1).sum())
        if n_tiles == 0 and not new_fine.any():
            return 0
        self.version += 1
        built = 0
        second = "second_depth" in self.pools
        if n_tiles:
            f, lv, px, py = key_fields(keys[page_i])
            tkeys = page_key(f, lv, px * np.uint64(S) + (tile_b % S).astype(np.uint64),
                             py * np.uint64(S) + (tile_b // S).astype(np.uint64))
            tslots = slot_ids[page_i]
            tpt = T * T
            idx = dr.arange(mi.UInt32, n_tiles * tpt)
            tile = idx // tpt
            local = idx - tile * tpt
            ti, tj = morton_xy(local, T)   # 4 x 2 blocks of neighbours per vector
            # one upload of the tile keys (decoded in the kernel) and one of the slots
            f_l, lev, tx, ty = key_fields(dr.gather(mi.UInt64, _array(mi.UInt64, tkeys), tile))
            gx, gy = tx * T + ti, ty * T + tj
            res = mi.Float64(mi.UInt32(lay.res0) >> lev)
            uv = mi.Point2d((mi.Float64(gx) + TEXEL_SAMPLE[0]) / res,
                            (mi.Float64(gy) + TEXEL_SAMPLE[1]) / res)
            o64, d64 = lay.view.ray_through_f64(f_l, uv)
            o = mi.Point3f(o64 + d64 * lay.t0)     # start near the scene: float32 stays exact
            d = dr.normalize(mi.Vector3f(d64))
            slot = dr.gather(mi.UInt32, _array(mi.UInt32, tslots.astype(np.uint32)), tile)
            dst = slot * (P * P) + (gy & (P - 1)) * P + (gx & (P - 1))
            # depths from the rays' start (t0 along them, VirtualLayout.t0)
            depth = first_hit(scene, lay.view, o, d)
            dr.scatter(self.pools["depth"], depth, dst)
            if second:
                sd = second_depth_along(scene, lay.view, o, d)
                dr.scatter(self.pools["second_depth"], sd, dst)
            # one kernel: the depths (kept: the tile minima read them) and the scatters
            dr.eval(depth)
            np.minimum.at(self.page_min, tslots, page_minima(depth, tpt))
            built = n_tiles * tpt * (1 + second)
        self.slot_mask[slot_ids] |= masks
        if new_fine.any():
            self._fill_from_coarsest(keys[new_fine], slot_ids[new_fine], masks[new_fine])
        return built

    def _fill_from_coarsest(self, keys, slots, masks) -> None:
        """The tiles of new pages that were not cast: the coarsest level's texel over
        each (its page of face ``f`` is in slot ``f + 1``), as :meth:`BoundVirtualMap.
        fetch` reads beyond a lookup's 2 x 2 pages."""
        lay = self.layout
        P, T, S = lay.page_size, lay.tile_size, lay.tiles_per_side
        if S == 1:
            return
        tpp = P * P
        idx = dr.arange(mi.UInt32, len(keys) * tpp)
        page = idx // tpp
        local = idx - page * tpp
        ti, tj = local % P, local // P
        face, lev, px, py = key_fields(dr.gather(mi.UInt64, _array(mi.UInt64, keys), page))
        mask = dr.gather(mi.UInt32, _array(mi.UInt32, masks.astype(np.uint32)), page)
        slot = dr.gather(mi.UInt32, _array(mi.UInt32, slots.astype(np.uint32)), page)
        gx, gy = px * P + ti, py * P + tj
        shift = mi.UInt32(lay.coarsest) - lev
        src = (face + 1) * tpp + (gy >> shift) * P + (gx >> shift)
        b = (ti // T) + (tj // T) * S
        empty = ((mask >> b) & 1) == 0
        values = {name: dr.gather(mi.Float, pool, src, empty)
                  for name, pool in self.pools.items()}
        dr.eval(*values.values())     # read before the scatters write the same pools
        for name, v in values.items():
            dr.scatter(self.pools[name], v, slot * tpp + local, empty)
        dr.eval(*self.pools.values())

    def table(self):
        """The page table as Dr.Jit arrays ``(header, dense, face_near, tile_masks,
        dense_tiles)``,
        rebuilt when pages change (``face_near``: the nearest depth per face, PCSS's
        blocker-search bound; ``tile_masks``: which tiles of each slot are ray-cast).

        Per (face, level) -- entry ``face * n_levels + level`` -- ``header`` holds
        two 64-bit words, ``(x0 - 1) | (y0 - 1) << 32`` and ``W | H << 16 | base << 32``
        (32-bit fields, the first two signed): the grid of 2 x 2 blocks
        whose lower-left page is in ``[x0 - 1, x0 + w - 1] x [y0 - 1, y0 + h - 1]``,
        ``(x0, y0, w, h)`` the bounding rectangle of that level's built pages (in
        pages), ``W = w + 1``, ``H = h + 1``, and where its ``W x H`` entries start
        in ``dense``. Each entry of ``dense`` holds the block's 4 slots (pages
        ``(bx, by)``, ``(bx + 1, by)``, ``(bx, by + 1)``, ``(bx + 1, by + 1)``;
        ``_INVALID`` where none is built), so a lookup reads its block with no loop.
        A level whose grid would exceed :data:`MAX_TABLE` entries or
        :data:`MAX_TABLE_SIDE` per side keeps its pages out of the table (lookups
        there walk to another level). The coarsest page of face ``f`` is in slot
        ``f + 1`` (:class:`PageStore`), so it needs no table. The fourth array holds
        each slot's tile mask (which of its tiles are ray-cast), the fifth the tile mask
        of each entry of ``dense`` (0 where none is built): read with its slot, not after.
        """
        if self._table is not None and self._table[0] == self.version:
            return self._table[1]
        lay = self.layout
        L = lay.n_levels
        keys, slots = self._index()
        face, level, px, py = (f.astype(np.int64) for f in key_fields(keys))
        group = face * L + level
        header = np.zeros((lay.view.n_faces * L, 4), np.int64)   # W = H = 0: no block
        # keys are sorted, so each (face, level) group is one run: its bounding rectangle
        # by reduceat, then every page is one of the 4 corners of 4 blocks (vectorised)
        starts = (np.flatnonzero(np.concatenate([[True], group[1:] != group[:-1]]))
                  if len(keys) else np.zeros(0, np.int64))
        groups = group[starts]
        x0 = np.minimum.reduceat(px, starts) if len(keys) else starts
        y0 = np.minimum.reduceat(py, starts) if len(keys) else starts
        w = np.maximum.reduceat(px, starts) - x0 + 1 if len(keys) else starts
        h = np.maximum.reduceat(py, starts) - y0 + 1 if len(keys) else starts
        W, H = w + 1, h + 1
        fits = (W * H <= MAX_TABLE) & (np.maximum(W, H) <= MAX_TABLE_SIDE)
        for g, ww, hh in zip(groups[~fits], w[~fits], h[~fits]):
            warnings.warn(f"shadowmap: virtual map '{lay.view.label}': level "
                          f"{g % L} spans {ww} x {hh} pages, more than the page table "
                          "holds; its lookups use other levels", RuntimeWarning)
        base = np.cumsum(np.where(fits, W * H, 0)) - np.where(fits, W * H, 0)
        header[groups[fits]] = np.stack([x0 - 1, y0 - 1, W | (H << 16), base], -1)[fits]
        total = int(np.where(fits, W * H, 0).sum())
        dense = np.full(4 * total + 4, _INVALID, np.int64)   # + 4: one empty entry
        run = np.repeat(np.arange(len(starts)), np.diff(np.append(starts, len(keys))))
        keep = fits[run]
        px, py, slots, run = px[keep], py[keep], slots[keep], run[keep]
        lx0, ly0, e0, Wr = px - (x0[run] - 1), py - (y0[run] - 1), 4 * base[run], 4 * W[run]
        for k in range(4):     # page (px, py) is corner k of block (px - k & 1, py - k >> 1)
            dense[e0 + (ly0 - (k >> 1)) * Wr + 4 * (lx0 - (k & 1)) + k] = slots
        u32 = lambda a: a.astype(np.int64).astype(np.uint32).astype(np.uint64)  # noqa: E731
        words = np.stack([u32(header[:, 0]) | (u32(header[:, 1]) << np.uint64(32)),
                          u32(header[:, 2]) | (u32(header[:, 3]) << np.uint64(32))], -1)
        table = (_array(mi.UInt64, words.reshape(-1)),
                 _array(mi.UInt32, dense.astype(np.uint32)),
                 _array(mi.Float, self.face_near(lay.view.n_faces)),
                 _array(mi.UInt32, self.slot_mask[:max(self.next_slot, 1)].astype(np.uint32)),
                 _array(mi.UInt32, np.where(dense == _INVALID, 0, self.slot_mask[
                     np.where(dense == _INVALID, 0, dense)]).astype(np.uint32)))
        self._table = (self.version, table)
        return table

    def face_near(self, n_faces: int) -> np.ndarray:
        """Nearest finite depth per face over the built pages (+inf for none)."""
        out = np.full(n_faces, np.inf)
        used = self._index()[1]
        if len(used):
            np.minimum.at(out, self.page_face[used], self.page_min[used])
        return out.astype(np.float32)


# ------------------------------------------------------------ the map filters read
class VirtualShadowMap:
    """One emitter's virtual map for one render: the page pool and its table.

    What a filter reads is :meth:`bind`'s :class:`BoundVirtualMap`; this object is
    what ``integrator.maps`` holds (``view``, ``layout``, ``store``, ``stats``).
    """

    def __init__(self, store: PageStore, stats: dict, lod_bias: float = -0.5,
                 margin: float = 2.0, coarse_res: int | None = None):
        self.lod_bias = float(lod_bias)
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
            store.table()
        self.depth_bounds = _array(mi.Float64, self.layout.depth_range)
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
    def level_for(self, face, p64, dp_dx, dp_dy) -> mi.UInt32:
        """Level whose texel matches the pixel footprint ``dp_dx``, ``dp_dy`` at
        ``p64`` on ``face``: ``floor(log2(w) + lod_bias)`` clamped to the levels,
        ``w`` the footprint in level-0 texels (its shorter side, or 1/ANISO of its
        longer one if larger); at ``lod_bias = -0.5`` a texel is 0.35-0.7 of the
        footprint. No footprint (no ray differentials): level 0, and the
        lookup walks to the finest level built."""
        view, lay = self.view, self.layout
        p = mi.Point3f(p64)
        du_x = view.uv_differential(face, p, dp_dx)
        du_y = view.uv_differential(face, p, dp_dy)
        w = (dr.abs(du_x) + dr.abs(du_y)) * float(lay.res0)
        w_eff = dr.maximum(dr.minimum(w.x, w.y), dr.maximum(w.x, w.y) * (1.0 / ANISO))
        w_eff = dr.select(dr.isfinite(w_eff) & (w_eff > 1.0), w_eff, 1.0)
        # floor(log2(w) + lod_bias) is the binary exponent of w 2^lod_bias, a normal float
        # or +inf (w >= 1, |lod_bias| <= 8): read from its bits, not through a log2
        # polynomial (about 1 ns of a lookup's 6-13)
        scaled = w_eff * float(2.0 ** self.lod_bias)
        level = mi.Int32(dr.reinterpret_array(mi.UInt32, scaled) >> 23) - 127
        return mi.UInt32(dr.clip(level, 0, lay.coarsest))

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

    def with_view(self, view) -> "VirtualShadowMap":
        """This map read through ``view``, a view of some of its faces with the same
        float64 interface (an environment's region ``k``, per lane: its shading loop)."""
        out = copy.copy(self)
        out.view = view
        return out

    def bind(self, lk, active=True, per_tap: bool = False,
             walk: bool = True, level=None) -> "BoundVirtualMap":
        """The map as one batch of lookups reads it (see the module doc). With
        ``per_tap`` every read gathers its own page's slot (cheapest for lookups that
        read a texel or two: ``hard``); else the 2 x 2 pages' four slots are gathered
        here, once per lookup (wide kernels). With ``walk`` False (``per_tap`` only) every
        lane stays at its wanted level and each read checks that its own page and tile
        are built there, collecting the lanes where one is not in the result's
        ``missed`` (:meth:`visibility` runs those again, walked). ``level`` (per lane,
        clamped to the coarsest): the level wanted instead of the pixel footprint's (a
        PCSS kernel wider than ``max_kernel`` texels filters a coarser level); the walk
        is the same."""
        lay, P = self.layout, self.layout.page_size
        T, S = lay.tile_size, lay.tiles_per_side
        p64 = mi.Point3d(lk.p_world)
        face, uv64, depth64, inside = self.view.project_f64(p64)
        active = mi.Bool(active) & inside
        want = (self.level_for(face, p64, lk.dp_dx, lk.dp_dy) if level is None
                else dr.minimum(mi.UInt32(level), mi.UInt32(lay.coarsest)))

        def block(level, act):
            """The 2 x 2 pages around the point at ``level`` (their table entry), and
            whether the page under it is built."""
            res = mi.Int32(mi.UInt32(lay.res0) >> level)
            xy = uv64 * mi.Float64(res)
            bx = mi.Int32(dr.floor((xy.x - 0.5 * P) / P))
            by = mi.Int32(dr.floor((xy.y - 0.5 * P) / P))
            e, eok = self._block_entry(face, level, bx, by, act)
            cx = mi.Int32(dr.floor(xy.x / P)) > bx        # which of the 2 x 2 holds it
            cy = mi.Int32(dr.floor(xy.y / P)) > by
            q = mi.UInt32(dr.select(cx, 1, 0) + dr.select(cy, 2, 0))
            own = dr.gather(mi.UInt32, self.dense, e + q, eok)
            built = eok & (own != _INVALID)
            if S > 1:       # and the tile under it ray-cast (not the coarsest level's fill)
                ix = mi.UInt32(mi.Int32(dr.floor(xy.x)) & (P - 1)) // T
                iy = mi.UInt32(mi.Int32(dr.floor(xy.y)) & (P - 1)) // T
                tiles = dr.gather(mi.UInt32, self.tile_masks, own, built)
                built &= ((tiles >> (ix + iy * S)) & 1) != 0
            return res, bx, by, e, eok, built

        # the wanted level (nearly every lookup); else the next finer, else the next
        # coarser, else the coarsest (always built). The fallbacks run in a loop that
        # only lanes whose page is missing enter: most vector packets skip it.
        res, bx, by, e, eok, ok = block(want, active)
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
            lev = dr.select(step == 0, dr.maximum(want_i - 1, 0),
                            dr.select(step == 1, dr.minimum(want_i + 1, lay.coarsest),
                                      mi.Int32(lay.coarsest)))
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
        slots = None
        if not per_tap:
            slots = [dr.select(eok, dr.gather(mi.UInt32, self.dense, e + k, eok), _INVALID)
                     for k in range(4)]
        origin = mi.Point2i(bx * P, by * P)
        local = LocalView(self.view, face, res, origin, (lk.p_world, uv64, depth64, inside),
                          depth_origin=self.depth_origin)
        return BoundVirtualMap(self, local, res, level, (e, eok), slots, check_reads, inside)

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
        methods, the lookup runs once, walked."""
        if not per_tap or dr.grad_enabled(lk.p_world, lk.n_world):
            return lookup(self.bind(lk, active, per_tap), lk, opts, active)
        first = self.bind(lk, active, per_tap, walk=False)
        vis = mi.Float(lookup(first, lk, opts, active))
        if first.missed is None:       # the lookup read no texel
            return vis
        retry = mi.Bool(active) & first.inside & first.missed
        again = dataclasses.replace(lk, sampler=None if lk.sampler is None
                                    else _NoDraws(lk.sampler))

        def walked(vis):
            return mi.Float(lookup(self.bind(again, retry, per_tap), again, opts, retry))

        return dr.if_stmt((vis,), retry, walked, lambda vis: vis,
                          label="virtual map: lookups whose page is missing")


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
                 slots=None, check_reads: bool = False, inside=True):
        self.vmap = vmap
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
        self._scope = dr.flag(dr.JitFlag.SymbolicScope)
        pools = vmap.store.pools
        self.depth = pools["depth"]
        self.extra = {k: v for k, v in pools.items() if k != "depth"}
        self.extra["pcss_near"] = vmap.face_near
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
                          _INVALID)
        else:
            s = dr.select(q == 0, self.slots[0], dr.select(q == 1, self.slots[1],
                          dr.select(q == 2, self.slots[2], self.slots[3])))
        fine = in_block & (s != _INVALID)
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
            s = dr.select(far, dr.select(ok2, s2, _INVALID), s)
            fine = dr.select(far, s != _INVALID, fine)
        fine_idx = s * (P * P) + mi.UInt32(lj & (P - 1)) * P + mi.UInt32(li & (P - 1))
        # elsewhere: the coarsest level (one page per face, always built, in slot
        # face + 1; an empty page where a one-sided light does not shine)
        shift = mi.Int32(lay.coarsest) - mi.Int32(self.level)
        cx, cy = gx >> shift, gy >> shift
        coarse_idx = (mi.UInt32(face) + 1) * (P * P) + mi.UInt32(cy) * P + mi.UInt32(cx)
        return dr.select(fine, fine_idx, coarse_idx)

    def fetch(self, layer, face, i, j, active=True):
        return dr.gather(mi.Float, layer, self._index(face, i, j), active)

    def texel_index(self, face, uv):
        ij = mi.Point2i(dr.floor(uv * self.resolution))
        return self._index(face, ij.x, ij.y)

    def clamp_texel(self, ij):
        v = self.view
        g = dr.clip(mi.Point2i(ij) + v.origin, 0, self.resolution - 1)
        return g - v.origin


# ------------------------------------------------------------------- mark pass
#: The mark pass of a camera with a lens (``thinlens``, ``aperture_radius`` > 0) traces
#: each pixel through ``LENS_GRID``^2 points of its lens (cell centres of a square grid,
#: mapped to the disk as the camera maps its aperture samples). From the lens centre
#: alone, a blurred post 0.8 in front of an aperture of radius 0.8 hid a strip of ground
#: that the rest of the lens sees: its lookups fell to coarse levels (``hard``
#: misclassified 1.49 %, full maps 0.04 %; 4 x 4 points: 0.18 %).
LENS_GRID = 3


def _has_aperture(sensor) -> bool:
    """Whether ``sensor`` has a lens of positive radius (read from the traversal that
    :func:`camera_state` keeps per sensor); a ``batch`` sensor: whether one of its
    cameras has (its ``sample_ray`` passes the lens sample on to them)."""
    if "Batch" in sensor.class_name():
        from .light_views import _child_sensors
        return any(_has_aperture(s) for s in _child_sensors(sensor))
    if "ThinLens" not in sensor.class_name():
        return False
    slot = _CAMERAS.get(id(sensor))
    params = slot[1].params if slot is not None and slot[0] is sensor else mi.traverse(sensor)
    if "aperture_radius" not in params.keys():
        return False
    return float(np.max(np.asarray(params["aperture_radius"]))) > 0.0


def camera_hits(scene, sensor, evaluate: bool = True):
    """Camera hits at every pixel centre with their one-pixel footprints (where the next
    pixel's rays meet the tangent plane: a perspective camera's from its pinhole, as the
    render takes them, :func:`~mi_shadowmap.light_views.pinhole_footprint`; other
    sensors' from their ray differentials): ``(si, dp_dx, dp_dy, valid)``; unevaluated
    with ``evaluate=False`` (the mark pass traces them in its own kernel)."""
    frame = camera_frame(sensor)
    if frame is not None:    # plain rays: the footprints come from the frame, not differentials
        ray, _ = sensor.sample_ray(0.0, 0.5, pixel_centres(sensor), mi.Point2f(0.5))
    else:
        centres = pixel_centres(sensor)
        k = LENS_GRID if _has_aperture(sensor) else 1
        if k == 1:
            ray = pixel_ray_differentials(sensor, centres)
        else:
            # a lens: every pixel through k x k points of it (the render's samples spread
            # over the whole lens, and a near occluder hides different points from each)
            n = dr.width(centres)
            idx = dr.arange(mi.UInt32, n * k * k)
            a = idx // n
            lens = mi.Point2f((mi.Float(a % k) + 0.5) / k, (mi.Float(a // k) + 0.5) / k)
            ray = pixel_ray_differentials(sensor, dr.gather(mi.Point2f, centres, idx % n),
                                          aperture=lens)
    # position and geometric normal are all marking needs (RayFlags.All also computes
    # UVs, shading frames and their derivatives: about half the pass)
    si = scene.ray_intersect(ray, ray_flags=mi.RayFlags.Minimal,
                             coherent=depth_maps.COHERENT_RAYS)
    valid = si.is_valid()
    si.n = dr.select(dr.dot(si.n, ray.d) > 0, -si.n, si.n)    # facing the camera
    if frame is not None:       # as the render takes them (integrator._footprint)
        dp_dx, dp_dy = pinhole_footprint(si.p, si.n, frame)
        if evaluate:
            dr.eval(si.p, si.n, dp_dx, dp_dy, valid)
        return si, dp_dx, dp_dy, valid
    n = si.n

    def hit(o, d):
        t = dr.dot(n, si.p - o) / dr.select(dr.abs(dr.dot(n, d)) > 1e-12, dr.dot(n, d), 1e-12)
        return o + d * t

    ok = ray.has_differentials
    dp_dx = mi.Vector3f(dr.select(ok, hit(ray.o_x, ray.d_x) - si.p, 0.0))
    dp_dy = mi.Vector3f(dr.select(ok, hit(ray.o_y, ray.d_y) - si.p, 0.0))
    if evaluate:
        dr.eval(si.p, si.n, dp_dx, dp_dy, valid)
    return si, dp_dx, dp_dy, valid


def _marked_points(vmap_like, si, dp_dx, dp_dy, valid, active=None) -> tuple:
    """``(face, uv64, act, level)`` of the camera hits ``si`` a mark reads: their face and
    float64 uv, which of them mark (valid, on a face, in front of a one-sided planar
    light, and ``active(p, n)`` if given) and their footprint's level."""
    view = vmap_like.view
    p64 = mi.Point3d(si.p)
    face, uv64, _, inside = view.project_f64(p64)
    act = valid & inside
    if view.light_normal is not None:   # behind a one-sided planar light: no light
        act &= dr.dot(si.p - opaque_point(view.position), mi.Vector3f(*view.light_normal)) > 0
    if active is not None:
        act &= active(si.p, si.n)
    return face, uv64, act, vmap_like.level_for(face, p64, dp_dx, dp_dy)


def mark_candidates(vmap_like, si, dp_dx, dp_dy, valid, margin: float = 2.0,
                    active=None) -> tuple:
    """``(keys, oks)``, lists of candidate tile keys per point and whether each is one
    (unevaluated): the tiles the lookups at ``si`` read (see the module doc): at each
    point's level, the tiles (:attr:`VirtualLayout.tile_size` texels wide; keys as
    :func:`page_key` in tile units) overlapping ``margin + 1`` texels around it (the
    method's kernel, plus one texel for camera samples off the pixel centre), capped at
    ``page_size / 2`` texels (what :meth:`VirtualShadowMap.bind`'s 2 x 2 pages serve):
    ``ceil(2 m / tile_size) + 1`` tiles per axis at most (2 x 2 for ``hard``'s kernel).
    A wider tap (PCSS's kernel up to ``max_kernel / 2``) reads its own page through the
    page table (:meth:`BoundVirtualMap._index`), which the neighbouring points marked
    where the surface goes on, else the coarsest level. (Marking the whole kernel
    instead, 64 texels wide, cast 1.5-1.9x the texels and doubled a camera move's PCSS
    frame for the same error on the soft-shadow scenes.)
    ``active(p, n)``: which points to mark (``n`` the normal facing the camera), or
    None: every point the view sees."""
    lay, P = vmap_like.layout, vmap_like.layout.page_size
    T = lay.tile_size
    m = min(float(margin) + 1.0, 0.5 * P)
    per_axis = min(int(math.ceil(2.0 * m / T)) + 1, P // T + 1)
    face, uv64, act, level = _marked_points(vmap_like, si, dp_dx, dp_dy, valid, active)
    res = mi.Float64(mi.UInt32(lay.res0) >> level)
    xy = uv64 * res
    n_tiles = dr.maximum(mi.Int32(lay.pages_per_side(0)) >> mi.Int32(level), 1) \
        * lay.tiles_per_side
    lo = mi.Point2i(dr.floor((xy - m) / T))
    hi = mi.Point2i(dr.floor((xy + m) / T))
    # per_axis^2 candidates per point, all in one kernel; only the valid ones leave
    # Dr.Jit (most points read one tile or two)
    keys, oks = [], []
    for k in range(per_axis * per_axis):
        tx, ty = lo.x + (k % per_axis), lo.y + (k // per_axis)
        oks.append(act & (tx <= hi.x) & (ty <= hi.y) & (tx >= 0) & (ty >= 0)
                   & (tx < n_tiles) & (ty < n_tiles))
        keys.append(page_key(face, level, dr.maximum(tx, 0), dr.maximum(ty, 0)))
    return keys, oks


def coarser_levels(layout, level, coarse_res: int):
    """Per point, how many levels coarser than its own ``level`` (``mi.UInt32``) its
    lookups may read for a method with ``virtual_coarse_res = coarse_res``: those of
    resolution ``coarse_res`` or more (down to the coarsest, at most
    :data:`MAX_COARSER`)."""
    log_res = mi.Int32(int(math.log2(layout.res0))) - mi.Int32(level)
    k = log_res - int(math.ceil(math.log2(max(int(coarse_res), 1))))
    k = dr.minimum(k, mi.Int32(layout.coarsest) - mi.Int32(level))
    return mi.UInt32(dr.clip(k, 0, MAX_COARSER))


def mark_coarser(vmap_like, si, dp_dx, dp_dy, valid, coarse_res: int,
                 active=None) -> tuple:
    """``(keys, oks)`` like :func:`mark_candidates` for the coarser levels a method
    with ``virtual_coarse_res`` may read (:func:`coarser_levels`): at each of them, the
    tile under the point only (one candidate per level: neighbouring points mark the
    same few tiles there); the mark pass then adds the tiles within the method's margin
    of those on the host (:func:`dilate_tiles`)."""
    lay = vmap_like.layout
    T = lay.tile_size
    face, uv64, act, level = _marked_points(vmap_like, si, dp_dx, dp_dy, valid, active)
    k_max = coarser_levels(lay, level, coarse_res)
    keys, oks = [], []
    for k in range(1, min(MAX_COARSER, lay.coarsest) + 1):
        lev = dr.minimum(level + k, lay.coarsest)
        res = mi.Float64(mi.UInt32(lay.res0) >> lev)
        t = mi.Point2i(dr.floor(uv64 * res / T))
        n_tiles = dr.maximum(mi.Int32(lay.pages_per_side(0)) >> mi.Int32(lev), 1) \
            * lay.tiles_per_side
        oks.append(act & (k <= k_max) & (t.x >= 0) & (t.y >= 0) & (t.x < n_tiles)
                   & (t.y < n_tiles))
        keys.append(page_key(face, lev, dr.maximum(t.x, 0), dr.maximum(t.y, 0)))
    return keys, oks


def dilate_tiles(keys: np.ndarray, layout, margin: float) -> np.ndarray:
    """Tile keys ``keys`` and those within ``margin + 1`` texels of them on their level,
    sorted, distinct."""
    keys = _sorted_unique(keys)
    if len(keys) == 0:
        return keys
    T = layout.tile_size
    r = int(math.ceil((float(margin) + 1.0) / T))
    face, level, tx, ty = (f.astype(np.int64) for f in key_fields(keys))
    n = np.maximum(layout.pages_per_side(0) >> level, 1) * layout.tiles_per_side
    out = []
    for dy in range(-r, r + 1):
        for dx in range(-r, r + 1):
            x, y = tx + dx, ty + dy
            ok = (x >= 0) & (y >= 0) & (x < n) & (y < n)
            out.append(page_key(face[ok].astype(np.uint64), level[ok].astype(np.uint64),
                                x[ok].astype(np.uint64), y[ok].astype(np.uint64)))
    return _sorted_unique(np.concatenate(out).astype(np.uint64))


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


def tile_pages(tiles: np.ndarray, layout) -> tuple:
    """``(pages, masks)``: the distinct page keys of tile keys ``tiles`` (sorted) and
    each page's tile mask (bit ``tx + ty * tiles_per_side`` for tile ``(tx, ty)`` of
    the page)."""
    S = np.uint64(layout.tiles_per_side)
    face, level, tx, ty = key_fields(np.asarray(tiles, np.uint64))
    pk = page_key(face, level, tx // S, ty // S)
    pages, inv = np.unique(pk, return_inverse=True)
    masks = np.zeros(len(pages), np.int64)
    np.bitwise_or.at(masks, inv.reshape(-1), np.int64(1) << (tx % S + (ty % S) * S)
                     .astype(np.int64))
    return pages, masks


def _dedupe_many(groups: list, bits: int = 14) -> list:
    """For each ``(keys, oks)`` of ``groups`` (one per light), most of the keys
    ``keys[i][oks[i]]`` without repeats (neighbouring pixels read the same pages: 4 x
    65 k candidates hold a few thousand keys), so that the host sorts a few thousand keys
    (:func:`_sorted_unique`) instead of all candidates: one kernel computes every light's keys (and the
    camera hits they come from) and scatters each list into its hash table of
    ``2^bits`` slots; a second finds the candidates whose key lost its slot to another
    key and scatters them into a second table (another hash); a third finds those that
    lost there too. Per group, both tables' keys plus the twice-lost candidates are
    returned (a superset of the distinct keys, with few repeats: with one table, about
    a seventh of 5 k keys lost their slot, and with them 40 k of the 260 k candidates,
    whose ``np.unique`` was a tenth of a camera move's frame). Which key wins a slot
    does not matter: the returned set is the same. The selection is done on the host
    with numpy, so every frame runs the same kernels (a compress and gather would trace
    new ones whenever a frame first has 0, 1 or more lost keys)."""
    # one table per candidate list: Dr.Jit puts scatters into different arrays in one
    # kernel (a second scatter into the same array would start a new kernel)
    flat = [(k, ok) for keys, oks in groups for k, ok in zip(keys, oks)]

    def slots_of(k, mult):
        return mi.UInt32((k * mi.UInt64(mult)) >> (64 - bits))

    tables = [dr.full(mi.UInt64, _NO_KEY, 1 << bits) for _ in flat]
    slot = [slots_of(k, 0x9E3779B97F4A7C15) for k, _ in flat]
    for t, (k, ok), s in zip(tables, flat, slot):
        dr.scatter(t, k, s, ok)
    dr.eval(*tables, *(k for k, _ in flat), *(ok for _, ok in flat))
    # the second round, in one kernel with the first round's losers
    tables2 = [dr.full(mi.UInt64, _NO_KEY, 1 << bits) for _ in flat]
    slot2 = [slots_of(k, 0xC2B2AE3D27D4EB4F) for k, _ in flat]
    lost = [ok & (dr.gather(mi.UInt64, t, s, ok) != k)
            for t, (k, ok), s in zip(tables, flat, slot)]
    for t2, (k, _), s2, lo in zip(tables2, flat, slot2, lost):
        dr.scatter(t2, k, s2, lo)
    dr.eval(*tables2, *lost)
    lost2 = [lo & (dr.gather(mi.UInt64, t2, s2, lo) != k)
             for t2, (k, _), s2, lo in zip(tables2, flat, slot2, lost)]
    dr.eval(*lost2)
    out, start = [], 0
    for keys, _ in groups:
        idx = range(start, start + len(keys))
        start += len(keys)
        parts = []
        for tabs in (tables, tables2):
            # a group's tables share their hash: a key sits in the same slot in each, so
            # a slot's entries repeat across tables unless different keys won it
            rows = [tabs[i].numpy() for i in idx]
            for j, row in enumerate(rows):
                keep = row != np.uint64(_NO_KEY)
                for earlier in rows[:j]:
                    keep &= row != earlier
                parts.append(row[keep])
        for i in idx:
            lo = lost2[i].numpy()
            if lo.any():
                parts.append(flat[i][0].numpy()[lo])
        out.append(np.concatenate(parts) if parts else np.zeros(0, np.uint64))
    return out


class CameraState:
    """What :func:`camera_state` returns: equal to another exactly when every camera
    parameter is the same JIT variable (or, for a scalar one, the same value). It holds
    references to those variables, so their indices cannot be recycled while it lives
    (a page store keeps its marks' state), and a parameter written in place gets a new
    variable (Dr.Jit copies on write while another reference exists). A camera set
    back to earlier values through new variables compares unequal: the mark pass runs
    again, which is never wrong."""

    __slots__ = ("token", "refs")

    def __init__(self, token: tuple, refs: list):
        self.token, self.refs = token, refs

    def __eq__(self, other):
        return isinstance(other, CameraState) and self.token == other.token

    def __hash__(self):
        return hash(self.token)


def camera_state(sensor) -> CameraState:
    """Everything about ``sensor`` that moves what the camera sees (its
    ``mi.traverse`` parameters: ``to_world``, field of view, ...; the film's crop), as a
    :class:`CameraState`: a render with the same camera state marks the same pages, so
    the mark pass is skipped (a still camera re-rendering, e.g. more spp or another
    seed). Costs a read of each parameter's variable indices (the traversal is kept per
    sensor)."""
    from .map_manager import ParamWatch
    slot = _CAMERAS.get(id(sensor))
    if slot is None or slot[0] is not sensor:
        params = mi.traverse(sensor)
        slot = _CAMERAS[id(sensor)] = [sensor, ParamWatch(params, sorted(params.keys())),
                                       None]
    _CAMERAS.move_to_end(id(sensor))
    while len(_CAMERAS) > 8:
        _CAMERAS.popitem(last=False)
    _, watch, last = slot
    token, values = watch.read()
    film = sensor.film()
    token += (tuple(film.crop_size()), tuple(film.crop_offset()))
    if last is None or last.token != token:
        last = slot[2] = CameraState(token, watch.held(values))
    return last


#: Per sensor (by ``id``, holding it): ``[sensor, ParamWatch of its parameters, last
#: CameraState]``.
_CAMERAS = collections.OrderedDict()


def camera_frame(sensor):
    """:func:`~mi_shadowmap.light_views.pinhole_frame` of ``sensor`` as opaque JIT values
    (a moved camera compiles nothing), or None; kept per camera state
    (:func:`camera_state`), so the render and its mark pass share one, and a still camera
    measures its pixel steps once (a small kernel and a read-back each time)."""
    if sensor is None:
        return None
    state = camera_state(sensor)
    slot = _FRAMES.get(id(sensor))
    if slot is None or slot[0] is not sensor or slot[1] != state:
        frame = pinhole_frame(sensor)
        if frame is not None:
            frame = tuple(dr.opaque(mi.Point3f if k == 0 else mi.Vector3f, v)
                          for k, v in enumerate(frame))
        slot = _FRAMES[id(sensor)] = (sensor, state, frame)
        while len(_FRAMES) > 8:
            _FRAMES.pop(next(iter(_FRAMES)))
    return slot[2]


#: Per sensor (by ``id``, holding it): ``(sensor, CameraState, camera_frame)``.
_FRAMES = {}


# ----------------------------------------------------------------------- cache
class PageCache:
    """Page stores kept across renders: per scene (latest state only) and emitter view."""

    def __init__(self, max_scenes: int = 4):
        self.max_scenes = max_scenes
        # id(scene) -> [scene, state, {key: store, ("layout", ...): layout}]
        self._scenes = collections.OrderedDict()
        self._fingerprints = collections.OrderedDict()   # id(view) -> (view, fingerprint)

    def store(self, scene, state, key, make):
        from .map_manager import scene_slot
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
            from .map_manager import view_fingerprint
            hit = self._fingerprints[id(view)] = (view, view_fingerprint(view))
            while len(self._fingerprints) > 64:
                self._fingerprints.popitem(last=False)
        return hit[1]

    def layout(self, scene, state, view, fingerprint, opts) -> "VirtualLayout":
        """:func:`layout_for`, kept with the scene's stores (``state`` None: computed)."""
        if state is None:
            return layout_for(view, scene, opts)
        from .map_manager import scene_slot
        slot = scene_slot(self._scenes, scene, state, self.max_scenes)
        key = ("layout", fingerprint, opts.page_size, opts.resolution)
        if key not in slot[2]:
            slot[2][key] = layout_for(view, scene, opts)
        return slot[2][key]

    def retire(self, scene, state, label: str, fingerprint) -> None:
        """Keep one fingerprint's store and layout for ``label``'s camera-following view
        (cascades): when it changes, the stores and layouts of the previous one are
        dropped, so a camera path does not pile up page pools."""
        if state is None:
            return
        from .map_manager import scene_slot
        entries = scene_slot(self._scenes, scene, state, self.max_scenes)[2]
        group = ("follows camera", label)
        old = entries.get(group)
        if old is not None and old != fingerprint:
            for k in [k for k in entries if k != group and (
                    k[0] == old or k[0] == "layout" and k[1] == old)]:
                del entries[k]
        entries[group] = fingerprint

    def clear(self):
        self._scenes.clear()
        self._fingerprints.clear()
        _CAMERAS.clear()


#: The page cache of every ``shadowmap`` integrator (``PAGE_CACHE.clear()`` empties it).
PAGE_CACHE = PageCache()


def page_layers(opts) -> tuple:
    """The layers a virtual map's pages hold besides depth for ``opts``' method
    (``pcss_near`` is derived from the page table, not stored per page)."""
    return tuple(n for n in opts.record.layer_names(opts) if n != "pcss_near")


def page_bytes(opts) -> int:
    """Bytes of one page in the pool: depth and :func:`page_layers`, float32 each."""
    return opts.page_size ** 2 * 4 * (1 + len(page_layers(opts)))


def prepare_virtual(scene, sensor, opts, views, stats, params=None) -> list:
    """First pass with ``virtual=true``: mark, build missing pages, return one
    :class:`VirtualShadowMap` per emitter whose view supports it (None elsewhere).

    ``params``: the scene's ``mi.traverse`` where the caller has it (else traversed
    here). Updates ``stats`` (a :class:`~mi_shadowmap.map_manager.MapStats`): pages marked,
    built, reused, the level histogram of the marked pages and ``texels_built``.
    """
    from .map_manager import MAP_CACHE
    layer_names = page_layers(opts)
    state = MAP_CACHE.scene_state(scene, params) if opts.cache_maps else None
    cam = camera_state(sensor) if sensor is not None else None
    margins, coarse, stores = {}, {}, {}
    for i, view in enumerate(views):
        if view is None or not getattr(view, "supports_virtual", False):
            continue
        fingerprint = PAGE_CACHE.fingerprint(view)
        if getattr(view, "follows_camera", False):
            PAGE_CACHE.retire(scene, state, view.label, fingerprint)
        layout = PAGE_CACHE.layout(scene, state, view, fingerprint, opts)
        key = (fingerprint, layout.res0, layout.page_size, layer_names)
        store = (PAGE_CACHE.store(scene, state, key, lambda: PageStore(layout, layer_names))
                 if state is not None else PageStore(layout, layer_names))
        store.frame += 1
        stores[i] = store
        margins[i] = virtual_margin_of(opts.record, opts, view)
        coarse[i] = virtual_coarse_res_of(opts.record, opts, view)
    mark_key = {i: (cam, margins[i], coarse[i], opts.lod_bias) for i in stores}
    # the mark pass: every light whose marks are stale, from one set of camera hits traced
    # in the same kernel as all their marks (a still camera reuses its marks)
    stale = [i for i, st in stores.items() if cam is not None
             and (st.last_mark is None or st.last_mark[0] != mark_key[i])]
    stale = [i for k, i in enumerate(stale)         # views sharing a store: marked once
             if all(stores[j] is not stores[i] for j in stale[:k])]
    if stale:
        # lights marked from their own view: all in one kernel; an environment's regions
        # (mark_views): one kernel per region, the same code for every region (their
        # values are opaque), from hits evaluated once (and whether each hit's BSDF
        # transmits: light reaches it from behind too)
        plain = [i for i in stale if not hasattr(stores[i].layout.view, "mark_views")]
        multi = [i for i in stale if i not in plain]
        hits = camera_hits(scene, sensor, evaluate=bool(multi))
        if multi:
            si_m, valid_m = hits[0], hits[3]
            through = valid_m & mi.has_flag(si_m.bsdf().flags(), mi.BSDFFlags.Transmission)
            dr.eval(through)
        def marks(i, marker, active=None):
            """The candidate lists of light ``i`` (its own levels', then the coarser
            levels' its kernels may filter, :func:`mark_coarser`)."""
            out = [mark_candidates(marker, *hits, margin=margins[i], active=active)]
            if coarse[i]:
                out.append(mark_coarser(marker, *hits, coarse_res=coarse[i], active=active))
            return out

        def tiles(i, found):
            """Light ``i``'s tile keys from its :func:`marks` lists' keys: ``(own levels',
            coarser levels')`` (the latter empty without ``virtual_coarse_res``)."""
            extra = (dilate_tiles(found[1], stores[i].layout, margins[i]) if coarse[i]
                     else np.zeros(0, np.uint64))
            return found[0], extra

        def settle(i, parts):
            """Light ``i``'s mark: every tile, and those only the coarser levels' kernels
            read (a full budget drops them first)."""
            own = _sorted_unique(np.concatenate([p[0] for p in parts]))
            extra = _sorted_unique(np.concatenate([p[1] for p in parts]))
            optional = np.setdiff1d(extra, own, assume_unique=True)
            stores[i].last_mark = (mark_key[i], _with_keys(own, optional), optional)

        groups = [marks(i, _Marker(stores[i].layout, opts.lod_bias)) for i in plain]
        found = _dedupe_many([g for gs in groups for g in gs])
        for i, gs in zip(plain, groups):
            mine, found = found[:len(gs)], found[len(gs):]
            settle(i, [tiles(i, mine)])
        for i in multi:
            parts = []
            for mark_view, mark_active in stores[i].layout.view.mark_views():
                gs = marks(i, _Marker(stores[i].layout, opts.lod_bias, mark_view),
                           active=lambda p, n, f=mark_active: f(p, n, through))
                parts.append(tiles(i, _dedupe_many(gs)))
            settle(i, parts)
    out = []
    for i, view in enumerate(views):
        if i not in stores:
            out.append(None)
            continue
        store = stores[i]
        layout = store.layout
        mark = store.last_mark if cam is not None else None
        # memory: the whole budget split evenly over the virtual maps
        per_page = page_bytes(opts)
        view = layout.view      # the emitter's view, or one face aimed at a far scene
        if store.lit_faces is None:
            store.lit_faces = _lit_faces(view)
            store.coarse_keys = np.sort(np.array([page_key(f, layout.coarsest, 0, 0)
                                                  for f in store.lit_faces],
                                                 np.uint64).reshape(-1))
        unlit = view.n_faces - len(store.lit_faces)
        budget_pages = max(int(opts.budget_bytes // len(stores) // per_page) - 1 - unlit,
                           view.n_faces)       # - 1: the empty page (slot 0); unlit faces'
        #                                        reserved coarsest slots stay empty pages
        store.max_pages = budget_pages + 1 + unlit
        settled = store.settled
        if (settled is not None and settled[0] is mark and settled[1] == budget_pages
                and settled[2] == store.version):
            # the same marks, budget and pages as the last render (a still camera): every
            # needed page is built; only their last use is recorded
            needed, slots, hist, degraded = settled[3:]
            n_cast = 0
            dt = 0.0
            store.slot_frame[slots] = store.frame
        else:
            marked = mark[1] if mark is not None else np.zeros(0, np.uint64)
            tiles = _with_keys(marked, store.coarse_keys)
            dropped = 0
            if mark is not None and len(mark[2]) and _n_pages(tiles, layout) > budget_pages:
                # over budget: first the tiles only coarser-level kernels read (their
                # lookups walk to a coarser level built), then the finest levels
                kept = _with_keys(np.setdiff1d(marked, mark[2], assume_unique=True),
                                  store.coarse_keys)
                dropped = _n_pages(tiles, layout) - _n_pages(kept, layout)
                tiles = kept
            tiles, degraded = _fit_budget(tiles, budget_pages, layout)
            degraded += dropped
            needed, masks = tile_pages(tiles, layout)
            have, _ = store.lookup(needed)
            over = store.n_pages + int((~have).sum()) - budget_pages
            if over > 0:
                store.evict(needed, over)
            t0 = time.perf_counter()
            stats.texels_built += store.build(scene, needed, masks)
            n_cast = store.pages_cast
            store._grow(store.next_slot)   # never an empty pool: slot 0, the empty page
            dr.sync_thread()
            dt = time.perf_counter() - t0
            store.cast_seconds += dt
            store.cast_pages += n_cast
            present, slots = store.lookup(needed)    # (all of them, once built)
            slots = slots[present]
            store.slot_frame[slots] = store.frame
            levels = ((needed >> np.uint64(54)) & np.uint64(31)).astype(int)
            hist = np.bincount(levels, minlength=layout.n_levels)
            store.settled = (mark, budget_pages, store.version, needed, slots, hist,
                             degraded)
        if degraded:
            warnings.warn(f"shadowmap: emitter '{view.label}': memory_budget = "
                          f"{opts.memory_budget:g} MiB holds {budget_pages} pages of "
                          f"{layout.page_size}^2; {degraded} marked pages were replaced by "
                          "coarser ones", RuntimeWarning, stacklevel=3)
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
        out.append(VirtualShadowMap(store, {"pages": int(len(needed)), "new": int(n_cast)},
                                    opts.lod_bias, margins[i], coarse.get(i)))
    return out


def page_minima(depth, tpp: int, on_host: bool | None = None) -> np.ndarray:
    """Nearest finite depth of each page of ``depth`` (evaluated, ``tpp`` texels a page;
    +inf for a page with none), as numpy. ``on_host`` (default: on the CPU backend, which
    reads the depths in place): numpy; else a block reduction on the device, so that a
    GPU copies one value a page instead of the pages."""
    if on_host is None:
        on_host = dr.backend_v(depth) == dr.JitBackend.LLVM
    if on_host:
        d = depth.numpy().reshape(-1, tpp)
        return np.where(np.isfinite(d), d, np.inf).min(axis=1)
    finite = dr.select(dr.isfinite(depth), depth, dr.inf)
    return dr.block_reduce(dr.ReduceOp.Min, finite, tpp).numpy()


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


def _sorted_unique(keys: np.ndarray) -> np.ndarray:
    """``np.unique(keys)`` by a sort (numpy 2.4's ``np.unique`` hashes, then sorts: 0.63
    ms against 0.15 ms for 5 k page keys, a mark pass's per light)."""
    s = np.sort(np.asarray(keys).reshape(-1))
    if len(s) < 2:
        return s
    return s[np.concatenate(([True], s[1:] != s[:-1]))]


def _with_keys(keys: np.ndarray, more: np.ndarray) -> np.ndarray:
    """Sorted distinct ``keys`` (sorted, distinct) with sorted distinct ``more`` (a
    few) merged in, without sorting ``keys`` again."""
    if len(keys) == 0:
        return more.copy()
    pos = np.searchsorted(keys, more)
    there = (pos < len(keys)) & (keys[np.minimum(pos, len(keys) - 1)] == more)
    return np.insert(keys, pos[~there], more[~there])


def _n_pages(tiles: np.ndarray, layout) -> int:
    """How many pages hold ``tiles`` (sorted tile keys)."""
    S = np.uint64(layout.tiles_per_side)
    face, level, tx, ty = key_fields(tiles)
    return len(_sorted_unique(page_key(face, level, tx // S, ty // S)))


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
        if len(_sorted_unique(pages)) <= budget_pages:
            break
        levels = level.astype(int)
        finest = levels.min()
        if finest >= layout.coarsest:
            break
        sel = levels == finest
        k = tiles[sel]
        parents = page_key(face[sel], finest + 1, tx[sel] >> np.uint64(1),
                           ty[sel] >> np.uint64(1)) if len(k) else k
        degraded += len(_sorted_unique(pages[sel]))
        tiles = _sorted_unique(np.concatenate([tiles[~sel], parents.astype(np.uint64)]))
    return tiles, degraded


class _Marker:
    """The level choice of a :class:`VirtualShadowMap` without a store (mark pass);
    ``view``: the faces marked (default: the layout's view)."""

    def __init__(self, layout, lod_bias: float, view=None):
        self.layout = layout
        self.view = layout.view if view is None else view
        self.lod_bias = float(lod_bias)

    level_for = VirtualShadowMap.level_for
