"""Lookups only in the vector packets that hold a lit sample (:mod:`mi_shadowmap.packets`):
full maps, cascades, other samplers than ``independent`` and users' methods marked with
:func:`mi_shadowmap.lit_packets`."""
import dataclasses

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

import mi_shadowmap
from mi_shadowmap import integrator as integrator_mod
from mi_shadowmap import methods
from mi_shadowmap.filters.common import receiver
from mi_shadowmap.methods import MethodError
from mi_shadowmap.scenes import default_scene
from conftest import error_chain


def _every_packet(run, lk, active, draws=True):
    """:func:`~mi_shadowmap.packets.in_lit_packets` as before it: every packet looks up."""
    return run(lk)


def _scene(light, size=32, spp=4, sampler="independent", second_light=False):
    d = default_scene(width=size, height=size, spp=spp, light=light)
    d["sensor"]["sampler"] = {"type": sampler, "sample_count": spp}
    if second_light:        # a later light's sample: drawn after the first light's lookup
        d["lamp"] = {"type": "point", "position": [2.0, 3.0, 2.5],
                     "intensity": {"type": "rgb", "value": 30.0}}
    return mi.load_dict(d)


def _render(scene, spp=4, **props):
    return np.asarray(mi.render(scene, integrator=mi.load_dict({"type": "shadowmap", **props}),
                                spp=spp, seed=3))


def _spied(monkeypatch, name):
    """Replace built-in ``name``'s record by one whose lookup records, at each call,
    whether it is traced inside a symbolic operation (the lookup's own loops open later)."""
    record = methods.get(name)
    calls = []

    def lookup(*args, **kwargs):
        calls.append(dr.flag(dr.JitFlag.SymbolicScope))
        return record.lookup(*args, **kwargs)

    monkeypatch.setitem(methods._REGISTRY, name, dataclasses.replace(record, lookup=lookup))
    return calls


@pytest.mark.parametrize("method, light, props", [
    ("hard", "spot", {}), ("hard", "point", {}), ("pcf", "spot", {}),
    ("second_depth", "point", {}), ("mdsm", "spot", {}), ("vsm", "spot", {}),
    ("pcss", "area", {}), ("bilinear", "area", {}),
    ("hard", "directional", {"cascades": 2}), ("pcf", "directional", {"cascades": 2})])
def test_full_map_lookups_run_only_in_packets_with_a_lit_sample(monkeypatch, method, light,
                                                                props):
    """A built-in method's lookup on full maps (spot, cube faces, cascades) is traced
    inside a symbolic conditional on its lit lanes: a vector packet without one skips it.
    The image, AOVs included, is the one every packet looking up gives, bit for bit."""
    scene = _scene(light)
    calls = _spied(monkeypatch, method)
    props = dict(method=method, virtual=False, resolution=128, **props)
    img = _render(scene, **props)
    assert calls and all(calls), calls
    dark = np.all(img[..., :3] == 0.0, axis=-1)
    assert 0 < dark.sum() < dark.size - 50
    monkeypatch.setattr(integrator_mod, "in_lit_packets", _every_packet)
    calls.clear()
    every = _render(scene, **props)
    assert calls and not any(calls), calls
    np.testing.assert_array_equal(img, every)


@pytest.mark.parametrize("sampler", ["stratified", "multijitter", "ldsampler"])
@pytest.mark.parametrize("virtual", [False, True])
def test_samplers_that_count_dimensions_draw_the_same_numbers(monkeypatch, sampler, virtual):
    """Samplers other than ``independent`` advance a dimension index in every lane at every
    draw, and the conditional merges it per lane: the skipping branch makes the lookup's
    draws with no lane active, so a lane without a lit sample reads the same dimensions
    afterwards (the second light's lookup draws its taps' seed here) as when every packet
    looks up. Without it about 1 % of the image's values differed (``pcf``, full maps and
    virtual)."""
    scene = _scene("spot", sampler=sampler, second_light=True)
    props = dict(method="pcf", virtual=virtual, resolution=128)
    img = _render(scene, **props)
    monkeypatch.setattr(integrator_mod, "in_lit_packets", _every_packet)
    np.testing.assert_array_equal(img, _render(scene, **props))


# --------------------------------------------------------------------------- user methods
def _user_lookup(calls):
    """A user's ``hard`` that draws a number (which changes nothing), as a filter's taps
    would, and records whether it is traced inside a symbolic operation."""
    def lookup(smap, lk, opts, active=True):
        calls.append(dr.flag(dr.JitFlag.SymbolicScope))
        jitter = lk.sampler.next_1d(active)
        r = receiver(smap, lk, opts)
        z = dr.gather(mi.Float, smap.depth, smap.texel_index(r.face, r.uv), active & r.inside)
        return dr.select((~r.inside | (r.depth <= z)) & (jitter < 2.0), 1.0, 0.0)
    return lookup


@pytest.fixture
def user_methods():
    calls = {"marked": [], "plain": []}
    names = []
    for name in calls:
        lookup = _user_lookup(calls[name])
        if name == "marked":
            assert mi_shadowmap.lit_packets(lookup) is lookup
        mi_shadowmap.register_method(f"lit_{name}", lookup)
        names.append(f"lit_{name}")
    yield calls
    for name in names:
        mi_shadowmap.unregister_method(name)


@pytest.mark.parametrize("light", ["spot", "point"])
def test_user_methods_marked_lit_packets_run_only_in_packets_with_a_lit_sample(user_methods,
                                                                              light):
    """``mi_shadowmap.lit_packets`` lets a user's method run as the built-ins do; an unmarked
    one still looks up in every packet. The same image either way."""
    scene = _scene(light, sampler="stratified", second_light=True)
    marked = _render(scene, method="lit_marked", virtual=False, resolution=128)
    plain = _render(scene, method="lit_plain", virtual=False, resolution=128)
    assert user_methods["marked"] and all(user_methods["marked"])
    assert user_methods["plain"] and not any(user_methods["plain"])
    np.testing.assert_array_equal(marked, plain)


def test_a_marked_lookup_that_draws_without_a_mask_is_refused():
    @mi_shadowmap.lit_packets
    def unmasked(smap, lk, opts, active=True):
        return mi.Float(lk.sampler.next_1d() > 2.0)

    mi_shadowmap.register_method("lit_unmasked", unmasked)
    try:
        with pytest.raises(RuntimeError) as info:
            _render(_scene("spot", size=8, spp=1), spp=1, method="lit_unmasked",
                    virtual=False, resolution=32)
        errors = [c for c in error_chain(info.value) if isinstance(c, MethodError)]
        assert errors and "lk.sampler.next_1d(active)" in str(errors[0])
    finally:
        mi_shadowmap.unregister_method("lit_unmasked")
    with pytest.raises(MethodError, match="lookup function"):
        mi_shadowmap.lit_packets(3)
