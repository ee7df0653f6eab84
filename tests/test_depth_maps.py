"""First pass: stored depths equal analytic distances; export to numpy and EXR."""
import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from mi_shadowmap.depth_maps import build_depth_map, write_exr
from mi_shadowmap.light_views import make_light_view

T = mi.ScalarTransform4f
RES = 64


def plane(origin, normal, size=100.0):
    return {"type": "rectangle",
            "to_world": T().look_at(origin=origin, target=[o - n for o, n in zip(origin, normal)],
                                    up=[0, 0, 1] if abs(normal[2]) < 0.9 else [1, 0, 0])
            @ T().scale(size)}


def build(scene_dict, res=RES):
    scene = mi.load_dict({"type": "scene", **scene_dict})
    view = make_light_view(scene.emitters()[0], scene, 0)
    return scene, view, build_depth_map(scene, view, res)


def rays_np(view, res):
    o, d, _ = view.texel_rays(res)
    return np.asarray(o).T if np.asarray(o).shape[0] == 3 else np.asarray(o), np.asarray(d).T


def plane_t(o, d, q, n):
    q, n = np.asarray(q, float), np.asarray(n, float)
    return ((q - o) @ n) / (d @ n)


def test_spot_depth_is_distance_to_plane():
    q, n = [0.0, -1.0, 0.0], [0.1, 1.0, 0.05]
    n = list(np.asarray(n) / np.linalg.norm(n))
    _, view, smap = build({
        "floor": plane(q, n),
        "spot": {"type": "spot", "cutoff_angle": 40.0,
                 "to_world": T().look_at(origin=[0.2, 3.0, 0.1], target=[0, 0, 0], up=[0, 0, 1])}})
    o, d = rays_np(view, RES)
    expected = plane_t(np.broadcast_to(o, d.shape), d, q, n)
    got = smap.to_numpy().reshape(-1)
    np.testing.assert_allclose(got, expected, rtol=1e-5)
    assert smap.to_numpy().shape == (1, RES, RES)


def test_directional_depth_is_distance_from_light_plane():
    q, n = [0.0, 0.0, 0.0], [0.0, 1.0, 0.0]
    _, view, smap = build({
        "floor": plane(q, n, size=3.0),
        "ball": {"type": "sphere", "center": [0, 1, 0], "radius": 0.5},
        "sun": {"type": "directional", "direction": [0.3, -1.0, 0.2]}})
    o, d = rays_np(view, RES)
    got = smap.to_numpy().reshape(-1)
    expected = plane_t(o, d, q, n)
    # texels whose ray hits the floor before/without hitting the ball
    p = o + d * expected[:, None]
    on_floor = (np.abs(p[:, 0]) < 3.0) & (np.abs(p[:, 2]) < 3.0)
    clear = np.linalg.norm(np.cross(np.array([0, 1, 0]) - o, d), axis=1) > 0.51
    sel = on_floor & clear
    assert sel.mean() > 0.5   # the map is fitted: most texels see the floor
    np.testing.assert_allclose(got[sel], expected[sel], rtol=1e-5)
    # all rays are parallel to the light direction, and start on one plane
    np.testing.assert_allclose(d, np.broadcast_to(d[0], d.shape), atol=1e-6)
    assert np.all(np.isinf(got[on_floor == False]))  # noqa: E712  (misses are +inf)


def test_cube_faces_depth_is_distance_to_room_walls():
    h, c = 2.0, np.array([0.3, -0.2, 0.5])
    walls = {}
    for a in range(3):
        for s in (1.0, -1.0):
            q = [0.0, 0.0, 0.0]
            q[a] = s * h
            nrm = [0.0, 0.0, 0.0]
            nrm[a] = -s
            walls[f"wall{a}{int(s)}"] = plane(q, nrm, size=h)
    _, view, smap = build({**walls, "lamp": {"type": "point", "position": c.tolist()}})
    assert smap.to_numpy().shape == (6, RES, RES)
    o, d = rays_np(view, RES)
    with np.errstate(divide="ignore"):
        t_axes = (np.sign(d) * h - c) / d
    expected = np.min(np.where(t_axes > 0, t_axes, np.inf), axis=1)
    got = smap.to_numpy().reshape(-1)
    per_face = np.abs(got - expected).reshape(6, -1).max(axis=1) / expected.max()
    assert np.all(per_face < 1e-5), per_face
    np.testing.assert_allclose(got, expected, rtol=1e-5)


def test_projection_inverts_texel_rays():
    """Every texel's own hit point looks up that texel, at its stored depth."""
    scene = mi.load_dict({"type": "scene", "ball": {"type": "sphere", "radius": 5.0},
                          "lamp": {"type": "point", "position": [0.5, 0.2, -0.3]}})
    view = make_light_view(scene.emitters()[0], scene, 0)
    smap = build_depth_map(scene, view, 32)
    o, d, _ = view.texel_rays(32)
    face, uv, depth, inside = view.project(o + d * smap.depth)
    assert dr.all(inside)
    assert dr.all(smap.texel_index(face, uv) == dr.arange(mi.UInt32, 6 * 32 * 32))
    assert dr.max(dr.abs(depth - smap.depth) / smap.depth)[0] < 1e-5


def test_exr_export_roundtrip(tmp_path):
    _, view, smap = build({"floor": plane([0, 0, 0], [0, 1, 0]),
                           "lamp": {"type": "point", "position": [0, 1, 0]}}, res=16)
    path = tmp_path / "lamp_depth.exr"
    write_exr(smap, str(path))
    back = np.asarray(mi.Bitmap(str(path))).reshape(6, 16, 16)
    np.testing.assert_array_equal(back, smap.to_numpy())


def test_unsupported_emitter_is_named():
    scene = mi.load_dict({"type": "scene", "env": {"type": "constant"}})
    with pytest.raises(ValueError, match="env.*not supported.*point, spot, directional, area"):
        make_light_view(scene.emitters()[0], scene, 0)
