"""``pcss`` on virtual maps under a light with extent: filter kernels as wide as the
light's penumbra (``filters/pcss.py``'s ``_light_width_cap``) read the coarser levels this
frame's marks built under their point (``_built_beyond``, ``VirtualShadowMap.tile_marked``),
and the mark pass builds no level for them."""
from __future__ import annotations

import pathlib
import sys

import drjit as dr
import mitsuba as mi
import numpy as np

from test_virtual import _built

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1] / "benchmarks"))
import bench_unseen  # noqa: E402  (the benchmark's scene generator)

sys.path.pop(0)


def _render(size: int, light_width_cap: bool, monkeypatch):
    """``pcss`` at defaults on ``random_local_lights('area', 7)`` (a disk light about 4
    wide), ``size``^2, 1 spp, a first frame: the integrator and the image."""
    import mi_shadowmap
    import mi_shadowmap.filters.pcss as pcss_mod
    monkeypatch.setattr(pcss_mod, "LIGHT_WIDTH_CAP", light_width_cap)
    mi_shadowmap.clear_caches()
    d, drawn = bench_unseen.random_local_lights("area", 7, size, 1)
    assert drawn == "disk large"
    integ = mi.load_dict({"type": "shadowmap", "method": "pcss"})
    img = np.asarray(mi.render(mi.load_dict(d), integrator=integ, seed=0))
    return integ, img


def test_a_light_wide_kernel_costs_no_texels(monkeypatch):
    """The light-width cap changes the image (the penumbra's kernels read coarser levels)
    and builds exactly the texels without it: the levels it reads are those the frame
    built for other points (a mark pass building coarser levels for it around every
    point cost every area light's ``pcss`` 10-25 % more texels, per point 8-23 %,
    ``wip/pcss-light-cap-51H``, ``wip/pcss-light-levels-51I``)."""
    on, img_on = _render(64, True, monkeypatch)
    off, img_off = _render(64, False, monkeypatch)
    changed = np.mean(np.any(img_on != img_off, axis=-1))
    print(f"texels {on.stats.texels_built} / {off.stats.texels_built}, pixels changed "
          f"{changed:.1%}")
    assert on.stats.texels_built == off.stats.texels_built
    assert changed > 0.01


def test_tile_marked_is_the_store_s_record():
    """``VirtualShadowMap.tile_marked`` (what ``_built_beyond`` asks before a kernel reads a
    coarser level) says, at every camera point and every level from its own to 4 coarser,
    what the store's records say: the page is in the table and its tile among the frame's
    marked tiles. Both answers occur."""
    from mi_shadowmap import virtual
    from mi_shadowmap.virtual import marks
    d, _ = bench_unseen.random_local_lights("area", 7, 64, 1)
    scene = mi.load_dict(d)
    integ = mi.load_dict({"type": "shadowmap", "method": "pcss"})
    mi.render(scene, integrator=integ, spp=1)
    vmap = integ.maps[0]
    lay = vmap.layout
    si, dp_dx, dp_dy, valid = virtual.camera_hits(scene, scene.sensors()[0])
    face, uv64, act, level = marks.marked_points(marks.Marker(lay, -0.5), si, dp_dx,
                                                 dp_dy, valid)[:4]
    lanes = np.flatnonzero(act.numpy())
    faces = np.broadcast_to(np.asarray(face.numpy()).ravel(), act.numpy().shape)[lanes]
    uv = uv64.numpy().T[lanes]
    seen = set()
    for k in range(5):
        lv = dr.minimum(level + k, lay.coarsest)
        got = vmap.tile_marked(face, uv64, lv, act).numpy()[lanes]
        want = _built(vmap, faces, lv.numpy()[lanes].astype(np.int64), uv)
        np.testing.assert_array_equal(got, want, err_msg=f"{k} levels coarser")
        seen.update(np.unique(got).tolist())
    assert seen == {False, True}


def test_a_camera_moved_and_put_back_reads_the_coarser_levels_as_afresh():
    """The coarser levels a kernel beyond the face-width cap reads are those whose tile
    under its point *this frame's* marks built (``tile_marked`` reads the frame's page
    table): a camera moved and put back renders what a fresh integrator renders there,
    whatever tiles the moved frame left in the page cache. (Asking the store's records
    instead, every tile any frame built, this put-back differed from the fresh render
    in 4 pixels: those kernels read a level whose tile this frame did not mark, so its
    taps fell back to the coarsest level.)"""
    import mi_shadowmap
    d, drawn = bench_unseen.random_local_lights("area", 7, 64, 1)
    assert drawn == "disk large"
    scene = mi.load_dict(d)
    params = mi.traverse(scene)
    key = next(k for k in params.keys() if k.endswith("to_world")
               and isinstance(params.properties[k][2], mi.Sensor))
    start = mi.ScalarTransform4f(params[key].matrix.numpy()[..., 0])

    def render(integ):
        return np.asarray(mi.render(scene, integrator=integ, spp=1, seed=0))

    mi_shadowmap.clear_caches()
    fresh = render(mi.load_dict({"type": "shadowmap", "method": "pcss"}))
    mi_shadowmap.clear_caches()
    integ = mi.load_dict({"type": "shadowmap", "method": "pcss"})
    render(integ)
    params[key] = mi.ScalarTransform4f().translate([2.0, 1.0, 0.0]) @ start
    params.update()
    render(integ)
    params[key] = start
    params.update()
    again = render(integ)
    assert integ.stats["pages_reused"] > 0
    differ = int(np.sum(np.any(again != fresh, axis=-1)))
    print(f"{differ} pixels differ from the fresh render")
    assert differ == 0
