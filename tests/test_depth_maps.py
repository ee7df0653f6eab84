"""First pass: stored depths equal analytic distances; export to numpy and EXR."""
import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from mi_shadowmap.depth_maps import build_depth_map, write_exr
from mi_shadowmap.light_views import make_light_view
from mi_shadowmap.light_views.base import TEXEL_SAMPLE

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


def texel_st(res, n_faces=1):
    """``(face, s, t)`` of every texel in the documented flat order
    ``face*res*res + j*res + i``, its ray at ``(i + TEXEL_SAMPLE[0]) / res`` (the
    centre, moved a little) mapped to [-1, 1]."""
    face, j, i = np.meshgrid(np.arange(n_faces), np.arange(res), np.arange(res), indexing="ij")
    s = 2.0 * (i.reshape(-1) + TEXEL_SAMPLE[0]) / res - 1.0
    t = 2.0 * (j.reshape(-1) + TEXEL_SAMPLE[1]) / res - 1.0
    return face.reshape(-1), s, t


def cube_dirs_np(res):
    """Documented cube convention: face 2a+s looks along axis a with sign +/- (s=0/1);
    its u axis is (a+1)%3, its v axis (a+2)%3. Unit directions, numpy only."""
    face, s, t = texel_st(res, 6)
    d = np.zeros((len(face), 3))
    axis = face // 2
    rows = np.arange(len(face))
    d[rows, axis] = np.where(face % 2 == 0, 1.0, -1.0)
    d[rows, (axis + 1) % 3] = s
    d[rows, (axis + 2) % 3] = t
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def spot_dirs_np(to_world, cutoff_deg, res):
    """The spot's own frame: map u/v along the emitter's local x/y (the normalised
    columns of its to_world), +z the axis, half-width tan(cutoff)."""
    M = np.array(to_world.matrix, dtype=float)[:3, :3]
    M = M / np.linalg.norm(M, axis=0, keepdims=True)
    _, s, t = texel_st(res)
    tan = np.tan(np.radians(cutoff_deg))
    d_local = np.stack([s * tan, t * tan, np.ones_like(s)], axis=1)
    d = d_local @ M.T
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def plane_t(o, d, q, n):
    q, n = np.asarray(q, float), np.asarray(n, float)
    return ((q - o) @ n) / (d @ n)


def test_spot_depth_is_distance_to_plane():
    """Texel rays built in numpy from the spot's to_world and cutoff (not from
    texel_rays); an asymmetric up vector pins the map's orientation to the
    emitter's local x/y."""
    q, n = [0.0, -1.0, 0.0], [0.1, 1.0, 0.05]
    n = list(np.asarray(n) / np.linalg.norm(n))
    to_world = T().look_at(origin=[0.2, 3.0, 0.1], target=[0, 0, 0], up=[0.3, 0.1, 1])
    # A tilted floor seen obliquely: the depths are not symmetric in u/v, so a
    # mirrored or rotated map orientation fails.
    _, view, smap = build({
        "floor": plane(q, n),
        "spot": {"type": "spot", "cutoff_angle": 40.0, "to_world": to_world}})
    o = np.array([0.2, 3.0, 0.1])
    d = spot_dirs_np(to_world, 40.0, RES)
    expected = plane_t(np.broadcast_to(o, d.shape), d, q, n)
    got = smap.to_numpy().reshape(-1)
    np.testing.assert_allclose(got, expected, rtol=1e-5)
    assert smap.to_numpy().shape == (1, RES, RES)
    # the map depends on its orientation: a transposed map would not match
    assert not np.allclose(smap.to_numpy()[0].T.reshape(-1), expected, rtol=1e-3)


def test_directional_depth_is_distance_from_light_plane():
    """Texel rays in numpy: all along the emitter's direction, starting on the map's
    near plane (through ``view.position``, orthogonal to the direction) at the
    documented texel centres of the ``half_extent`` rectangle."""
    q, n = [0.0, 0.0, 0.0], [0.0, 1.0, 0.0]
    direction = np.array([0.3, -1.0, 0.2]) / np.linalg.norm([0.3, -1.0, 0.2])
    _, view, smap = build({
        "floor": plane(q, n, size=3.0),
        "ball": {"type": "sphere", "center": [0, 1, 0], "radius": 0.5},
        "sun": {"type": "directional", "direction": direction.tolist()}})
    L = np.array(view.light_from_world.matrix, dtype=float)[:3, :3]
    np.testing.assert_allclose(L[2], direction, atol=1e-6)     # light +z = the direction
    np.testing.assert_allclose(L @ L.T, np.eye(3), atol=1e-6)  # a rigid frame
    _, s, t = texel_st(RES)
    hx, hy = view.half_extent
    o = (np.array([float(c) for c in view.position])
         + (s * hx)[:, None] * L[0] + (t * hy)[:, None] * L[1])
    d = np.broadcast_to(direction, o.shape)
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
    d = cube_dirs_np(RES)
    with np.errstate(divide="ignore"):
        t_axes = (np.sign(d) * h - c) / d
    expected = np.min(np.where(t_axes > 0, t_axes, np.inf), axis=1)
    got = smap.to_numpy().reshape(-1)
    per_face = np.abs(got - expected).reshape(6, -1).max(axis=1) / expected.max()
    assert np.all(per_face < 1e-5), per_face
    np.testing.assert_allclose(got, expected, rtol=1e-5)


FLOOR = {"type": "rectangle", "to_world": T().scale(10.0)}


def closed_box_around(position, half):
    return {"box": {"type": "cube", "to_world": T().translate(position).scale(half)},
            "floor": FLOOR}


@pytest.mark.parametrize("light", ["point", "spot"])
@pytest.mark.parametrize("half", [0.1, 0.3, 0.7])
def test_no_ray_escapes_a_closed_box_centred_on_the_light(light, half):
    """A light at the centre of a closed cube mesh: every texel's ray hits the cube.

    Texel centres lie on the faces' diagonals, here the planes of the cube's
    triangle diagonals; Embree misses rays exactly on a shared edge, so with
    rays through the exact centres 16-87 texels per cube map read the floor
    behind (a line of light through the box). base.TEXEL_SAMPLE moves the rays
    off those planes.
    """
    pos = [0.0, 0.0, 3.0]
    lamp = ({"type": "point", "position": pos} if light == "point" else
            {"type": "spot", "cutoff_angle": 40.0,
             "to_world": T().look_at(origin=pos, target=[0, 0, 0], up=[0, 1, 0])})
    _, view, smap = build({**closed_box_around(pos, half), "lamp": lamp})
    depth = smap.to_numpy().reshape(-1)
    assert np.all(depth >= half * (1 - 1e-5)), depth.min()
    escaped = np.flatnonzero(depth > half * np.sqrt(3.0) * (1 + 1e-5))
    assert escaped.size == 0, (escaped.size, depth[escaped[:5]])


def uv_sphere_mesh(centre, radius, n_lon, n_lat):
    """A closed UV-sphere mesh (poles as rings of coincident vertices): its meridian
    edges lie in planes through ``centre``."""
    theta = np.pi * np.arange(n_lat + 1) / n_lat
    phi = 2.0 * np.pi * np.arange(n_lon) / n_lon
    th, ph = np.meshgrid(theta, phi, indexing="ij")
    v = np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], -1)
    v = (np.asarray(centre) + radius * v).reshape(-1, 3).astype(np.float32)
    faces = []
    for j in range(n_lat):
        for i in range(n_lon):
            a, b = j * n_lon + i, j * n_lon + (i + 1) % n_lon
            c, d = a + n_lon, b + n_lon
            faces += [[a, c, b], [b, c, d]]
    faces = np.asarray(faces, np.uint32)
    mesh = mi.Mesh("ball", len(v), len(faces))
    params = mi.traverse(mesh)
    params["vertex_positions"] = mi.Float(v.ravel())
    params["faces"] = mi.UInt32(faces.ravel())
    params.update()
    return mesh


@pytest.mark.parametrize("segments", [(8, 4), (16, 8)])
def test_no_ray_escapes_a_closed_uv_sphere_centred_on_the_light(segments):
    """The same for a sphere mesh: with rays through the exact centres its cube map
    had texels reading the floor through it (measured: 61 lit pixels over 8 spheres)."""
    pos, radius = [0.0, 0.0, 3.0], 0.3
    _, view, smap = build({"ball": uv_sphere_mesh(pos, radius, *segments),
                           "floor": FLOOR, "lamp": {"type": "point", "position": pos}})
    depth = smap.to_numpy().reshape(-1)
    escaped = np.flatnonzero(depth > radius * (1 + 1e-4))
    assert escaped.size == 0, (escaped.size, depth[escaped[:5]])


@pytest.mark.parametrize("virtual", [True, False])
def test_nothing_lit_outside_a_closed_box_around_a_point_light(virtual):
    """The same through the whole render, virtual pages included: the floor and
    the box's outside stay dark for hard and pcf."""
    pos = [0.0, 0.0, 3.0]
    scene = mi.load_dict({
        "type": "scene", **closed_box_around(pos, 0.3),
        "lamp": {"type": "point", "position": pos, "intensity": {"type": "rgb", "value": 20.0}},
        "cam": {"type": "perspective", "fov": 45.0,
                "to_world": T().look_at(origin=[6, -6, 5], target=[0, 0, 0.5], up=[0, 0, 1]),
                "film": {"type": "hdrfilm", "width": 48, "height": 48,
                         "rfilter": {"type": "box"}}}})
    for method in ("hard", "pcf"):
        integ = mi.load_dict({"type": "shadowmap", "method": method, "virtual": virtual})
        img = np.asarray(mi.render(scene, integrator=integ, spp=4, seed=1))
        assert np.all(img == 0.0), (method, int(np.count_nonzero(img[..., 3])))


@pytest.mark.parametrize("cutoff", [40.0, 79.0, 80.0, 90.0, 170.0])
def test_wide_spot_gets_cube_faces_at_the_spot(cutoff):
    """Below ``WIDE_SPOT_CUTOFF`` one perspective face covers the cone; from there on
    (Mitsuba allows any cutoff; 90 and more cover a half space or beyond) six cube faces
    at the spot's position, whose depths are the distances to the room's walls, and the
    spot's own frame (PCSS's and ``multiview``'s light square)."""
    from mi_shadowmap.light_views import CubeView, PerspectiveView
    from mi_shadowmap.light_views.perspective import WIDE_SPOT_CUTOFF
    c, h = np.array([0.3, -0.2, 0.5]), 2.0
    walls = {}
    for a in range(3):
        for s in (1.0, -1.0):
            q, nrm = [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]
            q[a], nrm[a] = s * h, -s
            walls[f"wall{a}{int(s)}"] = plane(q, nrm, size=h)
    to_world = T().look_at(origin=c.tolist(), target=[1.0, -1.0, 0.7], up=[0, 0, 1])
    _, view, smap = build({**walls, "lamp": {"type": "spot", "cutoff_angle": cutoff,
                                              "to_world": to_world}})
    if cutoff < WIDE_SPOT_CUTOFF:
        assert isinstance(view, PerspectiveView)
        return
    assert isinstance(view, CubeView) and view.kind == "spot" and view.label == "lamp"
    np.testing.assert_allclose(np.array(view.light_from_world.matrix),
                               np.array(to_world.inverse().matrix), atol=1e-6)
    d = cube_dirs_np(RES)
    with np.errstate(divide="ignore"):
        t_axes = (np.sign(d) * h - c) / d
    expected = np.min(np.where(t_axes > 0, t_axes, np.inf), axis=1)
    np.testing.assert_allclose(smap.to_numpy().reshape(-1), expected, rtol=1e-5)


def test_projector_gets_cube_faces_at_its_position():
    from mi_shadowmap.light_views import CubeView
    to_world = T().look_at(origin=[0.3, -0.2, 0.5], target=[1.0, -1.0, 0.7], up=[0, 0, 1])
    scene = mi.load_dict({"type": "scene", "floor": plane([0, -1, 0], [0, 1, 0]),
                          "lamp": {"type": "projector", "fov": 30, "to_world": to_world}})
    view = make_light_view(scene.emitters()[0], scene, 0)
    assert isinstance(view, CubeView) and view.kind == "projector" and view.label == "lamp"
    np.testing.assert_allclose(np.array(view.position), [0.3, -0.2, 0.5], atol=1e-6)
    np.testing.assert_allclose(np.array(view.light_from_world.matrix),
                               np.array(to_world.inverse().matrix), atol=1e-6)
    smap = build_depth_map(scene, view, 16)
    d = cube_dirs_np(16)
    with np.errstate(divide="ignore"):
        t = (-1.0 - (-0.2)) / d[:, 1]        # the floor plane y = -1 (100 wide)
    expected = np.where(t > 0, t, np.inf)
    np.testing.assert_allclose(smap.to_numpy().reshape(-1), expected, rtol=1e-5)


def test_spot_without_a_cone_is_refused_by_name():
    scene = mi.load_dict({"type": "scene", "lamp": {"type": "spot", "cutoff_angle": 0.0}})
    with pytest.raises(ValueError, match="lamp.*cutoff_angle=0.0.*> 0"):
        make_light_view(scene.emitters()[0], scene, 0)


@pytest.mark.parametrize("beam", [float("nan"), float("inf")])
def test_spot_with_a_beam_width_that_is_not_finite_is_refused_by_name(beam):
    """Mitsuba loads it; ``direct`` rendered NaN inside the cone (NaN) or black (inf),
    and every method here black with visibility AOV 0."""
    scene = mi.load_dict({"type": "scene", "lamp": {"type": "spot", "cutoff_angle": 30.0,
                                                    "beam_width": beam}})
    with pytest.raises(ValueError, match="lamp.*beam_width=(nan|inf).*finite"):
        make_light_view(scene.emitters()[0], scene, 0)


def test_projection_inverts_texel_rays():
    """Every texel's own hit point looks up that texel, at its stored depth."""
    scene = mi.load_dict({"type": "scene", "ball": {"type": "sphere", "radius": 5.0},
                          "lamp": {"type": "point", "position": [0.5, 0.2, -0.3]}})
    view = make_light_view(scene.emitters()[0], scene, 0)
    smap = build_depth_map(scene, view, 32)
    o, d = view.texel_rays(32)
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


def test_exr_export_with_one_drjit_thread(tmp_path):
    """After ``dr.set_thread_count(1)`` Mitsuba 3.9.1's ``mi.Bitmap(...).write`` of an
    EXR never returns (its OpenEXR tasks wait for a thread that is not there): the
    export hung. Run in a child process, so a hang is a timeout, not a stuck suite."""
    import subprocess
    import sys
    import textwrap
    path = tmp_path / "one_thread.exr"
    code = textwrap.dedent(f"""
        import drjit as dr, mitsuba as mi, numpy as np
        import mi_shadowmap
        from mi_shadowmap.depth_maps import build_depth_map, write_exr
        from mi_shadowmap.light_views import make_light_view
        scene = mi.load_dict({{"type": "scene",
                              "floor": {{"type": "rectangle"}},
                              "lamp": {{"type": "point", "position": [0, 0, 1]}}}})
        smap = build_depth_map(scene, make_light_view(scene.emitters()[0], scene, 0), 8)
        dr.set_thread_count(1)
        write_exr(smap, {str(path)!r})
        dr.set_thread_count(2)
        back = np.asarray(mi.Bitmap({str(path)!r})).reshape(6, 8, 8)
        assert np.array_equal(back, smap.to_numpy())
        print("written")
    """)
    try:
        run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                             timeout=120)
    except subprocess.TimeoutExpired:
        pytest.fail("write_exr did not return within 120 s with one Dr.Jit thread")
    assert run.returncode == 0 and "written" in run.stdout, run.stderr[-2000:]


def test_unsupported_emitter_is_named():
    scene = mi.load_dict({"type": "scene", "env": {"type": "constant"}})
    with pytest.raises(ValueError, match="env.*not supported.*point, spot, directional, area"):
        make_light_view(scene.emitters()[0], scene, 0)


def test_summed_area_table_and_box_mean_against_numpy():
    """The prefiltered methods' tables: float64 sums per face equal numpy's cumulative
    sums, and a box mean with fractional edges equals the texel values weighted by
    their covered area (computed independently, cell by cell)."""
    from mi_shadowmap.depth_maps import box_mean, summed_area_table
    rng = np.random.default_rng(1)
    faces, res = 3, 16
    a = rng.random((faces, res, res)).astype(np.float32)
    sat = summed_area_table(mi.Float(a.ravel()), faces, res)
    expected = np.cumsum(np.cumsum(a.astype(np.float64), axis=2), axis=1)
    np.testing.assert_allclose(np.asarray(sat).reshape(faces, res, res), expected, rtol=1e-12)

    def covered_mean(f, x0, y0, x1, y1):
        x0, y0, x1, y1 = (min(max(v, 0.0), res) for v in (x0, y0, x1, y1))
        total = area = 0.0
        for j in range(res):
            for i in range(res):
                w = max(0.0, min(x1, i + 1) - max(x0, i)) * max(0.0, min(y1, j + 1) - max(y0, j))
                total += w * a[f, j, i]
                area += w
        return total / area

    boxes = [(0, 0.0, 0.0, 16.0, 16.0), (1, 2.5, 3.25, 9.75, 4.5), (2, 7.1, 7.2, 7.9, 7.6),
             (2, -3.0, 14.5, 2.0, 20.0)]
    got = box_mean(sat, res, mi.UInt32([b[0] for b in boxes]),
                   mi.Point2f([b[1] for b in boxes], [b[2] for b in boxes]),
                   mi.Point2f([b[3] for b in boxes], [b[4] for b in boxes]))
    want = [covered_mean(*b) for b in boxes]
    np.testing.assert_allclose(np.asarray(got), want, rtol=1e-5)


def test_coherent_and_incoherent_ray_queries_give_the_same_maps(monkeypatch):
    """``depth_maps.COHERENT_RAYS`` follows the CPU (Embree's coherent mode on
    AVX-512): either way a full cube map and a render on virtual pages (the mark pass's
    camera rays and the page casts) are bit-identical to the other mode's."""
    from mi_shadowmap import depth_maps
    pos = [0.0, 0.0, 3.0]
    scene = mi.load_dict({
        "type": "scene", "ball": uv_sphere_mesh([0.4, 0.2, 1.5], 0.5, 16, 8),
        "floor": FLOOR, "lamp": {"type": "point", "position": pos,
                                 "intensity": {"type": "rgb", "value": 20.0}},
        "cam": {"type": "perspective", "fov": 45.0,
                "to_world": T().look_at(origin=[6, -6, 5], target=[0, 0, 0.5], up=[0, 0, 1]),
                "film": {"type": "hdrfilm", "width": 48, "height": 48,
                         "rfilter": {"type": "box"}}}})
    view = make_light_view(scene.emitters()[0], scene, 0)

    def maps_and_image(mode):
        monkeypatch.setattr(depth_maps, "COHERENT_RAYS", mode)
        depth = build_depth_map(scene, view, RES).to_numpy()
        integ = mi.load_dict({"type": "shadowmap", "method": "hard", "cache_maps": False})
        return depth, np.asarray(mi.render(scene, integrator=integ, spp=4, seed=1))

    depth_a, img_a = maps_and_image(True)
    depth_b, img_b = maps_and_image(False)
    # a shadowed floor (the first AOV: the lamp's visibility) and lit pixels
    assert np.isfinite(depth_a).any() and 0 < np.count_nonzero(img_a[..., 3] < 0.5) < 48 * 48 / 2
    np.testing.assert_array_equal(depth_a, depth_b)
    np.testing.assert_array_equal(img_a, img_b)


@pytest.mark.parametrize("light", [
    {"type": "directional", "direction": [0.1, 0.05, -1.0], "irradiance": 1.0},
    {"type": "spot", "cutoff_angle": 70, "intensity": 10.0,
     "to_world": T().look_at(origin=[0.3, 0.2, 5.0], target=[0, 0, 0], up=[0, 1, 0])}],
    ids=["directional", "spot"])
def test_fit_frusta_keeps_every_visible_receiver_in_the_map(light):
    """``fit_frusta`` fits the map to the camera-visible receivers (plus a margin): every
    one of them must project inside it. Under a plate covering the whole view the ground
    the camera sees is in shadow up to the image's border; a receiver left outside the
    fitted window counts as lit (Reeves), so a window fitted 10 % too small (mutation
    audit) lit the border: 10.6 % of the pixels false lit under the sun."""
    from conftest import render_np
    scene = mi.load_dict({
        "type": "scene",
        "cam": {"type": "perspective", "fov": 60,
                "to_world": T().look_at(origin=[0, 0, 1.0], target=[0, 0, 0], up=[0, 1, 0]),
                "film": {"type": "hdrfilm", "width": 48, "height": 48},
                "sampler": {"type": "independent", "sample_count": 2}},
        "light": light,
        "ground": {"type": "rectangle", "to_world": T().scale(10.0)},
        "plate": {"type": "rectangle", "to_world": T().translate([0, 0, 2.0]).scale(10.0),
                  "flip_normals": True}})
    for props in ({"method": "raytraced"},
                  {"method": "hard", "fit_frusta": True, "resolution": 256}):
        _, aovs = render_np(scene, {"type": "shadowmap", **props}, spp=2)
        (vis,) = aovs.values()
        assert np.count_nonzero(vis >= 0.5) == 0, props


@pytest.mark.parametrize("light", ["directional", "spot"])
def test_fit_frusta_leaves_eight_texels_around_the_visible_receivers(light):
    """``fit_frusta`` grows the fitted window by ``(8 + normal_bias)`` texels of the map
    per side (normal offsets and filter taps of the outermost receivers), so the
    outermost visible point lies about 8 texels inside the fitted map; half that margin
    went unnoticed by the renders above (mutation audit: ``OrthoView.fit``'s and
    ``_aimed_extents``' growth halved)."""
    from mi_shadowmap.options import parse_options
    lights = {"directional": {"type": "directional", "direction": [0.2, -1.0, 0.3]},
              "spot": {"type": "spot", "cutoff_angle": 60.0,
                       "to_world": T().look_at(origin=[0.5, 6.0, 0.2], target=[0, 0, 0],
                                               up=[0, 0, 1])}}
    scene = mi.load_dict({"type": "scene", "light": lights[light],
                          "ground": plane([0, 0, 0], [0, 1, 0], 20.0)})
    view = make_light_view(scene.emitters()[0], scene, 0)
    res = 256
    opts = parse_options({"method": "hard", "fit_frusta": True, "resolution": res})
    rng = np.random.default_rng(1)
    visible = np.stack([rng.uniform(-1.0, 2.0, 500), np.zeros(500),
                        rng.uniform(-1.5, 0.5, 500)], 1)
    fitted, gain = view.refine(opts, scene, None, visible, res)
    assert gain > 4.0                                   # the window did shrink
    _, uv, _, inside = fitted.project(mi.Point3f(*(mi.Float(visible[:, k]) for k in range(3))))
    assert np.all(inside.numpy())
    u, v = uv.x.numpy(), uv.y.numpy()
    border = res * np.minimum(np.minimum(u, 1 - u), np.minimum(v, 1 - v)).min()
    print(f"{light}: the outermost visible point {border:.2f} texels inside the fitted map")
    assert 7.5 <= border <= 9.0


def test_a_rectangular_faces_texels_are_as_wide_as_its_rays_are_apart():
    """``PerspectiveView.texel_parallel_xy`` of a rectangular face (a far light's face
    aimed at the scene, ``tan_half_y`` < ``tan_half``): a texel's world widths along the
    face's x and y, parallel to its image plane at the point's axial depth, are the
    distances between the rays through neighbouring texels there (PCSS sizes its kernels
    in texels per axis by them; both widths taken along x went unnoticed, mutation
    audit)."""
    from mi_shadowmap.light_views.perspective import PerspectiveView
    res = 64
    view = PerspectiveView("point", mi.ScalarPoint3f(0, 0, 0), T(), label="r",
                           tan_half=1.0, tan_half_y=0.25)
    p = np.array([0.6, -0.3, 4.0])
    P = mi.Point3f(*[float(c) for c in p])
    face, uv, depth, inside = view.project(P)
    assert bool(inside[0])
    uv = np.array([uv.x[0], uv.y[0]])

    def at_depth(du, dv):        # the ray through uv + (du, dv) at the point's axial depth
        o, d = view.ray_through(face, mi.Point2f(float(uv[0] + du), float(uv[1] + dv)))
        d = np.array([d.x[0], d.y[0], d.z[0]], np.float64)
        return d * (p[2] / d[2])
    h = 0.5 / res
    want_x = np.linalg.norm(at_depth(h, 0) - at_depth(-h, 0))
    want_y = np.linalg.norm(at_depth(0, h) - at_depth(0, -h))
    w_x, w_y = view.texel_parallel_xy(res, face, P, view.texel_world_size(res, depth, P, None))
    assert float(w_x[0]) == pytest.approx(want_x, rel=1e-4)
    assert float(w_y[0]) == pytest.approx(want_y, rel=1e-4)
    assert want_y == pytest.approx(0.25 * want_x, rel=1e-4)


@pytest.mark.parametrize("props", [{}, {"resolution": 256}], ids=["virtual", "full"])
def test_a_directional_map_covers_the_scene_to_its_edges(props):
    """A directional light's map is fitted to the scene's bounds (``directional_view``):
    a receiver at the edge of the scene must still project inside it. A sun straight
    down on a ground under a plate of the same size, seen from between them to beyond
    the ground's edges: every ground pixel is shadowed. A window 10 % too small
    (mutation audit: it passed test_depth_maps and test_cascades) lit the ground's rim,
    152 of the 48^2 pixels, on virtual and full maps alike."""
    from conftest import render_np
    scene = mi.load_dict({
        "type": "scene",
        "cam": {"type": "perspective", "fov": 120,
                "to_world": T().look_at(origin=[0, 0, 0.9], target=[0, 0, 0], up=[0, 1, 0]),
                "film": {"type": "hdrfilm", "width": 48, "height": 48},
                "sampler": {"type": "independent", "sample_count": 2}},
        "sun": {"type": "directional", "direction": [0, 0, -1], "irradiance": 1.0},
        "ground": {"type": "rectangle"},
        "plate": {"type": "rectangle", "to_world": T().translate([0, 0, 1.0]),
                  "flip_normals": True}})
    _, aovs = render_np(scene, {"type": "shadowmap", "method": "hard", **props}, spp=2)
    (vis,) = aovs.values()
    assert np.count_nonzero(vis >= 0.5) == 0
    _, aovs = render_np(scene, {"type": "shadowmap", "method": "raytraced"}, spp=2)
    (vis,) = aovs.values()
    assert np.count_nonzero(vis >= 0.5) == 0


def nested_boxes(path, centre, halves):
    """A PLY of closed, outward, welded boxes (``procedural.box``) nested about
    ``centre``, one per half size of ``halves``, as one mesh."""
    from mi_shadowmap.procedural import box, merge, write_ply
    parts = []
    for h in halves:
        v, f, _ = box((h, h, h))
        parts.append((v + np.asarray(centre, np.float32), f, None))
    v, f, _ = merge(*parts)
    return write_ply(str(path), v, f)


def test_a_map_ray_skips_many_layers_of_the_lights_own_shape(tmp_path):
    """``first_hit`` skips up to 32 hits of the emitter's own shape along a ray: an area
    light on 6 nested box shells (its rays from the centre cross all 6) still sees the
    plate above it; a loop stopped after 2 skips stored +inf there, lit (mutation
    audit)."""
    path = nested_boxes(tmp_path / "shells.ply", [0, 0, 0], [0.05, 0.07, 0.09, 0.11, 0.13, 0.15])
    scene, view, smap = build({
        "lamp": {"type": "ply", "filename": path, "face_normals": True,
                 "emitter": {"type": "area", "radiance": 1.0}},
        "plate": plane([0, 2.0, 0], [0, -1, 0], 1.0)}, res=16)
    assert view.kind == "area"
    up = smap.to_numpy()[2]              # face 2: +y
    centre = up[6:10, 6:10]              # texels whose rays meet the plate (|s|, |t| < 0.5)
    assert np.all(np.isfinite(centre))
    d = cube_dirs_np(16)[2 * 256:3 * 256].reshape(16, 16, 3)[6:10, 6:10]
    np.testing.assert_allclose(centre, 2.0 / d[..., 1], rtol=1e-4)


def test_second_depth_passes_many_nested_solids(tmp_path):
    """``second_depth_along`` continues past up to 64 hits: a ray down through 8 nested
    closed boxes enters all 8 (front faces, skipped) before it leaves the innermost one,
    whose bottom is the second surface; a loop stopped after 6 hits stored +inf, and the
    ground under the boxes was lit (mutation audit)."""
    from mi_shadowmap.depth_maps import second_depth_along
    halves = [0.1 + 0.05 * k for k in range(8)]
    path = nested_boxes(tmp_path / "nest.ply", [0, 1.0, 0], halves)
    scene = mi.load_dict({"type": "scene",
                          "nest": {"type": "ply", "filename": path, "face_normals": True},
                          "ground": plane([0, 0, 0], [0, 1, 0], 5.0),
                          "light": {"type": "point", "position": [0, 3.0, 0]}})
    view = make_light_view(scene.emitters()[0], scene, 0)
    xs = [-0.02, 0.0, 0.03]
    d = mi.Vector3f(mi.Float(xs), mi.Float([-1.0] * 3), mi.Float([0.02, 0.0, -0.01]))
    d = dr.normalize(d)
    z2 = second_depth_along(scene, view, mi.Point3f(0, 3.0, 0), d).numpy()
    dy = d.y.numpy()
    want = (3.0 - (1.0 - halves[0])) / -dy     # the innermost box's bottom
    np.testing.assert_allclose(z2, want, rtol=1e-4)


def test_vertex_welding_numbers_rows_as_numpy_unique_does():
    """``depth_maps._weld`` (one lexsort) numbers the vertices equal at 5 decimals as
    ``np.unique(..., axis=0, return_inverse=True)`` did (duplicates, signed zeros,
    values that round together); it replaced that call, most of the face-solidity
    pass's time on large meshes."""
    from mi_shadowmap.depth_maps import _weld
    rng = np.random.default_rng(3)
    v = rng.integers(-3, 4, (500, 3)).astype(np.float64) * 0.5
    v[::7] += 2e-6                   # rounds onto its neighbour at 5 decimals
    v[::11] *= -1.0                  # signed zeros
    v = np.concatenate([v, v[::3]])
    weld, count = _weld(v)
    _, expected = np.unique(np.round(v, 5), axis=0, return_inverse=True)
    assert count == int(expected.max()) + 1
    assert np.array_equal(weld, expected.reshape(-1))
    assert _weld(np.zeros((0, 3)))[1] == 0


def test_flat_shaded_meshes_need_no_solid_tables(tmp_path):
    """Every map method's lookup pays a per-hit test where ``solid_face_tables`` has
    faces. A ``cube`` and a ``rectangle`` carry vertex normals equal to their faces'
    (as does a mesh exported flat): their shading frame is the geometric one, so light
    from behind a face is never reflected and they need no entry. The scenes of
    ``scenes_xml/`` got tables (and the per-hit test) for their cubes and walls when the
    terminator rule reached every map method; a smooth-shaded icosahedron keeps its."""
    from mi_shadowmap.depth_maps import solid_face_tables
    from mi_shadowmap.procedural import _icosphere, write_ply
    T = mi.ScalarTransform4f
    flat = {"type": "scene",
            "box": {"type": "cube", "to_world": T().translate([0, 1, 0])},
            "floor": {"type": "rectangle", "to_world": T().scale(5)}}
    assert solid_face_tables(mi.load_dict(flat)) is None
    v, f = _icosphere(0)
    tri = v[f].reshape(-1, 3)           # unshared vertices, each with its face's normal
    n = np.cross(tri[1::3] - tri[0::3], tri[2::3] - tri[0::3])
    n = np.repeat(n / np.linalg.norm(n, axis=1, keepdims=True), 3, axis=0)
    faces = np.arange(len(tri)).reshape(-1, 3)
    flat_ply = write_ply(str(tmp_path / "flat.ply"), tri, faces, normals=n)
    smooth_ply = write_ply(str(tmp_path / "smooth.ply"), v, f, normals=v)
    assert solid_face_tables(mi.load_dict(
        {**flat, "ball": {"type": "ply", "filename": flat_ply}})) is None
    tables = solid_face_tables(mi.load_dict(
        {**flat, "ball": {"type": "ply", "filename": smooth_ply}}))
    assert tables is not None and int(np.count_nonzero(tables[1].numpy())) == len(f)


def test_a_warm_frame_does_not_scan_the_scene_for_solid_meshes(monkeypatch, tmp_path):
    """Every map method reads which faces bound solids (the terminator rule) every
    render; the scene's shapes and their shapegroups' meshes (a ``mi.traverse`` of the
    whole scene) were found again each time: a warm ``hard`` frame of 300 cubes and an
    instance made 25k Python calls against 7.6k before. They are remembered while the
    scene lists the same shapes; the image is the same."""
    from mi_shadowmap import depth_maps
    T = mi.ScalarTransform4f
    d = {"type": "scene",
         "cam": {"type": "perspective", "fov": 40,
                 "to_world": T().look_at([0, 4, 6], [0, 0, 0], [0, 1, 0]),
                 "film": {"type": "hdrfilm", "width": 16, "height": 16,
                          "rfilter": {"type": "box"}}},
         "light": {"type": "point", "position": [0, 5, 0], "intensity": 30.0},
         "floor": {"type": "rectangle", "to_world": T().rotate([1, 0, 0], -90).scale(4)},
         "grp": {"type": "shapegroup", "s": {"type": "sphere", "radius": 0.3}},
         "inst": {"type": "instance", "shapegroup": {"type": "ref", "id": "grp"},
                  "to_world": T().translate([1, 1, 0])},
         "ball": {"type": "ply", "filename": _smooth_icosphere_ply(tmp_path)}}
    scene = mi.load_dict(d)
    integ = mi.load_dict({"type": "shadowmap", "method": "hard"})
    first = np.asarray(mi.render(scene, integrator=integ, spp=1))
    assert depth_maps.solid_face_tables(scene) is not None     # the ball is a solid
    calls = []
    real = depth_maps._grouped_shapes
    monkeypatch.setattr(depth_maps, "_grouped_shapes",
                        lambda *a: calls.append(1) or real(*a))
    again = np.asarray(mi.render(scene, integrator=integ, spp=1))
    assert calls == []
    assert np.array_equal(first, again)


def _smooth_icosphere_ply(folder) -> str:
    """A smooth (vertex normals) 80-face icosphere at (-1, 1, 0) as a PLY file in
    ``folder`` (a test's ``tmp_path``: a temporary folder of its own was never removed)."""
    from mi_shadowmap.procedural import _icosphere, write_ply
    v, f = _icosphere(1)
    v = np.asarray(v) * 0.5 + np.array([-1.0, 1.0, 0.0])
    n = v - np.array([-1.0, 1.0, 0.0])
    return write_ply(str(folder / "ico.ply"), v, f, normals=n)
