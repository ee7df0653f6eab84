"""Virtual shadow maps (issue 11): frame times with a still and a moving camera,
interleaved, against the unshadowed frame. One run, by hand:

    python benchmarks/bench_virtual_move.py [--scenes large_world far_point ...]
                                            [--method hard] [--image 256] [--spp 16]
                                            [--rounds 3] [--profile N]

``bench_virtual.py`` times one camera move per configuration, after the others, against
an unshadowed frame timed once per scene, so its move ratios drift with the machine's
load (by up to +-0.3 between runs here). This script interleaves everything: per
round, 3 warm frames each of ``unshadowed``, ``--method`` with full maps
(``virtual=false``, maps cached) and with virtual maps (the default; still camera,
marks and pages reused), then 4 frames each after a small camera move (0.05 units
sideways times the move's index, 1 degree of yaw; maps cached, camera put back after
each). Medians over ``--rounds`` rounds; ratios are over the unshadowed frame of the
same run. Every move goes to a new place, so each builds the pages it has not seen.
A moved view costs a little more or less to render than the still one, so each moved
frame is also timed ``unshadowed`` at the same moved camera, right after it (2 frames,
their median); the last column divides by that frame of the same view.

``--profile N`` (instead of the timing rounds): where a moved frame's time goes, per
scene. ``N`` moved frames of ``--method`` (virtual maps) and, after each at the same
moved camera, an unshadowed frame, under ``cProfile`` with the main thread's CPU clock
(``time.thread_time_ns``: what the host runs, and the kernels' share the main thread
executes while it waits for them; other processes on the machine do not inflate it as
they inflate wall time). Printed: each frame's median CPU time, the functions whose own
time (``tottime``, Dr.Jit's tracing calls and numpy's included in the Python function
that makes them) grows most from the unshadowed frame to the moved one, and the last
frames' kernel history (launches by type; per JIT kernel its width, operations, code
generation and execution in ms, and whether it compiled). ``timing.py:render_timed``'s
own time is Mitsuba's C++ render and the main thread's wait for (and share of) the
render kernel; ``marks.py:<listcomp>``'s, the host reads after the mark kernels, their
wait. The profiler adds about 1 us a Python call.

``--cpu N`` (instead of the timing rounds): a moved frame's work on one thread
(``dr.set_thread_count(1)``: the kernels run on the calling thread), which other processes
on the machine do not inflate as they inflate wall time: ``N`` moves, each a moved frame of
``--method`` (virtual maps) and the unshadowed frame at the same camera, timed by the
thread's CPU time and cut into the mark pass (tracing its camera hits to the dedupe's host
reads, its kernels included), the rest of the integrator's first pass (plan, casts, page
tables) and the render (``sample()`` traced, the render kernel, the film); medians. Then
the mark pass's camera rays alone, as kernels of their own (one thread, medians of
``N``): their closest hits (``ray_intersect_preliminary``), with their surface interaction
(``ray_intersect``, ``RayFlags.Minimal``) and with their footprints
(``marks.camera_hits``), against the whole mark pass. With one thread every kernel runs
as it is launched (Dr.Jit 1.5: ``set_thread_count(n)`` is ``n - 1`` pool threads and the
calling thread; with 1, no pool), so ``--cpu`` does not show host work that the pool
overlaps with a kernel (two threads: the mark pass's camera hits run while the host
traces the marks, fifty-sixth session); the main thread's CPU at the default thread
count (``--profile``) does, where the machine leaves the pool a core.
"""
from __future__ import annotations

import argparse
import cProfile
import pathlib
import pstats
import statistics
import sys
import time

import mi_shadowmap  # noqa: F401  (LLVM set-up, registration)
import drjit as dr
import mitsuba as mi

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
from bench_virtual import move_camera, set_camera  # noqa: E402

from mi_shadowmap import harness  # noqa: E402
from mi_shadowmap.timing import render_timed  # noqa: E402

ROOT = pathlib.Path(__file__).resolve().parents[1]
SCENES = ["large_world", "far_point", "spot_sphere_box", "directional_mesh",
          "room_two_points", "cbox_area", "contact_hardening", "spectral_point"]


def scene_and_integrators(name, args) -> tuple:
    """``scenes_xml/<name>.xml`` at ``args.image``^2 and its ``unshadowed``, ``full``
    (``args.method``, ``virtual=false``) and ``virtual`` (``args.method``) integrators
    (also ``bench_lookup_kernel.py``'s)."""
    scene = harness.load_scene(str(ROOT / "scenes_xml" / f"{name}.xml"),
                               width=str(args.image), height=str(args.image))
    props = {"unshadowed": {"method": "unshadowed"},
             "full": {"method": args.method, "virtual": False},
             "virtual": {"method": args.method}}
    return scene, {k: mi.load_dict({"type": "shadowmap", **v}) for k, v in props.items()}


def bench_scene(name, args) -> dict:
    scene, integ = scene_and_integrators(name, args)
    for i in integ.values():                        # compile, build, prime the caches
        render_timed(scene, i, args.spp, 0)
    times = {k: [] for k in ("unshadowed", "full", "virtual", "move", "move_unshadowed")}
    for r in range(args.rounds):
        for k in ("unshadowed", "full", "virtual"):
            times[k].append(statistics.median(render_timed(scene, integ[k], args.spp, 0)[1]
                                              for _ in range(3)))
        moves, moves_unsh = [], []
        for j in range(4):
            old = move_camera(scene, 0.05 * (1 + j + 4 * r), 1.0)
            try:
                moves.append(render_timed(scene, integ["virtual"], args.spp, 0)[1])
                moves_unsh.append(statistics.median(
                    render_timed(scene, integ["unshadowed"], args.spp, 0)[1] for _ in range(2)))
            finally:
                set_camera(scene, old)
            render_timed(scene, integ["virtual"], args.spp, 0)
        times["move"].append(statistics.median(moves))
        times["move_unshadowed"].append(statistics.median(moves_unsh))
    med = {k: statistics.median(v) for k, v in times.items()}
    return {"scene": name, **med}


def _own_times(prof, n: int) -> dict:
    """Each profiled function's own CPU time (ms) per frame, by ``file:function``."""
    out = {}
    for (path, _, func), (_, _, tottime, _, _) in pstats.Stats(prof).stats.items():
        key = f"{path.split('/mi_shadowmap/')[-1].split('/')[-1]}:{func}"
        out[key] = out.get(key, 0.0) + tottime * 1e3 / n
    return out


def _kernels(history) -> str:
    """One frame's kernel history: launches by type, then each JIT kernel."""
    kinds = {}
    for k in history:
        kinds[str(k["type"]).split(".")[-1]] = kinds.get(str(k["type"]).split(".")[-1], 0) + 1
    jit = [k for k in history if k["type"] == dr.KernelType.JIT]
    rows = "; ".join(f"{k['size']} wide: {k['operation_count']} ops, codegen "
                     f"{k.get('codegen_time', 0.0):.2f}, exec {k.get('execution_time', 0.0):.2f}"
                     + ("" if k.get("cache_hit") else ", COMPILED") for k in jit)
    return f"{len(history)} launches {kinds}\n    JIT kernels: {rows}"


def _warmed_up(name, args):
    """The scene ``name`` at ``args.image``^2 and its ``unshadowed`` and ``virtual``
    (``args.method``) integrators, after three moves back and forth: kernels compiled,
    pages built (the first move compiles its kernels)."""
    scene = harness.load_scene(str(ROOT / "scenes_xml" / f"{name}.xml"),
                               width=str(args.image), height=str(args.image))
    integ = {k: mi.load_dict({"type": "shadowmap", "method": m})
             for k, m in (("unshadowed", "unshadowed"), ("virtual", args.method))}
    for j in range(3):
        old = move_camera(scene, 0.05 * (1 + j), 1.0)
        for i in integ.values():
            render_timed(scene, i, args.spp, 0)
        set_camera(scene, old)
        render_timed(scene, integ["virtual"], args.spp, 0)
    return scene, integ


def profile_scene(name, args) -> None:
    """``--profile``: see the module doc."""
    scene, integ = _warmed_up(name, args)
    profs = {k: cProfile.Profile(time.thread_time_ns, 1e-9) for k in integ}
    cpu = {k: [] for k in integ}
    history = {}

    def frame(k):
        dr.kernel_history()                       # (emptied: this frame's from here)
        t0 = time.thread_time_ns()
        profs[k].enable()
        render_timed(scene, integ[k], args.spp, 0)
        profs[k].disable()
        cpu[k].append((time.thread_time_ns() - t0) * 1e-6)
        history[k] = dr.kernel_history()

    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        for j in range(args.profile):
            old = move_camera(scene, 0.05 * (4 + j), 1.0)
            try:
                frame("virtual")
                frame("unshadowed")
            finally:
                set_camera(scene, old)
            render_timed(scene, integ["virtual"], args.spp, 0)
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    moved, unsh = (_own_times(profs[k], args.profile) for k in ("virtual", "unshadowed"))
    print(f"## {name}: moved frame {statistics.median(cpu['virtual']):.1f} ms CPU, "
          f"unshadowed {statistics.median(cpu['unshadowed']):.1f} ms (medians of "
          f"{args.profile}; main thread, profiled)\n")
    print("| function (own time) | moved [ms] | unshadowed [ms] | extra [ms] |")
    print("|---|---|---|---|")
    for key in sorted(moved, key=lambda k: unsh.get(k, 0.0) - moved[k])[:args.top]:
        print(f"| {key} | {moved[key]:.2f} | {unsh.get(key, 0.0):.2f} | "
              f"{moved[key] - unsh.get(key, 0.0):+.2f} |")
    for k in ("virtual", "unshadowed"):
        print(f"\n{k}: {_kernels(history[k])}")
    print(flush=True)


def _cpu_frame(scene, integ, spp: int) -> tuple:
    """One frame on the calling thread: ``(CPU ms, first pass ms, mark pass ms, kernels
    compiled)`` (the first pass: the integrator's maps and marks; the mark pass: from
    tracing its camera hits to the dedupe's host reads, which wait for its kernels)."""
    from mi_shadowmap.virtual import planner
    ticks = {}

    def timed(label, f):
        def call(*a, **kw):
            ticks.setdefault(label + "0", time.thread_time_ns())
            try:
                return f(*a, **kw)
            finally:
                ticks[label + "1"] = time.thread_time_ns()
        return call

    saved = planner.camera_hits, planner.dedupe_many, integ._first_pass
    planner.camera_hits = timed("mark", saved[0])
    planner.dedupe_many = timed("dedupe", saved[1])
    integ._first_pass = timed("first", saved[2])
    try:
        dr.sync_thread()
        dr.kernel_history()                   # (emptied: this frame's from here)
        t0 = time.thread_time_ns()
        render_timed(scene, integ, spp, 0)
        dr.sync_thread()
        cpu = (time.thread_time_ns() - t0) * 1e-6
    finally:
        planner.camera_hits, planner.dedupe_many = saved[:2]
        del integ._first_pass
    jit = [k for k in dr.kernel_history() if k["type"] == dr.KernelType.JIT]
    first = (ticks["first1"] - ticks["first0"]) * 1e-6
    mark = (ticks["dedupe1"] - ticks["mark0"]) * 1e-6 if "mark0" in ticks else 0.0
    return cpu, first, mark, sum(not k.get("cache_hit") for k in jit)


def _mark_rays(scene, sensor, n: int) -> list:
    """Median one-thread CPU ms of the mark pass's camera rays as kernels of their own:
    closest hits, with their surface interaction, with their footprints (the hits as
    :func:`~mi_shadowmap.virtual.marks.camera_hits` traces them)."""
    from mi_shadowmap import depth_maps
    from mi_shadowmap.light_views import pixel_centres
    from mi_shadowmap.virtual import camera_hits

    def parts(k):
        if k == 2:
            hits = camera_hits(scene, sensor, evaluate=False)
            return hits[0].p, hits[0].n, hits[0].shape, hits[1], hits[2], hits[3]
        ray, _ = sensor.sample_ray(0.0, 0.5, pixel_centres(sensor, blocks=True),
                                   mi.Point2f(0.5))
        if k == 0:
            pi = scene.ray_intersect_preliminary(ray, coherent=depth_maps.COHERENT_RAYS)
            return pi.t, pi.prim_index, pi.shape
        si = scene.ray_intersect(ray, ray_flags=mi.RayFlags.Minimal,
                                 coherent=depth_maps.COHERENT_RAYS)
        return si.p, si.n, si.shape, si.is_valid()

    times = [[], [], []]
    for r in range(n + 1):
        for k in (0, 1, 2) if r % 2 else (2, 1, 0):
            out = parts(k)
            dr.sync_thread()
            t0 = time.thread_time_ns()
            dr.eval(*out)
            dr.sync_thread()
            if r:                              # (round 0 compiles)
                times[k].append((time.thread_time_ns() - t0) * 1e-6)
    return [statistics.median(t) for t in times]


def cpu_scene(name, args) -> None:
    """``--cpu``: see the module doc."""
    threads = dr.thread_count()
    dr.set_thread_count(1)
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    rows, compiled = [], 0
    try:
        scene, integ = _warmed_up(name, args)
        for j in range(args.cpu):
            old = move_camera(scene, 0.05 * (4 + j), 1.0)
            try:
                moved = _cpu_frame(scene, integ["virtual"], args.spp)
                unsh = _cpu_frame(scene, integ["unshadowed"], args.spp)
            finally:
                set_camera(scene, old)
            render_timed(scene, integ["virtual"], args.spp, 0)
            compiled += moved[3] + unsh[3]
            rows.append((moved[0], unsh[0], moved[2], moved[1] - moved[2], unsh[1],
                         moved[0] - moved[1], unsh[0] - unsh[1]))
        old = move_camera(scene, 0.05 * 4, 1.0)        # (the first measured move's view)
        try:
            rays = _mark_rays(scene, scene.sensors()[0], args.cpu)
        finally:
            set_camera(scene, old)
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
        dr.set_thread_count(threads)
    m = [statistics.median(r[k] for r in rows) for k in range(7)]
    print(f"| {name} | {m[0]:.1f} | {m[1]:.1f} | {m[0] / m[1]:.2f} | {m[2]:.1f} | "
          f"{m[3]:.1f} / {m[4]:.1f} | {m[5]:.1f} / {m[6]:.1f} | {rays[0]:.1f} / {rays[1]:.1f} "
          f"/ {rays[2]:.1f} |" + (f" ({compiled} kernels COMPILED)" if compiled else ""),
          flush=True)


def frame_parser(doc: str, scenes: list, rounds: int) -> argparse.ArgumentParser:
    """The arguments of this script's and ``bench_lookup_kernel.py``'s frames: the
    scenes, ``--method``, the image, spp and rounds; the description is ``doc``'s first
    paragraph."""
    ap = argparse.ArgumentParser(description=doc.split("\n\n")[0])
    ap.add_argument("--scenes", nargs="+", default=scenes)
    ap.add_argument("--method", default="hard")
    ap.add_argument("--image", type=int, default=256)
    ap.add_argument("--spp", type=int, default=16)
    ap.add_argument("--rounds", type=int, default=rounds)
    return ap


def main(argv=None) -> int:
    ap = frame_parser(__doc__, SCENES, 3)
    ap.add_argument("--profile", type=int, default=0, metavar="N",
                    help="profile N moved frames instead (see the module doc)")
    ap.add_argument("--top", type=int, default=25, help="--profile: functions listed")
    ap.add_argument("--cpu", type=int, default=0, metavar="N",
                    help="one thread's CPU time of N moved frames, by part (module doc)")
    args = ap.parse_args(argv)
    if args.profile:
        for name in args.scenes:
            profile_scene(name, args)
        return 0
    if args.cpu:
        print(f"# {args.method}, {args.image}^2, {args.spp} spp, one thread's CPU time, "
              f"medians of {args.cpu} moves\n")
        print("| scene | moved [ms] | unshadowed [ms] | ratio | mark pass [ms] | rest of the "
              "first pass, moved / unsh. [ms] | render, moved / unsh. [ms] | mark rays: hits "
              "/ + surface / + footprints [ms] |")
        print("|---|---|---|---|---|---|---|---|")
        for name in args.scenes:
            cpu_scene(name, args)
        return 0
    print(f"# {args.method}, {args.image}^2, {args.spp} spp, median of {args.rounds} "
          "interleaved rounds; ratios over the unshadowed frame\n")
    print("| scene | unshadowed [ms] | full, cached (x unsh.) | virtual, still camera "
          "(x unsh.) | virtual, after a move (x unsh.) | unshadowed, moved views [ms] | "
          "virtual, after a move (x unsh. of the same view) |")
    print("|---|---|---|---|---|---|---|")
    for name in args.scenes:
        m = bench_scene(name, args)
        u = m["unshadowed"]
        print(f"| {name} | {u * 1e3:.1f} | {m['full'] * 1e3:.1f} ({m['full'] / u:.2f}) | "
              f"{m['virtual'] * 1e3:.1f} ({m['virtual'] / u:.2f}) | "
              f"{m['move'] * 1e3:.1f} ({m['move'] / u:.2f}) | "
              f"{m['move_unshadowed'] * 1e3:.1f} | {m['move'] / m['move_unshadowed']:.2f} |",
              flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
