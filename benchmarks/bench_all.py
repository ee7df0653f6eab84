"""Cost ratios of every method, each measured within one run (run by hand, not in CI).

    python benchmarks/bench_all.py [--image 512] [--map 1024] [--repeats 5] [--quick]
                                   [--triangles 1000000] [--markdown FILE]

Prints one table of ratios (and the times they come from):

  A. depth-map build / bare ray cast over the same texel rays
     (built-in scene, and a procedural mesh of >= 1 M triangles);
  B. frame / unshadowed frame for every method (Reeves et al. 1987, Table 1: shadows
     cost +40..50 % over the unshadowed render), on both scenes;
  C. frame with L = 1, 2, 4, 8 spot lights / frame with L = 1, per method
     (Reeves: less than (1 + L) x);
  D. cold (first render, JIT) / warm (kernels cached, maps rebuilt) / cached
     (maps and kernels cached) per method;
  E. equal-time visibility error against ray tracing on a soft-shadow (area light)
     scene: for each map method configuration, the error of the best ray-traced
     configuration that is not slower, divided by its own error (> 1: the map method
     wins), with Mitsuba's 'independent' and 'multijitter' (stratified) samplers.

Every method comes from ``mi_shadowmap.options.METHODS`` (those with an
implementation); times are medians of ``--repeats`` warm renders. Times move with
the machine's load: compare ratios measured in the same run, not across runs.
"""
from __future__ import annotations

import argparse
import datetime
import os
import platform
import statistics
import sys
import tempfile
import time

import mi_shadowmap  # noqa: F401  (LLVM set-up, variant, registration)
import drjit as dr
import mitsuba as mi

from mi_shadowmap import harness, procedural
from mi_shadowmap.depth_maps import build_depth_map
from mi_shadowmap.light_views import make_light_view
from mi_shadowmap.options import MAP_METHODS
from mi_shadowmap.scenes import default_scene

T = mi.ScalarTransform4f
LINES: list[str] = []


def out(line: str = "") -> None:
    print(line, flush=True)
    LINES.append(line)


def timed(fn, repeats):
    """(cold, median warm) seconds of ``fn`` (synchronised)."""
    t0 = time.perf_counter()
    fn()
    dr.sync_thread()
    cold = time.perf_counter() - t0
    warm = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        dr.sync_thread()
        warm.append(time.perf_counter() - t0)
    return cold, statistics.median(warm)


# --------------------------------------------------------------------------- scenes
def heavy_name(n_triangles: int) -> str:
    """The heavy scene's label in the table: its ``--triangles`` (rows said "1M" for any)."""
    if n_triangles % 1_000_000 == 0:
        return f"{n_triangles // 1_000_000}M-triangle mesh"
    return f"{n_triangles:,}-triangle mesh"


def heavy_scene(n_triangles: int, width: int, folder: str) -> dict:
    """The procedural terrain-with-pillars mesh (written as PLY) under a spot light."""
    path = os.path.join(folder, "big_mesh.ply")
    v, f, _ = procedural.big_mesh(n_triangles, path=path)
    out(f"# heavy scene: {len(f):,} triangles, {len(v):,} vertices ({path})")
    return {
        "type": "scene",
        "sensor": {"type": "perspective", "fov": 45,
                   "to_world": T().look_at(origin=[0, 2.6, 4.2], target=[0, 0.2, 0],
                                           up=[0, 1, 0]),
                   "sampler": {"type": "independent", "sample_count": 1},
                   "film": {"type": "hdrfilm", "width": width, "height": width,
                            "rfilter": {"type": "box"}}},
        "terrain": {"type": "ply", "filename": path,
                    "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb",
                                                                "value": [0.6, 0.55, 0.5]}}},
        "spot": {"type": "spot", "to_world": T().look_at(origin=[-2.5, 4.0, -2.0],
                                                        target=[0, 0, 0], up=[0, 1, 0]),
                 "intensity": {"type": "rgb", "value": 150.0},
                 "cutoff_angle": 45.0, "beam_width": 40.0},
    }


def multi_light_scene(n_lights: int, width: int) -> dict:
    """The built-in scene with ``n_lights`` spot lights around it (same total power)."""
    scene = default_scene(width=width, height=width, spp=1, light="spot")
    spot = scene.pop("spot")
    for k in range(n_lights):
        s = dict(spot)
        s["to_world"] = T().rotate([0, 1, 0], 360.0 * k / n_lights) @ spot["to_world"]
        s["intensity"] = {"type": "rgb", "value": 120.0 / n_lights}
        scene[f"spot{k}"] = s
    return scene


def methods_to_time() -> list[str]:
    return [m for m in harness.available_methods() if m != "unshadowed"]


# --------------------------------------------------------------------------- parts
def build_vs_bare(scene, res, repeats):
    """``((cold, warm) bare ray cast, (cold, warm) depth-map build)`` over the same
    texel rays of the first emitter's view."""
    view = make_light_view(scene.emitters()[0], scene, 0)

    def bare():
        o, d = view.texel_rays(res)
        pi = scene.ray_intersect_preliminary(mi.Ray3f(o, d), coherent=True)
        dr.eval(pi.t)

    def build():
        build_depth_map(scene, view, res)

    return timed(bare, repeats), timed(build, repeats)


def part_a(scene, res, repeats, label):
    (cb, wb), (cm, wm) = build_vs_bare(scene, res, repeats)
    out(f"| A | {label}: depth-map build / bare ray cast ({res}^2 rays) | {wm / wb:.2f} | "
        f"build {wm * 1e3:.1f} ms, rays {wb * 1e3:.1f} ms (cold {cm * 1e3:.0f} / "
        f"{cb * 1e3:.0f} ms) |")


def frames(scene, methods, spp, repeats, res, cached=False):
    """{method: MethodResult} for every method (maps rebuilt per frame)."""
    resd = {}
    for m in methods:
        params = {"resolution": res} if m in MAP_METHODS else {}
        resd[m] = harness.run_method(scene, m, spp=spp, repeats=repeats,
                                     measure_cached=cached, **params)
    return resd


def part_b(results, label):
    base = results["unshadowed"].times["warm"]
    base_c = results["unshadowed"].times.get("cached")
    for m, r in results.items():
        if m == "unshadowed":
            continue
        cached = ""
        if base_c and r.times.get("cached"):
            cached = (f"; maps cached: {r.times['cached'] / base_c:.2f} "
                      f"({r.times['cached'] * 1e3:.1f} ms)")
        out(f"| B | {label}: {m} frame / unshadowed frame | {r.times['warm'] / base:.2f} | "
            f"{r.times['warm'] * 1e3:.1f} ms vs {base * 1e3:.1f} ms (build "
            f"{r.times['build'] * 1e3:.1f} ms){cached} |")


def part_c(width, spp, repeats, res, methods):
    times = {}
    for n in (1, 2, 4, 8):
        scene = mi.load_dict(multi_light_scene(n, width))
        for m in methods + ["unshadowed"]:
            params = {"resolution": res} if m in MAP_METHODS else {}
            r = harness.run_method(scene, m, spp=spp, repeats=repeats, measure_cached=False,
                                   **params)
            times[(m, n)] = r.times["warm"]
    for m in methods + ["unshadowed"]:
        ratios = ", ".join(f"L={n}: {times[(m, n)] / times[(m, 1)]:.2f}" for n in (2, 4, 8))
        ok = all(times[(m, n)] / times[(m, 1)] < 1 + n for n in (2, 4, 8))
        out(f"| C | {m}: frame(L) / frame(1) | {ratios} | bound 1+L = 3, 5, 9: "
            f"{'within' if ok else 'EXCEEDED'}; L=1 {times[(m, 1)] * 1e3:.1f} ms |")


def part_d(results, label):
    for m, r in results.items():
        t = r.times
        out(f"| D | {label}: {m} cold / warm / cached | {t['cold'] / t['warm']:.1f} / 1 / "
            f"{t['cached'] / t['warm']:.2f} | cold {t['cold'] * 1e3:.0f} ms (compile "
            f"{t['compile'] * 1e3:.0f} ms, {r.kernels_compiled} kernels compiled), warm "
            f"{t['warm'] * 1e3:.1f} ms, cached {t['cached'] * 1e3:.1f} ms |")


def part_e(width, spp, repeats, quick):
    soft_methods = [m for m in harness.available_methods() if m in MAP_METHODS]
    if not soft_methods:
        out("| E | no map method available | - | |")
        return
    rt_spp = [1, 4, 9] if quick else [1, 4, 9, 16, 36]   # squares: multijitter keeps them
    grid = [{"method": [m for m in soft_methods if m in ("pcss", "pcf", "hard")]
             or soft_methods, "resolution": [256, 512], "spp": [1, spp]},
            {"method": "raytraced", "spp": rt_spp, "shadow_rays": [1, 4]}]
    for sampler in ("independent", "multijitter"):
        d = default_scene(width=width, height=width, spp=spp, light="area")
        d["sensor"]["sampler"] = {"type": sampler, "sample_count": spp}
        scene = mi.load_dict(d)
        table = harness.sweep(scene, grid, spp=spp, repeats=repeats, progress=False,
                              measure_cached=True,
                              ref_spp=64, ref_shadow_rays=64 if quick else 256)
        cached = {r["name"]: r for r in
                  harness.analyse([dict(r) for r in table.rows], time_key="time_cached")}
        for r in table:
            if r["method"] == "raytraced":
                continue
            ratio = r["error_ratio_equal_time"]
            ratio_c = cached[r["name"]]["error_ratio_equal_time"]
            rt_err = r["rt_error_equal_time"]
            fmt = lambda v: "-" if v is None else f"{v:.2f}"  # noqa: E731
            out(f"| E | area light, {sampler}: {r['name']}: equal-time error ratio RT / map "
                f"(maps rebuilt; maps cached) | {fmt(ratio)}; {fmt(ratio_c)} | map RMSE "
                f"{r['error']:.4f} in {r['time'] * 1e3:.1f} ms (cached "
                f"{r['time_cached'] * 1e3:.1f} ms); best RT not slower: "
                f"{'-' if rt_err is None else f'{rt_err:.4f}'} |")
        best = min((r for r in table if r["method"] == "raytraced"), key=lambda r: r["error"])
        out(f"| E | area light, {sampler}: best ray tracing of the grid | - | "
            f"{best['name']}: RMSE {best['error']:.4f} in {best['time'] * 1e3:.1f} ms |")


# --------------------------------------------------------------------------- main
def machine() -> str:
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    return (f"{cpu}, {os.cpu_count()} cores visible, Dr.Jit {dr.thread_count()} threads, "
            f"{platform.system()} {platform.release()}, Python {platform.python_version()}, "
            f"Mitsuba {mi.__version__}, Dr.Jit {dr.__version__}, variant {mi.variant()}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--image", type=int, default=512, help="image side (default 512)")
    ap.add_argument("--map", type=int, default=1024, help="depth-map resolution (default 1024)")
    ap.add_argument("--spp", type=int, default=1, help="spp of the frame timings (default 1)")
    ap.add_argument("--repeats", type=int, default=5, help="warm repeats (median; default 5)")
    ap.add_argument("--triangles", type=int, default=1_000_000,
                    help="triangles of the heavy procedural mesh (default 1,000,000)")
    ap.add_argument("--quick", action="store_true", help="smaller parts C and E")
    ap.add_argument("--markdown", default=None, help="also write the table to this file")
    args = ap.parse_args(argv)

    t_start = time.perf_counter()
    stamp = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    out(f"# bench_all {stamp}")
    out(f"# machine: {machine()}")
    out(f"# image {args.image}^2 @ {args.spp} spp, maps {args.map}^2, median of "
        f"{args.repeats} warm renders; command: python benchmarks/bench_all.py "
        + " ".join(sys.argv[1:] if argv is None else argv))
    out()
    out("| part | ratio | value | times |")
    out("|---|---|---|---|")
    methods = methods_to_time()
    with tempfile.TemporaryDirectory() as tmp:
        base = mi.load_dict(default_scene(width=args.image, height=args.image, spp=args.spp))
        part_a(base, args.map, args.repeats, "built-in scene")
        res_base = frames(base, methods + ["unshadowed"], args.spp, args.repeats, args.map,
                          cached=True)
        part_b(res_base, "built-in scene")
        part_d(res_base, "built-in scene")
        t0 = time.perf_counter()
        heavy = mi.load_dict(heavy_scene(args.triangles, args.image, tmp))
        out(f"# heavy scene loaded in {time.perf_counter() - t0:.1f} s")
        heavy_label = heavy_name(args.triangles)
        part_a(heavy, args.map, args.repeats, heavy_label)
        res_heavy = frames(heavy, [m for m in ("raytraced", "hard") if m in methods]
                           + ["unshadowed"], args.spp, args.repeats, args.map, cached=True)
        part_b(res_heavy, heavy_label)
        part_c(args.image, args.spp, max(args.repeats, 7), args.map,
               [m for m in ("raytraced", "hard", "pcf") if m in methods])
        part_e(128 if args.quick else 192, 4, max(2, args.repeats // 2), args.quick)
    out()
    out(f"# total benchmark time {time.perf_counter() - t_start:.0f} s")
    if args.markdown:
        with open(args.markdown, "w") as f:
            f.write("\n".join(LINES) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
