"""Maps without first depths (``second_depth``'s, a user method's with ``reads_depth``
False) counted and read alike everywhere: the harness orders the methods sharing maps by
the rule the map manager builds by (:func:`mi_shadowmap.map_manager.holds_first_depth`),
``memory_budget`` counts the layers a virtual page holds
(:func:`mi_shadowmap.methods.page_bytes`), and ``pcss_near`` (the nearest first
depth of a face) is missing from virtual maps without first depths as from full ones."""
from __future__ import annotations

import warnings

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

import mi_shadowmap
from mi_shadowmap import harness, methods, virtual
from mi_shadowmap.depth_maps import second_depth_layer
from mi_shadowmap.filters.common import receiver
from mi_shadowmap.filters.pcss import face_near_depth
from mi_shadowmap.options import OptionError, mib_up, parse_options, virtual_cube_bytes
from mi_shadowmap.scenes import default_scene

from conftest import SCENES, error_chain
from test_second_depth_one_layer import _copy, _second_hard


def test_shared_maps_of_a_differentiated_scene_take_the_costliest_texels():
    """A scene whose box has vertex gradients enabled: its full maps hold first depths for
    every method (``second_depth``'s too: a gradient render's lookups follow its
    gradients), so ``second_depth``'s texels cost two float32, ``pcss``'s one (its
    ``pcss_near`` is a value a face). The harness ordered the methods by a copy of the
    map manager's rule without the gradient cases (one float32 for ``second_depth``, a
    tie kept in the order given): ``["pcss", "second_depth"]`` under a ``memory_budget``
    that binds (0.05 MiB) gave ``pcss``'s 114^2 to ``second_depth`` too, over its budget:
    an OptionError, where the other order gave 80^2. Now both orders give 80^2, the
    resolution of ``second_depth``'s own maps; without gradients both give 114^2."""
    scene = mi.load_dict(default_scene(width=32, height=32, spp=1))
    params = mi.traverse(scene)
    params_kw = dict(memory_budget=0.05, virtual=False, cache_maps=False)
    try:
        dr.enable_grad(params["box.vertex_positions"])
        own = harness.prepare_maps(scene, ["second_depth"], **params_kw)[0]
        assert own.has_depth and own.resolution == 80
        for order in (["pcss", "second_depth"], ["second_depth", "pcss"]):
            shared = harness.prepare_maps(scene, order, **params_kw)[0]
            assert shared.resolution == own.resolution, order
            assert set(shared.layers()) == {"depth", "pcss_near", "second_depth"}, order
    finally:
        dr.disable_grad(params["box.vertex_positions"])
    for order in (["pcss", "second_depth"], ["second_depth", "pcss"]):
        assert harness.prepare_maps(scene, order, **params_kw)[0].resolution == 114, order


@pytest.mark.parametrize("method, layers", [("hard", 1), ("second_depth", 1),
                                            ("second_depth_both", 2)])
def test_the_budget_counts_the_layers_a_virtual_page_holds(method, layers):
    """The options' check whether ``memory_budget`` holds a virtual cube map's coarsest
    level counted two float32 layers a texel for every method and 6 pages (0.047 MiB at
    32^2 pages), where the render needs the pages' own layers
    (:func:`~mi_shadowmap.methods.page_bytes`: one for ``hard`` and
    ``second_depth``, two for a copy of ``second_depth`` that reads first depths too)
    and the map's empty page (7 pages: 0.028 / 0.055 MiB). So under 0.03 MiB ``hard``
    lost its automatic virtual maps, and a method of two layers passed the options under
    0.05 MiB to fail at its render with another number. Now the options and the render
    count alike: a point light's virtual maps render within the exact need, and one byte
    less is refused when the options are read (``virtual=true``) or gives full maps with
    a warning quoting that need (the automatic ``virtual``)."""
    if method == "second_depth_both":
        _copy(method, "second_depth", reads_depth=True)
    try:
        opts = parse_options({"method": method, "virtual": True})
        need = virtual_cube_bytes(opts)
        assert need == 7 * opts.page_size ** 2 * 4 * layers
        scene = mi.load_dict(default_scene(width=16, height=16, spp=1, light="point"))
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")     # (a degraded map's warning)
            integ = _render(scene, method=method, memory_budget=need / 2 ** 20)
        assert isinstance(integ.maps[0], virtual.VirtualShadowMap)
        assert integ.maps[0].store.nbytes <= need
        short = (need - 1) / 2 ** 20
        with pytest.raises(OptionError, match=rf"virtual cube map .*{layers} float32 layers? "
                           rf"a texel\): at least {mib_up(need)} MiB"):
            parse_options({"method": method, "virtual": True, "memory_budget": short})
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            integ = _render(scene, method=method, memory_budget=short)
        assert not isinstance(integ.maps[0], virtual.VirtualShadowMap)
        msgs = [str(w.message) for w in caught if "memory_budget" in str(w.message)]
        assert len(msgs) == 1 and f"{mib_up(need)} MiB" in msgs[0], msgs
    finally:
        if method == "second_depth_both":
            mi_shadowmap.unregister_method(method)


def _render(scene, **props):
    integ = mi.load_dict({"type": "shadowmap", "cache_maps": False, **props})
    img = np.asarray(mi.render(scene, integrator=integ, spp=1, seed=0))
    assert np.isfinite(img).all()
    return integ



def _second_near(smap, lk, opts, active):
    """Lit where the receiver is in front of the second depth and the face has a first
    depth (``pcss``'s ``face_near_depth``: the layer ``pcss_near``, the nearest first
    depth of each face)."""
    r = receiver(smap, lk, opts)
    ok = active & r.inside
    near = dr.gather(mi.Float, face_near_depth(smap), r.face, ok)
    z = dr.gather(mi.Float, smap.second_depth, smap.texel_index(r.face, r.uv), ok)
    return dr.select(~r.inside | ((r.depth <= z) & (near < dr.inf)), 1.0, 0.0)


@pytest.mark.parametrize("virtual_maps", [False, True])
def test_pcss_near_is_missing_from_maps_without_first_depths(virtual_maps):
    """``pcss_near`` is the nearest first depth of each face (``face_near_layer``, a
    reduction of ``smap.depth``). A user method registered with ``reads_depth=False``
    (its maps hold second depths alone) whose lookup read it failed on full maps (a
    MethodError naming ``reads_depth``: the layer is reduced from the empty first
    depth), but on virtual maps got the second depths' minima, another quantity, and
    rendered. Now both fail alike, and a method that lists ``pcss_near`` among its
    layers fails on virtual maps as on full ones (naming the layer), whether its lookup
    reads it or not. Registered with ``reads_depth=True``, the same methods render on
    both. spot_sphere_box, 32^2."""
    scene = mi.load_file(str(SCENES / "spot_sphere_box.xml"), width=32, height=32)
    second = {"second_depth": second_depth_layer}
    listed = {**second, **methods.get("pcss").layers}
    kinds = {"near_one": (_second_near, second, False), "near_both": (_second_near, second, True),
             "listed_one": (_second_hard, listed, False),
             "listed_both": (_second_hard, listed, True)}
    for name, (lookup, layers, reads) in kinds.items():
        mi_shadowmap.register_method(name, lookup, layers=layers, virtual=True,
                                     reads_depth=reads)
    errors = {}
    try:
        for name, (_, _, reads) in kinds.items():
            if reads:
                integ = _render(scene, method=name, virtual=virtual_maps)
                assert isinstance(integ.maps[0], virtual.VirtualShadowMap) == virtual_maps
                continue
            with pytest.raises(Exception) as err:
                _render(scene, method=name, virtual=virtual_maps)
            errors[name] = [str(e) for e in error_chain(err.value)]  # (mi.render wraps it)
    finally:
        for name in kinds:
            mi_shadowmap.unregister_method(name)
    for name, chain in errors.items():
        assert any(f"'{name}' was registered with reads_depth=False" in c for c in chain), chain
    assert any("layer 'pcss_near'" in c for c in errors["listed_one"])

