"""Exponential variance shadow maps (``method="evsm"``, Lauritzen & McCool 2008).

Hand-made orthographic maps (no scene): shadow / lit / a monotone edge, each
warp's Chebyshev bound against numpy from the box moments, less light
bleeding than plain Chebyshev on the depth where two occluders overlap, the
summed-area-table precision guard; the exponent clamp and bad input; every
repository scene against the reference; the mono and spectral variants.
"""
import math

import mitsuba as mi
import numpy as np
import pytest

from conftest import SCENE_FILES, full_map_scenes, render_np
from mi_shadowmap import methods, metrics
from mi_shadowmap.depth_maps import ShadowMap, build_layer
from mi_shadowmap.filters import evsm as E
from mi_shadowmap.filters.common import DEPTH_ULPS, Lookup
from mi_shadowmap.light_views import OrthoView, emitter_kind
from mi_shadowmap.options import OptionError, parse_options
from mi_shadowmap.reference import converged_visibility
from mi_shadowmap.scenes import default_scene

RES = 64
NO_BIAS = {"slope_bias": 0.0, "normal_bias": 0.0}


# ------------------------------------------------------------------ helpers
def ortho_map(depth: np.ndarray) -> ShadowMap:
    """Orthographic map over [-1, 1]^2 looking along +z; depth[j, i] (row j = v)."""
    view = OrthoView("directional", mi.ScalarPoint3f(0, 0, 0), mi.ScalarTransform4f(),
                     half_extent=(1.0, 1.0), label="unit")
    return ShadowMap(view, depth.shape[0], mi.Float(np.asarray(depth, np.float32).ravel()))


def lookup(x, y, z):
    """Receivers at (x, y) (map coordinates in [-1, 1]) and depth z, facing the light,
    with no pixel footprint (the box is ``filter_size`` wide)."""
    x = np.atleast_1d(np.asarray(x, np.float64))
    y = np.broadcast_to(np.asarray(y, np.float64), x.shape)
    z = np.broadcast_to(np.asarray(z, np.float64), x.shape)
    p = mi.Point3f(mi.Float(x), mi.Float(np.array(y)), mi.Float(np.array(z)))
    return Lookup(p, mi.Vector3f(0, 0, -1), mi.Vector3f(0), mi.Vector3f(0), None, None, None)


def options(**props):
    return parse_options({"method": "evsm", "virtual": False, **props})   # full-map layers


def with_layers(smap: ShadowMap, opts) -> ShadowMap:
    """Build the layers ``opts`` reads (as the map manager does)."""
    for name in opts.record.layer_names(opts):
        if name not in smap.extra:
            smap.extra[name] = build_layer(None, smap, name, opts.record.layers[name])
    return smap


def vis(smap, lk, **props) -> np.ndarray:
    opts = options(**props)
    v = methods.get("evsm").lookup(with_layers(smap, opts), lk, opts, mi.Bool(True))
    return np.asarray(v.numpy(), np.float64)


def bounds(smap, lk, **props):
    opts = options(**props)
    p, n, _ = E.evsm_bounds(with_layers(smap, opts), lk, opts, mi.Bool(True))
    return np.asarray(p.numpy()), np.asarray(n.numpy())


def x_of_texel(c, res=RES):
    """Map coordinate of continuous texel coordinate ``c``."""
    return np.asarray(c, np.float64) * 2.0 / res - 1.0


def numpy_bounds(depth, x, y, z_r, filter_size, cp, cn, min_variance):
    """Both Chebyshev bounds from the box moments, computed independently in numpy
    (float64 normalisation over the map's finite depth span as :func:`normalized_depth`,
    ``[d_lo, d_hi]`` to ``[0, 1/2]``, float64 moments)."""
    res = depth.shape[0]
    finite = np.isfinite(depth)
    d_lo, d_hi = np.float64(depth[finite].min()), np.float64(depth[finite].max())
    scale = 0.5 / (d_hi - d_lo)
    z = np.where(finite, (depth.astype(np.float64) - d_lo) * scale, 1.0)
    lo, hi = 0.0, 0.5

    def u_of(zz):
        return np.clip(2.0 * (np.float64(zz) - lo) / (hi - lo) - 1.0, -1.0, 1.0)

    u = u_of(z)
    out = []
    for xi, yi, zi in zip(x, y, z_r):
        cx = np.float32((np.float32(xi) + 1) * 0.5) * res
        cy = np.float32((np.float32(yi) + 1) * 0.5) * res
        w = max(filter_size, 1.0)
        hx = min(w / 2, max(min(cx, res - cx), 0.5))
        hy = min(w / 2, max(min(cy, res - cy), 0.5))
        k = np.arange(res)
        wx = np.clip(np.minimum(cx + hx, k + 1) - np.maximum(cx - hx, k), 0, None)
        wy = np.clip(np.minimum(cy + hy, k + 1) - np.maximum(cy - hy, k), 0, None)
        wgt = wy[:, None] * wx[None, :]
        wgt /= wgt.sum()
        u_r = u_of((np.float64(np.float32(zi)) - d_lo) * scale)
        res_k = []
        for c, sign in ((cp, 1.0), (cn, -1.0)):
            wv = sign * np.exp(sign * c * u)
            m1, m2 = (wgt * wv).sum(), (wgt * wv * wv).sum()
            t = sign * np.exp(sign * c * u_r)
            var = max(m2 - m1 * m1, min_variance * (c * t * 2.0 / (hi - lo)) ** 2)
            res_k.append(1.0 if t <= m1 else var / (var + (t - m1) ** 2))
        out.append(res_k)
    return np.array(out).T


def plain_chebyshev(depth, cx, width, z_r, rows):
    """Chebyshev on the normalised depth itself (VSM without bleeding reduction), over
    texel columns ``[cx - width/2, cx + width/2)`` of ``rows``."""
    far = 2.0 * depth[np.isfinite(depth)].max()
    box = depth[rows, int(cx - width / 2):int(cx + width / 2)] / far
    m1, m2, t = box.mean(), (box ** 2).mean(), z_r / far
    var = m2 - m1 * m1
    return 1.0 if t <= m1 else var / (var + (t - m1) ** 2)


# --------------------------------------------------------- (1) hand-made map
def edge_map():
    d = np.full((RES, RES), 3.0, np.float32)      # a flat receiver plane at depth 3
    d[:, : RES // 2] = 1.0                        # columns i < 32: occluder at depth 1
    return ortho_map(d)


def test_behind_an_occluder_is_shadowed_in_front_lit():
    smap = edge_map()
    behind = vis(smap, lookup([-0.5, -0.3, -0.8], 0.1, 3.0))        # under the occluder
    lit = vis(smap, lookup([0.3, 0.5, 0.8], 0.1, 3.0))              # beside it
    in_front = vis(smap, lookup([-0.5, -0.3, 0.5], 0.1, 0.5))       # nearer than both
    print("behind", behind, "beside", lit, "in front", in_front)
    assert behind.max() <= 1e-6
    assert lit.min() >= 1.0 - 1e-6 and in_front.min() >= 1.0 - 1e-6
    outside = vis(smap, lookup([1.5, -2.0], 0.0, 3.0))               # off the map: lit
    assert outside.tolist() == [1.0, 1.0]


@pytest.mark.parametrize("filter_size", [1.0, 2.0, 5.0])
def test_edge_is_the_box_filtered_compare_and_monotone(filter_size):
    """One occluder over a flat receiver at the receiver's own depth: both warps hold
    two depths and the receiver sits on the deeper one, where Chebyshev is exact --
    the visibility is the box filter of the depth test, a linear ramp ``filter_size``
    texels wide across the edge, monotone."""
    smap = edge_map()
    offs = np.linspace(-4.0, 4.0, 321)                               # texels from the edge
    v = vis(smap, lookup(x_of_texel(RES / 2 + offs), 0.1, 3.0), filter_size=filter_size,
            **NO_BIAS)
    expected = np.clip(0.5 + offs / filter_size, 0.0, 1.0)
    print(f"filter_size {filter_size}: max |v - ramp| {np.abs(v - expected).max():.2e}")
    np.testing.assert_allclose(v, expected, atol=1e-5)      # float32 texel coordinates
    assert np.all(np.diff(v) >= -1e-9)      # monotone up to the float64 rounding (~1e-13)


# --------------------------------------- (2) each bound against numpy, the min
@pytest.mark.parametrize("cp, cn, filter_size, min_variance",
                         [(6.0, 6.0, 3.0, 1e-7), (10.0, 4.0, 2.5, 0.0), (2.0, 9.0, 7.3, 1e-5)])
def test_each_warp_is_chebyshev_on_its_box_moments(cp, cn, filter_size, min_variance):
    rng = np.random.default_rng(5)
    depth = rng.choice(np.array([1.0, 1.7, 2.2, 3.0, np.inf], np.float32), (RES, RES))
    depth[rng.random((RES, RES)) < 0.3] = 2.6
    smap = ortho_map(depth)
    n = 400
    x, y = rng.uniform(-0.98, 0.98, (2, n))
    x[:8] = np.linspace(-1.0, -0.99, 8)                      # boxes at the face border
    z_r = rng.uniform(0.8, 3.2, n)
    props = dict(exponent=cp, negative_exponent=cn, filter_size=filter_size,
                 min_variance=min_variance, **NO_BIAS)
    p_pos, p_neg = bounds(smap, lookup(x, y, z_r), **props)
    # the receiver depth after the rounding margin (common.DEPTH_ULPS), in float32
    z32 = z_r.astype(np.float32)
    z32 = z32 - np.float32(DEPTH_ULPS) * z32
    want_pos, want_neg = numpy_bounds(depth, x, y, z32, filter_size, cp, cn, min_variance)
    print(f"c+ {cp} c- {cn}: max |p+ - numpy| {np.abs(p_pos - want_pos).max():.2e}, "
          f"max |p- - numpy| {np.abs(p_neg - want_neg).max():.2e}; "
          f"{np.mean((want_pos > 0.01) & (want_pos < 0.99)):.0%} / "
          f"{np.mean((want_neg > 0.01) & (want_neg < 0.99)):.0%} fractional")
    np.testing.assert_allclose(p_pos, want_pos, rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(p_neg, want_neg, rtol=1e-6, atol=1e-9)
    v = vis(smap, lookup(x, y, z_r), **props)
    np.testing.assert_allclose(v, np.minimum(want_pos, want_neg), rtol=1e-6, atol=1e-7)
    assert np.any(want_pos < want_neg - 0.05) and np.any(want_neg < want_pos - 0.05)


def test_light_bleeding_reduction_is_applied_to_each_bound():
    smap = edge_map()
    lk = lookup(x_of_texel(RES / 2 + np.array([-1.0, -0.4, 0.0, 0.4])), 0.1, 3.0)
    p0 = np.minimum(*bounds(smap, lk, filter_size=3.0, **NO_BIAS))
    v = vis(smap, lk, filter_size=3.0, light_bleeding=0.3, **NO_BIAS)
    np.testing.assert_allclose(v, np.clip((p0 - 0.3) / 0.7, 0.0, 1.0), atol=1e-7)


# ----------------------------------------------- (3) less light bleeding than VSM
@pytest.mark.parametrize("res", [RES, 256])
def test_two_occluders_bleed_less_than_plain_chebyshev(res):
    """A near occluder A (depth 0.5) and a far one B (1.8) side by side over a receiver
    at depth 2 (truth: fully shadowed), with a far plane (depth 3) in the first columns,
    i.e. first in the tables' scan order (their precision's worst case). Plain Chebyshev on
    the depth leaks up to ~0.6 near the A|B border; the paper's claim is that the
    exponential warps do not."""
    d = np.full((res, res), 3.0, np.float32)
    h = res // 2
    d[:, res // 8:h] = 0.5
    d[:, h:h + res // 8] = 1.8
    rows = slice(res // 2 - 4, res // 2 + 4)
    offs = np.array([-3.0, -2.0, -1.0, 0.0, 1.0, 2.0, 3.0])
    v = vis(ortho_map(d), lookup(x_of_texel(h + offs, res), 0.0, 2.0), filter_size=8.0,
            **NO_BIAS)
    vsm = np.array([plain_chebyshev(d, h + o, 8, 2.0, rows) for o in offs])
    print(f"{res}^2: plain Chebyshev {np.round(vsm, 3)}, evsm {np.round(v, 4)}")
    assert vsm.max() > 0.5                       # the plain bound does bleed here
    assert v.max() <= 0.1 and np.all(v <= vsm / 4)


def test_the_negative_warp_bounds_a_ledge_over_a_far_background():
    """A receiver on a narrow ledge (depth 2) between a near occluder (1) and a far
    background (3.5) beside it: the background inflates the positive warp's mean past
    the receiver (bound 1); the negative warp keeps the visibility near the truth."""
    d = np.full((RES, RES), 3.5, np.float32)
    d[:, 16:32] = 1.0
    d[:, 32:38] = 2.0
    smap = ortho_map(d)
    lk = lookup(x_of_texel(np.array([35.0])), 0.0, 2.0)
    p_pos, p_neg = bounds(smap, lk, filter_size=12.0, **NO_BIAS)
    truth = 9.0 / 12.0                            # 3 of 12 columns hold the occluder
    print(f"ledge: truth {truth:.3f}, p+ {p_pos[0]:.3f}, p- {p_neg[0]:.3f}")
    assert p_pos[0] == 1.0 and truth <= p_neg[0] <= truth + 0.1


# ---------------------------------------- precision of the summed-area tables
def test_unresolvable_warps_read_lit_instead_of_noise(monkeypatch):
    """Far rows first in the scan, receivers on a near plane, exponents at the clamp: the
    positive warp's box means are below the tables' rounding. With the error bound the
    bound reads 1 (the negative warp decides: lit); without it, rounding noise shadows
    lit receivers."""
    res = 256
    d = np.full((res, res), 1.0, np.float32)
    d[:32, :] = 10.0
    smap = ortho_map(d)
    rng = np.random.default_rng(2)
    x, y = rng.uniform(-0.9, 0.9, 500), rng.uniform(-0.4, 0.9, 500)
    props = dict(exponent=42.0, negative_exponent=42.0, filter_size=2.0)
    guarded = vis(smap, lookup(x, y, 1.0), **props)
    monkeypatch.setattr(E, "SAT_ERROR", 0.0)
    unguarded = vis(smap, lookup(x, y, 1.0), **props)
    print(f"lit receivers shadowed: {np.mean(guarded < 0.5):.1%} with the error bound, "
          f"{np.mean(unguarded < 0.5):.1%} without")
    assert guarded.min() >= 1.0 - 1e-9
    assert np.mean(unguarded < 0.5) > 0.05


def test_map_whose_surfaces_share_one_depth():
    """All texels at one depth (up to rounding): the span is widened to common.MIN_SPAN
    of the depth (64 float32 ulps) instead of stretching float32 rounding over [-1, 1];
    deeper receivers are shadowed, nearer ones and the surface itself lit. With a
    rounding of 1 ulp (stdev) the negative warp sees the texels spread over ~1/16 of the
    warp's range and the positive warp decides: ``min_variance (4 c e^c)^2`` over
    ``e^(2c)``, 5.8e-5 (the old floor, 2^-10 of twice the largest depth, kept the
    negative warp below 1e-6 here, and lost the shadows of a spot 1e4 away)."""
    for noise, shadow in ((1e-7, 1e-4), (0.0, 1e-6)):
        d = (np.float32(0.6) * (1 + noise * np.random.default_rng(0)
                                .standard_normal((RES, RES)))).astype(np.float32)
        v = vis(ortho_map(d), lookup([-0.5, 0.0, 0.5], 0.0, 0.9))
        print(f"rounding {noise}: behind {v.max():.2e}")
        assert v.max() <= shadow
        v = vis(ortho_map(d), lookup([-0.5, 0.0, 0.5], 0.0, [0.5, 0.6, 0.6]))
        assert v.min() >= 1.0 - 1e-6
    empty = ortho_map(np.full((RES, RES), np.inf, np.float32))
    assert vis(empty, lookup([0.0, 0.5], 0.0, 2.0)).tolist() == [1.0, 1.0]


def test_normalisation_follows_the_depth_span_not_the_distance():
    """The same map 1e4 farther from the light (every depth + 1e4) gives the same
    visibility: min_variance is relative to the map's depth span. (Relative to twice the
    largest depth, sigma_min grew with the distance and lit the occluder's shadow:
    0.73-0.96 under it at + 1e4.)"""
    d = np.full((RES, RES), 3.0, np.float32)
    d[:, : RES // 2] = 1.0
    x = np.array([-0.6, -0.3, 0.3, 0.6, -0.5])
    z = np.array([3.0, 2.0, 3.0, 3.0, 0.9])
    near = vis(ortho_map(d), lookup(x, 0.1, z))
    far = vis(ortho_map(d + np.float32(1e4)), lookup(x, 0.1, z + 1e4))
    print("near", near, "1e4 farther", far)
    assert near[:2].max() <= 1e-6 and near[2:].min() >= 1.0 - 1e-6
    np.testing.assert_allclose(far, near, atol=1e-4)


@pytest.mark.parametrize("props", [{}, {"fit_frusta": True}])
def test_full_maps_keep_the_shadows_of_a_spot_far_away(props):
    """A spot 1e4 away, its cone fitted to an 8-unit scene (test_vsm.far_spot_scene):
    full maps lost every shadow (1.90 % misclassified, all false lit; ``hard`` 0.20 %);
    normalised over the map's own depth span 0.15 %."""
    from test_vsm import assert_far_spot_keeps_shadows
    assert_far_spot_keeps_shadows("evsm", props)


# --------------------------------------------------------- (4) exponent clamp
@pytest.mark.parametrize("name", ["exponent", "negative_exponent"])
@pytest.mark.parametrize("value", [42.5, 100.0, 0.0, -1.0])
def test_out_of_range_exponent_names_the_property_and_range(name, value):
    with pytest.raises(OptionError, match=rf"'{name}'.*> 0\.0 and <= 42\.0"):
        options(**{name: value})


def test_clamp_is_the_float32_limit_of_the_second_moment():
    assert E.MAX_EXPONENT == 42.0
    assert math.isfinite(float(np.float32(np.exp(2 * E.MAX_EXPONENT))))
    assert 2 * 44.4 > math.log(float(np.finfo(np.float32).max))   # 44.4 would overflow


@pytest.mark.parametrize("cp, cn", [(42.0, 42.0), (42.0, 1e-3), (1e-3, 42.0), (1e-3, 1e-3)])
def test_in_range_extremes_render_finite_visibility(cp, cn):
    scene = mi.load_dict(default_scene(width=24, height=24, spp=2, light="point"))
    _, v = render_np(scene, {"type": "shadowmap", "method": "evsm", "exponent": cp,
                             "negative_exponent": cn, "resolution": 128}, spp=2)
    v = np.stack(list(v.values()))
    print(f"c+ {cp} c- {cn}: visibility mean {v.mean():.3f}")
    assert np.isfinite(v).all() and v.min() >= 0.0 and v.max() <= 1.0 and v.max() > 0.5


# --------------------------------------------------------- layers and caching
def test_layers_are_named_after_their_exponents_and_cached():
    assert options().record.layer_names(options()) == (
        "evsm_span", "evsm_p1_6p0", "evsm_p2_6p0", "evsm_n1_6p0", "evsm_n2_6p0")
    assert E.moment_layer_names(2.5, 1e-3) == (
        "evsm_p1_2p5", "evsm_p2_2p5", "evsm_n1_0p001", "evsm_n2_0p001")
    scene = mi.load_dict(default_scene(width=16, height=16, spp=1))

    def built(**props):
        integ = mi.load_dict({"type": "shadowmap", "method": "evsm", "resolution": 32,
                              **props})
        mi.render(scene, integrator=integ, spp=1)
        return integ.stats["layers_built"], sorted(integ.maps[0].layers())

    n, layers = built()
    assert n == 5 and layers == sorted(["depth", *options().record.layer_names(options())])
    assert built(min_variance=1e-5, light_bleeding=0.2, filter_size=3.0)[0] == 0
    n, layers = built(exponent=2.5)          # only the positive pair is new
    assert n == 2 and "evsm_p1_2p5" in layers and "evsm_n1_6p0" in layers
    assert built(exponent=2.5)[0] == 0


# ------------------------------------------------------- (5) repository scenes
SPP = 4
_REFS = {}


def reference(path):
    if path not in _REFS:
        scene = mi.load_file(str(path), width=64, height=64)
        if any(emitter_kind(e) == "area" for e in scene.emitters()):
            ref = converged_visibility(scene, n_light=1024, spp=SPP, seed=0)
        else:
            _, ref = render_np(scene, {"type": "shadowmap", "method": "raytraced"},
                               spp=SPP, seed=0)
        _REFS[path] = (scene, ref)
    return _REFS[path]


@pytest.mark.parametrize("path", full_map_scenes(
    "full maps lose the shadows of the issue-11 scenes (see conftest.VIRTUAL_SCENES); "
    "this test pins full maps (resolution 1024)"))
def test_repository_scene_misclassified_and_false_lit(path):
    scene, ref = reference(path)
    _, v = render_np(scene, {"type": "shadowmap", "method": "evsm", "resolution": 1024},
                     spp=SPP, seed=0)
    r = np.stack([ref[k] for k in sorted(ref)])
    v = np.stack([v[k] for k in sorted(v)])
    assert np.isfinite(v).all() and v.min() >= 0 and v.max() <= 1
    m = metrics.misclassified(r, v)
    rmse = float(np.sqrt(np.mean((r - v) ** 2)))
    print(f"{path.stem} evsm: misclassified {m['misclassified']:.2%} (false shadow "
          f"{m['false_shadow']:.2%}, false lit {m['false_lit']:.2%}), vis RMSE {rmse:.4f}")
    assert m["misclassified"] <= 0.03 and m["false_lit"] <= 0.01


# -------------------------------------------------------------- (6) bad input
@pytest.mark.parametrize("props, name", [
    ({"filter_size": -1.0}, "filter_size"),
    ({"filter_size": "2"}, "filter_size"),
    ({"filter_size": float("inf")}, "filter_size"),
    ({"exponent": "6"}, "exponent"),
    ({"exponent": True}, "exponent"),
    ({"exponent": float("nan")}, "exponent"),
    ({"negative_exponent": None}, "negative_exponent"),
    ({"negative_exponent": [6.0]}, "negative_exponent"),
    ({"min_variance": -1e-9}, "min_variance"),
    ({"min_variance": 1.5}, "min_variance"),
    ({"min_variance": "small"}, "min_variance"),
    ({"light_bleeding": 1.0}, "light_bleeding"),
    ({"light_bleeding": -0.1}, "light_bleeding"),
    ({"light_bleeding": False}, "light_bleeding"),
    ({"num_samples": 4}, "num_samples"),        # a pcf property
    ({"moment_bias": 1e-3}, "moment_bias"),      # another prefiltered method's property
])
def test_bad_input_names_the_property(props, name):
    with pytest.raises(OptionError, match=name):
        options(**props)


# ------------------------------------------------------ (7) mono and spectral
@pytest.mark.parametrize("variant", ["llvm_ad_mono", "llvm_ad_spectral"])
def test_renders_in_mono_and_spectral(variant):
    mi.set_variant(variant)
    scene = mi.load_file(str(SCENE_FILES[0].parent / "spot_sphere_box.xml"),
                         width=48, height=48)
    _, ref = render_np(scene, {"type": "shadowmap", "method": "raytraced"}, spp=4)
    img, v = render_np(scene, {"type": "shadowmap", "method": "evsm", "resolution": 256},
                       spp=4)
    assert img.shape[-1] == (1 if variant.endswith("mono") else 3)
    r, v = np.stack(list(ref.values())), np.stack(list(v.values()))
    m = metrics.misclassified(r, v)["misclassified"]
    print(f"{variant}: evsm misclassified {m:.2%}")
    assert np.isfinite(img).all() and img.max() > 0
    assert np.isfinite(v).all() and v.min() >= 0 and v.max() <= 1 and m <= 0.03


@pytest.mark.parametrize("tilt", [1.0, 5.0])
def test_full_maps_do_not_shade_a_wall_a_spot_grazes(tilt):
    """A spot 0.05 from a wall, turned ``tilt`` degrees into it: full maps shaded a band
    of the lit wall at a fixed distance from the light (11.6 % of its lit pixels at 1
    degree, 6.3 % at 5), its normal offset (0.25 texel) too small where the slope bias
    is clamped; at least half a texel there now (filters.common.GRAZING_OFFSET)."""
    T = mi.ScalarTransform4f
    a = math.radians(tilt)
    target = [-3.5 + math.cos(a), 1.0, 0.05 - math.sin(a)]
    scene = mi.load_dict({
        "type": "scene",
        "sensor": {"type": "perspective", "fov": 60, "near_clip": 1e-2, "far_clip": 100,
                   "to_world": T().look_at(origin=[0.5, 1.0, 5.0], target=[0.5, 1.0, 0],
                                           up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": 64, "height": 64,
                            "rfilter": {"type": "box"}}},
        "wall": {"type": "rectangle", "to_world": T().scale(4), "bsdf": {"type": "diffuse"}},
        "spot": {"type": "spot", "to_world": T().look_at(origin=[-3.5, 1.0, 0.05],
                                                         target=target, up=[0, 1, 0]),
                 "intensity": {"type": "rgb", "value": 200.0}, "cutoff_angle": 30,
                 "beam_width": 25}})

    def vis(**kw):
        integ = mi.load_dict({"type": "shadowmap", **kw})
        return np.asarray(mi.render(scene, integrator=integ, spp=4, seed=2))[..., -1]
    lit = vis(method="raytraced") >= 0.5
    assert lit.mean() > 0.5
    shaded = float(np.mean(vis(method="evsm", virtual=False)[lit] < 0.5))
    print(f"tilt {tilt}: {shaded:.2%} of the lit wall shaded")
    assert shaded <= 0.01


def test_chebyshev_with_error_bounds_is_the_largest_bound_of_the_error_box():
    """``chebyshev`` with the moments' error bounds ``err1``, ``err2`` must not read less
    light than the plain bound of any moments within them (the guard of the
    summed-area tables' rounding reads lit, never shadow): it is at least the largest
    plain bound over a grid of ``(m1 + a err1, m2 + b err2)``, ``|a|, |b| <= 1``. A
    large mean (the positive warp near a receiver) makes the ``2 |m1| err1`` term of the
    variance's bound the one that matters. (Mutation audit: the variance's bound
    without its ``m1`` terms survived every test.)"""
    m1, m2, t = 100.0, 100.0 ** 2 + 50.0, 110.0
    err1, err2 = 0.5, 1.0
    a, b = np.meshgrid(np.linspace(-1, 1, 41), np.linspace(-1, 1, 41))
    m1s, m2s = m1 + a.ravel() * err1, m2 + b.ravel() * err2
    f64 = mi.Float64
    plain = np.asarray(E.chebyshev(f64(m1s), f64(m2s), f64(np.full(m1s.size, t)), 0.0))
    guarded = np.asarray(E.chebyshev(f64([m1]), f64([m2]), f64([t]), 0.0, 0.0, f64([err1]),
                                     f64([err2])))[0]
    print(f"plain at the centre {plain[m1s.size // 2]:.3f}, largest in the box "
          f"{plain.max():.3f}, guarded {guarded:.3f}")
    assert plain.max() > plain[m1s.size // 2] + 0.1      # the error box matters here
    assert guarded >= plain.max() - 1e-12
    assert guarded < 1.0                                 # and still a bound, not 'lit'
