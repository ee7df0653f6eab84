"""The mark pass drops the biases' level where the light is behind the surface the camera
sees (:func:`mi_shadowmap.virtual.marks._light_behind`): no lookup reads it there."""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from mi_shadowmap import virtual
from mi_shadowmap.virtual import marks
from mi_shadowmap.virtual.camera import camera_frame

T = mi.ScalarTransform4f

#: A point light low behind the wall's far side, which grazes it (``n . l`` -0.08 at
#: its centre): the biases cap the wall's pixels the camera sees and the probes keep
#: their level (posts between light and wall)
LIGHT = {"type": "point", "position": [-0.5, 0.5, -6], "intensity": {"type": "rgb",
                                                                      "value": 10.0}}


#: A 0.2-wide square area light there, facing the posts: wholly behind the wall's plane
AREA = {"type": "rectangle", "to_world": T().translate([-0.5, 0.5, -6]).scale(0.1),
        "emitter": {"type": "area", "radiance": {"type": "rgb", "value": 100.0}}}


def _wall_scene(wall_bsdf: dict, light: dict = LIGHT):
    """A 2-high wall in the ``x = 0`` plane the camera sees at grazing incidence from
    its ``+x`` side (64^2), posts on its ``-x`` side, ``light`` on that side."""
    return mi.load_dict({
        "type": "scene",
        "sensor": {"type": "perspective", "fov": 40,
                   "to_world": T().look_at(origin=[0.5, 1.2, 6.0], target=[0, 1, -2],
                                           up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": 64, "height": 64,
                            "rfilter": {"type": "box"}}},
        "floor": {"type": "rectangle", "to_world": T().rotate([1, 0, 0], -90).scale(10)},
        "wall": {"type": "rectangle", "bsdf": wall_bsdf,
                 "to_world": T().translate([0, 1, 0]).rotate([0, 1, 0], 90).scale([4, 1, 1])},
        **{f"post{i}": {"type": "cube", "to_world": T().translate([-0.4, 1, -3 + 0.8 * i])
                        .scale([0.05, 1, 0.05])} for i in range(8)},
        "light": light})


def _render(scene, method, today: bool, monkeypatch):
    """(image, texels built, the wall's capped and kept pixel centres) of virtual
    ``method``; ``today``: without the rule (``_light_behind`` never true)."""
    with monkeypatch.context() as m:
        if today:
            m.setattr(marks, "_light_behind", lambda *a, **k: mi.Bool(False))
        integ = mi.load_dict({"type": "shadowmap", "method": method, "virtual": True,
                              "cache_maps": False})
        img = np.asarray(mi.render(scene, integrator=integ, spp=4, seed=1))
        vmap, sensor = integ.maps[0], scene.sensors()[0]
        si, dp_dx, dp_dy, valid = virtual.camera_hits(scene, sensor)
        marker = marks.Marker(vmap.layout, vmap.lod_bias, reach=vmap.reach, scene=scene,
                              eye=camera_frame(sensor)[0])
        out = marks.marked_points(marker, si, dp_dx, dp_dy, valid)
    wall = [s for s in scene.shapes() if s.id() == "wall"][0]
    on = (dr.reinterpret_array(mi.UInt32, si.shape)
          == dr.reinterpret_array(mi.UInt32, mi.ShapePtr(wall))[0]).numpy()
    capped = (out[5].numpy() | out[6].numpy()) & on
    return img, integ.stats.texels_built, int(capped.sum()), int((out[6].numpy() & on).sum())


@pytest.mark.parametrize("light", ["point", "area"])
@pytest.mark.parametrize("method", ["hard", "pcf"])
def test_a_wall_lit_from_behind_keeps_no_biases_level(method, light, monkeypatch):
    """A diffuse wall seen from the side the light does not reach: its pixels' lookups
    are never made (the BSDF reaches no light from behind), so the mark drops the
    biases' level there (measured 64^2 ``hard``: 220 of the wall's 241 capped centres
    kept it before, texels 31616 -> 28032; ``pcf`` 48192 -> 42752; since the kept
    points mark their bands, not their boxes, ``marks.kept_tiles``: ``hard`` 31424 ->
    27840, ``pcf`` 45056 -> 40576), and the image is bit-identical to the one with every
    probe's decision. Likewise under a small area light wholly behind the wall's plane."""
    scene = _wall_scene({"type": "diffuse"}, LIGHT if light == "point" else AREA)
    img, texels, capped, kept = _render(scene, method, False, monkeypatch)
    img0, texels0, capped0, kept0 = _render(scene, method, True, monkeypatch)
    print(f"{method} {light}: wall capped {capped}, kept {kept0} -> {kept}; texels {texels0} -> "
          f"{texels}")
    assert capped == capped0 > 100 and kept0 > 0.5 * capped0
    assert kept == 0
    assert texels < 0.92 * texels0
    np.testing.assert_array_equal(img, img0)


@pytest.mark.parametrize("bsdf", [{"type": "thindielectric"},
                                  {"type": "mask", "opacity": 0.5,
                                   "b": {"type": "diffuse"}}])
def test_a_transmitting_wall_lit_from_behind_keeps_todays_marks(bsdf, monkeypatch):
    """The same wall with a BSDF that transmits (``BSDFFlags.Transmission``: light from
    behind reaches the camera through it): the wall's marks and the image are today's."""
    scene = _wall_scene(bsdf)
    img, texels, capped, kept = _render(scene, "hard", False, monkeypatch)
    img0, texels0, capped0, kept0 = _render(scene, "hard", True, monkeypatch)
    assert capped > 100 and kept0 > 0.5 * capped0
    assert (capped, kept) == (capped0, kept0)
    np.testing.assert_array_equal(img, img0)


def test_an_area_light_across_the_walls_plane_keeps_todays_marks(monkeypatch):
    """An area light reaching across the wall's plane lights its camera side in part:
    the wall's marks and the image are today's."""
    across = {**AREA, "to_world": T().translate([0.0, 0.5, -6]).scale([0.5, 0.1, 0.1])}
    scene = _wall_scene({"type": "diffuse"}, across)
    img, _, capped, kept = _render(scene, "hard", False, monkeypatch)
    img0, _, capped0, kept0 = _render(scene, "hard", True, monkeypatch)
    print(f"wall capped {capped0}, kept {kept0} -> {kept}")
    assert capped > 100 and kept0 > 0
    assert (capped, kept) == (capped0, kept0)
    np.testing.assert_array_equal(img, img0)
