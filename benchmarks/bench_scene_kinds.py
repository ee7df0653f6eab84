"""Every method at defaults on kinds of scene the repository does not hold. One run, by hand:

    python benchmarks/bench_scene_kinds.py [--methods hard pcf ...] [--kinds spot_wide ...]
                                           [--image 128] [--spp 16]

Each kind is one small procedural scene (a floor, a box, a ball and a thin post, or a
room) with one light or a few, built here as a Mitsuba dict: degenerate and extreme
lights (a straight-down or horizontal sun, a 3-degree sun, an 80-degree spot, a spot
with a scaled transform or a blocker just in front of it, a point light on the floor, a
1e-4 or a very thin or very large area light, a sliver 4 x 2e-4 (``second_depth``
passed its own surface from a far-off point, forty-sixth session), sphere and disk area
lights, a point light 1e-3 over the floor by the ball resting on it), extreme
scales (1e-3 with Mitsuba's default ``near_clip``, so the near plane is most of the way
to the scene; 1e4), other sensors (orthographic, thin lens, a crop window), instancing,
a point light inside a closed room, three light types together, and environment light
(a constant sky, at scale 1 and 1e4; the repository's sky rotated and tilted; that sky
with a sun).

For each kind: ``raytraced`` (seed 0) is the reference (with ``shadow_rays`` = 64 under an
environment, whose map methods' visibility is the fraction of its light arriving, which
one ray per sample gives only as binary noise), ``raytraced`` with seed 1 its
own noise (misclassified against it), and every method at defaults (only ``method``
given; virtual maps) is reported as misclassified (threshold 0.5) and visibility RMSE
against it per light, texels built per film pixel in its frame (methods run in turn on
one loaded scene, so a method whose pages an earlier one built shows 0), and whether its
output was finite. A method that raises is reported with its error. Under a uniform sky
an open floor's visibility is about 0.5 (the share of the sky above it), so
misclassification at 0.5 means nothing there: read the RMSE.
"""
from __future__ import annotations

import argparse
import pathlib
import time

import mi_shadowmap  # noqa: F401  (LLVM set-up, registration)
import mitsuba as mi
import numpy as np

from mi_shadowmap.metrics import misclassified
from mi_shadowmap.options import MAP_METHODS

T = mi.ScalarTransform4f
SKY = pathlib.Path(__file__).resolve().parents[1] / "scenes_xml" / "textures" / "sky_sun.exr"
#: every map method (the docstring's "every method"; the list named six of them, without
#: vsm, evsm, msm and multiview)
METHODS = list(MAP_METHODS)


def camera(origin, target, width, spp, kind="perspective", fov=45.0, **extra):
    d = {"type": kind, "to_world": T().look_at(origin=origin, target=target, up=[0, 1, 0]),
         "film": {"type": "hdrfilm", "width": width, "height": width},
         "sampler": {"type": "independent", "sample_count": spp}}
    if kind != "orthographic":
        d["fov"] = fov
    d.update(extra)
    return d


def objects(s=1.0):
    """A 20-unit floor, a box, a ball and a thin post, scaled by ``s``."""
    diffuse = {"type": "diffuse"}
    return {"type": "scene",
            "floor": {"type": "rectangle", "bsdf": diffuse,
                      "to_world": T().scale(s).rotate([1, 0, 0], -90).scale(10)},
            "box": {"type": "cube", "bsdf": diffuse,
                    "to_world": T().scale(s).translate([0, 1, 0]).scale(0.8)},
            "ball": {"type": "sphere", "center": [2.0 * s, 0.7 * s, 1.0 * s],
                     "radius": 0.7 * s, "bsdf": diffuse},
            "post": {"type": "cylinder", "p0": [-2 * s, 0, -1 * s], "p1": [-2 * s, 3 * s, -1 * s],
                     "radius": 0.1 * s, "bsdf": diffuse}}


def kinds(width: int, spp: int) -> dict:
    def scene(lights, s=1.0, **cam):
        d = objects(s)
        d["sensor"] = camera([6 * s, 5 * s, 8 * s], [0, 0.5 * s, 0], width, spp, **cam)
        d.update(lights)
        return d

    def spot(origin, target, cutoff=40.0, s=1.0, scale=None, **kw):
        to_world = T().look_at(origin=origin, target=target, up=[0, 1, 0])
        if scale is not None:
            to_world = to_world @ T().scale(scale)
        return {"type": "spot", "to_world": to_world, "cutoff_angle": cutoff,
                "intensity": 80.0 * s * s, **kw}

    def area(shape, to_world, radiance, **kw):
        return {"type": shape, "to_world": to_world, **kw,
                "emitter": {"type": "area", "radiance": radiance}}

    sun = lambda d: {"type": "directional", "direction": d, "irradiance": 3.0}  # noqa: E731
    point = lambda p, s=1.0: {"type": "point", "position": p, "intensity": 30.0 * s * s}  # noqa: E731
    room = {"type": "scene",
            "sensor": camera([0, 1.5, 3.5], [0, 1, 0], width, spp, fov=70.0),
            "room": {"type": "cube", "to_world": T().translate([0, 2, 0]).scale(4),
                     "bsdf": {"type": "twosided", "bsdf": {"type": "diffuse"}}},
            "ball": {"type": "sphere", "center": [0.5, 0.8, 0], "radius": 0.6,
                     "bsdf": {"type": "diffuse"}},
            "box": {"type": "cube", "to_world": T().translate([-1.2, 0.5, -1]).scale(0.5),
                    "bsdf": {"type": "diffuse"}},
            "light": point([0, 3, 0])}
    inst = scene({"light": spot([2, 7, 6], [0, 0, 1], 45.0)})
    inst["group"] = {"type": "shapegroup",
                     "cube": {"type": "cube", "to_world": T().scale(0.4),
                              "bsdf": {"type": "diffuse"}}}
    for i, x in enumerate([-3.0, 3.5, 0.5]):
        inst[f"instance{i}"] = {"type": "instance", "shapegroup": {"type": "ref", "id": "group"},
                                "to_world": T().translate([x, 0.4, 2.5])}
    near = scene({"light": spot([0, 1.85, 0], [3, 0, 1], 60.0)})
    near["cap"] = {"type": "rectangle", "bsdf": {"type": "diffuse"},
                   "to_world": T().translate([0.6, 1.7, 0.2]).rotate([1, 0, 0], 90).scale(0.3)}
    rect_at = T().look_at(origin=[1, 4, 1], target=[0, 0, 0], up=[0, 1, 0])
    crop = {"film": {"type": "hdrfilm", "width": width + width // 4, "height": (width * 9) // 16,
                     "crop_offset_x": width // 8, "crop_offset_y": width // 16,
                     "crop_width": (width * 3) // 4, "crop_height": (width * 3) // 8}}
    ortho_at = T().look_at(origin=[6, 5, 8], target=[0, 0.5, 0], up=[0, 1, 0]) @ T().scale([6, 6, 1])
    constant = {"type": "constant", "radiance": 1.0}
    envmap = lambda to_world=T(): {"type": "envmap", "filename": str(SKY),  # noqa: E731
                                   "to_world": to_world}
    return {
        "sun_straight_down": scene({"light": sun([0, -1, 0])}),
        "sun_3_degrees": scene({"light": sun([1, -0.05, 0.3])}),
        "sun_horizontal": scene({"light": sun([1, 0, 0.2])}),
        "spot_80_degrees": scene({"light": spot([3, 6, 3], [0, 0, 0], 80.0, beam_width=60.0)}),
        "spot_scaled_transform": scene({"light": spot([3, 6, 3], [0, 0, 0], scale=[2, 0.5, 1])}),
        "spot_blocker_at_light": near,
        "point_on_floor": scene({"light": point([0, 0.0, 3])}),
        "point_in_closed_room": room,
        "sphere_area": scene({"light": {"type": "sphere", "center": [1, 5, 1], "radius": 0.5,
                                        "emitter": {"type": "area", "radiance": 8.0}}}),
        "disk_area": scene({"light": area("disk", T().translate([0, 5, 0]).rotate([1, 0, 0], 90)
                                          .scale(0.6), 20.0)}),
        "area_1e-4_wide": scene({"light": area("rectangle", rect_at @ T().scale(1e-4), 1e9)}),
        "area_thin": scene({"light": area("rectangle", rect_at @ T().scale([2, 1e-3, 1]), 50.0)}),
        "area_sliver": scene({"light": area("rectangle", rect_at @ T().scale([2, 1e-4, 1]),
                                            5e3)}),
        "point_1e-3_over_floor": scene({"light": point([0.5, 1e-3, 2.5])}),
        "area_16_wide": scene({"light": area(
            "rectangle", T().look_at(origin=[0, 6, 0], target=[0, 0, 0], up=[0, 0, 1]).scale(8),
            1.0)}),
        "scale_1e-3_default_near_clip": scene(
            {"light": spot([3e-3, 6e-3, 3e-3], [0, 0, 0], 50.0, s=1e-3)}, s=1e-3),
        "scale_1e4_sun": scene({"light": sun([-0.4, -1, -0.3])}, s=1e4, near_clip=1.0,
                               far_clip=1e7),
        "scale_1e4_point": scene({"light": point([1e4, 4e4, 2e4], 1e4)}, s=1e4, near_clip=1.0,
                                 far_clip=1e7),
        "orthographic_camera": scene({"light": point([1, 4, 2])}, kind="orthographic",
                                     to_world=ortho_at),
        "thin_lens_camera": scene({"light": point([1, 4, 2])}, kind="thinlens",
                                  aperture_radius=0.1, focus_distance=9.0),
        "crop_window": scene({"light": spot([3, 6, 3], [0, 0, 0])}, **crop),
        "instances": inst,
        "three_light_types": scene({
            "point": point([-1, 4, 2]), "sun": {**sun([0.5, -1, -0.2]), "irradiance": 2.0},
            "rect": area("rectangle", T().look_at(origin=[2, 4, -2], target=[0, 0, 0],
                                                  up=[0, 1, 0]).scale(0.5), 10.0)}),
        "constant_sky": scene({"sky": constant}),
        "constant_sky_scale_1e4": scene({"sky": constant}, s=1e4, near_clip=1.0, far_clip=1e7),
        "envmap_rotated_tilted": scene({"sky": envmap(T().rotate([1, 0, 0], 25.0)
                                                      .rotate([0, 1, 0], 120.0))}),
        "envmap_and_sun": scene({"sky": envmap(), "sun": sun([0.3, -1, 0.6])}),
    }


def visibility(scene, method: str, seed: int, **props):
    integ = mi.load_dict({"type": "shadowmap", "method": method, **props})
    img = np.asarray(mi.render(scene, integrator=integ, seed=seed))
    return img, integ


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--methods", nargs="+", default=METHODS)
    ap.add_argument("--kinds", nargs="+", default=None)
    ap.add_argument("--image", type=int, default=128)
    ap.add_argument("--spp", type=int, default=16)
    args = ap.parse_args(argv)
    all_kinds = kinds(args.image, args.spp)
    names = args.kinds or list(all_kinds)
    unknown = sorted(set(names) - set(all_kinds))
    if unknown:
        ap.error(f"unknown kinds {unknown}; known: {', '.join(all_kinds)}")
    print(f"# bench_scene_kinds {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, "
          f"{args.image}^2 film, {args.spp} spp; misclassified (threshold 0.5) and RMSE "
          "against raytraced (seed 0), per light\n")
    print("| kind | method | misclassified [%] | visibility RMSE | texels / pixel | finite |")
    print("|---|---|---|---|---|---|")
    t0 = time.perf_counter()
    for name in names:
        scene = mi.load_dict(all_kinds[name])
        env = {"shadow_rays": 64} if any(e.is_environment() for e in scene.emitters()) else {}
        ref, _ = visibility(scene, "raytraced", 0, **env)
        n_lights = ref.shape[-1] - 3
        per_light = lambda f, img: " / ".join(f(ref[..., 3 + k], img[..., 3 + k])  # noqa: E731
                                              for k in range(n_lights))
        mis = lambda a, b: f"{100 * misclassified(a, b)['misclassified']:.2f}"  # noqa: E731
        rmse = lambda a, b: f"{float(np.sqrt(np.mean((a - b) ** 2))):.3f}"  # noqa: E731
        noise, _ = visibility(scene, "raytraced", 1, **env)
        print(f"| {name} | raytraced, seed 1 | {per_light(mis, noise)} | "
              f"{per_light(rmse, noise)} | - | {bool(np.all(np.isfinite(noise)))} |")
        for m in args.methods:
            try:
                img, integ = visibility(scene, m, 0)
            except Exception as e:  # noqa: BLE001  (reported, the run goes on)
                print(f"| {name} | {m} | error: {type(e).__name__}: {str(e)[:120]} | | | |")
                continue
            texels = integ.stats.get("texels_built", 0) / (img.shape[0] * img.shape[1])
            print(f"| {name} | {m} | {per_light(mis, img)} | {per_light(rmse, img)} | "
                  f"{texels:.1f} | {bool(np.all(np.isfinite(img)))} |", flush=True)
    print(f"\n# total {time.perf_counter() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
