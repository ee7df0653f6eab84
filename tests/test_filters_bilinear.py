"""Brabec & Seidel fixed-footprint / bilinear PCF (``method="bilinear"``, ``kernel``).

Unit tests on hand-made orthographic depth maps (no scene), shadow-level
counts against the paper's 5 vs 20, scene tests against ``raytraced``.
"""
import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from conftest import SCENE_FILES, frosted_bulb_scene, grazed_wall, render_np
from mi_shadowmap import metrics
from mi_shadowmap.depth_maps import ShadowMap
from mi_shadowmap import methods
from mi_shadowmap.filters.common import DEPTH_ULPS, Lookup
from mi_shadowmap.light_views import OrthoView
from mi_shadowmap.options import OptionError, parse_options

RES = 64
TEXEL = 2.0 / RES
KERNELS = (2, 3, 4, 5, 8)


def ortho_map(depth: np.ndarray) -> ShadowMap:
    """Orthographic map over [-1, 1]^2 looking along +z; depth[j, i] (row j = v)."""
    view = OrthoView("directional", mi.ScalarPoint3f(0, 0, 0),
                     mi.ScalarTransform4f(), half_extent=(1.0, 1.0), label="unit")
    return ShadowMap(view, depth.shape[0], mi.Float(np.asarray(depth, np.float32).ravel()))


def edge_map() -> ShadowMap:
    d = np.full((RES, RES), np.inf, np.float32)
    d[:, : RES // 2] = 1.0          # texel columns i < 32: occluder at depth 1
    return ortho_map(d)


def lookup(x, y=None, z=2.0):
    x = np.atleast_1d(np.asarray(x, np.float64))
    y = np.full(x.size, 0.01) if y is None else np.asarray(y, np.float64)
    p = mi.Point3f(mi.Float(x), mi.Float(y), mi.Float(np.full(x.size, z)))
    sampler = mi.load_dict({"type": "independent"})
    sampler.seed(0, x.size)
    return Lookup(p, mi.Vector3f(0, 0, -1), mi.Vector3f(0), mi.Vector3f(0), None, None, sampler)


def vis(method, smap, lk, **props):
    opts = parse_options({"method": method, **props})
    return np.asarray(methods.get(method).lookup(smap, lk, opts, mi.Bool(True)).numpy(), np.float64)


# --------------------------------------------------------------- hand-made edge
@pytest.mark.parametrize("receiver_plane", [True, False])
@pytest.mark.parametrize("kernel", KERNELS)
def test_edge_is_a_linear_ramp_of_width_kernel_minus_one(kernel, receiver_plane):
    smap = edge_map()
    offs = np.linspace(-6.0, 6.0, 481)               # texels from the edge
    v = vis("bilinear", smap, lookup(offs * TEXEL), kernel=kernel,
            receiver_plane=receiver_plane)
    assert v[np.argmin(np.abs(offs))] == 0.5         # exactly 0.5 on the edge
    assert np.all(np.diff(v) >= 0.0)                 # monotone, exactly
    np.testing.assert_allclose(v, np.clip(0.5 + offs / (kernel - 1), 0.0, 1.0), atol=1e-5)
    far = vis("bilinear", smap, lookup([-0.5, -0.6, 0.5, 0.6]), kernel=kernel)
    assert far.tolist() == [0.0, 0.0, 1.0, 1.0]      # exactly shadowed / lit


@pytest.mark.parametrize("eps", [0.001, 0.003])
def test_a_wall_the_light_grazes_is_not_shadowed_by_its_own_roof(eps):
    """A wall under its roof a sun grazes (:func:`conftest.grazed_wall`), lit everywhere:
    the 2x2 footprint's texel in the roof's column, compared with the receiver plane
    clamped on its near side, shadowed the wall from 1.2 below the roof down (mean
    visibility 0.65-0.77 at depths 2.2-2.6). Such a texel now takes the receiver's own
    texel's compare (:attr:`~mi_shadowmap.filters.common.ReceiverPlane.near_fallback`)."""
    smap, lk = grazed_wall(eps)
    v = vis("bilinear", smap, lk)
    print("bilinear visibility per depth:", v.reshape(8, 16).mean(axis=1).round(3))
    assert np.all(v == 1.0)


def test_kernel_1_is_the_nearest_texel_compare_on_a_hand_made_map():
    """kernel=1 against an independent numpy expectation: the texel
    ``floor(uv * res)`` (uv = (p + 1) / 2 on the unit orthographic map) shadows
    the receiver at depth 2 iff its depth is below 2."""
    rng = np.random.default_rng(3)
    depth = rng.choice(np.array([1.0, 3.0, np.inf], np.float32), (RES, RES))
    smap = ortho_map(depth)
    x, y = rng.uniform(-1, 1, (2, 5000)).astype(np.float32)
    uv = (np.stack([x, y]) + np.float32(1.0)) * np.float32(0.5)
    frac = uv * RES - np.floor(uv * RES)
    keep = np.all((frac > 1e-3) & (frac < 1 - 1e-3), axis=0)   # away from texel borders
    x, y = x[keep], y[keep]
    i, j = np.clip(np.floor(uv[:, keep] * RES).astype(int), 0, RES - 1)
    expected = np.where(depth[j, i] < 2.0, 0.0, 1.0)
    got = vis("bilinear", smap, lookup(x, y), kernel=1)
    assert 0.2 < expected.mean() < 0.9                      # both outcomes occur
    np.testing.assert_array_equal(got, expected)


def test_off_map_texels_are_lit():
    smap = ortho_map(np.full((RES, RES), 1.0, np.float32))    # everything occluded
    x = 1.0 - 0.25 * TEXEL        # a quarter texel inside the right border
    v = vis("bilinear", smap, lookup([x, 1.5]), kernel=2)
    # 2x2 bilinear: the tap column beyond the border has weight 0.25 and is lit
    np.testing.assert_allclose(v, [0.25, 1.0], atol=1e-6)


# --------------------------------------------------------------- shadow levels
def _level_map():
    """Random binary occluders whose density grows from 0 (left) to 1 (right)."""
    rng = np.random.default_rng(7)
    p = np.linspace(0.0, 1.0, RES)[None, :]
    return ortho_map(np.where(rng.random((RES, RES)) < p, 1.0, np.inf).astype(np.float32))


def _corner_levels(kernel):
    smap = _level_map()
    c = np.arange(4, RES - 4)                       # texel corners uv = c / RES
    cx, cy = np.meshgrid(c, c)
    x, y = (cx.ravel() * TEXEL - 1.0), (cy.ravel() * TEXEL - 1.0)
    return vis("bilinear", smap, lookup(x, y), kernel=kernel)


def test_levels_paper_5_for_2x2_and_17_for_4x4():
    """Brabec & Seidel: 2x2 PCF has 5 levels, their 4x4 (four 2x2 passes) 'about 20'.

    At texel corners the bilinear weights are equal, so ``kernel=2`` is exactly
    the paper's 2x2 compare count; ``kernel=5`` at corners weighs a 4x4 block
    of texels equally (the paper's 4x4 footprint): 16 + 1 = 17 levels (the
    paper's "4 * 5 = 20" counts five levels for each of its four passes).
    """
    v1, v2, v5 = _corner_levels(1), _corner_levels(2), _corner_levels(5)
    print("distinct levels at texel corners: kernel 1:", metrics.distinct_levels(v1),
          "kernel 2:", metrics.distinct_levels(v2), "kernel 5:", metrics.distinct_levels(v5))
    assert metrics.distinct_levels(v1) == 2
    assert sorted(np.unique(np.round(v2, 6))) == [0.0, 0.25, 0.5, 0.75, 1.0]
    assert metrics.distinct_levels(v5) == 17
    assert np.allclose(v5 * 16, np.round(v5 * 16), atol=1e-5)


@pytest.mark.parametrize("kernel", KERNELS)
def test_bilinear_weights_give_more_than_20_levels(kernel):
    """Anywhere between texel centres the weights vary: far more than the paper's 20."""
    rng = np.random.default_rng(11)
    x = np.linspace(-4 * TEXEL, 4 * TEXEL, 2000)     # across the straight edge
    y = rng.uniform(-0.5, 0.5, x.size)
    v = vis("bilinear", edge_map(), lookup(x, y), kernel=kernel)
    n = metrics.distinct_levels(v)
    print(f"kernel {kernel}: {n} distinct levels across an edge")
    assert n > 20


# ------------------------------------------------------------------ bad input
@pytest.mark.parametrize("props,name", [
    ({"kernel": 0}, "kernel"),
    ({"kernel": 9}, "kernel"),
    ({"kernel": 2.0}, "kernel"),
    ({"kernel": "2"}, "kernel"),
    ({"receiver_plane": "yes"}, "receiver_plane"),
    ({"num_samples": 4}, "num_samples"),       # a pcf property
])
def test_bad_input_names_the_property(props, name):
    with pytest.raises(OptionError, match=name):
        parse_options({"method": "bilinear", **props})


def test_kernel_rejected_for_other_methods():
    with pytest.raises(OptionError, match="kernel"):
        parse_options({"method": "hard", "kernel": 2})


# ------------------------------------------------------------------ scenes
def _scene(name, size=64):
    path = [p for p in SCENE_FILES if p.stem == name][0]
    return mi.load_file(str(path), width=size, height=size)


@pytest.mark.parametrize("name", [p.stem for p in SCENE_FILES])
def test_kernel_1_reproduces_hard_bitwise(name):
    scene = _scene(name, 48)
    rgb_h, hard = render_np(scene, {"type": "shadowmap", "method": "hard", "resolution": 256},
                            spp=2, seed=3)
    rgb_b, bil = render_np(scene, {"type": "shadowmap", "method": "bilinear", "kernel": 1,
                                   "resolution": 256}, spp=2, seed=3)
    assert sorted(hard) == sorted(bil)
    for k in hard:
        assert np.array_equal(hard[k], bil[k]), k
    assert np.array_equal(rgb_h, rgb_b)


def test_one_kernel_for_the_largest_footprint():
    smap = edge_map()
    lk = lookup(np.linspace(-0.1, 0.1, 256))
    dr.eval(lk.p_world)
    dr.sync_thread()
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        dr.kernel_history()                          # clear
        v = methods.get("bilinear").lookup(smap, lk, parse_options({"method": "bilinear", "kernel": 8}),
                                mi.Bool(True))
        dr.eval(v)
        dr.sync_thread()
        hist = [h for h in dr.kernel_history() if h.get("type") == dr.KernelType.JIT]
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    assert len(hist) == 1                            # 64 taps, one dr.while_loop kernel


# --------------------------------------------------------------- soft_compare (issue 13)
@pytest.mark.parametrize("kernel", (2, 4))
def test_soft_compare_is_the_step_far_from_the_receiver_and_differentiable_near(kernel):
    """``soft_compare = s``: a texel nearer than the receiver by ``d`` is lit by
    smoothstep(1 - d / w), ``w = s`` texel widths. The edge map's occluder is at depth 1
    and the receivers at 2: with ``w`` = 2 texels (0.0625) the compares are steps and the
    ramp is the step filter's, bit for bit; with receivers 0.03 behind the occluder the
    texels are half lit, and the visibility's derivative in the map's depth is that of
    the smoothstep, weighted bilinearly."""
    smap = edge_map()
    offs = np.linspace(-3.0, 3.0, 97)
    far = vis("bilinear", smap, lookup(offs * TEXEL), kernel=kernel, soft_compare=2.0)
    step = vis("bilinear", smap, lookup(offs * TEXEL), kernel=kernel)
    np.testing.assert_array_equal(far, step)
    # receivers just behind the occluder plane, deep in its shadow
    x = np.full(8, -0.5)
    w = 2.0 * TEXEL
    depth = mi.Float(np.where(np.arange(RES * RES) % RES < RES // 2, 1.0, np.inf)
                     .astype(np.float32))
    dr.enable_grad(depth)
    smap_ad = ShadowMap(smap.view, RES, depth)
    opts = parse_options({"method": "bilinear", "kernel": kernel, "soft_compare": 2.0,
                          "receiver_plane": False, "bias": 0.0, "slope_bias": 0.0,
                          "normal_bias": 0.0})
    # the receiver depth after the rounding margin (common.DEPTH_ULPS) is 1 + w / 2
    z = (1.0 + 0.5 * w) / (1.0 - DEPTH_ULPS)
    v = methods.get("bilinear").lookup(smap_ad, lookup(x, z=z), opts, mi.Bool(True))
    np.testing.assert_allclose(v.numpy(), 0.5, atol=1e-5)   # smoothstep(0.5) = 0.5
    dr.backward(dr.sum(v))
    g = dr.grad(depth).numpy()
    # d smoothstep(x) / dz_map at x = 1/2: 6 x (1 - x) / w = 1.5 / w per receiver, the
    # bilinear weights summing to one over the texels read
    np.testing.assert_allclose(g.sum(), len(x) * 1.5 / w, rtol=1e-4)
    assert np.count_nonzero(g) == kernel * kernel


def test_a_frosted_bulb_lit_from_inside_without_normal_offset():
    """A point light at the centre of a rough-glass sphere (radius 0.3) lights the
    shell along its normal: with ``normal_bias`` 0 nothing but the receiver plane's
    bend keeps the 2x2 taps' plane depths (behind the concave shell) from shadowing it
    (image 0.019-0.027 against raytraced's 0.392 in a 64^2 view before)."""
    scene = frosted_bulb_scene()
    imgs = [np.asarray(mi.render(scene, integrator=mi.load_dict(
        {"type": "shadowmap", **p}), spp=4, seed=0))
        for p in ({"method": "raytraced"},
                  {"method": "bilinear", "normal_bias": 0.0, "virtual": True},
                  {"method": "bilinear", "normal_bias": 0.0, "resolution": 128})]
    for img in imgs[1:]:
        wrong = int(np.sum(np.abs(img[..., -1] - imgs[0][..., -1]) > 0.1))
        print(f"image {img[..., :3].mean():.4f} vs {imgs[0][..., :3].mean():.4f}, "
              f"{wrong} pixels off")
        assert wrong <= 1


def test_soft_compare_is_measured_in_texels_at_the_receiver():
    """``soft_compare`` (README/options: the smooth compare's width in map texels at the
    receiver): the ramp of ``soft_tap_lit`` spans ``soft_compare * texel_world`` of
    depth, lit 1 at the map's depth, 0.5 half a width behind it, 0 a whole width behind.
    Twice that width survived every test (the gradient tests' tolerances hold either)."""
    import types
    from mi_shadowmap.filters.common import soft_compare_width, soft_tap_lit
    r = types.SimpleNamespace(texel_world=mi.Float([0.01, 0.2]))
    width = soft_compare_width(r, 3.0)
    assert np.allclose(np.asarray(width), [0.03, 0.6])
    assert soft_compare_width(r, 0.0) is None
    z_map = mi.Float([1.0, 1.0])
    for behind, lit in ((0.0, 1.0), (0.5, 0.5), (1.0, 0.0), (-0.5, 1.0)):
        got = soft_tap_lit(z_map, z_map + behind * width, mi.Bool(True), width)
        assert np.allclose(np.asarray(got), lit, atol=1e-5), (behind, np.asarray(got))


@pytest.mark.parametrize("a,b", [(1.0, 0.0), (3.0, 0.0), (4.0, 2.5), (3.0, 6.0), (7.0, 1.0)])
def test_trapezoid_cdf_is_the_convolution_of_two_boxes(a, b):
    """``_trapezoid_cdf`` (the pixel-centre derivative's kernel): the CDF of the unit-area
    convolution of centred boxes of widths ``a`` and ``b``, checked against the CDF of a
    numerical convolution: 0 below ``-(a + b) / 2``, 1/2 at 0, 1 above ``(a + b) / 2``,
    and ``b = 0`` the box itself. (Mutation audit: a box CDF shifted by ``a / 2``
    survived every test.)"""
    from mi_shadowmap.filters.bilinear import _trapezoid_cdf
    x = np.linspace(-0.5 * (a + b) - 1.0, 0.5 * (a + b) + 1.0, 97)
    got = np.asarray(_trapezoid_cdf(mi.Float(x), a, mi.Float(np.full(x.size, b))).numpy())
    if b == 0.0:
        want = np.clip((x + 0.5 * a) / a, 0.0, 1.0)
    else:
        # numerical convolution of the two boxes' densities on a fine grid, integrated
        h = 1e-3
        t = np.arange(-0.5 * (a + b) - 2.0, 0.5 * (a + b) + 2.0, h)
        box_a = (np.abs(t) <= 0.5 * a) / a
        box_b = (np.abs(t) <= 0.5 * b) / b
        dens = np.convolve(box_a, box_b, mode="same") * h
        cdf = np.cumsum(dens) * h
        want = np.interp(x, t, cdf)
    np.testing.assert_allclose(got, want, atol=5e-3)
    np.testing.assert_allclose(np.asarray(_trapezoid_cdf(mi.Float([0.0]), a,
                                                         mi.Float([b])).numpy()), [0.5],
                               atol=1e-6)


def test_pixel_average_of_a_wide_footprint_is_the_trapezoid_mass_on_the_lit_side():
    """``bilinear``'s pixel-centre run (``lk.centre``, ``soft_compare`` > 0) over a
    straight edge: the ``k x k`` box convolved with the pixel's footprint, so the lit
    fraction is the trapezoid's mass on the lit side, ``1 - F(-c)`` (``c`` the receiver's
    distance from the edge in texels, ``F`` :func:`_trapezoid_cdf`). A footprint of 40
    texels with ``k = 8`` spans 48 texels, read in groups of ``g = 3`` (``MAX_SIDE`` 16)
    each by its middle texel's compare: off by at most one texel's mass (1 / 40) where
    a group straddles the edge. (Mutation audit: groups read by their first texel, off
    by two texels' mass, survived every test.)"""
    from mi_shadowmap.filters.bilinear import _trapezoid_cdf
    smap = edge_map()
    foot, k = 40.0, 8
    x = np.linspace(-6, 6, 97) * TEXEL + 1e-4
    n = x.size
    p = mi.Point3f(mi.Float(x), mi.Float(np.full(n, 0.01)), mi.Float(np.full(n, 2.0)))
    lk = Lookup(p, mi.Vector3f(0, 0, -1), mi.Vector3f(foot * TEXEL, 0, 0),
                mi.Vector3f(0, foot * TEXEL, 0), None, None, None, True)
    v = vis("bilinear", smap, lk, kernel=k, soft_compare=0.5)
    c = x / TEXEL                          # the edge is at x = 0 (texel column 32)
    want = 1.0 - np.asarray(_trapezoid_cdf(mi.Float(-c), float(k - 1),
                                           mi.Float(np.full(n, foot))).numpy())
    err = np.abs(v - want)
    print(f"largest error {err.max():.4f}, one texel's mass {1.0 / foot:.4f}")
    assert err.max() <= 1.0 / foot + 1e-4
    assert v[-1] - v[0] > 0.2               # lit side to the right (+x)
