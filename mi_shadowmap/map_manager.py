"""The map manager: which depth maps a render needs, built or taken from the cache.

Like Filament's ``ShadowMapManager`` beside its ``ShadowMap``: the
:mod:`~mi_shadowmap.depth_maps` module builds one map; this module decides,
for one render, which maps and layers to build -- the resolution (explicit
or automatic, checked against ``memory_budget`` before anything is
allocated), cascades, fitted frusta, culled cube faces -- and keeps built
layers across renders in :data:`MAP_CACHE` (shared by every integrator
instance) until the scene's geometry or emitters change.
"""
from __future__ import annotations

import collections
import dataclasses
import hashlib
import time

import numpy as np

import drjit as dr
import mitsuba as mi

from .depth_maps import ShadowMap, build_culled_depth, build_depth_map, build_layer
from .filters import layers_for
from .light_views import (camera_visible_points, cascaded_view, cube_faces_needed,
                          emitter_kind, fit_view, footprint_ratio, make_light_view)
from .options import _BYTES_PER_TEXEL


@dataclasses.dataclass
class PreparedMaps:
    """The result of :func:`prepare_maps` for one render."""
    views: list            # LightView or None, per emitter
    maps: list             # ShadowMap or None, per emitter
    resolution: int | None  # per-face resolution (None: no map was needed)
    stats: dict


def prepare_maps(scene: mi.Scene, sensor, opts, views=None) -> PreparedMaps:
    """First pass: one depth map per emitter (None for ``raytraced``).

    ``views``: the emitters' light views if the caller already built them
    (the integrator's ``check_scene`` does; None for environment emitters),
    else they are built here.

    The resolution is ``resolution`` or the automatic one (see
    :meth:`~mi_shadowmap.options.Options.map_resolution`, from the film of
    ``sensor``, default the scene's first sensor; a scene without any sensor
    takes a 512 x 512 film, and a camera-dependent step -- cascades, culling,
    fitting, the footprint factor -- is then skipped); the memory the maps
    need is checked against ``memory_budget`` before anything is built.
    Only the layers the method uses are built (``filters.layers_for(opts)``), and
    with ``cache_maps`` every layer is taken from :data:`MAP_CACHE` when
    it holds one for the same scene state, light view and resolution.

    With ``cascades`` > 1 directional views become cascaded ones
    (:func:`cascaded_view`): the face count (``cascades``) is known before
    the resolution, which is chosen first from the cascades fitted without
    margin, then the cascades are fitted again with their margin in texels
    of that resolution.

    With ``cull_faces`` cube maps build only the faces camera-visible points
    project into (:func:`cube_faces_needed`; a camera that sees no surface
    needs none, and the map is all +inf without any ray traced); with ``fit_frusta`` spot and
    directional views are fitted to the camera-visible receivers
    (:func:`fit_view`) after the resolution is chosen, so the fit raises
    the texel density.

    ``stats`` records ``maps_built``, ``maps_reused``, ``faces_built``,
    ``faces_culled``, ``texel_density_gain`` (per fitted view, texel area
    before / after), ``texels_built`` (depth and extra layers), ``layers_built``,
    ``build_seconds`` (spent here) and ``naive_build_seconds`` (what building
    every layer from scratch took when it was built), whose difference is
    the time the cache saved.
    """
    t0 = time.perf_counter()
    layers = layers_for(opts)
    if not opts.uses_map:
        views = [None] * len(scene.emitters())
    elif views is None:
        views = [None if emitter_kind(e) == "environment" else make_light_view(e, scene, i)
                 for i, e in enumerate(scene.emitters())]
    else:
        views = list(views)
    maps = [None] * len(views)
    stats = dict(maps_built=0, maps_reused=0, faces_built=0, faces_culled=0,
                 texels_built=0, layers_built=0, naive_build_seconds=0.0)
    res = None
    if any(v is not None for v in views):
        if sensor is None and len(scene.sensors()) > 0:
            sensor = scene.sensors()[0]
        cascaded = opts.cascades > 1 and sensor is not None and any(
            v is not None and v.projection == "orthographic" for v in views)
        visible = None
        if (cascaded
                or (opts.cull_faces and any(v is not None and v.projection == "cube"
                                            for v in views))
                or (opts.fit_frusta and any(v is not None and v.n_faces == 1
                                            for v in views))):
            visible = camera_visible_points(scene, sensor)
        film_size = sensor.film().crop_size() if sensor is not None else (512, 512)
        # The face count is known before the cascades are fitted: `cascades` faces per
        # directional view (cascaded_view keeps one face when the camera sees nothing).
        n_faces = [0 if v is None else (opts.cascades if cascaded and len(visible) > 0
                                        and v.projection == "orthographic" else v.n_faces)
                   for v in views]
        face_layers = sum(n_faces) * (1 + len(layers))
        if cascaded:   # parallel-split maps for directional lights (issue 4)
            def cascade_all(res_for_margin):
                return [v if v is None else
                        cascaded_view(v, scene, sensor, opts.cascades, opts.split_lambda,
                                      res=res_for_margin, points=visible)
                        for v in views]
            if opts.resolution is None:   # the footprint of cascades without margin
                footprint = footprint_ratio(scene, sensor, cascade_all(None))
            else:
                footprint = 1.0
        else:
            footprint = footprint_ratio(scene, sensor, views) if opts.resolution is None else 1.0
        # Raises (naming the memory needed) before any map is allocated.
        res = opts.map_resolution(film_size, face_layers, footprint)
        if cascaded:
            views = cascade_all(res)
        state = MAP_CACHE.scene_state(scene) if opts.cache_maps else None
        if opts.fit_frusta:
            margin = 8.0 + opts.normal_bias_texels
            stats["texel_density_gain"] = []
            for k, view in enumerate(views):
                if view is not None and view.n_faces == 1:
                    views[k], gain = fit_view(view, visible, margin / res)
                    stats["texel_density_gain"].append(gain)
        for k, view in enumerate(views):
            if view is not None:
                faces = None
                if opts.cull_faces and visible is not None and view.projection == "cube":
                    margin = 2.0 * (4.0 + opts.normal_bias_texels) / res
                    faces = cube_faces_needed(view, visible, margin)
                maps[k] = _map_for(scene, view, res, layers, state, stats, faces)
    dr.sync_thread()
    stats["build_seconds"] = time.perf_counter() - t0
    return PreparedMaps(views, maps, res, stats)

def _map_for(scene, view, res, layers, state, stats, faces=None) -> ShadowMap:
    """One emitter's map: cached layers where possible, the rest built.

    ``faces``: the cube faces needed (``cull_faces``), None for all. A culled
    depth is cached under ``("depth", faces)`` and its extra layers under
    ``(name, faces)`` -- the face set of the depth they were built from -- so a
    layer is never taken from a depth of another face set (review item 2).
    No face needed (the camera sees no surface): a map of +inf, nothing traced.
    """
    key = (view_fingerprint(view), res)
    cached = MAP_CACHE.get(scene, state, key, "depth") if state is not None else None
    if faces is not None:
        faces = tuple(bool(f) for f in faces)
        if all(faces) or cached is not None:   # a full depth serves any face set
            faces = None
        elif cached is None and state is not None:   # a culled map with enough faces
            for layer, entry in MAP_CACHE.entries(scene, state, key):
                if (isinstance(layer, tuple) and layer[0] == "depth"
                        and all(h or not f for h, f in zip(layer[1], faces))):
                    cached, faces = entry, layer[1]
                    break
    depth_key = "depth" if faces is None else ("depth", faces)

    def layer_key(name):
        return name if faces is None else (name, faces)

    if cached is None and faces is not None:
        t0 = time.perf_counter()
        smap = ShadowMap(view=view, resolution=res,
                         depth=build_culled_depth(scene, view, res, faces))
        dt = time.perf_counter() - t0
        n_built = sum(faces)
        stats["maps_built"] += 1
        stats["faces_built"] += n_built
        stats["faces_culled"] += view.n_faces - n_built
        stats["texels_built"] += n_built * res * res
        stats["naive_build_seconds"] += dt
        if state is not None:
            MAP_CACHE.put(scene, state, key, depth_key, smap.depth, dt)
    elif cached is None:
        t0 = time.perf_counter()
        smap = build_depth_map(scene, view, res, () if state is not None else layers)
        dr.sync_thread()
        dt = time.perf_counter() - t0
        stats["maps_built"] += 1
        stats["faces_built"] += view.n_faces
        stats["texels_built"] += smap.nbytes // _BYTES_PER_TEXEL   # depth (+ layers if uncached)
        stats["naive_build_seconds"] += dt
        if state is None:
            return smap
        MAP_CACHE.put(scene, state, key, depth_key, smap.depth, dt)
    else:
        smap = ShadowMap(view=view, resolution=res, depth=cached[0])
        stats["maps_reused"] += 1
        stats["naive_build_seconds"] += cached[1]
    for name in layers:
        entry = (MAP_CACHE.get(scene, state, key, layer_key(name))
                 if state is not None else None)
        if entry is None:
            t0 = time.perf_counter()
            data = build_layer(scene, smap, name)   # raises for an unknown layer
            dr.sync_thread()
            entry = (data, time.perf_counter() - t0)
            if state is not None:
                MAP_CACHE.put(scene, state, key, layer_key(name), *entry)
            stats["layers_built"] += 1
            stats["texels_built"] += dr.width(data)
        stats["naive_build_seconds"] += entry[1]
        if name == "second_depth":
            smap.second_depth = entry[0]
        else:
            smap.extra[name] = entry[0]
    return smap


# ------------------------------------------------------------------ map cache
def _param_bytes(value) -> bytes:
    """Bytes of one scene parameter's value (transforms as their matrix)."""
    if hasattr(value, "matrix"):
        value = value.matrix
    if isinstance(value, (bool, int, float, str)):
        return repr(value).encode()
    try:
        return np.asarray(value).tobytes()
    except Exception:   # an exotic parameter type: its text form
        return repr(value).encode()


def view_fingerprint(view) -> tuple:
    """A hashable summary of every field of a :class:`LightView` (transforms by value)."""
    def fp(v):
        if v is None or isinstance(v, (bool, int, float, str)):
            return v
        if isinstance(v, (tuple, list)):
            return tuple(fp(x) for x in v)
        if isinstance(v, dict):
            return tuple(sorted((k, fp(x)) for k, x in v.items()))
        if hasattr(v, "matrix") or type(v).__module__.startswith(("mitsuba", "drjit")):
            try:
                return _param_bytes(v)
            except Exception:
                pass
        return ("id", id(v))   # e.g. the area light's own shape
    return tuple((f.name, fp(getattr(view, f.name))) for f in dataclasses.fields(view))


class MapCache:
    """Depth-map layers kept across renders, shared by every integrator instance.

    **Key.** ``(scene, scene state, light view, resolution, layer)`` where

    * the *scene state* is a BLAKE2 hash of the values of every
      ``mi.traverse(scene)`` parameter owned by a shape or an emitter
      (vertex positions, faces, normals, ``to_world``, spot angles, ...) plus
      the numbers of shapes and emitters. Mitsuba offers no change counter:
      ``params.update()`` calls ``parameters_changed`` on the C++ objects,
      which a Python plugin cannot observe, and JIT variable indices are
      recycled, so the values themselves are hashed. Camera, film, BSDF and texture
      parameters are not part of it, so changing them keeps the maps.
      Large buffers are hashed once per JIT variable (see
      :meth:`scene_state`), so an unchanged 63k-triangle mesh costs
      well under a millisecond per render.
    * the *light view* is :func:`view_fingerprint` of the emitter's
      :class:`~mi_shadowmap.light_views.LightView` (projection, transform,
      extents, ...), so anything that moves a frustum (a light, a directional
      light's fit to the scene bounds) also misses the cache.

    Geometry changed by other means than ``params.update()`` (e.g. writing
    into a buffer in place) is not seen.

    **Memory.** The cache holds a reference to each scene it has maps of
    (so a freed scene's ``id`` can never alias a live one), at most
    ``max_scenes`` scenes (least recently used first out), only the latest
    state of each scene (a new state drops the old maps), and at most
    ``max_bytes`` of layers. :meth:`clear` empties it.
    """

    def __init__(self, max_bytes: int = 1 << 30, max_scenes: int = 8):
        self.max_bytes = max_bytes
        self.max_scenes = max_scenes
        self._scenes = collections.OrderedDict()   # id(scene) -> [scene, state, {key: entry}]
        self._memo = collections.OrderedDict()     # id(scene) -> (scene, {param: (array, digest)})
        self.hits = 0
        self.misses = 0

    def scene_state(self, scene) -> str:
        """Hash of the scene's shape and emitter parameters (see the class doc).

        Large JIT buffers (> ``_MEMO_MIN`` entries, e.g. vertex positions)
        are hashed once per JIT variable: the digest is memoised with a
        reference to the array itself, so its variable index cannot be
        recycled while the memo entry lives, and an equal index means the
        same, unmodified data (``params.update()`` installs new variables;
        Dr.Jit copies on write when an array is shared).
        """
        params = mi.traverse(scene)
        memo_slot = self._memo.get(id(scene))
        if memo_slot is None or memo_slot[0] is not scene:
            memo_slot = self._memo[id(scene)] = (scene, {})
        self._memo.move_to_end(id(scene))
        while len(self._memo) > self.max_scenes:
            self._memo.popitem(last=False)
        memo = memo_slot[1]
        h = hashlib.blake2b(digest_size=16)
        h.update(f"{len(scene.shapes())}/{len(scene.emitters())}".encode())
        for name in params.keys():
            node = params.properties[name][2]
            if not isinstance(node, (mi.Shape, mi.Emitter)):
                continue
            value = params[name]
            h.update(name.encode())
            index = getattr(value, "index", 0) if isinstance(value, dr.ArrayBase) else 0
            if index and dr.width(value) > _MEMO_MIN:
                m = memo.get(name)
                if m is None or m[0].index != index:
                    # type(value)(value): our own reference to the variable (``value``
                    # views the shape's member, whose index changes on update).
                    m = memo[name] = (type(value)(value),
                                      hashlib.blake2b(_param_bytes(value)).digest())
                h.update(m[1])
            else:
                h.update(_param_bytes(value))
        return h.hexdigest()

    def _slot(self, scene, state):
        slot = self._scenes.get(id(scene))
        if slot is None or slot[0] is not scene or slot[1] != state:
            slot = [scene, state, {}]
            self._scenes[id(scene)] = slot
        self._scenes.move_to_end(id(scene))
        while len(self._scenes) > self.max_scenes:
            self._scenes.popitem(last=False)
        return slot

    def entries(self, scene, state, key):
        """``(layer, entry)`` pairs cached for ``key`` (e.g. culled cube maps)."""
        slot = self._scenes.get(id(scene))
        if slot is None or slot[0] is not scene or slot[1] != state:
            return []
        return [(layer, e) for (k, layer), e in slot[2].items() if k == key]

    def get(self, scene, state, key, layer):
        """``(array, build_seconds)`` or None."""
        slot = self._scenes.get(id(scene))
        if slot is None or slot[0] is not scene or slot[1] != state:
            self.misses += 1
            return None
        entry = slot[2].get((key, layer))
        if entry is not None:
            self._scenes.move_to_end(id(scene))   # least recently used goes first
        self.hits += entry is not None
        self.misses += entry is None
        return entry

    def put(self, scene, state, key, layer, data, seconds: float) -> None:
        slot = self._slot(scene, state)
        slot[2][(key, layer)] = (data, seconds)
        # Bound the memory: drop least recently used scenes' layers first.
        while self.nbytes > self.max_bytes and len(self._scenes) > 1:
            self._scenes.popitem(last=False)
        if self.nbytes > self.max_bytes:
            slot[2].clear()

    @property
    def nbytes(self) -> int:
        return sum(_BYTES_PER_TEXEL * dr.width(e[0])
                   for s in self._scenes.values() for e in s[2].values())

    def clear(self) -> None:
        self._scenes.clear()
        self._memo.clear()


_MEMO_MIN = 1024   # JIT buffers wider than this are hashed once per variable


#: The cache of every ``shadowmap`` integrator (``MAP_CACHE.clear()`` empties it).
MAP_CACHE = MapCache()
