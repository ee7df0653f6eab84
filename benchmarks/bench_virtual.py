"""Virtual shadow maps (issue 11): accuracy, texels built and frame times with
``virtual`` off and on, and the cost of a small camera move. One run, by hand:

    python benchmarks/bench_virtual.py [--scenes large_world far_point ...]
                                       [--methods hard pcf] [--virtual false true]
                                       [--image 256] [--spp 16] [--repeats 3]
                                       [--page-size N] [--props NAME=VALUE ...]
                                       [--out benchmarks/virtual_results.md]

For every scene of ``--scenes`` (names of scenes_xml/*.xml, default: all of them), at
``--image``^2 pixels and ``--spp`` spp, seed 0:

1. **Reference** (:func:`mi_shadowmap.harness.make_reference`, ``--reference``, default
   ``raytraced``: the same camera samples as every configuration) and **unshadowed**
   (median warm frame of ``method=unshadowed``, measured in the same run: the shading
   cost without any shadow).
2. For every method of ``--methods`` and every ``virtual`` of ``--virtual`` (passed
   explicitly: the integrator's default is automatic):

   * **misclassified** (threshold 0.5, pooled over emitters) against the reference;
   * **texels** built by the first frame (``stats["texels_built"]``) and per film pixel;
   * **built**: median warm frame with ``cache_maps=False`` (maps rebuilt every frame);
   * **cached**: median warm frame with the map cache on (maps and kernels cached);
   * for ``virtual=true``, ``pages_marked``, ``pages_built``, ``pages_reused`` and
     ``level_histogram`` of the first frame's stats when the integrator reports them;
   * **camera move**: with the maps cached, the sensor moves a little (``--move``
     world units sideways and ``--turn`` degrees of yaw, through ``mi.traverse``) and
     one frame renders: texels rebuilt / first-frame texels, that frame's time /
     unshadowed frame time, and the kernels Dr.Jit compiled for it (kernel history:
     entries without ``cache_hit``; a kernel loaded from the on-disk cache counts as
     a hit). The camera is put back afterwards.

A configuration whose integrator cannot be made (e.g. ``virtual=true`` before the
core has the property) prints its error and is reported as such in the table; the
other rows are still measured. Times are wall-clock on this machine after
``dr.sync_thread()``.
"""
from __future__ import annotations

import argparse
import pathlib
import statistics
import sys
import time

import mi_shadowmap  # noqa: F401  (LLVM set-up, registration)
import drjit as dr
import mitsuba as mi

from mi_shadowmap import harness
from mi_shadowmap.specs import parse_assignments, to_mitsuba, validate_spec
from mi_shadowmap.timing import compile_stats, render_timed, split_channels

ROOT = pathlib.Path(__file__).resolve().parents[1]
SCENES = ROOT / "scenes_xml"
PAGE_KEYS = ("pages_marked", "pages_built", "pages_reused", "level_histogram")


def parse_bool(s: str) -> bool:
    v = s.strip().lower()
    if v in ("true", "1", "yes", "on"):
        return True
    if v in ("false", "0", "no", "off"):
        return False
    raise argparse.ArgumentTypeError(f"not a boolean: {s!r}")


def make_integrator(method: str, virtual: bool, page_size: int | None, props=None,
                    **extra):
    """The shadowmap integrator of one configuration, validated like the harness does
    (an unknown property is an OptionError naming it); ``props``: ``--props``."""
    spec = {"method": method, "virtual": bool(virtual), **(props or {})}
    if virtual:
        if page_size is not None:
            spec["page_size"] = page_size
    validate_spec(spec)
    return mi.load_dict(to_mitsuba({"type": "shadowmap", **spec, **extra}))


def median_frame(scene, integ, spp, seed, repeats) -> float:
    return statistics.median(render_timed(scene, integ, spp, seed)[1]
                             for _ in range(max(1, repeats)))


def sensor_key(params) -> str:
    return next(k for k in params.keys() if k.endswith("to_world")
                and isinstance(params.properties[k][2], mi.Sensor))


def move_camera(scene, dx: float, yaw_deg: float):
    """Move the sensor ``dx`` along its own x axis and turn it ``yaw_deg`` about its own
    y axis; returns the previous transform (for :func:`set_camera`)."""
    params = mi.traverse(scene)
    key = sensor_key(params)
    old = params[key]
    old = type(old)(old)
    params[key] = (old @ mi.ScalarTransform4f().translate([dx, 0.0, 0.0])
                   @ mi.ScalarTransform4f().rotate([0.0, 1.0, 0.0], yaw_deg))
    params.update()
    return old


def set_camera(scene, to_world):
    params = mi.traverse(scene)
    params[sensor_key(params)] = to_world
    params.update()


def stat(stats, key):
    try:
        return stats.get(key)
    except AttributeError:   # a plain mapping without .get
        return stats[key] if key in stats else None


def run_config(scene, ref, method, virtual, args, t_unshadowed, n_pixels) -> dict:
    """Every measurement of one (method, virtual) configuration (see the module doc)."""
    row = {"method": method, "virtual": virtual}
    built = make_integrator(method, virtual, args.page_size, args.props, cache_maps=False)
    built.check_scene(scene)
    # first frame: kernels traced / compiled or loaded; maps built
    img, t_first = render_timed(scene, built, args.spp, args.seed)
    stats0 = built.stats
    row["texels"] = int(stats0["texels_built"])
    row["texels_per_pixel"] = row["texels"] / n_pixels
    if virtual:
        for k in PAGE_KEYS:
            row[k] = stat(stats0, k)
    image, vis = split_channels(img, built.aov_names())
    res = harness.MethodResult(name=method, method=method, params={"virtual": virtual},
                               image=image, visibility=vis, times={}, spp=args.spp)
    m = harness.score(res, ref)
    row["misclassified"] = m["vis_misclassified"]
    row["false_shadow"] = m["vis_false_shadow"]
    row["false_lit"] = m["vis_false_lit"]
    row["resolution"] = built.resolution
    row["t_first"] = t_first
    row["t_built"] = median_frame(scene, built, args.spp, args.seed, args.repeats)
    del built

    cached = make_integrator(method, virtual, args.page_size, args.props)
    render_timed(scene, cached, args.spp, args.seed)            # primes the map cache
    row["t_cached"] = median_frame(scene, cached, args.spp, args.seed, args.repeats)

    # camera move, maps cached: what the next frame rebuilds and compiles
    old = move_camera(scene, args.move, args.turn)
    try:
        had = dr.flag(dr.JitFlag.KernelHistory)
        dr.kernel_history()                                     # drop older entries
        dr.set_flag(dr.JitFlag.KernelHistory, True)
        try:
            _, t_move = render_timed(scene, cached, args.spp, args.seed)
            compile_s, n_compiled = compile_stats(dr.kernel_history())
        finally:
            dr.set_flag(dr.JitFlag.KernelHistory, had)
        stats1 = cached.stats
        row["move_texels"] = int(stats1["texels_built"])
        if virtual:
            for k in PAGE_KEYS:
                row["move_" + k] = stat(stats1, k)
    finally:
        set_camera(scene, old)
    row["t_move"] = t_move
    row["move_kernels_compiled"] = n_compiled
    row["move_compile_s"] = compile_s
    row["move_texel_ratio"] = row["move_texels"] / row["texels"] if row["texels"] else None
    row["move_vs_unshadowed"] = t_move / t_unshadowed
    return row


def bench_scene(name, args) -> dict:
    path = SCENES / f"{name}.xml"
    scene = harness.load_scene(str(path), width=str(args.image), height=str(args.image))
    n_pixels = args.image * args.image
    t0 = time.perf_counter()
    ref = harness.make_reference(scene, args.reference, spp=args.spp, seed=args.seed)
    print(f"{name}: reference {ref.name} ({time.perf_counter() - t0:.1f} s)", flush=True)
    unsh = harness.run_method(scene, "unshadowed", spp=args.spp, seed=args.seed,
                              repeats=args.repeats, measure_cached=False)
    t_unsh = unsh.times["warm"]
    print(f"{name}: unshadowed frame {t_unsh:.3f} s", flush=True)
    out = {"scene": name, "reference": ref.name, "t_unshadowed": t_unsh, "rows": [],
           "errors": []}
    for method in args.methods:
        for virtual in args.virtual:
            label = f"{name} {method} virtual={str(virtual).lower()}"
            t0 = time.perf_counter()
            try:
                row = run_config(scene, ref, method, virtual, args, t_unsh, n_pixels)
            except Exception as exc:   # reported, not hidden: the other rows still run
                msg = f"{type(exc).__name__}: {exc}"
                print(f"  {label}: FAILED -- {msg}", file=sys.stderr, flush=True)
                out["errors"].append({"method": method, "virtual": virtual, "error": msg})
                continue
            out["rows"].append(row)
            print(f"  {label}: misclassified {row['misclassified']:.2%}, "
                  f"{row['texels_per_pixel']:.1f} texels/pixel, built "
                  f"{row['t_built']:.3f} s, cached {row['t_cached']:.3f} s, move "
                  f"{row['t_move']:.3f} s ({row['move_kernels_compiled']} kernels compiled) "
                  f"[{time.perf_counter() - t0:.1f} s]", flush=True)
    return out


def fmt(v, spec=".3f"):
    if v is None:
        return "-"
    if isinstance(v, (list, tuple, dict)):
        return str(v).replace("|", "/")
    if isinstance(v, float):
        return format(v, spec)
    return str(v)


def report(results, args) -> str:
    lines = [f"# Virtual shadow maps: {args.image}^2 image, {args.spp} spp, seed {args.seed}, "
             f"median of {args.repeats} warm frames", "",
             f"Camera move: {args.move} units sideways, {args.turn} degrees of yaw, maps "
             "cached. Times in seconds; `x unsh.` = frame time / unshadowed frame time.", "",
             "| scene | method | virtual | misclassified | false lit | false shadow | "
             "texels (1st frame) | texels / pixel | built | cached | unshadowed | "
             "cached x unsh. | move: texels rebuilt / 1st | move: frame | move x unsh. | "
             "move: kernels compiled |",
             "|---" * 16 + "|"]
    for r in results:
        for x in r["rows"]:
            lines.append(
                f"| {r['scene']} | {x['method']} | {str(x['virtual']).lower()} | "
                f"{x['misclassified']:.2%} | {x['false_lit']:.2%} | {x['false_shadow']:.2%} | "
                f"{x['texels']} | {x['texels_per_pixel']:.1f} | {x['t_built']:.3f} | "
                f"{x['t_cached']:.3f} | {r['t_unshadowed']:.3f} | "
                f"{x['t_cached'] / r['t_unshadowed']:.2f} | {fmt(x['move_texel_ratio'])} | "
                f"{x['t_move']:.3f} | {x['move_vs_unshadowed']:.2f} | "
                f"{x['move_kernels_compiled']} |")
        for e in r["errors"]:
            lines.append(f"| {r['scene']} | {e['method']} | {str(e['virtual']).lower()} | "
                         f"error: {e['error'].replace('|', '/')} |" + " |" * 12)
    virt = [(r["scene"], x) for r in results for x in r["rows"] if x["virtual"]]
    if virt:
        lines += ["", "Virtual pages (first frame / after the camera move):", "",
                  "| scene | method | " + " | ".join(PAGE_KEYS) + " | "
                  + " | ".join("move: " + k for k in PAGE_KEYS) + " |",
                  "|---" * (2 + 2 * len(PAGE_KEYS)) + "|"]
        for scene, x in virt:
            lines.append(f"| {scene} | {x['method']} | "
                         + " | ".join(fmt(x.get(k)) for k in PAGE_KEYS) + " | "
                         + " | ".join(fmt(x.get("move_" + k)) for k in PAGE_KEYS) + " |")
    refs = ", ".join(f"{r['scene']}: {r['reference']}" for r in results)
    lines += ["", f"References: {refs}. Map resolution (automatic unless the core picks "
              "otherwise): " + ", ".join(f"{r['scene']} {x['method']} "
                                          f"virtual={str(x['virtual']).lower()}: "
                                          f"{x['resolution']}"
                                          for r in results for x in r["rows"])]
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", nargs="+",
                    default=sorted(p.stem for p in SCENES.glob("*.xml")),
                    help="scene names of scenes_xml/ (default: all)")
    ap.add_argument("--methods", nargs="+", default=["hard", "pcf"])
    ap.add_argument("--virtual", nargs="+", type=parse_bool, default=[False, True],
                    help="values of the integrator's virtual property to measure")
    ap.add_argument("--page-size", type=int, default=None,
                    help="page_size passed with virtual=true (default: the core's)")
    ap.add_argument("--image", type=int, default=256)
    ap.add_argument("--spp", type=int, default=16)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--reference", default="raytraced",
                    help="reference: a method spec, 'auto' or 'converged' (harness)")
    ap.add_argument("--move", type=float, default=0.05,
                    help="camera move, world units along the sensor's x axis")
    ap.add_argument("--turn", type=float, default=1.0, help="camera yaw, degrees")
    ap.add_argument("--props", nargs="+", default=[],
                    metavar="NAME=VALUE",
                    help="further integrator properties of every configuration, e.g. "
                         "cascades=4")
    ap.add_argument("--out", default=str(ROOT / "benchmarks" / "virtual_results.md"))
    args = ap.parse_args(argv)
    args.props = parse_assignments(args.props, "--props")
    missing = [s for s in args.scenes if not (SCENES / f"{s}.xml").exists()]
    if missing:
        ap.error(f"no scenes_xml/{missing[0]}.xml")
    results = [bench_scene(name, args) for name in args.scenes]
    text = report(results, args)
    print("\n" + text)
    pathlib.Path(args.out).write_text(text)
    print(f"written to {args.out}")
    return 1 if any(r["errors"] for r in results) and not any(r["rows"] for r in results) \
        else 0


if __name__ == "__main__":
    sys.exit(main())
