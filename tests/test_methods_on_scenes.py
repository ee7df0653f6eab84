"""Every shadow-map method on every scene of scenes_xml/, against the right reference.

Issue 3's acceptance: at 1024^2 maps, each method misclassifies (threshold
0.5) at most 3 % of the visibility pixels. The ``-virtualTrue`` cases read
virtual maps (issue 11) at their defaults instead of 1024^2 full maps. Each (scene, method) case asserts
its own bound, :data:`MEASURED` (the value measured on 2026-11-29) plus a
margin of 50 % or 0.1 percentage points, whichever is larger, so that a
regression shows long before 3 %; a method or scene without a measured value
(a new one) is held to the issue's 3 %. The reference is the ray-traced
visibility for scenes of delta lights (same camera samples: same seed and
spp) and the converged soft-shadow reference (1024 stratified light
positions, :func:`mi_shadowmap.reference.converged_visibility`) for scenes
with area lights, whose wide penumbrae make a 1-ray reference disagree with
itself on ~5 % of pixels by noise alone.
"""
import mitsuba as mi
import numpy as np
import pytest

from mi_shadowmap import metrics
from mi_shadowmap.light_views import emitter_kind
from mi_shadowmap.options import MAP_METHODS
from mi_shadowmap.reference import converged_visibility

from conftest import SCENE_FILES, VIRTUAL_SCENES, render_np

SPP = 4
VARIANTS = {  # method -> extra settings checked besides the defaults
    "bilinear": [{"kernel": 2}, {"kernel": 4}, {"kernel": 2, "virtual": True}],
    "mdsm": [{"depths": 2}, {"depths": 3}],
    # virtual maps (issue 11) at their default virtual resolution and lod_bias
    **{m: [{}, {"virtual": True}] for m in ("hard", "pcf", "pcss", "second_depth")},
}
CASES = [(m, p) for m in MAP_METHODS for p in VARIANTS.get(m, [{}])]
#: Misclassified fractions measured on 2026-11-29 (64^2 images, 4 spp, seed 0; multiview,
#: the virtual cases and the issue-11 scenes large_world and far_point on 2026-11-30),
#: scene -> {case id: value}; the case id is the method plus its settings.
MEASURED = {
    "cbox_area": {"hard": .0112, "pcss": .0100, "pcf": .0156, "bilinear-kernel2": .0107,
        "bilinear-kernel4": .0166, "second_depth": .0144, "mdsm-depths2": .0110,
        "mdsm-depths3": .0115, "multiview": .0002, "hard-virtualTrue": .0120,
        "pcss-virtualTrue": .0120, "pcf-virtualTrue": .0151,
        "bilinear-kernel2-virtualTrue": .0127, "second_depth-virtualTrue": .0168},
    "contact_hardening": {"hard": .0212, "pcss": .0220, "pcf": .0220,
        "bilinear-kernel2": .0208, "bilinear-kernel4": .0215, "second_depth": .0215,
        "mdsm-depths2": .0220, "mdsm-depths3": .0210, "multiview": .0098,
        "hard-virtualTrue": .0200, "pcss-virtualTrue": .0215, "pcf-virtualTrue": .0198,
        "bilinear-kernel2-virtualTrue": .0203, "second_depth-virtualTrue": .0205},
    "directional_mesh": {"hard": .0022, "pcss": .0022, "pcf": .0168,
        "bilinear-kernel2": .0042, "bilinear-kernel4": .0125, "second_depth": .0044,
        "mdsm-depths2": .0059, "mdsm-depths3": .0085, "multiview": .0020,
        "hard-virtualTrue": .0076, "pcss-virtualTrue": .0076, "pcf-virtualTrue": .0154,
        "bilinear-kernel2-virtualTrue": .0107, "second_depth-virtualTrue": .0088},
    # far_point's virtual cases re-measured on 2026-12-01, after its layout became one
    # face aimed at the scene (virtual.layout_for, box_view): 0.24 -> 0.42 % for pcf, 0.32
    # -> 0.37 % for hard, 0.49 -> 0.37 % for second_depth, 0.29 -> 0.24 % for bilinear,
    # all within 7 pixels of 4096; at 128^2 and 256^2 equal or lower (pcf 0.20 -> 0.19 %,
    # 0.08 -> 0.08 %; hard 0.23 -> 0.16 %, 0.09 -> 0.07 %)
    "far_point": {"hard": .0312, "hard-virtualTrue": .0037, "pcss": .0312,
        "pcss-virtualTrue": .0037, "pcf": .0312, "pcf-virtualTrue": .0042,
        "bilinear-kernel2": .0312, "bilinear-kernel4": .0322,
        "bilinear-kernel2-virtualTrue": .0024, "second_depth": .0312,
        "second_depth-virtualTrue": .0037, "mdsm-depths2": .0312, "mdsm-depths3": .0312,
        "evsm": .0312, "msm": .0393, "multiview": .0312, "vsm": .0312},
    "large_world": {"hard": .0254, "hard-virtualTrue": .0098, "pcss": .0254,
        "pcss-virtualTrue": .0098, "pcf": .0269, "pcf-virtualTrue": .0146,
        "bilinear-kernel2": .0266, "bilinear-kernel4": .0308,
        "bilinear-kernel2-virtualTrue": .0144, "second_depth": .0391,
        "second_depth-virtualTrue": .0120, "mdsm-depths2": .0288, "mdsm-depths3": .0281,
        "evsm": .0261, "msm": .0261, "multiview": .0251, "vsm": .0264},
    "room_two_points": {"hard": .0009, "pcss": .0009, "pcf": .0051,
        "bilinear-kernel2": .0013, "bilinear-kernel4": .0028, "second_depth": .0010,
        "mdsm-depths2": .0016, "mdsm-depths3": .0027, "multiview": .0005,
        "hard-virtualTrue": .0038, "pcss-virtualTrue": .0038, "pcf-virtualTrue": .0055,
        "bilinear-kernel2-virtualTrue": .0050, "second_depth-virtualTrue": .0081},
    # sky_sun's virtual cases re-measured on 2026-12-03, when the environment's regions
    # became faces of one virtual map (full maps before): hard 0.27 -> 0.42 %, pcss
    # 0.29 -> 0.34 %, pcf 0.42 -> 0.46 %, bilinear 0.34 -> 0.42 %, second_depth 0.27 ->
    # 0.37 % (3-6 pixels of 4096). At 64^2 a region's pages have a pixel's density, coarser
    # than 1024^2 full maps, and at 4 spp a hard edge's pixels keep one texel's answer:
    # hard over 4 seeds 0.32-0.42 % against 0.15-0.29 %, one level finer (lod_bias -1.5)
    # 0.17-0.37 %, as full maps; at 16 spp 0.22 against 0.20 %.
    "sky_sun": {"hard": .0032, "pcss": .0020, "pcf": .0037, "bilinear-kernel2": .0032,
        "bilinear-kernel4": .0029, "second_depth": .0027, "mdsm-depths2": .0032,
        "mdsm-depths3": .0032, "hard-virtualTrue": .0042, "pcss-virtualTrue": .0034,
        "pcf-virtualTrue": .0046, "bilinear-kernel2-virtualTrue": .0042,
        "second_depth-virtualTrue": .0037},
    "spectral_point": {"hard": .0002, "pcss": .0002, "pcf": .0032,
        "bilinear-kernel2": .0002, "bilinear-kernel4": .0012, "second_depth": .0007,
        "mdsm-depths2": .0005, "mdsm-depths3": .0010, "multiview": .0000,
        "hard-virtualTrue": .0022, "pcss-virtualTrue": .0022, "pcf-virtualTrue": .0027,
        "bilinear-kernel2-virtualTrue": .0024, "second_depth-virtualTrue": .0027},
    "spot_sphere_box": {"hard": .0010, "pcss": .0010, "pcf": .0027,
        "bilinear-kernel2": .0015, "bilinear-kernel4": .0037, "second_depth": .0015,
        "mdsm-depths2": .0012, "mdsm-depths3": .0024, "multiview": .0002,
        "hard-virtualTrue": .0032, "pcss-virtualTrue": .0032, "pcf-virtualTrue": .0042,
        "bilinear-kernel2-virtualTrue": .0037, "second_depth-virtualTrue": .0029},
}


def case_id(method, params):
    return method + "".join(f"-{k}{v}" for k, v in params.items())


def bound(scene, method, params) -> float:
    """The misclassified bound of a case: measured + max(50 %, 0.1 points), <= 3 % (the
    issue-11 scenes, :data:`conftest.VIRTUAL_SCENES`, where full maps lose the shadows by
    design: measured + 20 %, as a regression guard)."""
    m = MEASURED.get(scene, {}).get(case_id(method, params))
    if scene in VIRTUAL_SCENES and m is not None:
        return 1.2 * m + 0.001
    return 0.03 if m is None else min(max(1.5 * m, m + 0.001), 0.03)
_REFS = {}


def reference(path):
    if path not in _REFS:
        scene = mi.load_file(str(path), width=64, height=64)
        if any(emitter_kind(e) == "area" for e in scene.emitters()):
            ref = converged_visibility(scene, n_light=1024, spp=SPP, seed=0)
        elif any(emitter_kind(e) == "environment" for e in scene.emitters()):
            # Environment light (sky_sun): a shadow-map AOV is the fraction of the
            # emitter's light arriving unoccluded (mi_shadowmap.environment), which a
            # 1-ray reference only gives as binary noise: 256 rays per camera sample.
            _, ref = render_np(scene, {"type": "shadowmap", "method": "raytraced",
                                       "shadow_rays": 256}, spp=SPP, seed=0)
        else:
            _, ref = render_np(scene, {"type": "shadowmap", "method": "raytraced"},
                               spp=SPP, seed=0)
        _REFS[path] = (scene, ref)
    return _REFS[path]


@pytest.mark.parametrize("method, params", CASES, ids=[case_id(m, p) for m, p in CASES])
@pytest.mark.parametrize("path", SCENE_FILES, ids=lambda p: p.stem)
def test_misclassified_within_the_measured_bound(path, method, params):
    scene, ref = reference(path)
    res = {} if params.get("virtual") else {"resolution": 1024}
    _, vis = render_np(scene, {"type": "shadowmap", "method": method, **res, **params},
                       spp=SPP, seed=0)
    assert sorted(vis) == sorted(ref)
    r = np.stack([ref[k] for k in sorted(ref)])
    v = np.stack([vis[k] for k in sorted(vis)])
    assert np.isfinite(v).all() and v.min() >= 0 and v.max() <= 1
    m = metrics.misclassified(r, v)
    limit = bound(path.stem, method, params)
    print(f"{path.stem} {method} {params}: misclassified {m['misclassified']:.2%} "
          f"(false shadow {m['false_shadow']:.2%}, false lit {m['false_lit']:.2%}; "
          f"bound {limit:.2%})")
    assert m["misclassified"] <= limit
