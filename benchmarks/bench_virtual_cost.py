"""Virtual shadow maps (issue 11): the single-frame cost with maps built, and PCSS at
equal time. One run, by hand:

    python benchmarks/bench_virtual_cost.py [--triangles 1000000] [--image 256] [--spp 64]
                                            [--soft-image 512] [--rounds 5] [--cpu]
                                            [--best-of 3]

1. **Shadow cost, maps built, heavy scene.** The procedural mesh of
   ``benchmarks/bench_all.py`` (``--triangles``, under a spot light) at ``--image``^2 and
   ``--spp``: frames of ``unshadowed``, ``raytraced``, ``hard`` with full maps and
   ``hard`` with virtual maps, both with ``cache_maps=false`` (every frame builds its
   maps), rendered interleaved in ``--rounds`` rounds (medians). The shadow cost of a
   method is its frame minus the unshadowed frame; the table gives each method's shadow
   cost over ``raytraced``'s (issue 11's target for ``hard`` virtual: <= 0.7), from the
   medians, and the same ratio within each round (median and range over the rounds: the
   machine's speed drifts between rounds by more than a shadow cost).
2. **PCSS at equal time, maps built.** ``scenes_xml/cbox_area.xml`` at ``--soft-image``^2,
   1 spp: ``pcss`` (full maps and virtual maps, maps rebuilt every frame) against
   ``raytraced`` with 1, 2, 4, 8, 16 shadow rays; visibility RMSE against the converged
   reference (1024 light samples x 4 spp). For each PCSS configuration, the error of the
   best ``raytraced`` configuration that is not slower, over PCSS's error (issue 11's
   target: PCSS's error <= 0.7 x ray tracing's at equal time, i.e. a ratio >= 1/0.7).

Times are wall-clock medians on this machine's 2 shared cores, all configurations of a
part interleaved, so read the ratios.

``--cpu`` (part 1 only): every frame on one thread (``dr.set_thread_count(1)``: the kernels
run on the calling thread), timed as that thread's CPU time (``time.thread_time_ns``),
which other processes on the machine do not inflate the way they inflate wall time. The
configurations are ``unshadowed``, ``raytraced`` and ``hard`` with full and virtual maps
built every frame, interleaved (each ``--best-of`` times in a row a round, keeping its
frame of least CPU time); the tables give the medians, each round's own shadow-cost
ratio, and each frame cut into parts at its boundaries (the mark pass, the page build
kernels and their host reads, the rest of the first pass, the render): per part its CPU
time, split into kernels and host work in the proportion of its kernels' time (Dr.Jit's
kernel history) to its wall time. Every kernel of a frame is checked to be launched inside
its timed region. The lookup's cost relative to one shadow ray is taken from the render
parts of the same rounds.
"""
from __future__ import annotations

import argparse
import contextlib
import os
import pathlib
import statistics
import sys
import tempfile
import time

import mi_shadowmap  # noqa: F401  (LLVM set-up, registration)
import drjit as dr
import mitsuba as mi
import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
from bench_all import heavy_scene  # noqa: E402

from mi_shadowmap.reference import converged_visibility  # noqa: E402

ROOT = pathlib.Path(__file__).resolve().parents[1]


def frame(scene, integ, spp, seed):
    dr.sync_thread()
    t0 = time.perf_counter()
    img = mi.render(scene, integrator=integ, spp=spp, seed=seed)
    dr.eval(img)
    dr.sync_thread()
    return time.perf_counter() - t0, img


def interleaved(scene, configs, spp, rounds):
    """``{name: (median seconds, last image, integrator, per-round seconds)}``, the
    configurations rendered in turn."""
    integs = {n: mi.load_dict({"type": "shadowmap", **p}) for n, p in configs.items()}
    for n, i in integs.items():          # compile and warm up
        frame(scene, i, spp, 0)
    times = {n: [] for n in configs}
    last = {}
    for r in range(rounds):
        for n, i in integs.items():
            t, img = frame(scene, i, spp, r + 1)
            times[n].append(t)
            last[n] = img
    return {n: (statistics.median(times[n]), last[n], integs[n], times[n]) for n in configs}


def part_heavy(args):
    with tempfile.TemporaryDirectory() as tmp:
        scene = mi.load_dict(heavy_scene(args.triangles, args.image, tmp))
        configs = {"unshadowed": {"method": "unshadowed"},
                   "raytraced": {"method": "raytraced"},
                   "hard full (built)": {"method": "hard", "virtual": False,
                                         "cache_maps": False},
                   "hard virtual (built)": {"method": "hard", "virtual": True,
                                            "cache_maps": False},
                   "hard full (cached)": {"method": "hard", "virtual": False},
                   "hard virtual (cached)": {"method": "hard", "virtual": True}}
        res = interleaved(scene, configs, args.spp, args.rounds)
    base = res["unshadowed"][0]
    rt = res["raytraced"][0] - base
    # the same ratio within each round (its frames rendered a few seconds apart): this
    # machine's speed drifts between rounds by more than a shadow cost, which moves the
    # ratio of medians; the per-round ratios' median and range show how far
    per_round = {n: [(t - u) / (r - u) if r > u else float("nan")
                     for t, u, r in zip(res[n][3], res["unshadowed"][3], res["raytraced"][3])]
                 for n in res}
    print(f"\n## 1. {args.triangles:,}-triangle mesh, {args.image}^2, {args.spp} spp "
          f"(median of {args.rounds} interleaved rounds)\n")
    print("| configuration | frame [ms] | shadow cost [ms] | shadow cost / raytraced's | "
          "per round: median (min-max) | texels built |")
    print("|---|---|---|---|---|---|")
    for n, (t, _, integ, _) in res.items():
        cost = t - base
        texels = integ.stats.get("texels_built", "-") if hasattr(integ, "stats") else "-"
        ratio = f"{cost / rt:.2f}" if n != "unshadowed" and rt > 0 else "-"
        pr = per_round[n]
        spread = (f"{statistics.median(pr):.2f} ({min(pr):.2f}-{max(pr):.2f})"
                  if n != "unshadowed" and all(x == x for x in pr) else "-")
        print(f"| {n} | {t * 1e3:.1f} | {cost * 1e3:.1f} | {ratio} | {spread} | {texels} |")


# ------------------------------------------------------------------ --cpu: one thread
#: A frame's parts in the order they end (the tick that closes each, :class:`FrameClock`):
#: the mark pass (camera hits, marks and their dedupe kernels, ``planner.dedupe_many``), the
#: pages' planning (host), the page build (the cast, the new pages' fills and the tiles'
#: minima read: ``cast_tiles`` to ``read_minima``), the rest of the first pass (the full
#: maps' build where there are full maps) and the render (Mitsuba's, tracing ``sample()``
#: and its kernel).
PARTS = ("marks", "plan", "build", "first pass", "render")


class FrameClock:
    """A frame cut into parts: at each boundary (:meth:`tick`) the kernels launched so far
    are waited for, and this thread's CPU time, the wall time and the kernels launched
    since the last boundary (Dr.Jit's kernel history) are recorded. With one thread
    (``dr.set_thread_count(1)``) the kernels run on the calling thread, so its CPU time
    holds them."""

    def __init__(self):
        self.ticks = []
        self.outside = 0      # kernels launched between frames (outside every timed region)

    def start(self):
        dr.sync_thread()
        self.outside += len(dr.kernel_history())
        self.ticks = [("start", time.thread_time_ns(), time.perf_counter_ns(), [])]

    def tick(self, name: str):
        if not self.ticks:     # (not inside a timed frame)
            return
        dr.sync_thread()
        cpu, wall = time.thread_time_ns(), time.perf_counter_ns()
        self.ticks.append((name, cpu, wall, dr.kernel_history()))

    def cpu_ms(self) -> float:
        """The frame's CPU time (ms): from :meth:`start` to the last tick."""
        return (self.ticks[-1][1] - self.ticks[0][1]) / 1e6

    def parts(self) -> dict:
        """``{part: [kernels' CPU ms, host CPU ms, JIT kernels launched, the lanes and the
        operations of its longest JIT kernel]}`` (the kernels' time counts the copies,
        memsets and host functions too):
        each part's CPU time split in the proportion of its kernels' execution time to its
        wall time (the kernels' times are wall times on this thread: a descheduled thread
        lengthens both alike)."""
        out = {}
        for (_, c0, w0, _), (name, c1, w1, ks) in zip(self.ticks, self.ticks[1:]):
            cpu, wall = (c1 - c0) / 1e6, (w1 - w0) / 1e6
            kern = sum(k.get("execution_time", 0.0) for k in ks)
            share = min(kern / wall, 1.0) if wall > 0 else 0.0
            acc = out.setdefault(name, [0.0, 0.0, 0, 0, 0])
            acc[0] += cpu * share
            acc[1] += cpu * (1.0 - share)
            jit = [k for k in ks if k["type"] == dr.KernelType.JIT]
            acc[2] += len(jit)
            if jit:           # the lanes of the part's longest kernel (most operations)
                big = max(jit, key=lambda k: k.get("operation_count", 0))
                if big.get("operation_count", 0) >= acc[4]:
                    acc[3], acc[4] = int(big.get("size", 0)), big.get("operation_count", 0)
        return out


@contextlib.contextmanager
def clocked(clock: FrameClock, integs):
    """Ticks ``clock`` at a frame's boundaries (:data:`PARTS`) for the renders of ``integs``:
    wrappers around the planner's ``dedupe_many``, ``cast_tiles`` and ``read_minima`` and
    each integrator's ``_first_pass`` (instrumentation only: the same calls, the same
    arguments), removed on exit."""
    from mi_shadowmap.virtual import planner
    saved = {n: getattr(planner, n) for n in ("dedupe_many", "cast_tiles", "read_minima")}

    def dedupe_many(*a, **k):
        out = saved["dedupe_many"](*a, **k)
        clock.tick("marks")
        return out

    def cast_tiles(*a, **k):
        clock.tick("plan")
        return saved["cast_tiles"](*a, **k)

    def read_minima(*a, **k):
        out = saved["read_minima"](*a, **k)
        clock.tick("build")
        return out

    def first_pass_of(inner):
        def first_pass(*a, **k):
            out = inner(*a, **k)
            clock.tick("first pass")
            return out
        return first_pass

    for name, fn in (("dedupe_many", dedupe_many), ("cast_tiles", cast_tiles),
                     ("read_minima", read_minima)):
        setattr(planner, name, fn)
    for integ in integs:
        integ._first_pass = first_pass_of(integ._first_pass)
    try:
        yield clock
    finally:
        for name, fn in saved.items():
            setattr(planner, name, fn)
        for integ in integs:
            del integ._first_pass


def cpu_frame(scene, integ, spp: int, seed: int, clock: FrameClock):
    """One frame timed by ``clock`` (its parts and CPU time); the image."""
    clock.start()
    img = mi.render(scene, integrator=integ, spp=spp, seed=seed)
    dr.eval(img)
    clock.tick("render")
    return img


CPU_CONFIGS = {"unshadowed": {"method": "unshadowed"},
               "raytraced": {"method": "raytraced"},
               "hard full (built)": {"method": "hard", "virtual": False, "cache_maps": False},
               "hard virtual (built)": {"method": "hard", "virtual": True,
                                        "cache_maps": False}}


def interleaved_cpu(scene, configs: dict, spp: int, rounds: int, best_of: int = 1) -> dict:
    """``{name: {"cpu": [ms per round], "parts": [parts per round], "integ": integrator}}``:
    the configurations rendered in turn on one thread (a warm-up frame each first), each
    ``best_of`` times in a row a round, keeping its frame of least CPU time (other
    processes only ever add to it: their bursts lengthen a frame, through the caches
    they evict), and the kernels launched outside every timed frame (``"outside"``: 0
    when every kernel of the frames was timed)."""
    integs = {n: mi.load_dict({"type": "shadowmap", **p}) for n, p in configs.items()}
    threads = dr.thread_count()
    had_history = dr.flag(dr.JitFlag.KernelHistory)
    dr.set_thread_count(1)
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    clock = FrameClock()
    out = {n: {"cpu": [], "parts": [], "integ": i} for n, i in integs.items()}
    try:
        with clocked(clock, integs.values()):
            for n, i in integs.items():              # compile and warm up
                cpu_frame(scene, i, spp, 0, clock)
            clock.outside = 0
            for r in range(rounds):
                for n, i in integs.items():
                    best = None
                    for _ in range(max(1, best_of)):
                        cpu_frame(scene, i, spp, r + 1, clock)
                        if best is None or clock.cpu_ms() < best[0]:
                            best = (clock.cpu_ms(), clock.parts())
                    out[n]["cpu"].append(best[0])
                    out[n]["parts"].append(best[1])
            clock.ticks = []
            dr.sync_thread()
            clock.outside += len(dr.kernel_history())
    finally:
        dr.set_thread_count(threads)
        dr.set_flag(dr.JitFlag.KernelHistory, had_history)
    out["outside"] = clock.outside
    return out


def _med(xs):
    return statistics.median(xs) if xs else float("nan")


def part_heavy_cpu(args):
    with tempfile.TemporaryDirectory() as tmp:
        scene = mi.load_dict(heavy_scene(args.triangles, args.image, tmp))
        res = interleaved_cpu(scene, CPU_CONFIGS, args.spp, args.rounds, args.best_of)
    outside = res.pop("outside")
    samples = args.image * args.image * args.spp
    cpu = {n: r["cpu"] for n, r in res.items()}
    base, rt = _med(cpu["unshadowed"]), _med(cpu["raytraced"])
    print(f"\n## 1. {args.triangles:,}-triangle mesh, {args.image}^2, {args.spp} spp, one "
          f"thread's CPU time (median of {args.rounds} interleaved rounds, each "
          f"configuration's least of {args.best_of} frames a round; kernels launched "
          f"outside the timed frames: {outside}; load average at the end "
          f"{os.getloadavg()[0]:.1f})\n")
    print("| configuration | frame [ms] | shadow cost [ms] | shadow cost / raytraced's | "
          "per round: median (min-max) | texels built |")
    print("|---|---|---|---|---|---|")
    for n, r in res.items():
        t = _med(r["cpu"])
        pr = [(c - u) / (q - u) if q > u else float("nan")
              for c, u, q in zip(r["cpu"], cpu["unshadowed"], cpu["raytraced"])]
        ratio = f"{(t - base) / (rt - base):.2f}" if n != "unshadowed" and rt > base else "-"
        spread = (f"{_med(pr):.2f} ({min(pr):.2f}-{max(pr):.2f})"
                  if n != "unshadowed" and all(x == x for x in pr) else "-")
        texels = r["integ"].stats.get("texels_built", "-")
        print(f"| {n} | {t:.1f} | {t - base:.1f} | {ratio} | {spread} | {texels} |")
    print("\n### Each round's frames (CPU ms)\n")
    print("| configuration | " + " | ".join(str(r + 1) for r in range(args.rounds)) + " |")
    print("|---|" + "---|" * args.rounds)
    for n, r in res.items():
        print(f"| {n} | " + " | ".join(f"{t:.1f}" for t in r["cpu"]) + " |")
    # per part: medians over the rounds of each part's kernels' and host CPU ms
    print("\n### Per part (CPU ms, medians; kernels / host [JIT kernels launched, the "
          "lanes of the longest one])\n")
    print("| configuration | " + " | ".join(PARTS) + " | frame |")
    print("|---|" + "---|" * (len(PARTS) + 1))
    med_parts = {}
    for n, r in res.items():
        cells = []
        for p in PARTS:
            rows = [pp[p] for pp in r["parts"] if p in pp]
            if not rows:
                cells.append("-")
                continue
            k, h = _med([x[0] for x in rows]), _med([x[1] for x in rows])
            med_parts[n, p] = (k, h)
            cells.append(f"{k:.1f} / {h:.1f} [{rows[-1][2]}, {rows[-1][3]:,}]")
        print(f"| {n} | " + " | ".join(cells) + f" | {_med(r['cpu']):.1f} |")
    # the lookup against a shadow ray: the render parts' CPU time over the unshadowed
    # render's, paired per round, per sample (one light: a lookup or a ray a sample)
    render = {n: [pp["render"][0] + pp["render"][1] for pp in r["parts"]]
              for n, r in res.items()}
    per = {n: _med([(a - b) / samples * 1e6 for a, b in zip(render[n], render["unshadowed"])])
           for n in res if n != "unshadowed"}
    ray = per["raytraced"]
    print(f"\nRender part over the unshadowed render, per sample (paired medians, "
          f"{samples:,} samples): shadow ray {ray:.1f} ns; "
          + "; ".join(f"{n} {v:.1f} ns ({v / ray:.2f} of a ray)"
                      for n, v in per.items() if n != "raytraced")
          + f". The shadow rays' share of the raytraced frame: "
          f"{ray * samples / 1e6 / rt:.2f} ({ray * samples / 1e6:.1f} of {rt:.1f} ms).")


def part_soft(args):
    scene = mi.load_file(str(ROOT / "scenes_xml" / "cbox_area.xml"), width=args.soft_image,
                         height=args.soft_image)
    ref = converged_visibility(scene, n_light=1024, spp=4, seed=7)
    ref = np.stack([ref[k] for k in sorted(ref)])
    configs = {"pcss full (built)": {"method": "pcss", "virtual": False, "cache_maps": False},
               "pcss virtual (built)": {"method": "pcss", "virtual": True,
                                        "cache_maps": False}}
    for k in (1, 2, 4, 8, 16):
        configs[f"raytraced shadow_rays={k}"] = {"method": "raytraced", "shadow_rays": k}
    res = interleaved(scene, configs, 1, args.rounds)
    rows = {}
    for n, (t, img, integ, _) in res.items():
        a = np.asarray(img)
        vis = np.moveaxis(a[..., 3:], -1, 0)
        order = np.argsort(integ.aov_names())
        rows[n] = (t, float(np.sqrt(np.mean((vis[order] - ref) ** 2))))
    print(f"\n## 2. cbox_area, {args.soft_image}^2, 1 spp, maps rebuilt every frame "
          f"(median of {args.rounds} interleaved rounds)\n")
    print("| configuration | frame [ms] | visibility RMSE | RT error at equal time / this |")
    print("|---|---|---|---|")
    for n, (t, e) in rows.items():
        ratio = "-"
        if not n.startswith("raytraced"):
            rt = [ee for nn, (tt, ee) in rows.items() if nn.startswith("raytraced") and tt <= t]
            ratio = f"{min(rt) / e:.2f}" if rt else "no RT config as fast"
        print(f"| {n} | {t * 1e3:.1f} | {e:.4f} | {ratio} |")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--triangles", type=int, default=1_000_000)
    ap.add_argument("--image", type=int, default=256)
    ap.add_argument("--spp", type=int, default=64)
    ap.add_argument("--soft-image", type=int, default=512)
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--skip-heavy", action="store_true")
    ap.add_argument("--skip-soft", action="store_true")
    ap.add_argument("--cpu", action="store_true",
                    help="part 1 on one thread, timed by its CPU time, with each frame's "
                         "parts (the wall-clock part 2 is not run)")
    ap.add_argument("--best-of", type=int, default=3,
                    help="--cpu: frames of each configuration a round, in a row; the one "
                         "of least CPU time is kept")
    args = ap.parse_args(argv)
    print(f"# bench_virtual_cost {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, "
          f"{os.cpu_count()} cores visible, Mitsuba {mi.__version__}, Dr.Jit {dr.__version__}")
    if args.cpu:
        if not args.skip_heavy:
            part_heavy_cpu(args)
        return
    if not args.skip_heavy:
        part_heavy(args)
    if not args.skip_soft:
        part_soft(args)


if __name__ == "__main__":
    main()
