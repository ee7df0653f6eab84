"""What smaller tiles inside the default pages would buy on issue 11's 1M-triangle frame:
a probe of the first pass, not of the image. One run, by hand:

    python benchmarks/probe_tile_size.py [--tile 4] [--triangles 1000000] [--image 256]
                                         [--spp 64] [--rounds 7] [--best-of 2] [--half-res]

The heavy mesh of ``benchmarks/bench_all.py`` under its spot light, ``hard`` on virtual maps
built every frame (``cache_maps=false``), rendered on one thread (``dr.set_thread_count(1)``)
and timed by its CPU clock as ``bench_virtual_cost.py --cpu`` does (its ``FrameClock``:
marks, plan, build, first pass), in rounds alternating the layout's own tiles
(:attr:`~mi_shadowmap.virtual.layout.VirtualLayout.tile_size`, 8 for pages of 32^2) and
``--tile`` (the layout's tile size, tiles per side and full mask replaced in each new
layout's ``__dict__``; ``--tile 4``: 64 tiles a 32^2 page, a 64-bit mask on the host).
Printed: the tiles cast, the texels ray-cast, the mark pass's block keys after its dedupe
(:func:`~mi_shadowmap.virtual.marks.dedupe_many`) and the tiles they expand to
(:func:`~mi_shadowmap.virtual.marks.block_tiles`), its block lists (one where
:func:`~mi_shadowmap.virtual.marks.shape_bits` finds room in the keys, else ``per_axis^2``),
the pages; per part the CPU ms of both and their paired difference; then each frame's tiles
cast again alone (the build's ray casts only, one thread, alternating, ``--cast-rounds``).

The render part is not reported: the page tables and lookups read 32-bit tile words, so
with more than 32 tiles a page the render reads the wrong bits (the probe renders anyway,
so that the frame's kernels are the ones a render launches). ``--half-res``: the layout's
``res0`` halved for both tile sizes (the same texels where no level 0 is read, as on this
mesh), so that ``hard``'s blocks keep one list at 4^2 (at ``res0`` 2^25 tiles of 4 leave
no room for their 5 shape bits: 17^2 lists, about 70 ms more marks). See
``benchmarks/RESULTS.md``, the fifty-sixth session, helper B.
"""
from __future__ import annotations

import argparse
import dataclasses
import os
import pathlib
import statistics
import sys
import tempfile
import time

import mi_shadowmap  # noqa: F401  (LLVM set-up, registration)
import drjit as dr
import mitsuba as mi

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
from bench_all import heavy_scene  # noqa: E402
import bench_virtual_cost as bvc  # noqa: E402

from mi_shadowmap.virtual import planner, store as store_mod  # noqa: E402


class Probe:
    """The planner's ``layout_for``, ``block_tiles`` and ``cast_tiles`` wrapped while it
    is active: the tile size of the layouts made (``tile``: None, the layout's own), and
    what the last frame of each tile size marked and cast."""

    def __init__(self, half_res: bool):
        self.tile = None
        self.half_res = half_res
        self.seen = {}      # tile size -> {"blocks", "lists", "tiles", "jobs"}
        self.saved = {}

    def __enter__(self):
        self.saved = {n: getattr(planner, n) for n in ("layout_for", "block_tiles",
                                                       "cast_tiles")}

        def layout_for(view, scene, opts):
            lay = self.saved["layout_for"](view, scene, opts)
            if self.half_res:
                lay = dataclasses.replace(lay, res0=lay.res0 // 2)
            if self.tile is not None:
                n = lay.page_size // self.tile
                # (cached_property values: the instance's own entries win)
                lay.__dict__.update(tile_size=self.tile, tiles_per_side=n,
                                    full_mask=-1 if n * n == 64 else (1 << n * n) - 1)
            return lay

        def block_tiles(found, per_axis, bits=None):
            out = self.saved["block_tiles"](found, per_axis, bits)
            self._rec().update(blocks=sum(len(f) for f in found),
                               lists=1 if bits is not None else per_axis ** 2,
                               tiles=len(out))
            return out

        def cast_tiles(scene, jobs, minima=True):
            self._rec()["jobs"] = list(jobs)
            return self.saved["cast_tiles"](scene, jobs, minima)

        planner.layout_for = layout_for
        planner.block_tiles = block_tiles
        planner.cast_tiles = cast_tiles
        return self

    def __exit__(self, *exc):
        for n, fn in self.saved.items():
            setattr(planner, n, fn)

    def _rec(self) -> dict:
        return self.seen.setdefault(self.tile, {})


def cast_alone(scene, jobs) -> float:
    """One thread's CPU ms to cast ``jobs``' tiles again (each store's in its own kernel,
    first depths only), read back as the build reads them."""
    dr.sync_thread()
    t0 = time.thread_time_ns()
    for job in jobs:
        if job.n_tiles:
            store_mod._cast_alone(scene, job, False, True)
            job.cast[0].numpy()
            job.cast = None
    dr.sync_thread()
    return (time.thread_time_ns() - t0) / 1e6


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--tile", type=int, default=4)
    ap.add_argument("--triangles", type=int, default=1_000_000)
    ap.add_argument("--image", type=int, default=256)
    ap.add_argument("--spp", type=int, default=64)
    ap.add_argument("--rounds", type=int, default=7)
    ap.add_argument("--best-of", type=int, default=2)
    ap.add_argument("--cast-rounds", type=int, default=9)
    ap.add_argument("--half-res", action="store_true")
    args = ap.parse_args(argv)
    print(f"# probe_tile_size {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, "
          f"Mitsuba {mi.__version__}, Dr.Jit {dr.__version__}")
    tiles = (None, args.tile)
    threads = dr.thread_count()
    had_history = dr.flag(dr.JitFlag.KernelHistory)
    with tempfile.TemporaryDirectory() as tmp, Probe(args.half_res) as probe:
        scene = mi.load_dict(heavy_scene(args.triangles, args.image, tmp))
        integs = {t: mi.load_dict({"type": "shadowmap", "method": "hard", "virtual": True,
                                   "cache_maps": False}) for t in tiles}
        dr.set_thread_count(1)
        dr.set_flag(dr.JitFlag.KernelHistory, True)
        clock = bvc.FrameClock()
        res = {t: [] for t in tiles}
        try:
            with bvc.clocked(clock, integs.values()):
                for t in tiles:                  # compile and warm up
                    probe.tile = t
                    bvc.cpu_frame(scene, integs[t], args.spp, 0, clock)
                for r in range(args.rounds):
                    for t in (tiles if r % 2 == 0 else tiles[::-1]):
                        probe.tile = t
                        best = None
                        for _ in range(max(1, args.best_of)):
                            bvc.cpu_frame(scene, integs[t], args.spp, r + 1, clock)
                            if best is None or clock.cpu_ms() < best[0]:
                                best = (clock.cpu_ms(), clock.parts())
                        res[t].append(best[1])
                clock.ticks = []
            casts = {t: [] for t in tiles}
            for r in range(args.cast_rounds):
                for t in (tiles if r % 2 == 0 else tiles[::-1]):
                    casts[t].append(min(cast_alone(scene, probe.seen[t]["jobs"])
                                        for _ in range(2)))
        finally:
            dr.set_thread_count(threads)
            dr.set_flag(dr.JitFlag.KernelHistory, had_history)
        res0 = integs[None].maps[0].layout.res0
    name = {t: f"{integs[t].maps[0].layout.tile_size if t is None else t}^2" for t in tiles}
    print(f"\n## {args.triangles:,}-triangle mesh, {args.image}^2, {args.spp} spp, hard "
          f"virtual built every frame, res0 {res0}{' (halved)' if args.half_res else ''}; "
          f"one thread's CPU time, {args.rounds} rounds alternating, each the least of "
          f"{args.best_of} frames; load average at the end {os.getloadavg()[0]:.1f}\n")
    print("| tiles | texels ray-cast | tiles cast | pages | block keys (lists) | "
          "tiles of the blocks |")
    print("|---|---|---|---|---|---|")
    for t in tiles:
        s = probe.seen[t]
        jobs = s["jobs"]
        print(f"| {name[t]} | {integs[t].stats.texels_built:,} | "
              f"{sum(j.n_tiles for j in jobs):,} | "
              f"{sum(len(j.keys) for j in jobs if j.keys is not None):,} | "
              f"{s['blocks']:,} ({s['lists']}) | {s['tiles']:,} |")
    print(f"\n| part | {name[None]}: kernels / host | {name[args.tile]}: kernels / host | "
          "difference, paired: median (min..max) |")
    print("|---|---|---|---|")
    for p in bvc.PARTS[:-1]:
        cells, tot = [], {}
        for t in tiles:
            rows = [pp[p] for pp in res[t] if p in pp]
            tot[t] = [a + b for a, b, *_ in rows]
            cells.append(f"{statistics.median(x[0] for x in rows):.1f} / "
                         f"{statistics.median(x[1] for x in rows):.1f}")
        d = [a - b for a, b in zip(tot[args.tile], tot[None])]
        print(f"| {p} | {cells[0]} | {cells[1]} | {statistics.median(d):+.1f} "
              f"({min(d):+.1f}..{max(d):+.1f}) |")
    d = [a - b for a, b in zip(casts[args.tile], casts[None])]
    print(f"\nThe tiles cast again alone (one thread, {args.cast_rounds} rounds, the least of "
          f"2 each): {name[None]} {statistics.median(casts[None]):.1f} ms, {name[args.tile]} "
          f"{statistics.median(casts[args.tile]):.1f} ms, paired difference "
          f"{statistics.median(d):+.1f} ({min(d):+.1f}..{max(d):+.1f}) ms.")


if __name__ == "__main__":
    main()
