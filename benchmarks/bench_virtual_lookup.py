"""Where a virtual map's ``hard`` lookup spends its time, step by step (issue 11).

    python benchmarks/bench_virtual_lookup.py [--scenes large_world far_point ...]
                                              [--image 1024] [--repeats 9]

For each scene, the camera's pixel-centre hits at ``--image``^2 (one lookup per pixel,
about 1 M lookups at the default) are evaluated once; then each prefix of the lookup is
evaluated on them as its own kernel, and its execution time (Dr.Jit's kernel history,
median of ``--repeats``) is reported with the time of a kernel that only reads the
points (``read``), so that each row's increment is what that step adds:

  read            the points, plus one add (the kernel's fixed cost, reading the input)
  project         the float64 projection into the light (``project_f64``)
  level           + the level from the pixel footprint (``level_for``)
  page table      + ``bind``: the 2 x 2 pages' table entry, the own page's slot, the
                  fallback for a missing page (``per_tap``, as ``hard`` binds)
  receiver        + ``receiver()`` through the bound local frame (biases, normal offset)
  texel index     + the texel's pool index (page slot gathered per tap)
  hard            the whole lookup: + the depth gather and the compare
  full: hard      ``hard`` on the full map of ``virtual=false`` (same points)

Each row writes its outputs (a few arrays per lane), so increments are approximate; read
the ``hard`` rows against each other. Times are this machine's (2 shared cores).
"""
from __future__ import annotations

import argparse
import pathlib
import statistics

import mi_shadowmap  # noqa: F401  (LLVM set-up, registration)
import drjit as dr
import mitsuba as mi

from mi_shadowmap import harness, pages
from mi_shadowmap.filters.common import Lookup, receiver
from mi_shadowmap.filters.hard import hard

ROOT = pathlib.Path(__file__).resolve().parents[1]


def kernel_ms(fn, repeats: int) -> float:
    """Median execution time (ms) of the kernels that evaluating ``fn()`` launches."""
    times = []
    for _ in range(repeats + 2):
        dr.kernel_history()
        dr.eval(fn())
        dr.sync_thread()
        hist = [k for k in dr.kernel_history() if k["type"] == dr.KernelType.JIT]
        times.append(sum(k["execution_time"] for k in hist))
    return statistics.median(times[2:])


def bench_scene(name: str, args) -> list:
    scene = harness.load_scene(str(ROOT / "scenes_xml" / f"{name}.xml"),
                               width=str(args.image), height=str(args.image))
    virt = mi.load_dict({"type": "shadowmap", "method": "hard", "virtual": True})
    full = mi.load_dict({"type": "shadowmap", "method": "hard", "virtual": False})
    mi.render(scene, integrator=virt, spp=1)
    mi.render(scene, integrator=full, spp=1)
    vm = next(m for m in virt.maps if isinstance(m, pages.VirtualShadowMap))
    fm = full.maps[virt.maps.index(vm)]
    si, dp_dx, dp_dy, valid = pages.camera_hits(scene, scene.sensors()[0])
    p = dr.select(valid, si.p, 0.0)
    dr.eval(p, si.n, dp_dx, dp_dy, valid)
    lk = Lookup(p, si.n, dp_dx, dp_dy, si, None, None)
    n = int(valid.numpy().sum())
    vo, fo = virt.opts, full.opts

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
        ("page table", lambda: (lambda b: (b.view.origin, b.level, b.entry[0]))(bound())),
        ("receiver", lambda: (lambda br: (br[1].uv, br[1].depth, br[0].entry[0]))(rec())),
        ("texel index", lambda: (lambda br: (br[0].texel_index(br[1].face, br[1].uv),
                                             br[1].depth))(rec())),
        ("hard", lambda: hard(bound(), lk, vo, valid)),
        ("full: hard", lambda: hard(fm, lk, fo, valid)),
    ]
    rows = []
    base = None
    for label, fn in steps:
        t = kernel_ms(fn, args.repeats)
        base = t if base is None else base
        rows.append((name, label, t, (t - base) / max(n, 1) * 1e6))
    return rows


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", nargs="+", default=["large_world", "far_point",
                                                    "room_two_points", "cbox_area"])
    ap.add_argument("--image", type=int, default=1024)
    ap.add_argument("--repeats", type=int, default=9)
    args = ap.parse_args()
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    print(f"`hard` lookups at {args.image}^2 pixel-centre hits, kernel time, median of "
          f"{args.repeats}; ns / lookup = (kernel - read) / hits\n")
    print("| scene | step | kernel [ms] | ns / lookup over `read` |")
    print("|---|---|---|---|")
    for name in args.scenes:
        for scene, label, t, ns in bench_scene(name, args):
            print(f"| {scene} | {label} | {t:.3f} | {ns:.2f} |")


if __name__ == "__main__":
    main()
