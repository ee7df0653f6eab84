"""Built-in scenes, as Mitsuba dictionaries (no files needed).

:func:`default_scene` is the scene of the README's main command: a sphere
and a box on a ground plane under a spot light (the same layout as
``scenes_xml/spot_sphere_box.xml``). Every builder takes a uniform ``scale``
applied to geometry, lights and camera together (light intensities are
scaled by ``scale**2`` so the image stays the same), which the scale
invariance tests use. :func:`load_scene` turns any scene argument of the
harness (a loaded scene, a dict, an XML path with ``$`` parameters) into an
``mi.Scene``.
"""
from __future__ import annotations

import contextlib
import math
import os
import re
import sys

import drjit as dr
import mitsuba as mi
import numpy as np

T = mi.ScalarTransform4f


def camera(origin, target, width, height, spp, fov=40.0, scale=1.0) -> dict:
    """A perspective camera dict (box filter, independent sampler) looking from
    ``origin`` at ``target``, both multiplied by ``scale`` (clip planes too)."""
    return {
        "type": "perspective",
        "fov": fov,
        "near_clip": 1e-2 * scale,
        "far_clip": 1e4 * scale,
        "to_world": T().look_at(origin=[scale * c for c in origin],
                                target=[scale * c for c in target], up=[0, 1, 0]),
        "sampler": {"type": "independent", "sample_count": spp},
        "film": {"type": "hdrfilm", "width": width, "height": height,
                 "rfilter": {"type": "box"}},
    }


def load_scene(scene, **xml_params) -> mi.Scene:
    """An ``mi.Scene`` from a loaded scene, a scene dict, or an XML path.

    ``xml_params`` fill the file's ``$name`` parameters (e.g. ``width=64``), in it and
    in the files it ``<include>``s; a parameter that none of them uses is an error
    naming it (Mitsuba's parser finds them).
    """
    if isinstance(scene, (mi.Scene, dict)) and xml_params:
        raise ValueError("scene parameters (" + ", ".join(xml_params) + ") apply to XML "
                         "files only, not to a " + ("loaded scene" if isinstance(
                             scene, mi.Scene) else "scene dict (set them in the dict)"))
    if isinstance(scene, mi.Scene):
        return scene
    if isinstance(scene, dict):
        with _loading_threads():
            return mi.load_dict(scene)
    if not isinstance(scene, (str, bytes, os.PathLike)):
        other = scene_variant(scene)
        if other is not None:      # os.fspath said "expected str ..., not Scene"
            raise ValueError(
                f"the scene was loaded in Mitsuba variant '{other}', but the current "
                f"variant is '{mi.variant()}': load it again in '{mi.variant()}', or "
                f"call mi.set_variant('{other}') before using it")
        raise TypeError(f"a scene is an mi.Scene, a scene dict or the path of an XML "
                        f"file, not {type(scene).__name__}")
    path = os.fspath(scene)
    if not os.path.isfile(path):
        raise FileNotFoundError(f"scene file not found: {path}")
    try:
        with _loading_threads():
            return mi.load_file(path, **{k: str(v) for k, v in xml_params.items()})
    except RuntimeError as e:
        # Mitsuba's parser names the parameters no file of the scene (its <include>d
        # files too, resolved as Mitsuba resolves them) refers to: "Found unused
        # parameters:\n  - $width=64"
        if "unused parameters" not in str(e):
            raise
        missing = [k for k in xml_params if re.search(rf"^\s*- \${re.escape(k)}=", str(e),
                                                      re.MULTILINE)] or list(xml_params)
        raise ValueError(f"scene file {path} has no parameter "
                         + ", ".join(f"${k}" for k in missing)
                         + " (neither it nor the files it includes use it; declare "
                           "<default name=... value=.../> and use $name to make it "
                           "settable)") from None


@contextlib.contextmanager
def _loading_threads():
    """Two Dr.Jit threads while Mitsuba loads a scene, where the user set one
    (``dr.set_thread_count(1)``, a setting users debug with), restored after: Mitsuba
    3.9.1 reads EXR textures (an ``envmap``, a ``bitmap``) through tasks on that pool,
    and with one thread it waits for them forever (loading ``scenes_xml/sky_sun.xml``
    never returned). The renders still run on the one thread the user asked for."""
    one = dr.thread_count() == 1
    if one:
        dr.set_thread_count(2)
    try:
        yield
    finally:
        if one:
            dr.set_thread_count(1)


def scene_variant(obj) -> str | None:
    """The Mitsuba variant whose ``Scene`` class ``obj`` is an instance of, among the
    variants imported in this process; None for anything else."""
    for variant in mi.variants():
        module = sys.modules.get(f"mitsuba.{variant}")
        cls = getattr(module, "Scene", None) if module is not None else None
        if isinstance(cls, type) and isinstance(obj, cls):
            return variant
    return None


def integrator_properties(scene) -> tuple[dict | None, str | None]:
    """The properties given to ``scene``'s own integrator, if it is ``shadowmap`` (an
    XML ``<integrator type="shadowmap">``): ``(properties, None)``, ``method``
    included, values as validated (``resolution`` 0, automatic, left out). For a scene
    whose integrator is another one: ``(None, its class name)``; without one:
    ``(None, None)``. The CLI takes them as the base of every method's properties."""
    integrator = scene.integrator() if isinstance(scene, mi.Scene) else None
    if integrator is None:
        return None, None
    opts = getattr(integrator, "opts", None)
    if opts is None or not hasattr(opts, "given"):
        return None, integrator.class_name()
    values = opts.as_dict()
    return {k: values[k] for k in sorted(opts.given)
            if k in values and values[k] is not None}, None


def mesh(name: str, vertices, faces, to_world=None, bsdf: dict | None = None) -> mi.Mesh:
    """A ``mi.Mesh`` from numpy ``vertices`` ``(V, 3)`` and ``faces`` ``(F, 3)``
    (e.g. :func:`mi_shadowmap.procedural.box`), placed by ``to_world`` (a
    ``mi.ScalarTransform4f``); usable as a value of a ``mi.load_dict`` scene,
    and its ``vertex_positions`` can be optimised (``mi.traverse``)."""
    v = np.asarray(vertices, dtype=np.float64)
    if to_world is not None:
        m = np.array(to_world.matrix, dtype=np.float64)
        v = v @ m[:3, :3].T + m[:3, 3]
    f = np.asarray(faces, dtype=np.uint32)
    out = mi.Mesh(name, vertex_count=len(v), face_count=len(f), has_vertex_normals=False)
    params = mi.traverse(out)
    params["vertex_positions"] = dr.ravel(mi.Point3f(v.T.astype(np.float32)))
    params["faces"] = dr.ravel(mi.Vector3u(f.T))
    params.update()
    if bsdf is not None:
        out.set_bsdf(mi.load_dict(bsdf))
    return out


def _diffuse(r, g, b):
    return {"type": "diffuse", "reflectance": {"type": "rgb", "value": [r, g, b]}}


def default_scene(scale: float = 1.0, width: int = 128, height: int = 128, spp: int = 16,
                  light: str = "spot") -> dict:
    """Sphere and box on a ground plane, lit by one ``light``.

    ``light`` is 'spot' (default), 'point', 'directional' or 'area' (a
    0.6-unit square area light).
    """
    S = T().scale(scale)
    scene = {
        "type": "scene",
        "sensor": camera([0.2, 3.5, 4.9], [0.25, 0.25, 0.0], width, height, spp, scale=scale),
        "ground": {"type": "rectangle", "to_world": S @ T().rotate([1, 0, 0], -90).scale(4),
                   "bsdf": _diffuse(0.7, 0.7, 0.7)},
        "sphere": {"type": "sphere",
                   "to_world": S @ T().translate([-0.85, 0.65, -0.6]).scale(0.65),
                   "bsdf": _diffuse(0.75, 0.25, 0.2)},
        "box": {"type": "cube",
                "to_world": S @ T().translate([0.85, 0.5, -0.5]).rotate([0, 1, 0], 30).scale(0.5),
                "bsdf": _diffuse(0.2, 0.4, 0.75)},
    }
    origin, target = [-2.4, 4.0, -3.4], [0.2, 0.0, 0.3]
    if light == "spot":
        scene["spot"] = {"type": "spot", "to_world": S @ T().look_at(origin=origin, target=target,
                                                                    up=[0, 1, 0]),
                         "intensity": {"type": "rgb", "value": 120.0 * scale**2},
                         "cutoff_angle": 35.0, "beam_width": 28.0}
    elif light == "point":
        scene["point"] = {"type": "point", "position": [scale * c for c in origin],
                          "intensity": {"type": "rgb", "value": 60.0 * scale**2}}
    elif light == "directional":
        scene["sun"] = {"type": "directional",
                        "direction": [t - o for t, o in zip(target, origin)],
                        "irradiance": {"type": "rgb", "value": 3.0}}
    elif light == "area":
        scene["area"] = {"type": "rectangle",
                         "to_world": S @ T().look_at(origin=origin, target=target,
                                                     up=[0, 1, 0]).scale(0.3),
                         "emitter": {"type": "area",
                                     "radiance": {"type": "rgb", "value": 40.0}}}
    else:
        raise ValueError(f"default_scene: light={light!r}; valid: spot, point, directional, area")
    return scene


# ------------------------------------------------- random scenes (issue 11's kinds)
def _placed(rng, yaw: float, fov: float, dist: float, spread: float):
    """A ground point ``dist`` from the origin within ``spread`` half-fields of view of
    the heading ``yaw`` (radians)."""
    a = yaw + rng.uniform(-spread, spread) * math.radians(fov) / 2
    return dist * math.sin(a), -dist * math.cos(a)


def random_large_world(seed: int, width: int = 128, height: int | None = None,
                       spp: int = 16) -> dict:
    """A random scene like issue 11's large world (``scenes_xml/large_world.xml`` is
    one): a 4 km x 4 km ground under a sun 8-40 degrees high from any azimuth, seen
    from eye height (1.4-2.2) with a field of view of 45-75 degrees, 2-8 degrees
    below the horizon, in any heading; 4 thin posts 2-7 away (square or round: cubes or
    cylinders, as chance has it), 6 boxes or spheres
    8-80 away, 5 buildings 100-1500 away, all in or near the view. The same ``seed``
    gives the same scene (numpy's ``default_rng``). For checking that results hold
    beyond the repository's scenes (``benchmarks/bench_unseen.py``)."""
    rng = np.random.default_rng(seed)
    yaw = rng.uniform(0, 2 * math.pi)
    h, pitch = rng.uniform(1.4, 2.2), math.radians(rng.uniform(2, 8))
    fov = rng.uniform(45, 75)
    target = [20 * math.sin(yaw) * math.cos(pitch), h - 20 * math.sin(pitch),
              -20 * math.cos(yaw) * math.cos(pitch)]
    elev, az = math.radians(rng.uniform(8, 40)), rng.uniform(0, 2 * math.pi)
    scene = {
        "type": "scene",
        "sensor": camera([0.0, h, 0.0], target, width, height or width, spp, fov=fov),
        "ground": {"type": "rectangle", "to_world": T().scale(2000).rotate([1, 0, 0], -90),
                   "bsdf": _diffuse(0.55, 0.52, 0.45)},
        "sun": {"type": "directional",
                "direction": [-math.cos(elev) * math.cos(az), -math.sin(elev),
                              -math.cos(elev) * math.sin(az)],
                "irradiance": {"type": "rgb", "value": 3.0}},
    }
    # posts: square (cube) or round (cylinder), drawn from a stream of their own so the
    # scene is otherwise the one the seed gave before round posts existed
    round_posts = np.random.default_rng([seed, 1]).random(4) < 0.5
    for k, dist in enumerate(rng.uniform(2, 7, 4)):
        x, z = _placed(rng, yaw, fov, dist, 0.9)
        w, hh = rng.uniform(0.03, 0.08), rng.uniform(0.6, 1.5)
        scene[f"post_{k}"] = (
            {"type": "cylinder", "p0": [x, 0.0, z], "p1": [x, 2 * hh, z], "radius": w,
             "bsdf": _diffuse(0.8, 0.8, 0.8)} if round_posts[k] else
            {"type": "cube", "bsdf": _diffuse(0.8, 0.8, 0.8),
             "to_world": T().translate([x, hh, z]).scale([w, hh, w])})
    for k, dist in enumerate(rng.uniform(8, 80, 6)):
        x, z = _placed(rng, yaw, fov, dist, 0.9)
        r, sphere, turn = rng.uniform(0.3, 2.0), rng.random() < 0.5, rng.uniform(0, 90)
        scene[f"object_{k}"] = (
            {"type": "sphere", "center": [x, r, z], "radius": r, "bsdf": _diffuse(0.7, 0.3, 0.2)}
            if sphere else
            {"type": "cube", "bsdf": _diffuse(0.2, 0.3, 0.7),
             "to_world": T().translate([x, r, z]).rotate([0, 1, 0], turn).scale(r)})
    for k, dist in enumerate(rng.uniform(100, 1500, 5)):
        x, z = _placed(rng, yaw, fov, dist, 1.0)
        w, hh, turn, deep = (rng.uniform(10, 60), rng.uniform(10, 120), rng.uniform(0, 90),
                             rng.uniform(0.5, 2))
        scene[f"building_{k}"] = {"type": "cube", "bsdf": _diffuse(0.7, 0.68, 0.62),
                                  "to_world": T().translate([x, hh, z]).rotate([0, 1, 0], turn)
                                  .scale([w, hh, w * deep])}
    return scene


def random_far_point(seed: int, distance: float = 1e5, width: int = 128,
                     height: int | None = None, spp: int = 16) -> dict:
    """A random scene like issue 11's far point light (``scenes_xml/far_point.xml`` is
    one): a 12 x 12 ground with 4 boxes (flattened, up to 3 times as tall as wide)
    and 4 spheres (some floating), lit by a point light ``distance`` away at 25-75
    degrees of elevation from any azimuth (intensity ``3 distance^2``: the ground's
    irradiance stays about 3), seen from 8-14 away and 3-8 high with a field of view
    of 35-60 degrees. The same ``seed`` gives the same layout at every ``distance``."""
    if not (isinstance(distance, (int, float)) and math.isfinite(distance) and distance > 0):
        raise ValueError(f"random_far_point: distance must be a finite number > 0, got "
                         f"{distance!r}")
    rng = np.random.default_rng(seed)
    elev, az = math.radians(rng.uniform(25, 75)), rng.uniform(0, 2 * math.pi)
    position = [distance * math.cos(elev) * math.cos(az), distance * math.sin(elev),
                distance * math.cos(elev) * math.sin(az)]
    turn, r = rng.uniform(0, 2 * math.pi), rng.uniform(8, 14)
    origin = [r * math.cos(turn), rng.uniform(3, 8), r * math.sin(turn)]
    scene = {
        "type": "scene",
        "sensor": camera(origin, [0.0, 0.5, 0.0], width, height or width, spp,
                         fov=rng.uniform(35, 60)),
        "ground": {"type": "rectangle", "to_world": T().scale(6).rotate([1, 0, 0], -90),
                   "bsdf": _diffuse(0.5, 0.5, 0.5)},
        "light": {"type": "point", "position": position,
                  "intensity": {"type": "rgb", "value": 3.0 * distance ** 2}},
    }
    for k in range(8):
        x, z = rng.uniform(-4, 4, 2)
        s = rng.uniform(0.15, 0.9)
        if k % 2:
            scene[f"sphere_{k // 2}"] = {"type": "sphere", "radius": s,
                                         "center": [x, s + rng.uniform(0, 1), z],
                                         "bsdf": _diffuse(0.7, 0.3, 0.2)}
        else:
            turn, tall = rng.uniform(0, 90), rng.uniform(0.5, 3)
            scene[f"box_{k // 2}"] = {"type": "cube", "bsdf": _diffuse(0.2, 0.3, 0.7),
                                      "to_world": T().translate([x, s, z]).rotate([0, 1, 0], turn)
                                      .scale([s, s * tall, s * 0.3])}
    return scene


_PRIMITIVES = ("sphere", "cylinder", "disk", "rectangle", "cube")


def _primitive(kind: str, p, size: float, turn: float, colour) -> dict:
    """A Mitsuba primitive of ``kind`` standing on the ground point ``p`` (``size`` its
    scale; a disk a round sign and a rectangle a two-sided panel, both upright)."""
    x, y, z = p
    bsdf = _diffuse(*colour)
    if kind == "sphere":
        return {"type": "sphere", "center": [x, y + size, z], "radius": size, "bsdf": bsdf}
    if kind == "cylinder":
        return {"type": "cylinder", "p0": [x, y - 0.2 * size, z], "p1": [x, y + 3 * size, z],
                "radius": 0.3 * size, "bsdf": bsdf}
    if kind == "disk":
        return {"type": "disk", "bsdf": bsdf, "to_world": T().translate([x, y + 2 * size, z])
                .rotate([0, 1, 0], turn).scale(size)}
    if kind == "rectangle":
        return {"type": "rectangle", "bsdf": {"type": "twosided", "bsdf": bsdf},
                "to_world": T().translate([x, y + size, z]).rotate([0, 1, 0], turn)
                .scale([1.5 * size, size, 1])}
    return {"type": "cube", "bsdf": bsdf, "to_world": T().translate([x, y + size, z])
            .rotate([0, 1, 0], turn).scale([size, size, 0.6 * size])}


def random_terrain_world(seed: int, width: int = 128, height: int | None = None,
                         spp: int = 16, cells: int = 200) -> dict:
    """A random large world of the kinds issue 11's targets will be checked on beyond
    :func:`random_large_world`: a 4 km terrain mesh (gentle hills up to 25 units high
    and ripples up to a unit, on a grid of ``cells`` squared cells graded from 0.08
    units wide at the camera to 44 at the edges), a sun 2-5 degrees high, 8-40 or
    80-89.5 (``seed % 3`` = 0, 1, 2), seen from eye height (1.4-2.2, 2-8 degrees down),
    from a hill (25-80 up, 10-30 degrees down) or looking 15-35 degrees up at a tower
    20-50 away with a ledge (``seed // 3 % 3`` = 0, 1, 2: any 9 consecutive seeds hold
    every pair); 5 objects 2-7 away, 6 at 8-80, 5 buildings at 100-1500, the near and
    middle ones Mitsuba primitives (sphere, cylinder, disk, rectangle, cube) or, in
    half the seeds (drawn), some of them ``instance``s of a box and a rock mesh. The
    same ``seed`` gives the same scene (``benchmarks/bench_unseen.py --kinds
    terrain``)."""
    from .procedural import box, rock
    rng = np.random.default_rng(seed)
    # (random draws of the sun and the view gave seeds 0-10 no low sun)
    sun, view, instanced = seed % 3, (seed // 3) % 3, bool(rng.random() < 0.5)
    waves = [(rng.uniform(300, 1500), rng.uniform(0, 2 * math.pi), rng.uniform(0, math.pi),
              rng.uniform(5, 25)) for _ in range(4)]
    waves += [(rng.uniform(20, 80), rng.uniform(0, 2 * math.pi), rng.uniform(0, math.pi),
               rng.uniform(0.2, 1.0)) for _ in range(3)]

    def ground(x, z):
        x, z = np.asarray(x, np.float64), np.asarray(z, np.float64)
        return sum(a * (np.sin(2 * math.pi * (x * math.cos(t) + z * math.sin(t)) / lam + ph)
                        - math.sin(ph)) for lam, ph, t, a in waves)

    u = np.linspace(-1.0, 1.0, cells + 1)
    xs = 2000.0 * np.sign(u) * np.abs(u) ** 2.2
    X, Z = np.meshgrid(xs, xs, indexing="ij")
    idx = np.arange((cells + 1) ** 2).reshape(cells + 1, cells + 1)
    a, b, c, d = (idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, :-1].ravel(),
                  idx[1:, 1:].ravel())
    yaw = rng.uniform(0, 2 * math.pi)
    fwd = np.array([math.sin(yaw), 0.0, -math.cos(yaw)])
    fov = rng.uniform(45, 75)
    rise, pitch, near = ((rng.uniform(1.4, 2.2), -rng.uniform(2, 8), 2.0),
                         (rng.uniform(25, 80), -rng.uniform(10, 30), 2.0),
                         (1.7, rng.uniform(15, 35), 2.0))[view]
    origin = np.array([0.0, rise, 0.0])
    pitch = math.radians(pitch)
    target = origin + 20 * (fwd * math.cos(pitch) + np.array([0, math.sin(pitch), 0]))
    elev = math.radians((rng.uniform(2, 5), rng.uniform(8, 40), rng.uniform(80, 89.5))[sun])
    az = rng.uniform(0, 2 * math.pi)
    scene = {
        "type": "scene",
        "sensor": camera(origin.tolist(), target.tolist(), width, height or width, spp,
                         fov=fov),
        "ground": mesh("terrain", np.stack([X, ground(X, Z), Z], -1).reshape(-1, 3),
                       np.concatenate([np.stack([a, b, c], 1), np.stack([c, b, d], 1)]),
                       bsdf=_diffuse(0.55, 0.52, 0.45)),
        "sun": {"type": "directional",
                "direction": [-math.cos(elev) * math.cos(az), -math.sin(elev),
                              -math.cos(elev) * math.sin(az)],
                "irradiance": {"type": "rgb", "value": 3.0}},
    }

    def place(dist, spread=0.9):
        ang = yaw + rng.uniform(-spread, spread) * math.radians(fov) / 2
        x, z = dist * math.sin(ang), -dist * math.cos(ang)
        return [x, float(ground(x, z)), z]

    if instanced:
        bv, bf, _ = box((1.0, 1.0, 1.0))
        rv, rf, _ = rock((0.0, 0.0, 0.0), 1.0, rng)
        scene["post_group"] = {"type": "shapegroup", "post": mesh(
            "post", bv, bf, bsdf=_diffuse(0.8, 0.8, 0.8))}
        scene["rock_group"] = {"type": "shapegroup", "rock": mesh(
            "rock", rv, rf, bsdf=_diffuse(0.6, 0.5, 0.4))}
    for k, dist in enumerate(rng.uniform(near, near + 5, 5)):
        p = place(dist)
        if instanced and k % 2 == 0:
            w, h = rng.uniform(0.03, 0.1), rng.uniform(0.6, 1.5)
            scene[f"near_{k}"] = {"type": "instance",
                                  "shape": {"type": "ref", "id": "post_group"},
                                  "to_world": T().translate([p[0], p[1] + h, p[2]])
                                  .scale([w, h, w])}
        else:
            scene[f"near_{k}"] = _primitive(_PRIMITIVES[k], p, rng.uniform(0.1, 0.5),
                                            rng.uniform(0, 180), (0.7, 0.3, 0.2))
    for k, dist in enumerate(rng.uniform(8, 80, 6)):
        p = place(dist)
        if instanced and k % 2:
            r = rng.uniform(0.5, 2.5)
            scene[f"middle_{k}"] = {"type": "instance",
                                    "shape": {"type": "ref", "id": "rock_group"},
                                    "to_world": T().translate([p[0], p[1] + 0.3 * r, p[2]])
                                    .rotate([0, 1, 0], rng.uniform(0, 360)).scale(r)}
        else:
            scene[f"middle_{k}"] = _primitive(_PRIMITIVES[rng.integers(5)], p,
                                              rng.uniform(0.3, 2.0), rng.uniform(0, 180),
                                              (0.2, 0.3, 0.7))
    for k, dist in enumerate(rng.uniform(100, 1500, 5)):
        p = place(dist, 1.0)
        w, h = rng.uniform(10, 60), rng.uniform(10, 120)
        scene[f"building_{k}"] = {"type": "cube", "bsdf": _diffuse(0.7, 0.68, 0.62),
                                  "to_world": T().translate([p[0], p[1] + h - 2, p[2]])
                                  .rotate([0, 1, 0], rng.uniform(0, 90)).scale([w, h, w])}
    if view == 2:
        dist = rng.uniform(20, 50)
        x, z = dist * fwd[0], dist * fwd[2]
        y, h, turn = float(ground(x, z)), rng.uniform(30, 80), rng.uniform(0, 90)
        scene["tower"] = {"type": "cube", "bsdf": _diffuse(0.6, 0.6, 0.6),
                          "to_world": T().translate([x, y + h - 1, z]).rotate([0, 1, 0], turn)
                          .scale([4, h, 4])}
        scene["ledge"] = {"type": "cube", "bsdf": _diffuse(0.5, 0.5, 0.5),
                          "to_world": T().translate([x, y + 0.4 * h, z])
                          .rotate([0, 1, 0], rng.uniform(0, 90)).scale([6, 0.3, 6])}
    return scene
