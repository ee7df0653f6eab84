"""Virtual maps at defaults on Mitsuba features the other unseen kinds do not make
(``benchmarks/bench_unseen.py --kinds feature``: instances of a shapegroup, an open PLY
mesh light, a strip light, a sun through a room's window, hair-like linear curves, two
lights at one position, a sun along an axis, a thin-lens and an orthographic camera),
against the ray-traced reference."""
from __future__ import annotations

import pathlib
import sys

import mitsuba as mi
import numpy as np
import pytest

from mi_shadowmap.metrics import misclassified

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1] / "benchmarks"))
import bench_unseen  # noqa: E402  (the benchmark's scene generator)

sys.path.pop(0)


def _visibility(d: dict, method: str, seed: int = 0, **props):
    """Every light's visibility AOV of a fresh render of ``d``, and the integrator."""
    integ = mi.load_dict({"type": "shadowmap", "method": method, **props})
    img = np.asarray(mi.render(mi.load_dict(d), integrator=integ, seed=seed))
    return bench_unseen.by_name(img[..., 3:], integ.aov_names()), integ


@pytest.mark.parametrize("seed", range(len(bench_unseen.FEATURE_KINDS)))
@pytest.mark.filterwarnings("ignore:shadowmap. raytraced's shadow rays keep")
def test_feature_kind_at_defaults(seed):
    """Each feature (``seed`` picks it) at 48^2, 4 spp: virtual `hard` loads, renders
    finite visibility, one AOV a light, and misclassifies no more than the reference's own
    seed noise plus 1 % (measured at 48^2, 4 spp: 0.04-2.04 % against noise 0.61-4.60 %;
    at 32^2 the window's room leaks light at its roof's and floor's contact with the walls,
    1.76 % against noise 0.59 %: texels as wide as a 32^2 pixel's footprint put the roof
    within the depth bias of the wall under it; full maps of that density leak too)."""
    d, sub = bench_unseen.random_local_lights("feature", seed, 48, 4)
    assert sub == bench_unseen.FEATURE_KINDS[seed]
    n_lights = len(mi.load_dict(d).emitters())
    assert n_lights == (2 if sub == "twin lights" else 1)
    rays = {"shadow_rays": 16} if sub in ("mesh light", "strip light") else {}
    ref, _ = _visibility(d, "raytraced", **rays)
    noise = misclassified(ref, _visibility(d, "raytraced", 5, **rays)[0])["misclassified"]
    vis, integ = _visibility(d, "hard")
    assert vis.shape[-1] == n_lights
    assert np.isfinite(vis).all()
    assert integ.stats["texels_built"] > 0
    assert misclassified(ref, vis)["misclassified"] <= noise + 0.01, sub


def test_bench_unseen_runs_the_feature_kind_virtual_only():
    """``--virtual-only``: the local kinds' table without full maps ('-' in their
    columns)."""
    from test_benchmarks import run_bench
    out = run_bench("bench_unseen.py", "--kinds", "feature", "--seeds", "1", "--image",
                    "16", "--texel-image", "32", "--spp", "1", "--methods", "hard",
                    "--virtual-only")
    rows = [r.split("|") for r in out.splitlines() if r.startswith("| feature |")]
    assert [r[3].strip() for r in rows] == ["instances"]
    assert all(r[8].strip() == r[9].strip() == "-" for r in rows)   # no full maps
    assert all(r[10].strip() == "0" for r in rows)                  # no non-finite value


def test_bench_unseen_scores_each_light_against_its_own_reference_channel():
    """The bench renders the reference and each method on loads of their own, and
    Mitsuba's emitter order is not the dict's (the shapes' lights come after the others
    here; two shape lights of one type come in either order from one load to the next):
    its channels are put in the order of the AOVs' names, so channel k is one light in
    every render. Here the lamp (AOV ``vis_emitter``, Mitsuba's id of a nested emitter;
    it faces away from everything: visibility 0) is the scene's second emitter and the
    sun (``vis_z_sun``) its first."""
    d = {"type": "scene",
         "sensor": bench_unseen.camera([0, 6, 8], [0, 0, 0], 16, 16, 1),
         "ground": {"type": "rectangle", "to_world": bench_unseen.T().scale(6)
                    .rotate([1, 0, 0], -90)},
         "a_lamp": {"type": "rectangle", "emitter": {"type": "area", "radiance": 1.0},
                    "to_world": bench_unseen.T().translate([0, 3, 0])
                    .rotate([1, 0, 0], -90).scale(0.3)},
         "z_sun": bench_unseen._sun([0.2, -1, 0.3])}
    scene = mi.load_dict(d)
    assert [e.get_shape() is not None for e in scene.emitters()] == [False, True]
    vis, integ, _ = bench_unseen._render(scene, {"method": "hard"}, 0)
    assert integ.aov_names() == ["vis_z_sun", "vis_emitter"]
    assert np.all(vis[..., 0] == 0)                 # the lamp
    assert np.mean(vis[..., 1] == 1) > 0.5          # the sun on the ground (83 %)
