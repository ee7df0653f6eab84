"""The order in which a virtual page build casts its tiles (``store.cast_order``): by face,
then near tiles together whatever their level (Morton order of their corners in level 0's
tile units); the pages and the image the same as when cast in the keys' order (level by
level)."""
from __future__ import annotations

import mitsuba as mi
import numpy as np
import pytest

from mi_shadowmap.virtual import planner, store as page_store
from mi_shadowmap.virtual.layout import key_fields

from conftest import SCENE_FILES


def _morton(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Morton code of ``(x, y)`` bit by bit (the test's own, not the store's)."""
    code = np.zeros(len(x), dtype=object)
    for b in range(32):
        code += ((x >> b) & 1).astype(object) << (2 * b)
        code += ((y >> b) & 1).astype(object) << (2 * b + 1)
    return code


def _build(scene, method: str, monkeypatch, order=None) -> tuple:
    """The image, every cast job's tile keys and each store's pools and tile minima
    (numpy) of a frame that builds its pages (``cache_maps`` false); ``order``: the cast
    order used."""
    jobs = []
    cast = planner.cast_tiles

    def spy(scene_, jobs_, minima=True):
        jobs.extend(j for j in jobs_ if j.n_tiles)
        return cast(scene_, jobs_, minima)

    with monkeypatch.context() as m:
        m.setattr(planner, "cast_tiles", spy)
        if order is not None:
            m.setattr(page_store, "cast_order", order)
        integ = mi.load_dict({"type": "shadowmap", "method": method, "virtual": True,
                              "cache_maps": False})
        img = np.array(mi.render(scene, integrator=integ, spp=4, seed=1))
    # (the tile minima: PCSS's blocker-search bound, store.face_near)
    pools = [{**{k: np.array(v) for k, v in j.store.pools.items()},
              "tile_min": j.store.tile_min[:j.store.next_slot].copy()} for j in jobs]
    return img, [j.tkeys.copy() for j in jobs], pools


@pytest.mark.parametrize("name", ["large_world", "room_two_points"])
@pytest.mark.parametrize("method", ["hard", "second_depth"])
def test_page_build_casts_near_tiles_together_with_the_same_depths(name, method,
                                                                    monkeypatch):
    """A first frame's tiles are cast by face, then in Morton order of their corners at
    level 0, the levels mixed (the keys' order went level by level, each level sweeping
    the whole region again: 11 % slower on the 1M-triangle mesh); every page's depths
    (first and second), every tile's minimum (with its tile: read in the cast order)
    and the image are bit-identical to a cast in the keys' order. room_two_points: two
    point lights' cube faces cast in one kernel."""
    path = [p for p in SCENE_FILES if p.stem == name][0]
    scene = mi.load_file(str(path), width=48, height=48)
    img, tkeys, pools = _build(scene, method, monkeypatch)
    assert tkeys and sum(len(k) for k in tkeys) > 100
    mixed = False
    for keys in tkeys:
        face, level, tx, ty = (np.asarray(a, np.int64) for a in key_fields(keys))
        code = _morton(tx << level, ty << level)
        rank = list(zip(face.tolist(), code.tolist()))
        assert rank == sorted(rank)
        mixed |= bool(np.any(np.diff(level) < 0))   # a coarser tile before a finer one
    assert mixed
    img_k, tkeys_k, pools_k = _build(scene, method, monkeypatch,
                                     order=lambda face, *_: np.arange(len(face)))
    assert [sorted(k.tolist()) for k in tkeys] == [sorted(k.tolist()) for k in tkeys_k]
    assert any(not np.array_equal(a, b) for a, b in zip(tkeys, tkeys_k))
    assert len(pools) == len(pools_k)
    for p, q in zip(pools, pools_k):
        assert p.keys() == q.keys()
        for layer in p:
            assert np.array_equal(p[layer], q[layer], equal_nan=True), layer
    assert np.array_equal(img, img_k, equal_nan=True)
