"""Cost of one depth-map lookup / one shadow ray, and where the lookup's time goes (issue 11).

    python benchmarks/bench_lookup.py [--image 512] [--map 1024] [--repeats 9] [--heavy]
                                      [--triangles 1000000]

Per-sample costs, all measured interleaved in one run (every configuration is rendered
once per round, rounds repeated ``--repeats`` times, medians taken):

* lookup cost     = frame(hard, maps cached) - frame(unshadowed)
* shadow-ray cost = frame(raytraced) - frame(unshadowed)

and their ratio. Each frame is split with Dr.Jit's kernel history into the render
kernel's execution (the megakernel of ``sample()``, one lane per camera sample), the
other kernels (film development, small evaluations) and the host time (Python tracing
of ``sample()``, kernel-cache look-up, the first pass ``prepare_maps``: map-cache check,
light views), so that a per-frame fixed cost is not mistaken for a per-lookup one.

The ``hard`` lookup is then decomposed by registering variants of it as user methods
(``mi_shadowmap.register_method``; maps cached, same biases as ``hard``):

  lk_const     visibility 1: the integrator's work around a map lookup, no lookup
  lk_gather0   one gather of the depth map at a fixed texel and a compare
  lk_project   ``view.project`` + the nearest-texel gather + a compare, no biases
  lk_receiver  ``receiver()`` (biases) + a compare with a constant, no gather
  lk_hard      ``hard`` itself (``receiver()`` + the gather + the compare)
  rt_ray       ``raytraced`` itself (one shadow ray), as a user method

each returning exactly 1 (see below), so that the image and the work after the lookup
are those of ``unshadowed`` whatever the variant computes.

Times move with the machine's load: compare the ratios of one run.
"""
from __future__ import annotations

import argparse
import statistics
import tempfile
import time

import mi_shadowmap  # noqa: F401  (LLVM set-up, variant, registration)
import drjit as dr
import mitsuba as mi

from mi_shadowmap.filters.common import Lookup, RayTracedLight, receiver
from mi_shadowmap.filters.hard import hard
from mi_shadowmap.filters.raytraced import METHOD as RAYTRACED, raytraced
from mi_shadowmap.scenes import default_scene

from bench_all import heavy_scene, machine   # same folder: shared benchmark helpers


# --------------------------------------------------------------------------- lookups
# Every variant returns exactly 1 (its visibility, raised to a run-time 1 the compiler
# cannot see through): the image and all the work after the lookup are those of
# ``unshadowed``, so the differences are the lookup's own work. (A shadowed sample costs
# less after the lookup: ``hard - lk_hard`` shows that saving.)
def _one():
    return dr.opaque(mi.Float, 1.0)


def lk_const(smap, lk, opts, active):
    return _one()


def lk_gather0(smap, lk, opts, active):
    z = dr.gather(mi.Float, smap.depth, mi.UInt32(0), active)
    return dr.maximum(dr.select(dr.norm(lk.p_world) <= z, 1.0, 0.0), _one())


def lk_project(smap, lk, opts, active):
    face, uv, depth, inside = smap.view.project(lk.p_world)
    z = dr.gather(mi.Float, smap.depth, smap.texel_index(face, uv), active & inside)
    return dr.maximum(dr.select(~inside | (depth <= z), 1.0, 0.0), _one())


def lk_receiver(smap, lk, opts, active):
    r = receiver(smap, lk, opts)
    return dr.maximum(dr.select(~r.inside | (r.depth <= r.texel_world), 1.0, 0.0), _one())


def lk_hard(smap, lk, opts, active):
    return dr.maximum(hard(smap, lk, opts, active), _one())


def rt_ray(smap, lk, opts, active):
    return dr.maximum(raytraced(smap, lk, opts, active), _one())


#: name -> (lookup, uses_map)
VARIANTS = {"lk_const": (lk_const, True), "lk_gather0": (lk_gather0, True),
            "lk_project": (lk_project, True), "lk_receiver": (lk_receiver, True),
            "lk_hard": (lk_hard, True), "rt_ray": (rt_ray, False)}
#: properties a variant reads besides the common ones (``raytraced`` reads its
#: ``light_sample``: without it ``opts.light_sample`` raises)
PROPERTIES = {"rt_ray": list(RAYTRACED.properties)}


# --------------------------------------------------------------------------- timing
def frame_parts(scene, integ, n_samples, seed=0):
    """One synchronised render: ``{frame, kernel, other, host, prepare}`` seconds."""
    dr.sync_thread()
    dr.kernel_history()   # drop older entries
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    t0 = time.perf_counter()
    dr.eval(mi.render(scene, integrator=integ, spp=1, seed=seed))
    dr.sync_thread()
    frame = time.perf_counter() - t0
    dr.set_flag(dr.JitFlag.KernelHistory, False)
    hist = dr.kernel_history()
    main = [h["execution_time"] for h in hist
            if h["type"] == dr.KernelType.JIT and h["size"] == n_samples]
    total = sum(h.get("execution_time", 0.0) for h in hist) * 1e-3
    kernel = sum(main) * 1e-3
    return {"frame": frame, "kernel": kernel, "other": total - kernel, "host": frame - total,
            "prepare": getattr(integ, "build_seconds", 0.0)}


def measure(scene, configs, n_samples, repeats):
    """Interleaved: ``{name: {part: median seconds}}`` over ``repeats`` rounds."""
    integs = {name: mi.load_dict(props) for name, props in configs.items()}
    for integ in integs.values():          # compile and fill the map cache
        frame_parts(scene, integ, n_samples)
        frame_parts(scene, integ, n_samples)
    samples = {name: [] for name in integs}
    for _ in range(repeats):
        for name, integ in integs.items():
            samples[name].append(frame_parts(scene, integ, n_samples))
    return {name: {k: statistics.median(s[k] for s in runs) for k in runs[0]}
            for name, runs in samples.items()}


def report(label, t, n_samples):
    ns = lambda s: s * 1e9 / n_samples          # noqa: E731  seconds per frame -> ns/sample
    base = t["unshadowed"]
    print(f"\n## {label}: {n_samples:,} camera samples, medians (ms per frame; "
          f"d = minus unshadowed, ns per sample)")
    print(f"{'config':<13}{'frame':>8}{'kernel':>8}{'other':>7}{'host':>7}{'prepare':>8}"
          f"{'d frame':>9}{'d kernel':>9}{'d host':>8}")
    for name, r in t.items():
        print(f"{name:<13}{r['frame'] * 1e3:>8.2f}{r['kernel'] * 1e3:>8.2f}"
              f"{r['other'] * 1e3:>7.2f}{r['host'] * 1e3:>7.2f}{r['prepare'] * 1e3:>8.2f}"
              f"{ns(r['frame'] - base['frame']):>9.1f}{ns(r['kernel'] - base['kernel']):>9.1f}"
              f"{ns(r['host'] - base['host']):>8.1f}")
    print("lookup / shadow ray, (hard - unshadowed) / (raytraced - unshadowed):")
    for part in ("frame", "kernel"):
        look = t["hard"][part] - base[part]
        ray = t["raytraced"][part] - base[part]
        print(f"  {part:<7}{ns(look):6.1f} / {ns(ray):6.1f} ns per sample = "
              f"{look / ray if ray > 0 else float('nan'):.2f}")
    if "lk_hard" not in t:
        return
    c = t["lk_const"]["kernel"]
    look, ray = t["lk_hard"]["kernel"] - c, t["rt_ray"]["kernel"] - c
    print(f"  work only (render kernel, every sample lit: lk_hard / rt_ray - lk_const): "
          f"{ns(look):.1f} / {ns(ray):.1f} = {look / ray if ray > 0 else float('nan'):.2f}")

    hard_frame = t["hard"]["frame"] - base["frame"]
    rows = [("first pass: prepare_maps (map cache check, views)", t["hard"]["prepare"]),
            ("rest of the host: tracing sample(), launch",
             t["hard"]["host"] - t["hard"]["prepare"] - (base["host"] - base["prepare"])),
            ("other kernels (film, small evaluations)", t["hard"]["other"] - base["other"]),
            ("render kernel: integrator around a lookup", t["lk_const"]["kernel"] - base["kernel"]),
            ("render kernel: gather at a fixed texel + compare",
             t["lk_gather0"]["kernel"] - t["lk_const"]["kernel"]),
            ("render kernel: project + nearest-texel index",
             t["lk_project"]["kernel"] - t["lk_gather0"]["kernel"]),
            ("render kernel: receiver() biases", t["lk_hard"]["kernel"] - t["lk_project"]["kernel"]),
            ("render kernel: shadowed samples' saving after it",
             t["hard"]["kernel"] - t["lk_hard"]["kernel"])]
    print(f"where hard's frame cost goes ({ns(hard_frame):.1f} ns per sample = "
          f"{hard_frame * 1e3:.2f} ms per frame over unshadowed):")
    for what, d in rows:
        print(f"  {what:<52}{ns(d):7.1f} ns {d / hard_frame if hard_frame > 0 else float('nan'):6.0%}")
    rest = hard_frame - sum(d for _, d in rows)
    print(f"  {'(medians do not add up exactly)':<52}{ns(rest):7.1f} ns")
    d = t["lk_receiver"]["kernel"] - c
    print(f"  (receiver() alone, no gather: {ns(d):.1f} ns; lk_project - lk_const: "
          f"{ns(t['lk_project']['kernel'] - c):.1f} ns)")


# ------------------------------------------------------------------ isolated kernels
def shading_points(scene, width):
    """The camera's first hits (pixel centres) and one light sample each, evaluated:
    ``(Lookup, active)`` as the integrator builds them for the first emitter."""
    n = width * width
    idx = dr.arange(mi.UInt32, n)
    pos = mi.Point2f((mi.Float(idx % width) + 0.5) / width, (mi.Float(idx // width) + 0.5) / width)
    ray, _ = scene.sensors()[0].sample_ray(0.0, 0.5, pos, mi.Point2f(0.5))
    si = scene.ray_intersect(ray)
    rng = mi.PCG32(n)
    u = mi.Point2f(rng.next_float32(), rng.next_float32())
    ds, _ = scene.emitters()[0].sample_direction(si, u, si.is_valid())
    active = si.is_valid() & (ds.pdf > 0)
    dr.eval(si, ds, active)
    zero = mi.Vector3f(0.0)
    return Lookup(si.p, si.n, zero, zero, si, ds, None), active


def isolated(scene, integ, width, repeats):
    """Each lookup (and one shadow ray) alone in its own kernel over the same evaluated
    shading points: ``{name: median seconds}``, rounds interleaved. Its own loads and
    its one store included; ``load_store`` reads the point and writes a float only."""
    lk, active = shading_points(scene, width)
    smap, opts = integ.maps[0], integ.opts
    rt = RayTracedLight(scene, scene.emitters()[0])   # the emitter shading_points samples
    rt_opts = mi.load_dict({"type": "shadowmap", "method": "raytraced"}).opts
    kernels = {
        "load_store": lambda: dr.select(active, lk.p_world.x, 0.0),
        "gather0": lambda: lk_gather0_raw(smap, lk, active),
        "project": lambda: lk_project_only(smap, lk),
        "project+gather": lambda: lk_project_raw(smap, lk, active),
        "receiver": lambda: lk_receiver_raw(smap, lk, opts),
        "hard": lambda: hard(smap, lk, opts, active),
        "shadow ray": lambda: raytraced(rt, lk, rt_opts, active),
    }

    def one(fn):
        dr.sync_thread()
        dr.kernel_history()
        dr.set_flag(dr.JitFlag.KernelHistory, True)
        dr.eval(fn())
        dr.sync_thread()
        dr.set_flag(dr.JitFlag.KernelHistory, False)
        return sum(h["execution_time"] for h in dr.kernel_history()
                   if h["type"] == dr.KernelType.JIT) * 1e-3

    for fn in kernels.values():
        one(fn)
    runs = {name: [] for name in kernels}
    for _ in range(repeats):
        for name, fn in kernels.items():
            runs[name].append(one(fn))
    return {name: statistics.median(r) for name, r in runs.items()}


def lk_gather0_raw(smap, lk, active):
    z = dr.gather(mi.Float, smap.depth, mi.UInt32(0), active)
    return dr.select(dr.norm(lk.p_world) <= z, 1.0, 0.0)


def lk_project_raw(smap, lk, active):
    face, uv, depth, inside = smap.view.project(lk.p_world)
    z = dr.gather(mi.Float, smap.depth, smap.texel_index(face, uv), active & inside)
    return dr.select(~inside | (depth <= z), 1.0, 0.0)


def lk_project_only(smap, lk):
    face, uv, depth, inside = smap.view.project(lk.p_world)
    ij = smap.texel_index(face, uv)
    return dr.select(~inside | (depth <= mi.Float(ij)), 1.0, 0.0)


def lk_receiver_raw(smap, lk, opts):
    r = receiver(smap, lk, opts)
    return dr.select(~r.inside | (r.depth <= r.texel_world), 1.0, 0.0)


def report_isolated(label, t, n_samples):
    ns = lambda s: s * 1e9 / n_samples          # noqa: E731
    base = t["load_store"]
    print(f"isolated kernels ({label}; ns per sample, and minus load_store):")
    for name, s in t.items():
        print(f"  {name:<16}{ns(s):7.2f}{ns(s - base):7.2f}")
    print(f"  lookup / shadow ray (minus load_store): "
          f"{(t['hard'] - base) / (t['shadow ray'] - base):.2f}")


def run(scene, args, label, variants=True):
    n = args.image * args.image
    common = {"type": "shadowmap", "cache_maps": True}
    configs = {"unshadowed": {**common, "method": "unshadowed"},
               "raytraced": {**common, "method": "raytraced"},
               "hard": {**common, "method": "hard", "resolution": args.map}}
    if variants:
        for name, (_, uses_map) in VARIANTS.items():
            configs[name] = {**common, "method": name,
                             **({"resolution": args.map} if uses_map else {})}
    report(label, measure(scene, configs, n, args.repeats), n)
    integ = mi.load_dict(configs["hard"])
    dr.eval(mi.render(scene, integrator=integ, spp=1))   # its maps (cached)
    report_isolated(label, isolated(scene, integ, args.image, args.repeats), n)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--image", type=int, default=512)
    ap.add_argument("--map", type=int, default=1024)
    ap.add_argument("--repeats", type=int, default=9)
    ap.add_argument("--heavy", action="store_true", help="also the 1M-triangle scene")
    ap.add_argument("--triangles", type=int, default=1_000_000)
    args = ap.parse_args(argv)

    for name, (fn, uses_map) in VARIANTS.items():
        mi_shadowmap.register_method(name, fn, uses_map=uses_map, replace=True,
                                     properties=PROPERTIES.get(name),
                                     summary="bench_lookup variant")
    print(f"# bench_lookup: image {args.image}^2 @ 1 spp, map {args.map}^2, median of "
          f"{args.repeats} interleaved rounds")
    print(f"# machine: {machine()}")
    try:
        scene = mi.load_dict(default_scene(width=args.image, height=args.image, spp=1))
        run(scene, args, "built-in scene")
        if args.heavy:
            with tempfile.TemporaryDirectory() as tmp:
                scene = mi.load_dict(heavy_scene(args.triangles, args.image, tmp))
                run(scene, args, f"{args.triangles:,}-triangle mesh")
    finally:
        for name in VARIANTS:
            mi_shadowmap.unregister_method(name)


if __name__ == "__main__":
    main()
