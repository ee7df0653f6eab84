"""Proof that a change to the virtual maps' planner renders the same frames: record a
camera path's frames at one commit, record them again after the change, compare.

    python benchmarks/probe_same_frames.py record OUT.npz [--scenes far_point ...]
        [--methods hard pcf ...] [--image 128] [--spp 16] [--threads 2]
        [--no-extras] [--mono-scenes spot_sphere_box room_two_points]
    python benchmarks/probe_same_frames.py compare BEFORE.npz AFTER.npz

``record``: per scene (scenes_xml/<name>.xml at ``--image``^2) and method, with the page
cache emptied, a ``virtual=true`` integrator renders a first frame, three camera moves
(:func:`bench_virtual.move_camera`) and the return to the first camera, ``--spp`` spp,
seed 0, on ``--threads`` threads. Saved per frame: the image with its visibility AOVs,
``integrator.stats``' page counts and level histogram, every virtual map's page table
(``header``, ``dense_tiles``, ``face_near``), the render's shadowmap warnings with the
file and line they name, and how many JIT kernels it launched. Unless ``--no-extras``:
``memory_budget = 0.1`` on large_world and room_two_points (their maps degrade, one
warning a frame), a five-light scene (test_virtual's ``many_lights_scene``, 3 point
lights and 2 spots, box filter) whose second point light goes dark and is lit again
(``hard``, ``pcf``), and ``--mono-scenes`` in ``llvm_ad_mono`` (``hard``, ``pcss``).

``compare``: every array ``np.array_equal``; prints those that differ and exits 1 if any
does (or if the two files hold different frames). The kernels' hashes are not recorded:
they vary from process to process on the same commit (PYTHONHASHSEED=2 changed one
kernel's hash in 50 of 174 frames, with every image equal: benchmarks/RESULTS.md,
fifty-sixth session, helper D); their number does not.

Run ``record`` at both commits from the same checkout (``git stash`` or a worktree whose
folder is first on ``PYTHONPATH``): the warnings name their files.
"""
from __future__ import annotations

import argparse
import pathlib
import sys
import warnings

import numpy as np

ROOT = pathlib.Path(__file__).resolve().parents[1]
SCENES = ["far_point", "large_world", "room_two_points", "cbox_area", "sky_sun",
          "spot_sphere_box"]
METHODS = ["hard", "pcf", "pcss", "second_depth"]
STAT_KEYS = ("maps_built", "maps_reused", "texels_built", "pages_marked", "pages_built",
             "pages_reused", "level_histogram")
MOVES = [(0.05, 1.0), (0.05, -2.0), (-0.1, 3.0)]     # (sideways, yaw in degrees)


def _record_frame(out, tag, scene, integ, spp):
    import drjit as dr
    import mitsuba as mi
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        dr.kernel_history()
        img = np.asarray(mi.render(scene, integrator=integ, spp=spp, seed=0))
        history = dr.kernel_history()
    out[tag + "/kernels"] = np.asarray(sum(k["type"] == dr.KernelType.JIT for k in history))
    out[tag + "/img"] = img
    for k in STAT_KEYS:
        v = integ.stats[k]
        out[tag + "/" + k] = np.asarray(v if v is not None else [-1])
    for j, m in enumerate(getattr(integ, "maps", None) or []):
        if m is not None and hasattr(m, "header"):
            for a in ("header", "dense_tiles", "face_near"):
                out[f"{tag}/map{j}/{a}"] = np.asarray(getattr(m, a))
    said = [f"{pathlib.Path(c.filename).name}:{c.lineno}: {c.message}" for c in caught
            if "shadowmap" in str(c.message)]
    out[tag + "/warnings"] = np.asarray(said, dtype=str) if said else np.zeros(0)


def _path(out, name, scene, integ, spp):
    """The first frame, three moves and the return, from an empty page cache."""
    from bench_virtual import move_camera, set_camera
    from mi_shadowmap import virtual
    virtual.PAGE_CACHE.clear()
    _record_frame(out, f"{name}/first", scene, integ, spp)
    back = None
    for k, (dx, yaw) in enumerate(MOVES):
        old = move_camera(scene, dx, yaw)
        back = old if back is None else back
        _record_frame(out, f"{name}/move{k}", scene, integ, spp)
    set_camera(scene, back)
    _record_frame(out, f"{name}/back", scene, integ, spp)


def _lights_scene(size):
    import mitsuba as mi
    T = mi.ScalarTransform4f
    d = {"type": "scene",
         "sensor": {"type": "perspective", "fov": 60,
                    "to_world": T().look_at(origin=[0, 1.2, 3.6], target=[0, 0.5, 0],
                                            up=[0, 1, 0]),
                    "film": {"type": "hdrfilm", "width": size, "height": size,
                             "rfilter": {"type": "box"}}},
         "floor": {"type": "rectangle", "to_world": T().rotate([1, 0, 0], -90).scale(3)},
         "box": {"type": "cube", "to_world": T().translate([0.5, 0.3, 0]).scale(0.3)},
         "sph": {"type": "sphere", "center": [-0.7, 0.4, 0.3], "radius": 0.35}}
    for i in range(3):
        d[f"pl{i}"] = {"type": "point", "position": [-1.2 + 0.8 * i, 1.8, 0.5 - 0.3 * i]}
    for i in range(2):
        d[f"sp{i}"] = {"type": "spot", "cutoff_angle": 40,
                       "to_world": T().look_at(origin=[-1 + 0.6 * i, 2.2, 1.5],
                                               target=[0.2 * i - 0.3, 0, 0], up=[0, 1, 0])}
    return mi.load_dict(d)


def record(args) -> dict:
    from mi_shadowmap.scenes import load_scene     # (first: LLVM set-up, registration)
    import drjit as dr
    import mitsuba as mi
    dr.set_thread_count(args.threads)
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    out = {}

    def integrator(method, **kw):
        return mi.load_dict({"type": "shadowmap", "method": method, "virtual": True, **kw})

    def scene_of(name):
        return load_scene(str(ROOT / "scenes_xml" / f"{name}.xml"), width=str(args.image),
                          height=str(args.image))

    for s in args.scenes:
        scene = scene_of(s)
        for m in args.methods:
            _path(out, f"{s}/{m}", scene, integrator(m), args.spp)
        if not args.no_extras and s in ("large_world", "room_two_points"):
            _path(out, f"{s}/tight", scene, integrator("hard", memory_budget=0.1), args.spp)
    if not args.no_extras:
        scene = _lights_scene(args.image)
        params = mi.traverse(scene)
        for m in ("hard", "pcf"):
            integ = integrator(m)
            for tag, value in (("lit", 1.0), ("dark", 0.0)):
                params["pl1.intensity.value"] = value
                params.update()
                _path(out, f"lights/{m}/{tag}", scene, integ, args.spp)
            params["pl1.intensity.value"] = 1.0
            params.update()
            _record_frame(out, f"lights/{m}/lit_again", scene, integ, args.spp)
        if args.mono_scenes:
            mi.set_variant("llvm_ad_mono")
            for s in args.mono_scenes:
                scene = scene_of(s)
                for m in ("hard", "pcss"):
                    _path(out, f"mono/{s}/{m}", scene, integrator(m), args.spp)
    return out


def compare(a_path, b_path) -> int:
    a, b = np.load(a_path), np.load(b_path)
    only = sorted(set(a.files) ^ set(b.files))
    differ = [k for k in a.files if k in b.files and not np.array_equal(a[k], b[k])]
    frames = {k.rsplit("/", 1)[0] for k in a.files if k.endswith("/img")}
    print(f"{len(a.files)} / {len(b.files)} arrays, {len(frames)} frames; in one file "
          f"only: {len(only)}; different: {len(differ)}")
    for k in only[:20] + differ[:40]:
        print("  ", k)
    return 1 if only or differ else 0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    rec = sub.add_parser("record")
    rec.add_argument("out")
    rec.add_argument("--scenes", nargs="+", default=SCENES)
    rec.add_argument("--methods", nargs="+", default=METHODS)
    rec.add_argument("--image", type=int, default=128)
    rec.add_argument("--spp", type=int, default=16)
    rec.add_argument("--threads", type=int, default=2)
    rec.add_argument("--no-extras", action="store_true")
    rec.add_argument("--mono-scenes", nargs="*", default=["spot_sphere_box",
                                                          "room_two_points"])
    cmp_ = sub.add_parser("compare")
    cmp_.add_argument("before")
    cmp_.add_argument("after")
    args = ap.parse_args(argv)
    if args.cmd == "compare":
        return compare(args.before, args.after)
    sys.path.insert(0, str(ROOT / "benchmarks"))
    out = record(args)
    np.savez_compressed(args.out, **out)
    print(f"{len(out)} arrays, {sum(k.endswith('/img') for k in out)} frames -> {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
