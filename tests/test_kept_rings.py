"""What a virtual map's mark pass builds around a point that kept the receiver biases'
finer level, and ``pcf``'s margin (issue 11's texels): the ring its neighbours' boxes
read only where a neighbour reads that level (``planner._kept_read``); ``pcf``'s region
at that finer level; ``pcf``'s margin the bound of its region at the footprint's level,
with the film's border pixels marked half a footprint farther."""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from mi_shadowmap.metrics import misclassified
from mi_shadowmap.scenes import random_terrain_world
from mi_shadowmap.virtual import planner

from conftest import own_and_widest_marks


def _render(d: dict, method: str) -> tuple:
    """The visibility AOV of a fresh render of ``d`` (4 spp) and its texels built."""
    integ = mi.load_dict({"type": "shadowmap", "method": method, "cache_maps": False})
    img = np.asarray(mi.render(mi.load_dict(d), integrator=integ, spp=4, seed=0))
    return img[..., 3], integ.stats.get("texels_built", 0)


@pytest.mark.parametrize("method", ["pcf", "hard"])
def test_a_kept_point_marks_its_ring_only_where_a_neighbour_reads_its_level(method,
                                                                            monkeypatch):
    """``random_terrain_world(123)`` at 64^2 (sun 2-5 degrees, looking up at a tower):
    of the 203 points that kept the biases' level, 99 have a neighbouring pixel whose
    samples read it (an uncapped centre on their shape, or a centre on another). Only
    they mark the ring (their neighbours' centres with the kernel, ``marks.kept_tiles``;
    ``m + 2 spread`` bounds it); the others mark their own samples' kernels (``m +
    spread`` bounds them, with ``pcf``'s region at their level). Fewer texels than
    every kept point's ring (at 256^2 ``pcf`` 9.45 -> 7.91 texels a film pixel), more
    than none, and the image is bit-identical to the one with every ring: the rings
    left out were read by no lookup (against ``raytraced``: the same pixels
    misclassified). Without the neighbours' rings ``pcf`` and ``hard`` differ from it (2
    and 1 pixels): they are read."""
    d = random_terrain_world(123, width=64, spp=4)
    real = getattr(planner, "_kept_read", None)
    seen = []

    def counted(sensor, centre, kept):
        read = real(sensor, centre, kept)
        dr.eval(read)
        seen.append((int(np.sum(mi.Bool(kept).numpy())), int(np.sum(read.numpy()))))
        return read

    out = {}
    for rule, fn in (("each", counted), ("every", lambda s, c, kept: mi.Bool(kept)),
                     ("none", lambda s, c, kept: mi.Bool(False))):
        # (raising=False: without the rule nothing reads it and the three are the same)
        monkeypatch.setattr(planner, "_kept_read", fn, raising=False)
        out[rule] = _render(d, method)
    monkeypatch.undo()
    ref = _render(d, "raytraced")[0]
    mis = {k: misclassified(ref, v[0])["misclassified"] * ref.size for k, v in out.items()}
    print("kept, read by a neighbour:", seen, "texels:", {k: v[1] for k, v in out.items()},
          "misclassified:", mis)
    kept, read = seen[0]
    assert 0 < read < kept
    assert out["none"][1] < out["each"][1] < out["every"][1]
    assert np.array_equal(out["each"][0], out["every"][0])
    assert mis["each"] == mis["every"]
    assert not np.array_equal(out["none"][0], out["every"][0])


def test_pcf_marks_cover_its_region_at_a_finer_lod_bias(monkeypatch):
    """At ``lod_bias`` -2 a footprint's longer side spans up to 16 texels of its level,
    so ``pcf``'s region reaches ``res_factor 2^(1 - lod_bias)`` = 8 texels from the
    receiver, more than the ``4 res_factor`` its margin held before: under the spot
    light a pixel then read a tile its marks had not built (1 pixel of 4096 differed
    from marks as wide as the lookup's pages), as it does without the film border's
    half footprint (``Method.virtual_footprint``, ``marks._margins``)."""
    own, wide = own_and_widest_marks(monkeypatch, "spot", {"method": "pcf", "lod_bias": -2.0,
                                                           "sampling": "regular"})
    print("pixels that differ:", int(np.sum(own != wide)))
    assert np.array_equal(own, wide)
