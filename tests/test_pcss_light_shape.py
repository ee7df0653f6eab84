"""``pcss`` under a planar area light reads the light's own shape (``filters/pcss.py``'s
``_light_shape``, ``light_views.area_light_axes``): its blocker search and filter kernel
are the light's parallelogram as the receiver sees it across the map face, not the square
of its area (a strip light 6 x 0.02 was a 0.35 square: its penumbra along the strip far
too narrow, across it far too wide)."""
from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

T = mi.ScalarTransform4f


def _scene(res: int, spp: int, long_: float, short: float, height: float = 3.0,
           turn: float = 0.0) -> dict:
    """A ground, a plate 1 above it and a rectangle light ``long_ x short`` ``height``
    above the ground, facing down, turned ``turn`` degrees about the vertical."""
    white = {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.5}}
    return {
        "type": "scene",
        "sensor": {"type": "perspective", "fov": 50,
                   "to_world": T().look_at(origin=[0, 7, 4], target=[0, 0, 0], up=[0, 1, 0]),
                   "sampler": {"type": "independent", "sample_count": spp},
                   "film": {"type": "hdrfilm", "width": res, "height": res,
                            "rfilter": {"type": "box"}}},
        "ground": {"type": "rectangle", "bsdf": white,
                   "to_world": T().rotate([1, 0, 0], -90).scale(4)},
        "plate": {"type": "rectangle", "bsdf": white,
                  "to_world": T().translate([0.3, 1.0, 0.2]).rotate([1, 0, 0], -90)
                  .scale([0.5, 0.8, 1])},
        "light": {"type": "rectangle",
                  "to_world": T().translate([0, height, 0]).rotate([0, 1, 0], turn)
                  .rotate([1, 0, 0], 90).scale([0.5 * long_, 0.5 * short, 1]),
                  "emitter": {"type": "area", "radiance": {
                      "type": "rgb", "value": 3 * height ** 2 / (long_ * short)}}}}


def _vis(d: dict, method: str, seed: int = 1, **props) -> np.ndarray:
    """The light's visibility AOV (the last channel: one light; 1 colour channel in mono,
    3 in rgb and spectral)."""
    integ = mi.load_dict({"type": "shadowmap", "method": method, **props})
    return np.asarray(mi.render(mi.load_dict(d), integrator=integ, seed=seed))[..., -1:]


def _rmse(a, b) -> float:
    return float(np.sqrt(np.mean((a - b) ** 2)))


def _shaped_and_square(d, virtual, monkeypatch):
    """``(noise, {shaped: RMSE})``: the reference's own seed noise (``raytraced``, 32
    shadow rays, seeds 0 and 5) and ``pcss``'s visibility RMSE against it with the light's
    own shape (True) and read as the square of its area (False, the code before)."""
    import mi_shadowmap.filters.pcss as pcss_mod
    ref = _vis(d, "raytraced", 0, shadow_rays=32)
    noise = _rmse(ref, _vis(d, "raytraced", 5, shadow_rays=32))
    errs = {}
    for shaped in (True, False):
        monkeypatch.setattr(pcss_mod, "LIGHT_SHAPE", shaped)
        vis = _vis(d, "pcss", virtual=virtual)
        assert np.isfinite(vis).all()
        errs[shaped] = _rmse(ref, vis)
    print(f"noise {noise:.4f}, shaped {errs[True]:.4f}, square {errs[False]:.4f}")
    return noise, errs


@pytest.mark.parametrize("virtual", [True, False])
def test_a_strip_light_s_penumbra_follows_the_strip(virtual, monkeypatch):
    """A strip 6 x 0.02 over a plate: ``pcss``'s visibility RMSE against ``raytraced``
    (32 shadow rays) lies within the reference's own seed noise + 0.02; read as the square
    of its area (``LIGHT_SHAPE`` False, the code before) it does not. Measured at 32^2,
    8 spp: noise 0.0455, shaped 0.056 (virtual) / 0.056 (full), square 0.126 / 0.125
    (48^2, 4 spp, 16 rays: noise 0.075, 0.076 / 0.075 against 0.136 / 0.136)."""
    noise, errs = _shaped_and_square(_scene(32, 8, 6.0, 0.02), virtual, monkeypatch)
    assert errs[True] <= noise + 0.02
    assert errs[False] > noise + 0.05


def test_a_square_light_face_on_keeps_its_square(monkeypatch):
    """A square light 1.5 wide 6 above the ground (every receiver on the map's face that
    sees it face-on): the shaped kernel is the square the light's area gave, to
    rounding (its width from its sides, not ``sqrt(area)``): single filter or search taps
    flip where they fall on a texel's edge (48^2, 4 spp: 45 of 2304 pixels by 1/64 to
    3/16, the mean 2e-4), no more."""
    import mi_shadowmap.filters.pcss as pcss_mod
    d = _scene(48, 4, 1.5, 1.5, height=6.0)
    imgs = {}
    for shaped in (True, False):
        monkeypatch.setattr(pcss_mod, "LIGHT_SHAPE", shaped)
        imgs[shaped] = _vis(d, "pcss", 3)
    diff = imgs[True] - imgs[False]
    print(f"pixels changed {np.mean(diff != 0):.2%}, mean {diff.mean():.2e}")
    assert np.mean(diff != 0) < 0.05
    assert abs(diff.mean()) < 2e-3


def test_light_size_keeps_the_square(monkeypatch):
    """``light_size`` (a scalar: the square it means) keeps the isotropic kernel under a
    strip light: the image and the virtual map's texels are those without the light's
    shape, bit for bit."""
    import mi_shadowmap.filters.pcss as pcss_mod
    d = _scene(32, 2, 6.0, 0.02)
    out = {}
    for shaped in (True, False):
        monkeypatch.setattr(pcss_mod, "LIGHT_SHAPE", shaped)
        integ = mi.load_dict({"type": "shadowmap", "method": "pcss", "light_size": 1.0})
        img = np.asarray(mi.render(mi.load_dict(d), integrator=integ, seed=2))
        out[shaped] = (img, integ.stats["texels_built"])
    assert (out[True][0] == out[False][0]).all()
    assert out[True][1] == out[False][1]


def test_area_light_axes_of_each_shape():
    """A rectangle's half-sides, a disk's equal-area square, a planar mesh's rectangle of
    equal second moments (a strip quad turned 40 degrees: its own sides), None where the
    light is not planar (a sphere, a closed cube)."""
    from mi_shadowmap.light_views import area_light_axes
    emit = {"type": "area", "radiance": {"type": "rgb", "value": 1.0}}
    scene = mi.load_dict({
        "type": "scene",
        "r": {"type": "rectangle", "emitter": emit,
              "to_world": T().translate([1, 2, 3]).scale([3, 0.01, 1])},
        "d": {"type": "disk", "emitter": emit, "to_world": T().scale(0.5)},
        "s": {"type": "sphere", "emitter": emit},
        "c": {"type": "cube", "emitter": emit}})
    axes = {s.class_name(): area_light_axes(s.emitter().get_shape()) for s in scene.shapes()}
    assert np.allclose(axes["Rectangle"], [[3, 0, 0], [0, 0.01, 0]])
    assert np.allclose(axes["Disk"], [[0.5 * math.sqrt(math.pi) * 0.5, 0, 0],
                                      [0, 0.5 * math.sqrt(math.pi) * 0.5, 0]])
    assert axes["Sphere"] is None and axes["Cube"] is None
    mesh = mi.Mesh("strip", 4, 2)
    params = mi.traverse(mesh)
    c, s = math.cos(math.radians(40)), math.sin(math.radians(40))
    quad = np.array([[-3, 0, -0.05], [3, 0, -0.05], [3, 0, 0.05], [-3, 0, 0.05]])
    turned = quad @ np.array([[c, 0, -s], [0, 1, 0], [s, 0, c]])
    params["vertex_positions"] = mi.Float(turned.astype("f4").ravel())
    params["faces"] = mi.UInt32([0, 1, 2, 0, 2, 3])
    params.update()
    e1, e2 = (np.array(e) for e in area_light_axes(mesh))
    assert np.isclose(np.linalg.norm(e1), 3.0, rtol=1e-4)
    assert np.isclose(np.linalg.norm(e2), 0.05, rtol=1e-3)
    assert np.isclose(abs(e1 @ turned[1] - e1 @ turned[0]), 18.0, rtol=1e-4)   # along a side


def test_a_turned_light_is_read_again(monkeypatch):
    """Turning the strip by ``params.update()`` (the same shape object) gives the view
    the new axes: the image equals a fresh render of the turned scene."""
    import mi_shadowmap
    d = _scene(32, 2, 6.0, 0.02)
    scene = mi.load_dict(d)
    integ = mi.load_dict({"type": "shadowmap", "method": "pcss"})
    mi.render(scene, integrator=integ, seed=2)
    params = mi.traverse(scene)
    turned = _scene(32, 2, 6.0, 0.02, turn=60.0)["light"]["to_world"]
    params["light.to_world"] = turned
    params.update()
    moved = np.asarray(mi.render(scene, integrator=integ, seed=2))
    mi_shadowmap.clear_caches()
    fresh = np.asarray(mi.render(mi.load_dict(_scene(32, 2, 6.0, 0.02, turn=60.0)),
                                 integrator=mi.load_dict({"type": "shadowmap",
                                                          "method": "pcss"}), seed=2))
    assert np.abs(moved - fresh).max() < 1e-5


def test_camera_moves_under_a_strip_light_compile_nothing():
    """The shaped kernels' light axes are opaque inputs: after the first move, moving the
    camera compiles no kernel (virtual ``pcss``)."""
    from test_virtual import _moves
    scene = mi.load_dict(_scene(32, 2, 6.0, 0.02))
    integ = mi.load_dict({"type": "shadowmap", "method": "pcss"})
    compiled = _moves(scene, integ, 3)
    assert compiled[1:] == [0, 0], compiled


@pytest.mark.parametrize("variant", ["llvm_ad_mono", "llvm_ad_spectral"])
def test_shaped_kernels_in_other_variants(variant):
    """Mono and spectral: the strip light's ``pcss`` (virtual and full) is finite, and
    its mean visibility is rgb's to 0.01."""
    means = {}
    for v in ("llvm_ad_rgb", variant):
        mi.set_variant(v)
        d = _scene(24, 2, 6.0, 0.02)
        for virtual in (True, False):
            vis = _vis(d, "pcss", 2, virtual=virtual)
            assert np.isfinite(vis).all()
            means[v, virtual] = float(vis.mean())
    for virtual in (True, False):
        assert abs(means[variant, virtual] - means["llvm_ad_rgb", virtual]) < 0.01, means
    dr.sync_thread()


def test_a_far_strip_light_s_virtual_map_keeps_its_shape(monkeypatch):
    """A strip 2000 x 2, 2000 above the plate (so far that the virtual map aims one face
    at the scene, ``light_views.box_view``): that face keeps the light's half-axes, and
    ``pcss`` reads the strip, not the square of its area. The face dropped them: the
    image was the square's bit for bit. Measured (32^2, 8 spp, ``raytraced`` 32 shadow
    rays): noise 0.0358, shaped 0.0398, square 0.0489."""
    from mi_shadowmap.light_views import make_light_view
    from mi_shadowmap.light_views.perspective import box_view
    d = _scene(32, 8, 2000.0, 2.0, height=2000.0)
    scene = mi.load_dict(d)
    view = make_light_view(scene.emitters()[0], scene, 0)
    aimed = box_view(view, np.array([-4.0, 0.0, -4.0]), np.array([4.0, 1.0, 4.0]))
    assert aimed is not None and aimed.light_axes == view.light_axes is not None
    noise, errs = _shaped_and_square(d, True, monkeypatch)
    assert errs[True] <= noise + 0.01
    assert errs[True] < errs[False] - 0.005


def _mesh(vertices, faces) -> mi.Mesh:
    mesh = mi.Mesh("light", len(vertices), len(faces))
    params = mi.traverse(mesh)
    params["vertex_positions"] = mi.Float(np.asarray(vertices, "f4").ravel())
    params["faces"] = mi.UInt32(np.asarray(faces, "u4").ravel())
    params.update()
    return mesh


@pytest.mark.parametrize("split", ["two triangles", "fan", "grid", "ring"])
@pytest.mark.parametrize("turn", [0.0, 25.0])
def test_a_square_mesh_light_keeps_its_sides_whatever_its_triangles(split, turn):
    """A square mesh light (in-plane moments isotropic: no axis from them) is read along
    its sides however it is triangulated: two triangles, a fan around its centre, a 2 x 2
    grid, a square ring. The first triangle's shortest edge (6b56d0d) was a fan's
    half-diagonal and a ring's inner diagonal: the square read as itself turned 45
    degrees, 1.41 times as wide along the map's axes."""
    from mi_shadowmap.light_views import area_light_axes
    h = 0.75
    corners = [[-h, 0, -h], [h, 0, -h], [h, 0, h], [-h, 0, h]]
    if split == "two triangles":
        v, f, half = corners, [[0, 2, 1], [0, 3, 2]], h
    elif split == "fan":
        v, f, half = corners + [[0, 0, 0]], [[4, 1, 0], [4, 2, 1], [4, 3, 2], [4, 0, 3]], h
    elif split == "grid":
        v = [[x, 0, z] for z in (-h, 0, h) for x in (-h, 0, h)]
        f = [t for j in range(2) for i in range(2)
             for t in ([3 * j + i, 3 * j + i + 4, 3 * j + i + 1],
                       [3 * j + i, 3 * j + i + 3, 3 * j + i + 4])]
        half = h
    else:    # outer half-side 1.5, inner 1.0: equal second moments, half-side sqrt(3.25)
        o, i = 1.5, 1.0
        v = [[-o, 0, -o], [o, 0, -o], [o, 0, o], [-o, 0, o],
             [-i, 0, -i], [i, 0, -i], [i, 0, i], [-i, 0, i]]
        f = [[0, 1, 5], [0, 5, 4], [1, 2, 6], [1, 6, 5], [2, 3, 7], [2, 7, 6],
             [3, 0, 4], [3, 4, 7]]
        half = math.sqrt(o * o + i * i)
    c, s = math.cos(math.radians(turn)), math.sin(math.radians(turn))
    turned = np.asarray(v, float) @ np.array([[c, 0, -s], [0, 1, 0], [s, 0, c]]).T
    side = np.array([c, 0.0, s])          # the first corner's side, turned
    for e in area_light_axes(_mesh(turned, f)):
        e = np.asarray(e)
        assert np.isclose(np.linalg.norm(e), half, rtol=1e-4)
        along = abs(e @ side) / np.linalg.norm(e)
        assert along < 1e-3 or along > 1 - 1e-6, (split, turn, e)
