"""Does the tuner keep its promise? (issue 12, part 3) One run, by hand.

    python benchmarks/bench_tune.py [--size 256] [--budgets 0.05 0.02 0.01]
                                    [--scenes spot_sphere_box ...] [--methods M ...]
                                    [--search-size 128] [--max-spp 1024] [--json out.json]

For every scene of scenes_xml/ (default: all but the spectral one, whose
visibility equals the RGB one's) and every budget on ``vis_rmse``:

1. ``mi_shadowmap.tune`` at ``--size``^2 (search at ``--search-size``);
2. the pick measured again *independently*, through the harness alone: a fresh
   reference of the same kind and spp as the tuner's (``raytraced`` for delta
   lights, the converged reference for area lights) and a fresh render of the
   pick, with seeds the tuner never used (``harness.compare(..., reference=...)``);
   the same for the ``raytraced`` configuration the tuner reports;
3. whether the pick lies on the Pareto front of the tuner's sweep, checked
   again with ``metrics.pareto_front`` on the sweep's (time, error) rows.

Prints one table (scene, budget, pick, spp, error, re-measured error, seconds,
raytraced config, its seconds, speed ratio) and writes every row to ``--json``
as it goes. Times are warm frames with the maps rebuilt on this machine's 2
shared cores: read the ratios, not the milliseconds.
"""
from __future__ import annotations

import argparse
import json
import pathlib
import time

import mi_shadowmap  # noqa: F401
from mi_shadowmap import harness, metrics
from mi_shadowmap.tables import text_table
from mi_shadowmap.tune import TuneError, tune

ROOT = pathlib.Path(__file__).resolve().parents[1]
SCENES = ("spot_sphere_box", "directional_mesh", "room_two_points", "cbox_area",
          "contact_hardening", "sky_sun")


def remeasure(scene, res: dict, config: dict, seed: int) -> float:
    """``config``'s metric against a fresh reference (same kind and spp as the tuner's),
    both rendered with seeds of their own."""
    spec = {"method": config["method"], **config["params"], "spp": config["spp"]}
    return harness.remeasure(scene, res["reference"], spec, res["metric"], seed)


def on_front(res: dict) -> bool:
    """The pick on the Pareto front of the sweep's rows of the searched methods (all rows
    when every method is searched; without the raytraced comparison rows otherwise)."""
    rows = [r for r in res["sweep"].rows if r["method"] in res["methods"]]
    front = metrics.pareto_front([r["time"] for r in rows], [r["error"] for r in rows])
    return bool(front[[r["name"] for r in rows].index(res["name"])])


def write(rows, path):
    if path:
        with open(path, "w") as f:
            json.dump(rows, f, indent=2)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--search-size", type=int, default=128)
    ap.add_argument("--budgets", type=float, nargs="+", default=[0.05, 0.02, 0.01])
    ap.add_argument("--scenes", nargs="+", default=list(SCENES))
    ap.add_argument("--methods", nargs="+", default=None)
    ap.add_argument("--max-spp", type=int, default=1024,
                    help="largest spp the tuner searches (tune's max_spp; default 1024)")
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    print("methods:", ", ".join(args.methods or harness.available_methods()))
    print("max_spp:", args.max_spp)
    rows = []
    for name in args.scenes:
        path = str(ROOT / "scenes_xml" / f"{name}.xml")
        size = {"width": args.size, "height": args.size}
        for b in args.budgets:
            t0 = time.perf_counter()
            try:
                res = tune(path, b, methods=args.methods, scene_params=size,
                           search_size=args.search_size, max_spp=args.max_spp)
            except TuneError as e:     # e.g. --methods without raytraced: a bias floor
                print(f"{name} {b:g}: {e}", flush=True)
                rows.append({"scene": name, "budget": b, "pick": "none: " + str(e).split(
                    "best reachable: ")[-1], "met": None, "pareto": None, "seconds": None})
                write(rows, args.json)
                continue
            scene = harness.load_scene(path, **size)
            again = remeasure(scene, res, res, seed=7000)
            rt = res["raytraced"]
            rt_again = remeasure(scene, res, rt, seed=8000) if rt else None
            row = {"scene": name, "budget": b, "pick": res["name"], "spp": res["spp"],
                   "error": res["error"], "remeasured": again, "met": again <= b,
                   "seconds": res["seconds"], "raytraced": rt["name"] if rt else None,
                   "rt_error": rt["error"] if rt else None, "rt_remeasured": rt_again,
                   "rt_seconds": rt["seconds"] if rt else None,
                   "speed_ratio": res["speed_ratio"], "pareto": on_front(res),
                   "reference": res["reference"]["name"],
                   "ref_spp": res["reference"]["spp"], "renders": res["search"]["renders"],
                   "steps": len(res["steps"]), "tune_seconds": res["elapsed"],
                   "total_seconds": time.perf_counter() - t0}
            rows.append(row)
            print(f"{name} {b:g}: {row['pick']} {row['error']:.4f} (again {again:.4f}), "
                  f"{row['seconds'] * 1e3:.1f} ms; raytraced {row['raytraced']} "
                  f"{(row['rt_seconds'] or 0) * 1e3:.1f} ms; ratio "
                  f"{row['speed_ratio'] or 0:.2f}; front {row['pareto']}; "
                  f"{row['tune_seconds']:.0f} s", flush=True)
            write(rows, args.json)
    cols = [("scene", "scene", "{}"), ("budget", "budget", "{:g}"), ("pick", "pick", "{}"),
            ("error", "error", "{:.4f}"), ("remeasured", "again", "{:.4f}"),
            ("ms", "ms", "{:.1f}"), ("raytraced", "raytraced", "{}"),
            ("rt_ms", "rt ms", "{:.1f}"), ("speed_ratio", "ratio", "{:.2f}"),
            ("pareto", "front", "{}")]
    print()
    print(text_table([{**r, "ms": r["seconds"] * 1e3 if r["seconds"] else None,
                       "rt_ms": (r.get("rt_seconds") or float("nan")) * 1e3} for r in rows],
                     cols))
    picked = [r for r in rows if r["met"] is not None]
    print(f"\nre-measured error meets the budget: {sum(r['met'] for r in picked)} of "
          f"{len(picked)} picks; on the front: {sum(r['pareto'] for r in picked)} of "
          f"{len(picked)}; no pick: {len(rows) - len(picked)}")


if __name__ == "__main__":
    main()
