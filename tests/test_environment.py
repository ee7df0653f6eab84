"""Shadowed environment light (issue 12, part 2): ``mi_shadowmap.environment``.

Median-cut properties, the ``constant`` emitter's uniform regions, convergence
towards ``direct`` as ``env_lights`` grows on ``scenes_xml/sky_sun.xml`` (small
sizes), ``raytraced`` = ``direct``, the 'error' / 'unshadowed' choices, bad
input, and the mono / spectral variants.
"""
from __future__ import annotations

import math
import re
from pathlib import Path

import drjit as dr
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
    # pmfs sum to 1 per region, cdfs end at exactly 1 (a last texel ending at 1 - 1e-16
    # leaves draws above it to the next region's first texel; mutation audit)
    ends = np.append(reg.offset[1:], len(reg.cdf)) - 1
    assert np.all(reg.cdf[ends] == 1.0)
    starts = np.append(0, ends[:-1] + 1)
    for a, b in zip(starts, ends):
        assert np.all(np.diff(reg.cdf[a:b + 1]) >= 0.0)
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



def test_a_large_envmap_is_cut_on_its_texels():
    """A 2048 x 1024 envmap (a common HDRI size) refined to half texels is 8.4M cells,
    each evaluated twice (centre and corners) with float64 direction arrays: a 4096 x
    2048 one took 43 s of CPU and 4.6 GB per cut. Past MAX_REFINED_CELLS the cut works
    on the texels (4x fewer cells); small maps keep half-texel cells."""
    def envmap(H, W):
        img = np.ones((H, W, 3), np.float32)
        img[H // 4, W // 3] = 1e7    # a one-texel sun, most of the energy
        return mi.load_dict({"type": "envmap", "bitmap": mi.Bitmap(img)})
    assert env.grid_shape(envmap(64, 128)) == (128, 256)
    big = envmap(1024, 2048)
    H, W = env.grid_shape(big)
    assert H * W <= env.MAX_REFINED_CELLS and (H, W) == (1024, 2048)
    reg = env.emitter_regions(big, 16)
    assert reg.grid == (1024, 2048)
    # the sun's texel still gets a tiny region of its own share of the energy
    k = int(np.argmax(reg.energy))
    assert reg.solid_angle[k] < 1e-3 and reg.energy[k] / reg.energy.sum() > 0.1



def test_a_rotated_environment_keeps_its_cut(monkeypatch):
    """The cut is made in the emitter's frame: an envmap turned through params.update()
    (a sky's time of day) re-ran it every frame (a 2048 x 1024 sky: 2.0-2.8 s of CPU a
    frame with hard, now 0.1 s); its regions' directions rotate with it, as a fresh
    cut of an emitter loaded with that to_world gives them."""
    img = np.ones((16, 32, 3), np.float32)
    img[4, 20] = 500.0
    env._CACHE.clear()
    e = mi.load_dict({"type": "envmap", "bitmap": mi.Bitmap(img)})
    first = env.emitter_regions(e, 8)
    calls = []
    real = env.luminance_grid
    monkeypatch.setattr(env, "luminance_grid", lambda *a: calls.append(1) or real(*a))
    R = mi.ScalarTransform4f().rotate([1, 0, 0], -90).rotate([0, 0, 1], 35)
    p = mi.traverse(e)
    p["to_world"] = R
    p.update()
    turned, key = env.emitter_regions(e, 8, with_key=True)
    assert not calls
    assert env._CACHE[key] is turned     # the views read the world-space cut by key
    M = np.array(R.matrix, dtype=np.float64)[:3, :3]
    assert np.allclose(turned.directions, first.directions @ M.T, atol=1e-6)
    assert np.array_equal(turned.rects, first.rects)
    env._CACHE.clear()
    fresh = env.emitter_regions(mi.load_dict(
        {"type": "envmap", "bitmap": mi.Bitmap(img), "to_world": R}), 8)
    assert np.array_equal(fresh.rects, turned.rects)
    assert np.allclose(fresh.directions, turned.directions, atol=1e-5)


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
    ({"environment": "unshadowed", "env_lights": 8}, "env_lights.*environment='shadowed'"),
    ({"environment": "error", "env_lights": 8}, "env_lights.*environment='shadowed'"),
    # virtual=true asked for: more than 32 regions got full maps silently
    ({"virtual": True, "env_lights": 33}, "'env_lights' = 33 with virtual=true"),
])
def test_bad_input_names_the_property(props, name):
    with pytest.raises(OptionError, match=name):
        parse_options(props)


def test_more_regions_than_the_map_has_cells_warns():
    """A map of 2 x 4 texels (6 x 12 half-texel cells, with Mitsuba's padding) cannot
    be cut into 128 regions: the warning names env_lights and the count it got (before:
    fewer regions, silently)."""
    bmp = mi.Bitmap(np.ones((2, 4, 3), dtype=np.float32))
    emitter = mi.load_dict({"type": "envmap", "bitmap": bmp})
    with pytest.warns(UserWarning, match=r"'env_lights' = 128 .* gets 72 regions"):
        reg = env.emitter_regions(emitter, 128)
    assert reg.count == 72
    import warnings
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert env.emitter_regions(emitter, 64).count == 64


def _sunsky_scene(size=32, sun=(0.5, 0.7, 0.3), objects=True):
    """The sky_sun layout (a ball and a box on a ground; with ``objects`` False the ground
    alone) seen from above under Mitsuba's ``sunsky`` whose sun is at ``sun``."""
    T = mi.ScalarTransform4f
    scene = {
        "type": "scene",
        "cam": {"type": "perspective", "fov": 40,
                "to_world": T().look_at([0.2, 3.5, 4.9], [0.25, 0.25, 0], [0, 1, 0]),
                "film": {"type": "hdrfilm", "width": size, "height": size,
                         "rfilter": {"type": "box"}}},
        "ground": {"type": "rectangle", "to_world": T().rotate([1, 0, 0], -90).scale(4)},
        "sky": {"type": "sunsky", "sun_direction": [float(x) for x in sun]}}
    if objects:
        scene["ball"] = {"type": "sphere", "center": [0, 0.6, 0], "radius": 0.6}
        scene["box"] = {"type": "cube",
                        "to_world": T().translate([1.3, 0.4, 0.5]).scale(0.4)}
    return mi.load_dict(scene)


@pytest.mark.parametrize("variant", ["llvm_ad_rgb", "llvm_ad_spectral"])
def test_a_sunsky_sun_is_found_by_the_cut(variant):
    """``sunsky`` has no texels: on the 32 x 64 grid of a ``constant`` its 0.54-degree sun
    fell between the cells' points, so the cells' sampling missed it (or caught it on a
    corner): measured at 48^2, 16 spp, ``hard``'s image mean +16 % (rgb) / -12 %
    (spectral) against ``direct`` with the same seed, RMSE 48x / 39x ``direct``'s own
    noise (seed 0 against seed 1); now its grid is refined until its energy is the
    emitter's own sampled one: +0.6 % / +0.3 %, 0.82x / 0.76x. A constant keeps its
    32 x 64 cells."""
    mi.set_variant(variant)
    scene = _sunsky_scene()
    d0, d1 = _render(scene, DIRECT, 16, seed=0), _render(scene, DIRECT, 16, seed=1)
    noise = np.sqrt(np.mean((d0 - d1) ** 2))
    for props in ({}, {"virtual": False}):
        img = _render(scene, {"type": "shadowmap", **props}, 16, seed=0)[..., :3]
        assert np.isfinite(img).all()
        bias = img.mean() / d0.mean() - 1
        err = np.sqrt(np.mean((img - d0) ** 2)) / noise
        print(f"{variant} {props}: mean {bias:+.4f}, RMSE {err:.2f}x direct's noise")
        assert abs(bias) < 0.03 and err < 1.5
    assert env.grid_shape(mi.load_dict({"type": "constant"})) == env.CONSTANT_GRID
    H, W = env.grid_shape(scene.emitters()[0])
    assert H * W > env.CONSTANT_GRID[0] * env.CONSTANT_GRID[1]


def test_a_sunsky_gradient_follows_the_sun_around_the_zenith():
    """The image's derivative wrt ``sun_direction`` turned about the sky's zenith (+z in
    Mitsuba's ``sunsky``: the sun's elevation, and with it its radiance, is unchanged, so
    only the sun's and the sky's motion count) against central differences of
    ``direct`` (same seed). The regions' samples are drawn from tables without
    derivative, so the sun's disc moved over fixed samples: measured 0.0095 against
    0.0977 (no occluder in the view); with the samples near the sun turned with it
    (environment._sun_warp) 0.0903. (Other directions mix in
    Mitsuba's derivative of the sun's radiance wrt its direction, which ``direct``'s AD
    shares and which differs from its finite differences.)"""
    scene_at = _open_sunsky_scene
    s = np.array([0.5, 0.7, 0.3])
    t = np.array([-s[1], s[0], 0.0])                 # d s / d angle about +z
    h = 0.02
    fd = []
    for sign in (1, -1):
        c, n = math.cos(sign * h), math.sin(sign * h)
        r = [c * s[0] - n * s[1], n * s[0] + c * s[1], s[2]]
        fd.append(_render(scene_at(r), DIRECT, 256, seed=5)[..., 0].mean())
    fd = (fd[0] - fd[1]) / (2 * h)
    scene = scene_at(s)
    params = mi.traverse(scene)
    dr.enable_grad(params["sky.sun_direction"])
    params.update()
    img = mi.render(scene, params, integrator=mi.load_dict({"type": "shadowmap",
                                                             "method": "vsm"}),
                    spp=64, seed=1)
    dr.backward(dr.mean(img[..., 0]))
    g = np.array(dr.grad(params["sky.sun_direction"])).ravel()
    ad = float(g @ t)
    print(f"AD {ad:.4f}, FD {fd:.4f}")
    assert abs(ad - fd) <= 0.2 * abs(fd)


def _open_sunsky_scene(sun, size=16):
    """A diffuse ground seen from above under a ``sunsky`` whose sun is at ``sun``."""
    return _sunsky_scene(size, sun, objects=False)


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
        img = _render(scene, {"type": "shadowmap"}, 16)     # defaults: virtual regions
        full = _render(scene, {"type": "shadowmap", "resolution": 256}, 16)
        rt = _render(scene, {"type": "shadowmap", "method": "raytraced"}, 8, seed=4)
        assert np.isfinite(img).all() and np.isfinite(full).all()
        assert _rel(img, ref) < 0.15 and _rel(full, ref) < 0.15
        assert _rel(rt, _render(scene, DIRECT, 8, seed=4)) < 2e-3
    finally:
        mi.set_variant(old)


# ------------------------------------------------------- virtual region maps
def _sky_scene(eye, fov, **shapes):
    """``shapes`` under a constant sky, seen from ``eye`` towards the origin (32^2)."""
    T = mi.ScalarTransform4f
    return mi.load_dict({
        "type": "scene",
        "sensor": {"type": "perspective", "fov": fov,
                   "to_world": T().look_at(eye, [0, 0, 0], [0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": 32, "height": 32}},
        **shapes, "sky": {"type": "constant", "radiance": 1.0}})


def _virtual_render(scene, spp=4, **props):
    integ = mi.load_dict({"type": "shadowmap", **props})
    img = np.asarray(mi.render(scene, integrator=integ, spp=spp, seed=0))
    return img, integ


def test_region_views_project_and_cast_as_their_orthographic_maps():
    """Face k of the virtual environment map is region k's orthographic map: float64
    projection equal to the region map's own (float32) one, and the texel ray through a
    point's ``uv`` passes through the point at its depth -- for the per-lane region view
    the lookups read and the per-texel face the page build casts."""
    scene = _scene()
    view = env.environment_view(scene.emitters()[0], scene, "sky", 16)
    assert view.supports_virtual and view.n_faces == 16
    rng = np.random.default_rng(3)
    lo, hi = (np.array(scene.bbox().min), np.array(scene.bbox().max))
    p = lo + rng.random((64, 3)) * (hi - lo)
    P = mi.Point3f(*[mi.Float(p[:, a]) for a in range(3)])
    for k in (0, 5, 15):
        rv = view.region_view(mi.UInt32(np.full(64, k, np.uint32)))
        face, uv64, depth64, inside = rv.project_f64(mi.Point3d(P))
        _, uv32, depth32, _ = rv.inner.project(P)
        assert np.all(face.numpy() == k) and inside.numpy().all()
        assert np.allclose(uv64.numpy(), uv32.numpy(), atol=1e-5)
        assert np.allclose(depth64.numpy(), depth32.numpy(), rtol=1e-5, atol=1e-4)
        for o, d in (rv.ray_through_f64(face, uv64),
                     view.ray_through_f64(mi.UInt32(face), uv64)):
            q = np.asarray((o + d * depth64).numpy()).T
            assert np.allclose(q, np.asarray(P.numpy()).T, rtol=0.0,
                               atol=1e-9 * np.abs(hi - lo).max())
        # the float32 differentials are the float64 projection's
        dp = mi.Vector3f(1e-3, -2e-3, 5e-4)
        duv = rv.uv_differential(face, P, dp).numpy()
        uv2 = rv.project_f64(mi.Point3d(P) + mi.Vector3d(dp))[1].numpy()
        assert np.allclose(duv, uv2 - uv64.numpy(), atol=1e-7)


def test_virtual_regions_build_a_tenth_of_the_full_maps_and_match_them():
    """At defaults an environment's K regions are the K faces of one virtual map: pages
    where the camera's points read each region, at their pixels' density. On sky_sun at
    64^2 they cast about a tenth of the full maps' texels, and the visibility AOV is
    the full maps' (both against 256 shadow rays per camera sample). A still camera
    casts nothing again."""
    from mi_shadowmap.virtual import VirtualShadowMap
    scene = _scene(size=64)
    ref = _render(scene, {"type": "shadowmap", "method": "raytraced", "shadow_rays": 256},
                  16, seed=1)
    full, integ_f = _virtual_render(scene, 16, method="hard", virtual=False)
    virt, integ_v = _virtual_render(scene, 16, method="hard")
    vmap = integ_v.maps[0]
    assert isinstance(vmap, VirtualShadowMap) and isinstance(vmap.view, env.EnvironmentView)
    texels_v, texels_f = integ_v.stats.texels_built, integ_f.stats.texels_built
    print("texels per pixel: virtual", texels_v / 64 ** 2, "full", texels_f / 64 ** 2)
    assert 0 < texels_v < texels_f / 6
    assert set(vmap.page_records()["face"].tolist()) == set(range(16))
    n = 1 if mi.is_monochromatic else 3
    err_v = np.abs(virt[..., n] - ref[..., n]).mean()
    err_f = np.abs(full[..., n] - ref[..., n]).mean()
    print("mean |AOV - 256-ray AOV|: virtual", err_v, "full", err_f)
    assert err_v < 1.15 * err_f + 1e-3
    assert abs(virt[..., :n].mean() / full[..., :n].mean() - 1.0) < 0.01
    _virtual_render(scene, 16, method="hard")     # a still camera: every page cached
    again, integ_2 = _virtual_render(scene, 16, method="hard")
    assert integ_2.stats.texels_built == 0
    assert np.allclose(again, virt)


def test_mark_pass_skips_regions_below_a_points_horizon():
    """A region that cannot reach above a point's horizon (its extent plus
    ``MARK_SLACK``) is never read there, so the mark pass builds it no page: a flat
    ground seen from above under a constant sky gets fine pages in the regions of the
    upper hemisphere, none in those well below its horizon (they keep their coarsest
    page)."""
    scene = _sky_scene([0, 6, 0.01], 30, ground={
        "type": "rectangle", "to_world": mi.ScalarTransform4f().rotate([1, 0, 0], -90).scale(3)})
    img, integ = _virtual_render(scene, 4, method="hard")
    assert np.isfinite(img).all()
    vmap = integ.maps[0]
    view = vmap.view
    rec = vmap.page_records()
    fine = set(rec["face"][rec["level"] < vmap.layout.coarsest].tolist())
    # each region's highest and lowest elevation, from its rectangle of directions on a
    # fine grid (not from the view's own region_radii)
    R = np.asarray(view.to_world_env).reshape(3, 3)
    s = np.linspace(0.0, 1.0, 65)
    top = np.array([(env._directions((v0 + s * (v1 - v0)) * np.pi, (u0 + s * (u1 - u0))
                                     * 2.0 * np.pi).reshape(-1, 3) @ R.T)[:, 1].max()
                    for u0, u1, v0, v1 in np.asarray(view.rects)])
    below = set(np.flatnonzero(top < -math.sin(env.MARK_SLACK) - 0.02).tolist())
    above = set(np.flatnonzero(top > 0.02).tolist())
    assert below and above
    assert not (fine & below)
    assert above <= fine


def test_virtual_true_takes_up_to_32_regions():
    assert parse_options({"virtual": True, "env_lights": 32}).virtual
    parse_options({"env_lights": 33})                    # automatic: full maps for it
    assert not parse_options({"virtual": False, "env_lights": 64}).virtual


def test_more_regions_than_a_virtual_map_has_faces_keep_full_maps():
    from mi_shadowmap.depth_maps import ShadowMap
    scene = _scene(size=16)
    img, integ = _virtual_render(scene, 1, method="hard", env_lights=env.MAX_VIRTUAL_REGIONS + 1)
    assert np.isfinite(img).all() and isinstance(integ.maps[0], ShadowMap)


def _glass_pane_from_above():
    """A rough glass pane seen from above, a blocker below it: light reaches the pane
    from below, through it."""
    T = mi.ScalarTransform4f
    return _sky_scene(
        [0, 6, 0.01], 40,
        pane={"type": "rectangle", "to_world": T().rotate([1, 0, 0], -90).scale(2),
              "bsdf": {"type": "roughdielectric", "alpha": 0.3, "int_ior": 1.5}},
        blocker={"type": "rectangle", "to_world": T().translate([0.7, -0.3, 0])
                 .rotate([1, 0, 0], -90).scale(0.6),
                 "bsdf": {"type": "twosided", "bsdf": {"type": "diffuse"}}},
        far={"type": "sphere", "center": [60, 0, 0], "radius": 0.1})


def _two_sided_ceiling_from_below():
    """A two-sided ceiling seen from below (its normal faces away from the camera), a
    blocker under one side."""
    T = mi.ScalarTransform4f
    return _sky_scene(
        [0, -6, 0.01], 20,
        ceiling={"type": "rectangle", "to_world": T().rotate([1, 0, 0], -90).scale(2),
                 "bsdf": {"type": "twosided", "bsdf": {"type": "diffuse"}}},
        blocker={"type": "rectangle", "to_world": T().translate([1.6, -1.0, 0])
                 .rotate([1, 0, 0], 90).scale(0.4)},
        far={"type": "sphere", "center": [60, 0, 0], "radius": 0.1})


@pytest.mark.parametrize("make", [_glass_pane_from_above, _two_sided_ceiling_from_below],
                         ids=["transmitting", "two_sided_back"])
def test_mark_pass_skips_no_region_a_lookup_reads(make, monkeypatch):
    """The regions the mark pass skips are never read: the image equals the one where
    every region marks every point (``MARK_SLACK`` beyond any horizon) -- for a surface
    that transmits light (lit through from below: both sides' horizons count) and for
    the back of a two-sided surface (the normal facing the camera). Skipping the first
    lit the pane under the blocker from the coarsest page (mean 0.561 against 0.540)."""
    from mi_shadowmap import virtual
    scene = make()
    virtual.PAGE_CACHE.clear()
    img, _ = _virtual_render(scene, 4, method="hard")
    monkeypatch.setattr(env, "MARK_SLACK", 10.0)
    virtual.PAGE_CACHE.clear()
    every, _ = _virtual_render(scene, 4, method="hard")
    virtual.PAGE_CACHE.clear()
    full, _ = _virtual_render(scene, 4, method="hard", virtual=False)
    ref, _ = _virtual_render(scene, 16, method="raytraced", shadow_rays=16)
    err = {name: abs(a[..., :3].mean() / ref[..., :3].mean() - 1.0)
           for name, a in (("virtual", img), ("full maps", full))}
    print("mean: virtual", img[..., :3].mean(), "every region marked", every[..., :3].mean(),
          "relative error of the mean against raytraced:", err)
    assert np.abs(img - every).max() < 1e-5
    assert err["virtual"] < err["full maps"] + 0.01


def test_a_budget_below_the_regions_coarsest_pages_gets_full_maps():
    """``memory_budget`` too small for the K regions' coarsest pages: the automatic
    ``virtual`` gives the environment full maps (which the budget sizes), an explicit
    ``virtual=true`` is an error naming the property and what it needs."""
    from mi_shadowmap.depth_maps import ShadowMap
    scene = _scene(size=16)
    img, integ = _virtual_render(scene, 1, method="hard", memory_budget=0.05)
    assert np.isfinite(img).all() and isinstance(integ.maps[0], ShadowMap)
    from conftest import root_message
    with pytest.raises(Exception) as e:
        _virtual_render(scene, 1, method="hard", memory_budget=0.05, virtual=True)
    assert re.search(r"memory_budget.*0\.05 MiB.*'sky'.*16 faces", root_message(e.value))


def test_the_aov_under_a_black_sky_with_a_sun_is_one_where_nothing_occludes(tmp_path):
    """Each region's visibility counted a sampled dark direction (a black texel of the
    sun's region, drawn by the uniform share) as shadowed, with the region's whole energy
    share: an open ground under a black sky with a 2 x 2-texel sun read 0.90 for every
    map method (0.86 with one region, 0.965 with 256), where ``raytraced`` reads 1. Now
    each direction weighs its luminance over its pdf: 1.0000. With one region
    (``env_lights=1``) every camera sample whose one direction was dark fell back to the
    regions' shares with a visibility of 0 (the lookup ran only on bright directions):
    0.86; the lookup now runs wherever the direction is above the horizon: 1.0000."""
    img = np.zeros((64, 128, 3), np.float32)
    img[20:22, 90:92] = [1000.0, 900.0, 800.0]
    path = tmp_path / "sun.exr"
    mi.Bitmap(img).write(str(path))
    T = mi.ScalarTransform4f
    scene = mi.load_dict({
        "type": "scene",
        "sensor": {"type": "perspective", "fov": 40,
                   "to_world": T().look_at(origin=[0.2, 3.5, 4.9], target=[0.25, 0.25, 0],
                                           up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": 32, "height": 32}},
        "ground": {"type": "rectangle", "to_world": T().scale(4).rotate([1, 0, 0], -90)},
        "sky": {"type": "envmap", "filename": str(path)}})
    for props in ({"method": "raytraced"}, {"method": "hard"}, {"method": "pcf"},
                  {"method": "hard", "virtual": False, "resolution": 128},
                  {"method": "hard", "env_lights": 1}, {"method": "pcf", "env_lights": 1},
                  {"method": "multiview", "env_lights": 1}):
        img = np.asarray(mi.render(scene, integrator=mi.load_dict(
            {"type": "shadowmap", **props}), spp=16, seed=5))
        ground = img[20:, :, 3]
        print(props, f"ground AOV {ground.mean():.4f}")
        assert ground.mean() >= 0.99, props


@pytest.mark.parametrize("virtual", [True, False])
def test_a_sky_that_emits_nothing_has_visibility_zero_as_raytraced(virtual):
    """An environment of zero radiance lights nothing: its visibility AOV is 0, as
    ``raytraced``'s and the converged reference's are (and a delta light's of zero
    intensity). Map methods gave the geometric visibility (shares by solid angle):
    84 % of the pixels "false lit" against the reference."""
    from mi_shadowmap import harness
    scene = mi.load_dict({
        "type": "scene",
        "sensor": {"type": "perspective", "fov": 40,
                   "to_world": mi.ScalarTransform4f().look_at([0, 4, 4], [0, 0, 0], [0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": 16, "height": 16}},
        "ground": {"type": "rectangle",
                   "to_world": mi.ScalarTransform4f().rotate([1, 0, 0], -90).scale(3)},
        "sky": {"type": "constant", "radiance": 0.0}})
    res = harness.compare(scene, methods=[{"method": "hard", "virtual": virtual},
                                          "raytraced"], spp=1, repeats=1)
    for r in res:
        assert np.all(r.vis_stack() == 0.0), r.name
        assert r.metrics["vis_misclassified"] == 0.0


def test_gradient_wrt_a_sky_radiance_of_zero():
    """The image is linear in the sky's radiance, so its derivative wrt it is the same at
    0 as at 1. With environment='shadowed' it was not: the region term was gated by its
    contribution being > 0 (cut to 0 at radiance 0: only the visible sky's pixels kept a
    derivative), and an all-zero sky was cut at the regions' texel-count middle instead of
    by solid angle as a uniform sky is (other regions, other shadows): hard gave 371
    against 1004 at radiance 1 (raytraced 1013 at both) on a 24^2 scene (an envmap's
    scale of 0 likewise: 158.5 against 445.0 here). Reverse and forward mode; the
    visibility AOV of the zero sky stays 0."""
    T = mi.ScalarTransform4f

    def scene():
        return mi.load_dict({
            "type": "scene", "integrator": {"type": "shadowmap", "method": "hard"},
            "sensor": {"type": "perspective", "fov": 45,
                       "to_world": T().look_at([0, 3, 3], [0, 0, 0], [0, 1, 0]),
                       "film": {"type": "hdrfilm", "width": 16, "height": 16}},
            "floor": {"type": "rectangle", "to_world": T().rotate([1, 0, 0], -90).scale(2)},
            "box": {"type": "cube", "to_world": T().translate([0, 0.5, 0]).scale(0.3)},
            "sky": {"type": "constant", "radiance": {"type": "rgb", "value": 0.0}}})

    key = "sky.radiance.value"
    grads = []
    for value in (0.0, 1.0):
        sc = scene()
        params = mi.traverse(sc)
        params[key] = mi.Color3f(value)
        dr.enable_grad(params[key])
        params.update()
        image = mi.render(sc, params, seed=0, spp=2)
        if value == 0.0:
            assert np.all(np.asarray(image)[..., -1] == 0)   # vis_sky: lit by nothing
        dr.backward(dr.sum(image[:, :, :3], axis=None))
        reverse = float(np.sum(np.asarray(dr.grad(params[key]))))
        dr.set_grad(params[key], mi.Color3f(1.0))
        image = mi.render(sc, params, seed=0, spp=2)
        dr.forward_to(image)
        grads.append((reverse, np.asarray(dr.grad(image))[..., :3]))
    (r0, f0), (r1, f1) = grads
    assert r1 > 1.0
    assert r0 == pytest.approx(r1, rel=1e-4)
    np.testing.assert_allclose(f0, f1, rtol=1e-4, atol=1e-6)


def _framed_sky_scene(to_world):
    sky = np.full((16, 32, 3), 0.1, np.float32)
    sky[3:5, 10:12] = 200.0
    T = mi.ScalarTransform4f
    return mi.load_dict({
        "type": "scene",
        "sensor": {"type": "perspective", "fov": 45,
                   "to_world": T().look_at([0, 5, 5], [0, 0, 0], [0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": 16, "height": 16,
                            "rfilter": {"type": "box"}}},
        "ground": {"type": "rectangle", "to_world": T().rotate([1, 0, 0], -90).scale(3)},
        "box": {"type": "cube", "to_world": T().translate([0, 0.6, 0]).scale(0.4)},
        "sky": {"type": "envmap", "bitmap": mi.Bitmap(sky), "to_world": to_world}})


def test_a_scaled_environment_frame_is_refused_and_a_mirrored_one_renders():
    """An envmap whose ``to_world`` scales: Mitsuba reads the texel of the inverse-
    transformed direction as if it were a unit vector, so the regions' samples read
    other texels (scaled by 2 and turned: every map method 97 % darker than ``direct``,
    ``raytraced`` equal to it). Refused naming ``to_world``; a mirror (an orthogonal
    frame) renders as ``raytraced`` does."""
    T = mi.ScalarTransform4f
    scene = _framed_sky_scene(T().rotate([0, 1, 0], 50).scale(2.0))
    with pytest.raises(ValueError, match="to_world is not a rotation"):
        mi.load_dict({"type": "shadowmap"}).check_scene(scene)
    # ray tracing and an unshadowed environment do not use the regions
    for props in ({"method": "raytraced"}, {"environment": "unshadowed"}):
        assert np.isfinite(_render(scene, {"type": "shadowmap", **props}, 1)).all()
    scene = _framed_sky_scene(T().rotate([0, 1, 0], 50).scale([1, 1, -1]))
    rt = _render(scene, {"type": "shadowmap", "method": "raytraced"}, 256)
    hard = _render(scene, {"type": "shadowmap"}, 64)
    assert abs(hard[..., :3].mean() / rt[..., :3].mean() - 1.0) < 0.03


@pytest.mark.parametrize("sensor", [
    {"type": "perspective", "fov": 0.5, "film": {"type": "hdrfilm", "width": 8, "height": 8},
     "to_world": mi.ScalarTransform4f().look_at([2, 2, 2], [2, 0, 2.001], [0, 1, 0])},
    {"type": "radiancemeter", "origin": [2, 2, 2], "direction": [0, -1, 0],
     "film": {"type": "hdrfilm", "width": 1, "height": 1, "rfilter": {"type": "box"}}}],
    ids=["zoomed", "radiancemeter"])
def test_pcss_on_virtual_region_maps_reads_only_built_texels(sensor):
    """``pcss``'s mark margin asked the whole environment view for its light width: 0
    (a directional light's without ``angular_diameter``), so the pages got ``hard``'s
    margin of 2 texels while each region's lookup, with the region's angular diameter,
    searched and filtered up to ``max_kernel`` / 2 = 32 texels around the point, beyond
    the 2 x 2 pages it binds: where no neighbouring point had built them (a zoomed view, a
    radiancemeter) those taps read the coarsest level, whose wide texels stood in front
    of the receiver plane. An open ground under a uniform sky, far from the ball: virtual
    pcss 0.34 (zoomed, 0.5 degrees) and 0.26 (radiancemeter) where ``hard`` reads 0.44
    (full-map pcss 0.49, raytraced 0.49). Now the marks build the kernels' reach and
    the kernels stay in the bound pages: 0.44 for both."""
    T = mi.ScalarTransform4f
    scene = mi.load_dict({
        "type": "scene", "sensor": sensor,
        "ground": {"type": "rectangle", "to_world": T().rotate([1, 0, 0], -90).scale(4)},
        "ball": {"type": "sphere", "center": [-0.6, 0.6, -0.3], "radius": 0.6},
        "sky": {"type": "constant", "radiance": 1.0}})
    vis = {}
    for method in ("hard", "pcss"):
        img = np.asarray(mi.render(scene, integrator=mi.load_dict(
            {"type": "shadowmap", "method": method}), spp=64, seed=0))
        vis[method] = float(img[..., 3].mean())
    print(vis)
    # nothing occludes the ground there: pcss finds no blocker, as hard finds none
    assert vis["pcss"] >= vis["hard"] - 0.01


def test_multiview_does_not_darken_an_open_floor_under_a_sky():
    """``multiview`` under an environment looks each region up as one view, and its
    horizon test took the region's axis for the light point: a region straddling the
    floor's horizon, with its axis below it, counted every direction drawn from it above
    the horizon as shadowed. On a floor with nothing above it (16 regions of a 0.3 sky
    with a 60x sun) the image was 4.1 % darker than ``direct``'s and ``hard``'s (1.2226
    against 1.2742 / 1.2756 at 24^2, 16 spp), the AOV 0.799 against hard's 0.856."""
    T = mi.ScalarTransform4f
    sky = np.full((16, 32, 3), 0.3, np.float32)
    sky[3:5, 8:11] = 60.0
    scene = mi.load_dict({
        "type": "scene",
        "sensor": {"type": "perspective", "fov": 40,
                   "to_world": T().look_at([0, 4, 4], [0, 0, 0], [0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": 16, "height": 16,
                            "rfilter": {"type": "box"}}},
        "ground": {"type": "rectangle", "to_world": T().rotate([1, 0, 0], -90).scale(10)},
        "sky": {"type": "envmap", "bitmap": mi.Bitmap(sky)}})
    n = 1 if mi.is_monochromatic else 3
    hard = _render(scene, {"type": "shadowmap", "method": "hard"}, 16)
    mv = _render(scene, {"type": "shadowmap", "method": "multiview"}, 16)
    ratio = mv[..., :n].mean() / hard[..., :n].mean()
    print(f"multiview / hard image mean {ratio:.4f}, AOV {mv[..., -1].mean():.4f} / "
          f"{hard[..., -1].mean():.4f}")
    assert abs(ratio - 1) < 0.01
    assert abs(mv[..., -1].mean() - hard[..., -1].mean()) < 0.01


@pytest.mark.parametrize("props", [{"method": "hard"}, {"method": "pcss"},
                                   {"method": "hard", "virtual": False, "resolution": 64},
                                   {"method": "multiview", "resolution": 64}],
                         ids=lambda p: "-".join(f"{v}" for v in p.values()))
def test_a_rotated_environment_compiles_no_kernel(props):
    """An environment turned through ``params.update()`` (a sky's time of day) rebuilds
    its regions' maps with the kernels it had. Its rotation (the shading's region
    sampling) and the regions' refitted half sizes (projection, page casts) were kernel
    literals: each new angle compiled 1 kernel with full maps and multiview (about 300 /
    220 ms a frame against 20 ms for raytraced) and 3 with virtual maps (hard, pcss: 540-
    800 ms). Angles are random, so Dr.Jit's disk cache cannot hold an earlier run's;
    full maps at a given resolution (an automatic one may change with the regions' fit,
    and a resolution is a kernel literal by design)."""
    import random
    rng = random.Random()
    T = mi.ScalarTransform4f
    scene = _framed_sky_scene(T().rotate([0, 1, 0], 20.0))
    params = mi.traverse(scene)
    integ = {"type": "shadowmap", **props}
    had = dr.flag(dr.JitFlag.KernelHistory)
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        for step in range(3):
            if step:
                params["sky.to_world"] = T().rotate([0, 1, 0], 20.0 + rng.uniform(1, 30))
                params.update()
            dr.kernel_history()
            img = _render(scene, integ, 2, seed=step)
            compiled = [k for k in dr.kernel_history()
                        if k["type"] == dr.KernelType.JIT and not k.get("cache_hit", 1)]
        assert np.isfinite(img).all()
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, had)
    assert not compiled, [(k["size"], k["operation_count"]) for k in compiled]


@pytest.mark.parametrize("props", [{"method": "hard"}, {"method": "pcss"},
                                   {"method": "hard", "virtual": False, "resolution": 64}],
                         ids=lambda p: "-".join(f"{v}" for v in p.values()))
def test_an_environment_scaled_keeps_its_maps(props):
    """An envmap's ``scale`` (its intensity) changed through ``params.update()`` rebuilt
    every map, as a moved light does (hard: 671 pages, 337k texels a frame, 0.09 s
    against 0.02 s; pcss 1003 pages, 0.27 s; multiview 1.6M texels), while a point,
    spot, area or directional light's intensity rebuilds nothing: the scale is the
    emitter's own parameter, so it was part of the scene state and of the regions' key.
    The cut is of relative luminance, so only whether the scale is > 0 counts; every
    frame renders as a fresh scene at its scale does (the AOV of a zero sky included)."""
    T = mi.ScalarTransform4f
    scene = _framed_sky_scene(T().rotate([0, 1, 0], 20.0))
    params = mi.traverse(scene)
    integ = mi.load_dict({"type": "shadowmap", **props})
    np.asarray(mi.render(scene, integrator=integ, spp=2))
    for scale in (3.0, 0.37, 0.0, 1.0):
        params["sky.scale"] = scale
        params.update()
        img = np.asarray(mi.render(scene, integrator=integ, spp=2))
        if scale not in (0.0, 1.0):      # a zero sky, and back: the cut is redone
            assert integ.stats["maps_built"] == 0 and integ.stats["texels_built"] == 0
        fresh = _framed_sky_scene(T().rotate([0, 1, 0], 20.0))
        p2 = mi.traverse(fresh)
        p2["sky.scale"] = scale
        p2.update()
        want = np.asarray(mi.render(fresh, integrator=mi.load_dict(
            {"type": "shadowmap", **props}), spp=2))
        assert np.allclose(img, want, rtol=1e-5, atol=1e-7), scale


def test_clear_caches_empties_the_cuts():
    """``clear_caches()`` says it empties every cache the package keeps: the median cuts
    too (they stayed, up to 64 of them)."""
    from mi_shadowmap import clear_caches
    emitter = mi.load_dict({"type": "constant"})
    env.emitter_regions(emitter, 4)
    assert env._CACHE
    clear_caches()
    assert not env._CACHE


@pytest.mark.parametrize("method", ["hard", "pcss"])
def test_a_camera_move_marks_every_region_in_one_pass(method):
    """A camera move under a 16-region sky marks the regions in one pass: a few kernels
    (the mark pass launched 3 a region: 57 kernels a frame, with about 270 (hard) to 940
    (pcss) table memsets; a moved 128^2 pcss frame took 0.31-0.33 s of CPU, now
    0.18-0.19 s), none compiled, and the same marks as every region marked
    from its own view (:meth:`EnvironmentView.mark_views`, each candidate tile of
    :func:`~mi_shadowmap.virtual.marks.mark_candidates`)."""
    from mi_shadowmap import virtual
    from mi_shadowmap.virtual import marks
    virtual.PAGE_CACHE.clear()
    scene = _scene(size=32)
    params = mi.traverse(scene)
    key = "camera.to_world"
    T0 = mi.Transform4f(params[key])
    integ = mi.load_dict({"type": "shadowmap", "method": method})
    mi.render(scene, integrator=integ, spp=1)
    had = dr.flag(dr.JitFlag.KernelHistory)
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        for step in range(1, 4):
            params[key] = mi.Transform4f().translate([0.02 * step, 0.01 * step, 0.0]) @ T0
            params.update()
            dr.kernel_history()
            img = np.asarray(mi.render(scene, integrator=integ, spp=1, seed=step))
            hist = dr.kernel_history()
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, had)
    jit = [k for k in hist if k["type"] == dr.KernelType.JIT]
    assert np.isfinite(img).all()
    assert not [k for k in jit if not k.get("cache_hit", 1)]
    assert len(jit) <= 20, len(jit)
    # the marks of the last frame, against each region's own candidates
    vmap = integ.maps[0]
    store, view = vmap.store, vmap.layout.view
    assert view.n_views == 16
    from mi_shadowmap.methods import virtual_margin_of
    margin = virtual_margin_of(integ.opts.record, integ.opts, view)
    hits = marks.camera_hits(scene, scene.sensors()[0])
    through = hits[3] & mi.has_flag(hits[0].bsdf().flags(), mi.BSDFFlags.Transmission)
    want = []
    for mark_view, active in view.mark_views():
        marker = marks.Marker(vmap.layout, vmap.lod_bias, mark_view)
        lists = [marks.mark_candidates(marker, *hits, margin=margin,
                                       active=lambda p, n, f=active: f(p, n, through))]
        if vmap.coarse_res:
            lists.append(marks.mark_coarser(marker, *hits, coarse_res=vmap.coarse_res,
                                            active=lambda p, n, f=active: f(p, n, through)))
        for j, (keys, oks) in enumerate(lists):
            got = [k.numpy()[ok.numpy()] for k, ok in zip(keys, oks)]
            got = np.concatenate(got)
            if j == 1:
                got = marks.dilate_tiles(got, vmap.layout, margin)
            want.append(got)
    want = np.unique(np.concatenate(want))
    assert len(want) > 100
    assert np.array_equal(np.unique(store.last_mark[1]), want)


def test_search_guide_brackets_every_texel_the_search_finds():
    """:func:`env.search_guide`: for every float32 ``x`` in ``[0, 1)`` (bucket
    edges, the float32 just below them, random values) the first texel of its region whose
    cdf exceeds ``x`` lies in its bucket's ``[lo, lo + n]``, so the shading's search of
    those texels finds the texel a search of the whole region finds (renders bit-identical
    with it on four environment scenes): regions of 1 texel to 5000 (more than 2^GUIDE_BITS
    buckets), cdfs with runs of equal values and a texel holding nearly everything."""
    rng = np.random.default_rng(7)
    cdfs = []
    for n in (1, 2, 3, 17, 600, 5000):
        pmf = rng.random(n) ** 8
        pmf[rng.random(n) < 0.3] = 0.0                  # runs of equal cdf values
        pmf[rng.integers(0, n)] += 1e4 * pmf.sum() + 1.0  # one texel holds nearly all
        c = np.minimum(np.cumsum(pmf / pmf.sum()), 1.0)
        c[-1] = 1.0
        cdfs.append(c)
    count = np.array([len(c) for c in cdfs])
    offset = np.concatenate([[0], np.cumsum(count)[:-1]])
    cdf = np.concatenate(cdfs).astype(np.float32)
    guide, g0, scale = env.search_guide(cdf, offset, count)
    for k, (o, n) in enumerate(zip(offset, count)):
        G = np.float32(scale[k])
        edges = (np.arange(int(G)) / G).astype(np.float32)
        x = np.concatenate([edges, np.nextafter(edges[1:], np.float32(0)),
                            rng.random(2000).astype(np.float32),
                            cdf[o:o + n], np.nextafter(cdf[o:o + n], np.float32(0))])
        x = x[(x >= 0) & (x < 1)]
        bucket = np.minimum(x * G, G - np.float32(1)).astype(np.uint32)
        r = guide[g0[k] + bucket]
        lo = (r & np.uint64(0xFFFFFFFF)).astype(np.int64)
        hi = lo + (r >> np.uint64(32)).astype(np.int64)
        want = o + np.searchsorted(cdf[o:o + n], x, side="right")
        assert np.all((lo <= want) & (want <= hi)), k
        assert int(scale[k]) <= 2 ** env.GUIDE_BITS
    assert scale[-1] == 2 ** env.GUIDE_BITS and int((guide >> np.uint64(32)).max()) > 1


@pytest.mark.parametrize("symbolic", [True, False])
def test_guided_search_finds_the_fixed_step_searchs_texel(symbolic):
    """The shading's texel search (:func:`env.search_guide`'s bucket, then
    :func:`env._search_body` until the range is empty) returns, in the kernel, the texel
    the fixed-step search over the whole region returned (what the shading ran before),
    in symbolic and evaluated loops: regions of 0, 1 and 2 texels, an all-zero pmf (cdf 0
    up to the last texel's 1), one texel holding everything, float32 denormals in the cdf
    (Dr.Jit's kernels flush them to 0; numpy, which builds the guide, does not), and more
    texels than 2^GUIDE_BITS buckets; queries at random, at every cdf value, the float32
    on either side of it, and the buckets' edges."""
    rng = np.random.default_rng(5)
    pmfs = [np.zeros(0), np.ones(1), np.array([0.3, 0.7]), np.zeros(9),
            np.eye(1, 33, 20)[0], np.array([1e-43, 1e-40, 1e-39, 1.0, 0.0, 2.0]),
            rng.random(5000) ** 12, np.exp(rng.normal(0.0, 9.0, 700))]
    cdfs = []
    for p in pmfs:
        c = np.minimum(np.cumsum(p / p.sum() if p.sum() > 0 else p), 1.0)
        if len(c):
            c[-1] = 1.0
        cdfs.append(c)
    cdfs[5][:2] = [3.6e-43, 1.2e-40]            # denormal cdf values
    count = np.array([len(c) for c in cdfs])
    offset = np.concatenate([[0], np.cumsum(count)[:-1]])
    cdf = np.concatenate(cdfs).astype(np.float32)
    guide, g0, scale = env.search_guide(cdf, offset, count)
    ks, xs = [], []
    for k, (o, n) in enumerate(zip(offset, count)):
        G = int(scale[k])
        edges = (np.arange(G + 1) / G).astype(np.float32)
        c = cdf[o:o + n]
        x = np.concatenate([rng.random(3000).astype(np.float32), c, edges,
                            np.float32([0.0, 1e-45, 1e-41])]
                           + [np.nextafter(v, np.float32(d)) for v in (c, edges) for d in (0, 1)])
        x = x[(x >= 0) & (x < 1)].astype(np.float32)
        ks.append(np.full(len(x), k, np.uint32))
        xs.append(x)
    k, x = mi.UInt32(np.concatenate(ks)), mi.Float(np.concatenate(xs))
    cdf_d = mi.Float(cdf)
    flag = dr.flag(dr.JitFlag.SymbolicLoops)
    dr.set_flag(dr.JitFlag.SymbolicLoops, symbolic)
    try:
        # the fixed-step search the shading ran before the guide
        lo = dr.gather(mi.UInt32, mi.UInt32(offset.astype(np.uint32)), k)
        n = dr.gather(mi.UInt32, mi.UInt32(count.astype(np.uint32)), k)
        for _ in range(int(np.ceil(np.log2(count.max() + 1))) + 1):
            half = n >> 1
            mid = lo + half
            go = (n > 0) & (dr.gather(mi.Float, cdf_d, mid, n > 0) <= x)
            lo = dr.select(go, mid + 1, lo)
            n = dr.select(go, n - half - 1, half)
        # the guided search, as shade() runs it
        s = dr.gather(mi.Float, mi.Float(scale), k)
        bucket = mi.UInt32(dr.minimum(x * s, s - 1.0))
        r = dr.gather(mi.UInt64, mi.UInt64(guide),
                      dr.gather(mi.UInt32, mi.UInt32(g0), k) + bucket)
        got, _ = dr.while_loop((mi.UInt32(r), mi.UInt32(r >> 32)), env._search_cond,
                               env._search_body(cdf_d, x))
        old, new = lo.numpy(), got.numpy()
    finally:
        dr.set_flag(dr.JitFlag.SymbolicLoops, flag)
    assert len(new) > 40000 and np.array_equal(new, old)
