"""Soft shadows: PCSS vs ray tracing at equal time and equal error (issue 4), one run.

    python benchmarks/bench_soft_shadows.py [--image 512] [--map 512] [--ref-spp 4]
                                            [--pcss-spp 1] [--json out.json]

For each soft-shadow scene (scenes_xml/cbox_area.xml, scenes_xml/contact_hardening.xml):

1. the converged reference: ``converged_visibility`` (1024 fixed stratified light
   samples per camera sample, ``--ref-spp`` camera samples per pixel);
2. PCSS at ``--pcss-spp``: warm frame time (median of 3, maps rebuilt every frame:
   ``cache_maps`` off) and visibility RMSE overall and in the reference penumbra;
3. ``raytraced`` over a ladder of spp x shadow_rays (the scene's ``independent``
   sampler; shadow rays are stratified per camera sample), warm time and RMSE;
4. equal time: the ladder entry with the largest time <= PCSS's time, its RMSE;
   equal error: the cheapest ladder entry whose RMSE <= PCSS's RMSE, its time;
   the same on the "masked" RMSE, which leaves out pixels where the light straddles the
   receiver's horizon (``converged_visibility(..., occlusion=False)`` strictly between 0
   and 1): there every one-light-sample method (hard, pcss) outputs binary noise.

All errors are on the visibility AOV against the reference. Times are wall-clock on
this machine (``dr.sync_thread()`` before reading the clock); the first (compiling)
frame of each configuration is discarded.
"""
from __future__ import annotations

import argparse
import json
import pathlib
import statistics
import time

import mi_shadowmap  # noqa: F401
import drjit as dr
import mitsuba as mi
import numpy as np

from mi_shadowmap.metrics import penumbra_rmse
from mi_shadowmap.reference import converged_visibility

ROOT = pathlib.Path(__file__).resolve().parents[1]
SCENES = ("cbox_area", "contact_hardening")
LADDER = [(1, 1), (1, 2), (1, 4), (2, 4), (4, 4), (4, 8), (8, 8), (16, 8), (32, 8), (64, 8)]


def frame(scene, integ_dict, spp, repeats=3):
    integ = mi.load_dict(integ_dict)
    img = None
    times = []
    for k in range(repeats + 1):
        t0 = time.perf_counter()
        img = np.asarray(mi.render(scene, integrator=integ, spp=spp, seed=k))
        dr.sync_thread()
        if k > 0:
            times.append(time.perf_counter() - t0)
    return img[..., 3], statistics.median(times)


MASK = None   # pixels where the whole light is above the horizon (or none of it)


def errors(ref, vis):
    return float(np.sqrt(np.mean((vis - ref) ** 2))), penumbra_rmse(ref, vis)


def masked_rmse(ref, vis):
    return float(np.sqrt(np.mean((vis - ref)[MASK] ** 2)))


def bench_scene(name, args):
    scene = mi.load_file(str(ROOT / "scenes_xml" / f"{name}.xml"), width=args.image,
                         height=args.image)
    t0 = time.perf_counter()
    ref = converged_visibility(scene, n_light=1024, seed=0, spp=args.ref_spp)["vis_light"]
    out = {"scene": name, "reference_seconds": time.perf_counter() - t0}
    global MASK
    horizon = converged_visibility(scene, n_light=1024, seed=0, spp=args.ref_spp,
                                   occlusion=False)["vis_light"]
    MASK = (horizon <= 0.0) | (horizon >= 1.0)
    out["straddling_fraction"] = float(1.0 - MASK.mean())
    vis, t = frame(scene, {"type": "shadowmap", "method": "pcss", "resolution": args.map,
                           "cache_maps": False}, args.pcss_spp)
    out["pcss"] = {"spp": args.pcss_spp, "seconds": t, "rmse": errors(ref, vis)[0],
                   "penumbra_rmse": errors(ref, vis)[1], "masked_rmse": masked_rmse(ref, vis)}
    vis, t = frame(scene, {"type": "shadowmap", "method": "hard", "resolution": args.map,
                           "cache_maps": False}, args.pcss_spp)
    out["hard"] = {"spp": args.pcss_spp, "seconds": t, "rmse": errors(ref, vis)[0],
                   "penumbra_rmse": errors(ref, vis)[1], "masked_rmse": masked_rmse(ref, vis)}
    ladder = []
    for spp, rays in LADDER:
        vis, t = frame(scene, {"type": "shadowmap", "method": "raytraced", "shadow_rays": rays},
                       spp)
        e, pe = errors(ref, vis)
        ladder.append({"spp": spp, "shadow_rays": rays, "seconds": t, "rmse": e,
                       "penumbra_rmse": pe, "masked_rmse": masked_rmse(ref, vis)})
        print(f"  {name}: raytraced {spp:3d} spp x {rays} rays: {t:.3f} s, RMSE {e:.4f}, "
              f"penumbra {pe:.4f}, masked {ladder[-1]['masked_rmse']:.4f}", flush=True)
    out["raytraced"] = ladder
    p = out["pcss"]
    under = [r for r in ladder if r["seconds"] <= p["seconds"]]
    out["equal_time"] = under[-1] if under else None
    better = [r for r in ladder if r["rmse"] <= p["rmse"]]
    out["equal_error"] = min(better, key=lambda r: r["seconds"]) if better else None
    better = [r for r in ladder if r["masked_rmse"] <= p["masked_rmse"]]
    out["equal_masked_error"] = min(better, key=lambda r: r["seconds"]) if better else None
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--image", type=int, default=512)
    ap.add_argument("--map", type=int, default=512)
    ap.add_argument("--ref-spp", type=int, default=4)
    ap.add_argument("--pcss-spp", type=int, default=1)
    ap.add_argument("--json", type=str, default=None)
    args = ap.parse_args(argv)
    results = []
    for name in SCENES:
        r = bench_scene(name, args)
        results.append(r)
        p, h = r["pcss"], r["hard"]
        print(f"{name} ({args.image}^2 image, {args.map}^2 maps, reference 1024 light samples x "
              f"{args.ref_spp} spp, {r['reference_seconds']:.1f} s)")
        print(f"  light straddles the horizon at {r['straddling_fraction']:.1%} of pixels")
        print(f"  pcss  {p['spp']} spp: {p['seconds']:.3f} s, RMSE {p['rmse']:.4f}, "
              f"penumbra RMSE {p['penumbra_rmse']:.4f}, masked RMSE {p['masked_rmse']:.4f}")
        print(f"  hard  {h['spp']} spp: {h['seconds']:.3f} s, RMSE {h['rmse']:.4f}, "
              f"penumbra RMSE {h['penumbra_rmse']:.4f}, masked RMSE {h['masked_rmse']:.4f}")
        et, ee = r["equal_time"], r["equal_error"]
        print("  equal time : " + (f"raytraced {et['spp']} spp x {et['shadow_rays']} rays, "
                                   f"{et['seconds']:.3f} s, RMSE {et['rmse']:.4f}"
                                   if et else "no ray-traced entry is as fast as PCSS"))
        print("  equal error: " + (f"raytraced {ee['spp']} spp x {ee['shadow_rays']} rays, "
                                   f"{ee['seconds']:.3f} s, RMSE {ee['rmse']:.4f}"
                                   if ee else "no ray-traced entry reaches PCSS's error"))
        em = r["equal_masked_error"]
        print("  equal masked error: " + (f"raytraced {em['spp']} spp x {em['shadow_rays']} "
                                          f"rays, {em['seconds']:.3f} s, masked RMSE "
                                          f"{em['masked_rmse']:.4f}" if em else "none"))
    if args.json:
        pathlib.Path(args.json).write_text(json.dumps(results, indent=2))


if __name__ == "__main__":
    main()
