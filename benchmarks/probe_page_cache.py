"""Stress probe of the virtual page cache along a long camera path.

One long-lived ``shadowmap`` integrator renders a scene along a random camera path (small
steps, big jumps and returns to earlier poses, so pages are reused, evicted and rebuilt),
optionally under a small ``memory_budget`` and with a ``params.update()`` of a shape's
vertices or of the light in the middle of the path. At every pose a fresh integrator
(``cache_maps=false``) renders a twin of the scene (loaded separately, edited and moved
the same way: no memo of the package is shared) at the same pose, and ``raytraced``
renders the reference. Per pose it compares the images and every light's visibility
AOV, the misclassified pixels of both against ``raytraced``, the pixels the cached frame
has lit where both the fresh frame and ``raytraced`` have shadow, and the page stats.

    python benchmarks/probe_page_cache.py [--moves 24] [--size 64] [--spp 4] [--seed 0]
        [--configs room_hard large_hard ...] [--budgets none small tiny]
        [--edits none shape light back dark] [--shared budget=tiny|method=pcf]
        [--page-size 8] [--variant llvm_ad_mono]

Prints one line per pose where anything differs and a summary line per configuration.
"""
from __future__ import annotations

import argparse
import pathlib
import sys
import time
import warnings

import mitsuba as mi

if __name__ == "__main__":       # --variant NAME (before anything reads a variant)
    mi.set_variant(sys.argv[sys.argv.index("--variant") + 1] if "--variant" in sys.argv
                   else "llvm_ad_rgb")

import numpy as np  # noqa: E402

from mi_shadowmap.scenes import load_scene  # noqa: E402

SCENES = pathlib.Path(__file__).resolve().parents[1] / "scenes_xml"
T = mi.ScalarTransform4f

#: name -> (scene file, method, small step, big jump (scene units), shape edit key,
#: light edit key)
CONFIGS = {
    "room_hard": ("room_two_points", "hard", 0.08, 1.0, "cube.vertex_positions",
                  "key.position"),
    "room_pcf": ("room_two_points", "pcf", 0.08, 1.0, "cube.vertex_positions",
                 "key.position"),
    "large_hard": ("large_world", "hard", 0.3, 6.0, None, "sun.to_world"),
    "spot_pcf": ("spot_sphere_box", "pcf", 0.08, 1.0, "box.vertex_positions",
                 "spot.to_world"),
    "cbox_pcss": ("cbox_area", "pcss", 0.04, 0.4, None, "light_quad.vertex_positions"),
    "contact_pcss": ("contact_hardening", "pcss", 0.05, 0.5, None, None),
    "sky_hard": ("sky_sun", "hard", 0.08, 1.0, "box.vertex_positions", None),
    "far_point_pcf": ("far_point", "pcf", 0.1, 2.0, "box_big.vertex_positions",
                      "light.position"),
}


def sensor_key(params) -> str:
    return next(k for k in params.keys() if k.endswith("to_world")
                and isinstance(params.properties[k][2], mi.Sensor))


def camera_path(start: np.ndarray, n: int, small: float, big: float, rng) -> list:
    """``n`` camera-to-world matrices from ``start``: small steps (translate up to
    ``small``, turn up to 2 degrees), big jumps (up to ``big``, 12 degrees) and returns
    to an earlier pose (a third of the moves after the first few)."""
    poses = [start]
    cur = start
    for k in range(n):
        r = rng.random()
        if k > 2 and r < 0.3:
            cur = poses[rng.integers(0, len(poses))]
        else:
            step, turn = (small, 2.0) if r < 0.8 else (big, 12.0)
            d = rng.uniform(-step, step, 3)
            axis = [0, 1, 0] if rng.random() < 0.7 else [1, 0, 0]
            m = T(cur) @ T().translate(d.tolist()) @ T().rotate(axis, rng.uniform(-turn, turn))
            cur = np.array(m.matrix, np.float64)
        poses.append(cur)
    return poses


_DARK = {}


def edit(params, key: str, amount: float) -> None:
    """Move the shape or light ``key``: vertices or a point light's position up by
    ``amount``; a transform turned by ``10 amount`` degrees (sideways); an emitted value
    set to 0 (``amount`` > 0) or back to what it was."""
    if key.endswith(".value"):
        if amount > 0:
            _DARK[id(params), key] = np.array(params[key], np.float32)
            params[key] = type(params[key])(0.0)
        else:
            params[key] = type(params[key])(*_DARK.pop((id(params), key)).ravel().tolist())
    elif key.endswith("vertex_positions"):
        v = np.array(params[key], np.float32).reshape(-1, 3)
        v[:, 1] += amount
        params[key] = mi.Float(v.ravel())
    elif key.endswith("position"):
        p = np.array(params[key], np.float32).ravel()
        p[1] += amount
        params[key] = mi.Point3f(*(float(x) for x in p))
    else:
        m = np.array(params[key].matrix, np.float64).reshape(4, 4)
        params[key] = T().rotate([0, 0, 1], 10.0 * amount) @ T(m)
    params.update()


def _render(scene, integ, spp, seed):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", RuntimeWarning)
        img = np.asarray(mi.render(scene, integrator=integ, spp=spp, seed=seed))
    return img, [str(w.message)[:60] for w in caught]


def run(name: str, moves: int, size: int, spp: int, seed: int, budget: float | None,
        edit_kind: str | None, verbose: bool = True, shared: dict | None = None,
        page_size: int | None = None) -> dict:
    """One configuration's path; returns the totals. ``shared``: the extra properties
    of a second long-lived integrator rendering every pose after the first (sharing its
    page stores where the layers agree: another method, another budget), the first then
    rendering it again; ``edit_kind``
    ``"back"``: the light moved at a third of the path and put back at two thirds."""
    file, method, small, big, shape_key, light_key = CONFIGS[name]
    path = str(SCENES / f"{file}.xml")
    props = {"type": "shadowmap", "method": method}
    if budget is not None:
        props["memory_budget"] = budget
    if page_size is not None:
        props["page_size"] = page_size
    # with a second integrator: the first renders each pose again after it (a still
    # camera whose store the second one changed: evicted, shrunk, grown)
    other = {k: v for k, v in {**props, **(shared or {})}.items() if v is not None}
    every = [props] + ([other, props] if shared is not None else [])
    scene = load_scene(path, width=str(size), height=str(size))
    twin = load_scene(path, width=str(size), height=str(size))
    params, tparams = mi.traverse(scene), mi.traverse(twin)
    key = sensor_key(params)
    start = np.array(params[key].matrix, np.float64).reshape(4, 4)
    rng = np.random.default_rng(seed)
    poses = camera_path(start, moves, small, big, rng)
    integs = [mi.load_dict(p) for p in every[:2]]
    integs += integs[:len(every) - len(integs)]
    edit_key = {"shape": shape_key, "light": light_key, "back": light_key}.get(edit_kind)
    if edit_kind == "dark":     # the first light's emitted value 0, then back
        edit_key = next((k for k in params.keys() if k.endswith(
            ("intensity.value", "irradiance.value", "radiance.value"))), None)
        if edit_key is None:
            return None
    amount = 0.0
    if edit_key:
        amount = 0.05 if "vertex" in edit_key or "position" in edit_key else 0.3
    edits = ({len(poses) // 3: amount, 2 * len(poses) // 3: -amount}
             if edit_kind in ("back", "dark")
             else {len(poses) // 2: amount} if edit_key else {})
    tot = dict(poses=0, img_diff=0, aov_diff=0, false_lit=0, mis_cached=0.0,
               mis_fresh=0.0, texels_cached=0, texels_fresh=0, reused=0, warned=0,
               max_abs=0.0)
    t_start = time.perf_counter()
    for k, pose in enumerate(poses):
        if k in edits:
            for p in (params, tparams):
                edit(p, edit_key, edits[k])
        for p in (params, tparams):
            p[key] = T(pose)
            p.update()
        img_r, _ = _render(twin, mi.load_dict({"type": "shadowmap", "method": "raytraced"}),
                           spp, k)
        for which, (integ, p) in enumerate(zip(integs, every)):
            img_c, warn_c = _render(scene, integ, spp, k)
            st_c = dict(integ.stats)
            fresh = mi.load_dict({**p, "cache_maps": False})
            img_f, warn_f = _render(twin, fresh, spp, k)
            st_f = dict(fresh.stats)
            n_col = img_c.shape[-1] - len(integ.aov_names())
            vc, vf, vr = img_c[..., n_col:], img_f[..., n_col:], img_r[..., n_col:]
            img_diff = int(np.any(img_c[..., :n_col] != img_f[..., :n_col], axis=-1).sum())
            aov_diff = int(np.sum(vc != vf))
            false_lit = int(np.sum((vc >= 0.5) & (vf < 0.5) & (vr < 0.5)))
            mis_c = float(np.mean((vc >= 0.5) != (vr >= 0.5)))
            mis_f = float(np.mean((vf >= 0.5) != (vr >= 0.5)))
            max_abs = float(np.max(np.abs(img_c - img_f)))
            bad_table = table_mismatches(integ)
            tot["poses"] += 1
            tot["img_diff"] += img_diff
            tot["aov_diff"] += aov_diff
            tot["false_lit"] += false_lit
            tot["mis_cached"] += mis_c
            tot["mis_fresh"] += mis_f
            tot["texels_cached"] += st_c["texels_built"]
            tot["texels_fresh"] += st_f["texels_built"]
            tot["reused"] += st_c["pages_reused"]
            tot["warned"] += bool(warn_c)
            tot["max_abs"] = max(tot["max_abs"], max_abs)
            tot["bad_table"] = tot.get("bad_table", 0) + bad_table
            odd = (img_diff or aov_diff or false_lit or bad_table
                   or st_c["pages_marked"] != st_f["pages_marked"]
                   or st_c["texels_built"] > st_f["texels_built"]
                   or bool(warn_c) != bool(warn_f))
            if verbose and (odd or k in edits):
                print(f"  {name}[{which}] pose {k}{' (edited)' if k in edits else ''}: img "
                      f"{img_diff} aov {aov_diff} px (max |d| {max_abs:.3g}), false lit "
                      f"{false_lit}, mis {mis_c:.4f}/{mis_f:.4f}, marked "
                      f"{st_c['pages_marked']}/{st_f['pages_marked']}, built "
                      f"{st_c['pages_built']}/{st_f['pages_built']}, reused "
                      f"{st_c['pages_reused']}, texels {st_c['texels_built']}/"
                      f"{st_f['texels_built']}, table {bad_table}, warn "
                      f"{len(warn_c)}/{len(warn_f)} {warn_c[:1]}", flush=True)
    tot["seconds"] = time.perf_counter() - t_start
    tot["mis_cached"] /= tot["poses"]
    tot["mis_fresh"] /= tot["poses"]
    return tot


def table_mismatches(integ) -> int:
    """Entries of each virtual map's page table whose tile word (``dense_tiles``, what
    taps read) differs from its slot's tile mask (``tile_masks``, what :meth:`bind`'s
    walk reads), plus pages of the table whose slot holds another key in the store."""
    bad = 0
    for m in integ.maps:
        if not hasattr(m, "store"):
            continue
        dense = m.dense.numpy()
        tiles = m.dense_tiles.numpy()
        masks = m.tile_masks.numpy()
        ok = dense != 0xFFFFFFFF
        ok[len(dense) - 4:] = False          # the empty entry
        bad += int(np.sum(masks[dense[ok]] != tiles[ok]))
        held = set(m.store.slots.values())
        bad += len(set(dense[ok].tolist()) - held)
    return bad


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--moves", type=int, default=24)
    ap.add_argument("--size", type=int, default=64)
    ap.add_argument("--spp", type=int, default=4)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--configs", nargs="*", default=list(CONFIGS))
    ap.add_argument("--budgets", nargs="*", default=["none", "small"],
                    help="'none', 'small' (half the first frame's pages), 'tiny' (a "
                    "sixth) or MiB")
    ap.add_argument("--edits", nargs="*", default=["none", "shape", "light"],
                    help="none, shape, light, back (the light moved and put back), dark (a "
                    "light's emitted value 0, then back)")
    ap.add_argument("--page-size", type=int, default=None)
    ap.add_argument("--variant", default="llvm_ad_rgb")
    ap.add_argument("--shared", default=None,
                    help="a second long-lived integrator on the same scene: 'method=NAME', "
                    "'budget=none|small|tiny'")
    args = ap.parse_args()
    for name in args.configs:
        for b in args.budgets:
            budget = parse_budget(b, name, args.size, args.page_size)
            shared = None
            if args.shared:
                what, value = args.shared.split("=")
                shared = ({"method": value} if what == "method" else
                          {"memory_budget": None} if value == "none" else
                          {"memory_budget": parse_budget(value, name, args.size,
                                                         args.page_size)})
            for e in args.edits:
                kind = None if e == "none" else e
                if kind in ("shape", "light", "back") and CONFIGS[name][
                        4 if kind == "shape" else 5] is None:
                    continue
                tot = run(name, args.moves, args.size, args.spp, args.seed, budget, kind,
                          shared=shared, page_size=args.page_size)
                if tot is None:         # no emitted value to darken
                    continue
                print(f"{name} budget={b}{'' if budget is None else f' ({budget:.3f} MiB)'} "
                      f"edit={e} shared={args.shared} page_size={args.page_size}: "
                      + ", ".join(f"{k} {v:.4f}" if isinstance(v, float) else f"{k} {v}"
                                  for k, v in tot.items()), flush=True)


def parse_budget(b: str, name: str, size: int, page_size: int | None = None):
    if b == "none":
        return None
    if b in ("small", "tiny"):
        return small_budget(name, size, 2 if b == "small" else 6, page_size)
    return float(b)


def small_budget(name: str, size: int, div: int = 2, page_size: int | None = None) -> float:
    """The pages the first frame of ``name`` marks, divided by ``div``, with every
    map's fixed slots (MiB): a budget that degrades every frame's finest pages."""
    file, method = CONFIGS[name][:2]
    scene = load_scene(str(SCENES / f"{file}.xml"), width=str(size), height=str(size))
    integ = mi.load_dict({"type": "shadowmap", "method": method, "cache_maps": False,
                          **({} if page_size is None else {"page_size": page_size})})
    mi.render(scene, integrator=integ, spp=1)
    stores = {id(m.store): m.store for m in integ.maps if hasattr(m, "store")}
    st = next(iter(stores.values()))
    per_page = st.texels_per_page * 4 * len(st.pools)
    fixed = sum(1 + s.layout.view.n_faces for s in stores.values())
    return (integ.stats["pages_marked"] // div + fixed) * per_page / 2 ** 20


if __name__ == "__main__":
    main()
