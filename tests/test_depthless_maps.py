"""Maps without first depths (``second_depth``'s, a user method's with ``reads_depth``
False) counted and read alike everywhere: the harness orders the methods sharing maps by
the rule the map manager builds by (:func:`mi_shadowmap.map_manager.holds_first_depth`),
``memory_budget`` counts the layers a virtual page holds
(:func:`mi_shadowmap.virtual.store.page_bytes`), and ``pcss_near`` (the nearest first
depth of a face) is missing from virtual maps without first depths as from full ones."""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from mi_shadowmap import harness
from mi_shadowmap.scenes import default_scene


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
