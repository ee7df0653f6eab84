"""Zero-parameter defaults (issue 6): automatic resolution, memory budget,
automatic bias, and the accuracy targets with defaults only.

Targets (issue 6), ``hard`` and ``pcf`` with defaults only on every scene of
``scenes_xml/`` at its own film size: misclassified <= 1 % and false shadow
(acne, over-darkening: reference lit, method shadowed) <= 0.2 %, both at
threshold 0.5, against ``raytraced`` (delta lights) or the converged
soft-shadow reference (area lights). The issue's numbers are asserted as they
are; the cases measured to miss them are strict expected failures
(:data:`KNOWN_MISSES`, with the measured numbers and the reason), so a fix
that makes them pass is reported too.
"""
from __future__ import annotations

import re

import mitsuba as mi
import numpy as np
import pytest

import mi_shadowmap.map_manager as mm_mod
from mi_shadowmap.light_views import emitter_kind
from mi_shadowmap.metrics import misclassified
from mi_shadowmap.options import OptionError, parse_options
from mi_shadowmap.reference import converged_visibility
from mi_shadowmap.scenes import default_scene

from conftest import SCENE_FILES, root_message


# ----------------------------------------------------- automatic resolution
def test_resolution_is_automatic_and_follows_the_film():
    """Full maps (virtual=false; the default is virtual maps, whose automatic virtual
    resolution tests/test_virtual.py checks)."""
    assert parse_options({}).resolution is None
    res = {}
    for w in (32, 64):
        scene = mi.load_dict(default_scene(width=w, height=w, spp=1))
        integ = mi.load_dict({"type": "shadowmap", "virtual": False})
        mi.render(scene, integrator=integ, spp=1)
        res[w] = integ.resolution
        assert integ.maps[0].resolution == res[w]
        assert res[w] % 8 == 0 and 2 * w * 0.5 <= res[w] <= 2 * w * 4
    assert abs(res[64] - 2 * res[32]) <= 8   # proportional to the film size



def test_a_crop_window_gets_the_whole_films_automatic_resolution():
    """The footprint correction divides by the camera's field of view over the whole
    film's width, so the size it multiplies is the whole film's: a crop window's pixels
    are the film's. With the crop's size a 30 x 24 window of a 64^2 film got 80^2 maps
    instead of 176^2, and a 48^2 window of a 128^2 film misclassified 0.95 % of its
    pixels (hard, full maps) against the 0.43 % the same pixels get in the whole render."""
    res = {}
    for crop in (None, (30, 24)):
        d = default_scene(width=64, height=64, spp=1)
        if crop:
            d["sensor"]["film"].update(crop_offset_x=10, crop_offset_y=20,
                                       crop_width=crop[0], crop_height=crop[1])
        scene = mi.load_dict(d)
        integ = mi.load_dict({"type": "shadowmap", "virtual": False})
        mi.render(scene, integrator=integ, spp=1)
        res[crop] = integ.resolution
    assert res[(30, 24)] == res[None], res

def test_an_orthographic_camera_gets_the_automatic_resolution_of_its_view():
    """The footprint correction took 1 for every sensor but a perspective camera, so an
    orthographic camera's automatic full maps were 2 x its film whatever its zoom: a
    64^2 view 0.6 wide of a pole's shadow under a spot light got 128^2 maps where a
    perspective camera of the same view width gets 512^2, and ``multiview`` (full maps
    only) misclassified 4.54 % of it against the perspective view's 1.22 % (``hard`` with
    ``virtual=false``: 4.66 %). An orthographic camera spans its own width at any
    distance: its maps are now those of the perspective view (1.15 %)."""
    T = mi.ScalarTransform4f
    view = T().look_at(origin=[1, 5, 8.5], target=[1.0, 0, 0.5], up=[0, 1, 0])
    width = 0.6
    fov = float(np.degrees(2 * np.arctan(0.5 * width / np.linalg.norm([0, 5, 8]))))
    cameras = {"orthographic": {"to_world": view.scale([0.5 * width, 0.5 * width, 1])},
               "perspective": {"to_world": view, "fov": fov}}
    out = {}
    for kind, cam in cameras.items():
        scene = mi.load_dict({
            "type": "scene",
            "sensor": {"type": kind, **cam,
                       "film": {"type": "hdrfilm", "width": 64, "height": 64,
                                "rfilter": {"type": "box"}},
                       "sampler": {"type": "independent", "sample_count": 4}},
            "floor": {"type": "rectangle", "to_world": T().rotate([1, 0, 0], -90).scale(6)},
            "pole": {"type": "cube",
                     "to_world": T().translate([1.5, 1.0, 1.0]).scale([0.04, 1, 0.04])},
            "light": {"type": "spot", "cutoff_angle": 50, "intensity": 60,
                      "to_world": T().look_at(origin=[2.5, 6, 2], target=[0, 0, 0],
                                              up=[0, 1, 0])}})
        vis = {}
        for method in ("raytraced", "multiview"):
            integ = mi.load_dict({"type": "shadowmap", "method": method})
            img = np.asarray(mi.render(scene, integrator=integ, seed=0))
            vis[method] = img[..., -1]
        out[kind] = (integ.resolution,
                     misclassified(vis["raytraced"], vis["multiview"])["misclassified"])
    print(out)
    assert out["orthographic"][0] == out["perspective"][0]
    assert out["orthographic"][1] <= 0.02


@pytest.mark.parametrize("offset", [0.0, 500.0])
def test_a_batch_sensor_gets_the_automatic_resolution_of_its_cameras(offset):
    """A ``batch`` sensor's footprint correction took its first camera's field of view
    but the batch's own position (the world origin) as the camera's: the same two
    cameras (4 and 30 degrees, 64^2 each) over a pole's shadow got 1024^2 maps with the
    scene at the origin and 128^2 with everything moved 500 units away, where
    ``multiview`` (full maps only) misclassified 4.81 % of the 4-degree camera's half
    (0.66 % at the origin; that camera alone, 512^2: 1.42 %). Each camera's ratio is
    now taken at its own pixels: 1024^2 wherever the scene is, 0.66 %."""
    T = mi.ScalarTransform4f
    at = T().translate([offset, 0, 0])

    def cam(target, fov):
        return {"type": "perspective", "fov": fov,
                "to_world": at @ T().look_at(origin=[1, 5, 8.5], target=target, up=[0, 1, 0])}

    scene = mi.load_dict({
        "type": "scene",
        "sensor": {"type": "batch", "a": cam([1.25, 0, 0.75], 4), "b": cam([0, 0.5, 0], 30),
                   "film": {"type": "hdrfilm", "width": 128, "height": 64,
                            "rfilter": {"type": "box"}},
                   "sampler": {"type": "independent", "sample_count": 4}},
        "floor": {"type": "rectangle", "to_world": at @ T().rotate([1, 0, 0], -90).scale(6)},
        "pole": {"type": "cube",
                 "to_world": at @ T().translate([1.5, 1.0, 1.0]).scale([0.04, 1, 0.04])},
        "light": {"type": "spot", "cutoff_angle": 50, "intensity": 60,
                  "to_world": at @ T().look_at(origin=[2.5, 6, 2], target=[0, 0, 0],
                                               up=[0, 1, 0])}})
    vis = {}
    for method in ("raytraced", "multiview"):
        integ = mi.load_dict({"type": "shadowmap", "method": method})
        vis[method] = np.asarray(mi.render(scene, integrator=integ, seed=0))[:, :64, -1]
    miss = misclassified(vis["raytraced"], vis["multiview"])["misclassified"]
    print(offset, integ.resolution, miss)
    assert integ.resolution == 1024
    assert miss <= 0.01


def test_automatic_resolution_respects_the_memory_budget():
    scene = mi.load_dict(default_scene(width=64, height=64, spp=1, light="point"))
    budget_bytes = 6 * 4 * 40 * 40      # six cube faces of 40^2 float32 texels
    integ = mi.load_dict({"type": "shadowmap", "virtual": False,
                          "memory_budget": budget_bytes / 2**20})
    mi.render(scene, integrator=integ, spp=1)
    assert integ.resolution == 40
    assert sum(m.nbytes for m in integ.maps) <= budget_bytes


# ------------------------------------------------------------ memory budget
def test_a_resolution_over_the_budget_is_refused_before_allocating(monkeypatch):
    calls = []
    monkeypatch.setattr(mm_mod, "build_depth_map", lambda *a, **k: calls.append(1))
    scene = mi.load_dict(default_scene(width=8, height=8, spp=1, light="point"))
    integ = mi.load_dict({"type": "shadowmap", "resolution": 4096, "memory_budget": 256})
    with pytest.raises(RuntimeError) as e:
        mi.render(scene, integrator=integ, spp=1)
    msg = root_message(e.value)
    # 6 faces x 4096^2 x 4 bytes = 384 MiB
    assert re.search(r"'resolution' = 4096 would need 384\.0 MiB", msg), msg
    assert "memory_budget = 256 MiB" in msg
    assert calls == [] and integ.maps == [None]   # nothing was built


def test_one_face_over_the_budget_is_refused_at_load_time():
    with pytest.raises(OptionError, match=r"'resolution' = 65536 .* 16384\.0 MiB"):
        parse_options({"resolution": 65536})
    with pytest.raises(RuntimeError, match="memory_budget"):
        mi.load_dict({"type": "shadowmap", "resolution": 512, "memory_budget": 0.5})


@pytest.mark.parametrize("res", [1, 2, 3])
def test_tiny_resolutions_are_finite(res):
    scene = mi.load_dict(default_scene(width=16, height=16, spp=1, light="point"))
    img = np.asarray(mi.render(scene, integrator=mi.load_dict(
        {"type": "shadowmap", "resolution": res}), spp=1))
    assert np.isfinite(img).all()


# ------------------------------------------------- accuracy with defaults
_REFS: dict = {}

#: (scene, method) -> why the target is missed (numbers measured 2026-11-23,
#: the scene's own film, spp 4, automatic resolution).
KNOWN_MISSES = {
    ("directional_mesh", "pcf"): "false shadow 0.51 % > 0.2 %: the pixel footprint widens "
                                 "every shadow edge by about a pixel (Reeves' filter region); "
                                 "acne away from edges is 0.02 %",
    ("cbox_area", "hard"): "misclassified 1.22 %, false shadow 1.05 %: hard shadows from the "
                           "light's centre cannot reproduce the soft reference's penumbra",
    ("cbox_area", "pcf"): "misclassified 1.42 %, false shadow 1.34 %: as for hard (the light "
                          "is treated as its centre)",
    ("contact_hardening", "hard"): "misclassified 2.59 %, false shadow 1.71 %: 22 % of the "
                                   "pixels are penumbra, which a point-light model misses",
    ("contact_hardening", "pcf"): "misclassified 2.66 %, false shadow 1.66 %: as for hard",
}


def _reference(path, scene):
    if path.stem not in _REFS:
        if any(emitter_kind(e) == "area" for e in scene.emitters()):
            vis = converged_visibility(scene, n_light=1024, spp=4, seed=1)
            names = sorted(vis)
            _REFS[path.stem] = np.stack([vis[k] for k in names]), names
        else:
            # environment light (sky_sun): 256 rays per camera sample (a 1-ray AOV is
            # binary noise; see tests/test_methods_on_scenes.py)
            env = any(emitter_kind(e) == "environment" for e in scene.emitters())
            integ = mi.load_dict({"type": "shadowmap", "method": "raytraced",
                                  **({"shadow_rays": 256} if env else {})})
            img = np.asarray(mi.render(scene, integrator=integ, spp=4, seed=1))
            _REFS[path.stem] = np.moveaxis(img[..., 3:], -1, 0), integ.aov_names()
    return _REFS[path.stem]


CASES = [pytest.param(p, m, id=f"{p.stem}-{m}",
                      marks=[pytest.mark.xfail(strict=True, reason=KNOWN_MISSES[(p.stem, m)])]
                      if (p.stem, m) in KNOWN_MISSES else [])
         for p in SCENE_FILES for m in ("hard", "pcf")]


@pytest.mark.parametrize("path, method", CASES)
def test_defaults_meet_the_targets(path, method):
    scene = mi.load_file(str(path))   # the scene's own film
    ref, names = _reference(path, scene)
    integ = mi.load_dict({"type": "shadowmap", "method": method})
    img = np.asarray(mi.render(scene, integrator=integ, spp=4, seed=1))
    order = [integ.aov_names().index(n) for n in names]
    vis = np.moveaxis(img[..., 3:], -1, 0)[order]
    assert np.isfinite(vis).all()
    m = misclassified(ref, vis)
    print(f"{path.stem} {method} (resolution {integ.resolution}): misclassified "
          f"{m['misclassified']:.3%}, false shadow {m['false_shadow']:.3%}")
    assert m["misclassified"] <= 0.01
    assert m["false_shadow"] <= 0.002
