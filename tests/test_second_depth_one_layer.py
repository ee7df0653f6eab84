"""``second_depth``'s virtual pages cast its second depths alone
(:func:`mi_shadowmap.methods.casts_first_depth`): its lookups read no first depth
(Wang & Molnar's map holds the second surface only), so a page's texel casts one depth,
not two, and ``texels_built`` counts one. A method that reads both layers keeps both."""
from __future__ import annotations

import dataclasses

import mitsuba as mi
import numpy as np
import pytest

import mi_shadowmap
from mi_shadowmap import harness, methods, virtual
from mi_shadowmap.depth_maps import second_depth_layer
from mi_shadowmap.scenes import default_scene, random_terrain_world

from conftest import SCENES, error_chain

T = mi.ScalarTransform4f


def _render(scene, spp=4, **props):
    integ = mi.load_dict({"type": "shadowmap", **props})
    img = np.asarray(mi.render(scene, integrator=integ, spp=spp, seed=0))
    assert np.isfinite(img).all()
    return img[..., 3], integ


def _copy(name: str, of: str, **changes):
    """A user method that is ``of`` with ``changes`` (registered; unregister after)."""
    return methods.add(dataclasses.replace(methods.get(of), name=name, builtin=False,
                                           **changes))


def test_second_depth_pages_cast_one_depth_a_texel_and_render_as_with_both():
    """A rippled terrain with towers under a sun (``random_terrain_world(22)``, the issue's
    worst ``second_depth`` world, 9.25 texels a pixel at 256^2 counted with both depths),
    64^2: the same method with its first depths cast too (a user copy that reads them,
    ``reads_depth`` True) renders the same image bit for bit, and casts twice the
    texels. Before, both cast both (18.8 texels a pixel each); now ``second_depth`` 9.4.
    Its stores hold no first-depth pool (nothing reads it), the copy's both."""
    d = random_terrain_world(22, width=64, spp=4)
    _copy("second_depth_both_layers", "second_depth", reads_depth=True)
    try:
        both, integ_both = _render(mi.load_dict(d), method="second_depth_both_layers",
                                   cache_maps=False)
    finally:
        mi_shadowmap.unregister_method("second_depth_both_layers")
    one, integ = _render(mi.load_dict(d), method="second_depth", cache_maps=False)
    texels, texels_both = integ.stats["texels_built"], integ_both.stats["texels_built"]
    print(f"texels a pixel: second depths alone {texels / 64 ** 2:.2f}, both "
          f"{texels_both / 64 ** 2:.2f}; {int(np.sum(one != both))} pixels differ")
    assert np.array_equal(one, both)
    assert 2 * texels == texels_both > 0
    stores = [m.store for m in integ.maps if hasattr(m, "store")]
    assert stores
    for st in stores:
        assert tuple(st.pools) == ("second_depth",)
        assert np.isfinite(st.pools["second_depth"].numpy()).any()
    for st in (m.store for m in integ_both.maps if hasattr(m, "store")):
        assert tuple(st.pools) == ("depth", "second_depth")


def test_a_method_reading_both_layers_keeps_its_first_depths():
    """A user method registered with the ``second_depth`` layer whose lookup reads the
    first depths (here ``hard``'s compare) gets them cast, in stores of its own
    (:func:`~mi_shadowmap.methods.page_layers` lists ``depth`` for it): its image
    is ``hard``'s, bit for bit, also rendered after ``second_depth`` on the same scene
    (whose stores hold no first depth), and it casts both depths a texel."""
    virtual.PAGE_CACHE.clear()
    scene = mi.load_file(str(SCENES / "spot_sphere_box.xml"), width=64, height=64)
    _copy("hard_with_second", "hard", layers={"second_depth": second_depth_layer})
    try:
        _render(scene, method="second_depth")
        mixed, integ = _render(scene, method="hard_with_second")
    finally:
        mi_shadowmap.unregister_method("hard_with_second")
    hard, integ_hard = _render(scene, method="hard")
    print(f"{int(np.sum(mixed != hard))} pixels differ; texels {integ.stats['texels_built']}"
          f" against hard's {integ_hard.stats['texels_built']}")
    assert np.array_equal(mixed, hard)
    virtual.PAGE_CACHE.clear()
    _, integ_hard = _render(scene, method="hard", cache_maps=False)
    _, integ = _render(scene, method="second_depth", cache_maps=False)
    assert integ.stats["texels_built"] > 0
    _copy("hard_with_second", "hard", layers={"second_depth": second_depth_layer})
    try:
        _, integ_mixed = _render(scene, method="hard_with_second", cache_maps=False)
    finally:
        mi_shadowmap.unregister_method("hard_with_second")
    assert integ_mixed.stats["texels_built"] == 2 * integ_hard.stats["texels_built"]


def test_second_depth_camera_move_casts_second_depths_and_renders_as_afresh():
    """Two point lights (``room_two_points``: their tiles cast together in one kernel),
    64^2: after a camera move the new tiles get their second depths (the moved frame is
    the frame a fresh integrator renders there, bit for bit), a move casts at most a
    quarter of the first frame's texels, and the moves after the first compile nothing."""
    import drjit as dr
    virtual.PAGE_CACHE.clear()
    scene = mi.load_file(str(SCENES / "room_two_points.xml"), width=64, height=64)
    integ = mi.load_dict({"type": "shadowmap", "method": "second_depth"})
    params = mi.traverse(scene)
    key = next(k for k in params.keys() if k.endswith("to_world")
               and isinstance(params.properties[k][2], mi.Sensor))
    start = T(params[key].matrix.numpy()[..., 0])
    mi.render(scene, integrator=integ, spp=2, seed=0)
    first = integ.stats["texels_built"]
    built, compiled = [], []
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        dr.kernel_history()
        seen = set()
        for j in range(3):
            params[key] = start @ T().translate([0.05 * (j + 1), 0, 0]) \
                @ T().rotate([0, 1, 0], 1.0 * (j + 1))
            params.update()
            dr.kernel_history()
            moved = np.asarray(mi.render(scene, integrator=integ, spp=2, seed=0))[..., 3]
            hashes = {k["hash"] for k in dr.kernel_history()
                      if k["type"] == dr.KernelType.JIT}
            compiled.append(len(hashes - seen))
            seen |= hashes
            built.append(integ.stats["texels_built"])
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    fresh, _ = _render(scene, spp=2, method="second_depth", cache_maps=False)
    print(f"first frame {first} texels; moves built {built}, compiled {compiled}; "
          f"{int(np.sum(moved != fresh))} pixels differ from a fresh render")
    assert 0 < max(built) and all(b <= 0.25 * first for b in built)
    assert compiled[1:] == [0, 0]
    assert np.array_equal(moved, fresh)


def test_the_harness_does_not_give_hard_second_depths_virtual_map():
    """``harness.prepare_maps`` / ``emitter_maps`` with ``virtual=True`` merged ``hard``'s
    map into ``second_depth``'s (a virtual map was "the same map" whatever its pages):
    ``hard`` then got pages whose first depths are not cast (NaN). Now they are two maps,
    ``hard``'s with its first depths, and ``prepare_maps`` refuses to give one map."""
    scene = mi.load_dict(default_scene(width=32, height=32, spp=2))
    maps = harness.emitter_maps(scene, ["hard", "second_depth"], virtual=True)
    assert sorted(m.methods[0] for m in maps) == ["hard", "second_depth"]
    st = next(m.map.store for m in maps if m.methods == ["hard"])
    depth = st.pools["depth"].numpy()[:st.next_slot * st.texels_per_page]
    assert not np.isnan(depth).any()
    with pytest.raises(ValueError, match="different maps.*second depths only"):
        harness.prepare_maps(scene, ["hard", "second_depth"], virtual=True)


def _second_hard(smap, lk, opts, active=True):
    """A user lookup that reads the second depths alone: ``hard``'s nearest-texel compare,
    with the second depth (Wang & Molnar's compare without their virtual samples)."""
    import drjit as dr
    from mi_shadowmap.filters.common import receiver
    r = receiver(smap, lk, opts)
    z = dr.gather(mi.Float, smap.second_depth, smap.texel_index(r.face, r.uv), active & r.inside)
    return dr.select(~r.inside | (r.depth <= z), 1.0, 0.0)


def test_second_depth_page_bytes_and_its_budget_hold_one_depth_a_texel():
    """``second_depth``'s pages hold no first-depth pool, so a page costs ``hard``'s bytes
    (one float32 a texel; 2 before) and ``memory_budget`` holds twice the pages it held.
    Terrain 22 at 64^2 marks 77 pages of 32^2: under 0.5 MiB (128 pages of one depth, 64 of
    two) it rendered degraded before (a warning naming the map; the image changed), and
    now renders as without a budget, with no warning."""
    import warnings
    d = random_terrain_world(22, width=64, spp=4)
    free, _ = _render(mi.load_dict(d), method="second_depth", cache_maps=False)
    with warnings.catch_warnings():
        warnings.simplefilter("error")      # (the degraded map's warning)
        tight, integ = _render(mi.load_dict(d), method="second_depth", cache_maps=False,
                               memory_budget=0.5)
    st = next(m.store for m in integ.maps if hasattr(m, "store"))
    print(f"pages {st.n_pages}, capacity {st.capacity}, {st.nbytes} bytes")
    assert st.nbytes <= 0.5 * 2 ** 20 and st.nbytes == st.capacity * 32 ** 2 * 4
    assert np.array_equal(free, tight)
    opts = {m: mi_shadowmap.options.parse_options({"method": m})
            for m in ("hard", "second_depth")}
    assert virtual.page_bytes(opts["second_depth"]) == virtual.page_bytes(opts["hard"]) \
        == opts["hard"].page_size ** 2 * 4


@pytest.mark.parametrize("virtual_maps", [True, False])
def test_a_user_method_that_reads_second_depths_alone(virtual_maps):
    """``register_method(..., reads_depth=False)``: a user's lookup that reads the second
    depths alone (``_second_hard``) gets maps without first depths (virtual: no ``depth``
    pool, one depth a texel cast; full: the ``second_depth`` layer alone, half the bytes
    and texels), and renders bit for bit as the same lookup registered with
    ``reads_depth=True`` (both layers). A lookup that reads ``smap.depth`` anyway
    (``hard``'s) fails as it is traced, not with a wrong image: a MethodError naming it
    and ``reads_depth``. spot_sphere_box, 32^2."""
    scene = mi.load_file(str(SCENES / "spot_sphere_box.xml"), width=32, height=32)
    layers = {"second_depth": second_depth_layer}
    kinds = {"second_hard_one": False, "second_hard_both": True}
    for name, reads in kinds.items():
        mi_shadowmap.register_method(name, _second_hard, layers=layers, virtual=True,
                                     reads_depth=reads)
    mi_shadowmap.register_method("hard_misread", methods.get("hard").lookup, layers=layers,
                                 virtual=True, reads_depth=False)
    try:
        out = {name: _render(scene, method=name, virtual=virtual_maps, cache_maps=False)
               for name in kinds}
        with pytest.raises(Exception) as err:
            _render(scene, method="hard_misread", virtual=virtual_maps, cache_maps=False)
    finally:
        for name in (*kinds, "hard_misread"):
            mi_shadowmap.unregister_method(name)
    chain = [str(e) for e in error_chain(err.value)]   # (mi.render wraps it)
    assert any("'hard_misread' was registered with reads_depth=False" in c for c in chain)
    (one, integ), (both, integ_both) = out["second_hard_one"], out["second_hard_both"]
    assert 0.2 < one.mean() < 0.8
    assert np.array_equal(one, both)
    assert 2 * integ.stats["texels_built"] == integ_both.stats["texels_built"] > 0
    bytes_one = sum(m.nbytes for m in integ.maps if m is not None)
    assert 2 * bytes_one == sum(m.nbytes for m in integ_both.maps if m is not None)
    smap = next(m for m in integ.maps if m is not None)
    assert smap.layers() == ["second_depth"]
    if not virtual_maps:
        assert not smap.has_depth and smap.to_numpy("second_depth").size > 0


def test_reads_depth_is_validated_by_name():
    """``reads_depth`` must be a bool, and False needs the ``second_depth`` layer (the
    maps then hold second depths alone): both refused naming ``reads_depth``."""
    with pytest.raises(methods.MethodError, match="reads_depth must be True or False"):
        mi_shadowmap.register_method("bad_reads", _second_hard, reads_depth="no",
                                     layers={"second_depth": second_depth_layer})
    with pytest.raises(methods.MethodError, match="reads_depth=False.*'second_depth' layer"):
        mi_shadowmap.register_method("bad_reads", _second_hard, reads_depth=False)
    assert "bad_reads" not in mi_shadowmap.methods.METHODS


def test_second_depth_full_maps_hold_no_first_depth_and_the_harness_merges_them():
    """``virtual=false``: ``second_depth``'s map builds its second depths alone (half the
    texels and bytes of both), renders as before, and the harness still gives ``hard`` and
    ``second_depth`` one map per emitter, in either order, with ``hard``'s first depths
    (the map without them is the same view and resolution; ``hard``'s depth is added)."""
    scene = mi.load_dict(default_scene(width=32, height=32, spp=2))
    hard = harness.prepare_maps(scene, ["hard"])
    alone = harness.prepare_maps(scene, ["second_depth"])
    assert alone[0].layers() == ["second_depth"] and not alone[0].has_depth
    res = alone[0].resolution
    assert harness.describe_map(alone[0]).endswith(f" of {res}^2, second depths only")
    assert "second depths" not in harness.describe_map(hard[0])
    with pytest.raises(KeyError, match="not built"):
        alone[0].to_numpy("depth")
    for order in (["hard", "second_depth"], ["second_depth", "hard"]):
        both = harness.prepare_maps(scene, order)
        assert both[0].layers() == ["depth", "second_depth"]
        assert np.array_equal(both[0].to_numpy("depth"), hard[0].to_numpy("depth"))
        assert np.array_equal(both[0].to_numpy("second_depth"),
                              alone[0].to_numpy("second_depth"))


def test_a_layer_built_from_the_missing_first_depth_is_an_error_naming_it():
    """A user method registered with ``reads_depth=False`` whose full maps hold a layer
    built from the first depth (``pcss``'s ``pcss_near``: the nearest depth of each face,
    a reduction of ``smap.depth``) built it from the empty array: an empty layer, and the
    render went on without an error, as its lookup (``_second_hard``) does not read it
    (a lookup that did would have been told it read ``smap.depth``). Now it is a
    MethodError naming the method, the layer and ``reads_depth``; with ``reads_depth``
    True the same method renders, its ``pcss_near`` one value a face."""
    scene = mi.load_file(str(SCENES / "spot_sphere_box.xml"), width=32, height=32)
    layers = {"second_depth": second_depth_layer, **methods.get("pcss").layers}
    for name, reads in (("near_misread", False), ("near_both", True)):
        mi_shadowmap.register_method(name, _second_hard, layers=layers, reads_depth=reads)
    try:
        _, integ = _render(scene, method="near_both", virtual=False, cache_maps=False)
        with pytest.raises(Exception) as err:
            _render(scene, method="near_misread", virtual=False, cache_maps=False)
    finally:
        for name in ("near_misread", "near_both"):
            mi_shadowmap.unregister_method(name)
    smap = next(m for m in integ.maps if m is not None)
    assert smap.extra["pcss_near"].numpy().size == smap.view.n_faces
    chain = [str(e) for e in error_chain(err.value)]   # (mi.render wraps it)
    assert any("'near_misread' was registered with reads_depth=False" in c
               and "layer 'pcss_near'" in c for c in chain)
