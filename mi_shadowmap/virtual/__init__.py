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
a texel is 0.35-0.7 footprint wide; finer where the light grazes the receiver, so that
the texel-scaled receiver biases lose an occluder's shadow over at most
``REACH_PIXELS`` footprints along it) and marks the tiles its lookup reads: those
within the method's ``virtual_margin`` (its kernel's half-width) plus one texel
(camera samples off the pixel centre) of it, or, on such a finer level, at least the
pixel's footprint box up to ``MAX_SPREAD`` texels from it (where the pixel's samples
read). Kernels up to ``page_size / 2``
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
(a camera sample off the pixel centre) it takes the next finer level, else the nearest
coarser one built there, up to the coarsest level (one page per face), which is always
built, so no point is lit for want of a page (a loop that only lanes with a missing page
enter). The nearest: the biases scale with the texel, and the coarsest level's hid whole
occluders (a wall the sun grazes, read 2^13 times coarser than its neighbours had built). The
lookup of a method with ``virtual_per_tap`` (``hard``) does not wait for that walk: it
reads at its wanted level, each read checking its own page and tile, and only the lanes
where one is missing run again, walked (:meth:`VirtualShadowMap.visibility`). The
2 x 2 pages around the receiver are found in the page table once per lookup (per
face and level, a grid over the bounding rectangle of its built pages whose entry
holds the 2 x 2 block's four slots: no loop). The filter's taps then read through
:meth:`BoundVirtualMap.fetch`: a tap inside those pages reads its page's slot (the
four gathered once per lookup, or, for a method with ``virtual_per_tap`` such as
``hard``, each tap's own slot gathered when it reads), a tap outside them (a wide
kernel; taps are clamped to their cube face) the coarsest level, whose page of face
``f`` is always in slot ``f + 1`` (no gather). Filters see a
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
(``mark_views``; all regions in one pass, a lane per region and point:
``mark_lanes``) and read through the region of the shading loop
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
scene's shapes change (the map cache's scene state of the shapes), and a light's
pages when its view changes (a moved light: the other lights keep theirs). Every
camera-dependent value is data (page tables, levels, slots), never a kernel
literal, so moving the camera compiles no new kernel.

**Memory** (``memory_budget``): one render's pools together hold at most the
budget's pages (all layers; less what its full maps hold), shared by need
(:func:`.planner.share_pages`); a pool is resized to its share, smaller too. Cached
pages the frame does not read are evicted first; if the frame's own pages do not
fit, the finest marked pages are replaced by their parents (coarser, never missing)
with one warning a render naming the degraded lights.

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

Modules (data flows down the list; each imports only those above it):

* :mod:`.layout`: where pages are (levels, pages, tiles of a light view's faces) and
  page keys;
* :mod:`.store`: the page pool and page table of one emitter, and the ray casts that
  fill pages;
* :mod:`.lookup`: what filters read (:class:`VirtualShadowMap`, bound per batch of
  lookups);
* :mod:`.camera`: whether the camera moved since the last marks;
* :mod:`.marks`: the mark pass;
* :mod:`.planner`: the first pass (:func:`prepare_virtual`: marks, budget, builds) and
  the page cache across renders (:data:`PAGE_CACHE`).
"""
from .layout import (MAX_COARSER, MAX_VIRTUAL_RES, SCENE_TEXELS, TILE_SIZE,  # noqa: F401
                     VirtualLayout, key_fields, layout_for, page_key)
from .store import PageStore, page_bytes, page_layers, page_minima, page_pools  # noqa: F401
from .lookup import BoundVirtualMap, VirtualShadowMap  # noqa: F401
from .camera import camera_frame, camera_state  # noqa: F401
from .marks import camera_hits, camera_pixels, coarser_levels, mark_candidates  # noqa: F401
from .planner import PAGE_CACHE, PageCache, prepare_virtual  # noqa: F401
