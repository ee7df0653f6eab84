"""The ``shadowmap`` integrator: direct illumination with depth-map shadows.

``render()`` builds one :class:`~mi_shadowmap.depth_maps.ShadowMap` per
emitter (first pass), guarded against Mitsuba's re-entrant call of a Python
``render()`` override; ``sample()`` shades camera hits (second pass).
Shading is identical for every method -- only the visibility factor differs.

Maps are cached across renders (:class:`MapCache`, shared by every
integrator instance): a render whose scene geometry and emitters are
unchanged reuses them, whatever the camera or the method's filter
parameters.
"""
from __future__ import annotations

import collections
import dataclasses
import hashlib
import math
import time

import numpy as np

import drjit as dr
import mitsuba as mi

from . import options as opt_mod
from .depth_maps import LAYER_BUILDERS, ShadowMap, build_depth_map
from .filters import FILTERS, LAYERS, NEEDS_FOOTPRINT, Lookup, RayTracedLight, shifted_grid_point
from .light_views import cascaded_view, emitter_kind, emitter_label, make_light_view


class ShadowMapIntegrator(mi.SamplingIntegrator):
    __doc__ = r"""
Shadow-map direct illumination (``shadowmap``)
----------------------------------------------

Direct illumination from every emitter of the scene (emitter sampling only:
one light sample per emitter per camera sample, or ``shadow_rays`` for
``raytraced``), where visibility comes from a depth map built with Dr.Jit
ray queries from each light (first pass) and looked up with the chosen
``method`` (second pass). ``method='raytraced'`` traces real shadow rays and
is the ground truth; it matches Mitsuba's ``direct`` integrator with
``emitter_samples=1, bsdf_samples=0``.

One visibility AOV per emitter, ``vis_<id>`` (``vis_<index>`` when the
emitter has no id), carries the visibility used for it (0 where it
contributes nothing).

Maps: spot -- perspective covering the cutoff cone; point and area -- cube
maps (area lights as their centre); directional -- orthographic, fitted to
the scene bounds seen along the light. See :mod:`mi_shadowmap.light_views`.

""" + opt_mod.docs_table()

    def __init__(self, props=mi.Properties()):
        super().__init__(props)
        self.opts = opt_mod.parse_options(props)
        self.maps: list[ShadowMap] = []
        self.views = []
        self.build_seconds = 0.0
        self.resolution = None      # the resolution of the last render's maps
        self.stats: dict = {}       # see prepare_maps()
        self._in_render = False
        self._emitter_labels: list[str] = []
        self._diff_scale = 1.0

    # ---------------------------------------------------------------- passes
    def render(self, scene, sensor=0, seed=0, spp=0, develop=True, evaluate=True):
        if self._in_render:   # Mitsuba re-enters a Python render() override
            return super().render(scene, sensor, seed, spp, develop, evaluate)
        self._in_render = True
        try:
            if isinstance(sensor, int):
                sensor_obj = scene.sensors()[sensor]
            else:
                sensor_obj = sensor
            self.prepare_maps(scene, sensor_obj)
            n_spp = spp if spp > 0 else sensor_obj.sampler().sample_count()
            # Mitsuba scales ray differentials by 1/sqrt(spp); footprints use whole pixels.
            self._diff_scale = math.sqrt(n_spp)
            return super().render(scene, sensor, seed, spp, develop, evaluate)
        finally:
            self._in_render = False

    def prepare_maps(self, scene: mi.Scene, sensor=None) -> list[ShadowMap]:
        """First pass: one depth map per emitter (empty for ``raytraced``).

        The resolution is ``resolution`` or the automatic one (see
        :meth:`~mi_shadowmap.options.Options.map_resolution`, from the film of
        ``sensor``, default the scene's first sensor); the memory the maps
        need is checked against ``memory_budget`` before anything is built.
        Only the layers the method uses are built (``filters.LAYERS``), and
        with ``cache_maps`` every layer is taken from :data:`MAP_CACHE` when
        it holds one for the same scene state, light view and resolution.

        With ``cull_faces`` cube maps build only the faces camera-visible points
        project into (:func:`cube_faces_needed`); with ``fit_frusta`` spot and
        directional views are fitted to the camera-visible receivers
        (:func:`fit_view`) after the resolution is chosen, so the fit raises
        the texel density.

        ``self.stats`` records ``maps_built``, ``maps_reused``, ``faces_built``,
        ``faces_culled``, ``texel_density_gain`` (per fitted view, texel area
        before / after), ``texels_built`` (depth and extra layers), ``layers_built``,
        ``build_seconds`` (spent here) and ``naive_build_seconds`` (what building
        every layer from scratch took when it was built), whose difference is
        the time the cache saved.
        """
        self.check_scene(scene)
        t0 = time.perf_counter()
        opts = self.opts
        layers = tuple(LAYERS.get(opts.method, ()))
        self.views = [None if emitter_kind(e) == "environment" or not opts.uses_map
                      else make_light_view(e, scene, i)
                      for i, e in enumerate(scene.emitters())]
        self.maps = [None] * len(self.views)
        stats = dict(maps_built=0, maps_reused=0, faces_built=0, faces_culled=0,
                     texels_built=0, layers_built=0, naive_build_seconds=0.0)
        self.stats = stats
        if any(v is not None for v in self.views):
            if sensor is None and len(scene.sensors()) > 0:
                sensor = scene.sensors()[0]
            if opts.cascades > 1:   # parallel-split maps for directional lights (issue 4)
                self.views = [None if v is None else
                              cascaded_view(v, scene, sensor, opts.cascades, opts.split_lambda)
                              for v in self.views]
            film_size = sensor.film().crop_size() if sensor is not None else (512, 512)
            face_layers = sum(v.n_faces for v in self.views if v is not None) * (1 + len(layers))
            footprint = footprint_ratio(scene, sensor, self.views) if opts.resolution is None else 1.0
            # Raises (naming the memory needed) before any map is allocated.
            self.resolution = res = opts.map_resolution(film_size, face_layers, footprint)
            state = MAP_CACHE.scene_state(scene) if opts.cache_maps else None
            visible = None
            if ((opts.cull_faces and any(v is not None and v.projection == "cube"
                                         for v in self.views))
                    or (opts.fit_frusta and any(v is not None and v.n_faces == 1
                                                for v in self.views))):
                visible = camera_visible_points(scene, sensor)
            if opts.fit_frusta:
                margin = 8.0 + opts.normal_bias_texels
                stats["texel_density_gain"] = []
                for k, view in enumerate(self.views):
                    if view is not None and view.n_faces == 1:
                        self.views[k], gain = fit_view(view, visible, margin / res)
                        stats["texel_density_gain"].append(gain)
            for k, view in enumerate(self.views):
                if view is not None:
                    faces = None
                    if visible is not None and view.projection == "cube":
                        margin = 2.0 * (4.0 + opts.normal_bias_texels) / res
                        faces = cube_faces_needed(view, visible, margin)
                    self.maps[k] = self._map_for(scene, view, res, layers, state, stats, faces)
        dr.sync_thread()
        self.build_seconds = stats["build_seconds"] = time.perf_counter() - t0
        return self.maps

    def _map_for(self, scene, view, res, layers, state, stats, faces=None) -> ShadowMap:
        """One emitter's map: cached layers where possible, the rest built.

        ``faces``: the cube faces needed (``cull_faces``), None for all.
        """
        key = (view_fingerprint(view), res)
        cached = MAP_CACHE.get(scene, state, key, "depth") if state is not None else None
        if faces is not None:
            if all(faces):
                faces = None
            elif cached is None and state is not None:   # a culled map with enough faces
                for layer, entry in MAP_CACHE.entries(scene, state, key):
                    if (isinstance(layer, tuple) and layer[0] == "depth"
                            and all(h or not f for h, f in zip(layer[1], faces))):
                        cached = entry
                        break
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
                MAP_CACHE.put(scene, state, key, ("depth", tuple(faces)), smap.depth, dt)
        elif cached is None:
            t0 = time.perf_counter()
            smap = build_depth_map(scene, view, res, () if state is not None else layers)
            dr.sync_thread()
            dt = time.perf_counter() - t0
            stats["maps_built"] += 1
            stats["faces_built"] += view.n_faces
            stats["texels_built"] += smap.n_texels * (1 + (0 if state is not None else
                                                           len(layers)))
            stats["naive_build_seconds"] += dt
            if state is None:
                return smap
            MAP_CACHE.put(scene, state, key, "depth", smap.depth, dt)
        else:
            smap = ShadowMap(view=view, resolution=res, depth=cached[0])
            stats["maps_reused"] += 1
            stats["naive_build_seconds"] += cached[1]
        for name in layers:
            entry = MAP_CACHE.get(scene, state, key, name) if state is not None else None
            if entry is None:
                if name not in LAYER_BUILDERS:
                    raise KeyError(f"unknown depth-map layer '{name}'; "
                                   f"known: {sorted(LAYER_BUILDERS)}")
                t0 = time.perf_counter()
                data = LAYER_BUILDERS[name](scene, smap)
                dr.eval(data)
                dr.sync_thread()
                entry = (data, time.perf_counter() - t0)
                if state is not None:
                    MAP_CACHE.put(scene, state, key, name, *entry)
                stats["layers_built"] += 1
                stats["texels_built"] += smap.n_texels
            stats["naive_build_seconds"] += entry[1]
            if name == "second_depth":
                smap.second_depth = entry[0]
            else:
                smap.extra[name] = entry[0]
        return smap

    def check_scene(self, scene):
        """Raise ValueError naming any emitter this integrator cannot handle.

        Called by ``render()``; call it yourself before ``mi.render`` to get the
        error unwrapped (``mi.render`` re-raises errors of a Python
        integrator as a RuntimeError whose ``__cause__`` holds the message).
        """
        labels = []
        for i, e in enumerate(scene.emitters()):
            if emitter_kind(e) == "environment" and self.opts.environment == "error":
                raise ValueError(
                    f"shadowmap: emitter '{emitter_label(e, i)}' is an environment/constant "
                    "emitter, which has no finite frustum for a depth map; set the property "
                    "environment='unshadowed' to light it without shadows, or remove it")
            if emitter_kind(e) != "environment":
                make_light_view(e, scene, i)   # raises for unsupported emitters
            labels.append(emitter_label(e, i))
        # AOV names must be unique: fall back to indices for duplicate ids.
        self._emitter_labels = [
            lab if labels.count(lab) == 1 else str(i) for i, lab in enumerate(labels)]

    def aov_names(self):
        return [f"vis_{lab}" for lab in self._emitter_labels]

    def sample(self, scene, sampler, ray, medium=None, active=True):
        opts = self.opts
        if not isinstance(ray, mi.RayDifferential3f):   # copying drops the differentials
            ray = mi.RayDifferential3f(ray)
        si = scene.ray_intersect(ray, active)
        valid = active & si.is_valid()
        result = mi.Spectrum(0.0)
        if not opts.hide_emitters:
            result += si.emitter(scene, active).eval(si, active)
        bsdf = si.bsdf(ray)
        ctx = mi.BSDFContext()
        shade = valid & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth)
        if opts.method in NEEDS_FOOTPRINT:
            dp_dx, dp_dy = self._footprint(ray, si)
        else:
            dp_dx = dp_dy = mi.Vector3f(0.0)
        vis_fn = FILTERS[opts.method]
        aovs = []
        n_light = opts.shadow_rays if opts.method == "raytraced" else 1
        for k, emitter in enumerate(scene.emitters()):
            smap = self.maps[k] if opts.uses_map else RayTracedLight(scene)
            vis_sum = mi.Float(0.0)
            contributes = mi.Bool(False)
            shift = None
            for s in range(n_light):
                if n_light == 1:
                    u = sampler.next_2d(shade)
                else:
                    if s == 0:
                        shift = sampler.next_2d(shade)
                    u = shifted_grid_point(s, n_light, shift)
                ds, w = emitter.sample_direction(si, u, shade)
                lit = shade & (ds.pdf > 0)
                wo = si.to_local(ds.d)
                f = bsdf.eval(ctx, si, wo, lit)
                unshadowed = w * f
                lit &= dr.max(unshadowed) > 0
                if smap is None:     # environment emitter lit without shadows
                    vis = mi.Float(1.0)
                else:
                    lk = Lookup(si.p, si.n, dp_dx, dp_dy, si, ds, sampler)
                    vis = dr.select(lit, vis_fn(smap, lk, opts, lit), 0.0)
                result += dr.select(lit, unshadowed * vis, 0.0) / n_light
                vis_sum += vis
                contributes |= lit
            aovs.append(dr.select(contributes, vis_sum / n_light, 0.0))
        return result, valid, aovs

    def _footprint(self, ray: mi.RayDifferential3f, si):
        """World-space pixel footprint on the tangent plane (ray differentials)."""
        n = si.n
        scale = self._diff_scale

        def hit(o, d):
            t = dr.dot(n, si.p - o) / dr.select(dr.abs(dr.dot(n, d)) > 1e-12,
                                                dr.dot(n, d), 1e-12)
            return o + d * t

        o_x = ray.o + (ray.o_x - ray.o) * scale
        o_y = ray.o + (ray.o_y - ray.o) * scale
        d_x = ray.d + (ray.d_x - ray.d) * scale
        d_y = ray.d + (ray.d_y - ray.d) * scale
        ok = ray.has_differentials
        dp_dx = dr.select(ok, hit(o_x, d_x) - si.p, 0.0)
        dp_dy = dr.select(ok, hit(o_y, d_y) - si.p, 0.0)
        return mi.Vector3f(dp_dx), mi.Vector3f(dp_dy)

    def to_string(self):
        res = self.opts.resolution if self.opts.resolution is not None else "auto"
        return f"ShadowMapIntegrator[method={self.opts.method}, resolution={res}]"


# ------------------------------------------------------- automatic resolution
def footprint_ratio(scene, sensor, views) -> float:
    """Texel width over camera pixel width at the scene's centre (max over lights).

    Per unit resolution: a spot map spans ``2 tan(cutoff) d`` at distance
    ``d`` from the light, a cube face ``2 d``, an orthographic map its width;
    a perspective camera spans ``2 tan(x_fov / 2) d_cam`` per unit film width.
    ``d`` and ``d_cam`` are measured to the centre of the scene's bounding
    box. Returns 1 when it cannot be computed (no bounds, not a perspective
    camera, a projection this does not know). Used by the automatic
    ``resolution`` (:meth:`~mi_shadowmap.options.Options.map_resolution`).
    """
    try:
        bbox = scene.bbox()
        if sensor is None or not bbox.valid():
            return 1.0
        centre = np.array([float(c) for c in bbox.center()])
        params = mi.traverse(sensor)
        key = next((k for k in params.keys() if k.endswith("x_fov")), None)
        if key is None:
            return 1.0
        x_fov = float(dr.ravel(params[key])[0])
        cam = sensor.world_transform().translation()
        cam = np.array([float(dr.ravel(cam[k])[0]) for k in range(3)])
        cam_width = 2.0 * math.tan(math.radians(x_fov) / 2) * np.linalg.norm(centre - cam)
        if not cam_width > 0:
            return 1.0
        widths = []
        for v in views:
            if v is None:
                continue
            d = np.linalg.norm(centre - np.array([float(c) for c in v.position]))
            if v.projection == "perspective":
                widths.append(2.0 * v.tan_half * d)
            elif v.projection == "cube":
                widths.append(2.0 * d)
            elif v.projection == "orthographic":
                widths.append(2.0 * max(v.half_extent))
        return max(widths) / cam_width if widths else 1.0
    except Exception:   # never let a heuristic break a render
        return 1.0


# ------------------------------------------------------------ fitted frusta
def fit_view(view, p_world: np.ndarray, margin: float):
    """``(view fitted to the visible points, texel density gain)``.

    Only the points inside the original map are kept (the others get no
    light from a spot, or are lit by convention). Perspective (spot): a square
    frustum re-aimed at the mean direction of those points, with the smallest
    ``tan_half`` covering them; orthographic (directional): the light-space
    rectangle of their xy, same direction and near plane. Both grow by
    ``margin`` (a fraction of the window) per side for normal offsets and
    filter taps. A caster can only shadow a visible receiver along the light
    ray to it, which crosses the same (u, v): casters are kept (Reeves' and
    Filament's fitting of the frustum to what matters, restricted to what
    the camera sees). The gain is the ratio of texel areas (old / new) at the
    same resolution. The original view is returned (gain 1) if nothing is
    gained or the fit is not possible.
    """
    if len(p_world) == 0 or view.projection not in ("perspective", "orthographic"):
        return view, 1.0
    L = np.array(view.light_from_world.matrix, dtype=np.float64)
    p_l = p_world @ L[:3, :3].T + L[:3, 3]
    pos = np.array([float(c) for c in view.position])
    if view.projection == "perspective":
        z = p_l[:, 2]
        keep = (z > 0) & (np.abs(p_l[:, 0]) <= view.tan_half * z) \
            & (np.abs(p_l[:, 1]) <= view.tan_half * z)
        if not keep.any():
            return view, 1.0
        dirs = p_world[keep] - pos
        dirs /= np.maximum(np.linalg.norm(dirs, axis=1, keepdims=True), 1e-30)
        axis = dirs.mean(axis=0)
        if np.linalg.norm(axis) < 1e-6:
            return view, 1.0
        new_lfw = _look_along_light(pos, axis / np.linalg.norm(axis))
        M = np.array(new_lfw.matrix, dtype=np.float64)
        q = p_world[keep] @ M[:3, :3].T + M[:3, 3]
        if np.any(q[:, 2] <= 1e-9 * np.abs(q).max()):
            return view, 1.0
        tan = float(np.max(np.abs(q[:, :2]) / q[:, 2:3]))
        tan = max(tan * (1.0 + 2.0 * margin), 1e-6 * view.tan_half)
        if tan >= view.tan_half:
            return view, 1.0
        return (dataclasses.replace(view, light_from_world=new_lfw, tan_half=tan),
                (view.tan_half / tan) ** 2)
    hx, hy = view.half_extent
    keep = (np.abs(p_l[:, 0]) <= hx) & (np.abs(p_l[:, 1]) <= hy)
    if not keep.any():
        return view, 1.0
    lo, hi = p_l[keep, :2].min(axis=0), p_l[keep, :2].max(axis=0)
    centre = 0.5 * (lo + hi)
    size = max(hx, hy)
    half = 0.5 * (hi - lo) + 2.0 * margin * np.maximum(0.5 * (hi - lo), 1e-3 * size)
    half = np.maximum(half, 1e-6 * size)
    if max(half) >= max(hx, hy):
        return view, 1.0
    W = np.linalg.inv(L)
    origin = W[:3, :3] @ np.array([centre[0], centre[1], 0.0]) + W[:3, 3]
    fwd = W[:3, :3] @ np.array([0.0, 0.0, 1.0])
    new_lfw = _look_along_light(origin, fwd)
    return (dataclasses.replace(view, position=mi.ScalarPoint3f(*origin),
                                light_from_world=new_lfw,
                                half_extent=(float(half[0]), float(half[1]))),
            (max(hx, hy) / float(max(half))) ** 2)


def _look_along_light(origin, forward):
    from .light_views import _look_along
    return _look_along(mi.ScalarPoint3f(*[float(c) for c in origin]),
                       mi.ScalarVector3f(*[float(c) for c in forward]))


# --------------------------------------------------------- cube-face culling
def camera_visible_points(scene, sensor) -> np.ndarray:
    """World points the camera sees: one ray through every pixel centre, ``(N, 3)``."""
    if sensor is None:
        return np.zeros((0, 3))
    w, h = (int(x) for x in sensor.film().crop_size())
    idx = dr.arange(mi.UInt32, w * h)
    y = idx // w
    x = idx - y * w
    pos = mi.Point2f((mi.Float(x) + 0.5) / w, (mi.Float(y) + 0.5) / h)
    ray, _ = sensor.sample_ray(0.0, 0.5, pos, mi.Point2f(0.5))
    si = scene.ray_intersect(ray)
    p = np.stack([si.p.x.numpy(), si.p.y.numpy(), si.p.z.numpy()], axis=1)
    return p[si.is_valid().numpy()]


def cube_faces_needed(view, p_world: np.ndarray, margin: float) -> tuple:
    """Which of the 6 faces (``2*axis + (sign < 0)``) the points project into.

    A point within ``margin`` (in the face's [-1, 1] coordinates) of a face
    edge also needs the neighbour across that edge (normal offsets and
    sub-pixel camera samples may cross it).
    """
    need = [False] * 6
    if len(p_world) == 0:
        return tuple(need)
    d = p_world - np.array([float(c) for c in view.position])
    a = np.abs(d)
    major = np.argmax(a, axis=1)
    m = np.maximum(a[np.arange(len(d)), major], 1e-30)
    for axis in range(3):
        for sign in (0, 1):
            face_pts = (major == axis) & ((d[:, axis] < 0) == bool(sign))
            need[2 * axis + sign] |= bool(face_pts.any())
            # neighbours: points of other faces within `margin` of this face's direction
            near = (a[:, axis] >= m * (1.0 - margin)) & ((d[:, axis] < 0) == bool(sign))
            need[2 * axis + sign] |= bool(near.any())
    return tuple(need)


def build_culled_depth(scene, view, res: int, faces) -> mi.Float:
    """First-surface depth of the ``faces`` of a cube view; +inf in the others.

    Only the needed faces' texel rays are traced (gathered out of
    :meth:`LightView.texel_rays`, traced by :func:`depth_maps._first_hit`,
    scattered back into a full-size array).
    """
    from .depth_maps import _first_hit
    n = res * res
    idx = mi.UInt32(np.concatenate([np.arange(f * n, (f + 1) * n, dtype=np.uint32)
                                    for f in range(view.n_faces) if faces[f]]))
    o, d, max_t = view.texel_rays(res)
    if dr.width(o) > 1:
        o = dr.gather(mi.Point3f, o, idx)
    d = dr.gather(mi.Vector3f, d, idx)
    depth_sub = _first_hit(scene, view, o, d, max_t)
    depth = dr.full(mi.Float, dr.inf, view.n_faces * n)
    dr.scatter(depth, depth_sub, idx)
    dr.eval(depth)
    dr.sync_thread()
    return depth


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
        return sum(4 * dr.width(e[0]) for s in self._scenes.values() for e in s[2].values())

    def clear(self) -> None:
        self._scenes.clear()
        self._memo.clear()


_MEMO_MIN = 1024   # JIT buffers wider than this are hashed once per variable


#: The cache of every ``shadowmap`` integrator (``MAP_CACHE.clear()`` empties it).
MAP_CACHE = MapCache()


class _ScalarRefusal:
    """Registered for scalar variants: constructing it raises a clear error."""

    def __init__(self, variant):
        self.variant = variant

    def __call__(self, props):
        raise RuntimeError(
            f"shadowmap: the Mitsuba variant '{self.variant}' is not supported; the shadowmap "
            "integrator needs a JIT variant (llvm_ad_rgb, or cuda_ad_rgb where a GPU exists), "
            "because a Python integrator in a scalar variant runs once per ray")


def register(variant: str | None = None) -> None:
    """Register ``shadowmap`` for the current Mitsuba variant."""
    variant = variant or mi.variant()
    if variant is None:
        return
    if variant.startswith("scalar"):
        mi.register_integrator("shadowmap", _ScalarRefusal(variant))
    else:
        mi.register_integrator("shadowmap", lambda props: ShadowMapIntegrator(props))
