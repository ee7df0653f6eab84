"""The benchmark scripts still run (they are not part of the suite otherwise and call
internals that change): each at its smallest settings, in its own process."""
import os
import pathlib
import subprocess
import sys

ROOT = pathlib.Path(__file__).resolve().parents[1]


def run_bench(script: str, *args: str, timeout: float = 300) -> str:
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(
        [str(ROOT)] + [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p]))
    proc = subprocess.run([sys.executable, str(ROOT / "benchmarks" / script), *args],
                          cwd=ROOT, env=env, capture_output=True, text=True, timeout=timeout)
    assert proc.returncode == 0, f"{script} failed:\n{proc.stderr[-3000:]}"
    return proc.stdout


def test_bench_lookup_runs_to_the_end():
    # rt_ray (raytraced as a user method) and the isolated shadow-ray kernel read
    # opts.light_sample, which only raytraced's properties declare
    out = run_bench("bench_lookup.py", "--image", "32", "--map", "64", "--repeats", "1")
    assert "rt_ray" in out and "shadow ray" in out


def test_bench_virtual_lookup_skips_an_environment_map():
    # sky_sun's one virtual map is the environment's (sub-views, no project_f64 of its
    # own): the step breakdown raised NotImplementedError; the scene is now skipped
    out = run_bench("bench_virtual_lookup.py", "--scenes", "sky_sun", "--image", "32",
                    "--repeats", "1")
    assert "| scene | step |" in out and "| sky_sun |" not in out


def test_bench_virtual_lookup_times_realigned_kernels_and_a_shadow_ray():
    # a row's kernel alone (no Mitsuba call, so no aligned stack object) did not realign
    # its stack frame, and the same hard lookup took 21 or 35 ms by the caller's stack
    # depth (benchmarks/RESULTS.md, forty-seventh session); the rows now realign it, as
    # render kernels do, and the lookup is compared with a shadow ray of the same run
    out = run_bench("bench_virtual_lookup.py", "--scenes", "far_point", "--image", "16",
                    "--spp", "2", "--repeats", "1", "--threads", "1")
    assert "kernels with a realigned frame" in out and "| far_point | shadow ray |" in out
    assert "one lookup / one shadow ray (each over `read`): far_point" in out
    sys.path.insert(0, str(ROOT / "benchmarks"))
    try:
        import re

        import drjit as dr
        import mitsuba as mi
        from bench_virtual_lookup import framed
    finally:
        sys.path.pop(0)
    if not mi.variant().startswith("llvm"):
        return
    x = dr.arange(mi.Float, 1000) * 0.37 - 5.0
    dr.eval(x)
    dr.kernel_history()   # clear
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        out, value = framed(x + 1.0, x)
        dr.eval(out, value)
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    ir = "".join(k["ir"].getvalue() for k in dr.kernel_history()
                 if k["type"] == dr.KernelType.JIT)
    assert max([int(a) for a in re.findall(r"= alloca [^\n]*, align (\d+)", ir)],
               default=0) >= 32
    assert (value.numpy() == x.numpy()).all()


def test_bench_virtual_lookup_counts_the_lookups_that_run_again_walked():
    # a knock-out that changes the levels changes how many packets run the walked second
    # run, which the timings then measure (benchmarks/RESULTS.md, fifty-second session)
    out = run_bench("bench_virtual_lookup.py", "--scenes", "far_point", "--image", "16",
                    "--spp", "2", "--repeats", "1", "--threads", "1")
    import re
    m = re.search(r"retries \(`hard, rendered`'s walked second run\): far_point (\d+) of "
                  r"(\d+) lanes \([0-9.]+ %\), (\d+) 8-lane packets", out)
    assert m, out
    lanes, hits, packets = (int(g) for g in m.groups())
    assert 0 < hits <= 16 * 16 * 2 and lanes <= hits and packets <= lanes


def test_bench_environment_names_the_default_maps():
    # the scene's defaults render virtual maps (integrator.resolution None): the
    # acceptance line printed "None^2 maps"
    out = run_bench("bench_environment.py", "--image", "16", "--ref-spp", "16", "--spp", "1",
                    "--K", "1", "--methods", "hard", "--hi-spp", "1")
    assert "None^2" not in out and "virtual maps" in out


def test_bench_environment_times_camera_moves():
    # --moves: the still and moved frames of each method under sky_sun, in one process
    out = run_bench("bench_environment.py", "--moves", "--image", "16", "--spp", "1",
                    "--rounds", "1", "--move-methods", "hard")
    assert "| hard | moved |" in out and "| unshadowed | still |" in out


def bench_module(name: str):
    sys.path.insert(0, str(ROOT / "benchmarks"))
    try:
        return __import__(name)
    finally:
        sys.path.remove(str(ROOT / "benchmarks"))


def test_bench_all_names_the_heavy_mesh_by_its_triangles():
    # part A and B rows said "1M-triangle mesh" whatever --triangles was
    bench_all = bench_module("bench_all")
    assert bench_all.heavy_name(1_000_000) == "1M-triangle mesh"
    assert bench_all.heavy_name(20_000) == "20,000-triangle mesh"


def test_bench_multiview_quick_keeps_a_smaller_image():
    # --quick set the image to 128^2 even when --image asked for less
    import argparse
    bench_multiview = bench_module("bench_multiview")
    args = argparse.Namespace(quick=True, image=32, views=[4, 16, 128], res=[64, 1024])
    args = bench_multiview.quick_settings(args)
    assert (args.image, args.views, args.res) == (32, [4, 16], [64])
    args = argparse.Namespace(quick=True, image=512, views=[4], res=[128])
    assert bench_multiview.quick_settings(args).image == 128


def test_bench_scene_kinds_runs_every_map_method_by_default():
    # its docstring promises every method at defaults; the default list had six of the
    # ten map methods (no vsm, evsm, msm, multiview)
    from mi_shadowmap.options import MAP_METHODS
    assert set(bench_module("bench_scene_kinds").METHODS) == set(MAP_METHODS)


def test_bench_prefiltered_bias_scores_on_the_references_camera_samples(monkeypatch):
    # the methods rendered with seed 1 against a seed-0 reference: at 128^2, 16 spp
    # raytraced itself then misclassified 0.3-1.6 % (anti-aliasing noise, not bias)
    import numpy as np
    mod = bench_module("bench_prefiltered_bias")
    seeds = []

    def fake_aovs(scene, props, spp, seed):
        seeds.append(seed)
        return np.zeros((1, 2, 2))

    class FakeScene:
        def emitters(self):
            return [None]

    monkeypatch.setattr(mod, "aovs", fake_aovs)
    monkeypatch.setattr(mod, "emitter_kind", lambda e: "spot")
    monkeypatch.setattr(mod.mi, "set_variant", lambda *a: None)
    monkeypatch.setattr(mod.mi, "load_file", lambda *a, **k: FakeScene())
    monkeypatch.setattr(mod.os, "listdir", lambda p: ["one.xml"])
    assert mod.main(["--image", "8", "--spp", "1"]) == 0
    assert len(seeds) == 1 + 27 and set(seeds) == {seeds[0]}


def test_bench_unseen_starts_at_the_first_seed_given():
    # the unseen worlds beyond the default seeds 0-7 re-checked (terrain 22 was over
    # issue 11's texel target); the defaults are unchanged
    out = run_bench("bench_unseen.py", "--kinds", "terrain", "--first-seed", "22",
                    "--seeds", "2", "--image", "16", "--spp", "1", "--methods", "hard")
    rows = [line for line in out.splitlines() if line.startswith("| terrain | ")]
    assert [r.split("|")[2].strip() for r in rows[:2]] == ["22", "23"]
    assert "seeds 22-23" in out


def test_bench_unseen_texels_only_gives_each_methods_first_frame_texels():
    # --texels-only: the scan of many seeds for issue 11's texel target (no reference);
    # its numbers are the first frame's texels_built per film pixel of a real render
    import mitsuba as mi
    from mi_shadowmap.scenes import random_terrain_world
    out = run_bench("bench_unseen.py", "--texels-only", "--kinds", "terrain", "--first-seed",
                    "22", "--seeds", "1", "--image", "32", "--methods", "hard", "pcf")
    row = next(line for line in out.splitlines() if line.startswith("| terrain | 22 |"))
    got = [float(c) for c in row.split("|")[3:5]]
    want = []
    for m in ("hard", "pcf"):
        integ = mi.load_dict({"type": "shadowmap", "method": m})
        mi.render(mi.load_dict(random_terrain_world(22, width=32, spp=1)), integrator=integ)
        want.append(round(integ.stats["texels_built"] / 32 ** 2, 2))
    assert got == want and want[1] > want[0] > 0
    assert "rt noise" not in out and "over 8" in out


def test_bench_virtual_cost_cpu_mode_times_each_frames_parts_on_one_thread():
    # issue 11's single frame with maps built: wall-clock rounds on this shared machine
    # varied by more than the shadow cost; --cpu times each frame by one thread's CPU
    # time, cut into parts, every kernel of a frame inside its timed region
    out = run_bench("bench_virtual_cost.py", "--cpu", "--triangles", "2000", "--image", "16",
                    "--spp", "2", "--rounds", "2", "--best-of", "2")
    assert "one thread's CPU time" in out
    assert "kernels launched outside the timed frames: 0;" in out
    names = ("unshadowed", "raytraced", "hard full (built)", "hard virtual (built)")
    lines = out.splitlines()
    head = lines.index("| configuration | marks | plan | build | first pass | render | frame |")
    parts = {}
    for line in lines[head + 2:head + 2 + len(names)]:
        cells = [c.strip() for c in line.strip("|").split("|")]
        parts[cells[0]] = cells[1:]
    assert set(parts) == set(names)
    for name, cells in parts.items():
        assert float(cells[-1]) > 0.0
        # a part: "kernels / host [JIT kernels, the longest one's lanes]", or "-"
        virtual = name == "hard virtual (built)"
        for part, cell in zip(("marks", "plan", "build"), cells):
            assert (cell != "-") == virtual, (name, part, cell)
        render = cells[4]
        kern, host = (float(x) for x in render.split("[")[0].split("/"))
        assert kern > 0.0 and host >= 0.0
        assert render.endswith(", 512]")          # the render kernel: 16^2 pixels x 2 spp
    # the virtual frame's build: its cast kernel, at least one JIT kernel
    assert int(parts["hard virtual (built)"][2].split("[")[1].split(",")[0]) >= 1
    frames = [line for line in lines if line.startswith("| hard virtual (built) |")]
    assert frames and all("nan" not in line and "inf" not in line for line in frames)
    lookup = [line for line in lines if line.startswith("Render part over the unshadowed")]
    assert lookup and "of a ray" in lookup[0] and "nan" not in lookup[0]


def test_bench_lookup_kernel_times_the_still_frames_trace_and_kernels_on_one_thread():
    # issue 11's still frame: the virtual lookup's excess over full maps, cut into the
    # host's trace and the kernels by one thread's CPU time; the virtual frame twice a
    # round (the same kernel: the method's resolution), nothing compiled after round 0
    out = run_bench("bench_lookup_kernel.py", "--scenes", "far_point", "--image", "32",
                    "--spp", "1", "--rounds", "2")
    assert "one thread's CPU time" in out and "load average" in out
    rows = {}
    for line in out.splitlines():
        if line.startswith("| far_point |"):
            cells = [c.strip() for c in line.strip("|").split("|")]
            rows[cells[1]] = cells[2:]
    assert list(rows) == ["virtual", "virtual again", "full", "unshadowed"]
    for name, (trace, kern, diff, span, smaller, ops, compiled) in rows.items():
        assert float(trace) > 0.0 and float(kern) > 0.0, name
        lo, hi = (float(x) for x in span.replace("..", " ").split())
        assert lo <= float(diff) <= hi and smaller.endswith("/2") and compiled == "0", name
    assert float(rows["virtual"][2]) == 0.0           # (the reference of the differences)
    ops = {name: int(cells[5]) for name, cells in rows.items()}
    # the same kernel twice; the virtual lookup larger than a full map's, which is
    # larger than no lookup
    assert ops["virtual"] == ops["virtual again"] > ops["full"] > ops["unshadowed"]


def test_bench_virtual_move_profiles_a_moved_frame():
    # --profile: per function the moved frame's own CPU time against the unshadowed
    # frame's at the same camera, and both frames' kernels; a move compiles nothing
    out = run_bench("bench_virtual_move.py", "--profile", "2", "--scenes", "far_point",
                    "--image", "32", "--spp", "1", "--top", "8")
    lines = out.splitlines()
    assert lines[0].startswith("## far_point: moved frame")
    rows = [line for line in lines if line.startswith("| ") and "[ms]" not in line]
    assert len(rows) == 8
    # the virtual maps' own functions among the rows (prepare_virtual's steps are methods
    # of planner._FirstPass: none of them alone is in the top 8 of a 32^2 frame)
    assert any(row.split("|")[1].strip().split(":")[0] in ("planner.py", "marks.py")
               for row in rows)
    extra = [float(row.strip("|").split("|")[3]) for row in rows]
    assert extra == sorted(extra, reverse=True)
    kernels = [line for line in lines if "JIT kernels:" in line]
    assert len(kernels) == 2 and "COMPILED" not in out


def test_bench_virtual_move_cuts_a_moved_frame_on_one_thread():
    # --cpu: one thread's CPU time of moved and unshadowed frames, cut into the mark
    # pass, the rest of the first pass and the render, and the mark pass's camera rays
    # as kernels of their own; a move compiles nothing
    out = run_bench("bench_virtual_move.py", "--cpu", "2", "--scenes", "far_point",
                    "--image", "32", "--spp", "1")
    rows = [line for line in out.splitlines() if line.startswith("| far_point |")]
    assert len(rows) == 1 and "COMPILED" not in out
    cells = [c.strip() for c in rows[0].strip("|").split("|")]
    moved, unsh, ratio, mark = (float(c) for c in cells[1:5])
    first, render, rays = ([float(x) for x in c.split(" / ")] for c in cells[5:8])
    # (each printed to 0.1 ms: the ratio is of the unrounded medians); no timing is
    # compared with another (a shared machine): only the table's own arithmetic
    assert moved > 0.0 and unsh > 0.0
    assert abs(ratio - moved / unsh) < 0.01 + 0.1 * ratio / unsh
    # the mark pass and the rest of the first pass are parts of the moved frame
    assert 0.0 < mark <= moved + 0.1 and min(first) >= 0.0 and min(render) > 0.0
    assert abs(mark + first[0] + render[0] - moved) < 0.2 + 0.01 * moved
    # (the rays of a 32^2 film may take under 0.05 ms: printed 0.0)
    assert len(rays) == 3 and all(r >= 0.0 for r in rays)


def test_probe_tile_size_counts_the_smaller_tiles_and_times_the_first_pass():
    # 4^2 tiles inside 32^2 pages against the layout's 8^2 (fifty-sixth session, helper
    # B): the probe's layouts must take the smaller tiles (each row's texels are its
    # tiles times the tile's texels), mark inside the same pages, and with --half-res keep
    # hard's blocks in one list
    out = run_bench("probe_tile_size.py", "--triangles", "2000", "--image", "16", "--spp",
                    "1", "--rounds", "2", "--best-of", "1", "--cast-rounds", "1",
                    "--half-res")
    rows = {}
    for line in out.splitlines():
        cells = [c.strip() for c in line.strip("|").split("|")]
        if line.startswith("| 8^2 |") or line.startswith("| 4^2 |"):
            rows[cells[0]] = cells[1:]
    assert set(rows) == {"8^2", "4^2"}
    num = {k: [int(c.split(" ")[0].replace(",", "")) for c in v] for k, v in rows.items()}
    for name, side in (("8^2", 8), ("4^2", 4)):
        texels, tiles, pages = num[name][:3]
        assert texels == tiles * side * side > 0, (name, rows[name])
        assert rows[name][3].endswith("(1)"), rows[name]
    assert num["4^2"][2] == num["8^2"][2]                 # the same pages
    assert num["4^2"][0] < num["8^2"][0] and num["4^2"][1] > num["8^2"][1]
    parts = [line for line in out.splitlines()
             if line.split("|")[1:2] and line.split("|")[1].strip() in
             ("marks", "plan", "build", "first pass")]
    assert len(parts) == 4 and all("nan" not in p for p in parts)
    assert "The tiles cast again alone" in out


def test_bench_primary_reuse_splits_the_render_without_changing_its_image():
    # issue 11's reuse of the render's primary hits for the marks (fifty-second session,
    # helper F): the render driven from Python in one kernel, and split into a kernel of
    # closest hits and one of shading from the stored hits, gives Mitsuba's render
    # loop's image bit for bit (a rectangle, spheres and meshes; two point lights)
    out = run_bench("bench_primary_reuse.py", "--scenes", "large_world", "room_two_points",
                    "mesh", "--triangles", "2000", "--image", "32", "--spp", "2",
                    "--mesh-spp", "4", "--rounds", "1")
    lines = out.splitlines()
    for name, spp in (("large_world", 2), ("room_two_points", 2), ("mesh", 4)):
        head = lines.index(next(x for x in lines if x.startswith(f"## {name}, 32^2, {spp} spp")))
        rows = {}
        for line in lines[head + 4:]:
            if not line.startswith("| "):
                break
            cells = [c.strip() for c in line.strip("|").split("|")]
            rows[cells[0]] = cells[1:]
        same = {k: v[-1] for k, v in rows.items() if v[-1]}
        assert set(same) == {"render", "shadowmap unshadowed", "one kernel", "kernel 2",
                             "split", "kernel 2, 4 fields", "split, 4 fields"}
        # (shadowmap's unshadowed sums differently: up to 1 ulp apart)
        assert all(v == "True" for k, v in same.items() if k != "shadowmap unshadowed"), same
        assert all(float(v[0]) > 0.0 for v in rows.values())
    assert sum(x.startswith("split - render: ") for x in lines) == 3


def test_bench_primary_reuse_gathers_the_marks_inputs_from_the_stored_hits():
    # the marks' inputs from the split render's stored hits (each pixel's first, jittered
    # sample) against camera_hits' (its pixel centre): the same pixels, in the marks' lane
    # order, the point within a pixel's footprint of the centre's, the same footprints
    sys.path.insert(0, str(ROOT / "benchmarks"))
    try:
        import numpy as np

        from bench_primary_reuse import Wavefront, load
        from mi_shadowmap.virtual.marks import camera_hits
    finally:
        sys.path.pop(0)
    for name in ("large_world", "room_two_points"):
        scene = load(name, 48, 0, "")
        wave = Wavefront(scene, 4)
        wave.kernel1()
        p, n, _, dp_dx, _, valid = (np.array(x) for x in wave.mark_gather())
        si, c_dx, c_dy, c_valid = camera_hits(scene, scene.sensors()[0])
        c_valid = np.array(c_valid)
        both = valid & c_valid
        assert valid.shape == c_valid.shape and np.mean(valid == c_valid) > 0.97
        # a jittered sample is at most half a pixel from the centre in x and in y, on
        # the centre's plane: within the larger of the two one-pixel steps
        step_x, step_y = (np.linalg.norm(np.array(d), axis=0)[both] for d in (c_dx, c_dy))
        off = np.linalg.norm(p - np.array(si.p), axis=0)[both] / np.maximum(step_x, step_y)
        assert np.median(off) < 0.6 and np.mean(off < 1.01) > 0.9
        facing = np.sum(n * np.array(si.n), axis=0)[both]
        assert np.mean(facing > 0.99) > 0.9
        ratio = np.linalg.norm(dp_dx, axis=0)[both] / step_x
        assert np.median(np.abs(ratio - 1.0)) < 0.05


def test_probe_same_frames_finds_equal_frames_equal_and_a_changed_one(tmp_path):
    # two recordings of one commit compare equal (exit 0); a copy with one pixel of one
    # frame changed does not (exit 1, the array named)
    import numpy as np
    files = [str(tmp_path / f"{k}.npz") for k in "ab"]
    for f in files:
        out = run_bench("probe_same_frames.py", "record", f, "--scenes", "spot_sphere_box",
                        "--methods", "hard", "--image", "32", "--spp", "1", "--no-extras")
        assert "5 frames" in out
    assert "different: 0" in run_bench("probe_same_frames.py", "compare", *files)
    arrays = dict(np.load(files[1]))
    arrays["spot_sphere_box/hard/move1/img"][3, 4, 0] += 1.0
    np.savez(str(tmp_path / "c.npz"), **arrays)
    proc = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "probe_same_frames.py"),
                           "compare", files[0], str(tmp_path / "c.npz")],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 1 and "spot_sphere_box/hard/move1/img" in proc.stdout
