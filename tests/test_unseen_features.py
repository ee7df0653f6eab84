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
    return img[..., 3:], integ


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
