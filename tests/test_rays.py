"""mi_shadowmap.rays.spawn_shadow_ray: no self-intersection and no lost contact
occluders at any scale, for mesh and non-mesh receivers and every light kind."""
import math

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from mi_shadowmap.rays import spawn_shadow_ray

from conftest import translated_scene

N = 32     # N x N receiver points


def T():
    return mi.ScalarTransform4f()   # the current variant's (looked up per call)


def tilt():
    """A tilted frame: the receiver's points are not exact in float32."""
    return T().rotate([math.sqrt(0.5), 0.0, math.sqrt(0.5)], 23.0)


def place(s):
    """Receiver frame: scaled by s, off the origin, tilted; its surface is local y = 0."""
    return T().scale(s) @ T().translate([0.3, 0.2, -0.1]) @ tilt()


def plate(s):
    """A plate 0.03 s above the receiver (3 % of the scene), over local x in [0, 1]."""
    return {"type": "rectangle", "to_world": place(s) @ T().translate([0.5, 0.03, 0.0])
            @ T().rotate([1, 0, 0], -90) @ T().scale([0.5, 1.0, 1.0])}


def receiver_scene(s, occluder, receiver="rectangle"):
    """A tilted 2 s square (a mesh), or the top of a unit sphere (not a mesh:
    its hit points are computed along the camera ray), plus the plate."""
    if receiver == "rectangle":
        shape = {"type": "rectangle", "to_world": place(s) @ T().rotate([1, 0, 0], -90)}
    else:
        shape = {"type": "sphere", "center": list(place(s) @ mi.ScalarPoint3f(0, -1, 0)),
                 "radius": s}
    d = {"type": "scene", "receiver": shape}
    if occluder:
        d["plate"] = plate(s)
    return mi.load_dict(d)


def receiver_points(scene, s, extent):
    """Hits of rays cast down from just below the plate (local y = 0.01), on an N x N
    grid of local x, z in [-extent, extent]; x > 0 is under the plate."""
    g = (np.arange(N) + 0.5) / N * 2 * extent - extent
    x, z = [a.ravel() for a in np.meshgrid(g, g)]
    to_world = place(s)
    org = np.array([list(to_world @ mi.ScalarPoint3f(a, 0.01, b)) for a, b in zip(x, z)])
    down = list(to_world @ mi.ScalarVector3f(0, -1, 0))
    down = np.array(down) / np.linalg.norm(down)
    ray = mi.Ray3f(mi.Point3f(*[mi.Float(c.astype(np.float32)) for c in org.T]),
                   mi.Vector3f(*[float(c) for c in down]))
    si = scene.ray_intersect(ray)
    assert bool(dr.all(si.is_valid())), "every ray must hit the receiver"
    return si, x, z


def light_targets(si, s):
    """Point-light targets 1.5 s above each point, leaning 40 degrees towards local -z."""
    to_world = place(s)
    offset = np.array(list(to_world @ mi.ScalarVector3f(0, 1.5, -1.5 * math.tan(math.radians(40)))))
    return si.p + mi.Vector3f(*[float(c) for c in offset])


@pytest.mark.parametrize("receiver", ["rectangle", "sphere"])
@pytest.mark.parametrize("s", [1e-6, 1.0, 1e6])
def test_no_self_hit_and_contact_occluder_found(s, receiver):
    extent = 0.9 if receiver == "rectangle" else 0.5   # the sphere's top cap
    bare = receiver_scene(s, occluder=False, receiver=receiver)
    si, _, _ = receiver_points(bare, s, extent)
    hit = np.asarray(bare.ray_test(spawn_shadow_ray(si, light_targets(si, s), bare)))
    assert not hit.any(), f"{hit.mean():.1%} of the shadow rays re-hit the receiver"

    scene = receiver_scene(s, occluder=True, receiver=receiver)
    si, x, _ = receiver_points(scene, s, extent)
    target = light_targets(si, s)
    hit = np.asarray(scene.ray_test(spawn_shadow_ray(si, target, scene)))
    under, free = x > 0.1, x < -0.1
    mitsuba = np.asarray(scene.ray_test(si.spawn_ray_to(target)))
    print(f"s={s:g} {receiver}: occluded under the plate {hit[under].mean():.0%} "
          f"(Mitsuba's spawn_ray_to: {mitsuba[under].mean():.0%}), elsewhere "
          f"{hit[free].mean():.0%}")
    assert hit[under].all() and not hit[free].any()


@pytest.mark.parametrize("s", [1e-6, 1.0, 1e6])
def test_directional_and_area_light_targets(s):
    """``ds.p`` of a directional light (Mitsuba puts it beyond the scene's bounding
    sphere) and of an area light (on the light's own surface, which the ray must
    not reach)."""
    scene = mi.load_dict({
        "type": "scene",
        "receiver": {"type": "rectangle", "to_world": place(s) @ T().rotate([1, 0, 0], -90)},
        "plate": plate(s),
        "sun": {"type": "directional",
                "direction": list(place(1.0) @ mi.ScalarVector3f(0.0, -1.0, -0.3))},
        "panel": {"type": "rectangle",
                  "to_world": place(s) @ T().translate([0, 2, 0]) @ T().rotate([1, 0, 0], 90)
                  @ T().scale(0.2),
                  "emitter": {"type": "area", "radiance": {"type": "rgb", "value": 1.0}}}})
    si, x, z = receiver_points(scene, s, 0.9)
    under, free = (x > 0.1) & (np.abs(z) < 0.5), x < -0.3   # (the panel spans |x| < 0.2)
    assert len(scene.emitters()) == 2
    for emitter in scene.emitters():
        ds, _ = emitter.sample_direction(si, mi.Point2f(0.5, 0.5))
        hit = np.asarray(scene.ray_test(spawn_shadow_ray(si, ds.p, scene)))
        assert hit[under].all(), (str(emitter), s, hit[under].mean())
        # neither the receiver nor, for the area light, the light's own surface
        assert not hit[free].any(), (str(emitter), s, hit[free].mean())


@pytest.mark.parametrize("variant", ["llvm_ad_mono", "llvm_ad_spectral"])
def test_other_variants(variant):
    mi.set_variant(variant)
    scene = receiver_scene(1e-3, occluder=True)
    si, x, _ = receiver_points(scene, 1e-3, 0.9)
    ray = spawn_shadow_ray(si, light_targets(si, 1e-3), scene)
    assert isinstance(ray, mi.Ray3f)
    hit = np.asarray(scene.ray_test(ray))
    assert hit[x > 0.1].all() and not hit[x < -0.1].any()


def test_gradients_flow_through_the_origin():
    """The offset is detached, the point is not: d(ray.o)/d(p) = 1."""
    scene = receiver_scene(1.0, occluder=False)
    si, _, _ = receiver_points(scene, 1.0, 0.9)
    target = mi.Point3f(dr.detach(light_targets(si, 1.0)))
    p = mi.Point3f(si.p)
    dr.enable_grad(p)
    si.p = p
    ray = spawn_shadow_ray(si, target, scene)
    dr.forward_from(p, dr.ADFlag.ClearNone)
    assert np.allclose(np.asarray(dr.grad(ray.o)), 1.0)


@pytest.mark.parametrize("ground", [1e3, 1e6])
def test_a_huge_flat_ground_keeps_the_shadows_of_small_posts(ground):
    """The origin offset was 64 roundoffs of the shape's largest coordinate: on a
    ``rectangle`` ground 1e6 wide a shadow ray started about 4 units above it, over
    posts 1 unit tall, and ``raytraced`` rendered the unshadowed image (relative error
    0.26 against ``direct``; 0.16 at 1e5). The rounding of an interpolated point off its
    plane is that of the shape's coordinates along the normal: the ground's height is
    exact to far better than its width. Now ``raytraced`` equals ``direct`` at every
    size (measured: relative error < 1e-3 at 1e3-1e6)."""
    d = {"type": "scene",
         "sensor": {"type": "perspective", "fov": 60,
                    "to_world": T().look_at(origin=[0, 1, 0], target=[0, 0.8, -10],
                                            up=[0, 1, 0]),
                    "film": {"type": "hdrfilm", "width": 48, "height": 48}},
         "ground": {"type": "rectangle", "to_world": T().scale(ground).rotate([1, 0, 0], -90)},
         "sun": {"type": "directional", "direction": [1, -0.25, 0.3], "irradiance": 3.0}}
    for i in range(5):
        d[f"post{i}"] = {"type": "cube", "to_world": T().translate([-2 + i, 0.5, -3 - 2 * i])
                         @ T().scale([0.1, 0.5, 0.1])}
    scene = mi.load_dict(d)

    def render(integ):
        return np.asarray(mi.render(scene, integrator=mi.load_dict(integ), spp=16,
                                    seed=3))[..., :3]

    direct = render({"type": "direct", "emitter_samples": 1, "bsdf_samples": 0})
    ours = render({"type": "shadowmap", "method": "raytraced"})
    unshadowed = render({"type": "shadowmap", "method": "unshadowed"})
    err = float(np.sqrt(np.mean((ours - direct) ** 2)) / np.sqrt(np.mean(direct ** 2)))
    gap = float(np.sqrt(np.mean((unshadowed - direct) ** 2)) / np.sqrt(np.mean(direct ** 2)))
    print(f"ground {ground:g}: raytraced against direct {err:.2e}; the shadows {gap:.3f}")
    assert gap > 0.1 and err <= 1e-3


def test_the_reference_keeps_its_shadows_far_from_the_origin():
    """A unit-sized scene 1e5 from the origin: ``raytraced``'s visibility against its own
    at the origin. With 64 roundoffs of the coordinates as the origin offset (0.38
    units there, against a sphere of radius 0.5) it misclassified 2.15 % of the pixels,
    three times the shadow maps' 0.2-0.3 %; 16 roundoffs for meshes and spheres: 0.59 %
    (floating point at 1e5 is 0.008 units)."""
    def vis(scene):
        img = mi.render(scene, integrator=mi.load_dict({"type": "shadowmap",
                                                         "method": "raytraced"}),
                        spp=4, seed=1)
        return np.asarray(img)[..., 3]
    at_origin = vis(translated_scene(0.0))
    far = vis(translated_scene(1e5))
    wrong = float(np.mean((at_origin >= 0.5) != (far >= 0.5)))
    print(f"misclassified at 1e5 against the origin: {wrong:.2%}")
    assert (at_origin < 0.5).mean() > 0.05 and wrong < 0.01


# ------------------------------------------------ meshes Mitsuba merges (one BSDF)
def _billboard_scene(merged: bool):
    """A ground, a 1-unit post and a 20-unit billboard 40 units away under a 20-degree
    sun. With one BSDF for all three Mitsuba 3.9 merges them into one mesh whose bbox is
    the post's (the rectangles are left out), and so is ``scene.bbox()``; with another
    reflectance for the billboard it stays a shape of its own (the box then holds it)."""
    el = math.radians(20.0)

    def bsdf(v):
        return {"type": "diffuse", "reflectance": {"type": "rgb", "value": v}}
    from mi_shadowmap.scenes import camera
    return mi.load_dict({
        "type": "scene", "sensor": camera([0, 30, 60], [0, 0, -20], 48, 48, 4),
        "a_ground": {"type": "rectangle", "bsdf": bsdf(0.5),
                     "to_world": T().rotate([1, 0, 0], -90).scale(100)},
        "b_board": {"type": "rectangle", "bsdf": bsdf(0.5 if merged else 0.51),
                    "to_world": T().translate([0, 10, -40]).scale([10, 10, 1])},
        "c_post": {"type": "cube", "bsdf": bsdf(0.5),
                   "to_world": T().translate([0, 0.5, 0]).scale(0.5)},
        "sun": {"type": "directional", "direction": [0, -math.sin(el), math.cos(el)],
                "irradiance": {"type": "rgb", "value": 3.0}}})


def test_scene_bounds_hold_merged_meshes():
    """``scene_bounds`` holds every part of a merged mesh (its vertices), whatever its
    ``bbox()`` says."""
    from mi_shadowmap.light_views.base import scene_bounds
    scene = _billboard_scene(merged=True)
    lo, hi = scene_bounds(scene)
    print(f"merged: {len(scene.shapes())} shape(s), Mitsuba's bbox {scene.bbox().min} "
          f"{scene.bbox().max}, scene_bounds {lo} {hi}")
    assert np.allclose(lo, [-100, -0.01, -100], atol=0.02)
    assert np.allclose(hi, [100, 20, 100], atol=0.02)


@pytest.mark.parametrize("method", ["raytraced", "hard"])
def test_an_infinite_lights_rays_cross_the_whole_scene_with_merged_meshes(method):
    """The billboard's shadow under the sun is the same whether Mitsuba merged the
    meshes or not: ``raytraced``'s shadow rays toward an infinite emitter reach past
    the scene's real bounds (Mitsuba's ``direct`` stops them ``2 R`` away, ``R`` from
    ``scene.bbox()``: 0.34 of the image shadowed merged, 0.46 apart), and the
    directional map is fitted to the real bounds (``hard``)."""
    vis = {}
    for merged in (True, False):
        scene = _billboard_scene(merged)
        integ = mi.load_dict({"type": "shadowmap", "method": method})
        vis[merged] = np.asarray(mi.render(scene, integrator=integ, spp=4, seed=1))[..., -1]
    shadowed = {k: float(np.mean(v < 0.5)) for k, v in vis.items()}
    print(f"{method}: shadowed merged {shadowed[True]:.4f}, apart {shadowed[False]:.4f}")
    assert shadowed[False] > 0.4
    assert abs(shadowed[True] - shadowed[False]) < 0.003


def test_converged_reference_crosses_the_whole_scene_with_merged_meshes():
    from mi_shadowmap.reference import converged_visibility
    vis = {m: converged_visibility(_billboard_scene(m), n_light=4, spp=2)
           for m in (True, False)}
    shadowed = {k: float(np.mean(next(iter(v.values())) < 0.5)) for k, v in vis.items()}
    print(f"converged: shadowed merged {shadowed[True]:.4f}, apart {shadowed[False]:.4f}")
    assert shadowed[False] > 0.4
    assert abs(shadowed[True] - shadowed[False]) < 0.003


@pytest.mark.parametrize("method", ["raytraced", "hard", "second_depth"])
def test_a_far_cylinders_sunlit_side_is_lit(method):
    """Camera hits on a cylinder 225 units away lie up to 0.003 off its surface (Mitsuba's
    float32 cylinder test, radius 1.7); from inside it, shadow rays hit the post itself:
    ``raytraced`` differed from Mitsuba's ``direct`` by 11 % of the image (relative L1).
    ``second_depth`` (a non-solid's stored depth is its own, with no slope bias) read
    such points as behind the post's own depth: 24 % (the maps look up the hit found
    again too). Nothing else is in the scene, so nothing shadows it: the image equals
    ``direct``'s (same samples)."""
    scene = mi.load_dict({
        "type": "scene",
        "post": {"type": "cylinder", "p0": [0, -20, -225], "p1": [0, 20, -225],
                 "radius": 1.7},
        "sun": {"type": "directional", "direction": [0.3, -0.2, -1.0]},
        "sensor": {"type": "perspective", "fov": 1.0,
                   "to_world": mi.ScalarTransform4f().look_at([0, 0, 0], [0, 0, -1], [0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": 32, "height": 32}}})

    def render(integ):
        return np.asarray(mi.render(scene, integrator=mi.load_dict(integ), spp=16, seed=0))

    ref = render({"type": "direct", "emitter_samples": 1, "bsdf_samples": 0})
    img = render({"type": "shadowmap", "method": method})[..., :3]
    assert ref.mean() > 0.1
    assert np.abs(img - ref).mean() / ref.mean() < 1e-4


def _plates_scene(instanced: bool):
    """Two upright plates 0.01 apart (boxes 0.1 and 0.04 thick) on a ground 1e4 wide,
    under a low sun: given as shapes, or drawn through ``instance``s of one cube."""
    plates = [T().translate([0.2, 0.5, -1.2]) @ T().scale([0.8, 0.5, 0.05]),
              T().translate([0.2, 0.5, -1.12]) @ T().scale([0.6, 0.4, 0.02])]
    d = {"type": "scene",
         "sensor": {"type": "perspective", "fov": 40,
                    "to_world": T().look_at(origin=[-3, 2.5, 4], target=[0, 0.3, -0.5],
                                            up=[0, 1, 0]),
                    "film": {"type": "hdrfilm", "width": 64, "height": 64,
                             "rfilter": {"type": "box"}}},
         "ground": {"type": "rectangle", "to_world": T().rotate([1, 0, 0], -90).scale(5e3)},
         "sun": {"type": "directional", "direction": [1, -0.4, -0.6], "irradiance": 3.0}}
    if instanced:
        d["group"] = {"type": "shapegroup", "box": {"type": "cube"}}
    for k, m in enumerate(plates):
        d[f"plate{k}"] = ({"type": "instance", "shapegroup": {"type": "ref", "id": "group"},
                           "to_world": m} if instanced else {"type": "cube", "to_world": m})
    return mi.load_dict(d)


def test_instanced_receivers_take_their_instances_bounds():
    """A hit through an ``instance`` names its shape group's shape, which the offset
    table does not hold: it took the whole scene's magnitudes, so on a ground 1e4 wide a
    shadow ray from an instanced plate's side started 0.04 units off it, past a plate
    0.01 away, and ``raytraced`` lit the gap between two plates (0.44 % of this 64^2 view
    differed from the same plates given as shapes, and from ``direct``). The instance's
    own bounds now: the same visibility as the shapes'."""
    def vis(scene):
        img = mi.render(scene, integrator=mi.load_dict({"type": "shadowmap",
                                                         "method": "raytraced"}),
                        spp=4, seed=1)
        return np.asarray(img)[..., 3]
    shapes, instances = vis(_plates_scene(False)), vis(_plates_scene(True))
    differ = float(np.mean(np.abs(shapes - instances) > 0.05))
    print(f"instanced plates against shapes: {differ:.2%} of the pixels differ; "
          f"shadowed {(shapes < 0.5).mean():.2%}")
    assert (shapes < 0.5).mean() > 0.005 and differ == 0.0


def _tiny_ball_scene(radius: float, height: float, light: str):
    """A ball of ``radius`` ``height`` above a floor, a point light at twice the height
    (or the sun overhead), and a camera looking straight down at its shadow, a disc of
    radius ``2 radius`` (``radius``) that fills pi / 36 of the view."""
    shadow = 2.0 * radius if light == "point" else radius
    eye = 0.5 * height
    return mi.load_dict({
        "type": "scene",
        "floor": {"type": "rectangle", "to_world": T().rotate([1, 0, 0], -90).scale(10 * height)},
        "ball": {"type": "sphere", "center": [0, height, 0], "radius": radius},
        "light": ({"type": "point", "position": [0, 2 * height, 0], "intensity": 1.0}
                  if light == "point" else {"type": "directional", "direction": [0, -1, 0]}),
        "sensor": {"type": "perspective",
                   "fov": 2 * math.degrees(math.atan(3 * shadow / eye)),
                   "to_world": T().look_at(origin=[0, eye, 0], target=[0, 0, 0], up=[0, 0, 1]),
                   "film": {"type": "hdrfilm", "width": 32, "height": 32,
                            "rfilter": {"type": "box"}}}})


@pytest.mark.parametrize("light", ["point", "directional"])
def test_a_tiny_balls_shadow_from_far_away(light):
    """Mitsuba 3.9's sphere answers ``ray_test`` with the textbook quadratic in float32,
    which loses the radius from an origin thousands of radii away: a ball 1e-3 wide 1e4
    radii above a floor cast, in ``raytraced`` (and Mitsuba's ``direct``), a shadow 3.8x
    (sun: 4.9x) the area of its true one (33 % of this view against 8.7 %). The shadow
    ray is intersected where such spheres are (``rays.occluded``): the true disc."""
    scene = _tiny_ball_scene(1e-3, 10.0, light)
    vis = np.asarray(mi.render(scene, integrator=mi.load_dict(
        {"type": "shadowmap", "method": "raytraced"}), spp=4, seed=0))[..., 3]
    shadowed = float(np.mean(vis < 0.5))
    print(f"{light}: shadowed {shadowed:.4f}, the disc {math.pi / 36:.4f}")
    assert abs(shadowed - math.pi / 36) < 0.015


def test_occluded_is_exact_for_spheres_from_afar():
    """``rays.occluded`` against float64 for rays from 1e4 radii aimed within 1.3 radii of
    a sphere's centre (away from the outline by more than 1e-3 radii): none wrong (Mitsuba's
    ``ray_test``: about half). Beside an ``instance`` (whose shapes' hits are left to
    ``ray_test``) no shadow is lost, and no more are invented than ``ray_test`` does."""
    from mi_shadowmap.rays import occluded
    rng = np.random.default_rng(0)
    n, r = 4096, 0.01
    u = rng.normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    tgt = rng.uniform(-1.3, 1.3, size=(n, 3)) * r
    o = tgt + u * 1e4 * r
    b = np.sum(o * -u, 1)
    dist = np.sqrt(np.maximum(np.sum(o * o, 1) - b * b, 0.0))
    truth, clear = dist < r, np.abs(dist - r) > 1e-3 * r
    ray = mi.Ray3f(mi.Point3f(*[mi.Float(o[:, k]) for k in range(3)]),
                   mi.Vector3f(*[mi.Float(-u[:, k]) for k in range(3)]))
    ray.maxt = (1e4 + 3.0) * r       # ends past the ball (a third argument: the time)
    base = {"type": "scene", "ball": {"type": "sphere", "radius": r},
            "box": {"type": "cube", "to_world": T().translate([0, 200, 0])}}   # off every ray
    inst = dict(base, group={"type": "shapegroup", "c": {"type": "cube"}},
                copy={"type": "instance", "shapegroup": {"type": "ref", "id": "group"},
                      "to_world": T().translate([0, -200, 0])})
    wrong = {}
    for name, d in (("shapes", base), ("instance", inst)):
        scene = mi.load_dict(d)
        test = scene.ray_test(ray).numpy()
        ours = occluded(scene, ray).numpy()
        wrong[name] = (int(np.sum((test != truth) & clear)), int(np.sum((ours != truth) & clear)),
                       int(np.sum(~ours & truth & clear)), int(np.sum(ours & ~truth & clear)),
                       int(np.sum(test & ~truth & clear)))
    print(wrong)
    assert wrong["shapes"][0] > n // 4 and wrong["shapes"][1] == 0
    assert wrong["instance"][2] == 0 and wrong["instance"][3] <= wrong["instance"][4]


def _balls_scene(scale):
    """Three balls of radius 0.1 over a floor under a point light, each a ``sphere`` of
    radius ``0.1 / scale`` drawn through an ``instance`` scaled by ``scale`` (or, for
    ``scale`` None, given as shapes)."""
    d = {"type": "scene",
         "floor": {"type": "rectangle", "to_world": T().rotate([1, 0, 0], -90).scale(3)},
         "light": {"type": "point", "position": [2.7, 9.1, 1.8], "intensity": 100.0},
         "sensor": {"type": "perspective", "fov": 35,
                    "to_world": T().look_at(origin=[0, 3, 2.5], target=[0, 0, 0], up=[0, 1, 0]),
                    "film": {"type": "hdrfilm", "width": 48, "height": 48,
                             "rfilter": {"type": "box"}}}}
    if scale is not None:
        d["group"] = {"type": "shapegroup", "ball": {"type": "sphere", "radius": 0.1 / scale}}
    for k, (x, z) in enumerate([(-0.4, -0.3), (0.0, 0.2), (0.4, -0.1)]):
        if scale is None:
            d[f"ball{k}"] = {"type": "sphere", "radius": 0.1, "center": [x, 0.3, z]}
        else:
            d[f"ball{k}"] = {"type": "instance", "shapegroup": {"type": "ref", "id": "group"},
                             "to_world": T().translate([x, 0.3, z]) @ T().scale(scale)}
    return mi.load_dict(d)


def test_instanced_spheres_are_not_speckled():
    """Mitsuba 3.9 intersects a sphere drawn through a scaling ``instance`` with a ray
    direction that is not unit length, and its step to the plane through the centre then
    overshoots: camera hits on balls instanced at scale 0.3 lay off them, and
    ``raytraced``'s shadow rays (an offset smaller than Mitsuba's) speckled them, 5 % of
    the image off ``direct`` and off the balls given as shapes (``direct`` within 0.5 %
    of them). Such hits are found again from near them (``rays._on_cylinders``)."""
    def render(scene, integ):
        return np.asarray(mi.render(scene, integrator=mi.load_dict(integ), spp=4,
                                    seed=1))[..., :3]

    scene = _balls_scene(0.3)
    ours = render(scene, {"type": "shadowmap", "method": "raytraced"})
    direct = render(scene, {"type": "direct", "emitter_samples": 1, "bsdf_samples": 0})
    shapes = render(_balls_scene(None), {"type": "shadowmap", "method": "raytraced"})
    rel = lambda a, b: float(np.sqrt(np.mean((a - b) ** 2)) / np.sqrt(np.mean(b ** 2)))
    print(f"raytraced against direct {rel(ours, direct):.2e}, against shapes "
          f"{rel(ours, shapes):.2e}")
    assert rel(ours, direct) < 1e-3 and rel(ours, shapes) < 0.01     # before: 0.057, 0.057


@pytest.mark.parametrize("dist", [100.0, 200.0])
def test_a_thin_poles_long_shadow_in_the_reference(dist):
    """Mitsuba 3.9 intersects a cylinder in float32 in object space: a shadow ray from
    the ground ``dist`` units from a pole 0.06 wide (a sun 6 degrees high) missed it, and
    ``raytraced`` (as Mitsuba's ``direct``) lost the far part of its shadow: 3.7 % (at
    100) and 12.3 % (at 200) of this view misclassified against the same pole as a fine
    prism, of 12.5 % shadowed; ``hard`` 0.02 %. Past 100 radii the shadow ray now queries
    the maps' copy of the scene (cylinders as prisms)."""
    from mi_shadowmap import map_scene as ms
    el = math.radians(6.0)

    def scene(pole):
        return mi.load_dict({
            "type": "scene",
            "ground": {"type": "rectangle", "to_world": T().rotate([1, 0, 0], -90).scale(2000)},
            "pole": pole,
            "sun": {"type": "directional", "direction": [math.cos(el), -math.sin(el), 0.0],
                    "irradiance": 3.0},
            "sensor": {"type": "perspective", "fov": 2 * math.degrees(math.atan(0.12)),
                       "to_world": T().look_at([dist, 1, 1], [dist, 0, 0], [1, 0, 0]),
                       "film": {"type": "hdrfilm", "width": 32, "height": 32,
                                "rfilter": {"type": "box"}}}})

    cylinder = scene({"type": "cylinder", "p0": [0, 0, 0], "p1": [0, 30, 0], "radius": 0.03})
    shape = [s for s in cylinder.shapes() if s.shape_type() == mi.ShapeType.Cylinder][0]
    prism = scene(ms.cylinder_prism(shape, 2048))

    def vis(s):
        return np.asarray(mi.render(s, integrator=mi.load_dict(
            {"type": "shadowmap", "method": "raytraced"}), spp=4, seed=0))[..., -1]

    got, want = vis(cylinder), vis(prism)
    wrong = float(np.mean((got < 0.5) != (want < 0.5)))
    print(f"at {dist}: shadowed {np.mean(got < 0.5):.4f} against {np.mean(want < 0.5):.4f}, "
          f"misclassified {wrong:.4f}")
    assert np.mean(want < 0.5) > 0.08 and wrong < 0.005
    # the converged reference too (its query is prepared outside its symbolic loop)
    from mi_shadowmap.reference import converged_visibility
    conv = next(iter(converged_visibility(cylinder, n_light=2, spp=4).values()))
    assert float(np.mean((conv < 0.5) != (want < 0.5))) < 0.005


def test_shadow_rays_find_a_cylinders_hit_again_once_per_camera_hit(monkeypatch):
    """The retrace of a cylinder's camera hit (_on_cylinders, one ray_intersect) ran in
    every shadow ray's spawn: inside the light-sample loops (shadow_rays > 1, the
    converged reference's 1024 samples), once per sample and emitter. On 12 cylinders
    under an area light (128^2) the converged reference took 1.6-2x as long as without
    it, shadow_rays=16 1.5x. Now once per camera hit, the same shadow rays."""
    from mi_shadowmap import rays
    from mi_shadowmap.reference import converged_visibility
    scene = mi.load_dict({
        "type": "scene",
        "post": {"type": "cylinder", "p0": [0, -20, -225], "p1": [0, 20, -225],
                 "radius": 1.7},
        "sun": {"type": "directional", "direction": [0.3, -0.2, -1.0]},
        "sky": {"type": "directional", "direction": [-0.3, -0.2, -1.0]},
        "sensor": {"type": "perspective", "fov": 1.0,
                   "to_world": mi.ScalarTransform4f().look_at([0, 0, 0], [0, 0, -1], [0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": 8, "height": 8}}})
    calls = []
    real = rays._on_cylinders
    monkeypatch.setattr(rays, "_on_cylinders", lambda si, sc: calls.append(1) or real(si, sc))
    integ = mi.load_dict({"type": "shadowmap", "method": "raytraced", "shadow_rays": 4})
    img = np.asarray(mi.render(scene, integrator=integ, spp=2, seed=0))
    assert len(calls) == 1, len(calls)      # two emitters, four samples each
    assert img[..., 0].mean() > 0.1         # the sunlit post, lit
    calls.clear()
    vis = converged_visibility(scene, n_light=4, spp=1)
    assert len(calls) == 1, len(calls)
    assert min(float(np.mean(v)) for v in vis.values()) > 0.8   # (the post fills 0.89)


def test_a_large_cylinder_beside_a_far_thinner_one_does_not_shadow_itself():
    """A shadow ray that leaves a cylinder queried the scene itself for its first 100
    radii of the scene's smallest cylinder, the maps' copy beyond, where its own prism
    reaches r tan(pi/2n)^2 outside it: a tank 10 in radius on a 4 km ground, beside a
    wire 1e-4 in radius far away (near part 0.01 long), had rays from its sunlit side
    start inside its prism and hit it: 190 of 7797 lit pixels of a 128^2 view shadowed
    near its terminator (``raytraced`` and the converged reference; ``direct`` and
    ``hard`` lit). A ray leaving outwards now queries the scene until it is clear of
    its own prism."""
    from mi_shadowmap.reference import converged_visibility
    sun = np.array([1.0, 0.5, 0.0]) / math.sqrt(1.25)
    scene = mi.load_dict({
        "type": "scene",
        "ground": {"type": "rectangle", "to_world": T().rotate([1, 0, 0], -90).scale(2000)},
        "tank": {"type": "cylinder", "p0": [0, 0, 0], "p1": [0, 20, 0], "radius": 10.0},
        "wire": {"type": "cylinder", "p0": [300, 5, 300], "p1": [310, 5, 300], "radius": 1e-4},
        "sun": {"type": "directional", "direction": (-sun).tolist(), "irradiance": 3.0},
        "sensor": {"type": "perspective", "fov": 12,
                   "to_world": T().look_at([0, 10, -60], [0, 10, 0], [0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": 64, "height": 64,
                            "rfilter": {"type": "box"}}}})
    direct = np.asarray(mi.render(scene, integrator=mi.load_dict(
        {"type": "direct", "emitter_samples": 1, "bsdf_samples": 0}), spp=2, seed=0))[..., 0]
    got = np.asarray(mi.render(scene, integrator=mi.load_dict(
        {"type": "shadowmap", "method": "raytraced"}), spp=2, seed=0))
    lit = direct > 0.05 * direct.max()           # the tank's sunlit side (all of the view)
    assert lit.sum() > 1500
    dark = int(np.sum(lit & (got[..., 0] < 0.5 * direct)))
    conv = next(iter(converged_visibility(scene, n_light=1, spp=2).values()))
    dark_conv = int(np.sum(lit & (conv < 0.5)))
    print(f"lit {lit.sum()}: raytraced dark on {dark}, converged reference on {dark_conv}")
    assert dark == 0 and dark_conv == 0


def _hair_clump_scene(far_strand: float):
    """64 vertical strands of radius 2e-3, 5.2e-3 apart (a hair clump 0.04 wide), in one
    ``linearcurve``, under a sun 30 degrees high, seen from 0.1 away; ``far_strand`` > 0
    adds one more strand to the same curve set that far away (out of view)."""
    r, lines = 2e-3, []
    for i in range(8):
        for j in range(8):
            x, z = (i - 3.5) * 2.6 * r, (j - 3.5) * 2.6 * r
            lines += [f"{x + 0.3 * r * k / 3:.8g} {0.05 * k / 3:.8g} {z:.8g} {r}" for k in range(4)]
            lines.append("")
    if far_strand:
        lines += [f"{far_strand} {0.01 * k} 0 {r}" for k in range(4)]
    import os
    import tempfile
    path = tempfile.NamedTemporaryFile("w", suffix=".txt", delete=False)
    path.write("\n".join(lines) + "\n")
    path.close()
    el = math.radians(30.0)
    desc = {
        "type": "scene",
        "ground": {"type": "rectangle", "to_world": T().rotate([1, 0, 0], -90).scale(0.2)},
        "hair": {"type": "linearcurve", "filename": path.name},
        "sun": {"type": "directional", "direction": [math.cos(el), -math.sin(el), 0.4],
                "irradiance": 3.0},
        "sensor": {"type": "perspective", "fov": 30,
                   "to_world": T().look_at([0, 0.06, 0.08], [0, 0.025, 0], [0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": 48, "height": 48,
                            "rfilter": {"type": "box"}}}}
    try:
        return mi.load_dict(desc)
    finally:        # Mitsuba has read the strands: the file would be left in /tmp
        os.unlink(path.name)


def test_a_far_strand_does_not_light_a_hair_clump():
    """A curve shape's bounding box is its whole set of strands': one strand 1000 units
    away made the offset of every shadow ray from the clump's strands 64 ulps of 1000
    (0.004, twice their radius), past the neighbouring strands: ``raytraced`` lit 3.1 %
    of this view that it (and Mitsuba's ``direct``) shadows without that strand (64^2,
    16 spp: 2.5 %, image mean 2.1x ``direct``'s). A curve's hit is offset from its own coordinates and
    distance now: the same visibility with or without the far strand."""
    def vis(scene):
        return np.asarray(mi.render(scene, integrator=mi.load_dict(
            {"type": "shadowmap", "method": "raytraced"}), spp=4, seed=0))[..., -1]
    near, far = vis(_hair_clump_scene(0.0)), vis(_hair_clump_scene(1000.0))
    differ = float(np.mean((near < 0.5) != (far < 0.5)))
    print(f"shadowed {np.mean(near < 0.5):.4f}; with a far strand {differ:.4f} differ")
    assert np.mean(near < 0.5) > 0.5 and differ < 0.002


def _plate_far_along_x(x: float):
    """A plate 0.1 wide 0.03 above a flat ground 4 wide, both ``x`` units along the x axis
    (the ground's height, y = 0, is exact), under a sun 25 degrees high."""
    el = math.radians(25.0)
    return mi.load_dict({
        "type": "scene",
        "ground": {"type": "rectangle",
                   "to_world": T().translate([x, 0, 0]) @ T().rotate([1, 0, 0], -90).scale(2.0)},
        "plate": {"type": "rectangle", "to_world": T().translate([x, 0.03, 0])
                  @ T().rotate([1, 0, 0], -90).scale(0.05)},
        "sun": {"type": "directional", "direction": [math.cos(el), -math.sin(el), 0.0]},
        "sensor": {"type": "perspective", "fov": 25,
                   "to_world": T().look_at([x + 0.05, 0.5, 0.2], [x + 0.05, 0, 0], [1, 0, 0]),
                   "film": {"type": "hdrfilm", "width": 32, "height": 32,
                            "rfilter": {"type": "box"}}}})


@pytest.mark.parametrize("x", [1e4, 1e5])
def test_a_contact_shadow_far_along_one_axis(x):
    """The origin offset took the hit's largest coordinate, ``max|p|``: 1e5 along x put a
    shadow ray from a flat ground (its height exact, y = 0) 16 ulps of 1e5 = 0.095 above
    it, above a plate 0.03 high, whose shadow vanished (``raytraced``: 10.6 % of this view
    misclassified against the same scene at the origin, all of its shadow; 1e4: 0.0095
    above, 3.3 %). Only the rounding along the normal moves the origin off the surface: the
    coordinates weighted by the normal's components, ``|n| . |p|`` (0 here): 0 at 1e4,
    0.6 % at 1e5 (float32 spaces x by 0.008 there: the plate's edges move)."""
    def vis(scene):
        return np.asarray(mi.render(scene, integrator=mi.load_dict(
            {"type": "shadowmap", "method": "raytraced"}), spp=4, seed=0))[..., -1]
    near, far = vis(_plate_far_along_x(0.0)), vis(_plate_far_along_x(x))
    wrong = float(np.mean((near < 0.5) != (far < 0.5)))
    print(f"x={x:g}: shadowed {np.mean(near < 0.5):.4f}, misclassified {wrong:.4f}")
    assert np.mean(near < 0.5) > 0.1 and wrong < 0.015


def test_a_cylinder_hits_retrace_stays_near_it():
    """``_on_cylinders`` traces a camera hit again from ``CYLINDER_RETRACE t`` before it,
    over twice that span: ``mi.Ray3f(o, d, x)`` sets the ray's ``time``, not ``maxt``, so
    the retrace was unbounded, and a hit found inside the surface by more than that span
    (float32 in object space) was moved to the cylinder's far wall, a radius away. The
    span is now the ray's ``maxt``: such a point stays where the camera found it."""
    from mi_shadowmap import rays
    scene = mi.load_dict({
        "type": "scene",
        "post": {"type": "cylinder", "p0": [0, -20, -225], "p1": [0, 20, -225],
                 "radius": 1.7},
        "sun": {"type": "directional", "direction": [0.3, -0.2, -1.0]}})
    ray = mi.Ray3f(mi.Point3f(0, 0, 0), mi.Vector3f(0, 0, -1))
    si = scene.ray_intersect(ray)
    assert bool(si.is_valid()[0])
    near = rays._on_cylinders(si, scene)
    assert abs(float(near.z[0]) - float(si.p.z[0])) < 1e-2     # a hit on it: kept
    si.p = si.p + mi.Vector3f(0, 0, -1.0)        # 1.0 inside: more than 2 x 0.224
    si.t = si.t + 1.0
    moved = rays._on_cylinders(si, scene)
    print(f"inside point at z = {float(si.p.z[0]):.3f}, retraced to {float(moved.z[0]):.3f}")
    assert abs(float(moved.z[0]) - float(si.p.z[0])) < 1e-3      # before: the far wall
