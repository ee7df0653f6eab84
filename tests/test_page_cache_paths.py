"""The virtual page cache along a camera path: a long-lived integrator renders every
pose as a fresh one does.

One ``shadowmap`` integrator renders a scene along a path of small steps, a big jump and
returns to earlier poses (pages reused, evicted under a small ``memory_budget``, built
again in recycled slots), with a ``params.update()`` in the middle (a shape's vertices,
a light moved, a light's emitted value set to 0 and back). At every pose a fresh
integrator (``cache_maps=false``) renders a twin of the scene, loaded on its own and
edited and moved the same way (no memo of the package shared), and the two images,
visibility AOVs included, are bit-identical (a ``box`` rfilter: the scenes' own). Each
frame's page table agrees with the store: every slot it names holds a page, and each
entry's tile word (what taps read) is its slot's tile mask (what ``bind``'s walk reads).

``benchmarks/probe_page_cache.py`` runs the long version (25-pose random paths, six
configurations, budgets, edits, page sizes, two integrators sharing a store:
``benchmarks/RESULTS.md``, fifty-third session, helper D).
"""
from __future__ import annotations

import warnings

import mitsuba as mi
import numpy as np
import pytest

from mi_shadowmap import virtual
from mi_shadowmap.scenes import load_scene
from mi_shadowmap.virtual.layout import INVALID_SLOT

from conftest import SCENES

T = mi.ScalarTransform4f

#: The path, relative to the scene's camera (translation in scene units, a turn about
#: the camera's up axis in degrees); ``None``: back to pose k
PATH = [((0, 0, 0), 0), ((0.1, 0, 0), 2), ((0.15, 0.05, 0), 3), ((-1.0, 0.3, 0.5), -12),
        None, ((-0.95, 0.3, 0.5), -10), 0, 2]

#: (scene, method, budget: None or the first frame's marked pages divided by it,
#: parameter edited at pose 4 (suffix), kind of edit)
CASES = {
    "room_hard_budget_shape": ("room_two_points", "hard", 6, "cube.vertex_positions",
                               "move"),
    "room_pcf_light": ("room_two_points", "pcf", None, "key.position", "move"),
    "large_world_hard_sun": ("large_world", "hard", None, "sun.to_world", "turn"),
    "cbox_pcss_budget_dark": ("cbox_area", "pcss", 3, "emitter.radiance.value", "dark"),
}


def _sensor_key(params) -> str:
    return next(k for k in params.keys() if k.endswith("to_world")
                and isinstance(params.properties[k][2], mi.Sensor))


def _edit(params, key: str, kind: str, saved: dict) -> None:
    """Move (``key``'s vertices or position up 0.05), turn (3 degrees) or darken
    ``key`` (its emitted value 0; again: back to what it was)."""
    value = params[key]
    if kind == "dark":
        if key in saved:
            params[key] = type(value)(*saved.pop(key))
        else:
            saved[key] = np.array(value, np.float32).ravel().tolist()
            params[key] = type(value)(0.0)
    elif kind == "turn":
        params[key] = T().rotate([0, 0, 1], 3.0) @ T(value.matrix.numpy()[..., 0])
    elif key.endswith("vertex_positions"):
        v = np.array(value, np.float32).reshape(-1, 3)
        v[:, 1] += 0.05
        params[key] = mi.Float(v.ravel())
    else:
        p = np.array(value, np.float32).ravel()
        params[key] = mi.Point3f(float(p[0]), float(p[1]) + 0.05, float(p[2]))
    params.update()


def _render(scene, integ, seed: int) -> tuple:
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", RuntimeWarning)
        img = np.asarray(mi.render(scene, integrator=integ, spp=2, seed=seed))
    assert np.isfinite(img).all()
    return img, [str(w.message) for w in caught]


def _table_mismatches(integ) -> int:
    """Entries of each virtual map's frame table that name a slot holding no page, or
    whose tile word differs from the slot's tile mask; slots holding two pages."""
    bad = 0
    for m in integ.maps:
        if getattr(m, "store", None) is None:
            continue
        dense, tiles, masks = (a.numpy() for a in (m.dense, m.dense_tiles, m.tile_masks))
        ok = dense != INVALID_SLOT
        bad += int(np.sum(masks[dense[ok]] != tiles[ok]))
        held = list(m.store.slots.values())
        bad += len(set(dense[ok].tolist()) - set(held)) + len(held) - len(set(held))
    return bad


@pytest.mark.parametrize("case", list(CASES))
def test_a_long_lived_integrator_renders_every_pose_as_a_fresh_one(case, monkeypatch):
    file, method, divide, suffix, kind = CASES[case]
    path = str(SCENES / f"{file}.xml")
    scene, twin = (load_scene(path, width="64", height="64") for _ in range(2))
    params, tparams = mi.traverse(scene), mi.traverse(twin)
    cam = _sensor_key(params)
    edit_key = next(k for k in params.keys() if k.endswith(suffix))
    props = {"type": "shadowmap", "method": method}
    if divide is not None:          # a budget of a fraction of the first frame's pages
        probe = mi.load_dict({**props, "cache_maps": False})
        mi.render(twin, integrator=probe, spp=1)
        st = next(m.store for m in probe.maps if getattr(m, "store", None) is not None)
        fixed = sum(1 + m.store.layout.view.n_faces for m in probe.maps
                    if getattr(m, "store", None) is not None)
        props["memory_budget"] = ((probe.stats["pages_marked"] // divide + fixed)
                                  * st.texels_per_page * 4 * len(st.pools) / 2 ** 20)
    evicted = []
    evict = virtual.PageStore.evict
    monkeypatch.setattr(virtual.PageStore, "evict", lambda self, keep, n: evicted.append(
        evict(self, keep, n)) or evicted[-1])
    start = T(params[cam].matrix.numpy()[..., 0])
    poses, saved, saved_twin = [], {}, {}
    integ = mi.load_dict(props)
    reused, warned = 0, 0
    for k, step in enumerate(PATH):
        if k in (4, 6) and (k == 4 or kind == "dark"):      # dark: back on at pose 6
            _edit(params, edit_key, kind, saved)
            _edit(tparams, edit_key, kind, saved_twin)
        if step is None:
            pose = poses[-1]
        elif isinstance(step, int):
            pose = poses[step]
        else:
            (dx, dy, dz), turn = step
            pose = start @ T().translate([dx, dy, dz]) @ T().rotate([0, 1, 0], turn)
        poses.append(pose)
        for p in (params, tparams):
            p[cam] = pose
            p.update()
        cached, warn_c = _render(scene, integ, k)
        stats = dict(integ.stats)
        fresh_integ = mi.load_dict({**props, "cache_maps": False})
        fresh, warn_f = _render(twin, fresh_integ, k)
        diff = int(np.sum(np.any(cached != fresh, axis=-1)))
        print(f"pose {k}: {diff} pixels differ; pages marked {stats['pages_marked']}, built "
              f"{stats['pages_built']}, reused {stats['pages_reused']}; texels "
              f"{stats['texels_built']} (fresh {fresh_integ.stats['texels_built']}); "
              f"evicted {sum(evicted)}; warnings {len(warn_c)}")
        assert diff == 0, f"pose {k}: the cached frame differs from a fresh render"
        assert len(warn_c) == len(warn_f)
        assert stats["pages_marked"] == fresh_integ.stats["pages_marked"]
        assert stats["texels_built"] <= fresh_integ.stats["texels_built"]
        assert _table_mismatches(integ) == 0
        reused += stats["pages_reused"] if k else 0
        warned += bool(warn_c)
    assert reused > 0                   # the path reused cached pages
    if divide is not None:              # and evicted and degraded them
        assert sum(evicted) > 0 and warned > 0
