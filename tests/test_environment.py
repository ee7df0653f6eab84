"""Shadowed environment light (issue 12, part 2): ``mi_shadowmap.environment``.

Median-cut properties, the ``constant`` emitter's uniform regions, convergence
towards ``direct`` as ``env_lights`` grows on ``scenes_xml/sky_sun.xml`` (small
sizes), ``raytraced`` = ``direct``, the 'error' / 'unshadowed' choices, bad
input, and the mono / spectral variants.
"""
from __future__ import annotations

import math
from pathlib import Path

import mitsuba as mi
import numpy as np
import pytest

from mi_shadowmap import environment as env
from mi_shadowmap.options import OptionError, parse_options

SKY = Path(__file__).resolve().parents[1] / "scenes_xml" / "sky_sun.xml"
DIRECT = {"type": "direct", "emitter_samples": 1, "bsdf_samples": 0}


def _scene(size=32, **kw):
    return mi.load_file(str(SKY), width=size, height=size, **kw)


def _render(scene, integ, spp, seed=0):
    return np.asarray(mi.render(scene, integrator=mi.load_dict(integ), spp=spp, seed=seed))


def _rel(a, ref):
    n = 1 if mi.is_monochromatic else 3   # colour channels (the AOVs follow)
    return float(np.sqrt(np.mean((a[..., :n] - ref[..., :n]) ** 2))
                 / np.sqrt(np.mean(ref[..., :n] ** 2)))


@pytest.fixture(scope="module")
def sky_ref():
    scene = _scene()
    return scene, _render(scene, DIRECT, 1024, seed=7)


# ------------------------------------------------------------------ the cut
@pytest.mark.parametrize("K", [1, 2, 7, 16, 64])
def test_median_cut_properties(K):
    scene = _scene()
    reg = env.emitter_regions(scene.emitters()[0], K)
    assert reg.count == K
    assert abs(reg.solid_angle.sum() - 4 * math.pi) < 1e-6
    assert np.allclose(np.linalg.norm(reg.directions, axis=1), 1.0)
    assert (reg.solid_angle > 0).all() and (reg.energy >= 0).all()
    # the regions tile the map: the texel tables hold every cell once
    H, W = reg.grid
    cells = reg.tex_row.astype(np.int64) * W + reg.tex_col
    assert len(cells) == H * W and len(np.unique(cells)) == H * W
    # pmfs sum to 1 per region, cdfs end at 1
    ends = np.append(reg.offset[1:], len(reg.cdf)) - 1
    assert np.allclose(reg.cdf[ends], 1.0)
    # deterministic
    again = env.regions_of(*_lum(scene, reg), K, env._to_world(scene.emitters()[0]))
    assert np.array_equal(again.rects, reg.rects)


def _lum(scene, reg):
    return (env.luminance_grid(scene.emitters()[0], *reg.grid)[0],)


def test_median_cut_balances_energy_on_a_smooth_map():
    # a smooth map (no texel-sized sun): the median cut gives nearly equal energies
    H, W = 64, 128
    t = (np.arange(H) + 0.5) / H * np.pi
    lum = np.broadcast_to((1.0 + np.cos(t))[:, None], (H, W)).copy()
    reg = env.regions_of(lum, 16, np.eye(3))
    share = reg.energy / reg.energy.sum()
    assert share.max() / share.min() < 1.6


def test_sun_gets_its_own_small_regions():
    reg = env.emitter_regions(_scene().emitters()[0], 16)
    # the sun (about half of the energy) is cut into pieces of a few degrees
    small = reg.solid_angle < 0.05
    assert reg.energy[small].sum() / reg.energy.sum() > 0.4
    assert (reg.angular_diameter[small] < 8.0).all()


def test_constant_emitter_gives_uniform_regions():
    e = mi.load_dict({"type": "constant", "radiance": 1.0})
    reg = env.emitter_regions(e, 16)
    assert reg.count == 16
    assert abs(reg.solid_angle.sum() - 4 * math.pi) < 1e-6
    share = reg.energy / reg.energy.sum()
    assert np.allclose(share, 1 / 16, rtol=0.15)
    assert np.allclose(reg.solid_angle, 4 * math.pi / 16, rtol=0.15)


# ------------------------------------------------------------------ shading
def test_raytraced_equals_direct(sky_ref):
    scene, _ = sky_ref
    a = _render(scene, {"type": "shadowmap", "method": "raytraced"}, 16, seed=3)
    b = _render(scene, DIRECT, 16, seed=3)
    assert _rel(a, b) < 2e-3


def test_converges_towards_direct_as_K_grows(sky_ref):
    scene, ref = sky_ref
    err = {K: _rel(_render(scene, {"type": "shadowmap", "method": "hard", "env_lights": K,
                                   "resolution": 512}, 256, seed=1), ref)
           for K in (1, 4, 16, 64)}
    print("relative RMSE vs direct@1024 by K:", err)
    assert err[1] > err[4] > err[16] > err[64]
    assert err[64] < 0.04


@pytest.mark.parametrize("method", ["pcf", "pcss", "bilinear", "multiview", "vsm"])
def test_every_map_method_renders(sky_ref, method):
    scene, ref = sky_ref
    img = _render(scene, {"type": "shadowmap", "method": method, "resolution": 256}, 16)
    assert np.isfinite(img).all()
    vis = img[..., 3]
    assert vis.min() >= 0 and vis.max() <= 1 + 1e-5
    assert _rel(img, ref) < 0.2


def test_constant_emitter_is_shadowed():
    scene = mi.load_dict({
        "type": "scene",
        "sensor": {"type": "perspective", "fov": 40,
                   "to_world": mi.ScalarTransform4f().look_at([0, 4, 4], [0, 0, 0], [0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": 32, "height": 32,
                            "rfilter": {"type": "box"}}},
        "ground": {"type": "rectangle",
                   "to_world": mi.ScalarTransform4f().rotate([1, 0, 0], -90).scale(3)},
        "ball": {"type": "sphere", "center": [0, 0.6, 0], "radius": 0.5},
        "sky": {"type": "constant", "radiance": 1.0}})
    ref = _render(scene, DIRECT, 1024, seed=5)
    unsh = _render(scene, {"type": "shadowmap", "environment": "unshadowed"}, 64)
    img = _render(scene, {"type": "shadowmap", "env_lights": 64, "resolution": 256}, 64)
    assert _rel(img, ref) < 0.5 * _rel(unsh, ref)
    assert _rel(img, ref) < 0.05


def test_unshadowed_and_error():
    scene = _scene()
    unsh = _render(scene, {"type": "shadowmap", "environment": "unshadowed"}, 4)
    base = _render(scene, {"type": "shadowmap", "method": "unshadowed"}, 4)
    assert np.allclose(unsh, base, rtol=1e-5, atol=1e-6)   # no shadows at all
    shadowed = _render(scene, {"type": "shadowmap", "resolution": 256}, 4)
    assert shadowed[..., :3].mean() < 0.97 * unsh[..., :3].mean()
    integ = mi.load_dict({"type": "shadowmap", "environment": "error"})
    with pytest.raises(ValueError, match="environment"):
        integ.check_scene(scene)


def test_unshadowed_environment_with_several_shadow_rays():
    """``environment='unshadowed'`` with ``shadow_rays`` > 1: the environment's light
    samples run in the light-sample loop without a map (visibility 1), the sun's with
    shadow rays; the same expectation as one shadow ray (a crash before: the loop
    looked the environment's samples up in a map it does not have)."""
    scene = _scene()
    env_k = [k for k, e in enumerate(scene.emitters()) if e.is_environment()]
    assert env_k
    n = 1 if mi.is_monochromatic else 3
    many = _render(scene, {"type": "shadowmap", "method": "raytraced", "shadow_rays": 4,
                           "environment": "unshadowed"}, 16)
    one = _render(scene, {"type": "shadowmap", "method": "raytraced",
                          "environment": "unshadowed"}, 16)
    assert np.isfinite(many).all()
    for k in env_k:     # 1 wherever a sample contributes: no occlusion at all
        vis = many[..., n + k]
        assert vis.min() >= 0.0 and vis.max() == 1.0 and vis.mean() > 0.5
    assert abs(many[..., :n].mean() / one[..., :n].mean() - 1.0) < 0.03


@pytest.mark.parametrize("props, name", [
    ({"environment": "sometimes"}, "environment"),
    ({"env_lights": 0}, "env_lights"),
    ({"env_lights": 2000}, "env_lights"),
    ({"env_lights": 2.5}, "env_lights"),
    ({"method": "raytraced", "env_lights": 8}, "env_lights"),
])
def test_bad_input_names_the_property(props, name):
    with pytest.raises(OptionError, match=name):
        parse_options(props)


def test_defaults():
    o = parse_options({})
    assert o.environment == "shadowed" and o.env_lights == 16


@pytest.mark.parametrize("variant", ["llvm_ad_mono", "llvm_ad_spectral"])
def test_other_variants(variant):
    old = mi.variant()
    try:
        mi.set_variant(variant)
        scene = _scene(size=16)
        ref = _render(scene, DIRECT, 256, seed=2)
        img = _render(scene, {"type": "shadowmap", "resolution": 256}, 16)
        rt = _render(scene, {"type": "shadowmap", "method": "raytraced"}, 8, seed=4)
        assert np.isfinite(img).all()
        assert _rel(img, ref) < 0.15
        assert _rel(rt, _render(scene, DIRECT, 8, seed=4)) < 2e-3
    finally:
        mi.set_variant(old)
