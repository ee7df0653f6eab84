"""mdsm (Pagot, Comba & Oliveira 2004): the min/max layers, the n-shadow test, PCF(k, n)
and its Table 1 level counts, a straight edge, the paper's PCF(9, n) ~ PCF(16, 1) claim,
the scenes_xml scenes and bad input."""
import math

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from mi_shadowmap.depth_maps import ShadowMap
from mi_shadowmap import methods
from mi_shadowmap.filters import Lookup
from mi_shadowmap.filters.mdsm import neighbourhood_depth
from mi_shadowmap.light_views import OrthoView
from mi_shadowmap.light_views.base import TEXEL_SAMPLE
from mi_shadowmap.metrics import dilate, distinct_levels, misclassified, rmse
from mi_shadowmap.options import OptionError, parse_options
from mi_shadowmap.scenes import camera

from conftest import SCENE_FILES, own_and_widest_marks, render_np, vis_stack

T = mi.ScalarTransform4f
DIFFUSE = {"type": "diffuse"}


# ------------------------------------------------------------------ helpers
def hand_map(depth, res):
    """ShadowMap of an orthographic light looking along +z from z = 0 over x, y in [-1, 1]
    (texel (i, j) centre x = (i+.5)/res*2-1, y = (j+.5)/res*2-1), hand-written depths,
    with its min/max layers built by the real layer builders."""
    view = OrthoView("directional", mi.ScalarPoint3f(0, 0, 0),
                     mi.ScalarTransform4f(), half_extent=(1.0, 1.0), label="hand")
    smap = ShadowMap(view, res, depth=mi.Float(np.asarray(depth, np.float32).ravel()))
    for name, builder in methods.get("mdsm").layers.items():
        smap.extra[name] = builder(None, smap)
        dr.eval(smap.extra[name])
    return smap


def hand_lookup(x, y, z, normal=(0.0, 0.0, -1.0)):
    x = np.asarray(x, np.float32)
    n = len(x)
    f = lambda a: mi.Float(np.broadcast_to(np.asarray(a, np.float32), n).copy())  # noqa: E731
    nn = mi.Vector3f(*[dr.full(mi.Float, float(c), n) for c in normal])
    return Lookup(mi.Point3f(f(x), f(y), f(z)), nn, mi.Vector3f(0), mi.Vector3f(0),
                  None, None, None)


def mdsm_vis(smap, lk, **props):
    opts = parse_options({"method": "mdsm", **props})
    return np.asarray(methods.get("mdsm").lookup(smap, lk, opts, True))


def texel_centres(res):
    """x of the texels' rays (light_views.base.TEXEL_SAMPLE: the centres, moved a little)."""
    return (np.arange(res) + TEXEL_SAMPLE[0]) / res * 2.0 - 1.0


def np_window(depth, search, reduce):
    """Clamped search x search min/max of a 2-D array (reference for the layers)."""
    r = (search - 1) // 2
    res = depth.shape[0]
    out = np.empty_like(depth)
    for j in range(res):
        for i in range(res):
            out[j, i] = reduce(depth[max(j - r, 0):j + r + 1, max(i - r, 0):i + r + 1])
    return out


# ------------------------------------------------------------------ the map
def test_layers_are_3x3_min_and_max_and_built_only_for_mdsm():
    path = [p for p in SCENE_FILES if p.stem == "spot_sphere_box"][0]
    scene = mi.load_file(str(path), width=16, height=16)
    integ = mi.load_dict({"type": "shadowmap", "method": "mdsm", "resolution": 64,
                          "depths": 3})
    smap = integ.prepare_maps(scene)[0]
    assert smap.second_depth is None and sorted(smap.extra) == ["mdsm_max", "mdsm_min"]
    depth = smap.to_numpy()[0]
    np.testing.assert_array_equal(smap.to_numpy("mdsm_min")[0], np_window(depth, 3, np.min))
    np.testing.assert_array_equal(smap.to_numpy("mdsm_max")[0], np_window(depth, 3, np.max))
    for method, layers in (("hard", []), ("second_depth", ["second_depth"])):
        integ = mi.load_dict({"type": "shadowmap", "method": method, "resolution": 64})
        assert list(integ.prepare_maps(scene)[0].extra) == layers


@pytest.mark.parametrize("depths, search, layers", [
    (1, 3, ()), (1, 9, ()), (2, 1, ()), (3, 1, ()),
    (2, 3, ("mdsm_max",)), (2, 9, ("mdsm_max",)), (3, 3, ("mdsm_min", "mdsm_max"))])
def test_layers_requested_only_where_read(depths, search, layers):
    """The layers a render builds depend on the options (review item 36): ``depths=1``
    and ``search=1`` read only the base depth; a 2-SM reads only the maximum."""
    opts = parse_options({"method": "mdsm", "depths": depths, "search": search,
                          "virtual": False})
    assert opts.record.layer_names(opts) == layers
    assert set(layers) <= set(methods.get("mdsm").layers)     # every one is an exportable layer
    # virtual maps build none: the lookup computes them from the base depths
    opts = parse_options({"method": "mdsm", "depths": depths, "search": search,
                          "virtual": True})
    assert opts.record.layer_names(opts) == ()


@pytest.mark.parametrize("search", [1, 3, 5, 7, 9])
def test_search_neighbourhood(search):
    """Larger searches compose the stored 3x3 windows: exactly the search x search min/max."""
    res = 24
    depth = np.random.default_rng(search).uniform(1, 2, (res, res)).astype(np.float32)
    smap = hand_map(depth, res)
    jj, ii = np.meshgrid(np.arange(res), np.arange(res), indexing="ij")
    ij = mi.Point2i(mi.Int32(ii.ravel()), mi.Int32(jj.ravel()))
    for layer, reduce in (("mdsm_min", np.min), ("mdsm_max", np.max)):
        got = np.asarray(neighbourhood_depth(smap, layer, mi.UInt32(0), ij, search, True))
        np.testing.assert_array_equal(got.reshape(res, res), np_window(depth, search, reduce))


@pytest.mark.parametrize("search", [1, 3, 5, 7, 9])
def test_search_neighbourhood_without_stored_layers(search):
    """On a map without the min/max layers (virtual maps build none) the same extremes
    are computed from the base depths at lookup time: exactly the stored layers' values,
    also where the windows are clamped at the face's border."""
    from mi_shadowmap.filters.mdsm import neighbourhood_depths
    res = 24
    depth = np.random.default_rng(10 + search).uniform(1, 2, (res, res)).astype(np.float32)
    smap = hand_map(depth, res)
    bare = ShadowMap(smap.view, res, depth=smap.depth)
    assert not bare.extra
    jj, ii = np.meshgrid(np.arange(res), np.arange(res), indexing="ij")
    ij = mi.Point2i(mi.Int32(ii.ravel()), mi.Int32(jj.ravel()))
    names = ("mdsm_min", "mdsm_max")
    got = neighbourhood_depths(bare, names, mi.UInt32(0), ij, search, True)
    stored = neighbourhood_depths(smap, names, mi.UInt32(0), ij, search, True)
    for layer, reduce in (("mdsm_min", np.min), ("mdsm_max", np.max)):
        g = np.asarray(got[layer]).reshape(res, res)
        np.testing.assert_array_equal(g, np_window(depth, search, reduce))
        np.testing.assert_array_equal(g, np.asarray(stored[layer]).reshape(res, res))


@pytest.mark.parametrize("depths, search, k", [(2, 3, 9), (3, 3, 9), (3, 5, 4), (2, 9, 25),
                                                (3, 7, 16)])
def test_lookup_without_stored_layers_equals_the_stored_one(depths, search, k):
    """A map without the min/max layers (virtual maps) gives exactly the visibility of the
    same map with them, inside the face (where the taps' union block is read once) and at
    its border (where each tap's clamped windows are visited)."""
    res = 24
    rng = np.random.default_rng(100 * depths + search + k)
    depth = rng.uniform(1.0, 2.0, (res, res)).astype(np.float32)
    depth[rng.random((res, res)) < 0.3] = 1.5       # repeated depths: ties in min / max
    smap = hand_map(depth, res)
    bare = ShadowMap(smap.view, res, depth=smap.depth)
    n = 6000
    lk = hand_lookup(rng.uniform(-1.05, 1.05, n), rng.uniform(-1.05, 1.05, n),
                     rng.uniform(0.9, 2.1, n))
    props = dict(depths=depths, search=search, pcf_samples=k)
    a, b = mdsm_vis(smap, lk, **props), mdsm_vis(bare, lk, **props)
    assert 0.02 < np.mean((a > 0) & (a < 1))
    np.testing.assert_array_equal(a, b)


def test_search_1_is_a_standard_map():
    res = 32
    depth = np.random.default_rng(3).uniform(1, 2, (res, res))
    smap = hand_map(depth, res)
    rng = np.random.default_rng(4)
    lk = hand_lookup(rng.uniform(-0.9, 0.9, 3000), rng.uniform(-0.9, 0.9, 3000),
                     rng.uniform(0.9, 2.1, 3000))
    base = mdsm_vis(smap, lk, depths=1)
    for n in (2, 3):
        np.testing.assert_array_equal(mdsm_vis(smap, lk, depths=n, search=1), base)


# ------------------------------------------------------------------ Table 1
@pytest.mark.parametrize("k", [4, 9, 16])
@pytest.mark.parametrize("n", [1, 2, 3])
def test_table1_level_count(k, n):
    """PCF(k, n) reaches the paper's maximum n*k + 1 distinct outcomes (Table 1) on a
    synthetic edge: a slanted occluder edge (depth ~1 against a floor at ~2) with texel
    depth noise of +-0.3 (a rough edge), looked up at random positions and receiver
    depths between 0.6 and 2.4. It can never produce more."""
    res = 32
    xc = texel_centres(res)
    X, Y = np.meshgrid(xc, xc)
    ang = 0.37
    rng = np.random.default_rng(1)
    depth = (np.where(X * np.cos(ang) + Y * np.sin(ang) < 0.013, 1.0, 2.0)
             + rng.uniform(-0.3, 0.3, X.shape))
    smap = hand_map(depth, res)
    m = 40000
    lk = hand_lookup(rng.uniform(-0.6, 0.6, m), rng.uniform(-0.6, 0.6, m),
                     rng.uniform(0.6, 2.4, m))
    vis = mdsm_vis(smap, lk, pcf_samples=k, depths=n)
    levels = distinct_levels(vis)
    print(f"PCF({k},{n}): {levels} distinct values (paper: {n * k + 1})")
    assert levels == n * k + 1
    # the outcomes are the multiples of 1 / (n k)
    np.testing.assert_allclose(vis * n * k, np.round(vis * n * k), atol=1e-4)


# ------------------------------------------------------------------ a straight edge
@pytest.mark.parametrize("k", [4, 9, 16])
@pytest.mark.parametrize("n", [1, 2, 3])
def test_straight_edge(k, n):
    """Occluder (depth 1) for x < 0, floor (depth 2) for x >= 0, receivers on the floor.

    Monotone across the edge, exactly 0 and 1 away from it. On the edge: 0.5 for n = 1
    and n = 3 (exactly for even sqrt(k), within 1/(2 sqrt(k)) for odd); the 2-SM (standard
    depth + maximum) lightens only the shadow side -- a band one texel wide gets
    coverage 1/2 -- so its edge value lies above 0.5 (measured 0.75, 0.83, 0.625 for
    k = 4, 9, 16)."""
    res = 32
    xc = texel_centres(res)
    depth = np.where(xc[None, :] < 0.0, 1.0, 2.0) * np.ones((res, 1))
    smap = hand_map(depth, res)
    xs = np.linspace(-0.6, 0.6, 481)
    vis = mdsm_vis(smap, hand_lookup(xs, 0.013, 2.0), pcf_samples=k, depths=n)
    assert np.all(np.diff(vis) >= 0)
    side = math.isqrt(k)
    far = (side / 2 + 0.5 + 1) * 2.0 / res        # kernel half-width + search radius
    assert np.all(vis[xs < -far] == 0.0) and np.all(vis[xs > far] == 1.0)
    edge = mdsm_vis(smap, hand_lookup([0.0], 0.013, 2.0), pcf_samples=k, depths=n)[0]
    if n == 2:   # one column of the block half-shadowed at most: 1 - 1/(2 sqrt(k))
        assert 0.5 < edge <= 1.0 - 0.5 / side + 1e-6, edge
    else:
        tol = 0.0 if side % 2 == 0 else 0.5 / side
        assert abs(edge - 0.5) <= tol + 1e-6, edge


@pytest.mark.parametrize("k", [1, 4, 9])
@pytest.mark.parametrize("n, search", [(1, 3), (2, 3), (2, 5), (3, 3), (3, 5)])
def test_two_depths_move_the_edge_a_quarter_search_into_the_shadow(k, n, search):
    """The 2-SM's maximum is in front of a receiver only where its whole search square
    is: its shadow edge lies (search-1)/2 texels inside the standard depth's, so the
    2-SM moves every edge (search-1)/4 texels into the shadow (the paper's 'thinner'
    transition; README "Thinner shadows with mdsm depths=2"). Integrated across a
    straight edge: exactly that much added light; none for n = 1 and n = 3 (whose
    minimum moves the edge back as far)."""
    res = 32
    xc = texel_centres(res)
    smap = hand_map(np.where(xc[None, :] < 0.0, 1.0, 2.0) * np.ones((res, 1)), res)
    xs = np.linspace(-0.6, 0.6, 2401)
    vis = mdsm_vis(smap, hand_lookup(xs, 0.013, 2.0), pcf_samples=k, depths=n,
                   search=search)
    added = np.sum(vis - (xs >= 0.0)) * (xs[1] - xs[0]) * res / 2.0     # texels
    expected = (search - 1) / 4.0 if n == 2 else 0.0
    assert abs(added - expected) < 0.01, added


def test_tilted_receiver_does_not_shadow_itself():
    """A lit plane tilted 60 degrees from the light: every tap (and the 3x3 minimum, with
    its search-radius allowance) lies behind the receiver plane -> exactly 1."""
    res = 32
    xc = texel_centres(res)
    slope = math.tan(math.radians(60))
    smap = hand_map(2.0 + slope * xc[None, :] * np.ones((res, 1)), res)
    xs = np.linspace(-0.7, 0.7, 301)
    lk = hand_lookup(xs, 0.013, 2.0 + slope * xs, (slope, 0.0, -1.0))
    for k in (4, 9, 16):
        for n in (1, 2, 3):
            assert np.all(mdsm_vis(smap, lk, pcf_samples=k, depths=n) == 1.0), (k, n)


@pytest.mark.parametrize("degrees", [88.0, 89.0])
def test_a_grazing_receiver_keeps_the_minimums_allowance(degrees):
    """A lit plane the light grazes (within atan(max_tan_slope), 2.9 degrees, of its
    rays): its virtual samples are not taken (``c_L -> 0``), so the minimum's compare
    is lowered by the steepest clamped slope over the search radius instead, and one
    tap of a 3-depth map is lit as one tap of a standard map is. Without that
    allowance (mutation audit: no lowering there) the plane's own 3 x 3 minimum shadowed
    it: visibility 0.94 / 0.76 at 88 / 89 degrees."""
    res = 32
    xc = texel_centres(res)
    slope = math.tan(math.radians(degrees))
    smap = hand_map(2.0 + slope * xc[None, :] * np.ones((res, 1)), res)
    xs = np.linspace(-0.02, 0.02, 41)
    n = np.array([slope, 0.0, -1.0]) / math.hypot(slope, 1.0)     # unit, towards the light
    lk = hand_lookup(xs, 0.013, 2.0 + slope * xs, tuple(n))
    for depths in (1, 2, 3):
        assert np.all(mdsm_vis(smap, lk, pcf_samples=1, depths=depths) == 1.0), depths


@pytest.mark.parametrize("light", ["point", "spot"])
def test_virtual_marks_cover_every_window_a_wide_search_reads(light, monkeypatch):
    """On virtual maps ``mdsm`` reads the base depths of each tap's ``search x search``
    window, ``(search - 1) / 2`` texels beyond its taps; the record's ``virtual_margin``
    has the mark pass build them. The render then equals one whose marks reach as far
    as the 2 x 2 pages a lookup binds (margin 14 at page size 32). Without the windows'
    radius in the margin (mutation audit) 1-2 pixels of a 64^2 view read tiles that were
    not cast, at ``search`` 9."""
    own, wide = own_and_widest_marks(monkeypatch, light,
                                     {"method": "mdsm", "depths": 3, "search": 9})
    assert np.array_equal(own, wide)


# ------------------------------------------------------------------ the paper's claim
def edge_scene(width=128, spp=32):
    """A thin closed plate (turned 20 degrees) over an open floor under a near-vertical
    sun; the camera looks down at the straight shadow edge (a 256^2 map texel is ~4
    pixels wide)."""
    return mi.load_dict({
        "type": "scene",
        "cam": camera([0.0, 2.2, 1.6], [0.0, 0.0, 0.0], width, width, spp, fov=20),
        "ground": {"type": "rectangle", "bsdf": DIFFUSE,
                   "to_world": T().rotate([1, 0, 0], -90) @ T().scale(2.0)},
        "plate": {"type": "cube", "bsdf": DIFFUSE,
                  "to_world": T().translate([-0.75, 0.5, 0.1]) @ T().rotate([0, 1, 0], 20)
                  @ T().scale([0.75, 0.02, 0.75])},
        "sun": {"type": "directional", "direction": [0.15, -1, 0.1], "irradiance": 3.0}})


def test_pcf9_multiple_depths_close_to_pcf16():
    """Pagot et al.: PCF(9, 2 or 3) looks like PCF(16, 1). As a number: visibility RMSE
    against ray tracing on the edge scene, 256^2 map, 128^2 image, 32 spp.

    Measured (this machine, this test): PCF(16,1) 0.0208, PCF(9,2) 0.0261 (+25 %),
    PCF(9,3) 0.0223 (+7 %); at 64 spp also hard 0.0128 and PCF(9,1) 0.0165. The claim holds for n = 3 (within 10 %) but
    not for our 2-SM (standard depth + maximum: it widens the transition on the shadow
    side only). Against a hard-shadow reference every filter loses to ``hard``; the claim
    is about matching PCF(16, 1), not about beating it. (At 128^2 / 512^2 maps PCF(9,3)
    measured +4 % / +12 %, PCF(9,2) +15 % / +47 %.)
    """
    scene = edge_scene()
    _, ref = render_np(scene, {"type": "shadowmap", "method": "raytraced"}, spp=32)
    ref = vis_stack(ref)
    err = {}
    for k, n in ((16, 1), (9, 2), (9, 3)):
        _, v = render_np(scene, {"type": "shadowmap", "method": "mdsm", "resolution": 256,
                                 "pcf_samples": k, "depths": n}, spp=32)
        err[(k, n)] = rmse(ref, vis_stack(v))
    base = err[(16, 1)]
    print("RMSE vs raytraced: " + ", ".join(f"PCF{kn}={e:.4f} ({e / base - 1:+.1%})"
                                           for kn, e in err.items()))
    assert err[(9, 3)] <= 1.10 * base          # the paper's claim, n = 3


def closed_room(width=128):
    """A point light inside a closed box room (4 x 2 x 4, normals inward), a cube on the
    floor whose shadow crosses the map's -y/+x seam; the camera inside."""
    grey = lambda v: {"type": "diffuse",                               # noqa: E731
                      "reflectance": {"type": "rgb", "value": [v, v, v]}}
    return mi.load_dict({
        "type": "scene",
        "cam": camera([-1.2, 1.5, 1.2], [1.3, 0.0, -0.3], width, width, 4, fov=60),
        "light": {"type": "point", "position": [0.0, 1.6, 0.0], "intensity": 5.0},
        "room": {"type": "cube", "flip_normals": True, "bsdf": grey(0.7),
                 "to_world": T().translate([0, 1, 0]) @ T().scale([2, 1, 2])},
        "box": {"type": "cube", "bsdf": grey(0.5),
                "to_world": T().translate([1.0, 0.25, -0.3]) @ T().rotate([0, 1, 0], 20)
                @ T().scale(0.25)}})


def test_closed_room_two_depths_add_light_in_proportion_to_the_texel():
    """In a closed room the 2-SM's light beyond ``raytraced`` lies along the cube's
    shadow and is the edge shift above, proportional to the texel and to the search
    radius -- no leak that stays at finer maps. Measured (visibility summed over the
    shadow and 4 pixels around it, 128^2, 4 spp), the light depths=2 adds over
    depths=1 at 256^2 / 512^2 / 1024^2 maps: 6.0 / 2.9 / 1.6, search=5 at 256^2 11.1;
    depths=3 adds 0.8 / 0.0 / 0.3; depths=1 is -1.2 / -0.3 / -0.6 from raytraced.
    (Virtual maps: 10.7, the automatic 152^2 full map 8.9.)"""
    scene = closed_room()
    _, ref = render_np(scene, {"type": "shadowmap", "method": "raytraced"}, spp=4)
    ref = vis_stack(ref)[0]
    near = dilate(ref < 0.5, 4)
    assert 100 < np.sum(ref < 0.5) and np.all(ref[~near] == 1.0)

    def err(**props):
        _, v = render_np(scene, {"type": "shadowmap", "method": "mdsm", **props}, spp=4)
        return float(np.sum(vis_stack(v)[0][near] - ref[near]))

    added = {}
    for res in (256, 512):
        e1, e2, e3 = (err(resolution=res, depths=d) for d in (1, 2, 3))
        assert abs(e1) < 2.0, (res, e1)
        added[res] = e2 - e1
        assert abs(e3 - e1) < 0.25 * added[res], (res, e3 - e1, added[res])
    wide = err(resolution=256, depths=2, search=5) - err(resolution=256, depths=1)
    print("light added by depths=2:", added, "search=5:", wide)
    assert added[256] > 3.0
    assert 1.6 < added[256] / added[512] < 2.5
    assert 1.6 < wide / added[256] < 2.5


# ------------------------------------------------------------------ bad input
def test_defaults():
    o = parse_options({"method": "mdsm"})
    assert o.depths == 2 and o.search == 3 and o.pcf_samples == 9


@pytest.mark.parametrize("props, needle", [
    ({"method": "mdsm", "depths": 0}, "depths"),
    ({"method": "mdsm", "depths": 4}, "depths"),
    ({"method": "mdsm", "depths": 2.0}, "depths"),
    ({"method": "mdsm", "depths": "2"}, "depths"),
    ({"method": "mdsm", "search": 0}, "search"),
    ({"method": "mdsm", "search": 2}, "search"),
    ({"method": "mdsm", "search": 4}, "search"),
    ({"method": "mdsm", "search": 11}, "search"),
    ({"method": "mdsm", "search": True}, "search"),
    ({"method": "mdsm", "pcf_samples": 8}, "pcf_samples"),
    ({"method": "mdsm", "pcf_samples": 36}, "pcf_samples"),
    ({"method": "hard", "depths": 2}, "depths"),
    ({"method": "second_depth", "search": 3}, "search"),
    ({"method": "mdsm", "virtual_samples": True}, "virtual_samples"),
])
def test_bad_values_name_the_property(props, needle):
    with pytest.raises(OptionError, match=needle):
        parse_options(props)
    with pytest.raises(RuntimeError, match=needle):
        mi.load_dict({"type": "shadowmap", **props})
