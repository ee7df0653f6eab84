"""Differentiable shadow maps, the foundations (issue 13).

* Maps are built in the AD graph when a shape/emitter parameter has gradients
  enabled, and the map cache is then bypassed; without gradients the cache
  works as before (``maps_reused``).
* ``vsm`` and ``pcf`` with ``soft_compare`` pass gradients from an occluder's
  geometry to the shadow it casts on a receiver, and they agree with central
  finite differences of the same method's own output.

The scene: a directional light at an angle, a thin slab and a box above a
ground plane, and a tall thin post at a corner that fixes the scene's bounds
(the orthographic map is fitted to them, so moving the occluders inside the
bounds leaves the light view unchanged). The parameters move the occluders'
corners *along the light direction*: their outlines in the map stay where
they are, so the maps change only through their depths -- exactly what
depth gradients capture. (Moving an outline across texels changes the map
discontinuously; capturing that needs antialiased maps, a later step of
issue 13.) The loss reads only ground pixels a few pixels away from the
occluders on screen (their own silhouettes and shading are not shadows).
"""
import time

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from mi_shadowmap.metrics import dilate
from mi_shadowmap.scenes import camera

from mi_shadowmap.map_manager import MAP_CACHE, maps_need_gradients

T = mi.ScalarTransform4f


@pytest.fixture(autouse=True)
def _fresh_caches_per_test():
    """Each test here builds its own scenes: freed after it (``clear_caches``), the
    next test's kernels do not depend on them (with an empty kernel cache this file
    took 1265 s; with this and the Adam tests' maps at 128^2, 653 s)."""
    yield
    import mi_shadowmap
    mi_shadowmap.clear_caches()


RES = 32             # film
MAP = 128            # map resolution
SPP = 4
LIGHT = np.array([1.0, -1.2, 0.3])
LIGHT = LIGHT / np.linalg.norm(LIGHT)
# pcf: w = soft_compare x texel width (~0.07 here) = 1.7 > the occluders' distances
# to the ground along the light (0.8 and 1.4), so their shadows carry depth gradients
METHODS = {"vsm": {"method": "vsm", "filter_size": 4.0},
           "pcf": {"method": "pcf", "soft_compare": 24.0}}


def _diffuse(v):
    return {"type": "diffuse", "reflectance": {"type": "rgb", "value": v}}


def scene_dict():
    return {
        "type": "scene",
        "sensor": camera([0.0, 5.5, 3.0], [0.0, 0.0, 0.0], RES, RES, SPP),
        "ground": {"type": "rectangle", "to_world": T().rotate([1, 0, 0], -90).scale(4),
                   "bsdf": _diffuse(0.7)},
        # a thin slab 0.6 above the ground (its top is what the map stores)
        "slab": {"type": "cube", "to_world": T().translate([-1.0, 0.6, 0.3]).scale([0.35, 0.02, 0.35]),
                 "bsdf": _diffuse(0.5)},
        "box": {"type": "cube", "to_world": T().translate([0.3, 0.8, -0.6]).scale(0.25),
                "bsdf": _diffuse(0.55)},
        # fixes the scene's bounds (and so the directional map's frame)
        "post": {"type": "cube", "to_world": T().translate([3.8, 1.5, 3.8]).scale([0.05, 1.5, 0.05]),
                 "bsdf": _diffuse(0.6)},
        "sun": {"type": "directional", "direction": LIGHT.tolist(),
                "irradiance": {"type": "rgb", "value": 3.0}},
    }


def receiver_mask(scene, margin=2):
    """Ground pixels at least ``margin`` pixels from anything else on screen."""
    integ = mi.load_dict({"type": "aov", "aovs": "p:position"})
    img = np.asarray(mi.render(scene, integrator=integ, spp=SPP, seed=0))
    ground = np.abs(img[..., 1]) < 1e-4
    return ~dilate(~ground, margin)


class Corners:
    """Offsets along the light of each distinct corner of the named meshes: one
    parameter per corner (Mitsuba's cube has 24 vertices, 3 per corner)."""

    def __init__(self, scene, names):
        self.params = mi.traverse(scene)
        self.keys = [f"{n}.vertex_positions" for n in names]
        self.base, self.group, n = {}, {}, 0
        for k in self.keys:
            v = np.array(self.params[k]).reshape(-1, 3)
            _, inv = np.unique(np.round(v, 5), axis=0, return_inverse=True)
            self.base[k] = v.copy()
            self.group[k] = inv.ravel() + n
            n += int(inv.max()) + 1
        self.n = n

    def set(self, theta):
        """Move the corners by ``theta`` (numpy or an attached ``mi.Float``)."""
        if not isinstance(theta, mi.Float):
            theta = mi.Float(np.asarray(theta, dtype=np.float32))
        for k in self.keys:
            off = dr.gather(mi.Float, theta, mi.UInt32(self.group[k]))
            v = mi.Point3f(*[mi.Float(self.base[k][:, i]) + off * float(LIGHT[i])
                             for i in range(3)])
            self.params[k] = dr.ravel(v)
        self.params.update()


def masked_loss(img, mask):
    """Sum of the colour channels (not the visibility AOV) over ``mask``."""
    c = img.shape[-1]
    w = np.zeros(mask.shape + (c,), np.float32)
    w[..., :3] = mask[..., None]
    return dr.sum(img.array * mi.Float(w.ravel()))


def ad_gradient(scene, integ, corners, mask, theta0, seed=1):
    theta = mi.Float(np.asarray(theta0, dtype=np.float32))
    dr.enable_grad(theta)
    corners.set(theta)
    img = mi.render(scene, corners.params, integrator=integ, spp=SPP, seed=seed)
    loss = masked_loss(img, mask)
    dr.backward(loss)
    g = dr.grad(theta).numpy()
    corners.set(np.asarray(theta0))   # detached again
    return g, float(loss[0])


def loss_at(scene, integ, corners, mask, theta, seed=1):
    corners.set(theta)
    img = mi.render(scene, integrator=integ, spp=SPP, seed=seed)
    return float(masked_loss(img, mask)[0])


def fd_gradient(scene, integ, corners, mask, theta0, h, directions):
    out = []
    for u in directions:
        lp = loss_at(scene, integ, corners, mask, theta0 + h * u)
        lm = loss_at(scene, integ, corners, mask, theta0 - h * u)
        out.append((lp - lm) / (2 * h))
    corners.set(theta0)
    return np.array(out)


def make(method):
    scene = mi.load_dict(scene_dict())
    integ = mi.load_dict({"type": "shadowmap", "resolution": MAP, **METHODS[method]})
    return scene, integ


@pytest.mark.parametrize("method", sorted(METHODS))
def test_gradient_matches_finite_differences(method):
    """Corner offsets along the light (a 16-vector): the AD gradient of a loss on
    receiver pixels is nonzero and matches central differences (cosine >= 0.95);
    the translation of both occluders along the light (a scalar) within 10 %.
    Measured: vsm cosine 0.998, translation 0.5 %; pcf 0.996, 3.5 %."""
    MAP_CACHE.clear()
    scene, integ = make(method)
    mask = receiver_mask(scene)
    corners = Corners(scene, ["slab", "box"])
    theta0 = np.zeros(corners.n)
    t0 = time.perf_counter()
    g, _ = ad_gradient(scene, integ, corners, mask, theta0)
    t_ad = time.perf_counter() - t0
    assert np.abs(g).max() > 0, "no gradient reached the occluders"
    fd = fd_gradient(scene, integ, corners, mask, theta0, 0.02, np.eye(corners.n))
    cos = float(g @ fd / (np.linalg.norm(g) * np.linalg.norm(fd) + 1e-30))
    g_t = float(g.sum())   # translation along the light: every corner at once
    fd_t = float(fd_gradient(scene, integ, corners, mask, theta0, 0.02,
                             [np.ones(corners.n)])[0])
    rel = abs(g_t - fd_t) / max(abs(fd_t), 1e-30)
    print(f"{method}: AD {t_ad:.2f} s; cosine {cos:.4f}; translation AD {g_t:.4g} "
          f"FD {fd_t:.4g} (rel. error {rel:.3f}); |g| {np.linalg.norm(g):.4g}")
    assert cos >= 0.95
    assert rel <= 0.10


def test_no_gradients_uses_the_cache():
    MAP_CACHE.clear()
    scene, integ = make("vsm")
    assert not maps_need_gradients(scene)
    mi.render(scene, integrator=integ, spp=SPP, seed=1)
    assert integ.stats["maps_built"] == 1 and integ.stats["maps_reused"] == 0
    mi.render(scene, integrator=integ, spp=SPP, seed=2)
    assert integ.stats["maps_built"] == 0 and integ.stats["maps_reused"] == 1
    assert not dr.grad_enabled(integ.maps[0].depth)
    # a reflectance gradient does not move a map: still cached
    params = mi.traverse(scene)
    dr.enable_grad(params["ground.bsdf.reflectance.value"])
    assert not maps_need_gradients(scene)


def test_gradients_bypass_the_cache():
    """With a vertex gradient enabled the maps are built in the AD graph even when the
    cache holds the same scene state, and nothing detached is handed back."""
    MAP_CACHE.clear()
    scene, integ = make("vsm")
    mi.render(scene, integrator=integ, spp=SPP, seed=1)   # caches a detached map
    corners = Corners(scene, ["slab"])
    theta = mi.Float(np.zeros(corners.n, dtype=np.float32))
    dr.enable_grad(theta)
    corners.set(theta)                      # same values, now attached
    assert maps_need_gradients(scene)
    with dr.suspend_grad():                 # mi.render's primal pass: detached, cached
        assert not maps_need_gradients(scene)
    n_cached = MAP_CACHE.hits
    integ.render(scene, seed=1, spp=SPP)    # the pass dr.forward/backward re-runs
    assert integ.stats["maps_built"] == 1 and integ.stats["maps_reused"] == 0
    assert MAP_CACHE.hits == n_cached, "the cache was read with gradients enabled"
    assert dr.grad_enabled(integ.maps[0].depth)
    assert all(dr.grad_enabled(x) for x in integ.maps[0].extra.values())
    # forward mode reaches the image too
    img = mi.render(scene, corners.params, integrator=integ, spp=SPP, seed=1)
    dr.forward(theta)
    assert np.abs(np.asarray(dr.grad(img))).max() > 0


def test_adam_recovers_the_translation_along_the_light():
    """The box starts 0.3 units along the light from its true place (its outline in
    the map is the same: only the depths differ) and ``mi.ad.Adam`` on the receiver
    pixels' squared error against the target image (vsm, 32^2) brings it back to
    within 0.03 units, held over the last 10 of at most 100 steps. The primal renders
    use the target's seed: the depth-only signal (the loss is 0.009 at 0.3 units)
    is far below the 4-spp noise between two seeds (~0.5), so fresh seeds per step
    would drown it; Mitsuba's gradient pass still uses its own seed."""
    MAP_CACHE.clear()
    scene, integ = make("vsm")
    mask = receiver_mask(scene)
    corners = Corners(scene, ["box"])
    target = mi.TensorXf(mi.render(scene, integrator=integ, spp=SPP, seed=0))
    w = np.zeros(mask.shape + (target.shape[-1],), np.float32)
    w[..., :3] = mask[..., None]
    w = mi.Float(w.ravel())
    opt = mi.ad.Adam(lr=0.02)
    opt["t"] = mi.Float(0.3)
    history = []
    t0 = time.perf_counter()
    for it in range(100):
        corners.set(dr.gather(mi.Float, opt["t"], mi.UInt32(np.zeros(corners.n, np.uint32))))
        img = mi.render(scene, corners.params, integrator=integ, spp=SPP, seed=0)
        loss = dr.sum(dr.square(img.array - target.array) * w)
        dr.backward(loss)
        opt.step()
        history.append(float(opt["t"].numpy()[0]))
    dt = time.perf_counter() - t0
    print(f"Adam: t {history[0]:.4f} -> {history[-1]:.4f} in {len(history)} steps, "
          f"{dt:.1f} s; last 10: {np.round(history[-10:], 4)}")
    assert max(abs(t) for t in history[-10:]) <= 0.03


# ------------------------------------------ silhouettes and the light's pose (antialiased maps)
from mi_shadowmap import inverse   # noqa: E402

SOFT = {"vsm": {"method": "vsm", "filter_size": 4.0},
        "pcf": {"method": "pcf", "soft_compare": 8.0},
        "bilinear": {"method": "bilinear", "kernel": 4, "soft_compare": 2.0},
        "pcss": {"method": "pcss", "soft_compare": 2.0}}
IMAGE, SPP_AD, MAP_AA = 64, 8, 256
SEEDS = (1, 2, 3, 4)


def _integ(method, **kw):
    return mi.load_dict({"type": "shadowmap", "resolution": MAP_AA, **SOFT[method], **kw})


def _weights(mask, channels, channel=None):
    """Mean over ``mask`` of the colour channels (or of one ``channel``)."""
    w = np.zeros(mask.shape + (channels,), np.float32)
    if channel is None:
        w[..., :3] = mask[..., None] / (3.0 * mask.sum())
    else:
        w[..., channel] = mask / mask.sum()
    return mi.Float(w.ravel())


def _ad(param, integ, w, n, seed=1, spp=SPP_AD):
    x = mi.Float(np.zeros(n, np.float32))
    dr.enable_grad(x)
    param.set(x)
    img = mi.render(param.scene, param.params, integrator=integ, spp=spp, seed=seed)
    dr.backward(dr.sum(img.array * w))
    g = dr.grad(x).numpy()
    param.reset()
    return g


def _fd(param, integ, w, n, h, seed=1, spp=SPP_AD):
    out = []
    for k in range(n):
        e = np.zeros(n)
        e[k] = h
        vals = []
        for x in (e, -e):
            param.set(x)
            img = mi.render(param.scene, integrator=integ, spp=spp, seed=seed)
            vals.append(float(dr.sum(img.array * w)[0]))
        out.append((vals[0] - vals[1]) / (2 * h))
    param.reset()
    return np.array(out)


def _cos(a, b):
    return float(a @ b / (np.linalg.norm(a) * np.linalg.norm(b) + 1e-30))


@pytest.mark.parametrize("method", sorted(SOFT))
def test_sideways_gradient_matches_ray_tracing(method):
    """The occluder moves across the area light's rays (x and z): its outline crosses
    texels, which only antialiased maps differentiate. The AD gradient of the mean
    receiver colour matches central differences of ray-traced renders (cosine >= 0.95,
    each component within 30 %) and of the method's own antialiased output; without
    antialiasing it is at least 10x too small (measured: vsm about 600x, pcss 23x, pcf and
    bilinear 0). Measured: vsm cosine 0.996 against ray tracing, pcf 0.996, both 1 %
    shorter."""
    scene = inverse.occluder_scene("area", IMAGE, SPP_AD)
    mask = inverse.receiver_mask(scene)
    param = inverse.translate_shape(scene, axes="xz")
    w = _weights(mask, 4)
    g = _ad(param, _integ(method), w, 2)
    ref = _fd(param, mi.load_dict({"type": "shadowmap", "method": "raytraced"}), w, 2,
              0.03, spp=256)
    own = _fd(param, _integ(method, antialias="always"), w, 2, 0.01)
    plain = _ad(param, _integ(method, antialias="never"), w, 2)
    print(f"{method}: AD {g}, ray-traced FD {ref}, own FD {own}, not antialiased {plain}")
    assert _cos(g, ref) >= 0.95 and _cos(g, own) >= 0.95
    assert abs(np.linalg.norm(g) / np.linalg.norm(ref) - 1.0) <= 0.2
    assert np.linalg.norm(plain) < 0.1 * np.linalg.norm(ref)


def _along_the_light(scene):
    """The occluder's vertices moved by ``x[0]`` along the area light's ray through each
    (away from the light's centre): the outline in the light's map stays put, only its
    depths change, and the true shadow's penumbra narrows a little."""
    base = np.array(mi.traverse(scene)["occluder.vertex_positions"]).reshape(-1, 3)
    dirs = base - np.array(inverse.LIGHT_POSITION)[None, :]
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)

    def apply(b, x):
        v = np.array(b).reshape(-1, 3)
        return dr.ravel(mi.Point3f(*[mi.Float(v[:, c].astype(np.float32))
                                     + inverse._vec(x, 0) * mi.Float(dirs[:, c].astype(np.float32))
                                     for c in range(3)]))
    return inverse.Parameter(scene, "occluder.vertex_positions", apply, 1)


def test_along_the_light_a_narrow_soft_compare_does_not_leak():
    """Moving the occluder along the light's rays changes only its depths in the map.
    The true derivative is small and negative (ray-traced central differences in
    ``benchmarks/bench_gradients.py --param along``: -2.7e-5 against -6.0e-3 for the
    sideways motion). On an antialiased map a narrow ``soft_compare`` (2 texels) gives
    ``pcf``, whose kernel does not depend on depth, no derivative at all; a wide one
    (24 texels, wider than the occluder's height above the ground) lights the receiver
    as the occluder nears it and gets a large derivative of the wrong sign. (``pcss``'s
    penumbra follows the blocker's depth: its derivative here is checked against its
    own differences below.)"""
    scene = inverse.occluder_scene("area", IMAGE, SPP_AD)
    mask = inverse.receiver_mask(scene)
    w = _weights(mask, 4)
    side = inverse.translate_shape(scene, axes="z")
    along = _along_the_light(scene)

    def g(param, **props):
        integ = mi.load_dict({"type": "shadowmap", "resolution": 128, **props})
        return float(_ad(param, integ, w, 1)[0])

    scale = abs(g(side, method="pcf", soft_compare=2.0))
    pcf_narrow = g(along, method="pcf", soft_compare=2.0)
    pcf_wide = g(along, method="pcf", soft_compare=24.0)
    print(f"sideways |pcf| {scale:.3e}; along: pcf(2) {pcf_narrow:.3e}, pcf(24) {pcf_wide:.3e}")
    assert scale > 1e-3
    assert abs(pcf_narrow) < 1e-5 * scale
    assert pcf_wide > 1e-2 * scale


def test_pcss_along_the_light_matches_its_own_differences():
    """``pcss`` with ``soft_compare``, each of the occluder's 8 corners moved along the
    light's ray through it: the search region follows the nearest depth and the kernel
    the blocker depth, so the gradient runs through the blocker search. Its AD matches
    central differences of its own antialiased renders (cosine over the corners; the
    differences of PCSS's jittered taps are noisy, so both are summed over 16 seeds).
    ``gradient_at='sample'``: the derivative of the very renders that are differenced
    (the default pixel-centre run draws its taps per pixel, not per sample: a
    different, less noisy estimate of the same derivative).
    Measured 0.96 at 16 spp; before the blocker search weighted its taps smoothly, by
    coverage, with a fractional count dividing the depth sum, the AD had the wrong sign
    (cosine -0.56 to 0.35). Four seeds were noise-bound: seeds 1-4 / 5-8 / 9-12 / 13-16
    gave 0.917 / 0.776 / 0.980 / 0.972 (b29f57e) and 0.742 / 0.956 / 0.985 / 0.966 with
    the area light's own shape (``pcss``'s ``_light_shape``), seeds 1-16 0.987 / 0.953."""
    scene = inverse.occluder_scene("area", IMAGE, SPP_AD)
    mask = inverse.receiver_mask(scene)
    w = _weights(mask, 4)
    base = np.array(mi.traverse(scene)["occluder.vertex_positions"]).reshape(-1, 3)
    n = len(base)
    dirs = base - np.array(inverse.LIGHT_POSITION)[None, :]
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)

    def apply(b, x):
        v = np.array(b).reshape(-1, 3)
        xs = dr.gather(mi.Float, x if isinstance(x, mi.Float) else
                       mi.Float(np.asarray(x, np.float32)), mi.UInt32(np.arange(n)))
        return dr.ravel(mi.Point3f(*[mi.Float(v[:, c].astype(np.float32))
                                     + xs * mi.Float(dirs[:, c].astype(np.float32))
                                     for c in range(3)]))
    corners = inverse.Parameter(scene, "occluder.vertex_positions", apply, n)
    props = {"type": "shadowmap", "resolution": 128, "method": "pcss", "soft_compare": 2.0,
             "gradient_at": "sample"}   # the derivative of the very renders differenced
    integ, integ_aa = mi.load_dict(props), mi.load_dict({**props, "antialias": "always"})
    seeds = range(1, 17)
    g = sum(_ad(corners, integ, w, n, seed=s, spp=16) for s in seeds)
    fd = sum(_fd(corners, integ_aa, w, n, 0.05, seed=s, spp=16) for s in seeds)
    print(f"pcss along, per corner (1e-5): AD {np.round(g * 1e5 / len(seeds), 2)}, "
          f"FD {np.round(fd * 1e5 / len(seeds), 2)}, cosine {_cos(g, fd):.3f}")
    assert np.linalg.norm(g) > 0
    assert _cos(g, fd) >= 0.85


def test_along_the_light_sign_is_the_factored_visibilitys():
    """Why no shadow map gets the along-the-light motion's sign. The true derivative
    is negative (``benchmarks/bench_gradients.py --param along``, 128^2: ray-traced
    differences -2.8e-5 +- 0.5e-5, ``direct_projective`` -2.5e-5 +- 0.13e-5): as the
    occluder nears the receiver, each receiver point loses light from a different part
    of the area light, weighted by that part's cosines and distances. With the
    visibility a factor of the unshadowed light (``raytraced``,
    ``light_sample='independent'``: the shadow ray to an independent light sample;
    exact for that model) the derivative is *positive* (there +1.2e-5 +- 0.35e-5). A
    map's visibility does not depend on the light sample, so every map method
    estimates the factored quantity, and ``pcss``'s AD has its sign (there +0.6e-5 +-
    0.1e-5). Here (64^2) the ray-traced derivative is smaller (-0.6e-5 +- 0.5e-5):
    asserted are the factorization's error (factored minus true, +3.8e-5 +- 0.5e-5
    measured) and the signs of the factored derivative and of ``pcss``'s."""
    scene = inverse.occluder_scene("area", IMAGE, SPP_AD)
    mask = inverse.receiver_mask(scene)
    w = _weights(mask, 4)
    along = _along_the_light(scene)

    def fd(mode):
        integ = mi.load_dict({"type": "shadowmap", "method": "raytraced", "light_sample": mode})
        return np.array([_fd(along, integ, w, 1, 0.05, seed=s, spp=4096)[0] for s in SEEDS])

    def se(d):
        return d.std(ddof=1) / np.sqrt(len(d))

    shared, factored = fd("shared"), fd("independent")
    integ = mi.load_dict({"type": "shadowmap", "resolution": 128, "method": "pcss",
                          "soft_compare": 2.0})
    g = np.array([_ad(along, integ, w, 1, seed=s, spp=16)[0] for s in SEEDS])
    print(f"along: ray-traced {shared.mean():.2e} +- {se(shared):.1e}, factored "
          f"{factored.mean():.2e} +- {se(factored):.1e}, pcss {g.mean():.2e} +- {se(g):.1e}")
    assert factored.mean() - shared.mean() > 4 * np.hypot(se(shared), se(factored))
    assert factored.mean() > 3 * se(factored)
    assert g.mean() > 3 * se(g)


def test_point_light_position_gradient():
    """A point light's position (3 values): the gradient passes through the map's
    rays, the receivers' projections and the occluder's projected outline. Against
    central differences of the method's own antialiased output (cosine >= 0.95) and
    of ray-traced renders (cosine >= 0.9: the shading part, Mitsuba's, is the same
    in both; the shadow part is vsm's). Measured: 0.99 / 0.98."""
    scene = inverse.occluder_scene("point", IMAGE, SPP_AD)
    mask = inverse.receiver_mask(scene)
    param = inverse.light_position(scene)
    w = _weights(mask, 4)
    g = _ad(param, _integ("vsm"), w, 3)
    own = _fd(param, _integ("vsm", antialias="always"), w, 3, 0.02)
    ref = _fd(param, mi.load_dict({"type": "shadowmap", "method": "raytraced"}), w, 3,
              0.03, spp=256)
    print(f"AD {g}, own FD {own}, ray-traced FD {ref}; cosines {_cos(g, own):.4f} "
          f"{_cos(g, ref):.4f}")
    assert _cos(g, own) >= 0.95
    assert _cos(g, ref) >= 0.9


def _pose_parameter(scene, light):
    """The pose of the occluder scene's light: a point light's position (3 values);
    a directional light's rotation about z (radians); a spot or area light's
    ``to_world`` moved along x."""
    if light == "point":
        return inverse.light_position(scene)
    if light == "directional":
        def apply(base, x):   # a rotation about z by x[0] radians
            a = inverse._vec(x, 0)
            c, s = dr.cos(a), dr.sin(a)
            m = mi.Matrix4f(mi.Float(1.0) * c, -s, 0, 0, s, c, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1)
            return mi.Transform4f(m) @ mi.Transform4f(base)
    else:
        def apply(base, x):
            return mi.Transform4f().translate(mi.Vector3f(inverse._vec(x, 0), 0.0, 0.0)) \
                @ mi.Transform4f(base)
    return inverse.Parameter(scene, "light.to_world", apply, 1)


@pytest.mark.parametrize("light", ["spot", "directional", "area"])
def test_light_pose_moves_the_shadow(light):
    """Spot (``to_world`` translation), directional (``to_world`` rotation) and area
    lights (the shape's ``to_world`` translation): the gradient of the visibility AOV
    (shadows only: Mitsuba's own emitter gradients for these poses disagree with its
    finite differences by about 2x, in ``direct`` too) against central differences
    of the same method's antialiased visibility, both averaged over four seeds (the
    pixels' and the light's samples), within 25 %."""
    scene = inverse.occluder_scene(light, IMAGE, SPP_AD)
    mask = inverse.receiver_mask(scene)
    param = _pose_parameter(scene, light)
    w = _weights(mask, 4, channel=3)
    g = np.mean([_ad(param, _integ("vsm"), w, 1, seed=s)[0] for s in SEEDS])
    fd = np.mean([_fd(param, _integ("vsm", antialias="always"), w, 1, 0.01, seed=s)[0]
                  for s in SEEDS])
    print(f"{light}: AD {g:.5g}, FD {fd:.5g}")
    assert abs(fd) > 1e-4
    assert abs(g - fd) <= 0.25 * abs(fd)


@pytest.mark.parametrize("light", ["point", "spot"])
def test_optimising_a_light_pose_compiles_no_kernel_per_step(light):
    """``mi.render(scene, params)`` renders its primal image under
    ``dr.suspend_grad()``; that pass too reads the light through its reference view
    and opaque pose delta (``light_pose(..., detached=True)``), not through the
    current view, whose position would be a kernel literal: an optimisation would
    compile its map build and its render kernel at every step (measured before: 2
    kernels a step on the point, spot and directional lights). Steps 3 to 5 compile
    no render or map-build kernel, and the primal image is the plain render's at the
    same pose (up to rounding). The directional light's rotation takes the same path
    (``plan_maps``); it is left out here for time: its first steps compile 135 kernels
    (34 s in the suite), and it measured 0 a step from the third too (2 % of the pixels
    differ from the plain render by up to 0.03: its reference is the fit along the
    reference direction, turned, another texel grid)."""
    scene = inverse.occluder_scene(light, 32, 2)
    mask = inverse.receiver_mask(scene)
    target = mi.render(scene, integrator=mi.load_dict({"type": "shadowmap",
                                                       "method": "raytraced"}), spp=2)
    param = _pose_parameter(scene, light)
    x0 = np.full(param.size, 0.02)
    seen, new = set(), []

    def each(step, hist):
        kernels = {k["hash"]: (k["size"], k["operation_count"]) for k in dr.kernel_history()
                   if k["type"] == dr.KernelType.JIT}
        new.append(sorted(v for h, v in kernels.items() if h not in seen))
        seen.update(kernels)

    dr.kernel_history()   # clear
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        hist = inverse.optimize(param, _integ("vsm"), target, mask, x0, steps=5, lr=0.01,
                                spp=2, callback=each)
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    print(f"{light}: new kernels per step {[len(n) for n in new]}; "
          f"(size, operations) from step 3: {new[2:]}")
    # no render kernel (2 spp x 32^2 lanes) and no map build (faces x 256^2 texels); in
    # the full suite a step now and then compiles 2 small kernels of the loss on the
    # image (32^2 x 4 channels; 28 and 50 operations), which this does not look at
    big = [k for n in new[2:] for k in n if k[0] == 32 * 32 * 2 or k[0] % (256 * 256) == 0]
    assert not big
    # the primal pass at the last pose against a render without gradients there
    param.set(mi.Float(np.asarray(hist.x[-1], np.float32)))
    dr.enable_grad(param.params[param.key])
    primal = np.asarray(mi.render(scene, param.params, integrator=_integ("vsm"), spp=2,
                                  seed=3))
    dr.disable_grad(param.params[param.key])
    param.params.update()
    plain = np.asarray(mi.render(scene, integrator=_integ("vsm"), spp=2, seed=3))
    d = np.abs(primal[..., 3] - plain[..., 3])
    print(f"primal - plain visibility: max {d.max():.3g}, > 1e-3 on {np.mean(d > 1e-3):.2%}")
    assert np.all(np.isfinite(primal))
    assert d.max() <= 1e-4   # the same texel rays, moved: equal up to rounding


@pytest.mark.parametrize("method", sorted(SOFT))
def test_adam_recovers_an_occluder_translation(method):
    """The occluder starts 0.3 units from its place, across the light (x, z); Adam on
    the receiver pixels' squared error against a ray-traced target (256 spp) brings
    it within 0.03 units, held over the last 10 of 60 steps. Maps of 128^2 (the other
    gradient tests use 256^2; a step costs half as much, and the run converges the
    same: vsm 0.014 at 256^2, 0.0135 at 128^2). Measured (2026-12-07; worst of the
    last 10 of the first n steps, the seeds per step being the same for any n): every
    method within 0.03 from n = 43 on; at n = 60 vsm 0.0213, bilinear 0.0110, pcf
    0.0088, pcss 0.0096 (at 80, which this ran before: 0.0161, 0.0061, 0.0141, 0.0069)."""
    scene = inverse.occluder_scene("area", IMAGE, SPP_AD)
    mask = inverse.receiver_mask(scene)
    target = mi.render(scene, integrator=mi.load_dict({"type": "shadowmap",
                                                       "method": "raytraced"}),
                       spp=256, seed=7)
    param = inverse.translate_shape(scene, axes="xz")
    x0 = np.array([0.24, -0.18])   # 0.3 units away
    hist = inverse.optimize(param, _integ(method, resolution=128), target, mask, x0,
                            steps=60, lr=0.02, spp=SPP_AD)
    x, loss, sec = hist.as_arrays()
    err = np.linalg.norm(x[-10:], axis=1)
    print(f"{method}: |x| {np.linalg.norm(x0):.3f} -> {err[-1]:.4f} in {len(x)} steps, "
          f"{sec[-1]:.1f} s; worst of the last 10 {err.max():.4f}")
    assert err.max() <= 0.03


def test_adam_recovers_a_point_light_position():
    """A point light starts 0.71 units (9 % of the 8-unit scene) from its place; Adam
    against a ray-traced target brings it within 2 % of the scene's size (0.16),
    held over the last 10 of 50 steps. Without antialiased maps the same run
    drifts away (measured: 1.1 units after 100 steps). Cube faces of 128^2 (a step
    costs a third of 256^2's: 6 antialiased faces dominate it). Measured: 0.016 units
    at 256^2, 0.025 at 128^2 (80 steps). Measured 2026-12-07 (worst of the last 10 of
    the first n steps; the seeds per step are the same for any n): within 0.16 from
    n = 22 on; 0.0914 at n = 40, 0.0577 at 50, 0.0283 at 60, 0.0236 at 80."""
    scene = inverse.occluder_scene("point", IMAGE, SPP_AD)
    mask = inverse.receiver_mask(scene)
    target = mi.render(scene, integrator=mi.load_dict({"type": "shadowmap",
                                                       "method": "raytraced"}),
                       spp=256, seed=7)
    param = inverse.light_position(scene)
    x0 = np.array([0.5, 0.3, -0.4])
    hist = inverse.optimize(param, _integ("vsm", resolution=128), target, mask, x0,
                            steps=50, lr=0.03, spp=SPP_AD)
    x, loss, sec = hist.as_arrays()
    err = np.linalg.norm(x[-10:], axis=1)
    print(f"light: {np.linalg.norm(x0):.3f} -> {err[-1]:.4f} units in {len(x)} steps, "
          f"{sec[-1]:.1f} s; worst of the last 10 {err.max():.4f}")
    assert err.max() <= 0.02 * inverse.SCENE_SIZE


# ------------------------------------------------- gradient_at: the pixel-centre estimator
def test_pixel_centre_is_the_centre_rays_hit():
    """``_pixel_centre`` moves a sample's surface point to the point under its pixel's
    centre (first order, through the ray differentials): on the ground plane it lands
    within 2 % of a pixel's footprint of the centre ray's own hit."""
    scene = inverse.occluder_scene("area", 32, 1)
    sensor = scene.sensors()[0]
    integ = mi.load_dict({"type": "shadowmap", "method": "vsm"})
    integ._sensor = sensor
    integ._diff_scale = dr.opaque(mi.Float, 1.0)
    film = np.array([[3.2, 20.8], [10.9, 25.1], [20.5, 28.05], [16.01, 30.97]])
    pos = mi.Point2f(*[mi.Float(film[:, k].astype(np.float32)) for k in range(2)])
    ray, _ = sensor.sample_ray_differential(0.0, 0.5, pos / 32, mi.Point2f(0.5))
    si = scene.ray_intersect(ray)
    dp_dx, dp_dy = integ._footprint(ray, si)
    p_c, _ = integ._pixel_centre(si, dp_dx, dp_dy, si.is_valid())
    centre = mi.Point2f(*[mi.Float((np.floor(film[:, k]) + 0.5).astype(np.float32))
                          for k in range(2)])
    ray_c, _ = sensor.sample_ray(0.0, 0.5, centre / 32, mi.Point2f(0.5))
    si_c = scene.ray_intersect(ray_c)
    err = np.linalg.norm((p_c - si_c.p).numpy(), axis=0)   # (3, n) arrays
    pixel = np.linalg.norm(dp_dx.numpy(), axis=0)
    assert si.is_valid().numpy().all() and si_c.is_valid().numpy().all()
    assert (np.abs(si.p.y.numpy()) < 1e-4).all()   # on the ground
    print("error / pixel footprint:", err / pixel)
    assert (err <= 0.02 * pixel).all()


GRADIENT_SETTINGS = {"vsm": {"method": "vsm", "filter_size": 4.0, "light_bleeding": 0.0},
                     "pcf": {"method": "pcf", "soft_compare": 2.0, "sampling": "regular"},
                     "bilinear": {"method": "bilinear", "kernel": 4, "soft_compare": 2.0},
                     # its random taps are per pixel in the pixel-centre run (random
                     # per sample they cut the spread only 2x)
                     "pcss": {"method": "pcss", "soft_compare": 2.0}}


@pytest.mark.parametrize("method", sorted(GRADIENT_SETTINGS))
def test_pixel_centre_gradients_have_less_spread(method):
    """``gradient_at``: the default ``'pixel_centre'`` against ``'sample'`` (the plain
    derivative of each sample), the README's gradient settings, the occluder moved
    sideways, the ``independent`` sampler, 6 seeds: the same mean (within 4 %) and a
    spread at least 3x smaller (measured at 128^2, 16 spp: 5-12x). ``pcf``'s regular
    taps read nearest texels: their derivative sampled at the pixels' centres aliased
    against the texel grid (12 % off at 128^2) until each tap's derivative became its
    four texels' bilinear one."""
    scene = inverse.occluder_scene("area", IMAGE, SPP_AD)
    mask = inverse.receiver_mask(scene)
    param = inverse.translate_shape(scene, axes="z")
    w = _weights(mask, 4)
    props = {"type": "shadowmap", "resolution": 128, **GRADIENT_SETTINGS[method]}
    centre = [_ad(param, mi.load_dict(props), w, 1, seed=s)[0] for s in range(6)]
    plain = [_ad(param, mi.load_dict({**props, "gradient_at": "sample"}), w, 1, seed=s)[0]
             for s in range(6)]
    print(f"{method}: pixel_centre {np.mean(centre):.4e} +- {np.std(centre):.2e}; "
          f"sample {np.mean(plain):.4e} +- {np.std(plain):.2e}")
    assert abs(np.mean(centre) / np.mean(plain) - 1.0) <= 0.04
    assert np.std(centre) * 3.0 <= np.std(plain)


def test_bilinear_pixel_centre_gradient_with_a_map_finer_than_the_screen():
    """A 256^2 map face under a 64^2 image (a texel a quarter of a pixel): ``bilinear``'s
    4-texel box is narrower than the pixel, and the derivative of the box alone, taken
    at the pixels' centres, aliased against the texel grid (measured 9 % low). The
    pixel-centre run now widens the kernel by the pixel's footprint (the box convolved
    with it), so the gradient matches ray-traced differences (measured 0.7 % off) and
    keeps its small spread."""
    scene = inverse.occluder_scene("point", IMAGE, SPP_AD)
    mask = inverse.receiver_mask(scene)
    param = inverse.translate_shape(scene, axes="z")
    w = _weights(mask, 4)
    ref = np.mean([_fd(param, mi.load_dict({"type": "shadowmap", "method": "raytraced"}),
                       w, 1, 0.03, seed=s, spp=256)[0] for s in (1, 2)])
    integ = mi.load_dict({"type": "shadowmap", "method": "bilinear", "kernel": 4,
                          "soft_compare": 2.0, "resolution": 256})
    g = np.array([_ad(param, integ, w, 1, seed=s)[0] for s in range(6)])
    print(f"bilinear, 256^2 map: AD {g.mean():.4e} +- {g.std():.1e}, ray-traced FD {ref:.4e}")
    assert abs(g.mean() / ref - 1.0) <= 0.04
    assert g.std() <= 0.02 * abs(ref)


@pytest.mark.parametrize("kernel", [1, 2, 8])
def test_bilinear_pixel_centre_gradient_is_finite_for_any_kernel(kernel):
    """The pixel-centre run's widened kernel for every ``kernel``: 1 is ``hard`` (no
    smooth compare, so no shadow gradient, and no NaN), 8 spans the most texels."""
    scene = inverse.occluder_scene("area", 32, 4)
    mask = inverse.receiver_mask(scene)
    param = inverse.translate_shape(scene, axes="xz")
    integ = mi.load_dict({"type": "shadowmap", "method": "bilinear", "kernel": kernel,
                          "soft_compare": 2.0, "resolution": 512})
    g = _ad(param, integ, _weights(mask, 4), 2, spp=4)
    print(f"kernel {kernel}: {g}")
    assert np.isfinite(g).all()
    assert (np.abs(g).max() == 0.0) if kernel == 1 else (np.abs(g).max() > 1e-3)


def test_area_light_translation_reverse_mode_equals_forward_mode():
    """An area light's ``to_world`` translated along x, y and z, ``pcf`` with the
    README's gradient settings: the reverse-mode gradient (``dr.backward``) equals the
    forward-mode derivatives (``dr.forward``, one per axis) and is finite. A cube
    face's projection used to clamp its axial component at 1e-30, so an antialiased
    silhouette edge reaching behind the face plane gave ``1/major^2 = inf``; zero
    gradients times it were NaN in reverse mode only, and the z component came out 0."""
    scene = inverse.occluder_scene("area", IMAGE, SPP_AD)
    mask = inverse.receiver_mask(scene)
    w = _weights(mask, 4)

    def apply(base, x):
        return mi.Transform4f().translate(mi.Vector3f(inverse._vec(x, 0), inverse._vec(x, 1),
                                                      inverse._vec(x, 2))) @ mi.Transform4f(base)
    param = inverse.Parameter(scene, "light.to_world", apply, 3)
    integ = mi.load_dict({"type": "shadowmap", "resolution": 128,
                          **GRADIENT_SETTINGS["pcf"]})
    back = _ad(param, integ, w, 3)
    fwd = []
    for k in range(3):
        x = mi.Float(np.zeros(3, np.float32))
        dr.enable_grad(x)
        param.set(x)
        dr.set_grad(x, mi.Float(np.eye(3, dtype=np.float32)[k]))
        img = mi.render(scene, param.params, integrator=integ, spp=SPP_AD, seed=1)
        dr.forward_to(img)
        fwd.append(float(dr.sum(dr.grad(img).array * w)[0]))
        param.reset()
    print(f"reverse {back}, forward {np.array(fwd)}")
    assert np.isfinite(back).all()
    assert np.allclose(back, fwd, rtol=0.01, atol=1e-3 * np.abs(fwd).max())


def _two_light_scene(sensor_type="perspective"):
    """The occluder scene's ground and box under two area lights."""
    base = inverse.occluder_scene("area", 32, 4)
    params = mi.traverse(base)
    v = np.array(params["occluder.vertex_positions"]).reshape(-1, 3)
    f = np.array(params["occluder.faces"]).reshape(-1, 3)
    from mi_shadowmap.scenes import mesh
    light = {"type": "rectangle", "emitter": {"type": "area",
                                              "radiance": {"type": "rgb", "value": 10.0}}}
    sensor = {"type": sensor_type, "film": {"type": "hdrfilm", "width": 32, "height": 32},
              "sampler": {"type": "independent", "sample_count": 4},
              "to_world": T().look_at(origin=[0.0, 6.0, 4.0], target=[0.0, 0.0, 0.0],
                                      up=[0, 1, 0])}
    if sensor_type == "orthographic":
        sensor["to_world"] = sensor["to_world"] @ T().scale([4.0, 4.0, 1.0])
    else:
        sensor["fov"] = 50
    return mi.load_dict({
        "type": "scene",
        "ground": {"type": "rectangle", "to_world": T().rotate([1, 0, 0], -90).scale(4),
                   "bsdf": _diffuse(0.7)},
        "occluder": mesh("occluder", v, f, None, _diffuse(0.5)),
        "light_a": {**light, "to_world": T().translate([-1.2, 3.0, 0.0]).rotate([1, 0, 0], 90)
                    .scale(0.3)},
        "light_b": {**light, "to_world": T().translate([1.0, 3.5, 0.5]).rotate([1, 0, 0], 90)
                    .scale(0.3)},
        "sensor": sensor})


def test_pixel_centre_keeps_every_lights_values():
    """Two area lights: a gradient render's image is the same with either
    ``gradient_at`` (the light average draws no random number of its own, so the second
    light's samples are the primal render's)."""
    scene = _two_light_scene()
    param = inverse.translate_shape(scene, axes="z")
    images = []
    for at in ("pixel_centre", "sample"):
        x = mi.Float(0.0)
        dr.enable_grad(x)
        param.set(x)
        with dr.resume_grad():
            integ = mi.load_dict({"type": "shadowmap", "resolution": 128,
                                  **GRADIENT_SETTINGS["vsm"], "gradient_at": at})
            images.append(integ.render(scene, seed=5).numpy())
        param.reset()
    # equal up to float rounding (the film's accumulation of a pixel's samples is not
    # ordered between threads: once, a last-bit difference); a different light sample
    # would change pixels by several %
    scale = float(np.abs(images[1]).max())
    print("max difference", np.abs(images[0] - images[1]).max(), "of", scale)
    assert np.abs(images[0] - images[1]).max() <= 1e-5 * scale


def test_orthographic_camera_gradients_fall_back_to_the_sample():
    """An orthographic camera has no ``sample_direction``: its gradient renders take
    the visibility's derivative at the sample's point (only the light average of
    ``gradient_at='pixel_centre'`` applies), and do not fail."""
    scene = _two_light_scene("orthographic")
    param = inverse.translate_shape(scene, axes="xz")
    w = mi.Float(np.full(32 * 32 * 5, 1.0 / (32 * 32 * 3), np.float32))
    g = [_ad(param, mi.load_dict({"type": "shadowmap", "resolution": 128,
                                  **GRADIENT_SETTINGS["vsm"], "gradient_at": at}), w, 2,
             spp=4)
         for at in ("pixel_centre", "sample")]
    print("orthographic gradients:", g)
    assert np.isfinite(g[0]).all() and np.abs(g[0]).max() > 0
    assert np.allclose(g[0], g[1], rtol=0.03)


def test_light_pose_reference_follows_a_changed_spot_cone():
    """With gradients on a spot's ``to_world``, maps are built from a reference view
    (light_views.pose). A new ``cutoff_angle`` -- here across ``WIDE_SPOT_CUTOFF``, from
    one perspective face to a cube -- must replace the reference: the old 60-degree
    frustum does not cover an 85-degree cone."""
    from mi_shadowmap.light_views import CubeView, PerspectiveView, make_light_view
    from mi_shadowmap.light_views import pose as pose_mod
    from mi_shadowmap.light_views.pose import light_pose
    T = mi.ScalarTransform4f
    scene = mi.load_dict({"type": "scene", "floor": {"type": "rectangle"},
                          "sp": {"type": "spot", "cutoff_angle": 60.0,
                                 "to_world": T().look_at([0, 3, 0], [0, 0, 0], [0, 0, 1])}})
    emitter = scene.emitters()[0]
    bounds = (np.zeros(3), np.ones(3))
    try:
        for cutoff, kind in ((60.0, PerspectiveView), (85.0, CubeView),
                             (30.0, PerspectiveView)):
            params = mi.traverse(emitter)
            params["cutoff_angle"] = cutoff
            dr.enable_grad(params["to_world"])
            params.update()
            with dr.suspend_grad():     # no AD edges left behind for later tests
                view, pose = light_pose(emitter, make_light_view(emitter, scene, 0), bounds,
                                        detached=True)
            assert isinstance(view, kind) and pose is not None
            if kind is PerspectiveView:
                assert view.tan_half == pytest.approx(np.tan(np.radians(cutoff)))
    finally:
        params = mi.traverse(emitter)
        dr.disable_grad(params["to_world"])
        params.update()
        pose_mod._REFERENCES.pop(id(emitter), None)


def _forward(param, integ, w, n, seed=1, spp=4):
    """Forward-mode derivatives (``dr.forward_to``), one per component of ``x``."""
    out = []
    for k in range(n):
        x = mi.Float(np.zeros(n, np.float32))
        dr.enable_grad(x)
        param.set(x)
        dr.set_grad(x, mi.Float(np.eye(n, dtype=np.float32)[k]))
        img = mi.render(param.scene, param.params, integrator=integ, spp=spp, seed=seed)
        dr.forward_to(img)
        out.append(float(dr.sum(dr.grad(img).array * w)[0]))
        param.reset()
    return np.array(out)


@pytest.mark.parametrize("method", ["hard", "pcf", "second_depth", "mdsm", "multiview",
                                    "pcss"])
@pytest.mark.parametrize("what", ["occluder", "light"])
def test_forward_mode_with_maps_the_image_does_not_differentiate(method, what):
    """Methods that read their maps only through steps (``pcss`` under a point light is
    ``hard``): the maps are built in the AD graph (a shape or the light moves) but the
    image's derivatives do not pass through them. ``dr.forward`` used to fail ("tried
    to forward-propagate derivatives across edge ... outside of the current
    dr.isolate_grad() scope"); now it equals reverse mode, component by component."""
    scene = inverse.occluder_scene("point", 32, 4)
    param = (inverse.translate_shape(scene, axes="xz") if what == "occluder"
             else inverse.light_position(scene))
    integ = mi.load_dict({"type": "shadowmap", "method": method, "resolution": 128})
    w = _weights(np.ones((32, 32), bool), 4)
    fwd = _forward(param, integ, w, param.size)
    back = _ad(param, integ, w, param.size, spp=4)
    print(f"{method} {what}: forward {fwd}, reverse {back}")
    assert np.isfinite(fwd).all() and np.abs(fwd).max() > 0.0
    assert np.allclose(fwd, back, rtol=1e-3, atol=1e-4 * np.abs(back).max())


def test_optimising_from_the_largest_seed_wraps_the_seed():
    """``optimize`` renders step ``k`` at ``seed + k``: from the largest seed Mitsuba
    takes, 2^32 - 1, the second step failed in Dr.Jit's ``sample_tea_32`` ("incompatible
    function arguments"); the seed now wraps within [0, 2^32)."""
    scene = inverse.occluder_scene("point", 16, 1)
    mask = inverse.receiver_mask(scene)
    target = mi.render(scene, integrator=mi.load_dict({"type": "shadowmap",
                                                       "method": "raytraced"}), spp=1)
    param = _pose_parameter(scene, "point")
    x0 = np.zeros(param.size)
    hist = inverse.optimize(param, _integ("vsm"), target, mask, x0, steps=2, lr=0.01,
                            spp=1, seed=2 ** 32 - 1)
    assert len(hist.loss) == 2 and np.all(np.isfinite(hist.loss))


def test_environment_regions_antialias_their_own_silhouettes():
    """An occluder under an environment map (16 median-cut regions, one orthographic
    map each): its translation's gradient matches the method's own finite differences.
    The antialiasing pass took every region's silhouette edges as seen from the first
    region's direction (``MultiView.direction_to_light``, the template's), so most
    regions' outlines were not blended: the gradient was 0.3-0.4x the differences
    (here vsm -0.57 to -0.70 against -1.53 to -1.83 over two seeds; now -1.48 to -1.64)."""
    base = inverse.occluder_scene("area", 32, 8)
    params = mi.traverse(base)
    from mi_shadowmap.scenes import mesh
    sky = np.full((16, 32, 3), 0.2, np.float32)
    sky[2:4, 10:12] = 80.0            # a sun about 25 degrees from the zenith
    scene = mi.load_dict({
        "type": "scene", "sensor": base.sensors()[0],
        "ground": {"type": "rectangle", "to_world": T().rotate([1, 0, 0], -90).scale(4),
                   "bsdf": _diffuse(0.7)},
        "occluder": mesh("occluder", np.array(params["occluder.vertex_positions"]).reshape(-1, 3),
                         np.array(params["occluder.faces"]).reshape(-1, 3), None, _diffuse(0.5)),
        "sky": {"type": "envmap", "bitmap": mi.Bitmap(sky)}})
    mask = inverse.receiver_mask(scene)
    ramp = np.linspace(-1.0, 1.0, mask.shape[1])[None, :]
    w = np.zeros(mask.shape + (4,), np.float32)
    w[..., :3] = (mask * ramp)[..., None] / mask.sum()
    w = mi.Float(w.ravel())
    param = inverse.translate_shape(scene, "occluder", "x")
    spec = {"type": "shadowmap", "method": "vsm", "light_bleeding": 0.0, "resolution": 128}
    g = _ad(param, mi.load_dict(spec), w, 1, spp=8)[0]
    fd = _fd(param, mi.load_dict({**spec, "antialias": "always"}), w, 1, 0.05, spp=8)[0]
    print(f"AD {g:.4g}, own FD {fd:.4g}")
    assert abs(fd) > 1e-4
    assert abs(g - fd) <= 0.2 * abs(fd)


def test_a_method_without_shadow_gradients_says_so():
    """A gradient render that moves an occluder with a method whose visibility is a step
    of the maps' depths (``hard``, ``pcf`` without ``soft_compare``, ...) got the
    shading's derivative only -- exactly ``raytraced``'s image gradient, none of the
    shadow's motion -- with no word (README: they "pass no visibility gradient"). It now
    warns once, naming the method and the setting that gives shadow gradients; a smooth
    method (``vsm``, ``pcf`` with ``soft_compare``) and a reflectance-only gradient (maps
    not in the AD graph) do not warn. Forward and reverse mode alike."""
    import warnings
    scene = inverse.occluder_scene("point", 16, 1)

    def messages(integ, what="occluder", mode="backward"):
        param = (inverse.translate_shape(scene, axes="x") if what == "occluder"
                 else None)
        params = mi.traverse(scene)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            if param is not None:
                param.set(mi.Float(0.0))
                dr.enable_grad(param.params[param.key])
                param.params.update()
                key = param.key
            else:
                key = "ground.bsdf.reflectance.value"
                dr.enable_grad(params[key])
                params.update()
            p = param.params if param is not None else params
            img = mi.render(scene, p, integrator=integ, spp=1)
            if mode == "backward":
                dr.backward(dr.sum(img, axis=None))
            else:
                dr.forward(p[key])
            dr.disable_grad(p[key])
            p.update()
        return [str(w.message) for w in caught if "passes no shadow gradient" in str(w.message)]

    def integ(**kw):
        return mi.load_dict({"type": "shadowmap", "resolution": 64, **kw})

    hard = messages(integ(method="hard"))
    assert len(hard) == 1 and "'hard'" in hard[0] and "soft_compare" in hard[0]
    pcf = messages(integ(method="pcf"), mode="forward")
    assert len(pcf) == 1 and "soft_compare=0" in pcf[0]
    assert not messages(integ(method="pcf", soft_compare=2.0))
    assert not messages(integ(method="vsm"))
    assert not messages(integ(method="hard"), what="reflectance")
    # once per integrator
    it = integ(method="second_depth")
    assert len(messages(it)) == 1 and not messages(it)


def test_automatic_resolution_is_kept_while_gradients_are_enabled():
    """The automatic resolution follows the scene's bounds, so an optimisation moving an
    occluder changed it between steps (a helper's Adam run: 56^2 -> 64^2 at its second
    step, 12 kernels compiled, the optimised function changed). While a shape has
    gradients enabled the first gradient render's resolution is kept; without them it
    follows the scene as before (checked here first, so the test can tell)."""
    scene = mi.load_dict(scene_dict())
    params = mi.traverse(scene)
    key = "post.vertex_positions"
    base = mi.Float(params[key])

    def move(dx):
        params[key] = dr.ravel(dr.unravel(mi.Point3f, base) + mi.Vector3f(dx, 0.0, dx))
        params.update()

    # full maps, as a gradient render's automatic maps are (virtual maps have no
    # automatic resolution)
    integ = mi.load_dict({"type": "shadowmap", "method": "vsm", "virtual": False})
    seen = []
    for dx in (0.0, 6.0):                  # no gradients: the bounds grow, the maps follow
        move(dx)
        mi.render(scene, integrator=integ, spp=1)
        seen.append(integ.resolution)
    assert seen[0] != seen[1], seen
    move(0.0)
    dr.enable_grad(params[key])
    params.update()
    kept = []
    for dx in (0.0, 6.0):
        move(dx)
        dr.enable_grad(params[key])
        params.update()
        img = mi.render(scene, params, integrator=integ, spp=1)
        dr.backward(dr.sum(img, axis=None))
        kept.append(integ.resolution)
    assert kept == [seen[0], seen[0]], (seen, kept)


def test_a_render_without_gradients_forgets_the_kept_resolution():
    """The resolution is kept while gradients stay enabled, not for the session: after
    they were disabled and the scene changed, a second optimisation of one scene kept
    building the first one's maps, where a fresh scene in the same state (its first
    gradient render) got the automatic resolution of that state (measured, a camera
    moved closer: 256^2 against 384^2, ``hard`` 0.61 % misclassified against 0.35 %,
    ``vsm``'s gradient 7 % off). A render without gradients now forgets it."""
    key = "post.vertex_positions"

    def state(scene, dx):
        params = mi.traverse(scene)
        base = mi.Float(params[key])
        params[key] = dr.ravel(dr.unravel(mi.Point3f, base) + mi.Vector3f(dx, 0.0, dx))
        params.update()
        return params

    def gradient_render(scene, params, integ):
        dr.enable_grad(params[key])
        params.update()
        img = mi.render(scene, params, integrator=integ, spp=1)
        dr.backward(dr.sum(img, axis=None))
        dr.disable_grad(params[key])
        params.update()
        return integ.resolution

    def integrator():
        return mi.load_dict({"type": "shadowmap", "method": "vsm", "virtual": False})

    fresh = mi.load_dict(scene_dict())
    want = gradient_render(fresh, state(fresh, 6.0), integrator())   # a fresh session

    scene = mi.load_dict(scene_dict())
    integ = integrator()
    first = gradient_render(scene, state(scene, 0.0), integ)
    assert first != want                    # else the test cannot tell
    params = state(scene, 6.0)              # gradients disabled: the occluder moves
    mi.render(scene, integrator=integ, spp=1)
    assert integ.resolution == want
    assert gradient_render(scene, params, integ) == want, (first, want)


def _zero_light_scene(method, light, **props):
    lights = {
        "point": {"type": "point", "position": [0.3, 2.0, 0.2],
                  "intensity": {"type": "rgb", "value": 0.0}},
        "area": {"type": "rectangle",
                 "to_world": T().translate([0, 2.0, 0]).rotate([1, 0, 0], 90).scale(0.3),
                 "emitter": {"type": "area", "radiance": {"type": "rgb", "value": 0.0}}}}
    return mi.load_dict({
        "type": "scene", "integrator": {"type": "shadowmap", "method": method, **props},
        "sensor": camera([0, 3, 3], [0, 0, 0], 32, 32, 2),
        "floor": {"type": "rectangle", "to_world": T().rotate([1, 0, 0], -90).scale(2)},
        "box": {"type": "cube", "to_world": T().translate([0, 0.5, 0]).scale(0.25)},
        "light": lights[light]})


@pytest.mark.parametrize("method,light,props", [
    ("raytraced", "area", {}), ("hard", "point", {}),
    ("multiview", "point", {"light_size": 0.3, "views": 16, "lookups": 4}),
    ("multiview", "area", {"views": 16})])
def test_gradient_wrt_an_intensity_of_zero(method, light, props):
    """The image is linear in a light's intensity, so its derivative there is the same
    at 0 as at 1. The term was gated by the light's weight being > 0: at intensity 0 the
    derivative was 0 (raytraced, hard, pcf; direct: 55.5 on a point light), and a dark
    light's virtual map kept its coarsest level only (hard at 0: 55.11 against 55.60 at
    1). Reverse and forward mode; the visibility AOV stays 0 for the dark light.
    multiview gated its lookups by the weight too (a delta light's weight, an area
    light's per-point radiance): 0 at intensity 0 against 14.2 at 1 on a point light
    with light_size (16^2, 2 spp), 0 against 4.1 on a rectangle."""
    key = "light.emitter.radiance.value" if light == "area" else "light.intensity.value"
    grads = []
    for value in (0.0, 1.0):
        scene = _zero_light_scene(method, light, **props)
        params = mi.traverse(scene)
        params[key] = mi.Color3f(value)
        dr.enable_grad(params[key])
        params.update()
        image = mi.render(scene, params, seed=0, spp=2)
        if value == 0.0:
            assert np.all(np.asarray(image)[..., 3] == 0)   # vis_light: lit by nothing
        dr.backward(dr.sum(image[:, :, :3], axis=None))
        reverse = float(dr.sum(dr.grad(params[key])).array[0])
        dr.set_grad(params[key], mi.Color3f(1.0))
        image = mi.render(scene, params, seed=0, spp=2)
        dr.forward_to(image)
        forward = np.asarray(dr.grad(image))[..., :3]
        grads.append((reverse, forward))
    (r0, f0), (r1, f1) = grads
    assert r1 > 1.0
    assert r0 == pytest.approx(r1, rel=1e-5)
    assert float(f0.sum()) == pytest.approx(r1, rel=1e-4)
    np.testing.assert_allclose(f0, f1, rtol=1e-5, atol=1e-7)


def test_multiview_primal_is_the_same_with_an_intensity_tracked():
    """Where a delta light's intensity tracks gradients, multiview looks its views up
    wherever the light's sample has a pdf (so that an intensity of 0 has a derivative);
    its sampler must still advance only where the light emits, or every later lookup's
    random numbers change: with lookups < views the image of a spot and a point light
    (light_size 0.3) differed from the untracked one by up to 0.25 (found in review)."""
    from mi_shadowmap.scenes import default_scene
    d = default_scene(width=32, height=32, spp=4, light="spot")
    d["pt"] = {"type": "point", "position": [1, 2.5, 1], "intensity": 10}
    scene = mi.load_dict(d)
    integ = mi.load_dict({"type": "shadowmap", "method": "multiview", "light_size": 0.3,
                          "views": 16, "lookups": 4})
    before = np.asarray(mi.render(scene, integrator=integ, seed=1))
    params = mi.traverse(scene)
    dr.enable_grad(params["spot.intensity.value"])
    params.update()
    after = np.asarray(mi.render(scene, params, integrator=integ, seed=1))
    assert np.abs(after - before).max() == 0.0


def test_masked_mse_is_the_mean_squared_error_of_the_colour_channels_over_the_mask():
    """``inverse.masked_mse``: the mean of the squared differences over the masked
    pixels' first ``channels`` channels (AOV channels past them ignored), against
    numpy. (Mutation audit: a mean over pixels instead of pixel-channels, 3x the loss,
    survived: Adam is invariant to the loss's scale.)"""
    rng = np.random.default_rng(3)
    img = rng.uniform(0, 1, (6, 5, 4)).astype(np.float32)
    tgt = rng.uniform(0, 1, (6, 5, 4)).astype(np.float32)
    mask = rng.uniform(0, 1, (6, 5)) < 0.5
    want = float(np.mean((img[mask][:, :3] - tgt[mask][:, :3]) ** 2))
    got = float(inverse.masked_mse(mi.TensorXf(img), tgt, mask)[0])
    assert got == pytest.approx(want, rel=1e-5)
    assert float(inverse.masked_mse(mi.TensorXf(img), tgt, mask, channels=1)[0]) == \
        pytest.approx(float(np.mean((img[mask][:, 0] - tgt[mask][:, 0]) ** 2)), rel=1e-5)


def test_optimize_leaves_the_scene_at_the_final_value():
    """``optimize`` leaves the scene at the parameter of its last step (``hist.x[-1]``,
    after the last Adam step), not at the value it rendered last. (Mutation audit:
    without the final ``param.set`` the occluder stayed one step behind, and no test
    looked.)"""
    scene = inverse.occluder_scene("area", 32, 2)
    mask = inverse.receiver_mask(scene)
    target = mi.render(scene, integrator=mi.load_dict({"type": "shadowmap",
                                                       "method": "raytraced"}), spp=4)
    param = inverse.translate_shape(scene, axes="x")
    base = np.array(param.base).reshape(-1, 3)
    hist = inverse.optimize(param, _integ("vsm", resolution=128), target, mask,
                            np.array([0.2]), steps=2, lr=0.05, spp=2)
    x = hist.x[-1][0]
    assert abs(x - 0.2) > 1e-3                       # the steps moved it
    got = np.array(mi.traverse(scene)["occluder.vertex_positions"]).reshape(-1, 3)
    np.testing.assert_allclose(got[:, 0], base[:, 0] + x, atol=1e-6)
    np.testing.assert_allclose(got[:, 1:], base[:, 1:], atol=1e-6)
