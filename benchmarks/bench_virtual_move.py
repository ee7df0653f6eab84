"""Virtual shadow maps (issue 11): frame times with a still and a moving camera,
interleaved, against the unshadowed frame. One run, by hand:

    python benchmarks/bench_virtual_move.py [--scenes large_world far_point ...]
                                            [--method hard] [--image 256] [--spp 16]
                                            [--rounds 3]

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
"""
from __future__ import annotations

import argparse
import pathlib
import statistics
import sys

import mi_shadowmap  # noqa: F401  (LLVM set-up, registration)
import mitsuba as mi

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
from bench_virtual import move_camera, set_camera  # noqa: E402

from mi_shadowmap import harness  # noqa: E402
from mi_shadowmap.timing import render_timed  # noqa: E402

ROOT = pathlib.Path(__file__).resolve().parents[1]
SCENES = ["large_world", "far_point", "spot_sphere_box", "directional_mesh",
          "room_two_points", "cbox_area", "contact_hardening", "spectral_point"]


def bench_scene(name, args) -> dict:
    scene = harness.load_scene(str(ROOT / "scenes_xml" / f"{name}.xml"),
                               width=str(args.image), height=str(args.image))
    integ = {"unshadowed": {"method": "unshadowed"},
             "full": {"method": args.method, "virtual": False},
             "virtual": {"method": args.method}}
    integ = {k: mi.load_dict({"type": "shadowmap", **v}) for k, v in integ.items()}
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


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", nargs="+", default=SCENES)
    ap.add_argument("--method", default="hard")
    ap.add_argument("--image", type=int, default=256)
    ap.add_argument("--spp", type=int, default=16)
    ap.add_argument("--rounds", type=int, default=3)
    args = ap.parse_args(argv)
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
