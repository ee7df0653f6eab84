"""Where a virtual map's ``hard`` lookup spends its time, step by step (issue 11).

    python benchmarks/bench_virtual_lookup.py [--scenes large_world far_point ...]
                                              [--image 1024] [--repeats 9] [--spp 1]
                                              [--threads 1] [--unframed]

For each scene, the camera's pixel-centre hits at ``--image``^2 (one lookup per pixel; with
``--spp`` N, N jittered samples per pixel in adjacent lanes, as a render orders them;
about 1 M lookups at the default) are evaluated once; then each prefix of the lookup is
evaluated on them as its own kernel, and its execution time (Dr.Jit's kernel history,
median of ``--repeats``) is reported with the time of a kernel that only reads the
points (``read``), so that each row's increment is what that step adds:

  read            the points, plus one add (the kernel's fixed cost, reading the input)
  project         the float64 projection into the light (``project_f64``)
  level           + the level from the pixel footprint (``level_for`` without the normal)
  level, capped   + the biases' finer cap on it (``level_for`` with the receiver's normal,
                  no film pixel: the reach of ``hard``'s biases, mostly float32
                  divisions and square roots, computed for every lane)
  level, per pixel  the same level as ``bind`` takes it in a render: the mark pass's
                  word of the lane's film pixel says whether the cap applies, and only
                  vector packets with a lane that keeps it compute it (a conditional)
  page table      + ``bind``: the 2 x 2 pages' table entry, the own page's slot, the
                  fallback for a missing page (``per_tap``, as ``hard`` binds)
  receiver        + ``receiver()`` through the bound local frame (biases, normal offset)
  texel index     + the texel's pool index (page slot gathered per tap)
  hard            the whole lookup bound with the walk: + the depth gather and the compare
  hard, rendered  the lookup as the integrator runs it (``VirtualShadowMap.visibility``:
                  unwalked, each read checking its page and tile; lanes that miss
                  run again, walked; all of it only in vector packets with a hit,
                  ``packets.in_lit_packets``, as the render skips packets without a
                  lit sample)
  full: hard      ``hard`` on the full map of ``virtual=false`` (same points)
  shadow ray      one shadow ray towards a sample of the light (``raytraced``, as the
                  integrator traces it), from the same hits

and the ratio of one rendered lookup to one shadow ray (each over ``read``), and how many
lookups run ``hard, rendered``'s second, walked run (``retries``: the lanes whose unwalked
read found its page or tile missing, and the 8-lane packets holding one). A variant of the
lookup that changes the levels changes that count, and every packet holding such a lane
runs the walk (a loop of table reads) and the whole lookup again: with the biases' level
everywhere (no pixel's keep word) large_world's retrying packets went from 0.30 to 0.54 %
and room_two_points' from 0.012 to 1.46 %, so such a knock-out timed the retries, not the
work it removed (``benchmarks/RESULTS.md``, fifty-second session, helper A).

Each row writes its outputs (a few arrays per lane), so increments are approximate; read
the ``hard`` rows against each other. Times are this machine's (2 shared cores).

**Stack frames.** The lookup keeps more values live than an AVX2 CPU has vector
registers, and LLVM spills them (about 300 32-byte moves a packet of ``hard``). A
render kernel realigns its stack frame (Mitsuba's calls hold 32-byte-aligned buffers),
but a kernel of these rows alone does not, and where the calling thread's stack lay
then decided whether half of its spills crossed cache lines: the same ``hard`` kernel
took 21 or 35-37 ms (far_point, 256^2 x 16, one thread, AMD Zen 3; called at three
stack depths), and a code change that only moved its frame size could look 1.7x
faster or slower (``benchmarks/RESULTS.md``, forty-seventh session). Every row's
kernel therefore holds a small aligned local array (:func:`framed`), as a render's
does; ``--unframed`` leaves it out. With ``--threads 1`` a row's time is the CPU time
of this thread, on which Dr.Jit then runs the kernels (steady on a shared machine:
another process's time slices are not counted); else the kernels' wall time.

**Inputs from memory.** The rows' kernels read their inputs (the point, normal, both
differentials, pixel and shape, about 60 bytes a lane) from memory, where a render kernel
has them in registers; where LLVM places those loads decides how much of their latency
other work hides. The lookup with its projection in float32 (less work, the same
retries) took 2.3 ns more than the float64 one here (large_world, minimums of 25 rounds),
and perf put the extra on the instructions after the inputs' loads; in the render kernel
it was not slower (-0.7 ms a 39 ms frame, +-0.6). Compare variants in a render kernel too.
"""
from __future__ import annotations

import argparse
import pathlib
import statistics
import sys
import time

import numpy as np

import mi_shadowmap  # noqa: F401  (LLVM set-up, registration)
import drjit as dr
import mitsuba as mi

from mi_shadowmap import harness, virtual
from mi_shadowmap.filters.common import Lookup, RayTracedLight, receiver
from mi_shadowmap.filters.hard import hard
from mi_shadowmap.filters.raytraced import raytraced
from mi_shadowmap.light_views import pixel_ray_differentials
from mi_shadowmap.light_views.multi import MultiView
from mi_shadowmap.packets import in_lit_packets

ROOT = pathlib.Path(__file__).resolve().parents[1]


def kernel_ms(fn, repeats: int, cpu: bool = False) -> float:
    """Median time (ms) of the kernels that evaluating ``fn()`` launches: their execution
    time, or with ``cpu`` this thread's CPU time while they run (one Dr.Jit thread: the
    kernels run on the calling thread)."""
    times = []
    for _ in range(repeats + 2):
        out = fn()
        dr.kernel_history()
        c0 = time.thread_time_ns()
        dr.eval(out)
        dr.sync_thread()
        c1 = time.thread_time_ns()
        hist = [k for k in dr.kernel_history() if k["type"] == dr.KernelType.JIT]
        times.append((c1 - c0) * 1e-6 if cpu else sum(k["execution_time"] for k in hist))
    return statistics.median(times[2:])


def framed(out, value):
    """``(out, value)``, ``value`` (a ``mi.Float``) passed through a Dr.Jit local array
    of 2 entries at two opaque indices: LLVM keeps the array (it cannot prove the indices
    equal), and a frame holding an object aligned to the vector width is realigned, as a
    render kernel's is (see the module doc). One store and one load a packet, and one
    more output: in every row, ``read`` included."""
    local = dr.alloc_local(mi.Float, 2)
    local[dr.opaque(mi.UInt32, 0)] = value
    return out, local[dr.opaque(mi.UInt32, 0)]


def camera_samples(scene, spp: int):
    """``(virtual.camera_hits, film pixels)`` at the pixel centres (``spp`` 1), else
    ``spp`` uniformly jittered camera samples per pixel, a pixel's samples in adjacent
    lanes as Mitsuba's ``render()`` orders them, with one-pixel ray differentials; the
    film pixel of each lane (``x + 65536 y``, as ``Lookup.pixel``), so that the lookups
    read the mark pass's per-pixel decision of the biases' level as a render's do."""
    sensor = scene.sensors()[0]
    if spp <= 1:
        return virtual.camera_hits(scene, sensor), virtual.camera_pixels(sensor)
    w, h = (int(x) for x in sensor.film().crop_size())
    pixel = dr.arange(mi.UInt32, w * h * spp) // spp
    y = pixel // w
    film_pixel = pixel - y * w + y * 65536
    rng = mi.PCG32(size=w * h * spp)
    pos = mi.Point2f((mi.Float(pixel - y * w) + rng.next_float32()) / w,
                     (mi.Float(y) + rng.next_float32()) / h)
    ray = pixel_ray_differentials(sensor, pos)
    si = scene.ray_intersect(ray)
    n = si.n

    def hit(o, d):
        c = dr.dot(n, d)
        return o + d * (dr.dot(n, si.p - o) / dr.select(dr.abs(c) > 1e-12, c, 1e-12))

    return ((si, hit(ray.o_x, ray.d_x) - si.p, hit(ray.o_y, ray.d_y) - si.p, si.is_valid()),
            film_pixel)


def bench_scene(name: str, args) -> tuple:
    scene = harness.load_scene(str(ROOT / "scenes_xml" / f"{name}.xml"),
                               width=str(args.image), height=str(args.image))
    virt = mi.load_dict({"type": "shadowmap", "method": "hard", "virtual": True})
    full = mi.load_dict({"type": "shadowmap", "method": "hard", "virtual": False})
    mi.render(scene, integrator=virt, spp=1)
    mi.render(scene, integrator=full, spp=1)
    # the steps below take one view apart; an environment's (or multiview's) virtual map
    # reads many sub-views (MultiView), which has no projection of its own
    vm = next((m for m in virt.maps if isinstance(m, virtual.VirtualShadowMap)
               and not isinstance(m.view, MultiView)), None)
    if vm is None:
        print(f"# {name}: skipped, no single-view virtual map (only environment or "
              "multiview maps, whose lookups go through sub-views)", file=sys.stderr)
        return [], None
    fm = full.maps[virt.maps.index(vm)]
    (si, dp_dx, dp_dy, valid), pixel = camera_samples(scene, args.spp)
    p = dr.select(valid, si.p, 0.0)
    dr.eval(p, si.n, si.shape, dp_dx, dp_dy, valid, pixel)
    lk = Lookup(p, si.n, dp_dx, dp_dy, si, None, None, pixel=pixel)
    n = int(valid.numpy().sum())
    vo, fo = virt.opts, full.opts
    # a light sample per hit and the integrator's shadow ray towards it
    emitter = scene.emitters()[0]
    rng = mi.PCG32(dr.width(valid))
    ds, _ = emitter.sample_direction(si, mi.Point2f(rng.next_float32(), rng.next_float32()),
                                     valid)
    dr.eval(ds)
    lk_ray = Lookup(p, si.n, dp_dx, dp_dy, si, ds, None, pixel=pixel)
    rt = RayTracedLight(scene, emitter)
    rt_opts = mi.load_dict({"type": "shadowmap", "method": "raytraced"}).opts

    def bound():
        return vm.bind(lk, valid, per_tap=True)

    def rec():
        b = bound()
        return b, receiver(b, lk, vo)

    steps = [
        ("read", lambda: lk.p_world.x + 1.0),
        ("project", lambda: vm.view.project_f64(mi.Point3d(lk.p_world))[1]),
        ("level", lambda: vm.level_for(*vm.view.project_f64(mi.Point3d(lk.p_world))[:1],
                                       mi.Point3d(lk.p_world), lk.dp_dx, lk.dp_dy)),
        ("level, capped", lambda: vm.level_for(
            *vm.view.project_f64(mi.Point3d(lk.p_world))[:1], mi.Point3d(lk.p_world),
            lk.dp_dx, lk.dp_dy, lk.n_world, lk.p_world)),
        ("level, per pixel", lambda: vm._levels(
            *vm.view.project_f64(mi.Point3d(lk.p_world))[:1], mi.Point3d(lk.p_world),
            lk.dp_dx, lk.dp_dy, lk.n_world, lk.p_world,
            keep=vm.keeps(lk.pixel, si.shape, valid), active=valid)[0]),
        ("page table", lambda: (lambda b: (b.view.origin, b.level, b.entry[0]))(bound())),
        ("receiver", lambda: (lambda br: (br[1].uv, br[1].depth, br[0].entry[0]))(rec())),
        ("texel index", lambda: (lambda br: (br[0].texel_index(br[1].face, br[1].uv),
                                             br[1].depth))(rec())),
        ("hard", lambda: hard(bound(), lk, vo, valid)),
        ("hard, rendered", lambda: in_lit_packets(
            lambda lk: vm.visibility(hard, lk, vo, valid, per_tap=True), lk, valid,
            draws=False)),
        ("full: hard", lambda: hard(fm, lk, fo, valid)),
        ("shadow ray", lambda: raytraced(rt, lk_ray, rt_opts, valid & (ds.pdf > 0))),
    ]
    rows = []
    base = None
    cpu = args.threads == 1
    retries = retried_lookups(vm, lk, vo, valid)
    for label, fn in steps:
        if not args.unframed:
            fn = (lambda f: lambda: framed(f(), lk.p_world.x))(fn)
        t = kernel_ms(fn, args.repeats, cpu)
        base = t if base is None else base
        rows.append((name, label, t, (t - base) / max(n, 1) * 1e6))
    return rows, retries


def retried_lookups(vm, lk, opts, valid) -> tuple:
    """``(lanes, packets, hits)``: the lanes whose ``hard, rendered`` lookup runs again,
    walked (:meth:`~mi_shadowmap.virtual.VirtualShadowMap.visibility`: its unwalked read
    found its page or tile missing), the 8-lane packets (a render kernel's on AVX2; 16
    with AVX-512) that hold one, and the hits."""
    first = vm.bind(lk, valid, True, walk=False)
    hard(first, lk, opts, valid)
    retry = (mi.Bool(valid) & first.inside & first.missed).numpy()
    pad = (-len(retry)) % 8
    packets = int(np.concatenate([retry, np.zeros(pad, bool)]).reshape(-1, 8).any(axis=1).sum())
    return int(retry.sum()), packets, int(valid.numpy().sum())


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", nargs="+", default=["large_world", "far_point",
                                                    "room_two_points", "cbox_area"])
    ap.add_argument("--image", type=int, default=1024)
    ap.add_argument("--repeats", type=int, default=9)
    ap.add_argument("--spp", type=int, default=1,
                    help="jittered camera samples per pixel (1: the pixel centres)")
    ap.add_argument("--threads", type=int, default=0,
                    help="Dr.Jit's thread count (0: its default); 1: rows timed by CPU "
                         "time, steadier on a shared machine")
    ap.add_argument("--unframed", action="store_true",
                    help="time the rows' kernels without the realigned frame (framed)")
    args = ap.parse_args()
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    if args.threads > 0:
        dr.set_thread_count(args.threads)
    where = "pixel-centre hits" if args.spp <= 1 else f"hits, {args.spp} jittered per pixel"
    clock = "CPU time, one thread" if args.threads == 1 else "kernel time"
    frames = "unframed kernels" if args.unframed else "kernels with a realigned frame"
    print(f"`hard` lookups at {args.image}^2 {where}, {clock}, {frames}, median of "
          f"{args.repeats}; ns / lookup = (kernel - read) / hits\n")
    print("| scene | step | kernel [ms] | ns / lookup over `read` |")
    print("|---|---|---|---|")
    ratios, retried = [], []
    for name in args.scenes:
        rows, retries = bench_scene(name, args)
        for scene, label, t, ns in rows:
            print(f"| {scene} | {label} | {t:.3f} | {ns:.2f} |")
        if retries is not None:
            lanes, packets, hits = retries
            retried.append(f"{name} {lanes} of {hits} lanes ({100 * lanes / max(hits, 1):.3f} "
                           f"%), {packets} 8-lane packets")
        ns = {label: v for _, label, _, v in rows}
        if rows:
            ratios.append((name, ns["hard, rendered"] / ns["shadow ray"],
                           ns["full: hard"] / ns["shadow ray"]))
    print("\none lookup / one shadow ray (each over `read`): "
          + "; ".join(f"{n} {v:.2f} (full map {f:.2f})" for n, v, f in ratios))
    print("retries (`hard, rendered`'s walked second run): " + "; ".join(retried))


if __name__ == "__main__":
    main()
