"""Parallel-split (cascaded) maps for directional lights (thesis 002, sec. 2.1.6-2.1.7,
5.1): split positions, cascade selection by view depth, 4 x 512^2 cascades vs one
1024^2 map on a large ground plane at a low camera angle, PCSS from the sun, bad input."""
import re

import mitsuba as mi
import numpy as np
import pytest

from mi_shadowmap.light_views import CascadedView, split_depths
from mi_shadowmap.metrics import misclassified
from mi_shadowmap.options import OptionError, parse_options

from conftest import render_np

T = mi.ScalarTransform4f


def large_ground_scene(width=128, height=128):
    """A 200 x 200 ground plane with rows of thin posts (0.1 wide, 1 tall) from the
    camera's feet to 60 units away, a camera 1.6 units high looking almost along the
    ground, and a sun at about 45 degrees."""
    d = {"type": "scene",
         "sensor": {"type": "perspective", "fov": 50,
                    "to_world": T().look_at(origin=[0, 1.6, 6], target=[0, -0.4, -20],
                                            up=[0, 1, 0]),
                    "sampler": {"type": "independent", "sample_count": 4},
                    "film": {"type": "hdrfilm", "width": width, "height": height,
                             "rfilter": {"type": "box"}}},
         "ground": {"type": "rectangle", "to_world": T().rotate([1, 0, 0], -90).scale(100),
                    "bsdf": {"type": "diffuse"}},
         "sun": {"type": "directional", "direction": [0.8, -1.0, 0.35],
                 "irradiance": {"type": "rgb", "value": 3.0}}}
    for j in range(14):
        z = 4 - 0.6 * j ** 1.6
        for i in range(9):
            x = (i - 4) * (1.0 + 0.15 * (4 - z)) + 0.3 * (j % 2)
            d[f"post_{i}_{j}"] = {"type": "cube", "bsdf": {"type": "diffuse"},
                                  "to_world": T().translate([x, 0.5, z]).scale([0.05, 0.5, 0.05])}
    return mi.load_dict(d)


@pytest.fixture(scope="module")
def ground():
    return large_ground_scene()


def test_split_depths_follow_the_thesis_scheme():
    zn, zf, m = 0.5, 200.0, 4
    log = split_depths(zn, zf, m, 0.0)
    uni = split_depths(zn, zf, m, 1.0)
    mix = split_depths(zn, zf, m, 0.3)
    for i in range(m + 1):
        assert log[i] == pytest.approx(zn * (zf / zn) ** (i / m))
        assert uni[i] == pytest.approx(zn + (zf - zn) * i / m)
        assert mix[i] == pytest.approx(0.3 * uni[i] + 0.7 * log[i])
    assert all(a < b for a, b in zip(mix, mix[1:]))


def test_neighbouring_slices_overlap_by_two_percent_of_their_length():
    """Each cascade is fitted to the visible points of its slice of view depth grown by
    2 % of the slice's length at both ends (``cascaded_view``), so a camera sample a
    little past a split still finds itself inside its cascade; slices fitted without
    the overlap (mutation audit) passed the suite, the catch-all face standing in."""
    from mi_shadowmap.light_views import make_light_view
    from mi_shadowmap.light_views.base import light_matrix
    from mi_shadowmap.light_views.cascaded import cascaded_view
    scene = mi.load_dict({
        "type": "scene",
        "sensor": {"type": "perspective", "fov": 50,
                   "to_world": T().look_at(origin=[0, 1.6, 6], target=[0, -0.4, -20],
                                           up=[0, 1, 0])},
        "ground": {"type": "rectangle", "to_world": T().rotate([1, 0, 0], -90).scale(100)},
        "sun": {"type": "directional", "direction": [0.8, -1.0, 0.35]}})
    view = make_light_view(scene.emitters()[0], scene, 0)
    # visible points along a line receding from the camera (their light-space box grows
    # with the view depth)
    z = np.linspace(4.0, -60.0, 2001)
    points = np.stack([0.3 * z, np.zeros_like(z), z], 1)
    casc = cascaded_view(view, scene, scene.sensors()[0], 4, 0.5, res=None, points=points)
    cam_f = np.asarray(casc.camera_forward)
    z_view = (points - np.asarray(casc.camera_origin)) @ cam_f
    L = light_matrix(view)
    p_l = points @ L[:3, :3].T + L[:3, 3]
    splits = casc.split_depths
    for i, (cx, cy, hx, hy) in enumerate(casc.rects[:4]):
        pad = 0.02 * (splits[i + 1] - splits[i])
        sel = (z_view >= splits[i] - 0.99 * pad) & (z_view <= splits[i + 1] + 0.99 * pad)
        assert np.all(np.abs(p_l[sel, 0] - cx) <= hx * (1 + 1e-9)), i
        assert np.all(np.abs(p_l[sel, 1] - cy) <= hy * (1 + 1e-9)), i


def test_cascades_are_fitted_and_selected_by_view_depth(ground):
    integ = mi.load_dict({"type": "shadowmap", "method": "hard", "resolution": 64,
                          "cascades": 4, "split_lambda": 0.5})
    mi.render(ground, integrator=integ, spp=1)
    view = integ.views[0]
    assert isinstance(view, CascadedView) and view.n_faces == 4
    assert integ.maps[0].to_numpy().shape == (4, 64, 64)
    splits = view.split_depths
    assert len(splits) == 5 and all(a < b for a, b in zip(splits, splits[1:]))
    # nearer slices are smaller: finer texels where the camera is close
    sizes = [max(r[2], r[3]) for r in view.rects]
    assert all(a < b for a, b in zip(sizes, sizes[1:]))
    # points at view depths inside slice i use cascade i
    o = np.array(view.camera_origin)
    f = np.array(view.camera_forward)
    mids = [0.5 * (a + b) for a, b in zip(splits, splits[1:])]
    pts = np.array([o + f * z for z in mids])
    face = view.cascade_of(mi.Point3f(pts[:, 0], pts[:, 1], pts[:, 2])).numpy()
    assert list(face) == [0, 1, 2, 3]


def test_four_cascades_of_512_beat_one_map_of_1024(ground):
    _, ref = render_np(ground, {"type": "shadowmap", "method": "raytraced"}, spp=4)
    _, lit = render_np(ground, {"type": "shadowmap", "method": "unshadowed"}, spp=4)
    mask = lit["vis_sun"] > 0          # pixels the sun lights when unshadowed
    _, one = render_np(ground, {"type": "shadowmap", "method": "hard", "resolution": 1024},
                       spp=4)
    _, four = render_np(ground, {"type": "shadowmap", "method": "hard", "resolution": 512,
                                 "cascades": 4}, spp=4)
    m1 = misclassified(ref["vis_sun"], one["vis_sun"], mask=mask)["misclassified"]
    m4 = misclassified(ref["vis_sun"], four["vis_sun"], mask=mask)["misclassified"]
    print(f"misclassified (sunlit-when-unshadowed pixels): 1 x 1024^2 {m1:.3%}, "
          f"4 x 512^2 cascades {m4:.3%}")
    assert m4 < 0.75 * m1


def test_angular_diameter_softens_the_sun_with_cascades():
    from mi_shadowmap.scenes import default_scene
    scene = mi.load_dict(default_scene(light="directional", width=64, height=64))
    _, hard = render_np(scene, {"type": "shadowmap", "method": "pcss", "resolution": 256,
                                "cascades": 2}, spp=4)
    _, soft = render_np(scene, {"type": "shadowmap", "method": "pcss", "resolution": 256,
                                "cascades": 2, "angular_diameter": 8.0}, spp=4)
    partial = lambda v: np.mean((v > 0.05) & (v < 0.95))
    h, s = hard["vis_sun"], soft["vis_sun"]
    assert np.isfinite(s).all()
    assert partial(s) > 1.8 * partial(h)
    assert abs(s.mean() - h.mean()) < 0.03     # a blur of the same shadows


@pytest.mark.parametrize("name,value,pattern", [
    ("cascades", 0, ">= 1"), ("cascades", 5, "<= 4"), ("cascades", 2.0, "integer"),
    ("split_lambda", -0.1, ">= 0"), ("split_lambda", 1.5, "<= 1"), ("split_lambda", "log", "number"),
])
def test_bad_cascade_properties(name, value, pattern):
    with pytest.raises(OptionError, match=re.escape(f"'{name}'") + ".*" + re.escape(pattern)):
        parse_options({"method": "hard", name: value})


@pytest.mark.parametrize("name,value", [("cascades", 2), ("split_lambda", 0.5)])
def test_cascade_properties_refused_without_a_map(name, value):
    with pytest.raises(OptionError, match=f"'{name}' is not used by method 'raytraced'"):
        parse_options({"method": "raytraced", name: value})


def test_cascades_leave_other_lights_alone():
    from mi_shadowmap.scenes import default_scene
    scene = mi.load_dict(default_scene(light="spot", width=32, height=32))
    _, a = render_np(scene, {"type": "shadowmap", "method": "hard", "resolution": 128}, spp=1)
    _, b = render_np(scene, {"type": "shadowmap", "method": "hard", "resolution": 128,
                             "cascades": 4}, spp=1)
    assert np.array_equal(a["vis_spot"], b["vis_spot"])


def test_cascade_margin_uses_the_real_resolution(ground):
    """The cascades grow by 4 texels of the resolution actually used (review item 4):
    half = raw * (1 + g) + g * max(raw), g = 2 * 4 / res, with raw the unpadded fit."""
    from mi_shadowmap.light_views import cascaded_view, make_light_view
    sensor = ground.sensors()[0]
    base = make_light_view(ground.emitters()[0], ground, 0)
    raw = cascaded_view(base, ground, sensor, 4, 0.5, res=None).rects
    for res in (32, 256):
        integ = mi.load_dict({"type": "shadowmap", "method": "hard", "resolution": res,
                              "cascades": 4, "split_lambda": 0.5})
        mi.render(ground, integrator=integ, spp=1)
        rects = integ.views[0].rects
        g = 2.0 * 4.0 / res
        for r, q in zip(rects, raw):
            assert r[:2] == pytest.approx(q[:2], rel=1e-6, abs=1e-9)
            big = max(q[2], q[3])
            assert r[2] == pytest.approx(q[2] * (1 + g) + g * big, rel=1e-6)
            assert r[3] == pytest.approx(q[3] * (1 + g) + g * big, rel=1e-6)


def test_automatic_resolution_sees_cascaded_lights():
    """footprint_ratio has a cascaded branch (review item 5): the largest cascade's
    width over the camera pixel width, the same as an orthographic map of that width;
    the automatic resolution of a cascaded sun is the one this footprint gives."""
    import dataclasses
    from mi_shadowmap.light_views import cascaded_view, footprint_ratio, make_light_view
    from mi_shadowmap.options import parse_options
    scene = large_ground_scene(width=32, height=32)
    sensor = scene.sensors()[0]
    base = make_light_view(scene.emitters()[0], scene, 0)
    cas = cascaded_view(base, scene, sensor, 4, 0.5, res=None)
    w = max(max(r[2], r[3]) for r in cas.rects)
    ortho = dataclasses.replace(base, half_extent=(w, w))
    f = footprint_ratio(scene, sensor, [cas])
    assert f == pytest.approx(footprint_ratio(scene, sensor, [ortho]), rel=1e-9)
    assert f != 1.0 and f < footprint_ratio(scene, sensor, [base])
    integ = mi.load_dict({"type": "shadowmap", "method": "hard", "cascades": 4,
                          "split_lambda": 0.5})
    mi.render(scene, integrator=integ, spp=1)
    opts = parse_options({"method": "hard", "cascades": 4, "split_lambda": 0.5})
    assert integ.resolution == opts.map_resolution((32, 32), 4, f)


def test_a_cascades_texel_is_its_own_rectangles_texel(ground):
    """The biases' texel (``texel_world_size``) of a point in cascade ``i`` is a texel
    of that cascade's rectangle, ``2 h / res`` per side: the shorter side for a receiver
    facing the sun (its depth does not change across the texel), between the two sides
    along a ground's depth gradient. (Mutation audit: half of it, which halves every
    cascade's slope and normal biases, survived every test.)"""
    res = 64
    integ = mi.load_dict({"type": "shadowmap", "method": "hard", "resolution": res,
                          "cascades": 4, "split_lambda": 0.5})
    mi.render(ground, integrator=integ, spp=1)
    view = integ.views[0]
    o, f = np.array(view.camera_origin), np.array(view.camera_forward)
    splits = view.split_depths
    pts = np.array([o + f * 0.5 * (a + b) for a, b in zip(splits, splits[1:])])
    p = mi.Point3f(pts[:, 0], pts[:, 1], pts[:, 2])
    assert list(view.cascade_of(p).numpy()) == [0, 1, 2, 3]
    w = np.array([[2.0 * r[2] / res, 2.0 * r[3] / res] for r in view.rects])
    to_sun = -np.array([0.8, -1.0, 0.35]) / np.linalg.norm([0.8, -1.0, 0.35])
    facing = view.texel_world_size(res, mi.Float(np.ones(4)), p,
                                   mi.Vector3f(*[float(c) for c in to_sun]))
    np.testing.assert_allclose(facing.numpy(), w.min(axis=1), rtol=1e-5)
    up = view.texel_world_size(res, mi.Float(np.ones(4)), p, mi.Vector3f(0.0, 1.0, 0.0))
    assert np.all(up.numpy() >= w.min(axis=1) * (1 - 1e-5))
    assert np.all(up.numpy() <= w.max(axis=1) * (1 + 1e-5))
