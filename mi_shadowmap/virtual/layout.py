"""Where a virtual map's pages are: a light view's layout (levels, pages, tiles), page
keys and sets of them. See :mod:`mi_shadowmap.virtual` for the design.
"""
from __future__ import annotations

import dataclasses
import functools
import math

import mitsuba as mi
import numpy as np

from ..light_views.base import scene_bounds
from ..light_views import box_view


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

INVALID_SLOT = 0xFFFFFFFF
#: Never a page key (its level, 31, is beyond any layout's): an empty slot of the mark
#: pass's hash table.
NO_KEY = 0xFFFFFFFFFFFFFFFF
#: Largest page grid of one (face, level) in the page table (entries of 4 slots).
MAX_TABLE = 1 << 22
#: Largest page grid side (the header packs width and height into 32 bits of one uint64).
MAX_TABLE_SIDE = (1 << 15) - 1
#: Coarser levels the mark pass builds at most, beyond a point's own, for a method whose
#: kernel may filter a coarser level (``virtual_coarse_res``: PCSS's kernels wider than
#: ``max_kernel`` texels): up to 2^8 times its footprint level's texel.
MAX_COARSER = 8


def padded_array(cls, values):
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
    """The fixed (camera-independent) shape of one emitter's virtual map.

    Its fields are not changed after it is made (:func:`dataclasses.replace` makes
    another): the numbers derived from them (:attr:`n_levels`, :attr:`tile_size`, ...)
    are computed once, at their first read. Tracing a moved frame's lookups and marks
    read them about 75 times a light (room_two_points: 149 reads), and each read
    computed them again (``n_levels`` a logarithm)."""
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

    @functools.cached_property
    def n_levels(self) -> int:
        return int(math.log2(self.res0 // self.page_size)) + 1

    @functools.cached_property
    def coarsest(self) -> int:
        return self.n_levels - 1

    def pages_per_side(self, level: int) -> int:
        return max((self.res0 >> level) // self.page_size, 1)

    @functools.cached_property
    def tile_size(self) -> int:
        """Side of a tile, the unit pages are ray-cast in: :data:`TILE_SIZE` texels, or
        ``page_size / 4`` for pages wider than 32 (at most 4 x 4 tiles a page, one bit
        each in the page's tile mask)."""
        return max(min(TILE_SIZE, self.page_size), self.page_size // 4)

    @functools.cached_property
    def tiles_per_side(self) -> int:
        """Tiles per page side."""
        return self.page_size // self.tile_size

    @functools.cached_property
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


def sorted_unique(keys: np.ndarray) -> np.ndarray:
    """``np.unique(keys)`` by a sort (numpy 2.4's ``np.unique`` hashes, then sorts: 0.63
    ms against 0.15 ms for 5 k page keys, a mark pass's per light).

    The distinct keys are taken by ``np.compress``, not a boolean index: numpy 2.4's
    boolean indexing branches per element, and on a mask with no pattern (a sixth of the
    expanded tiles distinct, the blocks of each shape among all) it took 0.10-0.14 ms
    for 17.8 k uint64 where ``np.compress`` took 0.025 ms (the mark pass's selections on
    the host use it for that: :func:`~.marks.expand_blocks`, :func:`~.marks.dedupe_many`,
    :func:`~.marks.dilate_tiles`)."""
    s = np.sort(np.asarray(keys).reshape(-1))
    if len(s) < 2:
        return s
    keep = np.empty(len(s), bool)
    keep[0] = True
    np.not_equal(s[1:], s[:-1], out=keep[1:])
    return np.compress(keep, s)


def with_keys(keys: np.ndarray, more: np.ndarray) -> np.ndarray:
    """Sorted distinct ``keys`` (sorted, distinct) with sorted distinct ``more`` (a
    few) merged in, without sorting ``keys`` again."""
    if len(keys) == 0:
        return more.copy()
    pos = np.searchsorted(keys, more)
    there = (pos < len(keys)) & (keys[np.minimum(pos, len(keys) - 1)] == more)
    return np.insert(keys, pos[~there], more[~there])
