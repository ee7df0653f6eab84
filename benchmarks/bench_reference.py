"""What a ray-traced reference costs as its shadow rays grow (first render and warm).

    python benchmarks/bench_reference.py [--scenes sky_sun cbox_area room_two_points]
                                         [--image 64] [--spp 4] [--rays 1 16 64 256]

For each scene and ``shadow_rays`` count, ``raytraced`` renders the scene's film at
``--image``^2 and ``--spp`` three times with a new integrator each time (the same
kernels): the first render includes tracing the kernel and its compilation (or the
kernel cache's lookup, when an earlier run compiled it: Dr.Jit keeps compiled kernels on
disk), the next two are warm (their median is reported). ``kernel ops`` is the largest
render kernel's operation count: since the light samples of ``shadow_rays`` > 1 run in one
``dr.while_loop`` (``ShadowMapIntegratorMixin._light_samples``) it does not grow with the
ray count; an unrolled loop made it ``shadow_rays`` times one sample's. The harness's
default reference is 64 shadow rays (``compare(ref_shadow_rays=64)``).
"""
from __future__ import annotations

import argparse
import pathlib
import statistics
import time

import mi_shadowmap  # noqa: F401  (LLVM set-up, registration)
import drjit as dr
import mitsuba as mi

ROOT = pathlib.Path(__file__).resolve().parents[1]


def one_render(scene, rays: int, spp: int) -> tuple[float, int]:
    dr.kernel_history()
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        integ = mi.load_dict({"type": "shadowmap", "method": "raytraced",
                              "shadow_rays": rays})
        t0 = time.perf_counter()
        img = mi.render(scene, integrator=integ, spp=spp, seed=1)
        dr.eval(img)
        dr.sync_thread()
        seconds = time.perf_counter() - t0
        ops = max((k["operation_count"] for k in dr.kernel_history()
                   if k["type"] == dr.KernelType.JIT), default=0)
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    return seconds, ops


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scenes", nargs="+", default=["sky_sun", "cbox_area",
                                                     "room_two_points"])
    ap.add_argument("--image", type=int, default=64)
    ap.add_argument("--spp", type=int, default=4)
    ap.add_argument("--rays", nargs="+", type=int, default=[1, 16, 64, 256])
    ap.add_argument("--variant", default="llvm_ad_rgb")
    args = ap.parse_args(argv)
    mi.set_variant(args.variant)
    print(f"# raytraced reference, {args.image}^2, {args.spp} spp, {args.variant}")
    print("| scene | shadow_rays | first render [s] | warm render [s] | ns per shadow ray "
          "(warm) | kernel ops |")
    print("|---|---|---|---|---|---|")
    for name in args.scenes:
        scene = mi.load_file(str(ROOT / "scenes_xml" / f"{name}.xml"), width=args.image,
                             height=args.image)
        for rays in args.rays:
            first, ops = one_render(scene, rays, args.spp)
            warm = statistics.median(one_render(scene, rays, args.spp)[0] for _ in range(2))
            n = args.image * args.image * args.spp * rays * len(scene.emitters())
            print(f"| {name} | {rays} | {first:.2f} | {warm:.3f} | {1e9 * warm / n:.0f} "
                  f"| {ops} |", flush=True)


if __name__ == "__main__":
    main()
