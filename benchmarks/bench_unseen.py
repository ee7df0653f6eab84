"""Issue 11's accuracy and texel targets on random scenes of its two kinds, not the
repository's. One run, by hand:

    python benchmarks/bench_unseen.py [--seeds 8] [--first-seed 0] [--image 128] [--spp 16]
                                      [--kinds world 1e5 1e6 terrain] [--methods hard pcf]
                                      [--texels-only] [--texel-image 256] [--virtual-only]

``--first-seed``: run seeds ``first .. first + seeds - 1`` (the unseen worlds beyond the
default 0-7, e.g. ``--kinds terrain --first-seed 8 --seeds 22``).

For each kind and seed, :func:`mi_shadowmap.scenes.random_large_world` (``world``),
:func:`mi_shadowmap.scenes.random_terrain_world` (``terrain``: a terrain mesh, the sun
low, midway or nearly overhead, the camera at eye height, on a hill or looking up at a
tower, primitives and instances; not run unless asked) or
:func:`mi_shadowmap.scenes.random_far_point` at that distance (``1e5``, ``1e6``): every
method at defaults (nothing but the method given; the scene loaded afresh per method, so
each builds its own first frame) against ``raytraced`` with the same seed, misclassified
at threshold 0.5 (false lit / false shadow), and texels built per film pixel in that
first frame. ``rt noise`` is ``raytraced`` with another seed against the same reference:
how much the reference itself misclassifies from its camera samples alone.

``--texels-only``: no reference and no misclassified, only each method's texels per film
pixel, rendered at 1 spp (the mark pass reads the pixels' centres, so the texels do not
depend on the spp): a scan of many seeds at 256^2 for the texel target.

Local-light kinds (``--kinds spot area sphere_light room mixed scale_1e-3 scale_1e4
feature``, each run alone; :func:`random_local_lights`): spots narrow, wide, over 80
degrees (a cube map) or grazing the ground; one-sided rectangle and disk lights, small
and large; sphere lights; a point light 0.02-0.3 from a closed room's ceiling, wall or a
box top; 2-4 lights of mixed types, and that scene scaled by 1e-3 and 1e4; ``feature``
(``seed % 9``, ``FEATURE_KINDS``): instances of a shapegroup, an open PLY mesh light, a
strip light 2-6 long and 0.02-0.1 wide, a sun through a closed room's window, hair-like
``linearcurve`` strands, two lights at one position, a sun along an axis, a thin-lens
or an orthographic camera (the mesh and curve files are written to the temporary
directory). Each method on
virtual maps (defaults) and on full maps (``virtual=false``) at the automatic resolution
and at the largest power of two whose faces hold no more texels than the virtual map
built (equal texels), against ``raytraced`` (16 shadow rays a sample under area lights)
over every light's pixels (each light's in brackets), with the reference's own seed
noise, the virtual map's texels per film pixel at ``--image`` and at ``--texel-image``
(1 spp), non-finite values and the warnings raised. ``--virtual-only``: no full maps (a
sweep of many seeds at defaults).

Targets (issue 11, defaults only): misclassified <= 1 % on the large world (both
kinds), <= 0.3 % under the point light 1e5 and 1e6 away; <= 8 texels per film pixel per
light in the first frame at a 256^2 film.
"""
from __future__ import annotations

import argparse
import atexit
import math
import os
import tempfile
import time
import warnings

import mi_shadowmap  # noqa: F401  (LLVM set-up, registration)
import mitsuba as mi
import numpy as np

from mi_shadowmap import procedural
from mi_shadowmap.metrics import misclassified
from mi_shadowmap.scenes import (_diffuse, camera, random_far_point, random_large_world,
                                 random_terrain_world)
from mi_shadowmap.specs import parse_assignments

TARGET = {"world": 0.01, "terrain": 0.01, "1e5": 0.003, "1e6": 0.003}
T = mi.ScalarTransform4f


# ------------------------------------------- local lights (spot, area, near point, mixed)
LOCAL_KINDS = ("spot", "area", "sphere_light", "room", "mixed", "scale_1e-3", "scale_1e4",
               "feature")
SPOT_KINDS = ("narrow", "wide", "cube", "grazing")
AREA_KINDS = ("rectangle small", "rectangle large", "disk small", "disk large")
ROOM_KINDS = ("under the ceiling", "beside a wall", "over a box")
MIXED_TYPES = ("spot", "point", "rectangle", "disk", "sphere", "sun")
FEATURE_KINDS = ("instances", "mesh light", "strip light", "window", "curves", "twin lights",
                 "axis sun", "thinlens", "orthographic")


def _look(origin, target):
    up = [0, 0, 1] if abs(target[0] - origin[0]) + abs(target[2] - origin[2]) < 1e-9 * (
        1 + abs(target[1] - origin[1])) else [0, 1, 0]
    return T().look_at(origin=origin, target=target, up=up)


def _spot(rng, sub: str, s: float) -> dict:
    """A spot light of kind ``sub`` (``SPOT_KINDS``) at scale ``s``: its intensity gives
    the point it aims at an irradiance of about 3."""
    aim = [rng.uniform(-2, 2), 0.0, rng.uniform(-2, 2)]
    if sub == "grazing":      # 0.3-1.5 over the ground, 5-8 away: 3-17 degrees to the floor
        a, d = rng.uniform(0, 2 * math.pi), rng.uniform(5, 8)
        origin = [d * math.cos(a), rng.uniform(0.3, 1.5), d * math.sin(a)]
        aim = [-0.5 * origin[0], 0.0, -0.5 * origin[2]]
        cutoff = rng.uniform(20, 45)
    else:
        origin = [rng.uniform(-4, 4), rng.uniform(4, 9), rng.uniform(-4, 4)]
        cutoff = {"narrow": rng.uniform(5, 15), "wide": rng.uniform(50, 75),
                  "cube": rng.uniform(80, 89)}[sub]
    d2 = sum((o - t) ** 2 for o, t in zip(origin, aim))
    return {"type": "spot", "cutoff_angle": cutoff, "beam_width": 0.75 * cutoff,
            "to_world": _look([s * c for c in origin], [s * c for c in aim]),
            "intensity": {"type": "rgb", "value": 3.0 * d2 * s * s}}


def _area(rng, shape: str, size: float, s: float) -> dict:
    """A one-sided ``shape`` ('rectangle', 'disk' or 'sphere') area light ``size`` wide
    (a sphere: its radius), 2.5-7 over the ground, facing the scene, tilted up to 50
    degrees: about 3 of irradiance under it."""
    p = [rng.uniform(-3, 3), rng.uniform(2.5, 7), rng.uniform(-3, 3)]
    if shape == "sphere":
        area, light = math.pi * size * size, {"type": "sphere", "center": [s * c for c in p],
                                              "radius": s * size}
    else:
        tilt = math.radians(rng.uniform(0, 50))
        a = rng.uniform(0, 2 * math.pi)
        aim = [p[0] + p[1] * math.tan(tilt) * math.cos(a), 0.0,
               p[2] + p[1] * math.tan(tilt) * math.sin(a)]
        half = 0.5 * size
        area = 4 * half * half if shape == "rectangle" else math.pi * half * half
        light = {"type": shape, "to_world": _look([s * c for c in p], [s * c for c in aim])
                 @ T().scale(s * half)}
    light["emitter"] = {"type": "area", "radiance": {"type": "rgb",
                                                     "value": 3.0 * p[1] ** 2 / area}}
    return light


def _props(rng, scene: dict, s: float, extent: float = 4.0):
    """Boxes, spheres (some floating), a post and a floating plate on the ground."""
    for k in range(3):
        x, z = rng.uniform(-extent, extent, 2)
        w, h, turn = rng.uniform(0.2, 0.8), rng.uniform(0.3, 2.0), rng.uniform(0, 90)
        scene[f"box_{k}"] = {"type": "cube", "bsdf": _diffuse(0.2, 0.3, 0.7),
                             "to_world": T().scale(s).translate([x, h, z])
                             .rotate([0, 1, 0], turn).scale([w, h, 0.6 * w])}
    for k in range(3):
        x, z = rng.uniform(-extent, extent, 2)
        r = rng.uniform(0.15, 0.7)
        scene[f"sphere_{k}"] = {"type": "sphere", "radius": s * r, "bsdf": _diffuse(0.7, 0.3, 0.2),
                                "center": [s * x, s * (r + rng.uniform(0, 1.2)), s * z]}
    x, z = rng.uniform(-extent, extent, 2)
    scene["post"] = {"type": "cylinder", "p0": [s * x, 0.0, s * z], "radius": s * 0.06,
                     "p1": [s * x, s * rng.uniform(1, 2.5), s * z],
                     "bsdf": _diffuse(0.8, 0.8, 0.8)}
    x, z = rng.uniform(-extent, extent, 2)
    scene["plate"] = {"type": "rectangle", "bsdf": {"type": "twosided",
                                                    "bsdf": _diffuse(0.6, 0.6, 0.3)},
                      "to_world": T().scale(s).translate([x, rng.uniform(0.2, 1.5), z])
                      .rotate([0, 1, 0], rng.uniform(0, 90)).rotate([1, 0, 0], 90)
                      .scale(rng.uniform(0.3, 0.8))}


def _room(rng, sub: str, width: int, spp: int) -> dict:
    """A closed 8 x 4 x 8 room (two-sided walls) with a point light near its geometry."""
    scene = {"type": "scene",
             "room": {"type": "cube", "to_world": T().translate([0, 2, 0]).scale([4, 2, 4]),
                      "bsdf": {"type": "twosided", "bsdf": _diffuse(0.6, 0.6, 0.6)}}}
    _props(rng, scene, 1.0, 3.0)
    scene["plate"]["to_world"] = T().translate([rng.uniform(-2, 2), rng.uniform(0.2, 1.5),
                                                rng.uniform(-2, 2)]).rotate([1, 0, 0], 90) \
        .scale(0.5)
    gap = rng.uniform(0.02, 0.3)
    if sub == "under the ceiling":
        p = [rng.uniform(-3, 3), 4 - gap, rng.uniform(-3, 3)]
    elif sub == "beside a wall":
        p = [4 - gap, rng.uniform(0.5, 3.5), rng.uniform(-3, 3)]
    else:
        box = scene["box_0"]["to_world"]
        top = box @ mi.ScalarPoint3f(0, 1, 0)
        p = [float(top[0]), float(top[1]) + gap, float(top[2])]
    scene["light"] = {"type": "point", "position": p,
                      "intensity": {"type": "rgb", "value": 12.0}}
    a = rng.uniform(0, 2 * math.pi)
    origin = [3.5 * math.cos(a), rng.uniform(1.2, 3.5), 3.5 * math.sin(a)]
    scene["sensor"] = camera(origin, [0.0, 1.0, 0.0], width, width, spp,
                             fov=rng.uniform(60, 80))
    return scene


def _sun(direction) -> dict:
    return {"type": "directional", "irradiance": {"type": "rgb", "value": 3.0},
            "direction": list(direction)}


_SCRATCH: set = set()     # the feature files this process wrote (removed at its exit)


def _scratch_file(name: str) -> str:
    """A path in the temporary directory for a feature's mesh or curve file, removed
    when the process exits."""
    path = os.path.join(tempfile.gettempdir(), f"mi_shadowmap_unseen_{os.getpid()}_{name}")
    _SCRATCH.add(path)
    return path


@atexit.register
def _remove_scratch():
    for path in _SCRATCH:
        try:
            os.remove(path)
        except OSError:
            pass


def _strands(rng, path: str):
    """30-60 ``linearcurve`` strands, 1-2.5 high, in ``path`` (x y z radius lines)."""
    with open(path, "w") as fh:
        for _ in range(int(rng.integers(30, 61))):
            x, z = rng.uniform(-3, 3, 2)
            h, bend, phase = rng.uniform(1, 2.5), rng.uniform(0.05, 0.3), rng.uniform(0, 6)
            for j in range(6):
                fh.write(f"{x + bend * math.sin(j + phase):.5f} {0.02 + h * j / 5:.5f} "
                         f"{z + bend * math.cos(1.3 * j + phase):.5f} 0.03\n")
            fh.write("\n")


def _window_room(rng, scene: dict):
    """The props' scene closed into an 8 x 3 x 8 room (two-sided walls, a roof) whose -x
    wall has a window 2-4 wide and 0.8-1.6 high: the only way in for a sun from -x."""
    del scene["post"], scene["plate"]
    two = {"type": "twosided", "bsdf": _diffuse(0.6, 0.6, 0.6)}

    def wall(name, centre, turn, half):
        scene[name] = {"type": "rectangle", "bsdf": two, "to_world": T().translate(centre)
                       .rotate([0, 1, 0], turn).scale([half[0], half[1], 1])}
    scene["roof"] = {"type": "rectangle", "bsdf": two,
                     "to_world": T().translate([0, 3, 0]).rotate([1, 0, 0], 90).scale(4)}
    wall("wall_x", [4, 1.5, 0], -90, [4, 1.5])
    wall("wall_z", [0, 1.5, 4], 180, [4, 1.5])
    wall("wall_mz", [0, 1.5, -4], 0, [4, 1.5])
    w, h = rng.uniform(1, 2), rng.uniform(0.4, 0.8)
    z0, y0 = rng.uniform(-1.5, 1.5), rng.uniform(0.6 + h, 2.2 - h)
    for name, (z_lo, z_hi, y_lo, y_hi) in {"w_left": (-4, z0 - w, 0, 3),
                                           "w_right": (z0 + w, 4, 0, 3),
                                           "w_low": (z0 - w, z0 + w, 0, y0 - h),
                                           "w_high": (z0 - w, z0 + w, y0 + h, 3)}.items():
        wall(name, [-4, 0.5 * (y_lo + y_hi), 0.5 * (z_lo + z_hi)], 90,
             [0.5 * (z_hi - z_lo), 0.5 * (y_hi - y_lo)])
    elev = math.radians(rng.uniform(15, 40))
    turn = math.radians(rng.uniform(-25, 25))
    scene["light"] = _sun([math.cos(elev) * math.cos(turn), -math.sin(elev),
                           math.cos(elev) * math.sin(turn)])
    a = rng.uniform(-0.6, 0.6)
    scene["sensor"]["to_world"] = T().look_at(origin=[3.2, rng.uniform(1.2, 2.2), 3.2 * a],
                                              target=[-1.0, 0.6, -0.5 * a], up=[0, 1, 0])
    scene["sensor"]["fov"] = rng.uniform(60, 80)


def _feature(rng, sub: str, scene: dict, seed: int):
    """Adds what ``sub`` (``FEATURE_KINDS``) draws to the props' ``scene``: a Mitsuba
    feature the other kinds do not make, lit by a wide spot unless it is a light."""
    light = _spot(rng, "wide", 1.0)
    if sub == "instances":       # a shapegroup (a cube and a ball) placed 4-7 times
        scene["group"] = {"type": "shapegroup",
                          "cube": {"type": "cube", "bsdf": _diffuse(0.3, 0.6, 0.3),
                                   "to_world": T().scale([0.3, 0.6, 0.3])},
                          "ball": {"type": "sphere", "radius": 0.3, "center": [0, 1.0, 0],
                                   "bsdf": _diffuse(0.6, 0.6, 0.3)}}
        for k in range(int(rng.integers(4, 8))):
            x, z = rng.uniform(-4, 4, 2)
            scene[f"instance_{k}"] = {
                "type": "instance", "shapegroup": {"type": "ref", "id": "group"},
                "to_world": T().translate([x, rng.uniform(0.6, 1.5), z])
                .rotate([0, 1, 0], rng.uniform(0, 90)).scale(rng.uniform(0.6, 1.6))}
    elif sub == "mesh light":    # an open PLY mesh, two quads folded, emitting downwards
        w, fold = rng.uniform(0.3, 2.0), rng.uniform(0, 60)
        c, s = math.cos(math.radians(fold)), math.sin(math.radians(fold))
        v = np.array([[-1, 0, -1], [0, 0, -1], [0, 0, 1], [-1, 0, 1],
                      [c, s, -1], [c, s, 1]], float) * [w, w, 0.5 * w]
        path = _scratch_file(f"panel_{seed}.ply")
        procedural.write_ply(path, v, [[0, 1, 2], [0, 2, 3], [1, 4, 5], [1, 5, 2]])
        h = rng.uniform(3, 6)
        light = {"type": "ply", "filename": path, "emitter": {
            "type": "area", "radiance": {"type": "rgb", "value": 3.0 * h * h / (2 * w * w)}},
            "to_world": T().translate([rng.uniform(-2, 2), h, rng.uniform(-2, 2)])
            .rotate([0, 1, 0], rng.uniform(0, 180))}
    elif sub == "strip light":   # a rectangle 2-6 long and 0.02-0.1 wide
        long_, short = rng.uniform(2, 6), rng.uniform(0.02, 0.1)
        p = [rng.uniform(-2, 2), rng.uniform(3, 6), rng.uniform(-2, 2)]
        light = {"type": "rectangle",
                 "to_world": _look(p, [p[0] + rng.uniform(-1, 1), 0.0, p[2]])
                 @ T().rotate([0, 0, 1], rng.uniform(0, 180))
                 .scale([0.5 * long_, 0.5 * short, 1.0]),
                 "emitter": {"type": "area", "radiance": {
                     "type": "rgb", "value": 3.0 * p[1] ** 2 / (long_ * short)}}}
    elif sub == "window":
        _window_room(rng, scene)
        return
    elif sub == "curves":        # hair-like strands (Mitsuba's linearcurve)
        path = _scratch_file(f"strands_{seed}.txt")
        _strands(rng, path)
        scene["strands"] = {"type": "linearcurve", "filename": path,
                            "bsdf": _diffuse(0.7, 0.5, 0.2)}
    elif sub == "twin lights":   # two lights of one type at one position
        if rng.random() < 0.5:
            p = [rng.uniform(-3, 3), rng.uniform(2, 6), rng.uniform(-3, 3)]
            light = {"type": "point", "position": p,
                     "intensity": {"type": "rgb", "value": 1.5 * p[1] ** 2}}
            scene["light_b"] = dict(light, intensity={"type": "rgb", "value": 4 * p[1] ** 2})
        else:
            scene["light_b"] = _spot(rng, "wide", 1.0)
            scene["light_b"]["to_world"] = _look(
                list(light["to_world"].translation()), [rng.uniform(-2, 2), 0.0,
                                                        rng.uniform(-2, 2)])
    elif sub == "axis sun":      # a sun along -y, or along +-x / +-z onto a two-sided wall
        axis = int(rng.integers(3))
        if axis == 0:
            light = _sun([0, -1, 0])
        else:
            sign = 1.0 if rng.random() < 0.5 else -1.0
            d = [0.0, 0.0, 0.0]
            d[2 * axis - 2] = sign
            light = _sun(d)
            centre = [0.0, 2.0, 0.0]
            centre[2 * axis - 2] = 5.0 * sign
            scene["wall"] = {"type": "rectangle", "bsdf": {"type": "twosided",
                                                           "bsdf": _diffuse(0.5, 0.5, 0.5)},
                             "to_world": T().translate(centre).rotate(
                                 [0, 1, 0], 90 if axis == 1 else 0).scale([6, 2, 1])}
    elif sub in ("thinlens", "orthographic"):
        sensor = scene["sensor"]
        origin = np.array(sensor["to_world"].translation())
        dist = float(np.linalg.norm(origin - [0.0, 0.5, 0.0]))
        if sub == "thinlens":
            sensor.update(type="thinlens", aperture_radius=rng.uniform(0.02, 0.3),
                          focus_distance=dist * rng.uniform(0.7, 1.2))
        else:
            half = dist * math.tan(math.radians(0.5 * sensor.pop("fov")))
            sensor.update(type="orthographic",
                          to_world=sensor["to_world"] @ T().scale([half, half, 1]))
    scene["light"] = light


def random_local_lights(kind: str, seed: int, width: int = 128, spp: int = 16):
    """A random scene of ``kind`` (``LOCAL_KINDS``) and a label of what was drawn: a 12 x
    12 ground with 3 boxes, 3 spheres (some floating), a post and a floating plate, seen
    from 8-14 away and 3-8 high, under a spot (``seed % 4``: narrow 5-15 degrees, wide
    50-75, 80-89 (a cube map), grazing: 0.3-1.5 over the ground), a one-sided area light
    (``seed % 4``: rectangle or disk, 0.05-0.3 or 2-5 wide), a sphere light (radius
    0.05-1.2), 2-4 lights of mixed types, or that mixed scene scaled by 1e-3 or 1e4
    (camera clip planes too); ``room``: a point light 0.02-0.3 from the ceiling, a wall
    or a box top (``seed % 3``) inside a closed room; ``feature``: see
    ``FEATURE_KINDS`` and :func:`_feature`."""
    # the scaled kinds draw the mixed kind's scene of the same seed (scale invariance)
    rng = np.random.default_rng([seed, LOCAL_KINDS.index("mixed" if kind.startswith(
        "scale") else kind)])
    if kind == "room":
        sub = ROOM_KINDS[seed % 3]
        return _room(rng, sub, width, spp), sub
    s = {"scale_1e-3": 1e-3, "scale_1e4": 1e4}.get(kind, 1.0)
    turn, r = rng.uniform(0, 2 * math.pi), rng.uniform(8, 14)
    origin = [r * math.cos(turn), rng.uniform(3, 8), r * math.sin(turn)]
    scene = {"type": "scene",
             "sensor": camera(origin, [0.0, 0.5, 0.0], width, width, spp,
                              fov=rng.uniform(35, 60), scale=s),
             "ground": {"type": "rectangle", "bsdf": _diffuse(0.5, 0.5, 0.5),
                        "to_world": T().scale(6 * s).rotate([1, 0, 0], -90)}}
    _props(rng, scene, s)
    if kind == "spot":
        sub = SPOT_KINDS[seed % 4]
        scene["light"] = _spot(rng, sub, s)
    elif kind == "area":
        sub = AREA_KINDS[seed % 4]
        small = sub.endswith("small")
        scene["light"] = _area(rng, sub.split()[0], rng.uniform(0.05, 0.3) if small
                               else rng.uniform(2, 5), s)
    elif kind == "feature":
        sub = FEATURE_KINDS[seed % len(FEATURE_KINDS)]
        _feature(rng, sub, scene, seed)
    elif kind == "sphere_light":
        size = rng.uniform(0.05, 1.2)
        sub = f"radius {size:.2f}"
        scene["light"] = _area(rng, "sphere", size, s)
    else:
        types = list(rng.choice(MIXED_TYPES, size=int(rng.integers(2, 5)), replace=False))
        sub = "+".join(types)
        for k, t in enumerate(types):
            if t == "spot":
                light = _spot(rng, SPOT_KINDS[int(rng.integers(4))], s)
            elif t == "point":
                p = [rng.uniform(-4, 4), rng.uniform(1.5, 6), rng.uniform(-4, 4)]
                light = {"type": "point", "position": [s * c for c in p],
                         "intensity": {"type": "rgb", "value": 3.0 * p[1] ** 2 * s * s}}
            elif t == "sun":
                elev, az = math.radians(rng.uniform(15, 70)), rng.uniform(0, 2 * math.pi)
                light = {"type": "directional", "irradiance": {"type": "rgb", "value": 3.0},
                         "direction": [-math.cos(elev) * math.cos(az), -math.sin(elev),
                                       -math.cos(elev) * math.sin(az)]}
            else:
                small = rng.random() < 0.5
                light = _area(rng, t, (rng.uniform(0.05, 0.3) if small else
                                       rng.uniform(0.5, 3)) * (0.4 if t == "sphere" else 1), s)
            scene[f"light_{k}"] = light
    return scene, sub


def scene_dict(kind: str, seed: int, image: int, spp: int) -> dict:
    if kind == "world":
        return random_large_world(seed, width=image, spp=spp)
    if kind == "terrain":
        return random_terrain_world(seed, width=image, spp=spp)
    return random_far_point(seed, distance=float(kind), width=image, spp=spp)


def visibility(scene, props: dict, seed: int):
    integ = mi.load_dict({"type": "shadowmap", **props})
    img = np.asarray(mi.render(scene, integrator=integ, seed=seed))
    return img[..., 3], integ


def texel_scan(args, seeds, props: dict):
    """``--texels-only``: one row per kind and seed, each method's texels per film pixel."""
    t_start = time.perf_counter()
    print(f"# {args.image}^2, texels only (1 spp), seeds {seeds[0]}-{seeds[-1]}, "
          f"variant {mi.variant()}, map methods with {props or 'defaults'}\n")
    print("| scene | seed | " + " | ".join(f"{m}: texels / pixel" for m in args.methods)
          + " |")
    print("|" + "---|" * (2 + len(args.methods)))
    texels = {(k, m): [] for k in args.kinds for m in args.methods}
    for kind in args.kinds:
        for seed in seeds:
            d = scene_dict(kind, seed, args.image, 1)
            cells = []
            for m in args.methods:
                _, integ = visibility(mi.load_dict(d), {"method": m, **props}, 0)
                tpp = integ.stats["texels_built"] / (args.image * args.image)
                texels[(kind, m)].append(tpp)
                cells.append(f"{tpp:.2f}")
            print(f"| {kind} | {seed} | " + " | ".join(cells) + " |", flush=True)
    print("\n| scene | method | texels / pixel: max (median) | over 8 |")
    print("|---|---|---|---|")
    for (kind, m), t in texels.items():
        t = np.array(t)
        print(f"| {kind} | {m} | {t.max():.2f} ({np.median(t):.2f}) | {int(np.sum(t > 8))} "
              f"of {len(t)} |")
    print(f"\n# total {time.perf_counter() - t_start:.0f} s")


def _render(scene, props: dict, seed: int):
    """The visibility AOVs (one channel a light, in the order of their names), the
    integrator and the warnings raised."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        integ = mi.load_dict({"type": "shadowmap", **props})
        img = np.asarray(mi.render(scene, integrator=integ, seed=seed))
    return by_name(img[..., 3:], integ.aov_names()), integ, [str(w.message)[:80]
                                                             for w in caught]


def by_name(aovs: np.ndarray, names: list) -> np.ndarray:
    """``aovs`` (one channel a light, in the scene's emitter order) in the order of their
    ``names``: the reference and each method render their own load of the scene dict,
    and Mitsuba's emitter order differs between loads of one dict (shape lights of one
    type load in parallel: two rectangle lights came in either order, 6 loads in 30; 16
    lights in 9 orders in 20), so channel k of one was another light than channel k of
    the other."""
    return aovs[..., np.argsort(names, kind="stable")]


def _score(ref, vis) -> str:
    """Misclassified over every light's pixels (false lit / false shadow), the RMSE, and
    with several lights each light's misclassified in brackets."""
    mc = misclassified(ref, vis)
    rmse = float(np.sqrt(np.mean((ref - vis) ** 2)))
    each = "" if ref.shape[-1] == 1 else " [" + " / ".join(
        f"{100 * misclassified(ref[..., k], vis[..., k])['misclassified']:.2f}"
        for k in range(ref.shape[-1])) + "]"
    return f"{mc['misclassified']:.2%} ({mc['false_lit']:.2%} / {mc['false_shadow']:.2%}), " \
           f"{rmse:.3f}{each}"


def local_scan(args, seeds):
    """Local-light kinds (see the module's docstring): one row per kind, seed and
    method."""
    t_start = time.perf_counter()
    print(f"# {args.image}^2, {args.spp} spp, seeds {seeds[0]}-{seeds[-1]}, variant "
          f"{mi.variant()}; misclassified (false lit / false shadow), visibility RMSE over "
          "every light's pixels; full maps at equal texels: the largest power-of-two "
          "resolution whose faces hold no more texels than the virtual map\n")
    print("| kind | seed | drawn | method | rt noise | virtual | texels / px "
          f"{args.image}^2 / {args.texel_image}^2 | full, automatic (texels / px) | "
          "full, equal texels (resolution) | non-finite | warnings |")
    print("|" + "---|" * 11)
    for kind in args.kinds:
        for seed in seeds:
            d, drawn = random_local_lights(kind, seed, args.image, args.spp)
            scene = mi.load_dict(d)
            area = any(e.get_shape() is not None for e in scene.emitters())
            rt = {"method": "raytraced", **({"shadow_rays": 16} if area else {})}
            ref, _, _ = _render(scene, rt, 0)
            other, _, _ = _render(scene, rt, 5)
            noise = _score(ref, other)
            for m in args.methods:
                cells, bad, warns = [], 0, []
                try:
                    v, integ, w = _render(mi.load_dict(d), {"method": m}, 0)
                    texels = integ.stats["texels_built"]
                    _, i256, _ = _render(mi.load_dict(random_local_lights(
                        kind, seed, args.texel_image, 1)[0]), {"method": m}, 0)
                    f = e = None
                    wf = we = []
                    if not args.virtual_only:
                        f, fi, wf = _render(mi.load_dict(d), {"method": m,
                                                              "virtual": False}, 0)
                        faces = fi.stats["faces_built"]
                        res = max(16, 2 ** int(math.floor(math.log2(math.sqrt(
                            max(texels, 1) / max(faces, 1))))))
                        e, ei, we = _render(mi.load_dict(d), {
                            "method": m, "virtual": False, "resolution": res}, 0)
                except Exception as exc:  # noqa: BLE001  (reported, the run goes on)
                    print(f"| {kind} | {seed} | {drawn} | {m} | {noise} | error: "
                          f"{type(exc).__name__}: {str(exc)[:150]} | | | | | |", flush=True)
                    continue
                bad = sum(int(np.count_nonzero(~np.isfinite(x))) for x in (v, f, e)
                          if x is not None)
                warns = sorted(set(w + wf + we))
                px = args.image ** 2
                full = ["-", "-"] if f is None else [
                    f"{_score(ref, f)} ({fi.stats['texels_built'] / px:.1f})",
                    f"{_score(ref, e)} ({res})"]
                cells = [_score(ref, v), f"{texels / px:.2f} / "
                         f"{i256.stats['texels_built'] / args.texel_image ** 2:.2f}",
                         *full, str(bad), "; ".join(warns) or "-"]
                print(f"| {kind} | {seed} | {drawn} | {m} | {noise} | " + " | ".join(cells)
                      + " |", flush=True)
    print(f"\n# total {time.perf_counter() - t_start:.0f} s")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=int, default=8, help="N seeds per kind")
    ap.add_argument("--first-seed", type=int, default=0,
                    help="the first seed (seeds first .. first + N - 1)")
    ap.add_argument("--image", type=int, default=128)
    ap.add_argument("--spp", type=int, default=16)
    ap.add_argument("--kinds", nargs="+", default=["world", "1e5", "1e6"],
                    help="'world', 'terrain' and/or point-light distances")
    ap.add_argument("--methods", nargs="+", default=["hard", "pcf"])
    ap.add_argument("--texel-image", type=int, default=256,
                    help="local-light kinds: the film of the virtual map's texel count")
    ap.add_argument("--virtual-only", action="store_true",
                    help="local-light kinds: no full maps (their columns read '-')")
    ap.add_argument("--texels-only", action="store_true",
                    help="texels per pixel only (1 spp, no reference): a fast scan")
    ap.add_argument("--set", nargs="*", default=[], metavar="NAME=VALUE",
                    help="integrator properties for the map methods (not the reference), "
                         "e.g. normal_bias=0 (values: true/false, int, float or string)")
    args = ap.parse_args(argv)
    props = parse_assignments(args.set, "--set")
    if args.seeds < 1 or args.first_seed < 0:
        ap.error("--seeds must be at least 1 and --first-seed at least 0")
    local = [k for k in args.kinds if k in LOCAL_KINDS]
    if local and len(local) < len(args.kinds):
        ap.error("--kinds: local-light kinds (" + ", ".join(LOCAL_KINDS) + ") run alone")
    if local and (args.texels_only or props):
        ap.error("local-light kinds take neither --texels-only nor --set")
    if args.virtual_only and not local:
        ap.error("--virtual-only is for local-light kinds (the others build no full maps)")
    for k in args.kinds:
        if k not in ("world", "terrain") + LOCAL_KINDS:
            try:
                float(k)
            except ValueError:
                ap.error(f"--kinds {k!r}: expected 'world', 'terrain', a point-light "
                         "distance or one of " + ", ".join(LOCAL_KINDS))
    t_start = time.perf_counter()
    seeds = range(args.first_seed, args.first_seed + args.seeds)
    if local:
        local_scan(args, seeds)
        return
    if args.texels_only:
        texel_scan(args, seeds, props)
        return
    print(f"# {args.image}^2, {args.spp} spp, seeds {seeds[0]}-{seeds[-1]}, "
          f"variant {mi.variant()}, map methods with {props or 'defaults'}\n")
    head = "| scene | seed | rt noise | " + " | ".join(
        f"{m}: misclassified (false lit / false shadow) | {m}: texels / pixel"
        for m in args.methods) + " |"
    print(head)
    print("|" + "---|" * (3 + 2 * len(args.methods)))
    errors = {(k, m): [] for k in args.kinds for m in args.methods}
    texels = {(k, m): [] for k in args.kinds for m in args.methods}
    noise = {k: [] for k in args.kinds}
    for kind in args.kinds:
        for seed in seeds:
            d = scene_dict(kind, seed, args.image, args.spp)
            scene = mi.load_dict(d)
            ref, _ = visibility(scene, {"method": "raytraced"}, 0)
            other, _ = visibility(scene, {"method": "raytraced"}, 5)
            rt = misclassified(ref, other)["misclassified"]
            noise[kind].append(rt)
            cells = []
            for m in args.methods:
                v, integ = visibility(mi.load_dict(d), {"method": m, **props}, 0)
                mc = misclassified(ref, v)
                tpp = integ.stats["texels_built"] / (args.image * args.image)
                errors[(kind, m)].append(mc["misclassified"])
                texels[(kind, m)].append(tpp)
                cells.append(f"{mc['misclassified']:.2%} ({mc['false_lit']:.2%} / "
                             f"{mc['false_shadow']:.2%}) | {tpp:.1f}")
            print(f"| {kind} | {seed} | {rt:.2%} | " + " | ".join(cells) + " |", flush=True)
    print("\n| scene | method | misclassified: max (median) | over the target | above rt noise "
          "| texels / pixel: max (median) |")
    print("|---|---|---|---|---|---|")
    for (kind, m), errs in errors.items():
        e, t = np.array(errs), np.array(texels[(kind, m)])
        target = TARGET.get(kind, 0.003)
        over = int(np.sum(e > target))
        above = int(np.sum(e > np.array(noise[kind])))
        print(f"| {kind} | {m} | {e.max():.2%} ({np.median(e):.2%}) | {over} of {len(e)} "
              f"(target {target:.1%}) | {above} of {len(e)} | {t.max():.1f} "
              f"({np.median(t):.1f}) |")
    print(f"\n# total {time.perf_counter() - t_start:.0f} s")


if __name__ == "__main__":
    main()
