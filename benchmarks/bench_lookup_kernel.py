"""The virtual lookup's cost in a whole render kernel, one thread (issue 11's camera move).

    python benchmarks/bench_lookup_kernel.py [--scenes room_two_points large_world ...]
                                             [--method hard] [--image 256] [--spp 16]
                                             [--rounds 25]

A still frame of virtual maps builds nothing: its excess over full maps is the virtual
lookup alone, part of it in the render kernel and part in tracing that kernel on the
host, every frame. Per scene, frames of ``unshadowed``, ``--method`` on full maps
(``virtual=false``, maps cached) and ``--method`` on virtual maps (still camera) are
rendered in turn on one Dr.Jit thread (``dr.set_thread_count(1)``: the kernels run on
the calling thread), the order reversed every other round, and each frame is cut in two
by the calling thread's CPU time (``time.thread_time_ns``, which other processes on a
shared machine do not inflate): the trace (``integrator.render`` with ``evaluate=False``:
the first pass and the traced render, on the host) and the kernels (``dr.eval`` of the
image: the render kernel and the film's). The virtual frame is rendered twice a round
(``virtual`` and ``virtual again``, the same integrator and kernel): their paired
difference is what this method resolves between two runs of the same code.

Printed per configuration: medians over ``--rounds`` of the trace and the kernels [ms],
and the paired median difference of the kernels from the virtual frame of the same round,
its range and in how many rounds it was smaller; the render kernel's operation count
(Dr.Jit's; the frame's kernel of the most operations) and kernels compiled after the
first round (none: every frame after it reuses its kernels).

On an AVX-512 Xeon (the fifty-fourth session, helper B: ``benchmarks/RESULTS.md``) the
virtual lookup's excess over a full map's was 7-8 ms of room_two_points' 84 ms render
kernel and 4 of large_world's 56, and its trace 1.7 ms of the host's 5.5 on
room_two_points (0.7 of that the walked retry's code, traced every frame and run by about
0.01 % of the packets); on two threads the kernel's share halves and the trace's does
not. Timing-only knock-outs of single steps (each a Python patch of the lookup during the
trace) moved the kernel by less than the same code timed twice.
"""
from __future__ import annotations

import pathlib
import statistics
import sys
import time

import mi_shadowmap  # noqa: F401  (first: the package's LLVM set-up, registration)
import drjit as dr

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
from bench_virtual_move import frame_parser, scene_and_integrators  # noqa: E402

SCENES = ["room_two_points", "large_world", "far_point"]
#: The configurations timed, in the order of a round (reversed every other round).
CONFIGS = ("virtual", "virtual again", "full", "unshadowed")


def _frame(scene, integrator, spp: int) -> tuple:
    """One frame on the calling thread: ``(trace ms, kernels ms, render kernel's
    operations, kernels compiled)``, CPU times of this thread (the render kernel: the
    frame's kernel of the most operations)."""
    dr.sync_thread()
    dr.kernel_history()                       # (emptied: this frame's from here)
    t0 = time.thread_time_ns()
    img = integrator.render(scene, 0, 0, spp, True, False)
    t1 = time.thread_time_ns()
    dr.eval(img)
    dr.sync_thread()
    t2 = time.thread_time_ns()
    jit = [k for k in dr.kernel_history() if k["type"] == dr.KernelType.JIT]
    render = max(jit, key=lambda k: k["operation_count"]) if jit else {"operation_count": 0}
    return ((t1 - t0) * 1e-6, (t2 - t1) * 1e-6, render["operation_count"],
            sum(not k.get("cache_hit") for k in jit))


def bench_scene(name: str, args) -> list:
    """Rows ``(config, trace, kernels, diff, lo, hi, faster, ops, compiled)`` of one scene
    (see the module doc)."""
    scene, integ = scene_and_integrators(name, args)
    integ["virtual again"] = integ["virtual"]
    times = {k: [] for k in CONFIGS}
    for r in range(args.rounds + 1):          # (round 0: kernels compiled, maps built)
        for k in CONFIGS if r % 2 else CONFIGS[::-1]:
            out = _frame(scene, integ[k], args.spp)
            if r:
                times[k].append(out)
    base = [t[1] for t in times["virtual"]]
    rows = []
    for k in CONFIGS:
        kern = [t[1] for t in times[k]]
        diff = sorted(a - b for a, b in zip(kern, base))
        rows.append((k, statistics.median(t[0] for t in times[k]), statistics.median(kern),
                     statistics.median(diff), diff[0], diff[-1],
                     sum(d < 0.0 for d in diff), times[k][-1][2],
                     sum(t[3] for t in times[k])))
    return rows


def main(argv=None) -> int:
    args = frame_parser(__doc__, SCENES, 25).parse_args(argv)
    threads = dr.thread_count()
    dr.set_thread_count(1)
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        print(f"# {args.method}, {args.image}^2, {args.spp} spp, one thread's CPU time, "
              f"medians of {args.rounds} rounds; differences paired with the virtual frame "
              "of the same round\n")
        print("| scene | frame | trace [ms] | kernels [ms] | kernels - virtual [ms] | range "
              "| smaller | render kernel ops | compiled |")
        print("|---|---|---|---|---|---|---|---|---|")
        for name in args.scenes:
            for k, tr, ke, d, lo, hi, fast, ops, comp in bench_scene(name, args):
                print(f"| {name} | {k} | {tr:.2f} | {ke:.2f} | {d:+.2f} | {lo:+.2f}..{hi:+.2f} "
                      f"| {fast}/{args.rounds} | {ops} | {comp} |", flush=True)
        print(f"\nload average: {' '.join(open('/proc/loadavg').read().split()[:3])}"
              if pathlib.Path("/proc/loadavg").exists() else "")
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
        dr.set_thread_count(threads)
    return 0


if __name__ == "__main__":
    sys.exit(main())
