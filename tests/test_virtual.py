"""Virtual shadow maps (issue 11, :mod:`mi_shadowmap.virtual`).

Analytic page depths, the mark pass and the level choice, agreement with the
ray-traced reference for every virtual method and light type, the large-world
and far-point-light scenes at defaults, the page cache across camera moves
(no new kernel), invalidation, the memory budget, variants, bad input.
"""
from __future__ import annotations

import linecache
import math
import warnings

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from mi_shadowmap import virtual
from mi_shadowmap.light_views.base import scene_bounds
from mi_shadowmap.virtual import layout, marks, planner, store as page_store
from mi_shadowmap.light_views.base import TEXEL_SAMPLE
from mi_shadowmap.light_views.local import LocalView
from mi_shadowmap.options import OptionError, parse_options
from mi_shadowmap.scenes import default_scene

from conftest import SCENES, error_chain, open_wall_scene

VIRTUAL_METHODS = ["hard", "pcf", "bilinear", "pcss", "second_depth", "mdsm", "vsm", "evsm",
                   "msm"]
LIGHTS = ["spot", "point", "directional", "area"]
T = mi.ScalarTransform4f


def shadowmap(**kw):
    return mi.load_dict({"type": "shadowmap", **kw})


def vis_of(scene, integ, spp=4, seed=1):
    img = np.asarray(mi.render(scene, integrator=integ, spp=spp, seed=seed))
    assert np.isfinite(img).all()
    return img[..., 3]


_REF = {}


def reference(key, scene, spp=4):
    if key not in _REF:
        _REF[key] = vis_of(scene, shadowmap(method="raytraced"), spp)
    return _REF[key]


def misclassified(a, b):
    return float(np.mean((a >= 0.5) != (b >= 0.5)))


# ------------------------------------------------------------------ analytic
def plane_scene(light: dict):
    """A ground plane y = 0 and nothing else, seen from above."""
    return mi.load_dict({
        "type": "scene",
        "sensor": {"type": "perspective", "fov": 40,
                   "to_world": T().look_at(origin=[0, 6, 0.01], target=[0, 0, 0], up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": 32, "height": 32}},
        "ground": {"type": "rectangle", "to_world": T().rotate([1, 0, 0], -90).scale(3)},
        "light": light})


@pytest.mark.parametrize("kind", ["spot", "point", "directional"])
def test_page_texels_hold_the_analytic_depth(kind):
    """Every texel of every ray-cast tile stores the distance along its own ray to the
    plane y = 0 (or +inf where that ray misses the 6 x 6 rectangle); a page's other
    tiles hold the coarsest level's texel over them."""
    light = {"spot": {"type": "spot", "cutoff_angle": 40,
                      "to_world": T().look_at(origin=[0.3, 4, 0.2], target=[0, 0, 0],
                                              up=[0, 0, 1])},
             "point": {"type": "point", "position": [0.3, 4, 0.2]},
             "directional": {"type": "directional", "direction": [0.2, -1, 0.1]}}[kind]
    scene = plane_scene(light)
    integ = shadowmap(method="hard", virtual=True, cache_maps=False)
    vis_of(scene, integ, spp=1)
    vmap = integ.maps[0]
    store = vmap.store
    assert store.n_pages > 0 and integ.stats["pages_built"] == store.n_pages
    P = store.layout.page_size
    keys = np.array(list(store.slots), np.uint64)
    slots = np.array([store.slots[k] for k in keys], np.int64)
    depth = store.pools["depth"].numpy().reshape(-1, P * P)[slots]
    face = (keys >> np.uint64(59)).astype(np.int64)
    level = ((keys >> np.uint64(54)) & np.uint64(31)).astype(np.int64)
    px = ((keys >> np.uint64(27)) & np.uint64((1 << 27) - 1)).astype(np.int64)
    py = (keys & np.uint64((1 << 27) - 1)).astype(np.int64)
    t = np.arange(P * P)
    gx = px[:, None] * P + t % P
    gy = py[:, None] * P + t // P
    res = (store.layout.res0 >> level)[:, None].astype(np.float64)
    uv = mi.Point2d(((gx + TEXEL_SAMPLE[0]) / res).ravel(), ((gy + TEXEL_SAMPLE[1]) / res).ravel())
    o, d = vmap.view.ray_through_f64(mi.UInt32(np.repeat(face, P * P)), uv)
    oy, dy = o.y.numpy(), d.y.numpy()
    t_plane = -oy / dy
    hx = o.x.numpy() + t_plane * d.x.numpy()
    hz = o.z.numpy() + t_plane * d.z.numpy()
    hits = (t_plane > 0) & (np.abs(hx) <= 3) & (np.abs(hz) <= 3)
    inner = hits & (np.abs(hx) < 2.99) & (np.abs(hz) < 2.99)   # away from the rim
    z = depth.ravel()
    tile, S = store.layout.tile_size, store.layout.tiles_per_side
    bit = (t % P) // tile + ((t // P) // tile) * S
    cast = (((store.slot_mask[slots][:, None] >> bit[None, :]) & 1) == 1).ravel()
    assert inner[cast].sum() > 1000
    np.testing.assert_allclose(z[inner & cast], t_plane[inner & cast], rtol=2e-5, atol=1e-5)
    assert np.all(np.isinf(z[cast & (~hits & (np.abs(hx) > 3.01) | (t_plane <= 0))]))
    # the other tiles: the coarsest level's texel (face f's coarsest page in slot f + 1)
    pool = store.pools["depth"].numpy().reshape(-1, P * P)
    shift = (store.layout.coarsest - level)[:, None]
    src = pool[np.repeat(face, P * P) + 1, ((gy >> shift) * P + (gx >> shift)).ravel()]
    np.testing.assert_array_equal(z[~cast], src[~cast])


def test_level_follows_the_pixel_footprint():
    """A film twice as wide halves the footprint: the pages move one level finer and
    the texels per film pixel stay about the same (density follows the pixel)."""
    levels, per_px = {}, {}
    for w in (64, 128):
        scene = mi.load_dict(default_scene(width=w, height=w, spp=1))
        integ = shadowmap(method="hard", virtual=True, cache_maps=False)
        vis_of(scene, integ, spp=1)
        hist = np.array(integ.stats["level_histogram"], float)
        levels[w] = float((hist * np.arange(len(hist))).sum() / hist.sum())
        per_px[w] = integ.stats["texels_built"] / (w * w)
    assert 0.6 <= levels[64] - levels[128] <= 1.4, levels
    assert 0.4 <= per_px[128] / per_px[64] <= 1.6, per_px


def test_pages_are_ray_cast_in_the_tiles_their_lookups_read():
    """A page's lookups often read a corner of it (a thin post, the edge of what the
    camera sees): only the tiles they read are ray-cast. ``texels_built`` counts the
    tiles' texels, far fewer than the pages' on the large world."""
    scene = mi.load_file(str(SCENES / "large_world.xml"), width=128, height=128)
    integ = shadowmap(method="hard", cache_maps=False)
    vis_of(scene, integ, spp=1)
    store = integ.maps[0].store
    lay = store.layout
    _, slots = store._index()
    cast = sum(bin(int(m)).count("1") for m in store.slot_mask[slots])
    assert lay.tiles_per_side == 4
    assert integ.stats["texels_built"] == cast * lay.tile_size ** 2
    whole = integ.stats["pages_built"] * lay.page_size ** 2
    print(f"{integ.stats['texels_built']} texels cast of {whole} in whole pages")
    assert integ.stats["texels_built"] <= 0.75 * whole
    assert np.all(store.slot_mask[slots] > 0)       # no page without a tile


def test_a_lookup_whose_tile_is_not_cast_reads_another_level():
    """The tile under the receiver must be ray-cast for a lookup to read its level (the
    rest of a page holds the coarsest level's depths): pixel centres find their own
    level; with one of their tiles taken out of its page's mask, the lookups in it walk
    to another level and the others do not move."""
    from mi_shadowmap.filters.common import Lookup
    scene = mi.load_dict(default_scene(width=48, height=48, spp=1, light="spot"))
    integ = shadowmap(method="hard", virtual=True, cache_maps=False)
    vis_of(scene, integ, spp=1)
    vmap = integ.maps[0]
    store, lay = vmap.store, vmap.layout
    si, dp_dx, dp_dy, valid = virtual.camera_hits(scene, scene.sensors()[0])
    pixel = virtual.camera_pixels(scene.sensors()[0])      # as the render's lookups
    lk = Lookup(dr.select(valid, si.p, 0.0), si.n, dp_dx, dp_dy, si, None, None,
                pixel=pixel)
    p64 = mi.Point3d(lk.p_world)
    face, uv64, _, inside = vmap.view.project_f64(p64)
    want = vmap.level_for(face, p64, dp_dx, dp_dy, si.n, pixel=pixel,
                          shape=si.shape).numpy()
    lit = (valid & inside).numpy()
    before = vmap.bind(lk, valid, per_tap=True).level.numpy()
    assert lit.sum() > 500 and np.all(before[lit] == want[lit])
    # the tile of every lit lane at its level; take out the most common one
    T, S = lay.tile_size, lay.tiles_per_side
    res = (lay.res0 >> want).astype(np.float64)
    gx = np.floor(uv64.x.numpy() * res).astype(np.int64)
    gy = np.floor(uv64.y.numpy() * res).astype(np.int64)
    tile = virtual.page_key(face.numpy().astype(np.uint64), want.astype(np.uint64),
                          gx // T, gy // T)
    keys, counts = np.unique(tile[lit & (want < lay.coarsest)], return_counts=True)
    k = int(keys[np.argmax(counts)])
    tx, ty = (k >> 27) & ((1 << 27) - 1), k & ((1 << 27) - 1)
    page = virtual.page_key(k >> 59, (k >> 54) & 31, tx // S, ty // S)
    present, slot = store.lookup(np.array([page], np.uint64))
    assert present[0]
    store.slot_mask[slot[0]] &= ~(1 << (tx % S + (ty % S) * S))
    store.version += 1
    after = virtual.VirtualShadowMap(store, {}, vmap.lod_bias, reach=vmap.reach,
                                     keep=vmap.keep).bind(lk, valid, per_tap=True)
    moved = after.level.numpy() != want
    inside_tile = lit & (tile == np.uint64(k))
    assert inside_tile.sum() == counts.max() > 0
    assert np.all(moved[inside_tile]) and not np.any(moved[lit & ~inside_tile])


def test_a_lookup_whose_level_is_not_built_walks_to_the_next_finer_first():
    """The walk's order (``bind``): the wanted level, else the next finer, else the
    nearest coarser one built. Asked one level coarser than their pixels' (``level``),
    the lanes whose page is not built there must read their own level, one finer (built:
    the render marked it), not walk on to coarser ones (mutation audit: a walk trying
    ``want + 1`` first passed all of this module; here its 359 walked lanes read levels
    up to 4 coarser)."""
    from mi_shadowmap.filters.common import Lookup
    scene = mi.load_dict(default_scene(width=48, height=48, spp=1, light="spot"))
    integ = shadowmap(method="hard", virtual=True, cache_maps=False)
    vis_of(scene, integ, spp=1)
    vmap = integ.maps[0]
    lay = vmap.layout
    si, dp_dx, dp_dy, valid = virtual.camera_hits(scene, scene.sensors()[0])
    pixel = virtual.camera_pixels(scene.sensors()[0])      # as the render's lookups
    lk = Lookup(dr.select(valid, si.p, 0.0), si.n, dp_dx, dp_dy, si, None, None,
                pixel=pixel)
    p64 = mi.Point3d(lk.p_world)
    face, _, _, inside = vmap.view.project_f64(p64)
    want = vmap.level_for(face, p64, dp_dx, dp_dy, si.n, pixel=pixel, shape=si.shape)
    lit = (valid & inside).numpy() & (want.numpy() + 1 < lay.coarsest)
    assert np.all(vmap.bind(lk, valid, per_tap=True).level.numpy()[lit] == want.numpy()[lit])
    got = vmap.bind(lk, valid, per_tap=True, level=want + 1).level.numpy()[lit]
    w = want.numpy()[lit]
    walked = got != w + 1
    assert lit.sum() > 500 and walked.sum() > 100, (lit.sum(), walked.sum())
    np.testing.assert_array_equal(got[walked], w[walked])


def _built(vmap, face, level, uv):
    """Whether the page and tile under ``uv`` (numpy, per lane) are built at ``level``
    on ``face`` (per lane), from the store's records (what ``bind``'s walk reads)."""
    rec, lay = vmap.page_records(), vmap.layout
    P, T, S = lay.page_size, lay.tile_size, lay.tiles_per_side
    masks = {(int(f), int(lv), int(x), int(y)): int(vmap.store.slot_mask[s])
             for f, lv, x, y, s in zip(rec["face"], rec["level"], rec["px"], rec["py"],
                                       rec["slot"])}
    out = np.zeros(len(level), bool)
    for k, (f, lv) in enumerate(zip(face, level)):
        g = np.floor(uv[k] * (lay.res0 >> int(lv))).astype(np.int64)
        m = masks.get((int(f), int(lv), int(g[0] // P), int(g[1] // P)))
        out[k] = m is not None and (m >> int((g[0] % P) // T + (g[1] % P) // T * S)) & 1
    return out


def test_a_lookup_whose_level_is_not_built_walks_to_the_nearest_coarser_level_built():
    """Past the next finer level the walk (``bind``) tries the coarser levels one at a
    time, up to the coarsest: the nearest built one hides the least under the biases,
    which scale with the texel. Asked two levels finer than their pixels' (not built
    there), every lane reads the first level built of ``want - 3``, ``want - 1``,
    ``want``, ``want + 1``, ...: its own level or the next finer, which the render built
    (a walk from ``want - 1`` straight to the coarsest, as before, read the coarsest for
    most of them)."""
    from mi_shadowmap.filters.common import Lookup
    scene = mi.load_dict(default_scene(width=48, height=48, spp=1, light="spot"))
    integ = shadowmap(method="hard", virtual=True, cache_maps=False)
    vis_of(scene, integ, spp=1)
    vmap = integ.maps[0]
    lay = vmap.layout
    si, dp_dx, dp_dy, valid = virtual.camera_hits(scene, scene.sensors()[0])
    pixel = virtual.camera_pixels(scene.sensors()[0])
    lk = Lookup(dr.select(valid, si.p, 0.0), si.n, dp_dx, dp_dy, si, None, None,
                pixel=pixel)
    p64 = mi.Point3d(lk.p_world)
    face, uv64, _, inside = vmap.view.project_f64(p64)
    want = vmap.level_for(face, p64, dp_dx, dp_dy, si.n, pixel=pixel, shape=si.shape)
    w = want.numpy().astype(np.int64)
    lanes = np.flatnonzero((valid & inside).numpy() & (w >= 3) & (w < lay.coarsest))
    got = vmap.bind(lk, valid, per_tap=True, level=want - 2).level.numpy()[lanes]
    faces = np.broadcast_to(np.asarray(face.numpy()).ravel(), w.shape)[lanes]
    uv = uv64.numpy().T[lanes]                   # (lanes, 2)
    expected = np.full(len(lanes), lay.coarsest)
    left = np.ones(len(lanes), bool)
    for step in [-3, -2] + list(range(-1, lay.coarsest)):
        lev = np.minimum(w[lanes] + step, lay.coarsest)
        here = left & _built(vmap, faces, lev, uv)
        expected[here], left = lev[here], left & ~here
    assert len(lanes) > 500 and np.all(got < lay.coarsest), np.sum(got == lay.coarsest)
    np.testing.assert_array_equal(got, expected)


def test_a_grazed_tower_wall_beyond_the_marks_spread_stays_shadowed():
    """``random_terrain_world(15)``: a tower wall that a sun 2.8 degrees high grazes
    (``n . l`` = 0.05) in the shadow of the objects before it. The receiver biases keep
    the wall's pixels 5 levels finer than their footprints, where a pixel spans about
    140 texels of the map's finer axis, more than the marks build around its centre
    (``marks.MAX_SPREAD``): the samples beyond walked to the coarsest level (its slope
    bias 3 km) and read lit where both references are dark (64^2: 14 pixels of ``hard``
    at 0.375-0.69, 12 of ``pcf``; now none above 0.19 / 0.23). The levels 2-7 coarser
    than the wanted one are built there (by the neighbouring pixels): the walk reads the
    nearest, and they stay dark."""
    from mi_shadowmap.scenes import random_terrain_world
    scene = mi.load_dict(random_terrain_world(15, width=64, spp=16))
    ref = [vis_of(scene, shadowmap(method="raytraced"), spp=16, seed=s) for s in (0, 5)]
    dark = (ref[0] == 0) & (ref[1] == 0)
    assert dark.sum() > 300
    for method in ("hard", "pcf"):
        v = vis_of(scene, shadowmap(method=method), spp=16, seed=0)
        assert np.sum(dark & (v >= 0.375)) == 0, (method, np.sum(dark & (v >= 0.375)))


def test_per_tap_lookups_read_unwalked_and_run_again_where_a_read_misses():
    """``hard`` reads at every lane's wanted level and runs again, walked, where its
    read finds the page or tile missing (:meth:`VirtualShadowMap.visibility`): with one
    tile taken out of its page, the lanes reading it are the ones that miss, and the
    result equals the lookup bound with the walk, lane for lane."""
    from mi_shadowmap.filters.common import Lookup, receiver
    from mi_shadowmap.filters.hard import hard
    scene = mi.load_dict(default_scene(width=48, height=48, spp=1, light="spot"))
    integ = shadowmap(method="hard", virtual=True, cache_maps=False)
    vis_of(scene, integ, spp=1)
    vmap, opts = integ.maps[0], integ.opts
    store, lay = vmap.store, vmap.layout
    si, dp_dx, dp_dy, valid = virtual.camera_hits(scene, scene.sensors()[0])
    lk = Lookup(dr.select(valid, si.p, 0.0), si.n, dp_dx, dp_dy, si, None, None,
                pixel=virtual.camera_pixels(scene.sensors()[0]))   # as the render's
    first = vmap.bind(lk, valid, per_tap=True, walk=False)
    hard(first, lk, opts, valid)
    assert not np.any((valid & first.inside & first.missed).numpy())   # all marked: built
    # take out the tile the most lanes read
    r = receiver(first, lk, opts)
    idx = first.texel_index(r.face, r.uv).numpy()
    lit = (valid & r.inside).numpy()
    P, T, S = lay.page_size, lay.tile_size, lay.tiles_per_side
    slot, local = idx // (P * P), idx % (P * P)
    tile = slot * S * S + (local // P) // T * S + (local % P) // T
    fine = lit & (slot > vmap.view.n_faces)                 # not the coarsest pages
    tiles, counts = np.unique(tile[fine], return_counts=True)
    t = int(tiles[np.argmax(counts)])
    store.slot_mask[t // (S * S)] &= ~(1 << (t % (S * S)))
    store.version += 1
    vmap2 = virtual.VirtualShadowMap(store, {}, vmap.lod_bias, reach=vmap.reach,
                                     keep=vmap.keep)
    first = vmap2.bind(lk, valid, per_tap=True, walk=False)
    hard(first, lk, opts, valid)
    missed = (valid & first.inside & first.missed).numpy()
    assert missed.sum() == counts.max() > 0 and np.all(missed == (fine & (tile == t)))
    walked = hard(vmap2.bind(lk, valid, per_tap=True), lk, opts, valid).numpy()
    ours = vmap2.visibility(hard, lk, opts, valid, per_tap=True).numpy()
    np.testing.assert_array_equal(ours[valid.numpy()], walked[valid.numpy()])


@pytest.mark.parametrize("method, light", [("hard", "spot"), ("hard", "point"),
                                           ("pcf", "spot"), ("second_depth", "point")])
def test_lookups_run_only_in_packets_with_a_lit_sample(monkeypatch, method, light):
    """A built-in method's lookup runs, binds and all, inside a symbolic conditional on
    its lit lanes (:func:`mi_shadowmap.packets.in_lit_packets`): a vector
    packet without a lit sample (outside the spot's cone, a face turned away from the
    light) skips it. The image is the one every packet looking up gives, bit for bit
    (``pcf`` draws its taps' seed inside it)."""
    scene = mi.load_dict(default_scene(width=32, height=32, spp=4, light=light))
    binds = []
    bind = virtual.VirtualShadowMap.bind

    def spied(self, *args, **kwargs):
        binds.append(dr.flag(dr.JitFlag.SymbolicScope))
        return bind(self, *args, **kwargs)

    monkeypatch.setattr(virtual.VirtualShadowMap, "bind", spied)
    img = np.asarray(mi.render(scene, integrator=shadowmap(method=method, virtual=True),
                               spp=4, seed=3))
    assert binds and all(binds), binds       # hard's first run's bind too
    dark = np.all(img[..., :3] == 0.0, axis=-1)          # no lit sample in the pixel
    assert 0 < dark.sum() < dark.size - 100
    from mi_shadowmap import integrator as integrator_module
    monkeypatch.setattr(integrator_module, "in_lit_packets",
                        lambda run, lk, *args, **kwargs: run(lk))
    every = np.asarray(mi.render(scene, integrator=shadowmap(method=method, virtual=True),
                                 spp=4, seed=3))
    np.testing.assert_array_equal(img, every)


@pytest.mark.parametrize("light", ["spot", "point", "directional"])
def test_the_second_run_binds_with_the_first_runs_projection(light):
    """:meth:`VirtualShadowMap.visibility`'s second run binds with the first bind's float64
    projection (``projected``) instead of projecting the point again inside its
    conditional: the same face, ``uv``, depth and ``inside`` as a fresh projection, and
    the same bound map and ``hard`` result, lane for lane, as a bind that projects."""
    from mi_shadowmap.filters.common import Lookup
    from mi_shadowmap.filters.hard import hard
    scene = mi.load_dict(default_scene(width=48, height=48, spp=1, light=light))
    integ = shadowmap(method="hard", virtual=True, cache_maps=False)
    vis_of(scene, integ, spp=1)
    vmap, opts = integ.maps[0], integ.opts
    si, dp_dx, dp_dy, valid = virtual.camera_hits(scene, scene.sensors()[0])
    lk = Lookup(dr.select(valid, si.p, 0.0), si.n, dp_dx, dp_dy, si, None, None,
                pixel=virtual.camera_pixels(scene.sensors()[0]))
    first = vmap.bind(lk, valid, per_tap=True, walk=False)
    fresh = vmap.view.project_f64(mi.Point3d(lk.p_world))
    v = valid.numpy()

    def lanes(x):
        return np.broadcast_to(np.asarray(x.numpy()), v.shape)[v]

    def same_projection(projected):
        for a, b in zip(projected, fresh):
            for x, y in zip(*(c if dr.depth_v(c) > 1 else [c] for c in (a, b))):
                np.testing.assert_array_equal(lanes(x), lanes(y))

    same_projection(first.projected)
    # a level other than the wanted one, as the walk may pick (and the wanted one)
    for level in (first.level, dr.minimum(first.level + 1, vmap.layout.coarsest)):
        reused = vmap.bind(lk, valid, per_tap=True, level=level, projected=first.projected)
        again = vmap.bind(lk, valid, per_tap=True, level=level)
        same_projection(reused.projected)
        same_projection((reused.view.face,) + tuple(reused.view._bound[1:]))   # its view's
        for x, y in ((reused.level, again.level), (reused.resolution, again.resolution),
                     (reused.view.origin.x, again.view.origin.x),
                     (reused.view.origin.y, again.view.origin.y),
                     (reused.entry[0], again.entry[0]), (reused.entry[1], again.entry[1]),
                     (hard(reused, lk, opts, valid), hard(again, lk, opts, valid))):
            np.testing.assert_array_equal(lanes(x), lanes(y))
    assert v.sum() > 1000


@pytest.mark.parametrize("misuse", ["draws", "loops"])
def test_per_tap_lookups_that_draw_or_read_in_loops_are_refused(misuse):
    """A per-tap lookup may run twice for some lanes: one that draws random numbers or
    reads the map inside a ``dr.while_loop`` gets a MethodError naming the flag."""
    from mi_shadowmap.filters.hard import hard
    from mi_shadowmap.methods import MethodError, register_method, unregister_method

    def draws(smap, lk, opts, active=True):
        u = lk.sampler.next_1d(active)
        return hard(smap, lk, opts, active) * dr.select(u < 2.0, 1.0, 0.0)

    def loops(smap, lk, opts, active=True):
        def body(k, v):
            return k + 1, v + hard(smap, lk, opts, active)
        _, v = dr.while_loop((mi.UInt32(0), mi.Float(0.0)), lambda k, v: k < 2, body)
        return v * 0.5

    register_method("per_tap_misuse", draws if misuse == "draws" else loops, virtual=True,
                    virtual_per_tap=True)
    try:
        scene = mi.load_dict(default_scene(width=16, height=16, spp=1, light="spot"))
        with pytest.raises(RuntimeError) as info:
            mi.render(scene, integrator=shadowmap(method="per_tap_misuse", virtual=True), spp=1)
        errors = [c for c in error_chain(info.value) if isinstance(c, MethodError)]
        assert errors and "virtual_per_tap=False" in str(errors[0])
        assert ("random numbers" if misuse == "draws" else "symbolic loops") in str(errors[0])
    finally:
        unregister_method("per_tap_misuse")


@pytest.mark.parametrize("light", ["spot", "point"])
def test_a_per_tap_lookup_may_intersect_receiver_planes_in_loops(light):
    """A per-tap lookup's binds make the bound point's ray frame (``LocalView._frame``,
    the float32 path of ``ray_plane``) only where the lookup first asks for it (``hard``
    never does): asked for inside a ``dr.while_loop`` and again after it, it gives the
    values the same lookup registered with ``virtual_per_tap=False`` (whose binds make
    it up front) gives, and a frame first made inside the loop is not kept for use
    outside it (its variables belong to the loop)."""
    from mi_shadowmap.filters.common import receiver
    from mi_shadowmap.methods import register_method, unregister_method

    def planes(smap, lk, opts, active=True):
        r = receiver(smap, lk, opts)
        z_map = dr.gather(mi.Float, smap.depth, smap.texel_index(r.face, r.uv),
                          active & r.inside)

        def body(k, acc):
            uv = r.uv + mi.Point2f(mi.Float(k) - 1.0, 0.5) / mi.Float(smap.resolution)
            t, _ = smap.view.ray_plane(r.face, uv, lk.p_world, lk.n_world, 0.05)
            return k + 1, acc + t

        _, acc = dr.while_loop((mi.UInt32(0), mi.Float(0.0)), lambda k, acc: k < 3, body)
        t0, _ = smap.view.ray_plane(r.face, r.uv, lk.p_world, lk.n_world, 0.05)
        lit = ~r.inside | (r.depth <= z_map)
        # the planes' depths in the result (in [0, 1]): any change shows
        tilt = (acc - 3.0 * t0) / dr.maximum(r.texel_world, 1e-20)
        return dr.select(lit, 0.5, 0.0) + 0.25 + 0.25 * dr.tanh(tilt)

    register_method("planes_per_tap", planes, virtual=True, virtual_per_tap=True)
    register_method("planes_block", planes, virtual=True, virtual_per_tap=False)
    try:
        scene = mi.load_dict(default_scene(width=32, height=32, spp=2, light=light))
        a = vis_of(scene, shadowmap(method="planes_per_tap", virtual=True), spp=2)
        b = vis_of(scene, shadowmap(method="planes_block", virtual=True), spp=2)
        assert np.unique(np.round(a, 3)).size > 20
        np.testing.assert_array_equal(a, b)
    finally:
        unregister_method("planes_per_tap")
        unregister_method("planes_block")


# ---------------------------------------------------------- against the truth
#: (light, method) -> measured misclassified at 64^2, 4 spp (virtual defaults); bounds x2.
@pytest.mark.parametrize("light", LIGHTS)
@pytest.mark.parametrize("method", VIRTUAL_METHODS)
def test_virtual_maps_agree_with_raytracing(light, method):
    scene = mi.load_dict(default_scene(width=64, height=64, spp=4, light=light))
    ref = reference(("default", light), scene)
    full = misclassified(vis_of(scene, shadowmap(method=method, virtual=False)), ref)
    virt = misclassified(vis_of(scene, shadowmap(method=method, virtual=True)), ref)
    print(f"{light} {method}: misclassified full {full:.3%}, virtual {virt:.3%}")
    if method == "mdsm":
        # the 2-SM's maximum lights a band about one texel wide on an edge's shadow side,
        # so mdsm's error follows the texel's width more closely than the others': at
        # 64^2 the automatic full map has about 5 texels a pixel across, the virtual
        # level 1.4-2.8 (measured: point 1.10 % against 0.59 %, directional 1.00 against
        # 0.66; at 256^2 0.24 against 0.17 and 0.22 against 0.15)
        assert virt <= max(2.0 * full, full + 0.006)
    else:
        # virtual maps at lod_bias -0.5 are about as dense as the automatic full map
        assert virt <= max(1.5 * full, full + 0.004)


def boxed_light_scene(light_y: float = 1.1, orthographic: bool = False):
    """A closed unit cube floating 0.1 over a wide floor (y = 0.95), a point light inside
    it 0.05 over its bottom wall: nothing outside the cube is lit, and the light grazes
    the floor (tan(theta) of 3 to 20 and more, the cube's walls 0.5 from the light and
    the floor behind them 1-3 away). ``orthographic``: the same view through an
    orthographic camera 12 units wide."""
    to_world = T().look_at(origin=[8, 5, 10], target=[0, 1, 0], up=[0, 1, 0])
    sensor = ({"type": "orthographic", "to_world": to_world @ T().scale([6, 6, 1])}
              if orthographic else {"type": "perspective", "fov": 50, "to_world": to_world})
    return mi.load_dict({
        "type": "scene",
        "sensor": {**sensor,
                   "film": {"type": "hdrfilm", "width": 64, "height": 64,
                            "rfilter": {"type": "box"}}},
        "floor": {"type": "rectangle",
                  "to_world": T().translate([0, 0.95, 0]).rotate([1, 0, 0], -90).scale(20)},
        "box": {"type": "cube", "to_world": T().translate([0, 1.55, 0]).scale(0.5)},
        "light": {"type": "point", "position": [0, light_y, 0],
                  "intensity": {"type": "rgb", "value": 10.0}}})


@pytest.mark.parametrize("method", ["hard", "pcf", "bilinear", "mdsm"])
def test_a_light_grazing_the_floor_from_a_floating_box_lights_none_of_it(method):
    """"Never a wrong lit region": the receiver biases scale with the texel, and at the
    footprint's level (the coarsest, here) ``hard``'s slope bias, 1.6 units, passed the
    box wall 1.2-1.6 units in front of the floor: 6.8 % of the image lit (``pcf`` 2.5 %,
    ``bilinear`` 2.6 %, ``mdsm`` 7.0 %); full maps 0. The level's cap
    (:meth:`VirtualShadowMap.level_for`, the biases' reach) and the mark pass's blocks
    around such points: at most 2 pixels of 4096 (measured 1, 0, 1, 2)."""
    scene = boxed_light_scene()
    ref = reference(("boxed", 64), scene)
    assert ref.max() < 0.5
    full = vis_of(scene, shadowmap(method=method, virtual=False))
    integ = shadowmap(method=method, virtual=True, cache_maps=False)
    virt = vis_of(scene, integ)
    lit_full, lit_virt = int(np.sum(full >= 0.5)), int(np.sum(virt >= 0.5))
    print(f"{method}: lit pixels full {lit_full}, virtual {lit_virt}; levels "
          f"{integ.stats.level_histogram}, texels {integ.stats.texels_built}")
    assert lit_full == 0
    assert lit_virt <= 2


def test_an_orthographic_view_of_the_boxed_light_finds_its_capped_level_built():
    """Under an orthographic camera the boxed light's floor has footprints 1.4 x 54 texels
    wide at the level the biases chose (:meth:`VirtualShadowMap.level_for`), long along
    the light's direction, and the next row's pixel centres 27 texels away along it: the
    mark pass marked 4 texels around each point (:data:`marks.MAX_SPREAD`, then) and left
    gaps between rows where no level near the wanted one was built; 0.17 % of the floor's
    samples walked to the coarsest level and ``hard`` lit 9 pixels of 4096 (full maps 0).
    Marking each capped pixel's footprint box: 0 lit, no sample walking more than one
    level coarser."""
    from mi_shadowmap.filters.common import Lookup
    scene = boxed_light_scene(orthographic=True)
    integ = shadowmap(method="hard", virtual=True, cache_maps=False)
    vis = vis_of(scene, integ)
    lit = int(np.sum(vis >= 0.5))
    vmap = integ.maps[0]
    sensor = scene.sensors()[0]
    idx = dr.arange(mi.UInt32, 64 * 64)
    n = far = 0
    for off in [(0.04, 0.02), (0.81, 0.91), (0.61, 0.73), (0.5, 0.05), (0.05, 0.5),
                (0.95, 0.95)]:
        pos = mi.Point2f((mi.Float(idx % 64) + off[0]) / 64, (mi.Float(idx // 64) + off[1]) / 64)
        ray, _ = sensor.sample_ray_differential(0.0, 0.5, pos, mi.Point2f(0.5))
        si = scene.ray_intersect(ray)
        dp_dx, dp_dy = integ._footprint(ray, si)
        p64 = mi.Point3d(si.p)
        want = vmap.level_for(vmap.view.project_f64(p64)[0], p64, dp_dx, dp_dy, si.n).numpy()
        lk = Lookup(si.p, si.n, dp_dx, dp_dy, si, None, None)
        got = vmap.bind(lk, si.is_valid(), per_tap=False).level.numpy()
        floor = (si.is_valid() & (si.p.y < 1.0)).numpy()
        n += floor.sum()
        far += np.sum(floor & (got > want + 1))
    print(f"{lit} lit; {far} of {n} samples walked more than one level coarser; texels "
          f"{integ.stats.texels_built}")
    assert n > 10000 and far <= 0.0002 * n
    assert lit == 0


def grazed_gap_scene():
    """A closed unit cube 0.1 over a floor (y = 1), a point light 0.2 over the floor 3.5
    in front of the cube: the light grazes the floor (tan(theta) 20-35 behind the cube)
    and reaches it through the gap under the cube, a band under 1 degree tall as the
    light sees it; the cube's shadow starts 3 behind it."""
    return mi.load_dict({
        "type": "scene",
        "sensor": {"type": "perspective", "fov": 40,
                   "to_world": T().look_at(origin=[4, 3, 5], target=[0, 1.6, 0], up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": 64, "height": 64,
                            "rfilter": {"type": "box"}}},
        "floor": {"type": "rectangle",
                  "to_world": T().translate([0, 1.0, 0]).rotate([1, 0, 0], -90).scale(20)},
        "box": {"type": "cube", "to_world": T().translate([0, 1.6, 0]).scale(0.5)},
        "light": {"type": "point", "position": [-4, 1.2, 0],
                  "intensity": {"type": "rgb", "value": 10.0}}})


def test_second_depth_keeps_the_lit_gap_under_a_box_on_a_grazed_floor():
    """``second_depth`` has no texel-scaled receiver bias, so its virtual levels followed
    the pixel footprint alone, whose anisotropy clamp (``ANISO``) leaves texels many
    footprints long along a grazed floor: the lit floor seen through the gap under the
    cube (one texel tall at that level) was shadowed, 132 pixels of 4096 misclassified
    (full maps 57, ``hard``'s virtual maps 0: its biases' reach caps the level). Its
    ``virtual_edge`` (half a texel, where the virtual samples' lit fraction crosses
    1/2) now caps it the same way: 4 (``lod_bias`` -2: 4)."""
    scene = grazed_gap_scene()
    ref = reference(("grazed_gap", 64), scene)
    integ = shadowmap(method="second_depth", virtual=True, cache_maps=False)
    virt = vis_of(scene, integ)
    full = vis_of(scene, shadowmap(method="second_depth", virtual=False))
    bad_v = int(np.sum((virt >= 0.5) != (ref >= 0.5)))
    bad_f = int(np.sum((full >= 0.5) != (ref >= 0.5)))
    print(f"misclassified: virtual {bad_v}, full {bad_f}; texels {integ.stats.texels_built}")
    assert 20 < bad_f < 200           # the scene is hard for full maps too
    assert bad_v <= 12


@pytest.mark.parametrize("method, lod_bias", [("hard", -4), ("hard", -2), ("pcf", -4)])
def test_a_finer_lod_bias_keeps_the_boxed_lights_floor_dark(method, lod_bias):
    """A finer ``lod_bias`` finer maps, not a wrong lit region: the biases' cap moved with
    it chose levels up to 5 finer than its (already finer) footprint's, where a pixel
    spans hundreds of texels, far more than the mark pass builds around its centre; the
    floor's lookups walked to the coarsest level (16 % of them at -4, 3 % at -2) and lit
    it (``hard`` 458 and 52 pixels of 4096, ``pcf`` 126; full maps 0, without the cap
    3, 1, 0). Now the cap is the default's at finer biases: measured 3, 0, 0 lit."""
    scene = boxed_light_scene()
    integ = shadowmap(method=method, virtual=True, cache_maps=False, lod_bias=lod_bias)
    virt = vis_of(scene, integ)
    lit = int(np.sum(virt >= 0.5))
    print(f"{method} lod_bias {lod_bias}: {lit} lit, texels {integ.stats.texels_built}")
    assert lit <= 4


def test_the_biases_cap_levels_where_the_light_grazes_only():
    """:meth:`VirtualShadowMap.level_for` with the receiver's normal: on the boxed light's
    floor finer than the footprint's level where the light grazes, and at that level the
    biases' reach (:class:`~mi_shadowmap.filters.common.BiasReach`) is at most
    ``REACH_PIXELS`` footprints along the floor; on a ground lit from above (tan(theta)
    below 1) the footprint's level everywhere."""
    from mi_shadowmap.filters.common import BiasReach
    from mi_shadowmap.virtual.lookup import REACH_PIXELS
    for scene, grazed in ((boxed_light_scene(), True),
                          (plane_scene({"type": "point", "position": [0.3, 4, 0.2]}), False)):
        integ = shadowmap(method="hard", virtual=True, cache_maps=False)
        vis_of(scene, integ, spp=1)
        vmap = integ.maps[0]
        assert vmap.reach == BiasReach.of(integ.opts)
        si, dp_dx, dp_dy, valid = virtual.camera_hits(scene, scene.sensors()[0])
        floor = valid & (si.p.y < 1.0)
        p64 = mi.Point3d(si.p)
        face = vmap.view.project_f64(p64)[0]
        plain = vmap.level_for(face, p64, dp_dx, dp_dy).numpy()
        capped = vmap.level_for(face, p64, dp_dx, dp_dy, si.n).numpy()
        on = floor.numpy()
        assert on.sum() > 1000 and np.all(capped[on] <= plain[on])
        finer = on & (capped < plain)
        print(f"grazed {grazed}: {finer.sum()} of {on.sum()} floor points finer, by "
              f"{np.unique((plain - capped)[finer])} levels")
        if not grazed:
            assert not finer.any()
            continue
        assert finer.sum() > 0.5 * on.sum()
        # the reach at the chosen level, in pixel footprints along the floor
        to_light = vmap.view.direction_to_light(si.p)
        n = mi.Vector3f(0, 1, 0)
        c = dr.dot(n, to_light)
        along = to_light - n * c
        sin_nl = dr.norm(along)
        r = vmap.reach.texels(dr.abs(c), sin_nl).numpy()
        f = ((dr.abs(dr.dot(dp_dx, along)) + dr.abs(dr.dot(dp_dy, along))) / sin_nl).numpy()
        t = vmap.view.texel_world_size(vmap.layout.res0, vmap.view.depth_of(si.p), si.p,
                                       n).numpy() * 2.0 ** capped
        pixels = r * t / f
        print(f"reach at the chosen level: up to {pixels[finer].max():.2f} footprints, "
              f"at the footprint's: up to {(pixels * 2.0 ** (plain - capped))[finer].max():.1f}")
        assert np.all(pixels[finer] <= REACH_PIXELS * 1.0001)
        assert np.all(pixels[finer] > REACH_PIXELS / 2.0)      # the coarsest such level


def _ledge_scene(n_l: float):
    """A tower 8 wide and 60 high on a ground, with a 12-wide, 0.6-thick ledge at 24
    turned 40 degrees (it overhangs the wall by 0.3-3.9), under a sun 86 degrees high
    that grazes the wall facing the camera (``n . l`` = ``n_l``); the camera looks up
    at the wall under the ledge (``random_terrain_world(17)``'s tower, simplified)."""
    ce = math.cos(math.radians(86.0))
    s = n_l / ce
    to_light = [ce * math.sqrt(1.0 - s * s), math.sin(math.radians(86.0)), ce * s]
    return mi.load_dict({
        "type": "scene",
        "sensor": {"type": "perspective", "fov": 30,
                   "to_world": T().look_at(origin=[3, 8, 40], target=[0, 22, 4], up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": 64, "height": 64}},
        "ground": {"type": "rectangle", "to_world": T().rotate([1, 0, 0], -90).scale(200)},
        "tower": {"type": "cube", "to_world": T().translate([0, 30, 0]).scale([4, 30, 4])},
        "ledge": {"type": "cube", "to_world": T().translate([0, 24, 0]).rotate([0, 1, 0], 40)
                  .scale([6, 0.3, 6])},
        "sun": {"type": "directional", "direction": [-c for c in to_light]}})


@pytest.mark.parametrize("n_l", [0.001, 0.003])
def test_a_ledge_shadows_the_wall_a_high_sun_grazes_under_it(n_l):
    """Where the slope bias is clamped (``tan(theta) > max_tan_slope``) it hides
    ``slope max_tan`` texels of depth along the light's ray, which on a wall the light
    grazes runs along the wall: the biases' level must count that many texels of the wall
    (:meth:`~mi_shadowmap.filters.common.BiasReach.texels`, the longer of that and the
    grazing offset's). Counted as a height times
    the clamped ``tan`` (10.2 texels at ``n . l`` = 0.001), the level was too coarse and
    ``hard`` lit the wall up to 4 pixels under the ledge: 19-20 of the 3547 shadowed
    pixels falsely lit (64^2, 4 spp), 0-1 now."""
    scene = _ledge_scene(n_l)
    ref = vis_of(scene, shadowmap(method="raytraced"))
    v = vis_of(scene, shadowmap(method="hard", virtual=True, cache_maps=False))
    shadowed = ref < 0.5
    false_lit = int(np.sum(shadowed & (v >= 0.5)))
    print(f"n.l {n_l}: {false_lit} of {shadowed.sum()} shadowed pixels lit")
    assert shadowed.sum() > 3000
    assert false_lit <= 2


def test_samples_off_the_pixel_centre_find_the_biases_level_built():
    """A level the biases chose finer than the footprint's (``level_for``) puts a pixel's
    samples several texels from its centre: the mark pass marks up to ``MAX_SPREAD``
    texels around such points, so that samples anywhere in their pixels find their
    level built, not walk to coarse levels (whose biases lose the shadows again). On
    the boxed light's floor at six points off the pixel centres: 0.11 % of the samples
    walk more than one level coarser (marking the usual texel around each point: 0.62 %,
    and ``hard`` lit 3 pixels)."""
    from mi_shadowmap.filters.common import Lookup
    scene = boxed_light_scene()
    integ = shadowmap(method="hard", virtual=True, cache_maps=False)
    vis_of(scene, integ, spp=1)
    vmap = integ.maps[0]
    sensor = scene.sensors()[0]
    W = H = 64
    n = far = 0
    for off in [(0.1, 0.1), (0.9, 0.9), (0.1, 0.9), (0.9, 0.1), (0.5, 0.05), (0.05, 0.5)]:
        idx = dr.arange(mi.UInt32, W * H)
        pos = mi.Point2f((mi.Float(idx % W) + off[0]) / W, (mi.Float(idx // W) + off[1]) / H)
        ray, _ = sensor.sample_ray_differential(0.0, 0.5, pos, mi.Point2f(0.5))
        si = scene.ray_intersect(ray)
        dp_dx, dp_dy = integ._footprint(ray, si)
        pixel = idx % W + idx // W * 65536          # as the render's lookups
        lk = Lookup(si.p, si.n, dp_dx, dp_dy, si, None, None, pixel=pixel)
        p64 = mi.Point3d(si.p)
        want = vmap.level_for(vmap.view.project_f64(p64)[0], p64, dp_dx, dp_dy, si.n,
                              pixel=pixel, shape=si.shape).numpy()
        got = vmap.bind(lk, si.is_valid(), per_tap=False).level.numpy()
        floor = (si.is_valid() & (si.p.y < 1.0)).numpy()
        n += floor.sum()
        far += np.sum(floor & (got > want + 1))
    print(f"{far} of {n} samples walked more than one level coarser")
    assert n > 10000 and far <= 0.003 * n



def test_a_hard_lookup_chooses_its_level_once(monkeypatch):
    """The biases' cap costs a lookup the direction to the light, the texel's width and
    a few divisions: ``hard``'s lookup traces :meth:`VirtualShadowMap.level_for` once (its
    second run, for lanes whose page is missing, reuses the first run's wanted level:
    Dr.Jit shares nothing across the conditional, and the render kernel had both, 2084
    operations on cbox_area, now 1886) and gives it the lookup's own float32 point, the
    variable the receiver's biases read, so that the direction to the light is computed
    once. The levels are the same: bit-identical images on the scenes_xml scenes at 64^2
    (hard, pcf, pcss) and the boxed light."""
    calls = []
    real = virtual.VirtualShadowMap._levels

    def spy(self, face, p64, dp_dx, dp_dy, n=None, p=None, **kwargs):
        calls.append(p is not None)
        return real(self, face, p64, dp_dx, dp_dy, n, p, **kwargs)

    scene = boxed_light_scene()
    integ = shadowmap(method="hard", virtual=True, cache_maps=False)
    vis_of(scene, integ, spp=1)
    monkeypatch.setattr(virtual.VirtualShadowMap, "_levels", spy)
    vis = vis_of(scene, integ, spp=1)
    assert calls == [True]
    assert int(np.sum(vis >= 0.5)) <= 2
    # the same levels with the float32 point as without
    vmap = integ.maps[0]
    si, dp_dx, dp_dy, valid = virtual.camera_hits(scene, scene.sensors()[0])
    p64 = mi.Point3d(si.p)
    face = vmap.view.project_f64(p64)[0]
    a = real(vmap, face, p64, dp_dx, dp_dy, si.n)
    b = real(vmap, face, p64, dp_dx, dp_dy, si.n, si.p)
    on = valid.numpy()
    assert on.sum() > 1000
    assert np.array_equal(a[0].numpy()[on], b[0].numpy()[on])
    assert np.array_equal(a[1].numpy()[:, on], b[1].numpy()[:, on])


def posts_scene(light: dict, width: int = 64, crop: dict | None = None,
                instanced: bool = False):
    """A floor (y = 0) grazed by ``light``, with a row of six thin posts (0.04 wide, 0.25
    tall) standing on it 1.5 to 3 from the light, seen from above at an angle: most of
    the floor has no occluder near it (after branch ``wip/probe-cap``). ``crop``: the
    film's crop window (``crop_offset_x`` ...). ``instanced``: the posts are instances of
    one cube (a ``shapegroup``)."""
    post = ({"type": "instance", "shape": {"type": "ref", "id": "posts"}} if instanced
            else {"type": "cube"})
    shapes = {f"post{k}": post | {"to_world": T().translate([1.5 + 0.3 * k, 0.125,
                                                             -0.6 + 0.25 * k])
                                  .scale([0.02, 0.125, 0.02])} for k in range(6)}
    if instanced:
        shapes = {"posts": {"type": "shapegroup", "post": {"type": "cube"}}} | shapes
    return mi.load_dict({
        "type": "scene",
        "sensor": {"type": "perspective", "fov": 45,
                   "to_world": T().look_at(origin=[2.5, 3.5, 4.5], target=[2.0, 0, 0],
                                           up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": width, "height": width,
                            "rfilter": {"type": "box"}, **(crop or {})}},
        "floor": {"type": "rectangle", "to_world": T().rotate([1, 0, 0], -90).scale(10)},
        **shapes, "light": light})


POSTS_LIGHTS = {
    "point": {"type": "point", "position": [0, 0.3, 0],
              "intensity": {"type": "rgb", "value": 10.0}},
    "spot": {"type": "spot", "cutoff_angle": 50, "intensity": {"type": "rgb", "value": 10.0},
             "to_world": T().look_at(origin=[0, 0.3, 0], target=[2, 0, 0], up=[0, 1, 0])}}


@pytest.mark.parametrize("light", ["point", "spot"])
@pytest.mark.parametrize("method", ["hard", "pcf"])
def test_the_biases_level_is_kept_where_a_probe_finds_an_occluder_or_an_edge(
        method, light, monkeypatch):
    """The mark pass probes each capped pixel centre's ray towards the light and the
    shadow rays of its footprint's corners (:func:`~mi_shadowmap.virtual.marks.probe_keeps`)
    and drops the biases' level for that pixel where they find no occluder and no edge;
    the pixel's lookups read the mark's decision. Against every capped pixel keeping it
    (the probe taken as always keeping), the thin posts grazed by a point or spot light
    0.3 over the floor build about half the texels for the same misclassified pixels
    (64^2, 16 spp, measured ``hard`` 25 / 24 point, 15 / 15 spot, ``pcf`` 42 / 42, 46 /
    46; summed error to ``raytraced`` 11.7 / 11.5, 10.6 / 10.1, 37.2 / 37.5, 38.4 /
    38.0; texels 0.51, 0.44, 0.52, 0.48x). With the lookups blind to the decision
    (wanting the biases' level everywhere, walking where it was not built: branch
    ``wip/probe-cap``'s lookups) ``pcf``'s summed error was 47.1 and 45.5: that
    branch's worse ``pcf`` error on the posts was the disagreement, not the
    corner probes."""
    scene = posts_scene(POSTS_LIGHTS[light])
    ref = reference(("posts", light), scene, spp=16)
    texels, bad, err = [], [], []
    for probe in (True, False):
        if not probe:
            monkeypatch.setattr(marks, "probe_keeps", lambda *a, **k: mi.Bool(a[7]))
        integ = shadowmap(method=method, virtual=True, cache_maps=False)
        vis = vis_of(scene, integ, spp=16)
        texels.append(integ.stats.texels_built)
        bad.append(int(np.sum((vis >= 0.5) != (ref >= 0.5))))
        err.append(float(np.abs(vis - ref).sum()))
    print(f"{method} {light}: texels with probes {texels[0]}, without {texels[1]}; "
          f"misclassified {bad[0]}, {bad[1]}; summed error {err[0]:.1f}, {err[1]:.1f}")
    assert texels[0] < 0.6 * texels[1]
    assert bad[0] <= bad[1] + 2
    assert err[0] <= 1.1 * err[1]


@pytest.mark.parametrize("method", ["hard", "pcf"])
def test_a_contact_shadow_under_a_light_just_over_the_floor_keeps_the_biases_level(method):
    """A point light 0.01 over the floor beside a ball resting on it: the ball's contact
    shadow is a wedge the pixels' own shadow rays reach under the ball's bottom. The
    footprint's level (the mark's fallback where its probe finds no occluder and no edge)
    compares along rays lifted off the floor by its normal offset, which meet the ball
    beside the wedge: the view behind the ball (64^2, 4 spp) had 165 (``hard``) / 179
    (``pcf``) pixels falsely shadowed against ``raytraced``, whose own noise (another
    seed) misclassifies 36. :func:`~mi_shadowmap.virtual.marks.probe_keeps` probes that
    lifted ray too and keeps the biases' level where it disagrees with the point's:
    39 / 52."""
    scene = mi.load_dict({
        "type": "scene",
        "sensor": {"type": "perspective", "fov": 40,
                   "to_world": T().look_at(origin=[5, 3, 2.5], target=[3, 0, -0.5],
                                           up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": 64, "height": 64,
                            "rfilter": {"type": "box"}}},
        "floor": {"type": "rectangle", "to_world": T().rotate([1, 0, 0], -90).scale(10)},
        "ball": {"type": "sphere", "center": [2.0, 0.7, 1.0], "radius": 0.7},
        "light": {"type": "point", "position": [0.5, 0.01, 2.5],
                  "intensity": {"type": "rgb", "value": 30.0}}})
    ref = reference("contact_1e-2", scene, spp=4)
    noise = misclassified(ref, vis_of(scene, shadowmap(method="raytraced"), spp=4, seed=2))
    vis = vis_of(scene, shadowmap(method=method, virtual=True, cache_maps=False), spp=4)
    false_shadow = float(np.mean((ref >= 0.5) & (vis < 0.5)))
    print(f"{method}: false shadow {false_shadow * 4096:.0f} pixels, noise {noise * 4096:.0f}")
    assert false_shadow <= 2.0 * noise


def _posts_point_hits(crop=None):
    """The posts under a point light (:func:`posts_scene`) rendered once with virtual
    ``hard`` maps: ``(scene, integrator, its map, sensor, camera_hits, camera_pixels)``."""
    scene = posts_scene(POSTS_LIGHTS["point"], crop=crop)
    integ = shadowmap(method="hard", virtual=True, cache_maps=False)
    vis_of(scene, integ, spp=1)
    sensor = scene.sensors()[0]
    return (scene, integ, integ.maps[0], sensor, virtual.camera_hits(scene, sensor),
            virtual.camera_pixels(sensor))


def test_marks_and_lookups_agree_on_the_biases_level_per_pixel():
    """Each pixel centre's lookup wants the level its mark chose
    (:func:`~mi_shadowmap.virtual.marks.marked_points`, with the probe) and finds it
    built: the lookup reads the mark's decision by its film pixel and shape
    (:meth:`VirtualShadowMap.keeps`), so what it reads does not depend on other
    pixels' marks. On a cropped film (the pixel id is the crop's), the integrator's
    pixel of each camera hit is :func:`~mi_shadowmap.virtual.marks.camera_pixels`'
    (the mark's).
    With the pixel unknown (``Lookup.pixel`` None) the lookups want the biases' level
    everywhere, which the mark dropped at some centres (a lookup there walks)."""
    from mi_shadowmap.filters.common import Lookup
    scene, integ, vmap, sensor, (si, dp_dx, dp_dy, valid), pixel = _posts_point_hits(crop={
        "crop_offset_x": 20, "crop_offset_y": 12, "crop_width": 40, "crop_height": 44})
    integ._sensor = sensor
    np.testing.assert_array_equal(integ._film_pixel(si, valid).numpy()[valid.numpy()],
                                  pixel.numpy()[valid.numpy()])
    # the render's marker: its probes and its rule for lights behind a smooth mesh
    # (marks._light_behind) see the camera's pinhole
    marker = marks.Marker(vmap.layout, vmap.lod_bias, reach=vmap.reach, scene=scene,
                          eye=virtual.camera_frame(sensor)[0])
    face, _, act, marked, _, dropped, _ = marks.marked_points(marker, si, dp_dx, dp_dy,
                                                              valid)
    lk = Lookup(dr.select(valid, si.p, 0.0), si.n, dp_dx, dp_dy, si, None, None,
                pixel=pixel)
    on = act.numpy()
    drop = dropped.numpy() & on
    want = vmap.level_for(face, mi.Point3d(si.p), dp_dx, dp_dy, si.n, pixel=pixel,
                          shape=si.shape).numpy()
    got = vmap.bind(lk, valid, per_tap=True).level.numpy()
    print(f"{on.sum()} centres, {drop.sum()} dropped the biases' level")
    assert on.sum() > 1000 and drop.sum() > 0.1 * on.sum()
    np.testing.assert_array_equal(want[on], marked.numpy()[on])
    np.testing.assert_array_equal(got[on], want[on])
    blind = vmap.level_for(face, mi.Point3d(si.p), dp_dx, dp_dy, si.n).numpy()
    assert np.all(blind[drop] < want[drop]) and np.array_equal(blind[on & ~drop],
                                                               want[on & ~drop])


@pytest.mark.parametrize("method", ["hard", "pcf"])
def test_a_nested_render_reads_the_levels_a_plain_render_reads(method):
    """Mitsuba's ``aov`` calls our ``sample()`` in its own render, with no film pixel:
    its first pass marked without pixels (no probe: the biases' level kept wherever the
    biases ask for it) and its lookups read no pixel's decision, while a plain render's
    read their pixel's. Its film's colour differed from the plain image on the posts
    under a point light in 1 (``hard``) and 93 (``pcf``) of 4096 pixels. A nested
    ``sample()`` whose sensor is known now finds its film pixel as a plain render does
    (the pinhole projection of its hit) and reads the same marks: the images are
    bit-identical."""
    scene = posts_scene(POSTS_LIGHTS["point"])
    plain = np.asarray(mi.render(scene, integrator=shadowmap(method=method), spp=4, seed=1))
    inner = shadowmap(method=method)
    nested = mi.load_dict({"type": "aov", "aovs": "dd:depth", "inner": inner})
    mi.render(scene, integrator=nested, spp=4, seed=1)
    film = np.asarray(scene.sensors()[0].film().bitmap())[..., :3]
    print(f"pixels differing: {np.sum(np.any(film != plain[..., :3], axis=-1))}")
    np.testing.assert_array_equal(film, plain[..., :3])


def test_the_biases_level_is_computed_where_a_pixel_keeps_it_only():
    """A lookup computes the biases' level (:meth:`VirtualShadowMap._levels`) in a
    conditional that only vector packets with an active lane whose pixel keeps it enter:
    0.1-0.4 % of the pixels of the repository's scenes, a packet of 16 lanes being one
    pixel's samples at 16 spp. The levels of the active lanes are the same: the biases'
    where ``keep``, else the footprint's (an inactive lane's level is never read). Every
    lane of every packet computed it before, and kept it for 0.1 %."""
    scene, integ, vmap, sensor, (si, dp_dx, dp_dy, valid), pixel = _posts_point_hits()
    p64 = mi.Point3d(si.p)
    face = vmap.view.project_f64(p64)[0]
    keep = vmap.keeps(pixel, si.shape, valid)
    biased, _, footprint = vmap._levels(face, p64, dp_dx, dp_dy, si.n, probe=True)[:3]
    active = valid & (dr.arange(mi.UInt32, dr.width(valid)) % 3 != 0)
    got = vmap._levels(face, p64, dp_dx, dp_dy, si.n, keep=keep, active=active)[0]
    on, k = active.numpy(), keep.numpy()
    b, f = biased.numpy(), footprint.numpy()
    print(f"{on.sum()} active lanes, {(on & k).sum()} keep, "
          f"{(on & k & (b != f)).sum()} of them finer")
    assert (on & k & (b != f)).sum() > 100 and (on & ~k & (b != f)).sum() > 100
    np.testing.assert_array_equal(got.numpy()[on], np.where(k, b, f)[on])
    # the render's kernel has the conditional
    history = dr.flag(dr.JitFlag.KernelHistory)
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        dr.kernel_history()
        vis_of(scene, integ, spp=1)
        irs = [str(getattr(k["ir"], "getvalue", lambda: k["ir"])())
               for k in dr.kernel_history() if k["type"] == dr.KernelType.JIT]
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, history)
    assert any("virtual map: the receiver biases' level" in ir for ir in irs)


@pytest.mark.parametrize("method", ["hard", "pcf"])
def test_an_unseen_world_builds_at_most_8_texels_a_pixel(method):
    """Issue 11: at most 8 texels built per film pixel per light in the first frame at a
    256^2 film, on scenes not in the repository: ``random_large_world`` seed 5 (the
    worst of seeds 0-7) built 10.7 (``hard``) and 17.3 (``pcf``) with the biases' level
    kept wherever it applies, 9.2 and 14.9 with the probe counting a hit on the
    receiver's own shape behind it (the far sides of thin posts the sun grazes), 3.5 and
    4.9 now; misclassified 0.18 / 0.22 % before, 0.18 / 0.19 % now (``raytraced``'s own
    noise 0.57 %)."""
    from mi_shadowmap.scenes import random_large_world
    d = random_large_world(5, width=256, spp=16)
    ref = vis_of(mi.load_dict(d), shadowmap(method="raytraced"), spp=16, seed=0)
    integ = shadowmap(method=method)
    vis = vis_of(mi.load_dict(d), integ, spp=16, seed=0)
    per_pixel = integ.stats["texels_built"] / 256 ** 2
    mis = misclassified(vis, ref)
    print(f"{method}: {per_pixel:.2f} texels a pixel, misclassified {mis:.3%}")
    assert per_pixel <= 8.0
    assert mis <= 0.003


def ripple_scene(width: int = 64):
    """A ground of ridges 0.4 apart along x (facets 9 degrees steep, a triangle mesh) under
    a sun 12 degrees high from +x, seen from above at an angle: the facets facing away
    from the sun are lit at 3 degrees (their receiver biases capped), nothing is
    shadowed (the sun is higher than any facet is steep), and in every valley the
    tangent plane of a grazed facet runs under the facet before it."""
    n, period, slope, elev = 80, 0.4, math.radians(9.0), math.radians(12.0)
    xs = np.arange(n + 1) * period / 2 - n * period / 4
    ys = np.where(np.arange(n + 1) % 2 == 0, 0.0, period / 2 * math.tan(slope))
    v = np.array([[x, y, z] for z in (-10.0, 10.0) for x, y in zip(xs, ys)], np.float32)
    f = np.array([t for i in range(n) for t in ([i, n + 1 + i, i + 1],
                                                [i + 1, n + 1 + i, n + 2 + i])], np.uint32)
    mesh = mi.Mesh("ripples", len(v), len(f))
    params = mi.traverse(mesh)
    params["vertex_positions"] = mi.Float(v.ravel())
    params["faces"] = mi.UInt32(f.ravel())
    params.update()
    return mi.load_dict({
        "type": "scene",
        "sensor": {"type": "perspective", "fov": 40,
                   "to_world": T().look_at(origin=[0, 3, 6], target=[0, 0, 0], up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": width, "height": width,
                            "rfilter": {"type": "box"}}},
        "ground": mesh,
        "sun": {"type": "directional", "irradiance": {"type": "rgb", "value": 3.0},
                "direction": [-math.cos(elev), -math.sin(elev), 0.0]}})


def test_a_footprint_corner_under_the_receivers_own_surface_finds_no_edge(monkeypatch):
    """:func:`~mi_shadowmap.virtual.marks.probe_keeps`' corner probes leave the receiver's
    tangent plane; where the surface bends up within the footprint (a valley of a mesh)
    the corner lies under it, and its shadow ray hits the surface right there: an edge
    found where there is none. A corner whose probe disagrees with the centre's is
    probed again from the point the camera sees through it, on the receiver's own shape
    (:func:`~mi_shadowmap.virtual.marks._surface_corner_differs`). On the ridges of
    :func:`ripple_scene`, where nothing is shadowed, 184 of the 412 capped pixel centres
    kept the biases' level from the plane's corners (672 pixels read it, with the
    uncapped pixels beside them), none now; ``hard`` builds 26 % fewer texels (57,536 ->
    42,688 at 64^2) for the same image. ``random_terrain_world`` seed 22 at 256^2:
    4008 of its 4723 kept centres were such corners (the hit 0.05 footprints from the
    corner, median), 10.16 -> 6.64 texels a pixel (``hard``)."""
    scene = ripple_scene()
    ref = reference("ripples", scene)
    texels, kept = [], []
    for again in (True, False):
        if not again:
            monkeypatch.setattr(marks, "_surface_corner_differs",
                                lambda scene, view, c, n, differs, *a: differs, raising=False)
        integ = shadowmap(method="hard", virtual=True, cache_maps=False)
        vis = vis_of(scene, integ)
        vmap = integ.maps[0]
        words = vmap.keep[0].numpy()
        kept.append(int(np.sum((words & virtual.lookup.KEEP_CENTRE) != 0)))
        texels.append(integ.stats["texels_built"])
        # (the far edge of the ground, rows 5-7, is partly covered)
        assert misclassified(vis[8:], ref[8:]) == 0.0
        if again:
            vis_again = vis
    print(f"kept centres {kept}, texels {texels}")
    assert np.all(ref[8:] >= 0.99)      # nothing shadowed below the far edge
    assert kept[0] == 0 and kept[1] > 100
    assert texels[0] < 0.8 * texels[1]
    np.testing.assert_array_equal(vis_again, vis)


def test_terrain_22_builds_at_most_8_texels_a_pixel():
    """Issue 11's 8 texels per film pixel at 256^2 on ``random_terrain_world`` seed 22 (a
    hill's view of rippled terrain under a sun 8-40 degrees high), outside
    ``bench_unseen.py``'s seeds: ``hard`` built 10.16, the footprints' plane corners
    under the terrain's own facets keeping the biases' level on 4008 pixels
    (:func:`test_a_footprint_corner_under_the_receivers_own_surface_finds_no_edge`);
    6.64 now, misclassified at 128^2 1.07 -> 1.06 % (``raytraced`` with another seed
    1.25 %)."""
    from mi_shadowmap.scenes import random_terrain_world
    integ = shadowmap(method="hard")
    vis_of(mi.load_dict(random_terrain_world(22, width=256, spp=16)), integ, spp=16, seed=0)
    per_pixel = integ.stats["texels_built"] / 256 ** 2
    print(f"{per_pixel:.2f} texels a pixel")
    assert per_pixel <= 8.0


def test_the_probes_see_instanced_occluders():
    """:func:`~mi_shadowmap.virtual.marks.probe_distance` with a receiver's ``own`` shape
    (every per-pixel probe of a render passes one, null where the light is in front of the
    receiver): a preliminary intersection with an ``instance`` has a null shape, which
    ``pi.shape != own`` counted as the receiver's own and dropped, so the probes were blind
    to instanced occluders and their pixels dropped the biases' level under them. The
    posts of :func:`posts_scene` under the point light as instances of one cube keep the
    biases' level on about as many pixels as the posts as cubes (64^2: 291 pixels read
    it with cubes, 293 with instances; 3 with instances before)."""
    kept = []
    for instanced in (False, True):
        integ = shadowmap(method="hard", virtual=True, cache_maps=False)
        s = posts_scene(POSTS_LIGHTS["point"], instanced=instanced)
        vis_of(s, integ, spp=1)
        words = integ.maps[0].keep[0].numpy()
        kept.append(int(np.sum((words & virtual.lookup.KEEP_CENTRE) != 0)))
        if instanced:    # a probe from under a post finds it, the light in front of the floor
            view = integ.maps[0].view
            p = mi.Point3f(1.5, 0.0, -0.6)
            d = marks.probe_distance(s, view, p, mi.Vector3f(0, 1, 0), mi.Bool(True),
                                     dr.zeros(mi.ShapePtr, 1))
            seen = bool(np.isfinite(d.numpy()).all())
    print(f"pixels reading the biases' level: cubes {kept[0]}, instances {kept[1]}")
    assert kept[0] > 100 and abs(kept[1] - kept[0]) <= 0.05 * kept[0]
    assert seen


def test_the_mark_pass_dedupes_one_block_list_per_light(monkeypatch):
    """The mark pass folds its blocks' shapes into their keys (:func:`marks.mark_blocks`
    with :func:`marks.shape_bits`): one candidate list a light for ``hard``, where the
    biases' spread made 81 (9 x 9 shapes; 4 without the biases), and the same marked tiles
    as the lists of every shape (the boxed light's floor, most of its points capped)."""
    groups = []
    real = planner.dedupe_many

    def spy(gs, *args, **kwargs):
        groups.append(len(gs))
        return real(gs, *args, **kwargs)

    monkeypatch.setattr(planner, "dedupe_many", spy)
    scene = boxed_light_scene()
    marked = []
    for fold in (True, False):
        if not fold:
            monkeypatch.setattr(planner, "shape_bits", lambda layout, per_axis: None)
        integ = shadowmap(method="hard", virtual=True, cache_maps=False)
        vis_of(scene, integ, spp=1)
        marked.append(np.asarray(integ.maps[0].store.last_mark[1]))
    assert groups == [1, 81]
    assert len(marked[0]) > 100 and np.array_equal(marked[0], marked[1])


@pytest.mark.parametrize("method", ["hard", "pcf", "mdsm", "vsm", "evsm", "msm"])
def test_large_world_at_defaults(method):
    """Issue 11: <= 1 % misclassified at defaults (virtual maps; full maps: 3.3 % at
    256^2). Nothing but the method is given. The prefiltered methods hold it through
    their per-texel variance floor on virtual maps (with the scene-relative one 2.8-3.0 %
    for vsm and evsm)."""
    scene = mi.load_file(str(SCENES / "large_world.xml"), width=128, height=128)
    ref = reference("large_world", scene, spp=16)
    integ = shadowmap(method=method)
    mis = misclassified(vis_of(scene, integ, spp=16), ref)
    print(f"large_world {method}: {mis:.3%}, {integ.stats['texels_built'] / 128**2:.1f} "
          "texels per pixel")
    # the issue's 1 % is for hard and pcf; mdsm lights a band about a texel wide on an
    # edge's shadow side (measured 1.20 % here, 0.69 % at 256^2; full maps 3.4 %)
    assert mis <= (0.015 if method == "mdsm" else 0.01)


@pytest.mark.parametrize("distance", ["1e5", "1e6"])
@pytest.mark.parametrize("method", ["hard", "pcf", "mdsm", "vsm", "evsm", "msm"])
def test_far_point_light_at_defaults(method, distance):
    """Issue 11: <= 0.3 % misclassified with the point light 1e5 and 1e6 away (the
    prefiltered methods: 3.1 % with a scene-relative variance floor or full maps)."""
    intensity = {"1e5": "3e10", "1e6": "3e12"}[distance]
    scene = mi.load_file(str(SCENES / "far_point.xml"), width=128, height=128,
                         light_distance=distance, light_intensity=intensity)
    ref = reference(("far_point", distance), scene, spp=16)
    integ = shadowmap(method=method)     # defaults: nothing but the method
    mis = misclassified(vis_of(scene, integ, spp=16), ref)
    print(f"far_point {distance} {method}: {mis:.3%}")
    # the issue's 0.3 % is for hard and pcf; mdsm's lit band and msm's moment bias add
    # a little (measured mdsm 0.50 / 0.40 %, msm 0.24 / 0.37 %; full maps 3.1 %)
    assert mis <= (0.006 if method in ("mdsm", "msm") else 0.003)


@pytest.mark.parametrize("distance", ["1e7", "1e8", "1e9", "1e12"])
@pytest.mark.parametrize("method", ["hard", "pcf", "second_depth", "pcss", "msm"])
def test_far_point_light_beyond_the_issue(method, distance):
    """A point light 1e7 to 1e12 away keeps its shadows.

    * The pages hold depths measured from near the scene (``VirtualLayout.t0``):
      measured from the light, a depth 1e8 away rounds to 8 units in float32, and
      receivers lowered by their roundoff (0.24 units at 1e6, 24 at 1e8) lost every
      shadow of this 10-unit scene (before: 2.3 % false lit at 1e7, 3.1 % at 1e8, all of
      its shadow).
    * Beyond about 500 box diagonals the layout's view is one face aimed at the box
      (``box_view``): a cube face's finest level (``MAX_VIRTUAL_RES``) has 1.9-unit
      texels at 1e9 (before: 3.0 % false lit at 1e9 and 1e12)."""
    intensity = {"1e7": "3e14", "1e8": "3e16", "1e9": "3e18", "1e12": "3e24"}[distance]
    scene = mi.load_file(str(SCENES / "far_point.xml"), width=128, height=128,
                         light_distance=distance, light_intensity=intensity)
    ref = reference(("far_point", distance), scene, spp=16)
    vis = vis_of(scene, shadowmap(method=method), spp=16)
    mis = misclassified(vis, ref)
    false_lit = float(np.mean((vis >= 0.5) & (ref < 0.5)))
    print(f"far_point {distance} {method}: {mis:.3%} (false lit {false_lit:.3%})")
    assert mis <= 0.006 and false_lit <= 0.005


def test_a_far_light_gets_one_face_aimed_at_the_scene():
    """At 1e5 and 1e9 the layout's view is a perspective face whose frustum holds the
    scene's box (its corners project inside), ``SCENE_TEXELS`` to 16 times that across it
    (the face's axis is float32: 6e-8 rad off the box's centre at 1e9 is 60 units, which
    the frustum covers: 8 times there), and a first frame builds at most 8 texels per pixel;
    at 10 units (a light next to the scene) the cube stays."""
    from mi_shadowmap.light_views import make_light_view
    from mi_shadowmap.light_views.base import scene_bounds
    for distance, cube in (("1e9", False), ("1e5", False), ("10", True)):
        intensity = f"{3 * float(distance) ** 2:g}"
        scene = mi.load_file(str(SCENES / "far_point.xml"), width=64, height=64,
                             light_distance=distance, light_intensity=intensity)
        view = make_light_view(scene.emitters()[0], scene, 0)
        lay = virtual.layout_for(view, scene, parse_options(mi.Properties()))
        assert (lay.view.projection == "cube") == cube, distance
        if cube:
            continue
        assert lay.view.n_faces == 1
        assert virtual.SCENE_TEXELS <= lay.res0 <= 16 * virtual.SCENE_TEXELS
        lo, hi = scene_bounds(scene)
        corners = np.array([[(lo, hi)[k >> a & 1][a] for a in range(3)] for k in range(8)])
        p = mi.Point3d(*(mi.Float64(corners[:, a].tolist()) for a in range(3)))
        _, uv, _, inside = lay.view.project_f64(p)
        assert np.all(inside.numpy()), distance
        assert np.all((uv.x.numpy() > 0.01) & (uv.x.numpy() < 0.99)), distance
        scene = mi.load_file(str(SCENES / "far_point.xml"), width=128, height=128,
                             light_distance=distance, light_intensity=intensity)
        integ = shadowmap(method="hard")
        vis_of(scene, integ, spp=1)
        print(distance, integ.stats["texels_built"] / 128 ** 2, "texels per pixel")
        assert integ.stats["texels_built"] <= 8 * 128 * 128, integ.stats["texels_built"]


def _yard(light: dict):
    """A y-up yard 120 wide of posts, crates and a roof (not a repository scene)."""
    d = {"type": "scene",
         "ground": {"type": "rectangle", "to_world": T().rotate([1, 0, 0], -90).scale(60)},
         "light": light,
         "cam": {"type": "perspective", "fov": 50,
                 "to_world": T().look_at([0, 6, -30], [0, 0, 0], [0, 1, 0]),
                 "film": {"type": "hdrfilm", "width": 128, "height": 128,
                          "rfilter": {"type": "box"}}}}
    rng = np.random.default_rng(3)
    for i in range(14):
        x, z = rng.uniform(-15, 15, 2)
        h = rng.uniform(0.5, 4)
        d[f"post{i}"] = {"type": "cube",
                         "to_world": T().translate([x, h / 2, z]).scale([0.15, h / 2, 0.15])}
    for i in range(6):
        x, z = rng.uniform(-12, 12, 2)
        d[f"crate{i}"] = {"type": "cube", "to_world": T().translate([x, 0.5, z])
                          .rotate([0, 1, 0], rng.uniform(0, 90)).scale([1, 0.5, 0.7])}
    d["roof"] = {"type": "cube", "to_world": T().translate([4, 2.5, -5]).scale([3, 0.05, 2])}
    return mi.load_dict(d)


def test_a_far_low_point_light_does_as_well_as_a_sun_from_there():
    """A point light 1e5 away, 5 degrees above a yard, is nearly a sun: its face aimed at
    the scene is a rectangle fitted to the scene as a sun's orthographic map is
    (``perspective._aimed_rectangle``). The square face it had spent as many texels
    along the light's direction as across it, whose texels on the ground were then
    1 / sin(5 deg) = 11x as long as wide: 1.50 % misclassified against 1.07 % for the
    sun (1.01 % now; ``hard`` against the same samples of ``raytraced``)."""
    from mi_shadowmap.light_views import make_light_view
    e, a = math.radians(5.0), math.radians(30.0)
    to_light = np.array([math.cos(e) * math.cos(a), math.sin(e), math.cos(e) * math.sin(a)])
    out = {}
    for kind, light in (("point", {"type": "point", "position": (1e5 * to_light).tolist(),
                                   "intensity": 1e10}),
                        ("sun", {"type": "directional", "direction": (-to_light).tolist(),
                                 "irradiance": 1.0})):
        scene = _yard(light)
        ref = vis_of(scene, shadowmap(method="raytraced"), spp=16, seed=0)
        out[kind] = misclassified(vis_of(scene, shadowmap(method="hard"), spp=16, seed=0), ref)
        if kind == "point":
            view = virtual.layout_for(make_light_view(scene.emitters()[0], scene, 0), scene,
                                      parse_options(mi.Properties())).view
            assert view.tan_half_y is not None and view.tan_half_y < 0.3 * view.tan_half
    print(out)
    assert out["point"] <= out["sun"] + 0.001


def far_area_light_scene(distance: float, size: int = 64):
    """far_point.xml's layout (a 10 x 10 ground, a box, a sphere) lit by a square area
    light ``distance`` away and 0.04 ``distance`` wide, facing the scene (the same
    penumbrae at any distance)."""
    d = np.array([-0.4, 0.7, -0.55]) / np.linalg.norm([-0.4, 0.7, -0.55])
    T = mi.ScalarTransform4f
    return mi.load_dict({
        "type": "scene",
        "sensor": {"type": "perspective", "fov": 45,
                   "to_world": T().look_at([3, 8.5, 11], [0.2, 0, 0.3], [0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": size, "height": size,
                            "rfilter": {"type": "box"}}},
        "ground": {"type": "rectangle", "to_world": T().rotate([1, 0, 0], -90).scale(5)},
        "box": {"type": "cube", "to_world": T().translate([0, 1, 0]).scale([0.6, 1, 0.6])},
        "ball": {"type": "sphere", "center": [2, 0.5, 1.5], "radius": 0.5},
        "light": {"type": "rectangle",
                  "to_world": T().look_at((d * distance).tolist(), [0, 0, 0], [0, 1, 0])
                  .scale(0.04 * distance),
                  "emitter": {"type": "area", "radiance": 1.0}}})


@pytest.mark.parametrize("method", ["hard", "pcss"])
def test_far_area_light_keeps_its_shadows(method):
    """A large area light 1e6 away: the scene it shadows is every shape but its own, so
    the pages' depths start near the scene (``VirtualLayout.t0``), not at the light
    (its own shape in the box put it "inside" the scene: 2.2 % misclassified, every
    shadow lost to the float32 roundoff of depths near 1e6; now 0.15-0.17 %)."""
    scene = far_area_light_scene(1e6)
    ref = vis_of(scene, shadowmap(method="raytraced", shadow_rays=16), spp=16)
    vis = vis_of(scene, shadowmap(method=method), spp=16)
    mis = misclassified(vis, ref)
    rmse = float(np.sqrt(np.mean((vis - ref) ** 2)))
    print(f"far area light {method}: {mis:.3%}, RMSE {rmse:.4f}")
    assert mis <= 0.006 and rmse <= 0.05


# ------------------------------------------------------------ cache and moves
def _jit_hashes():
    return {k["hash"] for k in dr.kernel_history() if k["type"] == dr.KernelType.JIT}


def _moves(scene, integ, n, each=None) -> list:
    """After one render, ``n`` successive small moves and turns of ``scene``'s camera,
    each followed by a render of ``integ``; returns the JIT kernels each move compiled
    that no earlier render had (``(size, operations)``) and calls ``each()`` after each
    move's render. (Mitsuba's own sensor update runs a one-lane kernel whose rotation
    values are literals: new each move, with any integrator, ``direct`` included; it
    runs before the render and is not counted.)"""
    params = mi.traverse(scene)
    key = next(k for k in params.keys() if k.endswith("to_world")
               and isinstance(params.properties[k][2], mi.Sensor))
    start = type(params[key])(params[key])
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        dr.kernel_history()
        vis_of(scene, integ, spp=2)
        seen = _jit_hashes()
        compiled = []
        for j in range(n):
            params[key] = start @ T().translate([0.05 * (j + 1), 0, 0]) \
                @ T().rotate([0, 1, 0], 1.0 * (j + 1))
            params.update()
            dr.kernel_history()
            vis_of(scene, integ, spp=2)
            jit = [k for k in dr.kernel_history() if k["type"] == dr.KernelType.JIT]
            new = {k["hash"]: (k["size"], k["operation_count"]) for k in jit
                   if k["hash"] not in seen}
            print("new kernels (size, operations):", list(new.values()))
            compiled.append(len(new))
            seen |= set(new)
            if each is not None:
                each()
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    return compiled


def test_camera_move_reuses_pages_and_compiles_nothing():
    """Small camera moves build few pages and compile no kernel. (Mitsuba's sensor
    holds its first ``to_world`` as a kernel literal; the first ``params.update()``
    turns it into a variable, so the first move recompiles for full maps too: the
    check is on the moves after it.)"""
    virtual.PAGE_CACHE.clear()
    scene = mi.load_dict(default_scene(width=64, height=64, spp=2))
    integ = shadowmap(method="pcf", virtual=True)
    params = mi.traverse(scene)
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        dr.kernel_history()
        vis_of(scene, integ, spp=2)
        first = integ.stats["texels_built"]
        seen = _jit_hashes()
        built, reused, compiled = [], [], []
        for x in (0.25, 0.3, 0.35):
            params["sensor.to_world"] = T().look_at(origin=[x, 3.45, 4.85],
                                                    target=[0.3, 0.25, 0.0], up=[0, 1, 0])
            params.update()
            vis_of(scene, integ, spp=2)
            hashes = _jit_hashes()
            compiled.append(len(hashes - seen))
            seen |= hashes
            built.append(integ.stats["texels_built"])
            reused.append(integ.stats["pages_reused"])
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    print(f"first frame {first} texels; moves: built {built}, pages reused {reused}, "
          f"kernels compiled {compiled}")
    assert all(b <= 0.25 * first for b in built)
    assert all(r > 0 for r in reused)
    assert compiled[1:] == [0, 0], "moving the camera compiled a new kernel"


def test_camera_moves_in_a_large_world_compile_nothing():
    """Six successive moves and turns under a low sun (pages built and reused at many
    levels, the page table growing): after the first move, every render reuses the
    kernels already traced. (A page table read with packet gathers once made the render
    kernel depend on the table's size.)"""
    virtual.PAGE_CACHE.clear()
    scene = mi.load_file(str(SCENES / "large_world.xml"), width=128, height=128)
    integ = shadowmap(method="hard")
    built = []
    compiled = _moves(scene, integ, 6, lambda: built.append(integ.stats["pages_built"]))
    print(f"kernels compiled per move {compiled}, pages built {built}")
    assert sum(built) > 0
    assert compiled[1:] == [0] * 5, "moving the camera compiled a new kernel"


def test_a_moved_cameras_frame_is_the_frame_rendered_there_afresh():
    """A camera move reuses pages whose other tiles earlier frames cast; a kernel tap
    in a tile this frame did not mark reads the coarsest level's texel over it, as a
    new page holds there (:meth:`BoundVirtualMap._index`), not the depths cast for
    another camera. Reading those, a moved frame differed from the frame rendered afresh
    at the moved camera (64^2, 4 spp; moved 0.1 and turned 2 degrees): ``pcss`` on
    contact_hardening in 45 pixels, ``pcf`` on cbox_area and ``bilinear`` on
    spot_sphere_box in 1; now bit-identical (and every first frame the same as before,
    6 scenes x 5 methods)."""
    from mi_shadowmap.harness import load_scene
    virtual.PAGE_CACHE.clear()
    scene = load_scene(str(SCENES / "contact_hardening.xml"), width="64", height="64")
    integ = shadowmap(method="pcss")
    vis_of(scene, integ, spp=4, seed=0)
    params = mi.traverse(scene)
    key = next(k for k in params.keys() if k.endswith("to_world")
               and isinstance(params.properties[k][2], mi.Sensor))
    start = T(params[key].matrix.numpy()[..., 0])
    params[key] = start @ T().translate([0.1, 0.0, 0.0]) @ T().rotate([0, 1, 0], 2.0)
    params.update()
    moved = vis_of(scene, integ, spp=4, seed=0)
    assert integ.stats["pages_reused"] > 0
    virtual.PAGE_CACHE.clear()
    fresh = vis_of(scene, shadowmap(method="pcss", cache_maps=False), spp=4, seed=0)
    print(f"{np.sum(moved != fresh)} pixels differ")
    assert np.array_equal(moved, fresh)



def test_a_camera_moved_and_put_back_renders_hard_as_afresh():
    """``hard``'s lookups whose page is missing at their level run again walked; a walked
    read beside its point's tile reads the coarsest level's texel there when this frame
    did not mark that tile, as a fresh pool holds it. Reading what an earlier pose cast
    there, large_world (64^2, 4 spp) moved 0.3 and put back differed from a fresh render
    in 1 pixel (visibility 0.5 against 0.25; review E of the forty-third session)."""
    from mi_shadowmap.harness import load_scene
    from mi_shadowmap.map_manager import clear_caches
    scene = load_scene(str(SCENES / "large_world.xml"), width="64", height="64")
    integ = shadowmap(method="hard")
    params = mi.traverse(scene)
    key = next(k for k in params.keys() if k.endswith("to_world")
               and isinstance(params.properties[k][2], mi.Sensor))
    clear_caches()
    vis_of(scene, integ, spp=4, seed=0)
    for dx in (0.3, -0.3):
        params[key] = T().translate([dx, 0.0, 0.0]) @ T(params[key].matrix.numpy()[..., 0])
        params.update()
        again = vis_of(scene, integ, spp=4, seed=0)
    assert integ.stats["pages_reused"] > 0
    clear_caches()
    fresh = vis_of(scene, shadowmap(method="hard"), spp=4, seed=0)
    print(f"{np.sum(again != fresh)} pixels differ")
    assert np.array_equal(again, fresh)

def test_geometry_change_drops_the_pages():
    virtual.PAGE_CACHE.clear()
    scene = mi.load_dict(default_scene(width=32, height=32, spp=1))
    integ = shadowmap(method="hard", virtual=True)
    vis_of(scene, integ, spp=1)
    assert integ.stats["pages_reused"] == 0
    vis_of(scene, integ, spp=1)
    assert integ.stats["pages_built"] == 0 and integ.stats["texels_built"] == 0
    params = mi.traverse(scene)
    key = next(k for k in params.keys() if k.startswith("box") and "vertex_positions" in k)
    v = dr.unravel(mi.Point3f, params[key])
    params[key] = dr.ravel(v + mi.Vector3f(0.0, 0.3, 0.0))
    params.update()
    vis = vis_of(scene, integ, spp=1)
    assert integ.stats["pages_reused"] == 0 and integ.stats["pages_built"] > 0
    ref = vis_of(scene, shadowmap(method="raytraced"), spp=1)
    assert misclassified(vis, ref) <= 0.02


def test_still_camera_reuses_its_marks_and_a_moved_one_marks_again(monkeypatch):
    """A re-render with the same camera skips the mark pass and every page step (the
    same image); a camera move marks again, and so does moving it back through new
    variables (a camera state compares JIT variables, not values): the image is then
    the first one again."""
    virtual.PAGE_CACHE.clear()
    traced = []
    real = virtual.camera_hits
    monkeypatch.setattr(planner, "camera_hits", lambda *a, **k: traced.append(1) or real(*a, **k))
    scene = mi.load_dict(default_scene(width=32, height=32, spp=1))
    integ = shadowmap(method="pcf", virtual=True)
    first = vis_of(scene, integ, spp=1)
    assert len(traced) == 1
    assert np.array_equal(vis_of(scene, integ, spp=1), first)
    assert len(traced) == 1 and integ.stats["pages_built"] == 0
    assert integ.stats["pages_marked"] == integ.stats["pages_reused"] > 0
    params = mi.traverse(scene)
    start = T(params["sensor.to_world"].matrix.numpy()[..., 0])
    params["sensor.to_world"] = T().translate([0.3, 0.0, 0.0]) @ start
    params.update()
    moved = vis_of(scene, integ, spp=1)
    assert len(traced) == 2 and not np.array_equal(moved, first)
    params["sensor.to_world"] = start
    params.update()
    assert np.array_equal(vis_of(scene, integ, spp=1), first)
    assert len(traced) == 3


def test_methods_rendered_in_turn_keep_their_own_marks(monkeypatch):
    """``hard`` and ``pcf`` (different margins) share a light's store: rendered in turn
    with a still camera, each marks once and then recalls its own mark and page table
    (each re-marked every frame before, and rebuilt the table), and every image equals
    the one its first frame gave; a camera
    move marks again for each, and moving back through new variables too."""
    virtual.PAGE_CACHE.clear()
    traced = []
    real = virtual.camera_hits
    monkeypatch.setattr(planner, "camera_hits", lambda *a, **k: traced.append(1) or real(*a, **k))
    scene = mi.load_dict(default_scene(width=32, height=32, spp=1))
    integs = {m: shadowmap(method=m, virtual=True) for m in ("hard", "pcf", "pcss")}
    first = {m: vis_of(scene, i, spp=1) for m, i in integs.items()}
    stores = {id(i.maps[0].store) for i in integs.values()}
    n = len(traced)         # a mark pass per distinct mark (pcss may share pcf's)
    assert n >= 2 and len(stores) < 3          # at least two of them share a store
    dense = {}
    for r in range(3):
        for m, i in integs.items():
            assert np.array_equal(vis_of(scene, i, spp=1), first[m])
            assert i.stats["pages_built"] == 0
            if r:           # its page table kept (the first round's: no page built since)
                assert i.maps[0].dense is dense[m]
            dense[m] = i.maps[0].dense
    assert len(traced) == n
    params = mi.traverse(scene)
    start = T(params["sensor.to_world"].matrix.numpy()[..., 0])
    params["sensor.to_world"] = T().translate([0.3, 0.0, 0.0]) @ start
    params.update()
    for i in integs.values():
        vis_of(scene, i, spp=1)
    assert len(traced) == 2 * n
    params["sensor.to_world"] = start
    params.update()
    for m, i in integs.items():
        assert np.array_equal(vis_of(scene, i, spp=1), first[m])
    assert len(traced) == 3 * n
    for m, i in integs.items():          # the moved-back camera's marks, recalled
        assert np.array_equal(vis_of(scene, i, spp=1), first[m])
    assert len(traced) == 3 * n


def test_the_degraded_maps_warning_points_at_the_first_pass_caller():
    """The one warning a render about degraded maps (``memory_budget`` too small for the
    marked pages) is raised in the last of prepare_virtual's steps
    (``planner._FirstPass``), below it; its ``stacklevel`` still names the line of
    ``map_manager.prepare_maps`` that asks for the virtual maps, as when prepare_virtual raised it
    itself, not the planner's own lines (which a ``-W`` filter or a user's log would
    show instead)."""
    virtual.PAGE_CACHE.clear()
    scene = mi.load_dict(default_scene(width=32, height=32, spp=1, light="point"))
    integ = shadowmap(method="hard", virtual=True, memory_budget=0.06)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always", RuntimeWarning)
        vis_of(scene, integ, spp=1)
    found = [w for w in caught if "replaced by coarser" in str(w.message)]
    assert len(found) == 1, [str(w.message) for w in caught]
    line = linecache.getline(found[0].filename, found[0].lineno)
    assert found[0].filename.endswith("map_manager.py"), found[0].filename
    assert "_prepare_virtual(" in line, line      # prepare_maps' call, not the planner's


def test_recalled_marks_give_a_fresh_integrators_images():
    """Integrators sharing a point light's store whose marks differ by ``lod_bias`` alone
    (a key of the store's remembered marks, :meth:`PageStore.recall_mark`), one of them
    degraded by a small ``memory_budget`` (the mark is the same, the pages kept fewer),
    rendered in turn: with the light dark in between (its map keeps no marked page) and
    lit again through a new variable, and after a camera move, each image and page table
    (its pages and tiles) equals the one a fresh integrator renders of the same state
    (page cache emptied)."""
    virtual.PAGE_CACHE.clear()
    scene = mi.load_dict(default_scene(width=32, height=32, spp=1, light="point"))
    kinds = {"hard": dict(method="hard"), "coarse": dict(method="hard", lod_bias=1.5),
             "tight": dict(method="hard", memory_budget=0.06),
             "pcf": dict(method="pcf")}
    kinds = {k: dict(kw, virtual=True) for k, kw in kinds.items()}
    integs = {k: shadowmap(**kw) for k, kw in kinds.items()}
    degraded = []

    def seen(i, img):
        """The image and the page table's pages and tiles (not their slots)."""
        m = i.maps[0]
        return [img] + [np.array(a) for a in (m.header, m.dense_tiles, m.face_near)]

    def frame():
        out = {}
        for k, i in integs.items():
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always", RuntimeWarning)
                out[k] = seen(i, vis_of(scene, i, spp=1))
            degraded.extend(k for w in caught if "replaced by coarser" in str(w.message))
        return out

    def fresh(k):
        virtual.PAGE_CACHE.clear()          # each alone: no other's pages or marks
        i = shadowmap(**kinds[k])
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            return seen(i, vis_of(scene, i, spp=1))

    def same(a, b):
        return all(np.array_equal(x, y) for x, y in zip(a, b))

    first = frame()
    assert len({id(i.maps[0].store) for i in integs.values()}) == 1    # one shared store
    assert degraded == ["tight"]
    assert not same(first["hard"], first["coarse"])
    params = mi.traverse(scene)
    lit = [float(v[0]) for v in np.array(params["point.intensity.value"])]
    params["point.intensity.value"] = mi.Color3f(0.0)
    params.update()
    frame()
    params["point.intensity.value"] = mi.Color3f(*lit)
    params.update()
    again = frame()
    frame()
    for k in kinds:
        assert same(again[k], first[k]), k
        assert same(first[k], fresh(k)), k
    virtual.PAGE_CACHE.clear()
    integs = {k: shadowmap(**kw) for k, kw in kinds.items()}
    frame()
    params["sensor.to_world"] = (T().translate([0.2, 0.0, 0.1])
                                 @ T(params["sensor.to_world"].matrix.numpy()[..., 0]))
    params.update()
    moved = frame()
    moved_again = frame()
    for k in kinds:
        want = fresh(k)
        assert same(moved[k], want), k
        assert same(moved_again[k], want), k


def test_light_views_follow_an_emitter_edit():
    """The integrator keeps its light views while the scene's state is unchanged; a
    light moved through ``params.update()`` gets new views, and its render equals a
    new integrator's."""
    virtual.PAGE_CACHE.clear()
    scene = mi.load_dict(default_scene(width=32, height=32, spp=1))
    integ = shadowmap(method="hard", virtual=True)
    before = vis_of(scene, integ, spp=1)
    views = integ.views
    vis_of(scene, integ, spp=1)
    assert all(a is b for a, b in zip(integ.views, views))
    params = mi.traverse(scene)
    key = next(k for k in params.keys() if k.endswith("to_world") and "spot" in k)
    params[key] = T().translate([0.4, 0.0, 0.2]) @ T(params[key].matrix.numpy()[..., 0])
    params.update()
    after = vis_of(scene, integ, spp=1)
    assert not any(a is b for a, b in zip(integ.views, views))
    assert not np.array_equal(before, after)
    assert np.array_equal(after, vis_of(scene, shadowmap(method="hard", virtual=True),
                                        spp=1))


def test_moving_one_light_keeps_the_other_lights_pages():
    """Many lights: a light moved through ``params.update()`` rebuilds its own pages only
    (the page cache was keyed by the whole scene's state, so every light's pages were
    rebuilt: 4 point lights, 88 of 89 pages built again after moving one); the render
    equals a fresh integrator's, and moving it again and again keeps one store per
    light."""
    virtual.PAGE_CACHE.clear()
    scene_dict = default_scene(width=32, height=32, spp=1)
    scene_dict = {k: v for k, v in scene_dict.items()
                  if not (isinstance(v, dict) and v.get("type") in ("spot", "point"))}
    for k, x in enumerate([-1.5, -0.5, 0.5, 1.5]):
        scene_dict[f"pl{k}"] = {"type": "point", "position": [x, 3.0, 1.0 + 0.3 * k],
                                "intensity": {"type": "rgb", "value": [3.0] * 3}}
    scene = mi.load_dict(scene_dict)
    integ = shadowmap(method="hard", virtual=True)
    mi.render(scene, integrator=integ, spp=1)
    first = integ.stats["pages_built"]
    params = mi.traverse(scene)
    for step in range(3):
        params["pl1.position"] = mi.Point3f(-0.5 + 0.1 * (step + 1), 3.0, 1.3)
        params.update()
        img = np.asarray(mi.render(scene, integrator=integ, spp=1))
        built = integ.stats["pages_built"]
        # the moved light's pages (a quarter or so of the first frame's), not all four
        assert 0 < built < 0.5 * first, (step, built, first)
    fresh = np.asarray(mi.render(scene, integrator=shadowmap(method="hard", virtual=True,
                                                             cache_maps=False), spp=1))
    np.testing.assert_array_equal(img, fresh)
    stores = [k for slot in virtual.PAGE_CACHE._scenes.values() if slot[0] is scene
              for k in slot[2] if k[0] not in ("layout", "view of")]
    assert len(stores) == 4, stores


def _render_counting_kernels(scene, integ, seen: set):
    """Render at 1 spp (with ``dr.JitFlag.KernelHistory`` on): ``(JIT kernels launched,
    of them compiled for the first time: hashes not in seen)``; ``seen`` takes them in.
    Mitsuba's own updates before the render are not counted."""
    dr.kernel_history()
    mi.render(scene, integrator=integ, spp=1)
    jit = [k for k in dr.kernel_history() if k["type"] == dr.KernelType.JIT]
    new = {k["hash"] for k in jit} - seen
    seen.update(k["hash"] for k in jit)
    return len(jit), len(new)


def test_moving_any_set_of_lights_compiles_nothing_new():
    """Lights moved through ``params.update()`` are marked again, the others keep their
    marks: once one light of each kind has moved, moving any other light or set of
    lights compiles no kernel, and the pages built are the moved lights' own. (The stale
    lights were marked in one kernel, so each new set -- two point lights, a point and a
    spot -- compiled its own four mark kernels.)"""
    virtual.PAGE_CACHE.clear()
    scene = many_lights_scene(2, 2)
    params = mi.traverse(scene)
    integ = shadowmap(method="hard", virtual=True)

    def move(*names):
        for name in names:
            if name.startswith("pl"):
                p = params[f"{name}.position"]
                params[f"{name}.position"] = mi.Point3f(p.x[0] + 0.05, p.y[0], p.z[0])
            else:
                key = f"{name}.to_world"
                params[key] = T().translate([0.05, 0, 0]) @ T(params[key].matrix.numpy()[..., 0])
        params.update()
        _, new = _render_counting_kernels(scene, integ, seen)
        built = [m.stats["new"] for m in integ.maps]
        return new, built

    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        dr.kernel_history()
        mi.render(scene, integrator=integ, spp=1)
        seen = {k["hash"] for k in dr.kernel_history() if k["type"] == dr.KernelType.JIT}
        move("pl0")
        move("sp0")                          # each kind's first move may compile
        got = {names: move(*names) for names in
               [("pl1",), ("pl0", "pl1"), ("sp1", "pl0"), ("pl1", "sp0", "sp1")]}
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    print("kernels compiled, pages built per light:", got)
    order = ["pl0", "pl1", "sp0", "sp1"]
    for names, (compiled, built) in got.items():
        assert compiled == 0, f"moving {names} compiled {compiled} kernel(s)"
        assert all((b > 0) == (order[k] in names) for k, b in enumerate(built)), (names, built)


def test_a_camera_move_beside_a_dark_light_marks_in_one_kernel():
    """A camera move marks every light again; with one light dark (intensity 0: no
    marks) the lit ones were marked one light a kernel, as after a light move, so
    every camera move launched a mark kernel and a dedupe round per light (8 lights,
    one dark: 36-41 kernels a move against 11-16 with all lit). Now the move marks
    every light in the one kernel of a lit scene's moves (the dark light's marks are
    dropped): no more kernels than with every light lit, none compiled, and the image
    a fresh integrator's. The moves counted go back to camera positions whose pages are
    cached, so that no move launches page-building kernels (how many depends on which
    lights' marks reach new pages, not on how the lights are marked)."""
    virtual.PAGE_CACHE.clear()
    scene = many_lights_scene(2, 2)
    params = mi.traverse(scene)
    integ = shadowmap(method="hard", virtual=True)

    def move(k):
        params["sensor.to_world"] = T().look_at(origin=[0.1 * k, 1.2, 3.6],
                                                target=[0, 0.5, 0], up=[0, 1, 0])
        params.update()
        return _render_counting_kernels(scene, integ, seen)

    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        dr.kernel_history()
        mi.render(scene, integrator=integ, spp=1)
        seen = {k["hash"] for k in dr.kernel_history() if k["type"] == dr.KernelType.JIT}
        lit = [move(k) for k in (1, 2, 1, 2)][2:]
        params["pl1.intensity.value"] = 0.0
        params.update()
        mi.render(scene, integrator=integ, spp=1)
        seen.update(k["hash"] for k in dr.kernel_history() if k["type"] == dr.KernelType.JIT)
        dark = [move(k) for k in (1, 2)]
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    print("kernels launched, compiled per camera move: lit", lit, "one dark", dark)
    assert all(compiled == 0 for _, compiled in dark), dark
    assert max(n for n, _ in dark) <= max(n for n, _ in lit), (lit, dark)
    img = np.asarray(mi.render(scene, integrator=integ, spp=1))
    fresh = np.asarray(mi.render(scene, integrator=shadowmap(method="hard", virtual=True,
                                                             cache_maps=False), spp=1))
    assert np.array_equal(img, fresh)


def test_cache_off_builds_every_frame():
    scene = mi.load_dict(default_scene(width=32, height=32, spp=1))
    integ = shadowmap(method="hard", virtual=True, cache_maps=False)
    vis_of(scene, integ, spp=1)
    built = integ.stats["pages_built"]
    vis_of(scene, integ, spp=1)
    assert integ.stats["pages_built"] == built > 0


def _history_scene(light: dict):
    """A sphere and a box on a ground, 64^2 (the camera is moved by the test)."""
    return mi.load_dict({
        "type": "scene",
        "camera": {"type": "perspective", "fov": 40,
                   "to_world": T().look_at(origin=[0.2, 3.5, 4.9], target=[0.25, 0.25, 0],
                                           up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": 64, "height": 64,
                            "rfilter": {"type": "box"}}},
        "ground": {"type": "rectangle", "to_world": T().rotate([1, 0, 0], -90).scale(4)},
        "sphere": {"type": "sphere", "center": [-0.85, 0.65, -0.6], "radius": 0.65},
        "box": {"type": "cube", "to_world": T().translate([0.85, 0.5, -0.5])
                .rotate([0, 1, 0], 30).scale(0.5)},
        "light": light})


@pytest.mark.parametrize("light, props", [
    # a small pool: its room beyond the degraded marks kept finer pages of other poses,
    # which the level walk read (1.4 % of pixels changed)
    ({"type": "spot", "cutoff_angle": 35, "beam_width": 28,
      "intensity": {"type": "rgb", "value": 120.0},
      "to_world": T().look_at(origin=[-2.4, 4.0, -3.4], target=[0.2, 0, 0.3], up=[0, 1, 0])},
     {"method": "hard", "memory_budget": 0.1}),
    # wide PCSS kernels on small pages: their far taps and the blocker search's near
    # depth read pages of other poses (0.6 % of pixels changed)
    ({"type": "point", "position": [-2.4, 4.0, -3.4],
      "intensity": {"type": "rgb", "value": 60.0}},
     {"method": "pcss", "light_size": 1.5, "page_size": 8}),
])
def test_a_render_reads_only_its_own_pages_whatever_earlier_renders_built(light, props):
    """A camera pose rendered again after other poses gives its first image exactly, and
    a fresh integrator's: the page table holds only the render's own pages (the pool
    keeps others for later moves)."""
    scene = _history_scene(light)
    params = mi.traverse(scene)
    integ = shadowmap(**props)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)      # the small budget degrades
        first = vis_of(scene, integ, seed=0)
        poses = [([1.5, 3.0, 4.5], [0.0, 0.3, -0.3]), ([0.0, 1.0, 2.5], [-0.85, 0.5, -0.6]),
                 ([0.2, 7.0, 9.8], [0.25, 0.25, 0.0]), ([-3, 1.5, 2], [0.5, 0.3, -0.5]),
                 ([0.2, 3.5, 4.9], [0.25, 0.25, 0.0])]
        for origin, target in poses:
            params["camera.to_world"] = T().look_at(origin=origin, target=target,
                                                    up=[0, 1, 0])
            params.update()
            again = vis_of(scene, integ, seed=0)
        assert integ.stats["pages_built"] < integ.stats["pages_marked"]   # some reused
        fresh = vis_of(scene, shadowmap(**props, cache_maps=False), seed=0)
    print(f"pixels changed: {np.mean(np.abs(again - first) > 1e-6):.3%}")
    assert np.array_equal(fresh, first)
    assert np.array_equal(again, first)


def test_pcss_near_depth_reads_only_the_renders_own_tiles():
    """PCSS's blocker-search bound (the nearest depth of the face) came from whole pages:
    a tile an earlier pose cast into a page this pose reads, outside its marks (a thin
    pole's top), moved it from 3.03 to 2.81 and changed 7.3 % of the pixels of a pose
    rendered again. It is now over the render's own tiles."""
    scene = mi.load_dict({
        "type": "scene",
        "camera": {"type": "perspective", "fov": 40,
                   "to_world": T().look_at(origin=[1.4, 1.5, 1.5], target=[1.4, 0, 0],
                                           up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": 48, "height": 48,
                            "rfilter": {"type": "box"}}},
        "ground": {"type": "rectangle", "to_world": T().rotate([1, 0, 0], -90).scale(8)},
        "sphere": {"type": "sphere", "center": [-0.85, 0.65, -0.6], "radius": 0.65},
        "box": {"type": "cube", "to_world": T().translate([0.85, 0.5, -0.5])
                .rotate([0, 1, 0], 30).scale(0.5)},
        "pole": {"type": "cube", "to_world": T().translate([2.0, 2.0, 0.0])
                 .scale([0.03, 2.0, 0.03])},
        "light": {"type": "spot", "cutoff_angle": 70, "beam_width": 65,
                  "intensity": {"type": "rgb", "value": 120.0},
                  "to_world": T().look_at(origin=[0, 6, 0], target=[0, 0, 0],
                                          up=[0, 0, 1])}})
    params = mi.traverse(scene)
    integ = shadowmap(method="pcss", light_size=1.5)

    def pose(origin, target):
        params["camera.to_world"] = T().look_at(origin=origin, target=target, up=[0, 1, 0])
        params.update()
    first = vis_of(scene, integ, seed=0)
    near = integ.maps[0].face_near.numpy()
    pose([5.54, 5.21, 0.49], [0.0, 0.5, 0.0])
    vis_of(scene, integ, seed=0)
    pose([1.4, 1.5, 1.5], [1.4, 0, 0])
    again = vis_of(scene, integ, seed=0)
    print(f"near {near[0]:.3f} -> {integ.maps[0].face_near.numpy()[0]:.3f}; pixels changed "
          f"{np.mean(np.abs(again - first) > 1e-6):.2%}")
    assert np.array_equal(integ.maps[0].face_near.numpy(), near)
    assert np.array_equal(again, first)


# ----------------------------------------------------------------- memory budget
def test_a_small_budget_degrades_to_coarser_pages_never_lit():
    """A pool that holds half the marked pages: a warning, the finest pages replaced by
    their parents (coarser, never missing), and no more false-lit pixels than one
    level coarser everywhere (``lod_bias`` + 1) would give."""
    scene = mi.load_dict(default_scene(width=64, height=64, spp=2))
    ref = reference(("default", "spot"), mi.load_dict(default_scene(width=64, height=64,
                                                                    spp=4)))

    def run(**kw):
        integ = shadowmap(method="hard", virtual=True, cache_maps=False, **kw)
        vis = vis_of(scene, integ, spp=2)
        return integ, float(np.mean((vis >= 0.5) & (ref < 0.5))), misclassified(vis, ref)

    full, lit_full, mis_full = run()
    n_pages = full.stats["pages_marked"]
    page = full.opts.page_size
    budget = (n_pages // 2) * page * page * 4 / 2**20
    with pytest.warns(RuntimeWarning, match="memory_budget"):
        small, lit_small, mis_small = run(memory_budget=budget)
    coarse, lit_coarse, mis_coarse = run(lod_bias=0.5)
    print(f"{n_pages} pages: false lit {lit_full:.3%}; {small.maps[0].store.n_pages} pages: "
          f"{lit_small:.3%} (one level coarser: {lit_coarse:.3%}); misclassified "
          f"{mis_full:.3%} / {mis_small:.3%} / {mis_coarse:.3%}")
    assert small.maps[0].store.n_pages <= n_pages // 2
    assert lit_small <= lit_coarse + 0.002


@pytest.mark.parametrize("T", [1, 2, 8, 16])
def test_morton_order_visits_every_texel_of_a_tile_once(T):
    """The page build's texel order (:func:`~mi_shadowmap.virtual.store.morton_xy`) is a
    permutation of the tile's texels, whose first 8 are a 4 x 2 block (one vector of
    neighbours)."""
    i, j = page_store.morton_xy(dr.arange(mi.UInt32, T * T), T)
    i, j = i.numpy().astype(int), j.numpy().astype(int)
    assert sorted(zip(i, j)) == [(a, b) for a in range(T) for b in range(T)]
    if T >= 4:
        assert (i[:8].max(), j[:8].max()) == (3, 1)


@pytest.mark.parametrize("stored", [True, False])
@pytest.mark.parametrize("bits", [4, 14])
def test_mark_dedupe_returns_every_distinct_key(bits, stored, monkeypatch):
    """The mark pass's hash-table dedupe (:func:`~mi_shadowmap.virtual.marks.dedupe_many`)
    returns, per light, exactly the distinct keys of its valid candidates (repeats allowed,
    none missed): with tables of 2^14 slots (the default) and of 16 slots, where most keys
    lose their slot in both rounds and come back as candidates; its later rounds reading
    the keys its first kernel stored (``STORED_KEY_BYTES``) or recomputing them. Then the
    sort-based helpers give ``np.unique``'s answers."""
    monkeypatch.setattr(marks, "STORED_KEY_BYTES", (1 << 23) if stored else 0)
    rng = np.random.default_rng(11)
    groups, want = [], []
    for n_keys in (300, 40, 0):                 # lights with many, few and no keys
        keys, oks, valid = [], [], []
        pool = rng.integers(0, 2 ** 62, max(n_keys, 1), dtype=np.uint64)
        for _ in range(4):                      # four candidate lists per light
            k = pool[rng.integers(0, len(pool), 5000)]
            ok = rng.random(5000) < (0.7 if n_keys else 0.0)
            keys.append(mi.UInt64(k))
            oks.append(mi.Bool(ok))
            valid.append(k[ok])
        groups.append((keys, oks))
        want.append(np.unique(np.concatenate(valid)))
    found = marks.dedupe_many(groups, bits=bits)
    assert len(found) == 3
    for got, w in zip(found, want):
        assert np.array_equal(np.unique(got), w)
        if bits == 14 and len(w):
            assert len(got) < 2 * len(w)        # few repeats
    for a in (found[0], found[1], np.zeros(0, np.uint64), np.array([5], np.uint64)):
        assert np.array_equal(layout.sorted_unique(a), np.unique(a))
    base = np.unique(found[0])
    more = np.sort(np.concatenate([base[:3], rng.integers(0, 2 ** 62, 4, dtype=np.uint64)]))
    assert np.array_equal(layout.with_keys(base, more),
                          np.unique(np.concatenate([base, more])))
    assert np.array_equal(layout.with_keys(np.zeros(0, np.uint64), more), more)


@pytest.mark.parametrize("stored", [True, False])
def test_mark_dedupe_spills_per_partition(stored, monkeypatch):
    """:func:`~mi_shadowmap.virtual.marks.dedupe_many` with partitions (an environment's
    regions, each with its own slots) keeps ``SPILL`` twice-lost candidates per partition,
    not per list: a batch of regions whose candidates lose both slots a few hundred times
    together, fewer than ``SPILL`` each, runs the dedupe's three kernels and no fourth
    (at 256^2 under sky_sun each batch of 8 regions overflowed 4096 and read back all its
    524 k candidates); every distinct key is returned, as with the fourth kernel; the
    later rounds reading the stored keys (``STORED_KEY_BYTES``) or recomputing them."""
    monkeypatch.setattr(marks, "STORED_KEY_BYTES", (1 << 23) if stored else 0)
    monkeypatch.setattr(marks, "SPILL", 64)
    rng = np.random.default_rng(4)
    n_parts, per = 12, 100
    part = np.repeat(np.arange(n_parts), per).astype(np.uint32)
    keys = rng.integers(0, 2 ** 62, (n_parts, 20), dtype=np.uint64)
    k = keys[part, rng.integers(0, 20, n_parts * per)]
    ok = rng.random(n_parts * per) < 0.9
    want = np.unique(k[ok])
    flag = dr.flag(dr.JitFlag.KernelHistory)
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        dr.kernel_history()
        found = marks.dedupe_many([([mi.UInt64(k)], [mi.Bool(ok)])], bits=4,
                                  parts=[(mi.UInt32(part), n_parts)])
        kernels = [h for h in dr.kernel_history() if h["type"] == dr.KernelType.JIT]
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, flag)
    assert np.array_equal(np.unique(found[0]), want)
    assert len(kernels) == 3
    # more than SPILL in one partition: the fourth kernel, and still every key
    monkeypatch.setattr(marks, "SPILL", 2)
    found = marks.dedupe_many([([mi.UInt64(k)], [mi.Bool(ok)])], bits=4,
                              parts=[(mi.UInt32(part), n_parts)])
    assert np.array_equal(np.unique(found[0]), want)


def test_page_minima_on_the_host_and_on_the_device_agree():
    """Each page's nearest finite depth (+inf for an empty page), as the CPU backend
    computes it in numpy and a GPU would on the device: the same values."""
    rng = np.random.default_rng(3)
    tpp = 64
    d = rng.uniform(0.5, 1e5, 7 * tpp).astype(np.float32)
    d[rng.random(d.size) < 0.3] = np.inf
    d[2 * tpp:3 * tpp] = np.inf                 # an empty page
    # NaN and -inf are not finite depths: the host's plain minimum (which they would win)
    # is masked on their pages only (page_minima's fast path)
    d[4 * tpp + 5], d[5 * tpp + 9], d[6 * tpp:6 * tpp + 2] = np.nan, -np.inf, (np.nan, -np.inf)
    depth = mi.Float(d)
    dr.eval(depth)
    host = virtual.page_minima(depth, tpp, on_host=True)
    device = virtual.page_minima(depth, tpp, on_host=False)
    want = np.where(np.isfinite(d), d, np.inf).reshape(7, tpp).min(axis=1)
    assert np.array_equal(host, want) and np.array_equal(device, want)
    assert np.isinf(host[2]) and np.isfinite(host[4:]).all()


def test_camera_moves_under_a_budget_evict_and_reuse_slots(monkeypatch):
    """A pool that holds one view's pages and a bit: moving the camera away evicts the
    first view's pages (least recently used) into free slots, and moving back builds
    them again in recycled slots. Every frame equals a fresh integrator's render at that
    camera, and the store's sorted index and page table agree with its pages."""
    virtual.PAGE_CACHE.clear()
    scene = mi.load_dict(default_scene(width=64, height=64, spp=2))
    params = mi.traverse(scene)
    cams = [T().look_at(origin=o, target=[0.3, 0.25, 0.0], up=[0, 1, 0])
            for o in ([0.25, 3.45, 4.85], [-3.5, 2.0, 2.5], [0.25, 3.45, 4.85])]
    probe = shadowmap(method="hard", virtual=True)
    vis_of(scene, probe, spp=2)
    store = probe.maps[0].store
    budget = (int(store.n_pages * 1.2) + 2) * store.texels_per_page * 4 / 2**20
    integ = shadowmap(method="hard", virtual=True, memory_budget=budget)
    evicted = []
    evict = virtual.PageStore.evict
    monkeypatch.setattr(virtual.PageStore, "evict",
                        lambda self, keep, n: evicted.append(evict(self, keep, n)) or evicted[-1])
    for cam in cams:
        params["sensor.to_world"] = cam
        params.update()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)   # degraded pages: fine here
            vis = vis_of(scene, integ, spp=2)
            fresh = vis_of(scene, shadowmap(method="hard", virtual=True,
                                            memory_budget=budget, cache_maps=False), spp=2)
        assert np.array_equal(vis, fresh)
        store = integ.maps[0].store
        keys, slots = store._index()
        assert dict(zip(keys.tolist(), slots.tolist())) == store.slots
        assert np.all(keys[1:] > keys[:-1])          # sorted, no repeats
        assert len(set(store.slots.values())) == len(store.slots)   # one page per slot
        header, dense, *_ = store.table()
        assert set(np.unique(dense.numpy())) - {layout.INVALID_SLOT} <= set(slots.tolist())
    print(f"{store.n_pages} pages, {store.n_slots} slots, evicted {evicted}")
    assert sum(evicted) > 0, "the budget never made the store evict"


def many_lights_scene(n_point=4, n_spot=4, aim_away=(), width=32):
    """A floor, a box and a sphere under point and spot lights (spots ``aim_away``
    indices point at the floor's far corner: few pages). A box filter: its tests compare
    two renders bit for bit, and the default gaussian splats each sample into the
    neighbouring pixels with float atomic adds whose order varies with the LLVM
    backend's thread timing (a pixel read by two work blocks differs by an ulp from
    render to render, Mitsuba's own ``direct`` too)."""
    d = {"type": "scene",
         "sensor": {"type": "perspective", "fov": 60,
                    "to_world": T().look_at(origin=[0, 1.2, 3.6], target=[0, 0.5, 0],
                                            up=[0, 1, 0]),
                    "film": {"type": "hdrfilm", "width": width, "height": width,
                             "rfilter": {"type": "box"}}},
         "floor": {"type": "rectangle", "to_world": T().rotate([1, 0, 0], -90).scale(3)},
         "box": {"type": "cube", "to_world": T().translate([0.5, 0.3, 0]).scale(0.3)},
         "sph": {"type": "sphere", "center": [-0.7, 0.4, 0.3], "radius": 0.35}}
    for i in range(n_point):
        d[f"pl{i}"] = {"type": "point", "position": [-1.2 + 0.8 * i, 1.8, 0.5 - 0.3 * i]}
    for i in range(n_spot):
        target = [2.9, 0, -2.9] if i in aim_away else [0.2 * i - 0.3, 0, 0]
        d[f"sp{i}"] = {"type": "spot", "cutoff_angle": 5 if i in aim_away else 40,
                       "to_world": T().look_at(origin=[-1 + 0.6 * i, 2.2, 1.5],
                                               target=target, up=[0, 1, 0])}
    return mi.load_dict(d)


def maps_bytes(integ) -> int:
    """Bytes of one render's maps: every virtual map's pool (once per store) and every
    full map."""
    stores, total = [], 0
    for m in integ.maps:
        st = getattr(m, "store", None)
        if st is not None and all(st is not s for s in stores):
            stores.append(st)
            total += st.nbytes
        elif st is None and m is not None:
            total += m.nbytes
    return total


def test_memory_budget_caps_virtual_and_full_maps_together():
    """Point (cube) and spot lights under a budget that holds every virtual map's
    coarsest level but not a cube's even share of it: the maps stay within the budget
    (cube maps given full maps sized by the whole budget, beside virtual maps sized by it
    too, held 1.9x it)."""
    virtual.PAGE_CACHE.clear()
    scene = many_lights_scene(4, 4)
    budget = 0.15         # 37 pages of 32^2: 4 x 7 + 4 x 2 the coarsest levels
    integ = shadowmap(method="hard", memory_budget=budget)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)      # degraded pages: expected
        vis = vis_of(scene, integ, spp=2)
    used = maps_bytes(integ)
    print(f"{used} bytes of {budget * 2**20:.0f}")
    assert used <= budget * 2**20
    assert misclassified(vis, reference(("many", 4, 4), many_lights_scene(4, 4), 2)) < 0.1


def test_memory_budget_caps_an_environments_full_map_beside_virtual_maps():
    """An environment cut into 64 regions (more than a virtual map's 32 faces: a full
    map) beside a point and a spot light's virtual maps: the full map gets what the
    virtual maps' coarsest levels leave, the virtual pools what the full map leaves
    (each was sized by the whole budget: 1.76x it at 0.2 MiB)."""
    from mi_shadowmap.depth_maps import ShadowMap
    virtual.PAGE_CACHE.clear()
    scene = mi.load_dict({
        "type": "scene",
        "sensor": {"type": "perspective", "fov": 60,
                   "to_world": T().look_at(origin=[0, 1.2, 3.6], target=[0, 0.5, 0],
                                           up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": 32, "height": 32}},
        "floor": {"type": "rectangle", "to_world": T().rotate([1, 0, 0], -90).scale(3)},
        "box": {"type": "cube", "to_world": T().translate([0.5, 0.3, 0]).scale(0.3)},
        "sky": {"type": "constant", "radiance": 0.5},
        "sp": {"type": "spot", "cutoff_angle": 40,
               "to_world": T().look_at(origin=[-1, 2.2, 1.5], target=[0, 0, 0],
                                       up=[0, 1, 0])},
        "pl": {"type": "point", "position": [0.5, 2, 0.5]}})
    integ = shadowmap(method="hard", env_lights=64, memory_budget=0.2)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        img = np.asarray(mi.render(scene, integrator=integ, spp=1))
    assert np.isfinite(img).all()
    assert [type(m) for m in integ.maps] == [ShadowMap, virtual.VirtualShadowMap,
                                            virtual.VirtualShadowMap]
    assert maps_bytes(integ) <= 0.2 * 2**20


def test_memory_budget_is_shared_by_need():
    """One spot light reads many pages, three read few: a budget that holds all their
    pages (but not four times the first's) degrades nothing, warns nothing, and renders
    what an unlimited budget renders (split evenly, the first light degraded while the
    others' shares stayed unused)."""
    virtual.PAGE_CACHE.clear()
    scene = many_lights_scene(0, 4, aim_away=(1, 2, 3))
    probe = shadowmap(method="hard", cache_maps=False)
    want = vis_of(scene, probe, spp=2)
    stores = [m.store for m in probe.maps]
    slots = sum(st.n_pages + 1 for st in stores)
    pages = [st.n_pages for st in stores]
    assert pages[0] + 1 > slots / 4, pages       # an even split cannot hold the first
    budget = slots * stores[0].texels_per_page * 4 / 2**20
    integ = shadowmap(method="hard", memory_budget=budget, cache_maps=False)
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        vis = vis_of(scene, integ, spp=2)
    assert np.array_equal(vis, want)
    assert maps_bytes(integ) <= budget * 2**20


def test_one_budget_warning_per_render_names_the_degraded_lights():
    """Eight lights degraded by a small budget: one warning, naming the count, the first
    lights and the budget that would hold every marked page (was one per light)."""
    virtual.PAGE_CACHE.clear()
    scene = many_lights_scene(2, 6)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        vis_of(scene, shadowmap(method="hard", memory_budget=0.12, cache_maps=False), spp=1)
    msgs = [str(w.message) for w in caught if "memory_budget" in str(w.message)]
    assert len(msgs) == 1, msgs
    assert "'pl0'" in msgs[0] and "more" in msgs[0] and "would hold every marked" in msgs[0]


def test_a_budget_below_every_lights_coarsest_level_warns_of_its_full_maps():
    """Four lights whose coarsest virtual levels together (18 pages of 32^2: 0.07 MiB)
    do not fit the budget: the automatic ``virtual`` gives them full maps, with one
    warning naming the budget, what virtual maps need and the full maps' resolution
    (it was silent: 24 lights so degraded were 1-7 % false lit, the warning of a
    degraded virtual map never came); ``virtual=false`` asked for full maps: no warning."""
    from mi_shadowmap.depth_maps import ShadowMap
    virtual.PAGE_CACHE.clear()
    scene = many_lights_scene(2, 2)
    integ = shadowmap(method="hard", memory_budget=0.05, cache_maps=False)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        img = np.asarray(mi.render(scene, integrator=integ, spp=1))
    msgs = [str(w.message) for w in caught if "memory_budget" in str(w.message)]
    assert np.isfinite(img).all()
    assert all(isinstance(m, ShadowMap) for m in integ.maps)
    assert len(msgs) == 1, msgs
    assert ("memory_budget = 0.05 MiB" in msgs[0] and "0.071 MiB" in msgs[0]
            and f"full map of {integ.resolution}^2" in msgs[0]), msgs[0]
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        mi.render(scene, integrator=shadowmap(method="hard", memory_budget=0.05,
                                              virtual=False, cache_maps=False), spp=1)
    assert not [w for w in caught if "memory_budget" in str(w.message)]


def test_a_budget_below_one_virtual_cube_warns_of_its_full_maps():
    """A ``memory_budget`` below one virtual cube map's coarsest level (6 pages of 32^2
    and an empty page, ``hard``'s one float32 a texel: 0.028 MiB) turns the automatic
    ``virtual`` off when the options are read, so the render never reached the budget
    check that warns: full maps of 29^2 texels a face at 0.02 MiB, silently, where a
    slightly larger budget too small for 24 lights warned. Now the same warning, naming
    what a virtual cube map needs; none where full maps were asked for (``virtual=false``,
    a ``resolution``) or come anyway (``multiview``)."""
    from mi_shadowmap.depth_maps import ShadowMap
    virtual.PAGE_CACHE.clear()
    scene = many_lights_scene(1, 0)

    def budget_warnings(**props):
        integ = shadowmap(**{"method": "hard", "memory_budget": 0.02, "cache_maps": False,
                             **props})
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            mi.render(scene, integrator=integ, spp=1)
        return integ, [str(w.message) for w in caught if "memory_budget" in str(w.message)]

    integ, msgs = budget_warnings()
    assert isinstance(integ.maps[0], ShadowMap)
    assert len(msgs) == 1, msgs
    assert ("memory_budget = 0.02 MiB" in msgs[0] and "virtual cube map" in msgs[0]
            and "0.028 MiB" in msgs[0] and f"full map of {integ.resolution}^2" in msgs[0]), msgs[0]
    for props in ({"virtual": False}, {"resolution": 16}, {"method": "multiview"}):
        assert budget_warnings(**props)[1] == [], props


def test_a_smaller_budget_later_shrinks_the_shared_pools():
    """Pools kept in the page cache from a render with a large budget: a later render
    with a smaller one resizes them to it (they kept the largest size any render gave
    them), moving the pages it keeps into the remaining slots, and renders what a fresh
    integrator renders with that budget."""
    virtual.PAGE_CACHE.clear()
    scene = many_lights_scene(1, 2)
    params = mi.traverse(scene)
    cams = [T().look_at(origin=o, target=[0, 0.5, 0], up=[0, 1, 0])
            for o in ([0, 1.2, 3.6], [-3.0, 1.5, 1.0])]
    for cam in cams:                          # two poses' pages in one pool, large budget
        params["sensor.to_world"] = cam
        params.update()
        vis_of(scene, shadowmap(method="hard"), spp=1)
    big = sum(st.nbytes for st in {id(s): s for s in _stores()}.values())
    budget = big / 2 / 2**20
    integ = shadowmap(method="hard", memory_budget=budget)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        vis = vis_of(scene, integ, spp=1)
        fresh = vis_of(scene, shadowmap(method="hard", memory_budget=budget,
                                        cache_maps=False), spp=1)
    print(f"pools {big} bytes, then {maps_bytes(integ)} of {budget * 2**20:.0f}")
    assert maps_bytes(integ) <= budget * 2**20
    assert np.array_equal(vis, fresh)
    for m in integ.maps:
        st = m.store
        keys, slots = st._index()
        assert slots.max() < st.capacity and len(set(slots.tolist())) == len(slots)


def test_a_light_of_zero_intensity_builds_only_its_coarsest_pages(monkeypatch):
    """A point light of intensity 0 lights no sample: its map keeps the coarsest level
    (6 pages; 22 marked before), the image and every visibility AOV are those of a render
    that builds its pages, and once lit again (``params.update``) its pages are built as
    a fresh integrator's."""
    virtual.PAGE_CACHE.clear()
    scene = many_lights_scene(2, 1)
    params = mi.traverse(scene)
    params["pl1.intensity.value"] = 0.0
    params.update()
    integ = shadowmap(method="hard")
    img = np.asarray(mi.render(scene, integrator=integ, spp=1))
    assert integ.maps[1].store.n_pages == 6 < integ.maps[0].store.n_pages
    with monkeypatch.context() as m:
        m.setattr(planner, "_dark", lambda emitter, store=None: False)
        want = np.asarray(mi.render(scene, integrator=shadowmap(method="hard",
                                                                cache_maps=False), spp=1))
    assert np.array_equal(img, want)
    params["pl1.intensity.value"] = 1.0
    params.update()
    img = np.asarray(mi.render(scene, integrator=integ, spp=1))
    assert integ.maps[1].store.n_pages > 6
    fresh = np.asarray(mi.render(scene, integrator=shadowmap(method="hard",
                                                             cache_maps=False), spp=1))
    assert np.array_equal(img, fresh)


def _stores():
    """Every page store in the page cache."""
    return [v for slot in virtual.PAGE_CACHE._scenes.values() for k, v in slot[2].items()
            if isinstance(v, virtual.PageStore)]


# -------------------------------------------------------------------- variants
@pytest.mark.parametrize("variant", ["llvm_ad_mono", "llvm_ad_spectral"])
@pytest.mark.parametrize("light, extra", [("point", {}), ("directional", {"cascades": 2})])
def test_virtual_maps_in_other_variants(variant, light, extra):
    mi.set_variant(variant)
    scene = mi.load_dict(default_scene(width=32, height=32, spp=2, light=light))
    img = np.asarray(mi.render(scene, integrator=shadowmap(method="pcf", virtual=True, **extra),
                               spp=2))
    ref = np.asarray(mi.render(scene, integrator=shadowmap(method="raytraced"), spp=2))
    assert np.isfinite(img).all()
    assert misclassified(img[..., -1], ref[..., -1]) <= 0.02


# -------------------------------------------------------------------- cascades
def test_virtual_cascades_at_the_same_density_match_full_cascades():
    """Issue 11, point 4: cascades read through virtual maps too. With ``resolution`` R
    and ``lod_bias`` -8 every lookup reads level 0 of its cascade's virtual face, whose
    texel centres are the full R^2 cascade's: both fit their rectangles to the same
    camera-visible points, grown by 4 texels of 256."""
    scene = mi.load_file(str(SCENES / "large_world.xml"), width=64, height=64)
    full = vis_of(scene, shadowmap(method="hard", cascades=4, resolution=256), spp=2)
    integ = shadowmap(method="hard", cascades=4, resolution=256, virtual=True, lod_bias=-8.0)
    virt = vis_of(scene, integ, spp=2)
    assert isinstance(integ.maps[0], virtual.VirtualShadowMap)
    # 4 cascades and the catch-all face (the whole rectangle, for points outside theirs)
    assert integ.views[0].n_faces == 5 and integ.maps[0].layout.res0 == 256
    assert {0, 1, 2, 3} <= set(integ.maps[0].page_records()["face"])
    differ = float(np.mean(np.abs(full - virt) > 0.01))
    print(f"{differ:.3%} of the pixels differ")
    assert differ <= 0.002


def test_points_outside_their_cascade_read_the_catch_all_face():
    """A virtual cascade's rectangle holds the visible points of its depth slice at the
    pixel centres; a point outside it (a camera sample off the centre, towards the
    horizon) reads the last face, the whole scene-fitted rectangle, instead of finding no
    map; float32 and float64 projections agree on the face."""
    from mi_shadowmap.map_manager import _virtual_cascades
    from mi_shadowmap.light_views import make_light_view
    scene = mi.load_file(str(SCENES / "large_world.xml"), width=64, height=64)
    opts = parse_options({"method": "hard", "virtual": True, "cascades": 4})
    sun = next(i for i, e in enumerate(scene.emitters())
               if e.flags() & mi.EmitterFlags.DeltaDirection)
    base = make_light_view(scene.emitters()[sun], scene, sun)
    view = _virtual_cascades(scene, scene.sensors()[0], opts, [base])[0]
    assert view.catch_all and view.n_faces == 5 and view.rects[-1][:2] == (0.0, 0.0)
    rng = np.random.default_rng(3)
    lo, hi = scene_bounds(scene)
    p = rng.uniform(lo, hi, (20000, 3))
    p[:, 1] = 0.0                                # on the ground
    p64 = mi.Point3d(*(p[:, a].copy() for a in range(3)))
    face, uv, _, inside = view.project_f64(p64)
    face32 = view.project(mi.Point3f(p64))[0]
    cascade = view._cascade_of_f64(p64).numpy()
    light = np.asarray(view.light_from_world.matrix, np.float64)
    p_l = p @ light[:3, :3].T + light[:3, 3]
    rects = np.array(view.rects)
    in_own = ((np.abs(p_l[:, 0] - rects[cascade, 0]) <= rects[cascade, 2])
              & (np.abs(p_l[:, 1] - rects[cascade, 1]) <= rects[cascade, 3]))
    face = face.numpy()
    assert inside.numpy().all()
    assert (~in_own).sum() > 1000, "the test needs points outside their cascade"
    np.testing.assert_array_equal(face[in_own], cascade[in_own])
    assert (face[~in_own] == 4).all()
    assert np.mean(face32.numpy() == face) > 0.999   # float32 differs only at edges


@pytest.mark.parametrize("method, cascades", [("hard", 4), ("pcf", 4), ("pcss", 2),
                                              ("vsm", 4), ("mdsm", 3)])
def test_virtual_cascades_agree_with_raytracing(method, cascades):
    """``virtual=true`` with ``cascades``: each cascade a virtual face at the pixel
    footprint's level; on the large world as accurate as the default's levels (measured
    0.48-0.59 %, mdsm 0.99 %; full 4 x 1024^2 cascades 2.3 % at this film)."""
    scene = mi.load_file(str(SCENES / "large_world.xml"), width=128, height=128)
    ref = reference("large_world", scene, spp=16)
    integ = shadowmap(method=method, virtual=True, cascades=cascades)
    mis = misclassified(vis_of(scene, integ, spp=16), ref)
    print(f"{method}, {cascades} virtual cascades: {mis:.3%}")
    assert type(integ.views[0]).__name__ == "CascadedView"
    assert mis <= (0.015 if method == "mdsm" else 0.01)


def test_virtual_cascades_follow_the_camera_and_compile_nothing():
    """Cascades follow the camera, so their pages are built anew after a move (the
    footprint-chosen levels without cascades keep theirs); a still camera rebuilds
    nothing, the page cache keeps one set of cascades per light (no pile-up along a
    camera path), and moves after the first compile no kernel (the cascades' values are
    data)."""
    virtual.PAGE_CACHE.clear()
    scene = mi.load_file(str(SCENES / "large_world.xml"), width=64, height=64)
    integ = shadowmap(method="hard", virtual=True, cascades=4)
    vis_of(scene, integ, spp=2)
    first = integ.stats["texels_built"]
    vis_of(scene, integ, spp=2)
    assert integ.stats["texels_built"] == 0 and integ.stats["pages_reused"] > 0
    built, entries = [], []

    def each():
        built.append(integ.stats["texels_built"])
        entries.append(len(next(iter(virtual.PAGE_CACHE._scenes.values()))[2]))

    compiled = _moves(scene, integ, 4, each)
    print(f"first {first} texels; moves: built {built}, compiled {compiled}, cache "
          f"entries {entries}")
    assert all(b > 0 for b in built)
    assert len(set(entries)) == 1, "the page cache grows along the camera path"
    assert compiled[1:] == [0] * 3, "moving the camera compiled a new kernel"


# ------------------------------------------------------------------- bad input
@pytest.mark.parametrize("props, match", [
    ({"method": "multiview", "virtual": True},
     r"'virtual' = true is not supported by method 'multiview'"),
    ({"virtual": True, "page_size": 48}, r"'page_size' = 48 must be a power of two"),
    ({"virtual": True, "resolution": 1000}, r"'resolution' = 1000 must be a power of two"),
    ({"virtual": True, "cull_faces": True}, r"'cull_faces' applies to full maps only"),
    ({"virtual": True, "fit_frusta": True}, r"'fit_frusta' applies to full maps only"),
    ({"resolution": 2**20}, r"'resolution' = 1048576 is above 65536"),
    ({"virtual": True, "memory_budget": 0.01}, r"'memory_budget' = 0.01 MiB cannot hold"),
    ({"method": "raytraced", "virtual": True}, r"'virtual' is not used by method"),
])
def test_bad_virtual_input_is_named(props, match):
    with pytest.raises(OptionError, match=match):
        parse_options(props)


def test_virtual_options_parse():
    o = parse_options({"virtual": True, "resolution": 2**24, "page_size": 32})
    assert o.virtual and o.resolution == 2**24 and o.page_size == 32
    assert parse_options({"virtual": True}).lod_bias == -0.5


def test_one_sided_area_light_builds_only_the_faces_in_front():
    """cbox_area's light is a rectangle emitting downwards: no page of the cube face
    looking up (+y, face 2) is built, not even its coarsest level; lookups there read
    the empty page (lit), which no lit point ever asks for."""
    scene = mi.load_file(str(SCENES / "cbox_area.xml"), width=32, height=32)
    integ = shadowmap(method="pcss", virtual=True, cache_maps=False)
    vis = vis_of(scene, integ, spp=2)
    rec = integ.maps[0].page_records()
    assert 2 not in set(rec["face"].tolist())
    assert set(rec["face"][rec["level"] == integ.maps[0].layout.coarsest].tolist()) == \
        {0, 1, 3, 4, 5}
    assert 0.0 <= vis.min() and vis.max() <= 1.0


def test_a_tilted_one_sided_light_shines_through_every_face_a_corner_ray_leaves_in_front():
    """``planner._lit_faces``: a face is lit where any of its corner rays leaves the
    emitting plane's front, however grazing. A rectangle light tilted 40 degrees from
    facing down reaches the +z face only at grazing directions (its best corner ray 4
    degrees in front of the plane): that face must keep its coarsest page; a threshold
    of 0.3 on the corner rays' cosine (mutation audit) dropped it unnoticed, since the
    renders' lights face along an axis."""
    from mi_shadowmap.light_views import CubeView
    a = math.radians(40.0)
    n = (0.0, -math.cos(a), -math.sin(a))
    view = CubeView("area", mi.ScalarPoint3f(0, 1, 0), T(), light_normal=n, label="tilted")
    assert planner._lit_faces(view) == [0, 1, 3, 4, 5]
    flat = CubeView("area", mi.ScalarPoint3f(0, 1, 0), T(), light_normal=(0.0, -1.0, 0.0),
                    label="down")
    assert planner._lit_faces(flat) == [0, 1, 3, 4, 5]
    assert planner._lit_faces(CubeView("point", mi.ScalarPoint3f(0, 1, 0), T(),
                                       label="p")) == list(range(6))


def test_coarsest_pages_sit_in_fixed_slots():
    """Face f's coarsest page is in slot f + 1, so a lookup finds it without the table;
    a face a one-sided light does not shine through keeps an empty (+inf) page there."""
    scene = mi.load_file(str(SCENES / "cbox_area.xml"), width=32, height=32)
    integ = shadowmap(method="hard", virtual=True, cache_maps=False)
    vis_of(scene, integ, spp=1)
    store = integ.maps[0].store
    lay, P = store.layout, store.layout.page_size
    pool = store.pools["depth"].numpy().reshape(-1, P * P)
    for f in range(lay.view.n_faces):
        slot = store.slots.get(np.uint64(virtual.page_key(f, lay.coarsest, 0, 0)))
        if f == 2:                       # +y: behind the downward-emitting light
            assert slot is None and np.all(np.isinf(pool[f + 1]))
        else:
            assert slot == f + 1
    others = [s for k, s in store.slots.items()
              if ((int(k) >> 54) & 31) != lay.coarsest]
    assert others and min(others) > lay.view.n_faces


@pytest.mark.parametrize("light", ["point", "area"])
def test_page_table_resolves_every_built_page(light):
    """Decoding the page table as a lookup does (the two 64-bit header words of the
    page's face and level, then the entry of the 2 x 2 block whose lower-left page it
    is) gives every built page's slot, and the block below and left of it holds it as
    its upper-right corner."""
    scene = mi.load_dict(default_scene(width=48, height=48, spp=1, light=light))
    integ = shadowmap(method="pcf", virtual=True, cache_maps=False)
    vis_of(scene, integ, spp=1)
    vmap = integ.maps[0]
    L = vmap.layout.n_levels
    words = vmap.header.numpy().reshape(-1, 2)
    dense = vmap.dense.numpy().reshape(-1, 4)
    rec = vmap.page_records()
    assert len(rec["slot"]) > 10
    for f, lev, px, py, slot in zip(rec["face"], rec["level"], rec["px"], rec["py"],
                                    rec["slot"]):
        w0, w1 = (int(w) for w in words[f * L + lev])
        x0 = np.int64(np.uint32(w0 & 0xFFFFFFFF).view(np.int32))
        y0 = np.int64(np.uint32(w0 >> 32).view(np.int32))
        W, H, base = w1 & 0xFFFF, (w1 >> 16) & 0xFFFF, w1 >> 32
        lx, ly = px - x0, py - y0
        assert 0 <= lx < W and 0 <= ly < H
        assert dense[base + ly * W + lx][0] == slot
        # the block to its upper right holds it as corner 3 (lower-left of that block:
        # px - 1, py - 1, which the border of the rectangle always covers)
        assert dense[base + (ly - 1) * W + (lx - 1)][3] == slot
    # and the kernel's own decoding (VirtualShadowMap._block_entry) agrees
    e, ok = vmap._block_entry(mi.UInt32(rec["face"]), mi.UInt32(rec["level"]),
                              mi.Int32(rec["px"]), mi.Int32(rec["py"]), mi.Bool(True))
    assert ok.numpy().all()
    np.testing.assert_array_equal(vmap.dense.numpy()[e.numpy()], rec["slot"])


@pytest.mark.parametrize("light", ["spot", "point", "directional"])
def test_local_taps_continue_off_the_face_as_in_float64(light):
    """A bound lookup's taps (local texel coordinates, on the face or up to 3 texels off
    it, at levels of 2^3 to 2^20 texels and anywhere on the face): the same texel as
    the wrapped view's float64 continuation of the global coordinates (the neighbouring
    cube face, or off the map of a spot or directional light), which
    :class:`~mi_shadowmap.light_views.local.LocalView` only runs for taps off the face."""
    from mi_shadowmap.light_views import make_light_view
    from mi_shadowmap.light_views.local import LocalView
    scene = mi.load_dict(default_scene(width=16, height=16, spp=1, light=light))
    view = make_light_view(scene.emitters()[0], scene, 0)
    rng = np.random.default_rng(11)
    n = 8192
    res = 1 << rng.integers(3, 21, n)
    face = rng.integers(0, view.n_faces, n)
    # the bound block's first texel: anywhere, mostly near an edge of the face
    ox = np.where(rng.random(n) < 0.5, rng.integers(-2, 3, n), res - rng.integers(0, 40, n))
    oy = np.where(rng.random(n) < 0.5, rng.integers(0, 1 << 20, n) % res,
                  res - rng.integers(0, 40, n))
    origin = mi.Point2i(mi.Int32(ox), mi.Int32(oy))
    local = LocalView(view, mi.UInt32(face), mi.Int32(res), origin)
    xy = mi.Point2f(mi.Float(rng.uniform(-4.0, 68.0, n)), mi.Float(rng.uniform(-4.0, 68.0, n)))
    got = local.tap_texel(mi.UInt32(face), xy, mi.Int32(res))
    xy64 = mi.Point2d(xy) + mi.Point2d(origin)
    f, i, j, inside = view.face_texel_f64(mi.UInt32(face), xy64, mi.Int32(res))
    want = (f, i - origin.x, j - origin.y, inside)
    g = [np.broadcast_to(np.asarray(a.numpy()), (n,)).astype(np.int64) for a in got]
    w = [np.broadcast_to(np.asarray(a.numpy()), (n,)).astype(np.int64) for a in want]
    ins = w[3].astype(bool)
    gx, gy = ox + np.floor(xy.x.numpy()), oy + np.floor(xy.y.numpy())
    off = (gx < 0) | (gx >= res) | (gy < 0) | (gy >= res)
    print(f"{light}: {off.sum()} of {n} taps off the face, {np.sum(off & ins)} continued "
          "on another face")
    assert off.sum() > 1000 and np.all(g[3] == w[3])
    for a, b in zip(g[:3], w[:3]):
        assert np.all(a[ins] == b[ins])


def test_a_level_resolution_divides_as_its_exact_reciprocal_multiplies():
    """Virtual lookups divide by a per-lane level resolution (a power of two) as a product
    with its reciprocal built from the exponent bits (:func:`~mi_shadowmap.light_views.
    base.divide_by_res`, :meth:`~mi_shadowmap.light_views.local.LocalView._to_local_uv`):
    bit for bit the quotients' float32 and float64 values, for resolutions 2^0 to 2^30
    and numerators from subnormals to the largest floats, signed zeros, infinities and
    NaN; a full map's ``int`` resolution (not a power of two) still divides."""
    from mi_shadowmap.light_views.base import divide_by_res, pow2_reciprocal
    rng = np.random.default_rng(5)
    k = np.repeat(np.arange(31), 400)
    x = rng.uniform(1.0, 2.0, k.size) * 2.0 ** rng.integers(-149, 128, k.size)
    x = np.where(rng.random(k.size) < 0.5, -x, x)
    x[:8] = [0.0, -0.0, np.inf, -np.inf, np.nan, 3.4028235e38, 1e-45, -1e-45]
    x32 = x.astype(np.float32)
    res = mi.Int32((1 << k).astype(np.int32))
    got = divide_by_res(mi.Float(x32), res).numpy()
    want = (mi.Float(x32) / mi.Float(res)).numpy()
    assert np.array_equal(got.view(np.uint32), want.view(np.uint32))
    x64 = rng.uniform(-1.0, 1.0, k.size) * 2.0 ** rng.integers(-1074, 1000, k.size)
    got64 = (mi.Float64(x64) * pow2_reciprocal(res, mi.Float64)).numpy()
    want64 = (mi.Float64(x64) / mi.Float64(res)).numpy()
    assert np.array_equal(got64.view(np.uint64), want64.view(np.uint64))
    assert divide_by_res(mi.Float(1.0), 3)[0] == mi.Float(1.0 / 3.0)[0]


@pytest.mark.parametrize("light", ["spot", "point", "area"])
def test_reading_slots_per_tap_or_per_block_gives_the_same_image(light):
    """``virtual_per_tap`` is a speed hint only: ``hard`` (per-tap slot reads) and the
    same lookup registered to read the 2 x 2 block's four slots up front render
    identical images."""
    from mi_shadowmap.filters.hard import hard
    from mi_shadowmap.methods import register_method, unregister_method
    from mi_shadowmap.filters.common import Lookup
    register_method("hard_block_reads", hard, virtual=True, virtual_per_tap=False)
    try:
        scene = mi.load_dict(default_scene(width=48, height=48, spp=2, light=light))
        integ = shadowmap(method="hard", virtual=True)
        a = vis_of(scene, integ, spp=2)
        b = vis_of(scene, shadowmap(method="hard_block_reads", virtual=True), spp=2)
        assert 0.0 < a.mean() < 1.0
        np.testing.assert_array_equal(a, b)
    finally:
        unregister_method("hard_block_reads")
    # the two ways of reading slots give the same pool index for every texel around the
    # receiver: its 2 x 2 pages, the pages beyond them, and a neighbouring face
    si, dp_dx, dp_dy, valid = virtual.camera_hits(scene, scene.sensors()[0])
    lk = Lookup(dr.select(valid, si.p, 0.0), si.n, dp_dx, dp_dy, si, None, None)
    vmap = integ.maps[0]
    per_tap, block = vmap.bind(lk, valid, per_tap=True), vmap.bind(lk, valid, per_tap=False)
    assert per_tap.slots is None and len(block.slots) == 4
    P = vmap.layout.page_size
    n_faces = vmap.view.n_faces
    for di in range(-P, 3 * P, P // 2 + 1):
        for dj in range(-P, 3 * P, P // 2 + 1):
            for df in (0, 1) if n_faces > 1 else (0,):
                face = (per_tap.view.face + df) % n_faces
                i, j = mi.Int32(di), mi.Int32(dj)
                np.testing.assert_array_equal(
                    np.where(valid.numpy(), per_tap._index(face, i, j).numpy(), 0),
                    np.where(valid.numpy(), block._index(face, i, j).numpy(), 0))


@pytest.mark.parametrize("per_tap", [False, True])
def test_fetch_centre_gives_the_point_whose_ray_cast_the_texel_read(per_tap):
    """``BoundVirtualMap.fetch_centre``: the texel ``fetch`` reads, and the point (local
    texel coordinates) whose ray gave it: the texel's own ``TEXEL_SAMPLE`` point where
    its page and tile were cast at the bound level, else that point of the coarsest
    level's texel over it, ``2^k`` texels wide (the receiver plane of ``pcf``,
    ``bilinear`` and ``pcss`` is evaluated there). Checked for taps within and beyond
    the bound pages, so that both kinds of read occur."""
    from mi_shadowmap.filters.common import Lookup
    scene = mi.load_dict(default_scene(width=48, height=48, spp=1, light="spot"))
    integ = shadowmap(method="pcf", virtual=True, cache_maps=False)
    vis_of(scene, integ, spp=1)
    vmap = integ.maps[0]
    si, dp_dx, dp_dy, valid = virtual.camera_hits(scene, scene.sensors()[0])
    lk = Lookup(dr.select(valid, si.p, 0.0), si.n, dp_dx, dp_dy, si, None, None)
    bound = vmap.bind(lk, valid, per_tap=per_tap)
    lay, P, v = vmap.layout, vmap.layout.page_size, valid.numpy()
    ox, oy = (np.asarray(c.numpy())[v] for c in bound.view.origin)
    level = np.broadcast_to(bound.level.numpy(), v.shape)[v]
    shift = lay.coarsest - level.astype(np.int64)
    ts = np.array(TEXEL_SAMPLE)
    kinds = set()
    for di in range(-2 * P, 4 * P, 11):
        for dj in (-P, P // 2, 2 * P):
            i, j = dr.opaque(mi.Int32, di), dr.opaque(mi.Int32, dj)    # one kernel
            z, c = bound.fetch_centre(bound.depth, bound.view.face, i, j, valid)
            np.testing.assert_array_equal(z.numpy()[v], bound.fetch(
                bound.depth, bound.view.face, i, j, valid).numpy()[v])
            # where the tap's page is built at the bound level (a tile of it this frame
            # did not mark reads the coarsest level's depth, which a new page holds there,
            # at its own point: PageStore._fill_from_coarsest)
            own = np.broadcast_to(bound._read_at[0].numpy(), v.shape)[v] | (shift == 0)
            cx, cy = (np.asarray(a.numpy())[v] for a in c)
            res = np.broadcast_to(bound.resolution.numpy(), v.shape)[v]
            gx, gy = np.clip(di + ox, 0, res - 1), np.clip(dj + oy, 0, res - 1)
            # there the texel's own point (a tap clamped to the face; float32: within a
            # thousandth of a texel)
            close = dict(rtol=0.0, atol=1e-3)
            np.testing.assert_allclose(cx[own], (gx - ox + ts[0])[own], **close)
            np.testing.assert_allclose(cy[own], (gy - oy + ts[1])[own], **close)
            # else the coarsest level's texel over it
            w = 2.0 ** shift
            np.testing.assert_allclose(cx[~own], (((gx >> shift) + ts[0]) * w - ox)[~own],
                                       **close)
            np.testing.assert_allclose(cy[~own], (((gy >> shift) + ts[1]) * w - oy)[~own],
                                       **close)
            kinds |= {bool(k) for k in np.unique(own)}
    assert kinds == {True, False}


@pytest.mark.parametrize("light", LIGHTS)
def test_same_density_matches_the_full_map(light):
    """Issue 11: at the same effective density a virtual map gives today's result. With
    ``resolution`` R (the finest level) and ``lod_bias`` -8 every lookup reads level 0,
    whose texel centres are the full R^2 map's, so ``hard`` classifies every pixel alike
    but for float rounding at texel and depth boundaries (the virtual map projects in
    float64 and lowers the receiver depth by 4 float32 roundoffs)."""
    scene = mi.load_dict(default_scene(width=64, height=64, spp=2, light=light))
    full = vis_of(scene, shadowmap(method="hard", resolution=256), spp=2)
    virt = vis_of(scene, shadowmap(method="hard", virtual=True, resolution=256,
                                   lod_bias=-8.0, page_size=32), spp=2)
    differ = float(np.mean(np.abs(full - virt) > 0.01))
    print(f"{light}: {differ:.3%} of the pixels differ")
    assert differ <= 0.002


@pytest.mark.parametrize("light", ["spot", "point"])
@pytest.mark.parametrize("depths, search", [(2, 3), (3, 5)])
def test_mdsm_same_density_matches_the_full_map(light, depths, search):
    """Virtual maps store no multiple-depth layers: ``mdsm`` computes the stored 3 x 3
    extremes it reads from the base depths at lookup time. At the same effective density
    (level 0 of a 256 virtual map against the full 256^2 map with its stored layers) it
    renders the same visibility but for float rounding, also where the windows are
    composed (``search`` 5) and clamped at the face's border (the point light's cube)."""
    scene = mi.load_dict(default_scene(width=64, height=64, spp=2, light=light))
    props = dict(method="mdsm", depths=depths, search=search, resolution=256)
    full_integ = shadowmap(virtual=False, **props)
    full = vis_of(scene, full_integ, spp=2)
    assert set(full_integ.maps[0].extra) >= ({"mdsm_max"} if depths == 2
                                             else {"mdsm_max", "mdsm_min"})
    virt_integ = shadowmap(virtual=True, lod_bias=-8.0, page_size=32, **props)
    virt = vis_of(scene, virt_integ, spp=2)
    assert not set(virt_integ.maps[0].extra) & {"mdsm_max", "mdsm_min"}
    partial = float(np.mean((full > 0.01) & (full < 0.99)))
    differ = float(np.mean(np.abs(full - virt) > 0.01))
    print(f"{light} depths {depths} search {search}: {partial:.2%} partly lit, "
          f"{differ:.3%} of the pixels differ")
    assert partial > 0.01, "no pixel reads the extra depths"
    assert differ <= 0.003


@pytest.mark.parametrize("light", LIGHTS)
@pytest.mark.parametrize("method", ["vsm", "evsm", "msm"])
def test_prefiltered_same_density_matches_the_full_map(light, method):
    """Virtual maps build no moment tables: the prefiltered methods sum their box's
    texels at lookup time and normalise by the scene's depth bounds. At the same
    effective density (level 0 of a 256 virtual map against the full 256^2 map and its
    summed-area tables) the visibility is the same to within the normalisation's
    difference (measured: at most 0.32 % of the pixels differ by more than 0.01, 0.024 %
    by more than 0.05 or across 0.5)."""
    scene = mi.load_dict(default_scene(width=64, height=64, spp=2, light=light))
    full_integ = shadowmap(method=method, resolution=256)
    full = vis_of(scene, full_integ, spp=2)
    assert any(k.startswith(method) for k in full_integ.maps[0].extra)
    virt_integ = shadowmap(method=method, virtual=True, resolution=256, lod_bias=-8.0,
                           page_size=32)
    virt = vis_of(scene, virt_integ, spp=2)
    assert isinstance(virt_integ.maps[0], virtual.VirtualShadowMap)
    assert not any(k.startswith(method) for k in virt_integ.maps[0].extra)
    partial = float(np.mean((full > 0.01) & (full < 0.99)))
    assert partial > 0.02, "no pixel reads a filtered value"
    assert float(np.mean(np.abs(full - virt) > 0.01)) <= 0.006
    assert float(np.mean(np.abs(full - virt) > 0.05)) <= 0.001
    assert misclassified(full, virt) <= 0.001


def test_box_means_of_depths_equal_the_summed_area_tables():
    """The texel-by-texel box means (virtual maps) equal the summed-area tables' (full
    maps) on random boxes: fractional texels, boxes clipped at the face's border, boxes
    under one texel wide."""
    from mi_shadowmap.depth_maps import ShadowMap, box_mean, summed_area_table
    from mi_shadowmap.filters.common import box_means_of_depths
    from mi_shadowmap.light_views import OrthoView
    res = 32
    rng = np.random.default_rng(5)
    depth = rng.uniform(1.0, 3.0, (res, res)).astype(np.float32)
    depth[rng.random((res, res)) < 0.1] = np.inf           # empty texels
    view = OrthoView("directional", mi.ScalarPoint3f(0, 0, 0), mi.ScalarTransform4f(),
                     half_extent=(1.0, 1.0), label="hand")
    smap = ShadowMap(view, res, depth=mi.Float(depth.ravel()))
    z = np.where(np.isfinite(depth), depth / 8.0, 1.0).astype(np.float64)
    sats = [summed_area_table(mi.Float64(v.ravel()), 1, res) for v in (z, z * z)]
    n = 4000
    centre = rng.uniform(-2.0, res + 2.0, (n, 2))
    width = rng.choice([0.3, 1.0, 2.5, 7.0, 20.0], (n, 2)) * rng.uniform(0.5, 1.5, (n, 2))
    lo = mi.Point2f(*(centre - 0.5 * width).T.astype(np.float32))
    hi = mi.Point2f(*(centre + 0.5 * width).T.astype(np.float32))
    face = mi.UInt32(np.zeros(n, np.uint32))

    def divide_by_res(d):
        zz = dr.select(dr.isfinite(d), mi.Float64(d) / 8.0, 1.0)
        return zz, zz * zz

    (m1, m2), count = box_means_of_depths(smap, face, lo, hi, divide_by_res, 2)
    # the tables' means are differences of sums over the whole face: on the 1e-6 texel^2
    # boxes of boxes clipped away entirely their cancellation reaches 1e-7 (the direct
    # sums are exact there), elsewhere both agree to float64 rounding
    lo_c, hi_c = np.clip(lo.numpy(), 0, res), np.clip(hi.numpy(), 0, res)
    big = np.prod(hi_c - lo_c, axis=0) >= 0.01
    assert big.mean() > 0.8
    for got, sat in ((m1, sats[0]), (m2, sats[1])):
        want = box_mean(sat, res, face, lo, hi)
        np.testing.assert_allclose(got.numpy()[big], want.numpy()[big], rtol=1e-10)
        np.testing.assert_allclose(got.numpy(), want.numpy(), rtol=1e-6)
    assert count.numpy().max() > 100 and count.numpy().min() >= 1


@pytest.mark.parametrize("light", LIGHTS)
def test_layout_depth_range_bounds_every_built_texel(light):
    """The prefiltered methods normalise virtual maps by the layout's depth range: every
    finite depth the pages hold lies inside it."""
    scene = mi.load_dict(default_scene(width=32, height=32, spp=1, light=light))
    integ = shadowmap(method="vsm", virtual=True)
    vis_of(scene, integ, spp=1)
    vmap = integ.maps[0]
    d_lo, d_hi = vmap.layout.depth_range
    d = vmap.depth.numpy()
    d = d[np.isfinite(d)]
    assert len(d) and 0.0 <= d_lo < d_hi
    assert d.min() >= d_lo * (1 - 1e-6) and d.max() <= d_hi * (1 + 1e-6)


def test_layout_depth_range_is_a_span_for_a_flat_scene_under_an_overhead_sun():
    """A ground alone under a sun straight above it holds one depth: the layout's depth
    range must still be a span (``d_lo < d_hi``), as the prefiltered methods divide by
    it; ``_depth_range`` widens it to ``[d_hi / 2, d_hi]`` (mutation audit: without that
    the span was 0 and nothing noticed)."""
    from mi_shadowmap.light_views import make_light_view
    scene = mi.load_dict({"type": "scene",
                          "ground": {"type": "rectangle",
                                     "to_world": T().rotate([1, 0, 0], -90).scale(2.0)},
                          "sun": {"type": "directional", "direction": [0, -1, 0]}})
    view = make_light_view(scene.emitters()[0], scene, 0)
    lay = layout.layout_for(view, scene, parse_options({"method": "vsm"}))
    d_lo, d_hi = lay.depth_range
    assert 0.0 <= d_lo < d_hi
    assert d_lo == pytest.approx(0.5 * d_hi)


def test_a_user_method_with_a_layer_virtual_maps_cannot_build_is_refused():
    from mi_shadowmap.methods import MethodError, register_method
    with pytest.raises(MethodError, match="virtual=True needs layers"):
        register_method("my_virtual", lambda smap, lk, opts, a: 1.0,
                        layers={"moments": lambda scene, smap: smap.depth}, virtual=True)


def test_a_user_method_whose_options_need_a_full_map_layer_is_refused_with_virtual():
    """A method whose ``layers_for`` decides its layers per option registers with
    ``virtual=True``; options under which it would read a layer virtual maps cannot
    build are refused when parsed, naming the method and the layer."""
    from mi_shadowmap.filters.hard import hard
    from mi_shadowmap.methods import Prop, register_method, unregister_method
    register_method("my_layered", hard, virtual=True,
                    properties=(Prop("fancy", "bool", False, "Read the moments layer."),),
                    layers={"moments": lambda scene, smap: smap.depth},
                    layers_for=lambda o: ("moments",) if o.fancy else ())
    try:
        assert parse_options({"method": "my_layered"}).virtual is True
        with pytest.raises(OptionError, match=r"my_layered.*\(moments\).*virtual=false"):
            parse_options({"method": "my_layered", "fancy": True, "virtual": True})
        assert parse_options({"method": "my_layered", "fancy": True,
                              "virtual": False}).virtual is False
    finally:
        unregister_method("my_layered")


@pytest.mark.parametrize("value", ["false", 1, None])
def test_virtual_per_tap_must_be_a_bool(value):
    """A string "false" would otherwise read as true: the record names the field."""
    from mi_shadowmap.filters.hard import hard
    from mi_shadowmap.methods import MethodError, register_method
    with pytest.raises(MethodError, match=r"whole_light=True lookups read full maps only"):
        register_method("whole_virtual", lambda smap, lk, opts, active: mi.Float(1.0),
                        whole_light=True, virtual=True)
    with pytest.raises(MethodError, match=r"virtual_per_tap must be True or False, got"):
        register_method("my_per_tap", hard, virtual=True, virtual_per_tap=value)


def test_a_user_method_reads_virtual_maps():
    """A user lookup written against ``fetch``/``texel_index`` reads virtual maps too."""
    import drjit as dr_
    from mi_shadowmap.filters.common import receiver
    from mi_shadowmap.methods import register_method, unregister_method

    def nearest(smap, lk, opts, active=True):
        r = receiver(smap, lk, opts)
        z = dr_.gather(mi.Float, smap.depth, smap.texel_index(r.face, r.uv), active & r.inside)
        return dr_.select(~r.inside | (r.depth <= z), 1.0, 0.0)

    register_method("my_nearest", nearest, virtual=True, needs_footprint=True)
    try:
        scene = mi.load_dict(default_scene(width=32, height=32, spp=2))
        a = vis_of(scene, shadowmap(method="my_nearest", virtual=True), spp=2)
        b = vis_of(scene, shadowmap(method="hard", virtual=True), spp=2)
        assert np.array_equal(a, b)
    finally:
        unregister_method("my_nearest")


def test_gradients_through_virtual_maps_are_refused_not_zero():
    """Virtual pages are built detached: with a shape parameter's gradients enabled the
    render says so instead of returning shadows without gradients."""
    scene = mi.load_dict(default_scene(width=16, height=16, spp=1))
    params = mi.traverse(scene)
    key = next(k for k in params.keys() if "vertex_positions" in k)
    dr.enable_grad(params[key])
    params.update()
    integ = shadowmap(method="hard", virtual=True)
    with pytest.raises(Exception) as e:
        img = mi.render(scene, params, integrator=integ, spp=1)
        dr.backward(dr.mean(img))
    msg = str(e.value) + str(getattr(e.value, "__cause__", ""))
    assert "virtual" in msg and "gradients" in msg


def test_the_automatic_default_gives_gradient_renders_full_maps():
    """``virtual`` left out: a scene whose shape has gradients enabled gets full maps
    (built in the AD graph) in its primal render and its gradient render alike, so the
    loss and its gradient see the same maps, and the shadows pass a gradient; once the
    gradients are disabled the same integrator renders virtual maps again."""
    from mi_shadowmap.depth_maps import ShadowMap
    scene = mi.load_dict(default_scene(width=16, height=16, spp=1))
    params = mi.traverse(scene)
    key = next(k for k in params.keys() if "vertex_positions" in k)
    integ = shadowmap(method="hard")
    dr.enable_grad(params[key])
    params.update()
    with dr.suspend_grad():   # how mi.render(scene, params) renders its primal image
        mi.render(scene, integrator=integ, spp=1)
    assert isinstance(integ.maps[0], ShadowMap), "the loss would see other maps"
    img = mi.render(scene, params, integrator=integ, spp=1)
    dr.backward(dr.mean(img, axis=None))
    assert isinstance(integ.maps[0], ShadowMap)
    assert dr.any(dr.grad(params[key]) != 0), "no gradient reached the occluder"
    dr.disable_grad(params[key])
    params.update()
    mi.render(scene, integrator=integ, spp=1)
    assert isinstance(integ.maps[0], virtual.VirtualShadowMap)


@pytest.mark.parametrize("props, virtual", [
    ({}, True), ({"method": "pcf"}, True), ({"method": "pcss"}, True),
    ({"method": "bilinear"}, True), ({"method": "second_depth"}, True),
    ({"resolution": 0}, True),                       # 0: automatic, as if left out
    ({"virtual": False}, False), ({"resolution": 512}, False),
    ({"cascades": 4}, False), ({"fit_frusta": True}, False), ({"cull_faces": True}, False),
    ({"antialias": "always"}, False), ({"cascades": 1}, True),
    ({"memory_budget": 0.02}, False),   # cannot hold a virtual cube map's coarsest level
    ({"method": "vsm"}, True), ({"method": "evsm"}, True), ({"method": "msm"}, True),
    ({"method": "mdsm"}, True), ({"method": "multiview"}, False)])
def test_virtual_is_automatic(props, virtual):
    assert parse_options(props).virtual is virtual


def test_a_light_with_no_page_still_renders():
    """A zero-area light emits nothing and marks no page (not even a coarse one): the
    pool still holds the empty page, so lookups read +inf instead of failing."""
    d = default_scene(width=16, height=16, spp=1, light="area")
    key = next(k for k, v in d.items() if isinstance(v, dict) and "emitter" in v)
    d[key]["to_world"] = d[key]["to_world"] @ T().scale(0.0)
    scene = mi.load_dict(d)
    for method in ("hard", "pcf", "pcss"):
        img = np.asarray(mi.render(scene, integrator=shadowmap(method=method, virtual=True),
                                   spp=1))
        assert np.isfinite(img).all() and img.max() == 0.0


@pytest.mark.parametrize("method", ["vsm", "evsm", "msm", "mdsm"])
def test_environment_regions_are_virtual_faces_for_derived_layer_methods(method):
    """An environment's regions are the faces of one virtual map in a virtual render,
    also for the methods whose full maps carry derived layers (they compute those from
    the pages' depths): finite, in range, and within 0.03 of the full maps' mean
    visibility."""
    from conftest import SCENE_FILES
    from mi_shadowmap.environment import EnvironmentView
    path = [p for p in SCENE_FILES if p.stem == "sky_sun"][0]
    scene = mi.load_file(str(path), width=16, height=16)
    integ = shadowmap(method=method, virtual=True)
    img = np.asarray(mi.render(scene, integrator=integ, spp=4))
    full = np.asarray(mi.render(scene, integrator=shadowmap(method=method, virtual=False),
                                spp=4))
    assert np.isfinite(img).all()
    vmap = integ.maps[0]
    assert isinstance(vmap, virtual.VirtualShadowMap) and isinstance(vmap.view, EnvironmentView)
    assert vmap.layers() == ["depth"]
    vis = img[..., -1]
    assert vis.min() >= 0.0 and vis.max() <= 1.0 + 1e-6
    assert abs(vis.mean() - full[..., -1].mean()) < 0.03


# ------------------------------------------------------ sensors without differentials
def test_batch_sensor_pages_follow_each_views_pixels():
    """Mitsuba's ``batch`` sensor (several cameras side by side on one film) gives rays
    without ray differentials. The mark pass then saw no footprint and asked for the
    finest level everywhere (2.3 M texels, 2,225 pages at a level the page table cannot
    hold, a warning) and lookups fell back to the coarsest page: 2.69 % misclassified.
    Now the mark pass takes the next pixel's ray and the render a cone of one pixel's
    angle: pages and accuracy as for the two cameras rendered alone (measured: 23,552
    texels against 18,432 + 17,408; 0.68 % against 0.29 / 0.59 %)."""
    views = {"a": {"type": "perspective", "fov": 40,
                   "to_world": T().look_at([0, 3, 5], [0, 0, 0], [0, 1, 0])},
             "b": {"type": "perspective", "fov": 40,
                   "to_world": T().look_at([5, 3, 0], [0, 0, 0], [0, 1, 0])}}
    film = {"type": "hdrfilm", "height": 32, "rfilter": {"type": "box"}}

    def load(sensor):
        d = default_scene(width=32, height=32)
        d["sensor"] = sensor
        return mi.load_dict(d)

    alone = []
    for name, v in views.items():
        integ = shadowmap(method="hard")
        vis_of(load({**v, "film": {**film, "width": 32}}), integ, spp=16)
        alone.append(integ.stats.texels_built)
    scene = load({"type": "batch", "film": {**film, "width": 64}, **views})
    integ = shadowmap(method="hard")
    with warnings.catch_warnings():
        warnings.simplefilter("error")        # no level beyond the page table
        vis = vis_of(scene, integ, spp=16)
    ref = vis_of(scene, shadowmap(method="raytraced"), spp=16)
    mis = misclassified(ref, vis)
    print(f"batch: {integ.stats.texels_built} texels (alone {alone}), misclassified {mis:.2%}")
    assert integ.stats.texels_built <= 1.5 * sum(alone)
    assert mis <= 0.015


@pytest.mark.parametrize("size", [(16, 8), (67, 45), (1, 9)])
def test_block_ordered_pixel_centres_cover_every_pixel_in_squares(size):
    """The mark pass's camera rays (``pixel_centres(blocks=True)``): every pixel centre
    of the crop, and nothing else; each run of 64 lanes an 8 x 8 square where the crop
    allows (Morton order: each 4 lanes a 2 x 2 square), the last column and row repeated
    to fill blocks a crop cuts."""
    from mi_shadowmap.light_views import PIXEL_BLOCK, pixel_centres
    w, h = size
    sensor = mi.load_dict({"type": "perspective", "film": {"type": "hdrfilm", "width": w,
                                                           "height": h}})
    rows = np.array(pixel_centres(sensor))
    got = np.array(pixel_centres(sensor, blocks=True))
    assert {tuple(c) for c in got.T} == {tuple(c) for c in rows.T}
    B = PIXEL_BLOCK
    assert got.shape[1] == -(-w // B) * -(-h // B) * B * B
    xy = np.round(got * np.array([[w], [h]]) - 0.5).astype(int)
    for start in range(0, got.shape[1], 4):           # 2 x 2 squares (clamped at edges)
        q = xy[:, start:start + 4]
        assert q[0].max() - q[0].min() <= 1 and q[1].max() - q[1].min() <= 1
    if w % B == 0 and h % B == 0:
        for start in range(0, got.shape[1], B * B):
            q = xy[:, start:start + B * B]
            assert len({tuple(c) for c in q.T}) == B * B
            assert q[0].max() - q[0].min() == B - 1 and q[1].max() - q[1].min() == B - 1


def test_pixel_ray_differentials_of_a_batch_equal_each_cameras_own():
    """The finite-difference differentials (next pixel's ray; at a sub-camera's last
    column the previous pixel's, mirrored: within 5 % of a pixel's step there) equal
    the differentials each camera gives alone, at every pixel centre of the batch."""
    from mi_shadowmap.light_views import pixel_centres, pixel_ray_differentials
    cams = [{"type": "perspective", "fov": 40, "to_world": T().look_at(o, [0, 0, 0], [0, 1, 0])}
            for o in ([0, 3, 5], [5, 3, 0])]
    batch = mi.load_dict({"type": "batch", "film": {"type": "hdrfilm", "width": 32,
                                                   "height": 8}, "a": cams[0], "b": cams[1]})
    ray = pixel_ray_differentials(batch, pixel_centres(batch))
    assert ray.has_differentials
    for k, cam in enumerate(cams):
        alone = mi.load_dict({**cam, "film": {"type": "hdrfilm", "width": 16, "height": 8}})
        own, _ = alone.sample_ray_differential(0.0, 0.5, pixel_centres(alone), mi.Point2f(0.5))
        x = np.arange(32 * 8) % 32
        cols = x // 16 == k
        last = (x[cols] % 16) == 15           # backward, mirrored: second order
        np.testing.assert_allclose(np.array(ray.d)[:, cols], np.array(own.d), atol=1e-6)
        # origins on the near plane (0.01 from the pinhole): the next pixel's, Mitsuba's o
        assert np.abs(np.array(ray.o_x)[:, cols] - np.array(own.o_x)).max() <= 1e-3
        for got, want in ((ray.d_x, own.d_x), (ray.d_y, own.d_y)):
            got, want = np.array(got)[:, cols], np.array(want)
            np.testing.assert_allclose(got[:, ~last], want[:, ~last], atol=2e-6)
            step = np.linalg.norm(want - np.array(own.d), axis=0)
            assert np.all(np.linalg.norm(got - want, axis=0) <= 0.05 * step)


@pytest.mark.parametrize("light", ["spot", "point", "directional", "area", "far_point",
                                   "cascades"])
def test_receiver_plane_depths_in_float32_match_float64(light):
    """A bound lookup meets a filter tap's ray with the receiver's plane in float32,
    relative to the receiver's own ray (:meth:`LocalView._plane_step`): at taps up to 12
    texels away (crossing onto another cube face too), on the camera's hits and on
    planes tilted up to 87 degrees from the light, the depth and cosine equal the
    float64 intersection's up to float32 rounding (a few units in the last place of the
    depth and of the step), also for a point light 1e5 away (depths from its
    ``depth_origin``), and on a directional light's virtual cascades; so does the tap's
    ray direction."""
    from mi_shadowmap.filters.common import Lookup
    from mi_shadowmap.light_views.local import LocalView
    if light == "far_point":
        scene = mi.load_file(str(SCENES / "far_point.xml"), width=48, height=48)
    else:
        scene = mi.load_dict(default_scene(width=48, height=48, spp=1, light={
            "cascades": "directional"}.get(light, light)))
    integ = shadowmap(method="pcf", virtual=True, cache_maps=False,
                      **({"cascades": 3} if light == "cascades" else {}))
    vis_of(scene, integ, spp=1)
    vmap = integ.maps[0]
    if light == "cascades":
        assert vmap.view.n_faces >= 3     # the cascades (and a catch-all face)
    si, dp_dx, dp_dy, valid = virtual.camera_hits(scene, scene.sensors()[0])
    lk = Lookup(dr.select(valid, si.p, 0.0), si.n, dp_dx, dp_dy, si, None, None)
    bound = vmap.bind(lk, valid)
    local = bound.view
    assert isinstance(local, LocalView) and local._frame is not None
    n = dr.width(si.p)
    rng = np.random.default_rng(5)
    res = bound.resolution
    uv0 = local._frame[4]
    for trial in range(3):
        off = mi.Point2f(mi.Float(rng.uniform(-12, 12, n)), mi.Float(rng.uniform(-12, 12, n)))
        uv = uv0 + off / mi.Float(res)
        # the surface normal, then random planes with |cos| to the light >= 0.05
        if trial == 0:
            nrm = mi.Vector3f(si.n)
        else:
            v = rng.normal(size=(3, n))
            nrm = dr.normalize(mi.Vector3f(*(mi.Float(x) for x in v)))
        face = local.face
        if trial == 2 and vmap.view.n_faces > 1:     # some taps on another face
            face = dr.select(mi.Float(rng.random(n)) < 0.2,
                             (local.face + 2) % vmap.view.n_faces, local.face)
        t, c = local.ray_plane(face, uv, lk.p_world, nrm, 1e-12)
        t64, c64 = local._ray_plane_f64(face, uv, lk.p_world, nrm, 1e-12)
        # the float32 path is the one taken on the bound face, also for a copy of the
        # point (mdsm's and second_depth's mi.Point3f(lk.p_world))
        t32 = local._plane_step(uv, nrm, 1e-12)[0]
        tc = local.ray_plane(face, uv, mi.Point3f(lk.p_world), nrm, 1e-12)[0]
        same = (valid & (mi.UInt32(face) == local.face)).numpy()
        assert same.sum() > 500
        for x in (t, tc):
            np.testing.assert_array_equal(x.numpy()[same], t32.numpy()[same])
        ok = (valid & bound.inside & (dr.abs(c64) >= 0.05)).numpy()
        t, t64, c, c64 = (np.asarray(x.numpy(), np.float64) for x in (t, t64, c, c64))
        t0 = np.asarray(local._frame[6].numpy(), np.float64)
        assert ok.sum() > 500
        ulp = np.spacing(np.maximum(np.abs(t64), np.abs(t0)).astype(np.float32))
        err = np.abs(t - t64)[ok]
        tol = (8.0 * ulp + 1e-5 * np.abs(t64 - t0))[ok]
        print(f"{light} trial {trial}: max |t - t64| / tolerance {np.max(err / tol):.3f}")
        assert np.all(err <= tol)
        np.testing.assert_allclose(c[ok], c64[ok], atol=2e-6)
        # the tap's ray direction (PCSS's front test for one-sided area lights)
        d = local.ray_through(face, uv)[1]
        d64 = local._ray_through_f64(face, uv)[1]
        for x, y in zip(d, d64):
            np.testing.assert_allclose(np.broadcast_to(x.numpy(), (n,))[ok],
                                       np.broadcast_to(y.numpy(), (n,))[ok], atol=2e-6)


@pytest.mark.parametrize("near", [1e-3, 0.8])
def test_footprints_start_at_the_pinhole_whatever_the_near_clip(near):
    """Mitsuba's ``perspective`` camera starts rays on its near plane and gives their
    differentials that same origin with the neighbouring pixels' directions through
    the pinhole (``light_views.differential_origins``). One pixel's footprint on a
    plane parallel to the film, ``D`` away, is ``2 D tan(fov / 2) / W`` at every pixel
    and any ``near_clip``: in the mark pass (``camera_hits``) and in the render
    (``_footprint``, differentials scaled by 1 / sqrt(spp) as Mitsuba's render does).
    From the near-plane origin it would be ``1 - near`` of that (a fifth at 0.8)."""
    from mi_shadowmap.light_views import pixel_centres
    D, W, fov, spp = 10.0, 32, 40.0, 4
    scene = mi.load_dict({
        "type": "scene",
        "sensor": {"type": "perspective", "fov": fov, "near_clip": near * D, "far_clip": 1e3,
                   "to_world": T().look_at([1, 2, 3], [1, 2, 3 - D], [0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": W, "height": W}},
        "plane": {"type": "rectangle", "to_world": T().translate([1, 2, 3 - D]).scale(50)},
        "light": {"type": "point", "position": [1, 2, 2]}})
    sensor = scene.sensors()[0]
    want = 2.0 * D * math.tan(math.radians(fov / 2)) / W
    si, dp_dx, dp_dy, valid = virtual.camera_hits(scene, sensor)
    assert np.all(valid.numpy())
    for dp in (dp_dx, dp_dy):
        np.testing.assert_allclose(np.linalg.norm(np.array(dp), axis=0), want, rtol=1e-3)
    integ = mi.load_dict({"type": "shadowmap", "method": "hard"})
    integ._first_pass(scene, sensor, spp)
    ray, _ = sensor.sample_ray_differential(0.0, 0.5, pixel_centres(sensor), mi.Point2f(0.5))
    s = 1.0 / math.sqrt(spp)         # RayDifferential3f.scale_differentials (C++ only)
    ray.o_x, ray.o_y = ray.o + (ray.o_x - ray.o) * s, ray.o + (ray.o_y - ray.o) * s
    ray.d_x, ray.d_y = ray.d + (ray.d_x - ray.d) * s, ray.d + (ray.d_y - ray.d) * s
    si = scene.ray_intersect(ray)
    for dp in integ._footprint(ray, si):
        np.testing.assert_allclose(np.linalg.norm(np.array(dp), axis=0), want, rtol=1e-3)


@pytest.mark.parametrize("camera", ["plain", "crop_and_principal_point"])
def test_pinhole_footprints_are_the_ray_differentials_hits(camera):
    """A perspective camera's footprints (``light_views.pinhole_footprint``, from the
    pinhole and one pixel's step, used by the mark pass and the render) are the points
    where the camera's own ray differentials (origins at the pinhole) meet each hit's
    tangent plane, at every pixel of a scene with spheres and tilted boxes: a finite
    difference of one pixel, not a derivative (on ground seen at grazing angles those
    differ by up to 98 %)."""
    from mi_shadowmap.light_views import (pinhole_footprint, pinhole_frame, pixel_centres,
                                          pixel_ray_differentials)
    d = default_scene(width=48, height=32)
    if camera != "plain":
        d["sensor"]["film"].update(crop_offset_x=8, crop_offset_y=4, crop_width=24,
                                   crop_height=20)
        d["sensor"].update(principal_point_offset_x=0.1, principal_point_offset_y=-0.05)
    scene = mi.load_dict(d)
    sensor = scene.sensors()[0]
    ray = pixel_ray_differentials(sensor, pixel_centres(sensor))
    si = scene.ray_intersect(ray)

    def hit(o, dd):
        return o + dd * (dr.dot(si.n, si.p - o) / dr.dot(si.n, dd))

    frame = pinhole_frame(sensor)
    got = pinhole_footprint(si.p, si.n, tuple(mi.Vector3f(*v) for v in frame))
    want = (hit(ray.o_x, ray.d_x) - si.p, hit(ray.o_y, ray.d_y) - si.p)
    valid = si.is_valid().numpy()
    assert valid.mean() > 0.5
    for g, w in zip(got, want):
        g, w = np.array(g)[:, valid], np.array(w)[:, valid]
        err = np.linalg.norm(g - w, axis=0) / np.linalg.norm(w, axis=0)
        assert np.percentile(err, 99) < 1e-4 and err.max() < 2e-4, (np.percentile(err, 99),
                                                                   err.max())


def test_pinhole_frame_reads_its_values_after_one_kernel():
    """``pinhole_frame`` evaluates the four rays' directions and the camera's transform
    in one kernel and then reads them: after a camera move it launches one kernel (two
    before: each array's ``np.array`` a ravel kernel of its own, each waited for), and
    gives the values those reads gave."""
    from mi_shadowmap.light_views import pinhole_frame
    scene = mi.load_dict(default_scene(width=48, height=32))
    sensor = scene.sensors()[0]
    params = mi.traverse(sensor)
    params["to_world"] = type(params["to_world"])(params["to_world"]) \
        @ T().translate([0.1, 0.0, 0.0]) @ T().rotate([0, 1, 0], 3.0)
    params.update()
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        dr.kernel_history()
        frame = pinhole_frame(sensor)
        jit = [k for k in dr.kernel_history() if k["type"] == dr.KernelType.JIT]
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    assert len(jit) == 1, [(k["size"], k["operation_count"]) for k in jit]
    pos = mi.Point2f(mi.Float([0.25, 0.75, 0.5, 0.5]), mi.Float([0.5, 0.5, 0.25, 0.75]))
    ray, _ = sensor.sample_ray(0.0, 0.5, pos, mi.Point2f(0.5))
    d = np.array(ray.d, dtype=np.float64)
    to_world = np.array(sensor.world_transform().matrix, dtype=np.float64).reshape(4, 4)
    fwd = to_world[:3, :3] @ np.array([0.0, 0.0, 1.0])
    fwd /= np.linalg.norm(fwd)
    unit = d / (fwd @ d)
    w, h = (int(x) for x in sensor.film().crop_size())
    want = (to_world[:3, 3], fwd, (unit[:, 1] - unit[:, 0]) / (0.5 * w),
            (unit[:, 3] - unit[:, 2]) / (0.5 * h))
    assert frame == tuple(tuple(float(x) for x in v) for v in want)


def test_view_transforms_are_converted_once_per_view():
    """A light view's transforms as numpy (``light_matrix``, its inverse
    ``world_matrix``) and as opaque JIT transforms (``opaque_light_from_world``,
    ``opaque_world_from_light``) are computed once per view object (each lookup, mark and
    page cast traced converted them again: 8-20 us a call, 18-26 calls a moved frame),
    read-only, equal to a fresh conversion, and forgotten with the view."""
    import gc
    from mi_shadowmap.light_views import base as lv_base
    scene = mi.load_file(str(SCENES / "large_world.xml"), width=16, height=16)
    integ = shadowmap(method="hard")
    vis_of(scene, integ, spp=1)
    view = integ.maps[0].view
    fresh = np.array(view.light_from_world.matrix, dtype=np.float64)
    L = lv_base.light_matrix(view)
    assert L is lv_base.light_matrix(view) and np.array_equal(L, fresh)
    W = lv_base.world_matrix(view)
    assert W is lv_base.world_matrix(view) and np.array_equal(W, np.linalg.inv(fresh))
    with pytest.raises(ValueError):
        L[0, 0] = 1.0                      # shared: not writable
    for get, t in ((lv_base.opaque_light_from_world, view.light_from_world),
                   (lv_base.opaque_world_from_light, view.light_from_world.inverse())):
        got = get(view)
        assert got is get(view)
        assert np.array_equal(np.array(got.matrix).reshape(4, 4),
                              np.array(mi.Transform4f(t).matrix).reshape(4, 4))
    other = __import__("dataclasses").replace(view)     # an equal view: its own entry
    assert lv_base.light_matrix(other) is not L
    n = len(lv_base._VIEW_MEMO)
    del other
    gc.collect()
    assert len(lv_base._VIEW_MEMO) == n - 1


def test_a_moved_frame_reads_the_camera_state_once_for_its_marks(monkeypatch):
    """The integrator's first pass reads the camera's state (``camera.camera_state``:
    every camera parameter) once and gives it to the page planner, whose mark pass's
    camera hits take it (``camera_frame`` with ``state``), and to the render's own
    pinhole frame: a moved frame reads it once (three times, then twice: the planner and
    the pinhole frame each read it, about 0.1 ms of a 256^2 far_point frame), and marks
    what it marked before (the frame kept per state is the same object)."""
    from mi_shadowmap import integrator as integrator_module
    from mi_shadowmap.virtual import camera
    virtual.PAGE_CACHE.clear()
    scene = mi.load_file(str(SCENES / "large_world.xml"), width=32, height=32)
    integ = shadowmap(method="hard")
    vis_of(scene, integ, spp=1)
    reads = []
    state = camera.camera_state
    monkeypatch.setattr(camera, "camera_state", lambda s: reads.append(1) or state(s))
    monkeypatch.setattr(planner, "camera_state", camera.camera_state)
    monkeypatch.setattr(integrator_module, "camera_state", camera.camera_state)
    params = mi.traverse(scene.sensors()[0])
    params["to_world"] = type(params["to_world"])(params["to_world"]) \
        @ T().translate([0.2, 0.0, 0.0])
    params.update()
    vis_of(scene, integ, spp=1)
    assert integ.stats["pages_marked"] > 0 and len(reads) == 1, len(reads)
    frame = camera.camera_frame(scene.sensors()[0])
    assert frame is camera.camera_frame(scene.sensors()[0], state(scene.sensors()[0]))


def test_a_moves_build_waits_once_for_its_cast_and_fills(monkeypatch):
    """A camera move's new pages: their tiles' cast and the fills of their other tiles
    (``store.fill_new_pages``) are both launched before the host reads the cast's depths
    for the tiles' minima (``store.read_minima``), so it waits once for the two, not
    once for the cast and again for the fills; the pages are those of the cast's minima
    read at once (``cast_tiles`` with ``minima`` True, as ``PageStore.build``)."""
    virtual.PAGE_CACHE.clear()
    scene = mi.load_file(str(SCENES / "large_world.xml"), width=64, height=64)
    integ = shadowmap(method="hard")
    vis_of(scene, integ, spp=1)
    params = mi.traverse(scene.sensors()[0])
    params["to_world"] = type(params["to_world"])(params["to_world"]) \
        @ T().translate([0.4, 0.0, 0.0]) @ T().rotate([0, 1, 0], 4.0)
    params.update()
    launched = []
    read = page_store.read_minima

    def spy(jobs):
        launched.append([k["size"] for k in dr.kernel_history()
                         if k["type"] == dr.KernelType.JIT])
        return read(jobs)
    monkeypatch.setattr(planner, "read_minima", spy)
    fills = []
    fill = page_store.fill_new_pages
    monkeypatch.setattr(planner, "fill_new_pages",
                        lambda jobs: fills.append(sum(
                            int(j.new_fine.sum()) for j in jobs if j.keys is not None))
                        or fill(jobs))
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        dr.kernel_history()
        vis_of(scene, integ, spp=1)
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    assert fills[0] > 0 and len(launched) == 1
    # the cast (its tiles' texels) and the fill's two kernels (the new pages' texels)
    # already launched when the depths are read
    assert launched[0][-2:] == [fills[0] * 32 * 32] * 2, launched
    # the same pages cast into two new stores, the minima read at once and later
    st = integ.maps[0].store
    keys = st._index()[0]
    minima = []
    for at_once in (True, False):
        new = page_store.PageStore(st.layout, st.layers)
        job = new.plan_build(keys)
        page_store.cast_tiles(scene, [job], minima=at_once)
        assert (job.minima is None) != at_once
        if not at_once:
            page_store.read_minima([job])
        minima.append(job.minima)
    assert len(minima[0]) == len(keys) * st.layout.tiles_per_side ** 2
    assert np.isfinite(minima[0]).any()
    assert np.array_equal(minima[0], minima[1])


def test_environment_regions_moves_compile_nothing_and_share_one_mark_kernel():
    """An environment's 16 regions are marked by one kernel code (their values opaque:
    a region's mark kernel with literals compiled per region, and a kernel marking all
    16 at once held 6,400 operations and took 44 s to compile with ``pcss``'s margin);
    camera moves rebuild at most a quarter of the first frame's texels and, after the
    first, compile no kernel."""
    from conftest import SCENE_FILES
    virtual.PAGE_CACHE.clear()
    path = [p for p in SCENE_FILES if p.stem == "sky_sun"][0]
    scene = mi.load_file(str(path), width=32, height=32)
    integ = shadowmap(method="pcss")
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        dr.kernel_history()
        vis_of(scene, integ, spp=1)
        jit = [k for k in dr.kernel_history() if k["type"] == dr.KernelType.JIT]
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    first = integ.stats["texels_built"]
    assert first > 0
    # the first render's kernels: the 16 regions' marks share their code (measured: 72
    # kernels, 20 distinct; 35 distinct with the regions' values as literals)
    distinct = len({k["hash"] for k in jit})
    print("kernels", len(jit), "distinct", distinct)
    assert distinct <= 27
    assert max(k["operation_count"] for k in jit) < 4000
    built = []
    compiled = _moves(scene, integ, 3, lambda: built.append(integ.stats["texels_built"]))
    print(f"first frame {first} texels; moves: built {built}, kernels compiled {compiled}")
    assert all(b <= 0.25 * first for b in built)
    assert compiled[1:] == [0, 0], "moving the camera compiled a new kernel"


@pytest.mark.parametrize("light", ["point", "spot", "directional"])
def test_to_numpy_of_a_level_equals_a_full_map_of_its_resolution(light):
    """``VirtualShadowMap.to_numpy(level=k)`` (there was no ``to_numpy`` on the default
    maps: an AttributeError) puts the ray-cast tiles of level k in place and NaN
    elsewhere; where cast they equal a full map of that level's resolution (measured:
    relative difference <= 1.4e-6, the same misses), and the coarsest level is complete.
    A level too large for one array is refused by name."""
    scene = mi.load_dict(default_scene(width=64, height=64, light=light))
    integ = shadowmap(method="hard")
    vis_of(scene, integ)
    vmap = integ.maps[0]
    assert isinstance(vmap, virtual.VirtualShadowMap)
    levels = np.unique(vmap.page_records()["level"])
    coarsest = vmap.to_numpy()
    assert not np.isnan(coarsest).any()
    for level in (int(levels[0]), int(levels[-1])):
        got = vmap.to_numpy(level=level)
        res = got.shape[-1]
        full = shadowmap(method="hard", virtual=False, resolution=res)
        vis_of(scene, full)
        want = full.maps[0].to_numpy()
        cast = ~np.isnan(got)
        assert cast.any() and got.shape == want.shape
        assert np.array_equal(np.isinf(got[cast]), np.isinf(want[cast]))
        fin = cast & np.isfinite(want)
        # a texel whose ray grazes a silhouette (a neighbour's depth 10 % off) hits where
        # the last bits of its direction put it: 1.3e-5 at one texel of the spot's level
        # 13 (depths 4.58 beside 6.31)
        pad = np.pad(want, ((0, 0), (1, 1), (1, 1)), mode="edge")
        jump = np.zeros(want.shape, bool)
        for dj, di in ((0, 1), (2, 1), (1, 0), (1, 2)):
            nb = pad[:, dj:dj + want.shape[1], di:di + want.shape[2]]
            with np.errstate(invalid="ignore"):
                jump |= ~(np.abs(nb - want) <= 0.1 * np.abs(want))
        np.testing.assert_allclose(got[fin & ~jump], want[fin & ~jump], rtol=1e-5)
        np.testing.assert_allclose(got[fin & jump], want[fin & jump], rtol=1e-4)
    with pytest.raises(ValueError, match="more than 2\\^26"):
        vmap.to_numpy(level=0)


@pytest.mark.parametrize("width", [1e4, 1e6])
def test_a_world_a_million_units_wide_keeps_one_unit_shadows(width):
    """Posts 2 units tall on a ground ``width`` units wide under a 14-degree sun, at
    defaults: the virtual map's finest level is ``SCENE_TEXELS`` texels across the
    scene, so the posts' shadows keep their shape at 1e6 (with 2^20 texels, about 1 unit
    a texel there: 0.96 % misclassified at 128^2; 0.34 % with 2^24, as with any finer
    level); the texels built stay within the issue's 8 per pixel."""
    from mi_shadowmap.scenes import camera
    T = mi.ScalarTransform4f
    el = math.radians(14.0)
    d = {"type": "scene", "sensor": camera([0, 1.7, 12], [0, 0.3, 0], 128, 128, 4),
         "ground": {"type": "rectangle", "to_world": T().rotate([1, 0, 0], -90).scale(width / 2),
                    "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.6}}},
         "sun": {"type": "directional", "irradiance": {"type": "rgb", "value": 3.0},
                 "direction": [math.cos(el) * 0.6, -math.sin(el), -math.cos(el) * 0.8]}}
    for i, x in enumerate([-3, 0, 3]):
        d[f"post{i}"] = {"type": "cube", "bsdf": {"type": "diffuse"},
                         "to_world": T().translate([x, 1.0, -2 * i]).scale([0.3, 1.0, 0.3])}
    scene = mi.load_dict(d)
    ref = vis_of(scene, shadowmap(method="raytraced"))
    integ = shadowmap(method="hard")
    v = vis_of(scene, integ)
    mis = float(np.mean((v < 0.5) != (ref < 0.5)))
    print(f"{width:g}: misclassified {mis:.3%}, {integ.stats['texels_built'] / 128 ** 2:.1f} "
          f"texels per pixel, res0 {integ.maps[0].resolution}")
    assert np.mean(ref < 0.5) > 0.2
    assert mis <= 0.005
    assert integ.stats["texels_built"] <= 8 * 128 * 128


@pytest.mark.parametrize("batch", [False, True])
def test_a_thin_lens_marks_what_its_whole_lens_sees(batch):
    """A blurred post 0.8 in front of a thin lens of radius 0.8 hides a strip of ground
    from the lens centre, which the rest of the lens sees. Marked from the lens centre
    alone, that strip's lookups fell to coarse levels: ``hard`` misclassified 1.49 %
    (RMSE 0.060) against 0.04 % (0.0046) with 2048^2 full maps (96^2, 16 spp); marked
    through 3 x 3 points of the lens, 0.18 % (0.0117). The same for a ``batch`` of two
    such lenses (RMSE 0.060 before, 0.020 now)."""
    o, t = np.array([0.2, 3.5, 4.9]), np.array([0.25, 0.25, 0.0])
    d = (t - o) / np.linalg.norm(t - o)
    up = np.array([0.0, 1.0, 0.0]) - d * d[1]
    up /= np.linalg.norm(up)
    c = o + 0.8 * d
    diffuse = {"type": "diffuse"}
    lens = {"type": "thinlens", "fov": 40.0, "aperture_radius": 0.8, "focus_distance": 5.9,
            "to_world": T().look_at(origin=list(o), target=list(t), up=[0, 1, 0])}
    film = {"type": "hdrfilm", "width": 64, "height": 64, "rfilter": {"type": "box"}}
    cam = {**lens, "film": film} if not batch else {
        "type": "batch", "a": lens, "b": dict(lens), "film": {**film, "width": 96, "height": 48}}
    scene = mi.load_dict({
        "type": "scene",
        "cam": cam,
        "ground": {"type": "rectangle", "to_world": T().scale(4).rotate([1, 0, 0], -90),
                   "bsdf": diffuse},
        "ball": {"type": "sphere", "center": [-0.85, 0.65, -0.6], "radius": 0.65,
                 "bsdf": diffuse},
        "box": {"type": "cube", "bsdf": diffuse, "to_world":
                T().translate([0.85, 0.5, -0.5]).rotate([0, 1, 0], 30).scale(0.5)},
        "post": {"type": "cylinder", "p0": list(c - up), "p1": list(c + up), "radius": 0.2,
                 "bsdf": diffuse},
        "light": {"type": "spot", "intensity": 120.0, "cutoff_angle": 35.0, "beam_width": 28.0,
                  "to_world": T().look_at(origin=[-2.4, 4.0, -3.4], target=[0.2, 0, 0.3],
                                          up=[0, 1, 0])}})
    ref = vis_of(scene, shadowmap(method="raytraced"), spp=8)
    virt = vis_of(scene, shadowmap(method="hard"), spp=8)
    full = vis_of(scene, shadowmap(method="hard", virtual=False, resolution=2048), spp=8)
    rmse = lambda a: float(np.sqrt(np.mean((a - ref) ** 2)))   # noqa: E731
    print(rmse(virt), rmse(full))
    assert rmse(virt) < 3.5 * rmse(full)


def test_finer_lod_bias_is_not_worse_than_the_default():
    """A negative ``lod_bias`` reads finer levels; the mark pass (one ray per pixel
    centre) must build the pages a pixel's off-centre samples read there. It marked one
    texel around the centre whatever the level, so at ``lod_bias`` -4 (texels 1/32-1/16
    of a pixel, allowed with pages of 32^2) many samples found no page and walked to
    coarse levels (the built-in scene under a spot, 64^2: ``bilinear`` visibility RMSE
    0.039 against 0.031 at the default -0.5, now 0.010; -6..-8 rendered the coarsest
    level alone). Marks now reach half a pixel at the level chosen."""
    scene = mi.load_dict(default_scene(width=64, height=64, spp=4, light="spot"))
    ref = reference("finer-lod-spot", scene)
    rmse = {}
    for lb in (-0.5, -4.0):
        vis = vis_of(scene, shadowmap(method="bilinear", lod_bias=lb))
        rmse[lb] = float(np.sqrt(np.mean((vis - ref) ** 2)))
    print(rmse)
    assert rmse[-4.0] <= rmse[-0.5]


def test_lod_bias_finer_than_the_pages_hold_is_an_error():
    """Below ``1 - log2(page_size)`` a pixel spans more than ``page_size`` texels of its
    level, beyond the pages the mark pass builds around its centre; with the automatic
    (virtual) resolution that is refused, naming ``lod_bias`` and ``page_size``; with a
    ``resolution`` given, lookups read level 0 where the footprint is that fine."""
    with pytest.raises(OptionError, match="lod_bias.*page_size = 32.*-4"):
        parse_options({"method": "hard", "lod_bias": -8.0})
    with pytest.raises(OptionError, match="lod_bias"):
        parse_options({"method": "pcf", "virtual": True, "lod_bias": -3.0, "page_size": 8})
    assert parse_options({"method": "hard", "lod_bias": -8.0, "page_size": 512}).lod_bias == -8
    assert parse_options({"method": "hard", "lod_bias": -8.0, "virtual": True,
                          "resolution": 256}).lod_bias == -8
    assert parse_options({"method": "hard", "lod_bias": -8.0, "virtual": False}).lod_bias == -8


def test_a_moved_camera_finds_each_lights_pages_once(monkeypatch):
    """A camera move's plan finds each light's pages and tile masks once
    (:func:`marks.tile_pages`, kept in ``plan_memo``) and the budget check and the build
    take them from there: two page counts of the same tiles (``_n_pages``) and a
    ``tile_pages`` were 0.31 ms of a large_world camera move's host time. The same image
    as a fresh integrator's at the moved pose."""
    virtual.PAGE_CACHE.clear()
    scene = many_lights_scene(1, 1)
    integ = shadowmap(method="hard")
    mi.render(scene, integrator=integ, spp=1)
    params = mi.traverse(scene)
    params["sensor.to_world"] = T().look_at(origin=[0.3, 1.3, 3.4], target=[0, 0.5, 0],
                                            up=[0, 1, 0])
    params.update()
    calls = []
    real_tile_pages, real_n_pages = planner.tile_pages, planner._n_pages
    monkeypatch.setattr(planner, "tile_pages",
                        lambda *a: calls.append("tile_pages") or real_tile_pages(*a))
    monkeypatch.setattr(planner, "_n_pages", lambda *a: calls.append("n") or real_n_pages(*a))
    moved = np.asarray(mi.render(scene, integrator=integ, spp=1))
    assert calls == ["tile_pages", "tile_pages"]       # one per light, no page count
    monkeypatch.undo()
    virtual.PAGE_CACHE.clear()
    fresh = np.asarray(mi.render(scene, integrator=shadowmap(method="hard"), spp=1))
    assert np.array_equal(moved, fresh)


def test_a_still_camera_plans_from_the_last_render(monkeypatch):
    """A still camera's frame takes its pages' plan from the last render: the planner's
    page counts (``_n_pages``: sorts of every marked tile) and each emitter's
    ``mi.traverse`` (``_dark``) ran every frame, 1.3 ms more host time a room_two_points
    frame than before them (0.2 ms an emitter). A changed intensity is still seen."""
    virtual.PAGE_CACHE.clear()
    scene = many_lights_scene(1, 1)
    integ = shadowmap(method="hard")
    mi.render(scene, integrator=integ, spp=1)
    first = np.asarray(mi.render(scene, integrator=integ, spp=1))
    calls = []
    real_n_pages, real_traverse = planner._n_pages, mi.traverse
    monkeypatch.setattr(planner, "_n_pages", lambda *a: calls.append("n") or real_n_pages(*a))
    monkeypatch.setattr(mi, "traverse", lambda obj, *a, **k: (
        calls.append("traverse") if isinstance(obj, mi.Emitter) else None)
        or real_traverse(obj, *a, **k))
    again = np.asarray(mi.render(scene, integrator=integ, spp=1))
    assert calls == [] and np.array_equal(first, again)
    monkeypatch.undo()
    params = mi.traverse(scene)
    light = next(e for e in scene.emitters() if e.class_name() == "PointLight")
    store = next(m.store for m, e in zip(integ.maps, scene.emitters()) if e is light)
    assert store.dark_memo[0] == id(light) and not planner._dark(light, store)
    for value, dark in ((0.0, True), (2.0, False)):
        params["pl0.intensity.value"] = value
        params.update()
        assert planner._dark(light, store) is dark


@pytest.mark.parametrize("fold", [False, True])
@pytest.mark.parametrize("margin", [0.0, 2.0, 5.5, 9.0, 12.0, 40.0])
def test_mark_blocks_give_the_candidate_tiles(margin, fold):
    """The mark pass dedupes one block of tiles per point (:func:`marks.mark_blocks`,
    expanded on the host by :func:`marks.expand_blocks`) instead of every candidate
    tile of :func:`marks.mark_candidates`: the same tiles, for points anywhere on a
    face (its edges too: blocks clipped at 0 and at the level's last tile), at every
    level, for kernels of every width (2 to 5 tiles a side), with and without the
    receiver biases' spread (``MAX_SPREAD`` texels around a capped point). With
    ``fold`` (:func:`marks.shape_bits`) the blocks' shapes ride in their keys: one list,
    not ``per_axis^2``."""
    from mi_shadowmap.filters.common import BiasReach
    scene = mi.load_dict({"type": "scene", "sensor": {
        "type": "perspective", "film": {"type": "hdrfilm", "width": 8, "height": 8}},
        "ground": {"type": "rectangle"},
        "sun": {"type": "directional", "direction": [0.2, 0.1, -1]}})
    integ = mi.load_dict({"type": "shadowmap", "method": "hard"})
    mi.render(scene, integrator=integ, spp=1)
    lay = integ.maps[0].layout
    for reach in (None, BiasReach.of(integ.opts)):
        marker = marks.Marker(lay, -0.5, reach=reach)
        rng = np.random.default_rng(5)
        n = 4000
        uv = rng.random((2, n))
        uv[:, :400] = rng.choice([0.0, 1e-9, 1.0 - 1e-9, 1.0], (2, 400))   # at the edges
        level = rng.integers(0, lay.coarsest + 1, n)
        spread = np.where(rng.random((2, n)) < 0.5, 0.0, rng.random((2, n)) * 6.0)
        points = (mi.UInt32(rng.integers(0, lay.view.n_faces, n)), mi.Point2d(uv[0], uv[1]),
                  mi.Bool(rng.random(n) < 0.9), mi.UInt32(level),
                  mi.Point2f(spread[0], spread[1]))
        keys, oks = marks.mark_candidates(marker, None, None, None, None, margin=margin,
                                          points=points)
        want = np.unique(np.concatenate([k.numpy()[ok.numpy()] for k, ok in zip(keys, oks)]))
        per_axis = marks.block_axis(marker, margin)
        bits = marks.shape_bits(lay, per_axis) if fold else None
        assert (bits is not None) == fold
        bkeys, boks = marks.mark_blocks(marker, points, margin=margin, bits=bits)
        assert len(bkeys) == (1 if fold else per_axis ** 2) and per_axis > 1
        found = [k.numpy()[ok.numpy()] for k, ok in zip(bkeys, boks)]
        got = np.unique(marks.expand_blocks(found, per_axis, bits))
        assert len(want) > 100 and np.array_equal(got, want)
        # painted per face and level (block_tiles): the same tiles, sorted and distinct
        painted = marks.block_tiles(found, per_axis, bits)
        assert painted.dtype == np.uint64 and np.array_equal(painted, want)


@pytest.mark.parametrize("fold", [False, True])
def test_block_tiles_are_every_tile_of_the_blocks(fold):
    """:func:`marks.block_tiles` (blocks painted into a grid per face and level, not
    expanded) gives every tile of every block, sorted and distinct, as a loop over the
    blocks' tiles does: blocks of every shape up to 9 x 9 tiles, overlapping (many points
    mark nearly the same block), at the top of the faces' and levels' bits and at tile 0,
    on many faces and levels; blocks scattered far apart on one level (its grid would be
    mostly empty: expanded and sorted instead) and small blocks (the same); no block."""
    rng = np.random.default_rng(11)
    for per_axis, n, spread in [(9, 3000, 60), (5, 2000, 1 << 20), (3, 500, 40),
                                (2, 800, 30), (7, 1, 10), (4, 0, 10)]:
        bits = max(int(per_axis - 1).bit_length(), 1)
        top = 27 - bits
        face = rng.integers(0, 31, n).astype(np.uint64)
        level = rng.choice([0, 3, 30], n).astype(np.uint64)
        x = rng.integers(0, spread, n)
        y = rng.integers(0, spread, n)
        x[:n // 10] = 0
        # face 31, level 31: near the last tiles a key can hold
        face[n // 10:n // 5] = level[n // 10:n // 5] = 31
        x[n // 10:n // 5] = (1 << top) - per_axis - rng.integers(0, 9, n // 5 - n // 10)
        y[n // 10:n // 5] = (1 << top) - per_axis - rng.integers(0, 9, n // 5 - n // 10)
        w = rng.integers(1, per_axis + 1, n)
        h = rng.integers(1, per_axis + 1, n)
        want = np.array(sorted({int(layout.page_key(int(f), int(lv), a + i, b + j))
                                for f, lv, a, b, ww, hh in zip(face, level, x, y, w, h)
                                for i in range(ww) for j in range(hh)}), np.uint64)
        if fold:
            found = [layout.page_key(face, level, (x | ((w - 1) << top)).astype(np.uint64),
                                     (y | ((h - 1) << top)).astype(np.uint64))]
        else:
            c = (w - 1) + (h - 1) * per_axis
            found = [layout.page_key(face[c == k], level[c == k], x[c == k].astype(np.uint64),
                                     y[c == k].astype(np.uint64))
                     for k in range(per_axis * per_axis)]
        got = marks.block_tiles(found, per_axis, bits if fold else None)
        assert got.dtype == np.uint64 and np.array_equal(got, want)


def test_dilate_tiles_adds_every_tile_within_the_margin_inside_its_level():
    """:func:`marks.dilate_tiles` (vectorised over its offsets): each tile and those
    within ``ceil((margin + 1) / tile_size)`` tiles of it on its own level, clipped at the
    level's grid (0 and its last tile, whose grid a coarse level's single page bounds),
    sorted and distinct, as a loop over tiles and offsets gives them."""
    class View:
        n_faces = 6
    rng = np.random.default_rng(8)
    for res0, P, margin in [(1 << 12, 32, 0.0), (1 << 12, 32, 9.5), (1 << 20, 32, 34.0),
                            (256, 8, 3.0), (1 << 10, 64, 20.0)]:
        lay = layout.VirtualLayout(View(), P, res0, 0.0)
        n = 300
        lev = rng.integers(0, lay.coarsest + 1, n)
        side = np.maximum(lay.pages_per_side(0) >> lev, 1) * lay.tiles_per_side
        tx = (rng.random(n) * side).astype(np.int64)
        ty = np.where(rng.random(n) < 0.3, side - 1, (rng.random(n) * side).astype(np.int64))
        tx[:40] = 0                                           # at the grid's edges
        face = rng.integers(0, 6, n)
        keys = layout.page_key(face.astype(np.uint64), lev.astype(np.uint64),
                               tx.astype(np.uint64), ty.astype(np.uint64))
        r = int(np.ceil((margin + 1.0) / lay.tile_size))
        want = {(int(f), int(lv), x, y)
                for f, lv, a, b, s in zip(face, lev, tx, ty, side)
                for x in range(a - r, a + r + 1) for y in range(b - r, b + r + 1)
                if 0 <= x < s and 0 <= y < s}
        want = np.sort(np.array([int(layout.page_key(*t)) for t in want], np.uint64))
        got = marks.dilate_tiles(keys, lay, margin)
        assert got.dtype == np.uint64 and np.array_equal(got, want)
    assert len(marks.dilate_tiles(np.zeros(0, np.uint64), lay, 2.0)) == 0


def test_dilate_tiles_takes_tile_keys_of_any_integer_dtype():
    """:func:`marks.dilate_tiles` reads the face and level bits of its keys with a uint64
    mask: int64 keys (what ``np.array`` of Python ints gives, and what the loop over
    offsets it replaced and the other host helpers -- ``key_fields``, ``tile_pages``,
    ``expand_blocks`` -- accept) give the same tiles as uint64 ones, not a TypeError."""
    class View:
        n_faces = 6
    lay = layout.VirtualLayout(View(), 32, 1 << 10, 0.0)
    keys = layout.page_key(np.array([0, 5, 3], np.uint64), np.array([0, 1, lay.coarsest],
                                                                    np.uint64),
                           np.array([0, 40, 0], np.uint64), np.array([7, 63, 1], np.uint64))
    want = marks.dilate_tiles(keys, lay, 9.0)
    assert len(want) > 3
    for given in (keys.astype(np.int64), [int(k) for k in keys]):
        got = marks.dilate_tiles(given, lay, 9.0)
        assert got.dtype == np.uint64 and np.array_equal(got, want)
    assert marks.dilate_tiles(np.zeros(0, np.int64), lay, 9.0).dtype == np.uint64


def test_dilate_tiles_of_a_wide_margin_holds_a_bounded_grid():
    """:func:`marks.dilate_tiles` forms its (keys x offsets) grid in chunks of at most
    ``DILATE_CHUNK`` pairs: a ``pcss`` with ``max_kernel = 4096`` (margin 2050 texels,
    515^2 offsets) held the whole grid, 2.4 GB for 300 coarse-level tiles (a 256^2
    cbox_area frame, 506 tiles: 4.4 GB resident against 1.2 GB for the loop it replaced).
    Peak traced memory for 200 tiles at margin 1026 (259^2 offsets) stays below 160 MiB
    (410 MiB as one grid), with the same tiles as a single grid gives."""
    import tracemalloc

    class View:
        n_faces = 6
    lay = layout.VirtualLayout(View(), 32, 1 << 13, 0.0)
    rng = np.random.default_rng(3)
    n = 200
    lev = rng.integers(2, lay.coarsest + 1, n)
    side = np.maximum(lay.pages_per_side(0) >> lev, 1) * lay.tiles_per_side
    keys = layout.page_key(rng.integers(0, 6, n).astype(np.uint64), lev.astype(np.uint64),
                           (rng.random(n) * side).astype(np.uint64),
                           (rng.random(n) * side).astype(np.uint64))
    tracemalloc.start()
    try:
        got = marks.dilate_tiles(keys, lay, 1026.0)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 160 * 2 ** 20, peak / 2 ** 20
    # the same tiles, tile by tile (each key's square clipped to its level's grid)
    r = int(np.ceil(1027.0 / lay.tile_size))
    f, lv, tx, ty = (a.astype(np.int64) for a in layout.key_fields(keys))
    want = []
    for k in range(n):
        xs = np.arange(max(tx[k] - r, 0), min(tx[k] + r, side[k] - 1) + 1)
        ys = np.arange(max(ty[k] - r, 0), min(ty[k] + r, side[k] - 1) + 1)
        gx, gy = np.meshgrid(xs, ys)
        want.append(layout.page_key(np.uint64(f[k]), np.uint64(lv[k]),
                                    gx.reshape(-1).astype(np.uint64),
                                    gy.reshape(-1).astype(np.uint64)))
    assert np.array_equal(got, np.unique(np.concatenate(want)))


def test_tile_pages_gives_each_page_of_the_tiles_with_its_tile_mask():
    """:func:`marks.tile_pages` (a sort of the pages' keys and a reduction over their
    runs): the distinct pages of tile keys, sorted, each with the bits of its tiles
    (``tx + ty * tiles_per_side`` within the page), as a loop over the tiles gives them;
    for sorted and unsorted tiles, repeated ones, every face and level, and none."""
    class View:
        n_faces = 6
    rng = np.random.default_rng(11)
    for res0, P in [(1 << 12, 32), (1 << 20, 32), (256, 8), (1 << 10, 64)]:
        lay = layout.VirtualLayout(View(), P, res0, 0.0)
        S = lay.tiles_per_side
        n = 2000
        lev = rng.integers(0, lay.coarsest + 1, n)
        side = np.maximum(lay.pages_per_side(0) >> lev, 1) * S
        # clustered (most pages hold several tiles) and anywhere on the level
        near = rng.random(n) < 0.8
        tx = np.where(near, rng.integers(0, 3 * S, n) % side, (rng.random(n) * side)
                      .astype(np.int64))
        ty = np.where(near, rng.integers(0, 3 * S, n) % side, (rng.random(n) * side)
                      .astype(np.int64))
        face = rng.integers(0, 6, n)
        keys = layout.page_key(face.astype(np.uint64), lev.astype(np.uint64),
                               tx.astype(np.uint64), ty.astype(np.uint64))
        want = {}
        for f, lv, x, y in zip(face, lev, tx, ty):
            k = int(layout.page_key(int(f), int(lv), int(x) // S, int(y) // S))
            want[k] = want.get(k, 0) | (1 << (int(x) % S + (int(y) % S) * S))
        pages = np.array(sorted(want), np.uint64)
        masks = np.array([want[int(k)] for k in pages], np.int64)
        for tiles in (keys, np.sort(keys), np.unique(keys)):
            got_pages, got_masks = marks.tile_pages(tiles, lay)
            assert got_pages.dtype == np.uint64 and got_masks.dtype == np.int64
            assert np.array_equal(got_pages, pages) and np.array_equal(got_masks, masks)
        assert S == 1 or len(pages) < len(np.unique(keys))     # pages of several tiles
    got_pages, got_masks = marks.tile_pages(np.zeros(0, np.uint64), lay)
    assert len(got_pages) == 0 and len(got_masks) == 0 and got_masks.dtype == np.int64


def test_share_pages_splits_what_is_left_evenly_after_needs_and_held_pages():
    """``planner.share_pages`` (docstring): everything fits -> each map gets its need, then
    the slots it holds already, then the rest evenly; it does not -> the maps below a
    common level get their need, the others that level. Giving one light all that was
    left survived every test (the renders' shares are not checked)."""
    share = planner.share_pages
    assert share(100, [5, 5, 5], [10, 20, 10], [0, 0, 0]) == [30, 40, 30]
    assert share(101, [5, 5], [10, 10], [0, 0]) == [51, 50]
    assert share(100, [5, 5], [10, 10], [40, 0]) == [65, 35]    # held first, then even
    assert share(30, [5, 5], [40, 40], [0, 0]) == [15, 15]      # degrades both alike
    assert share(30, [5, 5], [8, 40], [0, 0]) == [8, 22]        # the small need is met
    for total, least, need, held in [(100, [5, 5, 5], [10, 20, 10], [0, 0, 0]),
                                     (30, [5, 5], [40, 40], [0, 0]), (7, [3, 3], [9, 9], [9, 0])]:
        out = share(total, least, need, held)
        assert sum(out) == total and all(o >= lo for o, lo in zip(out, least))


def test_a_shrunk_store_frees_every_slot_it_does_not_use():
    """``PageStore.shrink`` after an eviction: every slot below ``next_slot`` is reserved
    (the empty page, the coarsest pages), a page's, or free -- a slot kept out of the
    free list is lost to every later build (keeping one survived every test: the
    budget tests' shrinks leave no holes)."""
    virtual.PAGE_CACHE.clear()
    scene = many_lights_scene(1, 1)
    integ = shadowmap(method="hard", cache_maps=False)
    vis_of(scene, integ, spp=1)
    st = integ.maps[0].store
    fixed = 1 + st.layout.view.n_faces
    fine = int((st._slot_of >= fixed).sum())
    assert fine >= 4, fine
    assert st.evict(np.zeros(0, np.uint64), fine // 2) == fine // 2
    st._grow(st.next_slot + 8)           # room above next_slot, so that shrink moves
    st.shrink(st.next_slot)
    owned = sorted(set(st._slot_of.tolist()) | set(st.free) | set(range(fixed)))
    assert owned == list(range(st.next_slot))
    assert len(st.free) == st.next_slot - fixed - int((st._slot_of >= fixed).sum()) > 0


def test_a_build_keeps_every_keys_slot_and_a_lookup_is_kept_until_pages_change():
    """A camera move's pages: the planner takes their slots from the build
    (``PageStore.built_slots``), not from a lookup after it, and the build reuses the
    planner's lookup of the same keys where nothing was evicted in between
    (``PageStore.lookup`` keeps its last answer while the pages are the same): both
    must be what a fresh lookup finds, and a lookup after the pages changed must not
    return the kept answer."""
    virtual.PAGE_CACHE.clear()
    scene = mi.load_file(str(SCENES / "room_two_points.xml"), width=64, height=64)
    integ = shadowmap(method="hard")
    vis_of(scene, integ, spp=1)
    params = mi.traverse(scene.sensors()[0])
    params["to_world"] = type(params["to_world"])(params["to_world"]) @ T().translate([0.3, 0, 0])
    params.update()
    vis_of(scene, integ, spp=1)
    for vmap in integ.maps:
        st = vmap.store
        keys, slots = st.built_slots
        needed, frame_slots, _ = st.settled[3:6]
        assert keys is needed and np.array_equal(frame_slots, slots)
        st._sorted = st._looked = None            # a fresh lookup: the same slots
        present, again = st.lookup(keys)
        assert present.all() and np.array_equal(again, slots)
        assert st.lookup(keys)[1] is again        # kept for the same keys ...
        victim = keys[np.flatnonzero(slots > st.layout.view.n_faces)[0]]
        st.evict(keys[keys != victim], 1 << 30)
        present, after = st.lookup(keys)          # ... not once the pages changed
        assert after is not again and (~present).sum() == 1
        assert not present[keys == victim][0]


def test_two_lights_cast_their_tiles_in_one_kernel_as_each_alone(monkeypatch):
    """A camera move's tiles of every light (``store.cast_tiles``): room_two_points' two
    point lights in one kernel (``first_hit`` traced once, not once per light), and their
    new pages' other tiles filled in one pair of kernels (``store.fill_new_pages``, not
    ``_fill_from_coarsest`` per light); their pages, images and stats bit-identical to
    each light's tiles cast and filled alone, and moves after the first compile nothing
    (the kernels take each light's lane range from opaque offsets)."""
    calls, fills = [], []
    first_hit = page_store.first_hit
    monkeypatch.setattr(page_store, "first_hit",
                        lambda *a, **k: calls.append(1) or first_hit(*a, **k))
    fill = page_store.PageStore._fill_from_coarsest
    monkeypatch.setattr(page_store.PageStore, "_fill_from_coarsest",
                        lambda *a, **k: fills.append(1) or fill(*a, **k))

    def run():
        virtual.PAGE_CACHE.clear()
        scene = mi.load_file(str(SCENES / "room_two_points.xml"), width=64, height=64)
        integ = shadowmap(method="hard")
        params = mi.traverse(scene.sensors()[0])
        start = type(params["to_world"])(params["to_world"])
        out, traced = [], []
        for dx in (0.0, 0.3, 0.3, 0.6, 0.0):    # a move, a still frame, two more
            params["to_world"] = start @ T().translate([dx, 0, 0])
            params.update()
            del calls[:], fills[:]
            out.append(vis_of(scene, integ, spp=1))
            traced.append((len(calls), len(fills)))
            out.append(np.array([integ.stats[k] for k in ("texels_built", "pages_built",
                                                         "pages_reused")]))
        out += [m.store.pools["depth"].numpy()[:m.store.next_slot * 32 * 32]
                for m in integ.maps]
        return out, traced

    together, traced = run()
    # a move: one cast, no fill of one light alone
    assert traced[1] == traced[3] == (1, 0) and traced[2] == (0, 0), traced
    scene = mi.load_file(str(SCENES / "room_two_points.xml"), width=64, height=64)
    compiled = _moves(scene, shadowmap(method="hard"), 4)
    assert compiled[1:] == [0, 0, 0], compiled
    alone = page_store._cast_alone

    def cast_alone(scene, jobs, minima=True):
        for j in jobs:
            if j.n_tiles:
                alone(scene, j, "second_depth" in j.store.pools)
        if minima:
            page_store.read_minima(jobs)
    monkeypatch.setattr(page_store, "cast_tiles", cast_alone)
    monkeypatch.setattr(planner, "cast_tiles", page_store.cast_tiles)
    monkeypatch.setattr(planner, "fill_new_pages", lambda jobs: [
        j.store._fill_from_coarsest(j.keys[j.new_fine], j.slot_ids[j.new_fine],
                                    j.masks[j.new_fine])
        for j in jobs if j.keys is not None and j.new_fine.any()])
    apart, traced = run()
    assert traced[1] == traced[3] == (2, 2), traced
    assert len(together) == len(apart)
    for a, b in zip(together, apart):
        assert a.shape == b.shape and np.array_equal(a, b)


def test_a_cast_and_fill_with_a_store_that_built_no_page_yet():
    """``cast_tiles`` and ``fill_new_pages`` with a store that built no page yet among
    the jobs (its keys none, its pools empty: an empty lane range): the other store's
    pages are what its own build gives, and the empty store stays empty. Before, the
    merged kernel scattered to (and the fill gathered from) the empty store's pools with
    every lane masked off, which Dr.Jit refuses ("attempted to scatter to an empty
    array"); a build alone of no keys was always fine."""
    virtual.PAGE_CACHE.clear()
    scene = mi.load_file(str(SCENES / "room_two_points.xml"), width=32, height=32)
    integ = shadowmap(method="hard")
    vis_of(scene, integ, spp=1)
    a, b = (m.store for m in integ.maps[:2])
    lay = a.layout
    assert lay.tiles_per_side > 1
    # every face's coarsest page, and a finer page with one tile cast (the rest filled)
    keys = np.sort(np.array([layout.page_key(f, lay.coarsest, 0, 0)
                             for f in range(lay.view.n_faces)]
                            + [layout.page_key(0, lay.coarsest - 1, 0, 0)], np.uint64))
    masks = np.ones(len(keys), np.int64)
    ref = page_store.PageStore(lay, a.layers)
    texels = ref.build(scene, keys, masks)
    new = page_store.PageStore(lay, a.layers)
    empty = page_store.PageStore(b.layout, b.layers)
    jobs = [new.plan_build(keys, masks), empty.plan_build(np.zeros(0, np.uint64))]
    page_store.cast_tiles(scene, jobs)
    page_store.fill_new_pages(jobs)
    assert new.finish_build(jobs[0], fill=False) == texels > 0
    assert empty.finish_build(jobs[1], fill=False) == 0 and empty.capacity == 0
    for name in ref.pools:
        assert np.array_equal(new.pools[name].numpy(), ref.pools[name].numpy())
    assert np.array_equal(new.tile_min, ref.tile_min)
    assert np.array_equal(new.slot_mask, ref.slot_mask)


@pytest.mark.parametrize("border", [False, True])
def test_batch_footprints_in_the_render_are_each_cameras_own(border):
    """The render's footprint of a ``batch`` lane (a cone of its pixel's one-pixel step,
    the pixel read from Mitsuba's wavefront order: ``spp`` lanes per pixel, row by row,
    with the filter's border where the film samples it) against each camera's own
    (``pinhole_footprint``), on a floor seen by a 4-degree and a 30-degree camera side by
    side: footprint areas were 16.5x / 0.30x theirs (one median cone for the whole
    batch), now within 1 %."""
    from mi_shadowmap.light_views import pinhole_footprint, pinhole_frame
    cams = [{"type": "perspective", "fov": fov,
             "to_world": T().look_at(origin=[1, 5, 8.5], target=target, up=[0, 1, 0])}
            for target, fov in (([1.25, 0, 0.75], 4), ([0, 0.5, 0], 30))]
    film = {"type": "hdrfilm", "width": 64, "height": 16, "sample_border": border,
            "rfilter": {"type": "gaussian"}}
    scene = mi.load_dict({
        "type": "scene", "sensor": {"type": "batch", "a": cams[0], "b": cams[1], "film": film},
        "floor": {"type": "rectangle", "to_world": T().rotate([1, 0, 0], -90).scale(20)},
        "light": {"type": "point", "position": [0, 5, 0]}})
    batch = scene.sensors()[0]
    integ = shadowmap(method="hard")
    spp = 4
    integ._first_pass(scene, batch, spp)
    b = batch.film().rfilter().border_size() if border else 0
    w, h = 64 + 2 * b, 16 + 2 * b
    sampler = mi.load_dict({"type": "independent"})
    sampler.seed(0, w * h * spp)
    pixel = np.arange(w * h * spp) // spp           # Mitsuba's lanes
    x, y = pixel % w - b, pixel // w - b
    inside = (x >= 0) & (x < 64) & (y >= 0) & (y < 16)
    pos = mi.Point2f(mi.Float(np.clip((x + 0.5) / 64, 0, 1)), mi.Float((y + 0.5) / 16))
    ray, _ = batch.sample_ray(0.0, 0.5, pos, mi.Point2f(0.5))
    ray = mi.RayDifferential3f(ray)
    si = scene.ray_intersect(ray)
    area = dr.norm(dr.cross(*integ._footprint(ray, si, sampler))).numpy()
    for k, cam in enumerate(cams):
        alone = mi.load_dict({**cam, "film": {"type": "hdrfilm", "width": 32, "height": 16}})
        frame = tuple(mi.Vector3f(v) for v in pinhole_frame(alone))
        own = dr.norm(dr.cross(*pinhole_footprint(si.p, si.n, frame))).numpy()
        lanes = inside & (x // 32 == k)
        ratio = area[lanes] / own[lanes]
        print(k, np.median(ratio), ratio.min(), ratio.max())
        assert np.all(np.abs(ratio - 1.0) <= 0.01)

@pytest.mark.parametrize("partner", ["wide", "ortho"])
def test_a_batch_of_unlike_cameras_takes_each_cameras_footprints(partner):
    """A ``batch`` of a 4-degree camera beside a 30-degree one (or an orthographic one)
    over a pole's shadow, 64^2 each: the render took one footprint for every pixel of
    the batch, the median over both cameras (their mean, with equal halves): 4x too wide
    for the narrow camera, whose lookups then read levels its pages were not built at
    (the mark pass takes each pixel's own): ``hard`` misclassified 1.49 % of its half
    (0.76 % beside the orthographic camera), ``pcf`` 1.54 %, where that camera alone
    gives 0.17 / 0.27 %. Each lane now takes its own pixel's steps: 0.29 / 0.27 %."""
    def cam(target, fov):
        return {"type": "perspective", "fov": fov,
                "to_world": T().look_at(origin=[1, 5, 8.5], target=target, up=[0, 1, 0])}
    other = cam([0, 0.5, 0], 30) if partner == "wide" else {
        "type": "orthographic", "to_world": T().look_at(
            origin=[1, 5, 8.5], target=[1.25, 0, 0.75], up=[0, 1, 0]) @ T().scale([0.6, 0.6, 1])}
    scene = mi.load_dict({
        "type": "scene",
        "sensor": {"type": "batch", "a": cam([1.25, 0, 0.75], 4), "b": other,
                   "film": {"type": "hdrfilm", "width": 128, "height": 64,
                            "rfilter": {"type": "box"}},
                   "sampler": {"type": "independent", "sample_count": 16}},
        "floor": {"type": "rectangle", "to_world": T().rotate([1, 0, 0], -90).scale(6)},
        "pole": {"type": "cube", "to_world": T().translate([1.5, 1.0, 1.0]).scale([0.04, 1, 0.04])},
        "light": {"type": "spot", "cutoff_angle": 50, "intensity": 60,
                  "to_world": T().look_at(origin=[2.5, 6, 2], target=[0, 0, 0], up=[0, 1, 0])}})
    ref = vis_of(scene, shadowmap(method="raytraced"), spp=16, seed=0)[:, :64]
    for method in ("hard", "pcf"):
        mis = misclassified(ref, vis_of(scene, shadowmap(method=method), spp=16, seed=0)[:, :64])
        print(partner, method, f"{mis:.2%}")
        assert mis <= 0.006, method


@pytest.mark.parametrize("props", [{"method": "pcf"}, {"method": "pcf", "lod_bias": -2.0},
                                   {"method": "pcf", "lod_bias": -4.0},
                                   {"method": "bilinear", "kernel": 8, "lod_bias": -4.0}])
def test_taps_on_the_coarsest_level_keep_an_open_wall_lit(props, monkeypatch):
    """A tap whose page is not built (beyond the bound pages; across a cube seam where
    taps cross it) reads the coarsest level, whose texel holds the depth along its own
    ray; compared with the receiver plane through the tap's fine texel, an inclined open
    wall fell into false shadow along the seams and page borders, more as ``lod_bias``
    went finer (64^2 image, pixels under 0.99, taps crossing the seams: pcf 77 / 271 /
    350 at lod_bias -0.5 / -2 / -4 (2111 when written); bilinear kernel 8 at -4: 363;
    full maps and ``hard``: 0). The tap is now compared with the nearer of the plane's
    depths at its texel and at the coarse texel's point: 0 / 0 / 331 and 180 (a point
    light in a room: pcf's RMSE at lod_bias -4 0.054 -> 0.047, at -0.5 unchanged).
    Virtual cube taps are clamped to their face since (``LocalView.taps_cross_seams``),
    which alone keeps most of this wall lit (0 / 0 / 343 without the comparison): the
    test lets the taps cross, as a user method's may, so that the comparison is what it
    checks (three of its four cases fail without it)."""
    monkeypatch.setattr(LocalView, "taps_cross_seams", property(lambda self: True))
    scene = open_wall_scene(64)
    img = np.asarray(mi.render(scene, integrator=mi.load_dict({"type": "shadowmap",
                                                                **props}), spp=4, seed=1))
    dim = int((img[..., -1] < 0.99).sum())
    limit = {-4.0: 620 if props["method"] == "pcf" else 210}.get(props.get("lod_bias"), 4)
    print(props, dim, "pixels under 0.99")
    assert dim <= limit
