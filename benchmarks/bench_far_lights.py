"""Lights far from the scene: misclassified, texels built and frame times against distance.

    python benchmarks/bench_far_lights.py [--distances 1e5 1e6 1e7 1e8 1e9 1e12]
                                          [--image 128] [--spp 16] [--methods hard pcf]

``far_point.xml`` (a 10 x 10 ground with boxes and spheres) under its point light
``distance`` units away, rendered at defaults (virtual maps) and with ``virtual=false``
(one full cube map). For each distance and method: the fraction of pixels whose
visibility is on the other side of 0.5 from ``raytraced``'s (one shadow ray, the same
seed and spp), the texels the first frame ray-casts per film pixel, the layout's view
(``cube``, or ``perspective`` where the light is so far that a virtual layout aims one
face at the scene, ``virtual.layout_for``) and its finest texel's width at the scene's
centre, and
the frame times: the first frame (maps built: a new integrator, the map and page caches
emptied; kernels warm) and a still-camera frame (maps cached), beside the unshadowed
frame, measured in the same run. Distances beyond 1e6 were out of reach before the thirteenth session:
depths measured from the light rounded away every shadow (1e7-1e8), and a cube face's
finest level (2^30 texels) was coarser than the scene's casters (1e9 and beyond).
"""
from __future__ import annotations

import argparse
import pathlib
import statistics
import time

import numpy as np

import mi_shadowmap  # noqa: F401  (LLVM set-up, registration)
import drjit as dr
import mitsuba as mi
from mi_shadowmap.map_manager import MAP_CACHE
from mi_shadowmap.virtual import PAGE_CACHE

ROOT = pathlib.Path(__file__).resolve().parents[1]
SCENE = ROOT / "scenes_xml" / "far_point.xml"


def load(distance: str, image: int, spp: int):
    return mi.load_file(str(SCENE), width=image, height=image, spp=spp,
                        light_distance=distance,
                        light_intensity=f"{3.0 * float(distance) ** 2:g}")


def timed(scene, integ, spp: int):
    t0 = time.perf_counter()
    img = mi.render(scene, integrator=integ, spp=spp, seed=1)
    dr.eval(img)
    dr.sync_thread()
    return np.asarray(img), time.perf_counter() - t0


def visibility(img) -> np.ndarray:
    return img[..., -1]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--distances", nargs="+",
                    default=["1e5", "1e6", "1e7", "1e8", "1e9", "1e12"])
    ap.add_argument("--image", type=int, default=128)
    ap.add_argument("--spp", type=int, default=16)
    ap.add_argument("--methods", nargs="+", default=["hard", "pcf"])
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--variant", default="llvm_ad_rgb")
    args = ap.parse_args(argv)
    mi.set_variant(args.variant)
    px = args.image ** 2
    print(f"# far_point.xml, {args.image}^2, {args.spp} spp, {args.variant}; times: median "
          f"of {args.rounds}")
    print("| distance | method | maps | misclassified | texels / pixel | view, finest "
          "texel at the scene | first frame [ms] | cached frame [ms] | unshadowed [ms] |")
    print("|---|---|---|---|---|---|---|---|---|")
    for distance in args.distances:
        scene = load(distance, args.image, args.spp)
        ref = visibility(timed(scene, mi.load_dict({"type": "shadowmap",
                                                    "method": "raytraced"}), args.spp)[0])
        unshadowed = mi.load_dict({"type": "shadowmap", "method": "unshadowed"})
        timed(scene, unshadowed, args.spp)
        t_plain = statistics.median(timed(scene, unshadowed, args.spp)[1]
                                    for _ in range(args.rounds))
        for method in args.methods:
            for virtual in (True, False):
                props = {"type": "shadowmap", "method": method, "virtual": virtual}
                # warm the kernels, then time first frames of a new integrator with the
                # caches emptied (maps built) and cached frames of the same one
                timed(scene, mi.load_dict(props), args.spp)
                firsts, cached = [], []
                for _ in range(args.rounds):
                    integ = mi.load_dict(props)
                    MAP_CACHE.clear()
                    PAGE_CACHE.clear()
                    img, t_first = timed(scene, integ, args.spp)
                    texels = integ.stats["texels_built"]
                    firsts.append(t_first)
                    cached.append(timed(scene, integ, args.spp)[1])
                vis = visibility(img)
                mis = float(np.mean((vis >= 0.5) != (ref >= 0.5)))
                m = integ.maps[0]
                view = getattr(getattr(m, "layout", None), "view", m.view)
                res = getattr(getattr(m, "layout", None), "res0", None) or m.resolution
                centre = np.zeros(3)
                texel = view.map_width(centre) / res
                print(f"| {distance} | {method} | {'virtual' if virtual else 'full'} | "
                      f"{mis:.2%} | {texels / px:.1f} | {view.projection}, {texel:.2g} | "
                      f"{1e3 * statistics.median(firsts):.0f} | "
                      f"{1e3 * statistics.median(cached):.0f} | {1e3 * t_plain:.0f} |",
                      flush=True)


if __name__ == "__main__":
    main()
