"""A point that kept the receiver biases' finer level marks the band its lookups read on
its tangent plane at that level (``marks.kept_tiles``: its samples' parallelogram, and
its neighbours' centres where a neighbour reads the level, each with the method's
kernel), not the box around it (issue 11's texels): fewer texels, the same image."""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from mi_shadowmap.metrics import misclassified
from mi_shadowmap.scenes import random_terrain_world
from mi_shadowmap.virtual import planner


def _render(d: dict, method: str, spp: int = 4) -> tuple:
    """The visibility AOV of a fresh render of ``d`` and its texels built."""
    integ = mi.load_dict({"type": "shadowmap", "method": method, "cache_maps": False})
    img = np.asarray(mi.render(mi.load_dict(d), integrator=integ, spp=spp, seed=0))
    return img[..., 3], integ.stats.get("texels_built", 0)


@pytest.mark.parametrize("method", ["pcf", "hard"])
def test_kept_points_mark_their_bands_not_their_boxes(method, monkeypatch):
    """``random_terrain_world(123)`` at 64^2 (sun 2-5 degrees: footprints long and thin
    in the map): the kept points' bands build fewer texels than their boxes (``m +
    spread``, ``m + 2 spread`` where a neighbour reads the level: what a point whose
    footprint's sides are not finite still marks), measured ``hard`` 21.5 -> 15.0 and
    ``pcf`` 30.3 -> 27.7 texels a film pixel; the image is bit-identical to the boxes',
    and it misclassifies as many pixels against ``raytraced`` as they and the marks as
    wide as a lookup's 2 x 2 pages (margin 14) do (``pcf``'s differs from the widest
    marks' in a few pixels, as the boxes' does)."""
    d = random_terrain_world(123, width=64, spp=4)
    bands = _render(d, method)
    with monkeypatch.context() as m:
        # sides not finite: every kept point marks its box (raising=False: without the
        # bands there is nothing to patch, and the two are the same)
        m.setattr(planner, "kept_axes", lambda *a: (mi.Point2f(dr.nan), mi.Point2f(dr.nan)),
                  raising=False)
        boxes = _render(d, method)
    with monkeypatch.context() as m:
        m.setattr(planner, "virtual_margin_of", lambda record, opts, view: 14.0)
        widest = _render(d, method)
    ref = _render(d, "raytraced")[0]
    mis = [misclassified(ref, img)["misclassified"] * ref.size for img, _ in
           (bands, boxes, widest)]
    print(f"{method}: texels a pixel, bands {bands[1] / 64 ** 2:.2f}, boxes "
          f"{boxes[1] / 64 ** 2:.2f}, widest {widest[1] / 64 ** 2:.2f}; misclassified {mis}; "
          f"pixels unlike the widest marks' {int(np.sum(bands[0] != widest[0]))}")
    assert bands[1] < 0.95 * boxes[1]
    assert np.array_equal(bands[0], boxes[0])
    assert mis[0] == mis[1] == mis[2]


@pytest.mark.parametrize("size", [(64, 64), (37, 21), (8, 100)])
def test_host_lane_pixels_are_the_mark_pass_camera_pixels(size):
    """``marks._lane_pixels`` (which film-border pixels' kept points widen their bands on
    the host) gives each camera-hit lane the pixel ``marks.camera_pixels`` gives it in
    Dr.Jit (both through ``light_views.block_pixels``), filler lanes of a crop that is not
    a multiple of the blocks included."""
    from mi_shadowmap.virtual.marks import _lane_pixels, camera_pixels
    w, h = size
    sensor = mi.load_dict({"type": "perspective",
                           "film": {"type": "hdrfilm", "width": w, "height": h}})
    word = np.asarray(camera_pixels(sensor).numpy(), np.int64)
    x, y = _lane_pixels(w, h)
    assert len(x) == len(word) >= w * h
    assert np.array_equal(x + 65536 * y, word)
    assert x.max() == w - 1 and y.max() == h - 1
