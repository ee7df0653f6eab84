"""The map manager: which depth maps a render needs, built or taken from the cache.

Like Filament's ``ShadowMapManager`` beside its ``ShadowMap``: the
:mod:`~mi_shadowmap.depth_maps` module builds one map; this module first
*plans* one render's maps (:func:`plan_maps`: the light views refined for the
camera, the resolution -- explicit or automatic, checked against
``memory_budget`` before anything is allocated -- the faces and layers each
map needs, and what :data:`MAP_CACHE` already holds), then *builds* what is
missing (:func:`build_maps`), keeping built layers across renders in
:data:`MAP_CACHE` (shared by every integrator instance) until the scene's
geometry or emitters change. It never asks what kind of view it holds: the
views refine themselves (:meth:`~mi_shadowmap.light_views.LightView.refine`,
``faces_needed``) and the method's record names the layers.
"""
from __future__ import annotations

import collections
import dataclasses
import hashlib
import math
import time
import warnings

import numpy as np

import drjit as dr
import mitsuba as mi

from .depth_maps import (ShadowMap, array_nbytes, build_culled_depth, build_depth_map,
                         build_layer)
from .light_views.base import scene_bounds
from .light_views.pose import light_pose
from .methods import (MethodError, OptionError, builds_first_depth, casts_first_depth,
                      page_layers, page_pools)
from .options import (camera_fit_pins, cube_pages_text, mib_up, unused_light_properties,
                      virtual_cube_bytes, virtual_lost_to_budget, virtual_map_bytes)
from .light_views import (aims_by_film, camera_visible_points, emitter_kind, emitter_labels,
                          footprint_ratio, make_light_view, _child_sensors)


@dataclasses.dataclass
class MapStats:
    """What preparing one render's maps did (``integrator.stats``).

    ``texel_density_gain`` lists, per fitted view (``fit_frusta``), the texel
    area before / after the fit (None without fitting); ``texels_built``
    counts every texel ray-cast or computed this render (depth and layers);
    ``naive_build_seconds`` is what building every layer from scratch took
    when it was built, so ``naive_build_seconds - build_seconds`` is the
    time the cache saved (virtual maps: the ray casting of every page the render
    reads, reused pages at their store's mean time a page; ``build_seconds`` also
    holds the mark pass and the page table, so on a first frame the difference is
    below 0: their cost). Reads like a dict too (``stats["maps_built"]``).
    """
    maps_built: int = 0
    maps_reused: int = 0
    faces_built: int = 0
    faces_culled: int = 0
    texels_built: int = 0
    layers_built: int = 0
    build_seconds: float = 0.0
    naive_build_seconds: float = 0.0
    texel_density_gain: list | None = None
    # virtual maps (mi_shadowmap.virtual): pages the camera reads, ray-cast, from the cache;
    # level_histogram[l]: marked pages of level l (0 finest)
    pages_marked: int = 0
    pages_built: int = 0
    pages_reused: int = 0
    level_histogram: list | None = None

    def __getitem__(self, key):
        d = self.as_dict()
        if key not in d:     # a KeyError, as a dict's (was AttributeError, or TypeError)
            raise KeyError(key)
        return d[key]

    def __contains__(self, key):
        return key in self.as_dict()

    def __iter__(self):      # dict(stats), list(stats): the keys, as a dict's
        return iter(self.as_dict())

    def __len__(self):
        return len(self.as_dict())

    def keys(self):
        return self.as_dict().keys()

    def values(self):
        return self.as_dict().values()

    def items(self):
        return self.as_dict().items()

    def get(self, key, default=None):
        return self.as_dict().get(key, default)

    def as_dict(self) -> dict:
        d = dataclasses.asdict(self)
        for key in ("texel_density_gain", "level_histogram"):
            if d[key] is None:
                del d[key]
        return d


@dataclasses.dataclass
class MapPlan:
    """The plan of one emitter's map: its view, the faces it needs (None: all), the
    layers (``{name: builder}``), the cache key and what the cache holds."""
    view: object
    faces: tuple | None
    layers: dict
    key: tuple
    cached_depth: tuple | None           # (array, seconds) or None
    depth_key: object                    # "depth", or ("depth", faces) when culled
    differentiable: bool = False         # build in the AD graph (maps_need_gradients)
    pose: object = None                  # the light's pose delta (light_views.pose)
    antialias: bool = False              # silhouette antialiasing (mi_shadowmap.antialias)
    first_depth: bool = True             # the first depths built (builds_first_depth)
    method: str = ""                     # the method's name (for messages)


@dataclasses.dataclass
class RenderPlan:
    """:func:`plan_maps`'s answer for one render."""
    views: list                          # LightView or None, per emitter
    maps: list                           # MapPlan or None, per emitter
    resolution: int | None               # per-face resolution (None: no map needed)
    state: str | None                    # the scene state the cache is keyed by
    texel_density_gain: list | None


@dataclasses.dataclass
class PreparedMaps:
    """The result of :func:`prepare_maps` for one render."""
    views: list            # LightView or None, per emitter
    maps: list             # ShadowMap or None, per emitter
    resolution: int | None  # per-face resolution (None: no map was needed)
    stats: MapStats


def scene_views(scene, opts) -> list:
    """Every emitter's :class:`~mi_shadowmap.light_views.LightView` for a render with
    ``opts`` (an environment's: :func:`mi_shadowmap.environment.light_view`, None
    unless shadowed by maps), named by :func:`~mi_shadowmap.light_views.emitter_labels`."""
    from .environment import light_view as environment_view
    emitters = scene.emitters()
    labels = emitter_labels(emitters)
    return [environment_view(e, scene, i, opts, labels[i]) if emitter_kind(e) == "environment"
            else make_light_view(e, scene, i, labels[i]) for i, e in enumerate(emitters)]


def plan_maps(scene: mi.Scene, sensor, opts, views=None, params=None,
              budget_bytes: int | None = None) -> RenderPlan:
    """Decide one render's maps; nothing is built (the camera-visible points may be
    traced, one ray per pixel, when a view's refinement needs them).

    ``views``: the emitters' light views if the caller already built them
    (the integrator's ``check_scene`` does; None for environment emitters),
    else they are built here. A method whose record has ``view_for`` replaces
    them with its own (``multiview``: K views of each light in one map), so
    everything below -- faces, memory, cache key -- sees the view it builds.
    ``sensor``: default the scene's first; a scene without any sensor takes a
    512 x 512 film and skips every camera-dependent step (cascades, culling,
    fitting, the footprint factor). ``budget_bytes``: what these maps may use
    (default ``memory_budget``; less where a render's virtual maps hold the rest).

    1. The views say whether they read camera-visible points
       (``cascades``/``fit_frusta``/``cull_faces``) and how many faces they
       will have.
    2. The resolution is ``resolution`` or the automatic one
       (:meth:`~mi_shadowmap.options.Options.map_resolution`, with the
       footprint of the views as refined without margin); the memory of all
       faces and layers is checked against ``memory_budget`` here, before
       anything is allocated.
    3. The views are refined for that resolution (cascades with their margin in
       texels, frusta fitted to the visible receivers) and say which faces
       the camera reads (``cull_faces``).
    4. The method's record names the layers; the cache is asked for each map --
       unless a shape or emitter parameter has gradients enabled
       (:func:`maps_need_gradients`): then the maps are built in the AD graph
       and the cache is neither read nor written (it only holds detached maps).
    """
    record = opts.record
    if not opts.uses_map:
        views = [None] * len(scene.emitters())
    elif views is None:
        views = scene_views(scene, opts)
    else:
        views = list(views)
    if record.view_for is not None and opts.uses_map:   # e.g. multiview: K views in one map
        made = [None if v is None else record.view_for(v, e, scene, opts)
                for v, e in zip(views, scene.emitters())]
        idle = [n for n in record.view_properties
                if n in opts.given and getattr(opts, n) != record.property(n).default]
        if idle and any(v is not None for v in views) and all(m is None for m in made):
            sizes = [f"'{n}'" for n in ("light_size", "angular_diameter")
                     if record.property(n) is not None]
            warnings.warn(
                f"shadowmap: {'property' if len(idle) == 1 else 'properties'} "
                f"{' and '.join(repr(n) for n in idle)} of method '{record.name}' "
                f"{'changes' if len(idle) == 1 else 'change'} nothing in this scene: none "
                "of its lights has a size, so each gets one view (hard shadows)"
                + (f"; give the lights a size ({' or '.join(sizes)}) or use an area light"
                   if sizes else ""), RuntimeWarning, stacklevel=2)
        views = [v if m is None else m for v, m in zip(views, made)]
    live = [v for v in views if v is not None]
    if not live:
        return RenderPlan(views, [None] * len(views), None, None, None)
    pins = camera_fit_pins(opts)
    if pins and not any(v.needs_camera_points(opts) for v in live):
        warnings.warn(
            f"shadowmap: property {' and '.join(pins)} applies to none of this scene's "
            "lights (cascades: directional lights; fit_frusta: spot and directional "
            "lights; cull_faces: cube maps of point, area and projector lights), so it "
            "changes nothing but turning the automatic virtual maps off: every light gets "
            "a full map (a far light's shadows can fall into a few of its texels and be "
            "lost); leave it out, or set virtual=false to keep full maps",
            RuntimeWarning, stacklevel=2)
    if sensor is None and len(scene.sensors()) > 0:
        sensor = scene.sensors()[0]
    visible = None
    if sensor is not None and any(v.needs_camera_points(opts) for v in live):
        if not aims_by_film(sensor):
            given = [f"'{name}' = {value}" for name, value, on in (
                ("fit_frusta", "true", opts.fit_frusta), ("cull_faces", "true", opts.cull_faces),
                ("cascades", opts.cascades, opts.cascades > 1)) if on]
            raise OptionError(
                f"shadowmap: property {' and '.join(given)} fits the maps to the points the "
                f"camera's pixels see, and sensor {_sensor_name(sensor)} has no such "
                "points (it spreads each pixel's rays over a surface or a hemisphere, or "
                "over a target); leave fit_frusta, cull_faces and cascades at their "
                "defaults (false, false, 1) for it")
        visible = camera_visible_points(scene, sensor)
    # a sensor that does not aim its pixels (irradiancemeter, distant: 1 x 1 films) or
    # whose pixel is one ray with no field of view (radiancemeter) sizes the automatic
    # resolution as no sensor does: 2 x 512. The whole film, not its crop window: the
    # footprint ratio is the camera's field of view over the film's width, and a crop
    # window's pixels are the whole film's
    film_size = (sensor.film().size() if sensor is not None and aims_by_film(sensor)
                 and _has_field_of_view(sensor) else (512, 512))
    layer_names = full_map_layers(opts)   # (also a virtual render's views without support)
    n_faces = sum(v.planned_faces(opts, visible) for v in live)
    footprint = 1.0
    if opts.resolution is None and (sensor is None or aims_by_film(sensor)):
        footprint = footprint_ratio(scene, sensor, [
            v if v is None else v.refine_for_footprint(opts, scene, sensor, visible)
            for v in views])
    params = params if params is not None else _traverse(scene, opts)
    diff = maps_need_gradients(scene, params)
    aa = getattr(opts, "antialias", "never")
    aa = aa == "always" or (aa == "gradients" and diff)
    grads = diff or differentiated(scene, params)
    first = holds_first_depth(record, layer_names, getattr(opts, "antialias", "never"),
                              grads)
    # Raises (naming the memory needed) before any map is allocated.
    cost = texel_cost(record, layer_names, first)
    res = opts.map_resolution(film_size, math.ceil(n_faces * cost), footprint, budget_bytes)
    if opts.resolution is None and grads:
        res = _gradient_resolution(scene, sensor, film_size, math.ceil(n_faces * cost),
                                   opts.budget_bytes if budget_bytes is None else budget_bytes,
                                   res)
    gains = [] if opts.fit_frusta else None
    for k, view in enumerate(views):
        if view is not None:
            views[k], gain = view.refine(opts, scene, sensor, visible, res)
            if gain is not None:
                gains.append(gain)
    # the cache holds detached, plain depths: neither read nor written for gradients
    # or antialiased maps
    # the shapes' state: maps are keyed by their light's view too, so a moved light (new
    # view) rebuilds its own map and keeps every other light's (MapCache.retire)
    state = (MAP_CACHE.scene_state(scene, params, shapes_only=True)
             if opts.cache_maps and not (diff or aa) else None)
    layers = {name: record.layers[name] for name in layer_names}
    poses = [None] * len(views)
    if grads:
        # a light whose pose has gradients: its reference view and pose delta, attached
        # in the gradient pass and detached in mi.render's primal pass (under
        # dr.suspend_grad), so that neither holds the moving light as kernel literals
        bounds = scene_bounds(scene)
        for k, (v, e) in enumerate(zip(views, scene.emitters())):
            if v is not None:
                views[k], poses[k] = light_pose(e, v, bounds, detached=not diff)
    # a posed map (a reference view moved by the pose) is never cached: its key would
    # be the reference view's
    maps = [None if v is None else _plan_one(scene, state if pose is None else None, v, res,
                                             layers, v.faces_needed(opts, visible, res),
                                             diff, pose, aa, first, record.name)
            for v, pose in zip(views, poses)]
    return RenderPlan(views, maps, res, state, gains)


#: (id(scene), id(sensor), film size, faces x layers, bytes allowed) -> ((scene, sensor),
#: resolution): the automatic resolution of renders with shape or emitter gradients, kept
#: (the scene and sensor held, so their ids are not reused) for the next such render;
#: the oldest dropped beyond _MAX_GRADIENT_RESOLUTIONS
_GRADIENT_RESOLUTIONS: collections.OrderedDict = collections.OrderedDict()
_MAX_GRADIENT_RESOLUTIONS = 16


def _gradient_resolution(scene, sensor, film_size, faces: int, budget: int, res: int) -> int:
    """The automatic resolution of a render whose shapes or emitters have gradients:
    the one the first such render of this scene, sensor, film size and map set chose.

    The automatic resolution follows the scene's bounds and the camera's footprint
    (:func:`footprint_ratio`), so an optimisation that moves an occluder or a light
    changed it between steps: measured, 56^2 -> 64^2 at an Adam step's second
    iteration (``vsm``, an occluder's translation), which compiled 12 kernels (about
    5 s against 0.15-0.2 s a step) and changed the function being optimised. Renders
    without gradients enabled keep following the scene, and the first of them forgets
    the scene's kept ones (:func:`_forget_gradient_resolutions`: kept while gradients
    stay enabled); a ``resolution`` given is used as is; :func:`clear_caches` forgets
    the kept ones."""
    key = (id(scene), id(sensor), tuple(int(x) for x in film_size), int(faces), int(budget))
    return _held_lru(_GRADIENT_RESOLUTIONS, key, (scene, sensor), lambda: res,
                     _MAX_GRADIENT_RESOLUTIONS)


def _keeps_gradient_resolution(scene) -> bool:
    """Whether :func:`_gradient_resolution` keeps a resolution for ``scene``."""
    return any(held[0] is scene for held, _ in _GRADIENT_RESOLUTIONS.values())


def _forget_gradient_resolutions(scene) -> None:
    """Drop the resolutions :func:`_gradient_resolution` keeps for ``scene``: called by a
    render of it without shape or emitter gradients, so the next optimisation takes the
    automatic resolution of the scene as it is then, as a fresh scene would. Kept past
    such renders, a second optimisation of one scene (after the camera moved closer:
    384^2 automatic maps) built the first one's maps (256^2): ``hard`` 0.61 % of the
    view misclassified against 0.35 % for the same state in a fresh session, ``vsm``'s
    gradient 7 % off that session's."""
    for key in [k for k, (held, _) in _GRADIENT_RESOLUTIONS.items() if held[0] is scene]:
        del _GRADIENT_RESOLUTIONS[key]


def _held_lru(table: collections.OrderedDict, key, held: tuple, make, limit: int):
    """``table[key]``'s value, made by ``make()`` where there is none or where the objects
    ``held`` with it are not these (a freed object's ``id`` in ``key`` reused): the entry
    holds them, so their ids stay theirs while it lives. The entry becomes the newest;
    the oldest beyond ``limit`` are dropped."""
    entry = table.get(key)
    if entry is None or any(a is not b for a, b in zip(entry[0], held)):
        entry = (held, make())
    table.pop(key, None)
    table[key] = entry
    while len(table) > limit:
        table.popitem(last=False)
    return entry[1]


def full_map_layers(opts) -> tuple:
    """The layers a full map of ``opts`` (validated) holds besides its first depth: those
    of ``opts`` with ``virtual`` false (a method's ``layers_for`` may leave some out for
    its virtual maps; a virtual render's views without virtual support get full maps)."""
    full_opts = opts.replace(virtual=False) if getattr(opts, "virtual", False) else opts
    return opts.record.layer_names(full_opts)


def holds_first_depth(record, layer_names, antialias: str, differentiated: bool) -> bool:
    """Whether a full map of ``record`` with the layers ``layer_names`` holds its first
    depth: where its lookup reads it (:func:`~.methods.builds_first_depth`: not
    ``second_depth``'s, whose lookups read the second depths alone), and always where it
    is antialiased (``antialias`` 'always'; 'gradients' antialiases differentiated
    renders only) or its scene is differentiated (``differentiated``: a shape or emitter
    parameter has gradients enabled, :func:`differentiated`; a gradient render's lookups
    follow its gradients, ``Integrator._gradient_render``, and both passes plan the same
    memory, so the same resolution). :func:`plan_maps` builds by it, and the harness orders the
    methods sharing maps by it (:func:`full_texel_cost`)."""
    return builds_first_depth(record, layer_names) or antialias == "always" or differentiated


def full_texel_cost(opts, differentiated: bool) -> float:
    """:func:`texel_cost` of a full map of ``opts`` (validated) in a render whose scene is
    ``differentiated`` or not (:func:`holds_first_depth`), as :func:`plan_maps` counts it."""
    names = full_map_layers(opts)
    first = holds_first_depth(opts.record, names, getattr(opts, "antialias", "never"),
                              differentiated)
    return texel_cost(opts.record, names, first)


def texel_cost(record, layer_names, first_depth: bool) -> float:
    """Float32 arrays a texel of a full map of ``record`` (a :class:`~.methods.Method`)
    holds: its first depth where built (``first_depth``: :func:`~.methods.builds_first_depth`,
    or the map antialiased or differentiated), and each of ``layer_names`` at its
    ``layer_cost`` (1 unless given). The memory check sizes maps by it (:func:`plan_maps`),
    and the harness lets the costliest method's maps pick the resolution they share."""
    return float(first_depth) + sum(record.layer_cost.get(name, 1.0) for name in layer_names)


def _plan_one(scene, state, view, res, layers, faces, differentiable=False, pose=None,
              antialias=False, first_depth=True, method="") -> MapPlan:
    """One emitter's plan. A culled depth (``faces``) is cached under
    ``("depth", faces)`` and its layers under ``("layer", name, builder, faces)`` --
    the face set of the depth they were built from -- so a layer is never taken from a
    depth of another face set, nor from another builder of the same name; a full cached
    depth, or a culled one with a superset of the faces, serves any face set.
    ``differentiable`` plans come with ``state`` None: no cache;
    ``pose``: the light's pose delta (gradients); ``antialias``: silhouette
    antialiasing (all faces are built, culling skipped; comes with ``state`` None);
    ``first_depth`` False: no first depth is built (:func:`~.methods.builds_first_depth`),
    nor read from the cache (the layers keep their keys, ``faces`` included)."""
    key = (view_fingerprint(view), res)
    if antialias:
        faces = None
    if state is not None:
        MAP_CACHE.retire(scene, state, (view.label, type(view).__name__, view.n_faces),
                         key[0])
    cached = (MAP_CACHE.get(scene, state, key, "depth") if state is not None and first_depth
              else None)
    if faces is not None:
        faces = tuple(bool(f) for f in faces)
        if all(faces) or cached is not None:
            faces = None
        elif state is not None and first_depth:
            for layer, entry in MAP_CACHE.entries(scene, state, key):
                if (isinstance(layer, tuple) and layer[0] == "depth"
                        and all(h or not f for h, f in zip(layer[1], faces))):
                    cached, faces = entry, layer[1]
                    break
    depth_key = "depth" if faces is None else ("depth", faces)
    return MapPlan(view, faces, layers, key, cached, depth_key, differentiable, pose, antialias,
                   first_depth, method)


def _layer_without_depth(scene, smap, name: str, builder, method: str) -> mi.Float:
    """:func:`~.depth_maps.build_layer` of a map without first depths (``method``
    registered with ``reads_depth`` False): a builder that reads ``smap.depth`` (an
    empty array) fails in Dr.Jit, gathering from it, or builds an empty layer (a
    reduction of it: ``pcss``'s ``pcss_near``), which the render then read as nothing,
    without an error where its lookup did not gather it. Both are a :class:`MethodError`
    naming the method, the layer and ``reads_depth``."""
    why = "the layer came out empty"
    try:
        data = build_layer(scene, smap, name, builder)
    except RuntimeError as e:
        if "empty array" not in str(e):
            raise
        data, why = None, f"Dr.Jit: {str(e).strip().splitlines()[0]}"
    if data is None or dr.width(data) == 0:
        # (from None: the CLI and the harness report the innermost error)
        raise _no_first_depth(method, name, f"smap.depth, an empty array; {why}") from None
    return data


def _no_first_depth(method: str, name: str, why: str) -> MethodError:
    """The error of a layer ``name`` built from the first depths of a map of ``method``
    (registered with ``reads_depth`` False: none), ``why`` saying how it showed."""
    return MethodError(
        f"shadowmap: method '{method}' was registered with reads_depth=False, so its "
        f"maps hold no first depth, and its layer '{name}' is built from one ({why}); "
        f"register it with reads_depth=True, or build '{name}' from the second depths "
        "(smap.second_depth)")


def build_maps(scene: mi.Scene, plan: RenderPlan) -> tuple[list, MapStats]:
    """Build what :func:`plan_maps` found missing; returns the maps and their stats."""
    stats = MapStats(texel_density_gain=plan.texel_density_gain)
    maps = [None if p is None else _build_one(scene, plan.state, plan.resolution, p, stats)
            for p in plan.maps]
    return maps, stats


def _build_one(scene, state, res, p: MapPlan, stats: MapStats) -> ShadowMap:
    view = p.view
    if p.pose is not None:
        # a posed map (the reference view moved by the pose) is keyed by the reference
        # view: neither its depth nor its layers may be cached (the scene state of the
        # shapes does not change with the pose)
        state = None
    layers_before = stats.layers_built
    if not p.first_depth:     # its layers alone (second_depth's; an empty first depth)
        smap = ShadowMap(view=view, resolution=res, depth=mi.Float(), pose=p.pose,
                         faces=p.faces)
    elif p.cached_depth is not None:     # (the layers follow its face set, p.faces)
        smap = ShadowMap(view=view, resolution=res, depth=p.cached_depth[0], faces=p.faces)
        stats.maps_reused += 1
        stats.naive_build_seconds += p.cached_depth[1]
    else:
        t0 = time.perf_counter()
        diff = {"differentiable": p.differentiable, "pose": p.pose}
        if p.faces is not None:   # no face needed: a map of +inf, nothing traced
            smap = ShadowMap(view=view, resolution=res,
                             depth=build_culled_depth(scene, view, res, p.faces, **diff),
                             pose=p.pose, faces=p.faces)
            n_built = sum(p.faces)
            n_texels = n_built * res * res
        else:   # what it traced: a one-sided light's multiview maps skip its back
            smap = build_depth_map(scene, view, res, antialias=p.antialias, **diff)
            n_built, n_texels = smap.faces_built, smap.texels_built
        dr.sync_thread()
        dt = time.perf_counter() - t0
        stats.maps_built += 1
        stats.faces_built += n_built
        stats.faces_culled += view.n_faces - n_built
        stats.texels_built += n_texels
        stats.naive_build_seconds += dt
        if state is not None:
            MAP_CACHE.put(scene, state, p.key, p.depth_key, smap.depth, dt)
    for name, builder in p.layers.items():
        # keyed by the builder too: two methods' layers of one name (a user's 'vsm_m1',
        # a method registered again with replace=True) are different data
        layer_key = ("layer", name, builder, p.faces)
        entry = MAP_CACHE.get(scene, state, p.key, layer_key) if state is not None else None
        if entry is None:
            t0 = time.perf_counter()
            data = (build_layer(scene, smap, name, builder) if p.first_depth
                    else _layer_without_depth(scene, smap, name, builder, p.method))
            dr.sync_thread()
            entry = (data, time.perf_counter() - t0)
            if state is not None:
                MAP_CACHE.put(scene, state, p.key, layer_key, *entry)
            stats.layers_built += 1
            stats.texels_built += dr.width(data)
        stats.naive_build_seconds += entry[1]
        smap.extra[name] = entry[0]
    if not p.first_depth:     # built where a layer was (on the faces p.faces), else reused
        built = stats.layers_built > layers_before
        n_built = view.n_faces if p.faces is None else sum(p.faces)
        stats.maps_built += built
        stats.maps_reused += not built
        stats.faces_built += n_built * built
        stats.faces_culled += (view.n_faces - n_built) * built
    return smap


def prepare_maps(scene: mi.Scene, sensor, opts, views=None,
                 pixels: bool = False, camera=None) -> PreparedMaps:
    """First pass: one depth map per emitter (None for methods without a map and for
    environment emitters): :func:`plan_maps`, then :func:`build_maps`. ``pixels``: the
    render's lookups know their film pixel (virtual maps,
    :func:`~mi_shadowmap.virtual.prepare_virtual`). ``camera``: ``sensor``'s
    :func:`~mi_shadowmap.virtual.camera_state` where the caller read it in this render
    (virtual maps; default: read there).

    ``stats`` (a :class:`MapStats`) records what was built and reused, and
    ``build_seconds``, the time spent here (planning included).
    """
    t0 = time.perf_counter()
    params = _traverse(scene, opts)    # once per render: read by every check below
    if opts.uses_map and _keeps_gradient_resolution(scene) and not differentiated(scene,
                                                                                   params):
        _forget_gradient_resolutions(scene)    # gradients disabled since: follow the scene
    kinds = {emitter_kind(e) for e in scene.emitters()}
    unused = unused_light_properties(opts, kinds)   # raytraced's sizes too
    if unused:
        warnings.warn(
            f"shadowmap: {'property' if len(unused) == 1 else 'properties'} "
            f"{' and '.join(unused)} {'changes' if len(unused) == 1 else 'change'} nothing "
            f"in this scene, whose lights are {', '.join(sorted(kinds))}", RuntimeWarning,
            stacklevel=3)
    if sensor is None and len(scene.sensors()) > 0:
        sensor, camera = scene.sensors()[0], None
    if opts.uses_map and opts.virtual and sensor is not None and not aims_by_film(sensor):
        if "virtual" in opts.given:
            raise OptionError(
                f"shadowmap: property 'virtual' = true marks the pages that the sensor's "
                f"pixels see, and sensor {_sensor_name(sensor)} spreads each pixel's rays "
                "over a surface or a hemisphere, or over a target (it sees no set of "
                "points a pixel at a time); set virtual=false (full maps) or leave "
                "'virtual' out")
        opts = opts.replace(virtual=False)     # automatic: full maps
    if opts.uses_map and opts.virtual and not (
            "virtual" not in opts.given and differentiated(scene, params)):
        # the automatic virtual=true: a scene being differentiated gets full maps (in the
        # AD graph), in its primal render too, so loss and gradient see the same maps
        return _prepare_virtual(scene, sensor, opts, views, t0, params, pixels, camera)
    plan = plan_maps(scene, sensor, opts, views, params)
    maps, stats = build_maps(scene, plan)
    if (opts.uses_map and virtual_lost_to_budget(opts)
            and (sensor is None or aims_by_film(sensor))
            and not differentiated(scene, params)):
        # the automatic virtual=true, but for a budget below one virtual cube map's
        # coarsest level (the options' check, whatever the lights): as _prepare_virtual's
        # budget check, one warning a render (it was silent below 0.047 MiB at the
        # default page_size, where the maps are coarsest: 44^2 a face at 0.046 MiB)
        wanted = [v if v is not None and getattr(v, "supports_virtual", False) else None
                  for v in plan.views]
        if any(v is not None for v in wanted):
            _warn_full_for_budget(opts, wanted, plan.resolution, cube=True)
    dr.sync_thread()
    stats.build_seconds = time.perf_counter() - t0
    return PreparedMaps(plan.views, maps, plan.resolution, stats)


def _has_field_of_view(sensor) -> bool:
    """Whether ``sensor``'s film spans a field of view that its pixels divide: a camera
    (``perspective``, ``thinlens``, ``orthographic``) or a ``batch`` holding one. Not a
    ``radiancemeter``: its 1 x 1 film is one ray, so sized by its film (2 x 1, rounded
    up to 8) the automatic full maps were 8^2 and lost a shadow the ray ends in
    (``multiview``, ``virtual=false``: lit where ``raytraced`` is shadowed)."""
    if isinstance(sensor, mi.ProjectiveCamera):
        return True
    if sensor.class_name() == "BatchSensor":
        return any(_has_field_of_view(s) for s in _child_sensors(sensor))
    return False


def _sensor_name(sensor) -> str:
    """``'id' (Class)`` of a sensor, for messages."""
    cls = sensor.class_name()     # not str(sensor): printing evaluates its JIT fields
    return f"'{sensor.id()}' ({cls})" if sensor.id() else f"({cls})"


#: Shape/emitter parameters that never move a depth map: a gradient on them alone does
#: not put the maps in the AD graph.
_NOT_DEPTH_PARAMS = ("silhouette_sampling_weight", "sampling_weight")


def _traverse(scene: mi.Scene, opts):
    """``mi.traverse(scene)`` if this render reads it (map caching or gradients), else
    None. One render reads it several times; it is about 0.15-0.3 ms each time."""
    if not opts.uses_map or not (opts.cache_maps or dr.is_diff_v(mi.Float)):
        return None
    return MAP_CACHE.traverse(scene)


def maps_need_gradients(scene: mi.Scene, params=None) -> bool:
    """Whether this render's maps must be built in the AD graph (issue 13).

    True when Dr.Jit tracks gradients here (an AD variant, outside
    ``dr.suspend_grad()``) and any ``mi.traverse(scene)`` parameter owned by
    a shape or an emitter (vertex positions, ``to_world``, a light's position
    or angles, ...) has gradients enabled (``dr.grad_enabled``); sampling
    weights do not count. Parameters of BSDFs, textures and emitters'
    radiance belong to other objects, so a reflectance gradient keeps the
    cached, detached maps. Cost: one ``mi.traverse`` and a flag read per
    parameter, about 0.15 ms on the default scene; the answer is False in
    non-AD variants without traversing. ``mi.render(scene, params)`` renders
    its primal image under ``dr.suspend_grad()`` (detached, cached maps as
    usual) and rebuilds the maps in the AD graph when it re-renders for
    ``dr.forward``/``dr.backward``.
    """
    if not dr.is_diff_v(mi.Float):
        return False
    params = params if params is not None else mi.traverse(scene)
    for name in params.keys():
        if name.rsplit(".", 1)[-1] in _NOT_DEPTH_PARAMS:
            continue
        if (isinstance(params.properties[name][2], (mi.Shape, mi.Emitter))
                and dr.grad_enabled(params[name])):
            return True
    return False


def differentiated(scene: mi.Scene, params=None) -> bool:
    """Whether a shape or emitter parameter has gradients enabled, whatever the current
    AD scope: ``mi.render(scene, params)`` renders its primal image under
    ``dr.suspend_grad()`` (where :func:`maps_need_gradients` is False) and its gradient
    with gradients tracked; the automatic ``virtual`` must pick the same maps for both."""
    with dr.resume_grad():
        return maps_need_gradients(scene, params)


def _prepare_virtual(scene, sensor, opts, views, t0, params=None,
                     pixels: bool = False, camera=None) -> PreparedMaps:
    """``virtual=true``: virtual maps (:mod:`mi_shadowmap.virtual`) for the emitters whose
    view supports them; the others (an environment cut into more than 32 regions) get
    full maps as usual."""
    from .virtual import prepare_virtual
    if "pcss_near" in opts.record.layer_names(opts) and not casts_first_depth(
            page_layers(opts)):
        # as a full map's layer builder fails on the empty first depth (_build_one)
        raise _no_first_depth(opts.record.name, "pcss_near", "virtual maps take it from "
                              "their pages' first depths, and these pages cast none")
    if "virtual" in opts.given and maps_need_gradients(scene, params):
        # virtual pages are built detached: shadows would pass no gradient, silently
        # (an automatic virtual=true never gets here with gradients: prepare_maps checked)
        raise ValueError("shadowmap: property 'virtual' = true builds no differentiable "
                         "maps, and a shape or emitter parameter of this render has "
                         "gradients enabled; set virtual=false (full maps are built in "
                         "the AD graph) or disable those gradients")
    if views is None:
        views = scene_views(scene, opts)
    if sensor is None and len(scene.sensors()) > 0:
        sensor, camera = scene.sensors()[0], None
    if opts.cascades > 1:
        views = _virtual_cascades(scene, sensor, opts, views)
    wanted = [v if v is not None and getattr(v, "supports_virtual", False) else None
              for v in views]
    virtual_views = _within_budget(opts, wanted)
    full_views = [v if w is None else None for v, w in zip(views, virtual_views)]
    stats = MapStats()
    maps = [None] * len(views)
    res = None
    # one memory_budget for both kinds: the full maps get what the virtual maps' coarsest
    # levels leave, the virtual maps what the full maps leave (each planned against the
    # whole budget, a mixed render held up to twice it)
    reserve = _virtual_minimum(opts, virtual_views)
    if any(v is not None for v in full_views):
        plan = plan_maps(scene, sensor, opts, full_views, params,
                         budget_bytes=opts.budget_bytes - reserve if reserve else None)
        maps, stats = build_maps(scene, plan)
        res = plan.resolution
        if any(v is not None for v in wanted) and all(v is None for v in virtual_views):
            _warn_full_for_budget(opts, wanted, res)
    full_bytes = sum(m.nbytes for m in maps if m is not None)
    virtual = prepare_virtual(scene, sensor, opts, virtual_views, stats, params,
                              budget_bytes=opts.budget_bytes - full_bytes, pixels=pixels,
                              camera=camera)
    maps = [vm if vm is not None else m for vm, m in zip(virtual, maps)]
    dr.sync_thread()
    stats.build_seconds = time.perf_counter() - t0
    return PreparedMaps(list(views), maps, res, stats)


def _virtual_minimum(opts, views: list) -> int:
    """Bytes the virtual maps of ``views`` (None: none) need at least: per map its
    empty page and one page per face (the coarsest level, always built)."""
    return sum(virtual_map_bytes(opts, v.n_faces) for v in views if v is not None)


def _within_budget(opts, views: list) -> list:
    """``views`` (those to get virtual maps), or all None when ``memory_budget`` cannot
    hold every one's coarsest level (one page per face, always built) and empty page
    (:func:`_virtual_minimum`): with ``virtual`` automatic they all get full maps, which
    the budget sizes together (a light given a full map beside the others' virtual
    maps was sized by the whole budget too: 1.9x it); ``virtual=true`` given raises,
    naming what it needs. (The options check a cube map's 6 faces; an environment's
    regions are up to 32 faces.)"""
    live = [v for v in views if v is not None]
    need = _virtual_minimum(opts, live)
    if not live or need <= opts.budget_bytes:
        return views
    if "virtual" in opts.given:
        layers = page_layers(opts)      # (their pools: page_pools)
        faces = ", ".join(f"'{v.label}' ({v.n_faces} faces)" for v in live[:4]) + (
            f", ... ({len(live)} maps)" if len(live) > 4 else "")
        raise OptionError(
            f"shadowmap: property 'memory_budget' = {opts.memory_budget:g} MiB cannot hold "
            f"the coarsest levels of the virtual maps ({faces}; one page "
            f"per face and an empty page per map, page_size^2 = {opts.page_size}^2 texels, "
            f"{len(page_pools(layers))} layer(s)): at least {mib_up(need)} MiB; raise it, "
            "lower page_size, or set virtual=false")
    return [None] * len(views)


def _warn_full_for_budget(opts, wanted: list, res: int, cube: bool = False) -> None:
    """The automatic ``virtual`` gave every light a full map because ``memory_budget``
    cannot hold the virtual maps' coarsest levels (:func:`_within_budget`), or
    (``cube``) a virtual cube map's coarsest level, which the options check whatever the
    lights (:func:`~mi_shadowmap.options.virtual_lost_to_budget`): one warning a render,
    naming the budget, what the virtual maps need and the full maps' resolution (it was
    silent: 24 lights under 0.44-0.09 MiB got full maps and 1.1-3.0 % of their
    pixel-light pairs false lit, against 0.32 % without a budget)."""
    live = [v for v in wanted if v is not None]
    if cube:
        need = virtual_cube_bytes(opts)
        what = (f"the coarsest level of a virtual cube map ({cube_pages_text(opts)}), "
                "which the automatic virtual maps need at least")
    else:
        need = _virtual_minimum(opts, live)
        what = (f"the coarsest levels of {len(live)} virtual map(s) (one page of "
                f"{opts.page_size}^2 texels per face and an empty page per map")
    warnings.warn(
        f"shadowmap: memory_budget = {opts.memory_budget:g} MiB cannot hold {what}: "
        f"{mib_up(need)} MiB), "
        f"so every light gets a full map of {res}^2 texels a face, which may lose shadows "
        "virtual maps keep; raise memory_budget (or lower page_size) to keep virtual "
        "maps, or set virtual=false for full maps", RuntimeWarning, stacklevel=3)


#: ``(id(view), camera state) -> CascadedView`` of the latest renders with ``virtual=true``
#: and ``cascades`` > 1 (a still camera keeps its cascades, and their pages).
_VIRTUAL_CASCADES = collections.OrderedDict()


def _virtual_cascades(scene, sensor, opts, views) -> list:
    """``cascades`` > 1 with ``virtual=true``: every directional light's one-face view
    becomes its :class:`~mi_shadowmap.light_views.CascadedView`, fitted to the
    camera-visible points as for full maps; each cascade is then a virtual face. The
    rectangles grow by 4 texels of a 256^2 map (3 % of a cascade), and one more face,
    the whole scene-fitted rectangle, serves the points outside their cascade's
    rectangle (:func:`~mi_shadowmap.light_views.cascaded.with_catch_all`: camera samples
    off the pixel centres, towards the horizon, at 2-4 % of the samples of a ground seen
    at eye height). Kept per camera state, so a still camera reuses its
    cascades and their pages; a moved one fits new cascades, whose pages are built anew
    (cascades follow the camera; the default, footprint-chosen levels without cascades,
    do not)."""
    from .light_views import CascadedView, cascaded_view
    from .light_views.cascaded import with_catch_all
    from .virtual import camera_state
    if sensor is None:
        return views
    cam = camera_state(sensor)
    out, points = [], None
    for v in views:
        if (v is not None and v.kind == "directional" and v.n_faces == 1
                and getattr(v, "supports_virtual", False)
                and not isinstance(v, CascadedView)):
            key = (id(v), cam)
            hit = _VIRTUAL_CASCADES.get(key)
            if hit is None or hit[0] is not v:
                if points is None:
                    points = camera_visible_points(scene, sensor)
                hit = _VIRTUAL_CASCADES[key] = (v, with_catch_all(cascaded_view(
                    v, scene, sensor, opts.cascades, opts.split_lambda, res=256,
                    points=points)))
                while len(_VIRTUAL_CASCADES) > 16:
                    _VIRTUAL_CASCADES.popitem(last=False)
            v = hit[1]
        out.append(v)
    return out


# ------------------------------------------------------------------ map cache
def is_transform(value) -> bool:
    """Whether ``value`` is a Mitsuba transform (read by value: its ``matrix``). Not
    ``hasattr(value, "matrix")`` alone: Dr.Jit answers ``.matrix`` on a 3-vector (a
    ``Point3f``, ``Vector3f``, ``Color3f``; scalar ones too) with its x component six
    times, so a point light's ``position`` was hashed by its x alone."""
    return not isinstance(value, dr.ArrayBase) and hasattr(value, "matrix")


def _param_bytes(value) -> bytes:
    """Bytes of one scene parameter's value (transforms as their matrix)."""
    if is_transform(value):
        value = value.matrix
    if isinstance(value, (bool, int, float, str)):
        return repr(value).encode()
    try:
        return np.asarray(value).tobytes()
    except Exception:   # an exotic parameter type: its text form
        return repr(value).encode()


def hold(value):
    """A new reference to the JIT variables of ``value`` (detached: holding it keeps no
    AD graph alive). While it lives their indices cannot be recycled, and Dr.Jit copies
    a variable written in place while a second reference exists, so the writer's value
    gets a new index."""
    return type(value)(dr.detach(value))


def param_digest(memo: dict, name: str, value) -> bytes:
    """Digest of parameter ``name``'s ``value``, through ``memo`` for JIT arrays.

    A value made of JIT variables (a ``mi.Float`` buffer, a transform, a point) is
    hashed once per set of variable indices: ``memo[name]`` keeps a reference to those
    variables (:func:`hold`), so their indices cannot be recycled while the entry lives,
    and equal indices mean the same, unmodified data: ``params.update()`` installs new
    variables, and a variable written in place gets a new index. Other values (Python
    and scalar types) are their bytes.
    """
    ids = (tuple(dr.detail.collect_indices(value))
           if isinstance(value, dr.ArrayBase) or is_transform(value) else ())
    if not ids or not all(ids):
        return _param_bytes(value)
    m = memo.get(name)
    if m is None or m[1] != ids:
        m = memo[name] = (hold(value), ids,
                          hashlib.blake2b(_param_bytes(value), digest_size=16).digest())
    return m[2]


class ParamWatch:
    """Reads parameters ``names`` of a ``mi.traverse`` result ``params`` with as little
    Python as a render's first pass can afford (it runs with cold caches after the
    previous frame's kernel: each Python operation costs several times its isolated
    time). :meth:`read` returns ``(token, values)``: ``token`` is the JIT variable
    indices of the JIT-array values (one ``collect_indices`` call over all of them)
    and the bytes of the others; equal tokens mean the same variables (while
    references to them are held, so indices cannot be recycled) and the same scalars.
    """

    def __init__(self, params, names):
        self.params = params
        self.names = list(names)
        props = [params.properties[n] for n in self.names]
        self._getters = [(v, t, node) for v, t, node, _ in props]
        first = self._values()
        self.jit = [isinstance(v, dr.ArrayBase) and dr.is_jit_v(v)
                     or is_transform(v) and dr.is_jit_v(v.matrix) for v in first]

    def _values(self) -> list:
        get = mi.get_property
        return [v if t is None else get(v, t, node) for v, t, node in self._getters]

    def held(self, values) -> list:
        """New references to the JIT values of ``values`` (a :meth:`read`'s): holding
        them keeps their indices from being recycled or written in place
        (:func:`hold`), so a later equal token means unchanged values."""
        return [hold(v) for v, j in zip(values, self.jit) if j]

    def read(self) -> tuple:
        values = self._values()
        jit = [v for v, j in zip(values, self.jit) if j]
        scalars = tuple(v if type(v) in (bool, int, float, str) else _param_bytes(v)
                        for v, j in zip(values, self.jit) if not j)
        return (tuple(dr.detail.collect_indices(jit)), scalars), values


#: Classes of the BSDFs whose flags ``params.update()`` changes (Mitsuba 3.9's
#: ``parameters_changed``; every other BSDF plugin's flags were checked fixed, each float
#: parameter set to 0, 0.5 and 1): ``principled`` gains ``GlossyTransmission`` where
#: ``spec_trans`` becomes > 0 (``Anisotropic`` with ``anisotropic``), ``principledthin``
#: likewise. The mark pass reads a BSDF's flags (a transmitting one takes light from
#: behind: :func:`~mi_shadowmap.virtual.marks._light_behind`).
FLAG_CHANGING_BSDFS = ("Principled", "PrincipledThin")


def flag_changing_bsdfs(objects) -> list:
    """The BSDFs among ``objects`` (any objects, None too; each BSDF once) whose flags
    ``params.update()`` may change (:data:`FLAG_CHANGING_BSDFS`): the scene state, the
    marks' tilt table and the solid faces' candidates read their flags
    (:func:`bsdf_flags`) to see such an edit."""
    seen = {}
    for b in objects:
        if isinstance(b, mi.BSDF) and b.class_name() in FLAG_CHANGING_BSDFS:
            seen[id(b)] = b
    return list(seen.values())


def bsdf_flags(bsdfs) -> tuple:
    """The flags of ``bsdfs`` now (:func:`flag_changing_bsdfs`), as a comparable tuple."""
    return tuple(int(b.flags()) for b in bsdfs)


def _flag_changing_bsdfs(params) -> list:
    """The BSDFs of a ``mi.traverse`` result ``params`` whose flags may change
    (:func:`flag_changing_bsdfs`): their flags are part of the scene state, so that a
    page store's marks (kept for a still camera) are made again when they change."""
    return flag_changing_bsdfs(value[2] for value in params.properties.values()
                               if len(value) > 2)


def _environment_scale(params, name: str) -> bool:
    """Whether parameter ``name`` is an environment emitter's ``scale``."""
    owner = params.properties[name][2]
    if name.rsplit(".", 1)[-1] != "scale" or not isinstance(owner, mi.Emitter):
        return False
    from .light_views import emitter_kind
    return emitter_kind(owner) == "environment"


def view_fingerprint(view) -> tuple:
    """A hashable summary of every field of a :class:`LightView` (transforms by value)."""
    def fp(v):
        if v is None or isinstance(v, (bool, int, float, str)):
            return v
        if dataclasses.is_dataclass(v) and not isinstance(v, type):
            return view_fingerprint(v)   # a view inside a view (multiview's template)
        if isinstance(v, (tuple, list)):
            return tuple(fp(x) for x in v)
        if isinstance(v, dict):
            return tuple(sorted((k, fp(x)) for k, x in v.items()))
        if is_transform(v) or type(v).__module__.startswith(("mitsuba", "drjit")):
            try:
                return _param_bytes(v)
            except Exception:
                pass
        return ("id", id(v))   # e.g. the area light's own shape
    return (type(view).__name__,) + tuple((f.name, fp(getattr(view, f.name)))
                                          for f in dataclasses.fields(view))


def scene_slot(scenes: collections.OrderedDict, scene, state, max_scenes: int) -> list:
    """The ``[scene, state, {key: entry}]`` slot of ``scene`` in ``scenes`` (by
    ``id``), emptied when the scene's state changed; at most ``max_scenes`` kept, least
    recently used out first. Shared by :class:`MapCache` and the virtual maps' page
    cache (:class:`mi_shadowmap.virtual.PageCache`)."""
    slot = scenes.get(id(scene))
    if slot is None or slot[0] is not scene or slot[1] != state:
        slot = [scene, state, {}]
        scenes[id(scene)] = slot
    scenes.move_to_end(id(scene))
    while len(scenes) > max_scenes:
        scenes.popitem(last=False)
    return slot


#: id(scene) -> ((scene,), token): :func:`scene_token` (at most 8 scenes; ``clear_caches``).
_SCENE_TOKENS = collections.OrderedDict()


def scene_token(scene) -> object:
    """A token standing for ``scene`` in an integrator's per-scene memos, the same object
    while the scene is held here (at most 8 scenes, least recently used out first;
    :func:`clear_caches` empties it). An integrator keeps the token, not the scene: a
    scene holds its own integrator (``<integrator type="shadowmap">``), and a Python
    reference back to the scene from it is a cycle through C++ that Python's collector
    cannot see, so every scene rendered with its own integrator stayed alive forever,
    ``clear_caches()`` and ``del`` notwithstanding (30 scenes of 45k triangles: +5 MiB
    each, and renders 0.23 -> 0.45 s as Dr.Jit traced every live scene's shapes)."""
    return _held_lru(_SCENE_TOKENS, id(scene), (scene,), _token_and_lease, 8)[0]


def scene_lease(scene) -> object:
    """An object that lives exactly as long as ``scene``'s entry here (while it lives,
    its scene does): evicted or ``clear_caches()``, only weak references to it remain.
    An integrator's memo of a scene's objects (which must not outlive the scene, as a
    token held by its other memos may) is kept in a ``weakref.WeakKeyDictionary`` keyed
    by it."""
    return _held_lru(_SCENE_TOKENS, id(scene), (scene,), _token_and_lease, 8)[1]


class _Lease:
    __slots__ = ("__weakref__",)


def _token_and_lease():
    return object(), _Lease()


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
      parameters are not part of it, so changing them keeps the maps; the flags of the
      BSDFs that ``params.update()`` may give new flags are (:data:`FLAG_CHANGING_BSDFS`:
      ``principled`` given ``spec_trans`` > 0 transmits, and the mark pass treats a
      transmitting surface's light from behind as seen; each such BSDF's flags are read
      at every :meth:`scene_state`, two a render: the light views' and the maps' or
      pages').
      JIT arrays are hashed once per JIT variable (:func:`param_digest`), so an
      unchanged scene costs a read of its parameters' variable indices per render
      (and ``mi.traverse(scene)`` is kept per scene: :meth:`traverse`).
    * the maps' plans use the state of the shapes' parameters alone
      (``scene_state(shapes_only=True)``): a map is keyed by its light's view too, so
      a moved light rebuilds its own map and the other lights keep theirs
      (:meth:`retire` keeps its two latest views' maps).
    * the *light view* is :func:`view_fingerprint` of the emitter's
      :class:`~mi_shadowmap.light_views.LightView` (its class, transform,
      extents, ...), so anything that moves a frustum (a light, a directional
      light's fit to the scene bounds) also misses the cache.

    A buffer written in place (``dr.scatter`` into a value read from a traversal) is
    seen too: Dr.Jit gives the written variable a new index while the memo holds a
    reference to the old one (``tests/test_cache.py``). Mitsuba itself only rebuilds
    its acceleration structure on ``params.update()``.

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
        # id(scene) -> [scene, {param: (held value, JIT ids, digest)}, its mi.traverse,
        #               [ParamWatch of its shape and emitter parameters, last state,
        #                an environment's scales' watch, their signs, the BSDFs whose
        #                flags count (_flag_changing_bsdfs)]]
        self._memo = collections.OrderedDict()
        self._views = {}        # id(scene) -> {"state": state, (label, ...): [fingerprints]}
        self.hits = 0
        self.misses = 0

    def _memo_slot(self, scene) -> list:
        slot = self._memo.get(id(scene))
        if slot is None or slot[0] is not scene:
            slot = self._memo[id(scene)] = [scene, {}, None, None]
        self._memo.move_to_end(id(scene))
        while len(self._memo) > self.max_scenes:
            self._memo.popitem(last=False)
        return slot

    def traverse(self, scene) -> mi.SceneParameters:
        """``mi.traverse(scene)``, kept per scene (about 0.1-0.3 ms a render otherwise).
        A kept traversal is never stale: ``SceneParameters`` holds a pointer and a type
        per parameter and reads the object's current value on every access, so it sees
        every ``params.update()`` made through any other traversal; a loaded scene's
        graph (its objects and their parameters) does not change."""
        slot = self._memo_slot(scene)
        if slot[2] is None:
            slot[2] = mi.traverse(scene)
        return slot[2]

    def scene_state(self, scene, params=None, shapes_only: bool = False) -> str:
        """Hash of the scene's shape and emitter parameters (see the class doc).

        Each JIT-array value is hashed once per set of JIT variables
        (:func:`param_digest`): an unchanged scene costs a read of each parameter's
        variable indices per render. ``shapes_only``: the hash of the shapes'
        parameters alone (the virtual maps' page cache, whose stores are also keyed
        by their light's view: a moved light must not drop every other light's pages).
        """
        params = params if params is not None else self.traverse(scene)
        slot = self._memo_slot(scene)
        if slot[3] is None or slot[3][0].params is not params:
            names = [name for name in params.keys()
                     if isinstance(params.properties[name][2], (mi.Shape, mi.Emitter))]
            # an environment map's scale moves no map (its regions' cut is of relative
            # luminance): only whether it is > 0 counts (environment.emitter_regions)
            scales = [name for name in names if _environment_scale(params, name)]
            slot[3] = [ParamWatch(params, [n for n in names if n not in scales]), None,
                       ParamWatch(params, scales) if scales else None, None,
                       _flag_changing_bsdfs(params)]
        watch, last, scale_watch, signs, flagged = slot[3]
        if scale_watch is not None:
            s_token, s_values = scale_watch.read()
            if signs is None or signs[0] != s_token:
                from .environment import positive_scale
                signs = slot[3][3] = (s_token, "".join(
                    "+" if positive_scale(v) else "0" for v in s_values),
                    scale_watch.held(s_values))
        suffix = "" if scale_watch is None else "/" + signs[1]
        token, values = watch.read()
        if flagged:       # (none in most scenes: nothing read)
            token = (token, bsdf_flags(flagged))
        if last is not None and last[0] == token:    # the same variables and values
            return last[2] if shapes_only else last[1] + suffix
        memo = slot[1]
        h = hashlib.blake2b(digest_size=16)
        hs = hashlib.blake2b(digest_size=16)
        counts = f"{len(scene.shapes())}/{len(scene.emitters())}".encode()
        h.update(counts)
        hs.update(counts)
        if flagged:
            for hh in (h, hs):
                hh.update(repr(token[1]).encode())
        for name, value in zip(watch.names, values):
            digest = param_digest(memo, name, value)
            for hh in ((h, hs) if isinstance(watch.params.properties[name][2], mi.Shape)
                       else (h,)):
                hh.update(name.encode())
                hh.update(digest)
        # the memo holds references to every JIT value of this token (param_digest)
        slot[3][1] = (token, h.hexdigest(), "shapes:" + hs.hexdigest())
        return slot[3][1][2] if shapes_only else slot[3][1][1] + suffix

    def _slot(self, scene, state):
        return scene_slot(self._scenes, scene, state, self.max_scenes)

    def entries(self, scene, state, key):
        """``(layer, entry)`` pairs cached for ``key`` (e.g. culled maps)."""
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

    def retire(self, scene, state, group, fingerprint, keep: int = 2) -> None:
        """Keep the maps of the ``keep`` latest view fingerprints of ``group`` (a light's
        label and kind of view): when the light moves, older ones are dropped, so a light
        moved every frame does not pile up maps (two: integrators whose views of one
        light differ, e.g. one with ``fit_frusta``, do not drop each other's)."""
        slot = self._slot(scene, state)
        for k in [k for k in self._views if k not in self._scenes]:
            del self._views[k]          # scenes the cache let go
        held = self._views.setdefault(id(scene), {})
        if held.get("state") != state:
            held.clear()
            held["state"] = state
        recent = [fingerprint] + [f for f in held.get(group, []) if f != fingerprint]
        for old in recent[keep:]:
            for k in [k for k in slot[2] if k[0][0] == old]:
                del slot[2][k]
        held[group] = recent[:keep]

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
        return sum(array_nbytes(e[0]) for s in self._scenes.values() for e in s[2].values())

    def clear(self) -> None:
        self._scenes.clear()
        self._memo.clear()
        self._views.clear()


#: The cache of every ``shadowmap`` integrator (``MAP_CACHE.clear()`` empties it).
MAP_CACHE = MapCache()


def clear_caches() -> None:
    """Empty every cache the package keeps across renders: depth maps
    (:data:`MAP_CACHE`), virtual pages and camera digests (:data:`~mi_shadowmap.virtual.
    PAGE_CACHE`), cascades of virtual maps, light-pose references
    (:mod:`~mi_shadowmap.light_views.pose`), gradient renders' automatic resolutions
    (:func:`_gradient_resolution`), meshes' edge topologies
    (:mod:`~mi_shadowmap.antialias`) and their bounds
    (:func:`~mi_shadowmap.light_views.base.shape_bounds`), and environment emitters'
    median cuts (:func:`~mi_shadowmap.environment.emitter_regions`: numpy arrays, keyed
    by the emitter's values, holding no scene).

    Each of them holds references to the scenes, emitters or meshes it describes (so
    that a freed object's ``id`` never aliases a live one), and so keeps them alive
    until evicted. Besides their memory, live shapes matter to Dr.Jit: a kernel that
    dispatches over shapes (``compute_surface_interaction``, a BSDF or emitter call)
    is traced over every registered instance, so the kernels of one scene differ --
    and are compiled again -- depending on which earlier scenes the caches still hold
    (measured: a differentiable render of a 64^2 scene compiled 69 kernels, 59 s,
    with one other small scene alive, and none without). Call this (then let the old
    scenes go) when switching between scenes in one process, e.g. between tests.
    """
    from . import antialias, depth_maps, virtual
    from . import environment as env_mod
    from .light_views import base, pose
    base.clear_memos()
    depth_maps.clear_memos()
    MAP_CACHE.clear()
    _GRADIENT_RESOLUTIONS.clear()
    virtual.PAGE_CACHE.clear()
    _VIRTUAL_CASCADES.clear()
    pose.clear_references()
    antialias.clear_meshes()
    env_mod._CACHE.clear()
    _SCENE_TOKENS.clear()
