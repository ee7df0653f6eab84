"""Reeves, Salesin & Cook 1987 percentage-closer filtering (``method="pcf"``).

Unit tests build a :class:`ShadowMap` by hand (an orthographic light looking
along +z, a depth array written directly) and call the filter with
:class:`Lookup` objects; scene tests compare with the ray-traced reference.
"""
import math

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from conftest import (SCENE_FILES, frosted_bulb_scene, grazed_wall, own_and_widest_marks,
                      render_np, vis_stack)
from mi_shadowmap import metrics
from mi_shadowmap.depth_maps import ShadowMap
from mi_shadowmap import methods
from mi_shadowmap.filters.common import Lookup
from mi_shadowmap.filters.pcf import reeves_sample_counts
from mi_shadowmap.light_views import CascadedView, CubeView, OrthoView
from mi_shadowmap.options import OptionError, parse_options

RES = 64
TEXEL = 2.0 / RES          # world width of a texel (half_extent 1)
SAMPLINGS = ("jitter", "uniform", "gaussian")


def ortho_map(depth: np.ndarray) -> ShadowMap:
    """Orthographic map over [-1, 1]^2 looking along +z; depth[j, i] (row j = v)."""
    res = depth.shape[0]
    view = OrthoView("directional", mi.ScalarPoint3f(0, 0, 0),
                     mi.ScalarTransform4f(), half_extent=(1.0, 1.0), label="unit")
    return ShadowMap(view, res, mi.Float(np.asarray(depth, np.float32).ravel()))


def edge_map() -> ShadowMap:
    """Columns i < RES/2 hold an occluder at depth 1; the rest is empty (+inf)."""
    d = np.full((RES, RES), np.inf, np.float32)
    d[:, : RES // 2] = 1.0
    return ortho_map(d)


def lookup(x, y=0.01, z=2.0, footprint=4.0, seed=0, n=(0.0, 0.0, -1.0)):
    """Receivers at world (x, y, z) facing the light, pixel footprint in texels."""
    x = np.atleast_1d(np.asarray(x, np.float64))
    N = x.size
    p = mi.Point3f(mi.Float(x), mi.Float(np.full(N, y)), mi.Float(np.full(N, z)))
    w = footprint * TEXEL
    sampler = mi.load_dict({"type": "independent"})
    sampler.seed(seed, N)
    return Lookup(p, dr.normalize(mi.Vector3f(*n)), mi.Vector3f(w, 0, 0), mi.Vector3f(0, w, 0),
                  None, None, sampler)


def pcf_vis(smap, lk, **props):
    opts = parse_options({"method": "pcf", **props})
    v = methods.get("pcf").lookup(smap, lk, opts, mi.Bool(True))
    return np.asarray(v.numpy(), np.float64)


def repeat_sweep(offsets_texels, lanes):
    """World x of each offset (in texels from the edge), repeated ``lanes`` times."""
    return np.repeat(np.asarray(offsets_texels) * TEXEL, lanes)


# --------------------------------------------------------------- hand-made edge
@pytest.mark.parametrize("sampling", SAMPLINGS)
def test_edge_half_far_exact_and_monotone(sampling):
    smap = edge_map()
    lanes = 2048
    offs = np.arange(-4.0, 4.01, 0.5)
    v = pcf_vis(smap, lookup(repeat_sweep(offs, lanes)), sampling=sampling)
    mean = v.reshape(len(offs), lanes).mean(axis=1)
    at_edge = mean[np.argmin(np.abs(offs))]
    print(sampling, "mean visibility across the edge:", np.round(mean, 3))
    if sampling == "jitter":
        # a 4x4-texel region, 4x4 stratified cells: 2 columns each side, exactly
        # (a jitter of 1 - 2^-24 can round onto the next texel: a few lanes differ)
        assert np.mean(v.reshape(len(offs), lanes)[np.argmin(np.abs(offs))] == 0.5) > 0.99
    assert abs(at_edge - 0.5) < 0.02
    if sampling == "gaussian":   # truncated normal, sigma = half-width / 2 = 1 texel
        phi = np.vectorize(lambda z: 0.5 * (1.0 + math.erf(z / math.sqrt(2.0))))
        expected = (phi(2.0) - phi(np.clip(-offs, -2.0, 2.0))) / (phi(2.0) - phi(-2.0))
    else:                        # box filter of the 4-texel region: a linear ramp
        expected = np.clip(0.5 + offs / 4.0, 0.0, 1.0)
    np.testing.assert_allclose(mean, expected, atol=0.03)
    assert np.all(np.diff(mean) >= -0.01)      # monotone (up to noise)
    assert mean[-1] - mean[0] > 0.99
    # far from the edge: exactly lit / exactly shadowed, every lane
    far = pcf_vis(smap, lookup(np.array([-0.5] * 64 + [0.5] * 64)), sampling=sampling)
    assert np.all(far[:64] == 0.0) and np.all(far[64:] == 1.0)


@pytest.mark.parametrize("footprint,res_factor,min_size", [
    (4.0, 1.0, 1.0),    # region = one pixel footprint (4 texels)
    (4.0, 2.0, 1.0),    # res_factor scales it (8 texels)
    (0.5, 1.0, 3.0),    # min_size raises it (3 texels)
    (0.0, 1.0, 1.0),    # no footprint: min_size (1 texel)
])
def test_region_is_scaled_footprint_clamped_to_min_size(footprint, res_factor, min_size):
    """Jittered PCF of a straight edge is the box filter of the region: a linear ramp."""
    width = max(footprint * res_factor, min_size)
    smap = edge_map()
    lanes = 1024
    offs = np.array([-0.75, -0.5, -0.25, 0.0, 0.25, 0.5, 0.75]) * width
    v = pcf_vis(smap, lookup(repeat_sweep(offs, lanes), footprint=footprint),
                res_factor=res_factor, min_size=min_size)
    mean = v.reshape(len(offs), lanes).mean(axis=1)
    expected = np.clip(0.5 + offs / width, 0.0, 1.0)
    print(f"width {width}: measured {np.round(mean, 3)}, box filter {expected}")
    np.testing.assert_allclose(mean, expected, atol=0.03)


def test_sample_counts_follow_figure_4():
    cases = {  # (width_s, width_t, num_samples, min_samples) -> (ns, nt), by hand
        (4, 4, 16, 2): (4, 4),      # 16 texels: not < 16 -> sqrt branch
        (1, 1, 16, 2): (2, 2),      # one per texel, raised to min_samples
        (3, 5, 16, 1): (3, 5),      # small region: one per texel
        (2, 8, 16, 2): (2, 8),      # nt = sqrt(8*16/2) = 8, ns = 16/8 = 2
        (0.2, 30, 16, 2): (2, 16),  # 6 texels: ns = 0 -> 2, nt = 30 -> 16
        (10, 10, 16, 1): (4, 4),
        (100, 1, 64, 2): (32, 2),   # nt = sqrt(64/100)+.5 -> 1 -> 2; ns = 64/2 = 32
        # ns rounds too: nt = sqrt(4*17/6)+.5 = 3.87 -> 3; ns = 17/3+.5 = 6.17 -> 6 (a
        # truncated 17/3 gives 5: mutation audit)
        (6, 4, 17, 2): (6, 3),
    }
    for (ws, wt, n, m), want in cases.items():
        ns, nt = reeves_sample_counts(mi.Float(ws), mi.Float(wt), n, m)
        assert (int(ns[0]), int(nt[0])) == want, (ws, wt, n, m)


@pytest.mark.parametrize("num_samples,levels", [(16, 17), (4, 5)])
def test_levels_are_num_samples_plus_one(num_samples, levels):
    """Reeves: the result filters num_samples binary values -> num_samples + 1 levels."""
    smap = edge_map()
    x = np.linspace(-4 * TEXEL, 4 * TEXEL, 4096)
    v = pcf_vis(smap, lookup(x), num_samples=num_samples, sampling="uniform")
    assert np.allclose(v * num_samples, np.round(v * num_samples), atol=1e-6)
    assert metrics.distinct_levels(v) == levels


def test_stochastic_bias_is_drawn_per_sample():
    """Receiver 0.015 behind a flat occluder at depth 1 (no other bias)."""
    smap = ortho_map(np.full((RES, RES), 1.0, np.float32))
    x = np.linspace(-0.5, 0.5, 4096)
    base = dict(slope_bias=0.0, normal_bias=0.0)
    assert np.all(pcf_vis(smap, lookup(x, z=1.015), **base) == 0.0)
    v = pcf_vis(smap, lookup(x, z=1.015), bias_range="0.01, 0.02", **base)
    print("mean visibility with bias in [0.01, 0.02]:", v.mean())
    assert abs(v.mean() - 0.5) < 0.02          # P(bias >= 0.015) = 1/2
    assert np.mean((v > 0) & (v < 1)) > 0.5    # per-sample draws: mostly partial values
    assert np.all(pcf_vis(smap, lookup(x, z=1.015), bias_range="0.02, 0.03", **base) == 1.0)
    # a degenerate range [b, b] is the constant bias b on every sample (mutation audit:
    # bias0 was dropped when bias1 == bias0)
    assert np.all(pcf_vis(smap, lookup(x, z=1.015), bias_range="0.02, 0.02", **base) == 1.0)
    assert np.all(pcf_vis(smap, lookup(x, z=1.015), bias_range="0.01, 0.01", **base) == 0.0)


def test_footprint_is_the_bounding_box_of_a_turned_pixel():
    """Reeves et al. 1987: the region is the bounding box of the shaded area's
    projected corners. A pixel footprint of side 4 texels turned 45 degrees on a plane
    facing the light spans 4 sqrt(2) texels per axis (``|e1| + |e2|`` per axis); its
    equal-variance width is the side, 4 (``sqrt(e1^2 + e2^2)``). An axis-aligned
    footprint cannot tell the bounding box from the larger edge (mutation audit)."""
    from mi_shadowmap.filters.common import footprint_texels, receiver
    smap = edge_map()
    h = 4.0 * TEXEL / math.sqrt(2.0)
    p = mi.Point3f(mi.Float([0.3]), mi.Float([0.01]), mi.Float([2.0]))
    sampler = mi.load_dict({"type": "independent"})
    sampler.seed(0, 1)
    lk = Lookup(p, mi.Vector3f(0.0, 0.0, -1.0), mi.Vector3f(h, h, 0.0), mi.Vector3f(-h, h, 0.0),
                None, None, sampler)
    r = receiver(smap, lk, parse_options({"method": "pcf"}))
    box = footprint_texels(smap, lk, r)
    var = footprint_texels(smap, lk, r, equal_variance=True)
    np.testing.assert_allclose([box.x[0], box.y[0]], [4.0 * math.sqrt(2.0)] * 2, rtol=1e-4)
    np.testing.assert_allclose([var.x[0], var.y[0]], [4.0, 4.0], rtol=1e-4)


def test_off_map_samples_are_lit():
    smap = ortho_map(np.full((RES, RES), 1.0, np.float32))   # everything occluded
    # a receiver half a texel inside the right border, region 8 texels wide
    x = np.full(4096, 1.0 - 0.5 * TEXEL)
    v = pcf_vis(smap, lookup(x, footprint=8.0))
    print("mean visibility at the border:", v.mean())
    assert abs(v.mean() - 3.5 / 8.0) < 0.02    # 3.5 of 8 texel columns are off the map
    assert np.all(pcf_vis(smap, lookup(np.full(8, 1.5))) == 1.0)   # receiver off the map


def test_receiver_plane_removes_self_shadowing_of_a_slope():
    """The map sees only a tilted plane z = 2 + x/2; receivers lie on it."""
    i = np.arange(RES)
    x_c = (i + 0.5) * TEXEL - 1.0
    smap = ortho_map(np.tile(2.0 + 0.5 * x_c, (RES, 1)).astype(np.float32))
    x = np.linspace(-0.6, 0.6, 512)
    n = (-0.5, 0.0, 1.0)        # normal of z - x/2 = 2 (sign does not matter)
    lk = lookup(x, z=0.0, footprint=8.0, n=n)
    lk.p_world = mi.Point3f(mi.Float(x), mi.Float(np.full(x.size, 0.01)),
                            mi.Float(2.0 + 0.5 * x))
    with_plane = pcf_vis(smap, lk)
    paper = pcf_vis(smap, lk, receiver_plane=False)
    print("lit fraction: receiver plane", with_plane.mean(), "single depth", paper.mean())
    assert np.all(with_plane == 1.0)
    assert paper.mean() < 0.8                  # Reeves' single depth shadows itself


@pytest.mark.parametrize("eps", [0.001, 0.003])
def test_a_wall_the_light_grazes_is_not_shadowed_by_its_own_roof(eps):
    """A wall under its roof a sun grazes (:func:`conftest.grazed_wall`): taps reaching
    the roof's texel column shadowed the wall from 1.2 below the roof down (mean
    visibility 0.69-0.91 at depths 2.2-2.6). Such taps now take the receiver's own
    texel's compare (:attr:`~mi_shadowmap.filters.common.ReceiverPlane.near_fallback`)."""
    smap, lk = grazed_wall(eps)
    v = pcf_vis(smap, lk)
    hard = methods.get("hard").lookup(smap, lk, parse_options({"method": "hard"}), mi.Bool(True))
    print("pcf visibility per depth:", v.reshape(8, 16).mean(axis=1).round(3))
    assert np.all(np.asarray(hard.numpy()) == 1.0)
    assert np.all(v == 1.0)


@pytest.mark.parametrize("kind", ["cube", "spot"])
def test_texel_world_size_is_the_texels_width_off_axis(kind):
    """The biases' texel width (``texel_world_size``) at a point far off the face's
    axis is the widest a texel-long step on the face gets across the ray there
    (measured between rays through the face); it had been the distance from the light
    times the width at the face's centre: 1.62x too wide at s = t = 0.9 on a cube face
    (1.73x at a corner of a spot's square frustum), so the slope bias and the normal
    offset were too, and contact shadows near a cube map's face corners leaked."""
    from mi_shadowmap.light_views import make_light_view
    res = 256
    if kind == "cube":
        view = CubeView("point", mi.ScalarPoint3f(0.5, -1, 2), mi.ScalarTransform4f(),
                        label="cube")
        p = np.array([0.5, -1, 2]) + 7.0 * np.array([1.0, 0.9, 0.9]) / np.linalg.norm([1, .9, .9])
    else:
        scene = mi.load_dict({"type": "scene", "light": {
            "type": "spot", "cutoff_angle": 48.0,
            "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0, 0], target=[0, 0, 1],
                                                         up=[0, 1, 0])},
            "plane": {"type": "rectangle",
                      "to_world": mi.ScalarTransform4f().translate([0, 0, 5]).scale(9)}})
        view = make_light_view(scene.emitters()[0], scene, 0)
        t = 0.9 * view.tan_half
        p = 6.0 * np.array([t, t, 1.0])
    P = mi.Point3f(*[float(c) for c in p])
    face, uv, depth, inside = view.project(P)
    assert bool(inside[0])
    uv = np.array([uv.x[0], uv.y[0]])
    dist = float(np.linalg.norm(p - np.array(view.position)))

    def ray(du, dv):
        _, d = view.ray_through(face, mi.Point2f(float(uv[0] + du), float(uv[1] + dv)))
        return np.array([d.x[0], d.y[0], d.z[0]], np.float64)

    # a texel-long step on the face in 16 directions, across the ray at the point
    h = 0.5 / res
    widths = [dist * np.linalg.norm(ray(h * math.cos(a), h * math.sin(a))
                                    - ray(-h * math.cos(a), -h * math.sin(a)))
              for a in np.arange(16) * math.pi / 16]
    got = float(view.texel_world_size(res, depth, P, None)[0])
    print(kind, "texel widths across the ray", min(widths), "-", max(widths),
          "texel_world_size", got, "distance-based", float(depth[0]) * 2 * view.tan_half / res)
    assert got == pytest.approx(max(widths), rel=0.01)


@pytest.mark.parametrize("props", [{}, {"virtual": False, "resolution": 256}],
                         ids=["virtual", "full"])
def test_an_overhead_sun_on_a_stretched_map_keeps_a_low_rods_shadow(props):
    """A sun straight above a ground 40 x 1 (its orthographic map 40:1): the ground's
    normal is along the light's rays, so its depth does not change across a texel and
    the biases take the texel's *shorter* side (``texel_width_along``); the longer one
    lifted the normal offset 40 times higher, above a rod 0.05 over the ground, whose
    shadow vanished: 4.6 % of the image false lit against 0.8 % (32^2; mutation audit)."""
    T = mi.ScalarTransform4f
    scene = mi.load_dict({
        "type": "scene",
        "sensor": {"type": "perspective", "fov": 20,
                   "to_world": T().look_at(origin=[0, 0.6, 0.6], target=[0, 0, 0], up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": 32, "height": 32,
                            "rfilter": {"type": "box"}}},
        "ground": {"type": "rectangle",
                   "to_world": T().rotate([1, 0, 0], -90).scale([20.0, 0.5, 1.0])},
        "rod": {"type": "cube", "to_world": T().translate([0, 0.05, 0]).scale([0.3, 0.01, 0.01])},
        "sun": {"type": "directional", "direction": [0, -1, 0]}})

    def vis(**p):
        return np.asarray(mi.render(scene, integrator=mi.load_dict({"type": "shadowmap", **p}),
                                    spp=4, seed=0))[..., -1]
    ref = vis(method="raytraced")
    assert np.mean(ref < 0.5) > 0.05                    # the rod's shadow is in view
    for method in ("hard", "pcf"):
        got = vis(method=method, **props)
        false_lit = float(np.mean((ref < 0.5) & (got >= 0.5)))
        print(f"{method} {props}: false lit {false_lit:.4f}")
        assert false_lit <= 0.015


def test_cube_taps_continue_on_the_neighbouring_face():
    """A point light whose +y face is fully occluded; a receiver on +x near that seam."""
    view = CubeView("point", mi.ScalarPoint3f(0, 0, 0), mi.ScalarTransform4f(), label="cube")
    d = np.full((6, RES, RES), np.inf, np.float32)
    d[2] = 0.5                                  # face 2 = +y
    smap = ShadowMap(view, RES, mi.Float(d.ravel()))
    N = 2048
    # +x face, s = y/x = 1 - 2/RES: one texel (2/RES in s) from the seam
    y = 1.0 - 2.0 / RES
    p = mi.Point3f(mi.Float(np.ones(N)), mi.Float(np.full(N, y)), mi.Float(np.zeros(N)))
    w = 8.0 * (2.0 / RES)                       # 8 texels on the face at distance 1
    sampler = mi.load_dict({"type": "independent"})
    sampler.seed(0, N)
    lk = Lookup(p, dr.normalize(mi.Vector3f(-1, -y, 0)), mi.Vector3f(0, w, 0),
                mi.Vector3f(0, 0, w), None, None, sampler)
    v = pcf_vis(smap, lk)
    print("mean visibility 2 texels from the cube seam:", v.mean())
    # 3 of the region's 8 texel rows lie beyond the seam, on the occluded face
    # (were they treated as off-map, they would be lit and the mean would be 1)
    assert abs(v.mean() - 5.0 / 8.0) < 0.03


def _cube_texel_numpy(face, x, y, res):
    """Expected (face, i, j) of a cube-map tap at continuous texel coordinates (x, y) of
    ``face``, off the face or not: its direction projected again (numpy, float64)."""
    s, t = x * (2.0 / res) - 1.0, y * (2.0 / res) - 1.0
    axis, sign = face // 2, np.where(face % 2 == 0, 1.0, -1.0)
    d = np.zeros((len(face), 3))
    rows = np.arange(len(face))
    d[rows, axis] = sign
    d[rows, (axis + 1) % 3] = s
    d[rows, (axis + 2) % 3] = t
    a = np.abs(d)
    ax2 = np.where((a[:, 0] >= a[:, 1]) & (a[:, 0] >= a[:, 2]), 0,
                   np.where(a[:, 1] >= a[:, 2], 1, 2))
    major = d[rows, ax2]
    f2 = 2 * ax2 + (major < 0)
    u, v = d[rows, (ax2 + 1) % 3] / np.abs(major), d[rows, (ax2 + 2) % 3] / np.abs(major)
    i = np.clip(np.floor((u + 1.0) * 0.5 * res), 0, res - 1)
    j = np.clip(np.floor((v + 1.0) * 0.5 * res), 0, res - 1)
    inside = (x >= 0) & (x < res) & (y >= 0) & (y < res)
    return (np.where(inside, face, f2), np.where(inside, np.floor(x), i),
            np.where(inside, np.floor(y), j))


@pytest.mark.parametrize("precision", ["float32", "float64"])
def test_cube_taps_off_the_face_land_on_the_neighbour_texel(precision):
    """Taps up to 3 texels off a cube face (wide kernels near a seam) continue on the
    texel of the neighbouring face their direction falls on, and taps on the face keep
    their texel, in one batch: the full map's ``tap_texel`` (float32) and the virtual
    map's ``face_texel_f64``, against the direction projected again in numpy."""
    view = CubeView("point", mi.ScalarPoint3f(0, 0, 0), mi.ScalarTransform4f(), label="cube")
    rng = np.random.default_rng(5)
    n = 4096
    face = rng.integers(0, 6, n)
    x, y = rng.uniform(-3.0, RES + 3.0, n), rng.uniform(-3.0, RES + 3.0, n)
    if precision == "float32":
        x, y = x.astype(np.float32).astype(np.float64), y.astype(np.float32).astype(np.float64)
        f, i, j, _ = view.tap_texel(mi.UInt32(face), mi.Point2f(x, y), RES)
    else:
        f, i, j, _ = view.face_texel_f64(mi.UInt32(face), mi.Point2d(x, y), mi.Int32(RES))
    ef, ei, ej = _cube_texel_numpy(face, x, y, RES)
    got = np.stack([f.numpy(), i.numpy(), j.numpy()]).astype(np.int64)
    want = np.stack([ef, ei, ej]).astype(np.int64)
    off = ~((x >= 0) & (x < RES) & (y >= 0) & (y < RES))
    same = np.all(got == want, axis=0)
    print(f"{precision}: {off.sum()} taps off the face, {np.mean(same[off]):.4f} exact "
          f"there, {np.mean(same[~off]):.4f} on the face")
    assert off.sum() > 300 and np.all(same[~off])
    # float32 roundoff may move a tap that falls within ~1e-5 texel of a texel edge
    assert np.mean(same[off]) >= 0.995
    assert np.all(np.abs(got - want)[1:, ~same] <= 1) and np.all(got[0] == want[0])


def test_one_kernel_whatever_num_samples():
    smap = edge_map()
    counts = []
    for n in (16, 1024):
        lk = lookup(np.linspace(-0.1, 0.1, 256))
        dr.eval(lk.p_world, lk.n_world, lk.dp_dx, lk.dp_dy)
        dr.sync_thread()
        dr.set_flag(dr.JitFlag.KernelHistory, True)
        dr.kernel_history()                      # clear
        v = methods.get("pcf").lookup(smap, lk, parse_options({"method": "pcf", "num_samples": n}),
                           mi.Bool(True))
        dr.eval(v)
        dr.sync_thread()
        hist = [h for h in dr.kernel_history() if h.get("type") == dr.KernelType.JIT]
        dr.set_flag(dr.JitFlag.KernelHistory, False)
        counts.append(len(hist))
    assert counts[0] == counts[1] == 1, counts


def test_pcf_reads_the_footprint():
    assert methods.get("pcf").needs_footprint


@pytest.mark.parametrize("props", [
    {"sampling": "uniform"},
    {"sampling": "regular"},
    {"sampling": "gaussian", "num_samples": 32, "min_samples": 3},
    {"bias_range": "0.005, 0.01", "res_factor": 2.0, "min_size": 2.0},
])
def test_options_through_the_plugin(props):
    """Every PCF option renders through the plugin and stays close to the reference."""
    path = [p for p in SCENE_FILES if p.stem == "spot_sphere_box"][0]
    scene = mi.load_file(str(path), width=48, height=48)
    _, ref = render_np(scene, {"type": "shadowmap", "method": "raytraced"}, spp=4)
    _, pcf = render_np(scene, {"type": "shadowmap", "method": "pcf", "resolution": 512,
                               **props}, spp=4)
    m = metrics.misclassified(vis_stack(ref), vis_stack(pcf))
    print(props, f"misclassified {m['misclassified']:.3%}")
    assert m["misclassified"] <= 0.03


# ------------------------------------------------------------------ bad input
@pytest.mark.parametrize("props,name", [
    ({"num_samples": 0}, "num_samples"),
    ({"min_samples": 0}, "min_samples"),
    ({"res_factor": 0.0}, "res_factor"),
    ({"res_factor": -1.0}, "res_factor"),
    ({"min_size": -1.0}, "min_size"),
    ({"bias_range": "0.4, 0.3"}, "bias_range"),
    ({"bias_range": "0.3"}, "bias_range"),
    ({"sampling": "poisson"}, "sampling"),
    ({"receiver_plane": 1}, "receiver_plane"),
    ({"kernel": 2}, "kernel"),                 # a bilinear property
])
def test_bad_input_names_the_property(props, name):
    with pytest.raises(OptionError, match=name):
        parse_options({"method": "pcf", **props})


def test_bad_input_through_the_plugin():
    with pytest.raises(RuntimeError, match="num_samples"):
        mi.load_dict({"type": "shadowmap", "method": "pcf", "num_samples": 0})


def test_footprint_stays_in_the_receivers_cascade():
    """Review item 3: at a cascade split, ``p + dp`` projects into the next cascade's
    rectangle; the footprint must be measured on the receiver's own cascade. Hand-made
    2-cascade view (light along +z, camera looking along +x, split at x = 1):
    cascade 0 spans [-1, 1]^2, cascade 1 [-2, 2]^2. A receiver at x = 0.99 with a
    pixel footprint of 0.04 world units spans 0.04 / 2 * RES texels of cascade 0."""
    from mi_shadowmap.filters.common import footprint_texels, receiver
    base = ortho_map(np.full((RES, RES), np.inf, np.float32)).view
    view = CascadedView(base.kind, base.position, base.light_from_world, label=base.label,
                        half_extent=base.half_extent,
                        rects=((0.0, 0.0, 1.0, 1.0), (0.0, 0.0, 2.0, 2.0)),
                        split_depths=(0.0, 1.0, 10.0), camera_origin=(0.0, 0.0, 0.0),
                        camera_forward=(1.0, 0.0, 0.0))
    smap = ShadowMap(view, RES, dr.full(mi.Float, dr.inf, 2 * RES * RES))
    p = mi.Point3f(mi.Float([0.99, -0.5]), mi.Float([0.0, 0.0]), mi.Float([2.0, 2.0]))
    d = 0.04
    lk = Lookup(p, mi.Vector3f(0, 0, -1), mi.Vector3f(d, 0, 0), mi.Vector3f(0, d, 0),
                None, None, None)
    r = receiver(smap, lk, parse_options({"method": "pcf"}))
    assert np.asarray(r.face).tolist() == [0, 0]
    w = footprint_texels(smap, lk, r)
    expected = d / 2.0 * RES          # cascade 0: 2 world units over RES texels
    np.testing.assert_allclose(np.asarray(w.x), [expected, expected], rtol=1e-4)
    np.testing.assert_allclose(np.asarray(w.y), [expected, expected], rtol=1e-4)


def test_regular_sampling_is_the_deterministic_staircase():
    """``sampling='regular'``: one tap at each cell's centre, so every lane (whatever its
    sampler seed) gives the same value, the box filter sampled at the 4 x 4 centres of a
    4 x 4-texel region: the fraction of tap columns right of the edge."""
    smap = edge_map()
    lanes = 64
    # receivers offset by a quarter texel: no tap centre falls on the edge
    offs = np.arange(-3.75, 3.76, 0.5)
    v = pcf_vis(smap, lookup(repeat_sweep(offs, lanes), seed=7), sampling="regular")
    v = v.reshape(len(offs), lanes)
    assert np.all(v == v[:, :1]), "regular taps depend on the sampler"
    cols = offs[:, None] + (np.arange(4)[None, :] - 1.5)   # tap columns, texels from edge
    expected = np.mean(cols >= 0.0, axis=1)
    np.testing.assert_array_equal(v[:, 0], expected)
    other = pcf_vis(smap, lookup(repeat_sweep(offs, lanes), seed=8), sampling="regular")
    np.testing.assert_array_equal(other, v.ravel())
    jitter = pcf_vis(smap, lookup(repeat_sweep(offs, lanes), seed=7), sampling="jitter")
    assert np.any(jitter.reshape(len(offs), lanes) != v)   # the default stays jittered


def test_normal_offset_is_scaled_by_cos_theta_below_the_slope_clamp():
    """The receiver's normal offset (``filters.common.receiver``): ``normal_bias *
    cos(theta)`` texels along the normal, so its sideways shift in the light's view is
    ``normal_bias sin(theta) cos(theta)`` texels; where ``tan(theta)`` exceeds
    ``max_tan_slope`` (20) the full offset, ``normal_bias sin(theta)`` sideways.
    (Unscaled, every angle moved ``normal_bias sin(theta)``: 0.43 texel at 60 degrees.)"""
    from mi_shadowmap.filters.common import receiver
    smap = ortho_map(np.full((RES, RES), np.inf, np.float32))   # light along +z
    angles = np.radians([0.0, 30.0, 60.0, 80.0, 88.0, 89.5])     # tan 88 deg = 28.6 > 20
    n = mi.Vector3f(mi.Float(np.sin(angles)), mi.Float(np.zeros(angles.size)),
                    mi.Float(-np.cos(angles)))
    p = mi.Point3f(mi.Float(np.full(angles.size, 0.1)), mi.Float(np.zeros(angles.size)),
                   mi.Float(np.full(angles.size, 2.0)))
    d = 0.01
    lk = Lookup(p, n, mi.Vector3f(d, 0, 0), mi.Vector3f(0, d, 0), None, None, None)

    def uv_x(normal_bias):
        opts = parse_options({"method": "hard", "normal_bias": normal_bias,
                              "slope_bias": 0.0})
        return np.asarray(receiver(smap, lk, opts).uv.x, np.float64)

    shift = (uv_x(0.5) - uv_x(0.0)) * RES                       # texels
    scale = np.where(np.tan(angles) > 20.0, 1.0, np.cos(angles))
    np.testing.assert_allclose(shift, 0.5 * scale * np.sin(angles), atol=2e-3)
    assert shift[2] < 0.22 and shift[4] > 0.49


def test_a_frosted_bulb_lit_from_inside_keeps_its_light():
    """A point light inside a rough-glass sphere (radius 0.3) lights the shell, which
    rises off its tangent plane towards the light: pcf's kernel (the pixel's footprint,
    many texels of a 256^2 map) compared its taps with that plane, which lies behind
    the shell, and shadowed it: the image 0.318 against raytraced's 0.392 (light
    centred), 0.075 against 0.175 (0.2 off the centre) in a 64^2 view; this 48^2 one
    0.176 against 0.378. The plane's depths now allow for its bend."""
    for dx in (0.0, 0.2):
        scene = frosted_bulb_scene(dx)
        imgs = [np.asarray(mi.render(scene, integrator=mi.load_dict(
            {"type": "shadowmap", **p}), spp=4, seed=0))
            for p in ({"method": "raytraced"}, {"method": "pcf", "resolution": 256})]
        wrong = int(np.sum(np.abs(imgs[1][..., -1] - imgs[0][..., -1]) > 0.1))
        print(f"dx={dx}: image {imgs[1][..., :3].mean():.4f} vs {imgs[0][..., :3].mean():.4f}, "
              f"{wrong} pixels off")
        assert wrong <= 1


@pytest.mark.parametrize("light", ["point", "spot"])
def test_virtual_marks_cover_the_scaled_region(light, monkeypatch):
    """On virtual maps ``pcf`` reads taps ``res_factor`` footprints wide around the
    receiver; the record's ``virtual_margin`` (``res_factor 2^(1 - lod_bias)`` texels of
    it, the region's bound at the footprint's level; ``4 res_factor`` before) has the
    mark pass build them. The render then equals one whose marks reach as far as the
    2 x 2 pages a lookup binds (margin 14 at page size 32), as for mdsm's windows
    (tests/test_mdsm.py). Mutation audit: the margin without its ``res_factor`` term
    survived every test."""
    own, wide = own_and_widest_marks(monkeypatch, light, {"method": "pcf", "res_factor": 2.5,
                                                          "sampling": "regular"})
    print("pixels that differ:", int(np.sum(own != wide)))
    assert np.array_equal(own, wide)
