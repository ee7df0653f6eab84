"""The README's method table: misclassified (false lit) and visibility RMSE of every
built-in map method on every scene of scenes_xml/, against the reference that
tests/test_methods_on_scenes.py uses (raytraced for delta lights, the converged
soft-shadow reference for area lights, raytraced with 256 shadow rays per camera sample
for environment lights), at 64^2 images, 1024^2 maps, 4 spp, seed 0.

    python benchmarks/methods_table.py [--scenes sky_sun ...]   # prints a Markdown table
"""
from __future__ import annotations

import argparse
import pathlib
import sys

import numpy as np

import mi_shadowmap  # noqa: F401  (LLVM set-up, registration)
import mitsuba as mi
from mi_shadowmap import metrics
from mi_shadowmap.light_views import emitter_kind
from mi_shadowmap.methods import records
from mi_shadowmap.reference import converged_visibility

ROOT = pathlib.Path(__file__).resolve().parents[1]
SETTINGS = {"bilinear": [{"kernel": 2}, {"kernel": 4}], "mdsm": [{"depths": 2}, {"depths": 3}]}


def render_vis(scene, props, spp=4, seed=0):
    integ = mi.load_dict({"type": "shadowmap", **props})
    img = np.asarray(mi.render(scene, integrator=integ, spp=spp, seed=seed))
    names = integ.aov_names()
    n_colour = img.shape[-1] - len(names)
    return np.stack([img[..., n_colour + k] for k in range(len(names))])


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", nargs="+", default=None,
                    help="scene names in scenes_xml/ (default: all)")
    args = ap.parse_args(argv)
    cases = [(m.name, p) for m in records() if m.uses_map and m.builtin
             for p in SETTINGS.get(m.name, [{}])]
    header = [f"{m} " + " ".join(f"{k}={v}" for k, v in p.items()) for m, p in cases]
    print("| scene | " + " | ".join(h.strip() for h in header) + " |")
    print("|---" * (len(cases) + 1) + "|")
    for path in sorted((ROOT / "scenes_xml").glob("*.xml")):
        if args.scenes is not None and path.stem not in args.scenes:
            continue
        scene = mi.load_file(str(path), width=64, height=64)
        if any(emitter_kind(e) == "area" for e in scene.emitters()):
            ref = converged_visibility(scene, n_light=1024, spp=4, seed=0)
            ref = np.stack([ref[k] for k in sorted(ref)])
        elif any(emitter_kind(e) == "environment" for e in scene.emitters()):
            # an environment's AOV is the fraction of its light arriving unoccluded: a
            # one-ray reference gives it only as binary noise (1.9 % "misclassified" for
            # every method, RMSE 0.131)
            ref = render_vis(scene, {"method": "raytraced", "shadow_rays": 256})
        else:
            ref = render_vis(scene, {"method": "raytraced"})
        cells = []
        for method, params in cases:
            vis = render_vis(scene, {"method": method, "resolution": 1024, **params})
            m = metrics.misclassified(ref, vis)
            rmse = float(np.sqrt(np.mean((vis - ref) ** 2)))
            cells.append(f"{m['misclassified']:.2%} ({m['false_lit']:.2%}) / {rmse:.3f}")
        print(f"| {path.stem} | " + " | ".join(cells) + " |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
