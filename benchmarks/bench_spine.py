"""Cost ratios of the spine, each measured within one run (not a test).

    python benchmarks/bench_spine.py [--image 512] [--map 1024] [--repeats 5]

Prints:
  (a) depth-map build time / a bare ray_intersect_preliminary over the same rays
  (b) hard frame / unshadowed frame  (Reeves 1987 reports +37..51 %), with the maps
      rebuilt every frame and with the maps cached across renders
  (c) hard frame / raytraced frame
  (d) every map method's frame / hard frame, at --map and --map/2 (issue 3)
warm (kernels cached: median of --repeats), with the cold (first, compiling) times too.
"""
from __future__ import annotations

import argparse
import time

import mi_shadowmap  # noqa: F401
import drjit as dr
import mitsuba as mi

from mi_shadowmap.scenes import default_scene

from bench_all import build_vs_bare, timed  # same folder: shared benchmark helpers


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--image", type=int, default=512)
    ap.add_argument("--map", type=int, default=1024)
    ap.add_argument("--spp", type=int, default=1)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--light", default="spot", choices=["spot", "point", "directional"])
    args = ap.parse_args(argv)

    scene = mi.load_dict(default_scene(width=args.image, height=args.image, light=args.light))
    res = args.map

    frames = {}
    for method, cache in (("unshadowed", False), ("hard", False), ("hard", True),
                          ("raytraced", False)):
        integ = mi.load_dict({"type": "shadowmap", "method": method, "resolution": res,
                              "cache_maps": cache})

        def render(integ=integ):
            dr.eval(mi.render(scene, integrator=integ, spp=args.spp))
        frames[method + (" (maps cached)" if cache else "")] = timed(render, args.repeats)

    (cb, wb), (cm, wm) = build_vs_bare(scene, res, args.repeats)
    print(f"# {args.light} light, image {args.image}^2 @ {args.spp} spp, map {res}^2, "
          f"{dr.thread_count()} threads, mitsuba {mi.__version__}")
    print(f"{'measurement':<42}{'warm ms':>10}{'cold ms':>10}")
    print(f"{'bare ray_intersect_preliminary':<42}{wb * 1e3:>10.2f}{cb * 1e3:>10.2f}")
    print(f"{'depth-map build':<42}{wm * 1e3:>10.2f}{cm * 1e3:>10.2f}")
    for m, (c, w) in frames.items():
        print(f"{'frame: ' + m:<42}{w * 1e3:>10.2f}{c * 1e3:>10.2f}")
    print()
    print(f"(a) build / bare ray cast      = {wm / wb:.3f}   (target <= 1.1)")
    print(f"(b) hard / unshadowed frame    = {frames['hard'][1] / frames['unshadowed'][1]:.3f}"
          "   (target <= 1.4; Reeves: 1.37..1.51; maps rebuilt every frame)")
    print(f"    with maps cached           = "
          f"{frames['hard (maps cached)'][1] / frames['unshadowed'][1]:.3f}")
    print(f"(c) hard / raytraced frame     = {frames['hard'][1] / frames['raytraced'][1]:.3f}"
          "   (maps rebuilt every frame)")
    print(f"    with maps cached           = "
          f"{frames['hard (maps cached)'][1] / frames['raytraced'][1]:.3f}")
    method_table(scene, (res // 2, res), args.spp, args.repeats)


def method_table(scene, maps, spp, repeats):
    """Frame of each map method / hard frame, maps rebuilt and cached, per map size."""
    from mi_shadowmap.options import MAP_METHODS
    print(f"\n(d) frame / hard frame{'':<20}" + "".join(
        f"{f'{r}^2 rebuilt':>15}{f'{r}^2 cached':>15}" for r in maps))
    times = {}
    for res in maps:
        for method in MAP_METHODS:
            for cache in (False, True):
                integ = mi.load_dict({"type": "shadowmap", "method": method,
                                      "resolution": res, "cache_maps": cache})

                def render(integ=integ):
                    dr.eval(mi.render(scene, integrator=integ, spp=spp))
                times[(method, res, cache)] = timed(render, repeats)[1]
    for method in MAP_METHODS:
        print(f"    {method:<38}" + "".join(
            f"{times[(method, r, c)] / times[('hard', r, c)]:>15.2f}"
            for r in maps for c in (False, True)))


if __name__ == "__main__":
    main()
