"""Map cache across renders (issue 6): reuse when only the camera or the
filter parameters change, rebuild when geometry or emitters change through
``mi.traverse`` + ``params.update()``. Builds are counted twice: by the
integrator's ``stats`` and by wrapping ``build_depth_map`` (the real one)."""
import gc

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

import mi_shadowmap
import mi_shadowmap.map_manager as mm_mod
from mi_shadowmap import methods
from mi_shadowmap.map_manager import MAP_CACHE, MapCache
from mi_shadowmap.methods import builds_first_depth
from mi_shadowmap.options import MAP_METHODS, parse_options
from mi_shadowmap.scenes import default_scene

from conftest import SCENE_FILES

RES = 64
MAP_READY = list(MAP_METHODS)


def layer_names(method):
    """The layers a render of ``method`` at its defaults with full maps of ``RES``
    builds (from its record), as :func:`shadowmap` renders them."""
    opts = parse_options({"method": method, "resolution": RES})
    return opts.record.layer_names(opts)


def map_layers(method):
    """:func:`layer_names` after the first depth, where the method's maps have one
    (``second_depth``'s hold its second depths alone: ``builds_first_depth``)."""
    names = layer_names(method)
    return ["depth"] * builds_first_depth(methods.get(method), names) + list(names)


@pytest.fixture
def builds(monkeypatch):
    calls = []
    real = mm_mod.build_depth_map
    monkeypatch.setattr(mm_mod, "build_depth_map",
                        lambda *a, **k: calls.append(a[1].label) or real(*a, **k))
    MAP_CACHE.clear()
    yield calls
    MAP_CACHE.clear()


def render(scene, integ, seed=1):
    img = mi.render(scene, integrator=integ, spp=2, seed=seed)
    return np.asarray(img)


def shadowmap(**props):
    return mi.load_dict({"type": "shadowmap", "resolution": RES, **props})


def test_camera_change_reuses_maps_and_matches_a_fresh_build(builds):
    scene = mi.load_dict(default_scene(width=32, height=32))
    integ = shadowmap()
    render(scene, integ)
    assert len(builds) == 1 and integ.stats["maps_built"] == 1
    params = mi.traverse(scene)
    params["sensor.to_world"] = mi.ScalarTransform4f().look_at(
        origin=[1.5, 3.0, 4.5], target=[0.0, 0.3, 0.0], up=[0, 1, 0])
    params.update()
    cached = render(scene, integ)
    assert len(builds) == 1, "a camera change rebuilt the maps"
    assert integ.stats["maps_built"] == 0 and integ.stats["maps_reused"] == 1
    saved = integ.stats["naive_build_seconds"] - integ.stats["build_seconds"]
    print(f"cached render: build {integ.stats['build_seconds'] * 1e3:.2f} ms, "
          f"naive {integ.stats['naive_build_seconds'] * 1e3:.2f} ms, saved {saved * 1e3:.2f} ms")
    fresh = render(scene, shadowmap(cache_maps=False))
    assert len(builds) == 2
    np.testing.assert_array_equal(cached, fresh)


@pytest.mark.parametrize("method", MAP_READY)
def test_filter_parameter_change_reuses_maps(builds, method):
    """Every map method, new integrator instances with other bias values:
    the maps (and extra layers) of the first render are reused."""
    scene = mi.load_dict(default_scene(width=16, height=16))
    first = shadowmap(method=method)
    render(scene, first)
    assert first.stats["maps_built"] == 1
    assert first.stats["layers_built"] == len(layer_names(method))
    for change in ({"slope_bias": 2.5}, {"normal_bias": 0.0}, {"bias": 1e-3}):
        integ = shadowmap(method=method, **change)
        render(scene, integ)
        assert integ.stats["maps_built"] == 0 and integ.stats["layers_built"] == 0, change
        assert integ.stats["maps_reused"] == 1
    assert len(builds) == map_layers(method).count("depth")     # (second_depth: none)


def test_methods_share_the_depth_layer(builds):
    """Integrators of different map methods share one depth build per scene state."""
    scene = mi.load_dict(default_scene(width=16, height=16))
    for method in MAP_READY:
        integ = shadowmap(method=method)
        render(scene, integ)
        # extra depths only for the methods that use them, even when cached (and no
        # first depth for second_depth, which reads none)
        assert integ.maps[0].layers() == map_layers(method)
    assert len(builds) == 1
    hard = shadowmap(method="hard")
    render(scene, hard)
    assert hard.maps[0].second_depth is None and hard.maps[0].extra == {}


@pytest.mark.parametrize("edit", ["shape_transform", "mesh_vertices", "spot_transform",
                                  "spot_cutoff"])
def test_geometry_or_emitter_change_rebuilds(builds, edit):
    scene = mi.load_dict(default_scene(width=32, height=32))
    integ = shadowmap()
    before = render(scene, integ)
    assert len(builds) == 1
    params = mi.traverse(scene)
    if edit == "shape_transform":
        params["sphere.to_world"] = (mi.Transform4f().translate([0.6, 0.0, 0.3])
                                     @ params["sphere.to_world"])
    elif edit == "mesh_vertices":
        v = dr.unravel(mi.Point3f, params["box.vertex_positions"])
        params["box.vertex_positions"] = dr.ravel(mi.Point3f(v.x * 0.5, v.y * 1.6, v.z))
    elif edit == "spot_transform":
        params["spot.to_world"] = mi.ScalarTransform4f().look_at(
            origin=[2.4, 4.0, -3.0], target=[0.0, 0.0, 0.3], up=[0, 1, 0])
    else:
        params["spot.cutoff_angle"] = 30.0
    params.update()
    after = render(scene, integ)
    assert len(builds) == 2, f"{edit}: the maps were not rebuilt"
    assert integ.stats["maps_built"] == 1
    fresh = render(scene, shadowmap(cache_maps=False))
    np.testing.assert_array_equal(after, fresh)
    assert not np.array_equal(before, after)   # the edit is visible
    render(scene, integ)                       # and the new state is cached again
    assert len(builds) == 3 and integ.stats["maps_reused"] == 1


def test_moving_one_light_rebuilds_its_map_only(builds):
    """Full maps, four point lights: a light moved through ``params.update()`` rebuilds
    its own map (the cache was keyed by every emitter's parameters, so moving one
    rebuilt all four); the render equals a fresh build, and a light moved every frame
    keeps its two latest maps in the cache."""
    d = {k: v for k, v in default_scene(width=32, height=32).items()
         if not (isinstance(v, dict) and v.get("type") in ("spot", "point"))}
    for k, x in enumerate([-1.5, -0.5, 0.5, 1.5]):
        d[f"pl{k}"] = {"type": "point", "position": [x, 3.0, 1.0 + 0.3 * k],
                       "intensity": {"type": "rgb", "value": [3.0] * 3}}
    scene = mi.load_dict(d)
    integ = shadowmap()
    render(scene, integ)
    assert sorted(builds) == ["pl0", "pl1", "pl2", "pl3"]
    params = mi.traverse(scene)
    for step in range(3):
        del builds[:]
        params["pl1.position"] = mi.Point3f(-0.5 + 0.1 * (step + 1), 3.0, 1.3)
        params.update()
        img = render(scene, integ)
        assert builds == ["pl1"], (step, builds)
        assert integ.stats["maps_built"] == 1 and integ.stats["maps_reused"] == 3
    np.testing.assert_array_equal(img, render(scene, shadowmap(cache_maps=False)))
    slot = MAP_CACHE._scenes[id(scene)]
    assert len({k[0] for k in slot[2]}) == 5


def test_material_change_keeps_maps(builds):
    scene = mi.load_dict(default_scene(width=16, height=16))
    integ = shadowmap()
    render(scene, integ)
    params = mi.traverse(scene)
    params["ground.bsdf.reflectance.value"] = mi.Color3f(0.1, 0.9, 0.1)
    params.update()
    render(scene, integ)
    assert len(builds) == 1 and integ.stats["maps_reused"] == 1


def test_resolution_change_rebuilds(builds):
    scene = mi.load_dict(default_scene(width=16, height=16))
    render(scene, shadowmap())
    render(scene, mi.load_dict({"type": "shadowmap", "resolution": RES // 2}))
    assert len(builds) == 2


def test_cache_off_builds_every_render(builds):
    scene = mi.load_dict(default_scene(width=16, height=16))
    integ = shadowmap(cache_maps=False)
    render(scene, integ)
    render(scene, integ)
    assert len(builds) == 2


def test_cache_memory_is_bounded():
    cache = MapCache(max_bytes=3 * 4 * 1000, max_scenes=2)
    scenes = [mi.load_dict(default_scene(width=8, height=8)) for _ in range(3)]
    for k, sc in enumerate(scenes):
        st = cache.scene_state(sc)
        for j in range(2):
            cache.put(sc, st, ("view", j), "depth", dr.zeros(mi.Float, 1000), 0.0)
            assert cache.nbytes <= cache.max_bytes
    assert len(cache._scenes) <= 2
    # a new state of a scene replaces its old maps
    st = cache.scene_state(scenes[-1])
    assert cache.get(scenes[-1], st, ("view", 1), "depth") is not None
    assert cache.get(scenes[-1], "other state", ("view", 1), "depth") is None
    cache.put(scenes[-1], "other state", ("view", 0), "depth", dr.zeros(mi.Float, 10), 0.0)
    assert cache.get(scenes[-1], st, ("view", 1), "depth") is None


def test_large_mesh_edits_are_seen_through_the_memo(builds):
    """JIT buffers are hashed once per JIT variable; every update
    (even back to an earlier value) must still rebuild."""
    path = [p for p in SCENE_FILES if p.stem == "directional_mesh"][0]
    scene = mi.load_file(str(path), width=16, height=16)
    integ = shadowmap()
    render(scene, integ)
    params = mi.traverse(scene)
    original = mi.Float(params["terrain.vertex_positions"])
    assert dr.width(original) > 1024
    for k, factor in enumerate((1.3, 1.0, 1.3, 0.7)):
        v = dr.unravel(mi.Point3f, original)
        params["terrain.vertex_positions"] = dr.ravel(mi.Point3f(v.x, v.y * factor, v.z))
        params.update()
        render(scene, integ)
        assert len(builds) == 2 + k, factor
        render(scene, integ)
        assert len(builds) == 2 + k


def test_scene_state_sees_every_edit_and_hashes_nothing_when_unchanged(monkeypatch):
    """The scene state compares JIT variables before hashing: an unchanged scene hashes
    no parameter; an edit through ``params.update()`` and a write in place into a buffer
    read from a traversal (Dr.Jit gives the shape's member a new variable) change it."""
    cache = MapCache()
    scene = mi.load_dict(default_scene(width=8, height=8))
    s0 = cache.scene_state(scene)
    digests = []
    real = mm_mod.param_digest
    monkeypatch.setattr(mm_mod, "param_digest", lambda *a: digests.append(a[1]) or real(*a))
    assert cache.scene_state(scene) == s0 and digests == []
    params = mi.traverse(scene)
    original = mi.Float(params["box.vertex_positions"])
    params["box.vertex_positions"] = original * 1.5
    params.update()
    s1 = cache.scene_state(scene)
    assert s1 != s0 and digests
    v = params["box.vertex_positions"]              # the member itself, written in place
    dr.scatter(v, mi.Float(7.0), mi.UInt32(0))
    s2 = cache.scene_state(scene)
    assert s2 not in (s0, s1)
    digests.clear()
    assert cache.scene_state(scene) == s2 and digests == []


# ------------------------------------------------------------ cube-face culling
@pytest.mark.parametrize("method", MAP_READY)
def test_cull_faces_builds_fewer_faces_with_identical_results(builds, method):
    """Point light: only the faces camera-visible points project into are built;
    the render is bit-identical to the full cube map's."""
    scene = mi.load_dict(default_scene(width=32, height=32, light="point"))
    culled = shadowmap(method=method, cull_faces=True)
    img_culled = render(scene, culled)
    full = shadowmap(method=method, cache_maps=False)
    img_full = render(scene, full)
    print(f"{method}: faces built {culled.stats['faces_built']} of 6 "
          f"({culled.stats['texels_built']} texels vs {full.stats['texels_built']})")
    assert 1 <= culled.stats["faces_built"] < 6
    assert culled.stats["faces_built"] + culled.stats["faces_culled"] == 6
    np.testing.assert_array_equal(img_culled, img_full)


@pytest.mark.parametrize("method", [m for m in ("hard", "mdsm", "second_depth")
                                    if m in MAP_READY])
def test_cull_faces_builds_new_faces_when_the_camera_needs_them(builds, method):
    """Extra layers (mdsm_min/max, second_depth) follow the depth's face set: after
    a camera change needing a new face, no layer comes from the old faces' cache
    (review item 2): the render equals an uncached one."""
    d = default_scene(width=32, height=32, light="point")
    d["high_ball"] = {"type": "sphere", "center": [-2.4, 7.0, -3.4], "radius": 1.0,
                      "bsdf": {"type": "diffuse"}}   # above the light, out of the first view
    # a ceiling above the light with a blocker's shadow on it: the light's +y face
    d["ceiling"] = {"type": "rectangle", "bsdf": {"type": "diffuse"},
                    "to_world": mi.ScalarTransform4f().translate([-2.4, 7.0, -3.4])
                    .rotate([1, 0, 0], 90).scale(3.0)}
    d["blocker"] = {"type": "sphere", "center": [-1.6, 5.5, -3.0], "radius": 0.4,
                    "bsdf": {"type": "diffuse"}}
    scene = mi.load_dict(d)
    integ = shadowmap(method=method, cull_faces=True)
    render(scene, integ)
    first = integ.stats["faces_built"]
    render(scene, integ)                       # same camera: cached
    assert integ.stats["maps_reused"] == 1 and integ.stats["faces_built"] == 0
    params = mi.traverse(scene)                # now look at the ceiling (the light's +y face)
    params["sensor.to_world"] = mi.ScalarTransform4f().look_at(
        origin=[1.0, 3.0, 0.0], target=[-2.4, 7.0, -3.4], up=[0, 1, 0])
    params.update()
    img = render(scene, integ)
    assert integ.stats["maps_built"] == 1 and integ.stats["faces_built"] >= 1
    print(f"faces built: {first} for the first view, {integ.stats['faces_built']} for the new one")
    assert integ.stats["layers_built"] == len(layer_names(method))
    np.testing.assert_array_equal(img, render(scene, shadowmap(method=method,
                                                               cache_maps=False)))


@pytest.mark.parametrize("method", MAP_READY)
def test_cull_faces_with_a_camera_that_sees_nothing(builds, method):
    """No camera-visible surface: no face is needed, the map is +inf (lit) without a
    ray traced, and the render (of the empty sky) works (review item 1)."""
    scene = mi.load_dict(default_scene(width=16, height=16, light="point"))
    params = mi.traverse(scene)
    params["sensor.to_world"] = mi.ScalarTransform4f().look_at(
        origin=[0.0, 5.0, 0.0], target=[0.0, 10.0, 0.0], up=[0, 0, 1])   # at the sky
    params.update()
    integ = shadowmap(method=method, cull_faces=True)
    img = render(scene, integ)
    assert integ.stats["faces_built"] == 0 and integ.stats["faces_culled"] == 6
    assert np.all(np.isinf(integ.maps[0].to_numpy(map_layers(method)[0])))
    assert np.all(img == 0)


def test_cull_faces_keeps_the_neighbour_of_points_near_a_face_edge():
    """``CubeView.faces_needed``: a point within ``2 (4 + normal_bias) / res`` of a face's
    edge (in face coordinates) also needs the face across that edge (its normal offset,
    sub-pixel camera samples and filter taps cross it); farther in, only its own face.
    With no margin the neighbour was culled and those taps read +inf, lit (mutation
    audit: the bit-identical renders above never put a point that close to a seam)."""
    from mi_shadowmap.light_views import CubeView
    view = CubeView("point", mi.ScalarPoint3f(0, 0, 0), mi.ScalarTransform4f(), label="p")
    res = 128                                   # margin 2 * 4.5 / 128 = 0.07 of the face
    opts = parse_options({"method": "pcf", "cull_faces": True, "resolution": res})

    def faces(*points):
        need = view.faces_needed(opts, np.array(points, np.float64), res)
        return {f for f in range(6) if need[f]}
    # -y is face 3, +x face 0, -z face 5
    assert faces([0.0, -1.0, 0.0]) == {3}
    assert faces([0.9, -1.0, 0.0]) == {3}               # 0.1 from the edge
    assert faces([0.96, -1.0, 0.0]) == {3, 0}           # 0.04 from the +x edge
    assert faces([0.0, -1.0, -0.97]) == {3, 5}
    assert faces([-0.97, -1.0, 0.97]) == {3, 1, 4}       # a corner: both neighbours


# ---------------------------------------------------------------- fitted frusta
def large_world(light: str):
    """A 80 x 80 ground with a far box; the camera sees a small box up close."""
    T = mi.ScalarTransform4f
    d = {"type": "scene",
         "sensor": {"type": "perspective", "fov": 30,
                    "to_world": T().look_at(origin=[1.5, 2.0, 3.0], target=[0, 0.2, 0],
                                            up=[0, 1, 0]),
                    "film": {"type": "hdrfilm", "width": 48, "height": 48,
                             "rfilter": {"type": "box"}}},
         "ground": {"type": "rectangle", "to_world": T().rotate([1, 0, 0], -90).scale(40)},
         "box": {"type": "cube", "to_world": T().translate([0, 0.3, 0]).scale(0.3)},
         "far_box": {"type": "cube", "to_world": T().translate([25, 2, -20]).scale(2)}}
    if light == "spot":
        d["spot"] = {"type": "spot", "cutoff_angle": 60,
                     "to_world": T().look_at(origin=[-8, 10, -6], target=[5, 0, -5], up=[0, 1, 0]),
                     "intensity": {"type": "rgb", "value": 400}}
    else:
        d["sun"] = {"type": "directional", "direction": [1, -2, 0.7],
                    "irradiance": {"type": "rgb", "value": 3}}
    return mi.load_dict(d)


@pytest.mark.parametrize("light", ["spot", "directional"])
def test_fitted_frusta_gain_texel_density(light):
    scene = large_world(light)
    ref = render(scene, mi.load_dict({"type": "shadowmap", "method": "raytraced"}))[..., 3]
    mis = {}
    for fit in (False, True):
        integ = shadowmap(resolution=128, fit_frusta=fit)
        vis = render(scene, integ)[..., 3]
        mis[fit] = float(np.mean((ref >= 0.5) != (vis >= 0.5)))
        if fit:
            gain = integ.stats["texel_density_gain"][0]
    print(f"{light}: texel density gain x{gain:.0f} at 128^2; misclassified "
          f"{mis[False]:.2%} -> {mis[True]:.2%}")
    assert gain > 4
    assert mis[True] < mis[False] and mis[True] <= 0.02


@pytest.mark.parametrize("method", MAP_READY)
def test_fitted_frusta_follow_the_camera(builds, method):
    scene = large_world("directional")
    integ = shadowmap(method=method, fit_frusta=True)
    render(scene, integ)
    params = mi.traverse(scene)
    params["sensor.to_world"] = mi.ScalarTransform4f().look_at(
        origin=[20.0, 6.0, -12.0], target=[25.0, 1.0, -20.0], up=[0, 1, 0])
    params.update()
    img = render(scene, integ)
    assert integ.stats["maps_built"] == 1      # the fitted view moved with the camera
    np.testing.assert_array_equal(img, render(scene, shadowmap(method=method, fit_frusta=True,
                                                               cache_maps=False)))
    assert np.isfinite(img).all()


def test_mdsm_builds_only_the_layers_its_depths_need(builds):
    """Pagot et al.: n = 1 is the standard map (no extra layer), n = 2 adds the
    neighbourhood maximum, n = 3 the maximum and the minimum."""
    scene = mi.load_dict(default_scene(width=16, height=16, spp=1))
    for depths, expected in ((1, set()), (2, {"mdsm_max"}), (3, {"mdsm_min", "mdsm_max"})):
        integ = mi.load_dict({"type": "shadowmap", "method": "mdsm", "depths": depths,
                              "resolution": RES, "cache_maps": False})
        mi.render(scene, integrator=integ, spp=1)
        assert set(integ.maps[0].extra) == expected, depths


def test_clear_caches_frees_the_scenes_and_their_kernels_repeat():
    """:func:`mi_shadowmap.clear_caches` empties every cache (depth maps, pages,
    antialiasing edges), so a scene dropped by the user is freed: the caches hold no
    reference to it afterwards, and a like scene loaded then renders with exactly the
    same kernels as the first did. (Dr.Jit traces calls over the live shapes and BSDFs,
    so a cached old scene can change a new scene's kernels; whether it does depends on
    the registry's state, which the rest of a test run changes, so only the references
    are asserted, not a differing kernel.)"""
    import sys

    import mi_shadowmap
    from mi_shadowmap import antialias, virtual

    def render_hashes(scene, props):
        dr.kernel_history()   # clear
        dr.set_flag(dr.JitFlag.KernelHistory, True)
        try:
            mi.render(scene, integrator=mi.load_dict({"type": "shadowmap", **props}),
                      spp=2)
        finally:
            dr.set_flag(dr.JitFlag.KernelHistory, False)
        return {k["hash"] for k in dr.kernel_history() if k["type"] == dr.KernelType.JIT
                and k["size"] == 32 * 32 * 2}         # the render kernel

    for props in ({"method": "hard", "virtual": False}, {"method": "pcf"}):  # full, virtual
        mi_shadowmap.clear_caches()
        gc.collect()
        scene = mi.load_dict(default_scene(width=32, height=32))
        unheld = sys.getrefcount(scene)
        first = render_hashes(scene, props)
        assert MAP_CACHE._scenes or virtual.PAGE_CACHE._scenes   # the scene is held
        assert sys.getrefcount(scene) > unheld
        mi_shadowmap.clear_caches()
        gc.collect()
        assert not MAP_CACHE._scenes and not MAP_CACHE._memo
        assert not virtual.PAGE_CACHE._scenes and not antialias._EDGES
        assert sys.getrefcount(scene) == unheld                # nothing holds it now
        del scene
        gc.collect()
        again = render_hashes(mi.load_dict(default_scene(width=32, height=32)), props)
        assert first and again == first



@pytest.mark.parametrize("props", [{"method": "hard"}, {"method": "pcf", "virtual": False},
                                   {"method": "raytraced"}],
                         ids=lambda p: "-".join(f"{v}" for v in p.values()))
def test_a_scene_rendered_by_its_own_integrator_is_freed(props):
    """A scene holds its own integrator (``<integrator type="shadowmap">``, or the dict's
    ``"integrator"``), so a reference from the integrator back to the scene is a cycle
    through C++ that Python's collector cannot break: the integrator kept the scene in
    its per-scene memos (last render, views, emitter values, delta BSDFs), and every
    scene rendered with ``mi.render(scene)`` stayed alive after ``del`` and
    ``clear_caches()`` (30 scenes of 45k triangles: +5 MiB each, and renders slowed from
    0.23 to 0.45 s as Dr.Jit traced every live scene's shapes). It keeps tokens now."""
    import sys

    mi_shadowmap.clear_caches()
    gc.collect()
    scene = mi.load_dict({**default_scene(width=16, height=16),
                          "integrator": {"type": "shadowmap", **props}})
    unheld = sys.getrefcount(scene)
    first = np.asarray(mi.render(scene, spp=2, seed=1))
    again = np.asarray(mi.render(scene, spp=2, seed=1))     # the memos serve this one
    assert np.array_equal(first, again)
    mi_shadowmap.clear_caches()
    gc.collect()
    assert sys.getrefcount(scene) == unheld     # nothing but this test holds it


def test_clear_caches_lets_the_sensors_go():
    """``clear_caches()`` forgot the sensors' camera states but kept their frames
    (``virtual.camera._FRAMES``): up to 8 sensors stayed alive with their films' storage
    after their scenes were dropped (8 scenes of 1024^2 films: 140 MiB)."""
    import sys

    mi_shadowmap.clear_caches()
    gc.collect()
    scene = mi.load_dict(default_scene(width=16, height=16))
    sensor = scene.sensors()[0]
    unheld = sys.getrefcount(sensor)
    integ = mi.load_dict({"type": "shadowmap", "method": "hard"})
    mi.render(scene, integrator=integ, spp=2)
    del integ        # it keeps the sensor of its last render
    mi_shadowmap.clear_caches()
    gc.collect()
    assert sys.getrefcount(sensor) == unheld

def _light_scene(light):
    T = mi.ScalarTransform4f
    d = default_scene(width=32, height=32)
    d = {k: v for k, v in d.items() if not (isinstance(v, dict) and v.get("type") in (
        "spot", "point", "directional"))}
    d["lamp"] = {"point": {"type": "point", "position": [-2.4, 4.0, -3.4], "intensity": 60.0},
                 "spot": {"type": "spot", "cutoff_angle": 35.0, "intensity": 120.0,
                          "to_world": T().look_at(origin=[-2.4, 4.0, -3.4],
                                                  target=[0.2, 0.0, 0.3], up=[0, 1, 0])},
                 "directional": {"type": "directional", "direction": [0.5, -1.0, 0.7],
                                 "irradiance": 3.0}}[light]
    return mi.load_dict(d)


def _move(params, light, j):
    T = mi.ScalarTransform4f
    if light == "point":
        params["lamp.position"] = mi.Point3f(-2.4 + j, 4.0, -3.4)
    elif light == "spot":
        params["lamp.to_world"] = T().look_at(origin=[-2.4 + j, 4.0, -3.4],
                                              target=[0.2, 0.0, 0.3], up=[0, 1, 0])
    else:
        params["lamp.to_world"] = T().look_at(origin=[0, 0, 0], target=[0.5 + j, -1.0, 0.7],
                                              up=[0, 1, 0])
    params.update()


@pytest.mark.parametrize("light", ["point", "spot", "directional"])
@pytest.mark.parametrize("props", [{"method": "hard"}, {"method": "pcf"},
                                   {"method": "second_depth"}, {"method": "multiview"},
                                   {"method": "hard", "virtual": False}],
                         ids=lambda p: "-".join(f"{v}" for v in p.values()))
def test_a_moved_light_compiles_no_kernel(light, props):
    """A light moved (or turned) through ``params.update()`` rebuilds its maps with the
    kernels it had: the views' positions, frames and extents enter kernels as opaque
    values. Before, they were literals, and each new position compiled 2-4 kernels
    (a moving point light: 260-350 ms a frame against 25 ms). Positions are random, so
    Dr.Jit's disk cache cannot hold the kernels of an earlier run."""
    import random
    rng = random.Random()
    scene = _light_scene(light)
    params = mi.traverse(scene)
    integ = mi.load_dict({"type": "shadowmap", **props})
    _assert_no_kernel_compiled_last(
        scene, integ, lambda step: _move(params, light,
                                         rng.uniform(-0.05, 0.05) if step else 0.0))


def _assert_no_kernel_compiled_last(scene, integ, edit, frames: int = 3):
    """Render ``frames`` frames of ``scene``, ``edit(step)`` before each; the last one
    must compile no kernel (cache hits excepted) and be finite."""
    had = dr.flag(dr.JitFlag.KernelHistory)
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        for step in range(frames):
            edit(step)
            dr.kernel_history()
            img = mi.render(scene, integrator=integ, spp=2, seed=step)
            dr.eval(img)
            compiled = [k for k in dr.kernel_history()
                        if k["type"] == dr.KernelType.JIT and not k.get("cache_hit", 1)]
        assert np.isfinite(np.asarray(img)).all()
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, had)
    assert not compiled, [(k["size"], k["operation_count"]) for k in compiled]



@pytest.mark.parametrize("case,props", [
    ("far_point", {"method": "hard"}), ("far_point", {"method": "pcf"}),
    ("spot_cutoff", {"method": "hard"}),
    ("spot_cutoff", {"method": "hard", "virtual": False, "resolution": 128})],
    ids=lambda p: p if isinstance(p, str) else "-".join(f"{v}" for v in p.values()))
def test_a_far_light_moved_or_a_new_cutoff_compiles_no_kernel(case, props):
    """A perspective face's ``tan_half`` entered kernels as a literal: a spot's new
    cutoff angle, and a far point light moved (its face aimed at the scene's box is
    refitted, :func:`~mi_shadowmap.light_views.perspective.box_view`), compiled 3
    kernels a frame with virtual maps (220-480 ms against 15-40 ms; full maps 2).
    Values are random, so Dr.Jit's disk cache cannot hold an earlier run's kernels."""
    import random
    rng = random.Random()
    T = mi.ScalarTransform4f
    d = default_scene(width=32, height=32)
    d = {k: v for k, v in d.items() if not (isinstance(v, dict) and v.get("type") in (
        "spot", "point", "directional"))}
    far = 1e5
    d["lamp"] = ({"type": "point", "position": [-0.6 * far, 0.64 * far, -0.48 * far],
                  "intensity": 60.0 * far * far / 30.0} if case == "far_point" else
                 {"type": "spot", "cutoff_angle": 35.0, "intensity": 120.0,
                  "to_world": T().look_at(origin=[-2.4, 4.0, -3.4], target=[0.2, 0.0, 0.3],
                                          up=[0, 1, 0])})
    scene = mi.load_dict(d)
    params = mi.traverse(scene)
    integ = mi.load_dict({"type": "shadowmap", **props})

    def edit(step):
        j = rng.uniform(-0.05, 0.05) if step else 0.0
        if case == "far_point":
            params["lamp.position"] = mi.Point3f(far * (-0.6 + j), 0.64 * far, -0.48 * far)
        else:
            params["lamp.cutoff_angle"] = 35.0 + 40.0 * j
        params.update()

    _assert_no_kernel_compiled_last(scene, integ, edit)


def test_stats_read_like_a_dict():
    """``integrator.stats`` "reads like a dict": ``dict(stats)`` and ``list(stats)``
    raised "attribute name must be string, not 'int'", ``stats.items()`` an
    AttributeError, and a misspelt key an AttributeError instead of a KeyError."""
    from mi_shadowmap.map_manager import MapStats
    stats = MapStats(maps_built=2, texels_built=7)
    as_dict = dict(stats)
    assert as_dict == stats.as_dict() and as_dict["texels_built"] == 7
    assert list(stats) == list(as_dict) and len(stats) == len(as_dict)
    assert dict(stats.items()) == as_dict and list(stats.keys()) == list(as_dict)
    assert "level_histogram" not in stats and "maps_built" in stats
    for key in ("level_histogram", "texel_built", 0):
        with pytest.raises(KeyError):
            stats[key]
    assert stats.get("texel_built", -1) == -1


@pytest.mark.parametrize("axis", [0, 1, 2])
def test_a_point_light_moved_along_any_axis_rebuilds_the_maps(axis):
    """The scene state (and the light views' fingerprints) hashed a 3-vector parameter
    through ``value.matrix``, meant for transforms; Dr.Jit answers it on a ``Point3f``
    with its x component six times, so a point light's ``position`` moved in y or z
    left the state unchanged and a reused integrator rendered the old shadows (the
    occluder scene's light moved by 0.3 in z: visibility off by up to 0.83 against a
    fresh integrator's, cached full maps)."""
    mi_shadowmap.clear_caches()
    scene = mi.load_dict(default_scene(width=16, height=16, spp=1, light="point"))
    params = mi.traverse(scene)
    integ = mi.load_dict({"type": "shadowmap", "method": "hard", "resolution": 128})
    state0 = MAP_CACHE.scene_state(scene)
    mi.render(scene, integrator=integ, spp=1)
    p = np.array(params["point.position"]).ravel()
    p[axis] += 0.5
    params["point.position"] = mi.Point3f(*[float(c) for c in p])
    params.update()
    assert MAP_CACHE.scene_state(scene) != state0
    reused = np.asarray(mi.render(scene, integrator=integ, spp=1, seed=3))[..., -1]
    fresh = np.asarray(mi.render(scene, integrator=mi.load_dict(
        {"type": "shadowmap", "method": "hard", "resolution": 128, "cache_maps": False}),
        spp=1, seed=3))[..., -1]
    assert np.array_equal(reused, fresh)


@pytest.mark.parametrize("method", ["hard", "second_depth"])
def test_a_mesh_deformed_every_frame_keeps_one_state_in_the_mesh_memos(method):
    """The per-mesh-state memos (bounds and per-face magnitudes, ``second_depth``'s
    face solidity) held every frame's vertex buffer of a mesh deformed by
    ``params.update()`` until 4096 entries: a 90k-vertex mesh animated with ``hard``
    grew RSS 1.1 MB a frame (263 -> 308 MB over 40 frames; ``second_depth`` 2 MB a
    frame), Mitsuba's ``direct`` not at all. Only a mesh's latest state is kept now."""
    from mi_shadowmap.light_views import base
    from mi_shadowmap import depth_maps
    mi_shadowmap.clear_caches()
    T = mi.ScalarTransform4f
    scene = mi.load_dict({
        "type": "scene",
        "integrator": {"type": "shadowmap", "method": method},
        "sensor": {"type": "perspective", "fov": 45,
                   "to_world": T().look_at(origin=[0, 4, 6], target=[0, 0, 0], up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": 24, "height": 24}},
        "floor": {"type": "rectangle", "to_world": T().rotate([1, 0, 0], -90).scale(4)},
        "blob": {"type": "cube", "to_world": T().translate([0, 1, 0]).scale(0.5)},
        "light": {"type": "point", "position": [1, 4, 1]}})
    params = mi.traverse(scene)
    v0 = np.array(params["blob.vertex_positions"]).reshape(-1, 3)
    blob = [s for s in scene.shapes() if s.id() == "blob"][0]
    for f in range(5):
        params["blob.vertex_positions"] = mi.Float((v0 + [0.2 * f, 0, 0]).ravel())
        params.update()
        mi.render(scene, spp=1, seed=f)
    for memo in (base._MESH_MEMO, depth_maps._SOLID_MEMO):
        assert len([k for k in memo if k[0] == id(blob)]) <= 1
    assert [k for k in base._MESH_MEMO if k[0] == id(blob)]      # it was remembered
    mi_shadowmap.clear_caches()
