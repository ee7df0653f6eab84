"""Property-based tests (hypothesis) of the integrator's parameters (issue 6).

Parameter sets are generated from the properties each method accepts
(``options.properties_for``: kind, range, choices), for every method in
``options.METHODS``, so new
properties and methods are covered without editing this file.

* **Valid inputs** render a tiny scene (8 x 8 image, maps of at most 16^2)
  with spot, point, directional and area lights: every run finishes, the
  output is finite and visibility is in [0, 1].
* **Invalid inputs** (wrong types, out of range, unknown names, a property of
  another method) raise a clean ``OptionError`` naming the property, both
  from ``parse_options`` and through Mitsuba's loader.

Profiles: the default suite runs 60 examples per test; the full run (>= 1000
valid parameter sets) is one command::

    HYPOTHESIS_PROFILE=full python -m pytest -q tests/test_properties.py
"""
from __future__ import annotations

import keyword
import math
import os

import mitsuba as mi
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mi_shadowmap import methods as _methods
from mi_shadowmap.options import (METHODS, OptionError, all_properties, parse_options,
                                  properties_for)
from mi_shadowmap.scenes import default_scene

# The default profile is derandomized: CI sees the same 60 examples on every run (a
# failure reproduces); the full profile explores new ones each time.
settings.register_profile("default", max_examples=60, deadline=None, derandomize=True,
                          suppress_health_check=[HealthCheck.too_slow,
                                                 HealthCheck.data_too_large])
settings.register_profile("full", max_examples=1100, deadline=None,
                          suppress_health_check=[HealthCheck.too_slow,
                                                 HealthCheck.data_too_large])
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "default"))

READY = list(METHODS)
MAX_RES = 16
#: Upper limits that keep a tiny render tiny (ranges stay those of the properties).
CAPS = {"resolution": MAX_RES, "shadow_rays": 16}
INT_CAP = 64        # other unbounded/huge integer ranges are sampled up to this
FLOAT_SPAN = 1e3    # floats without an upper bound: [lo, lo + FLOAT_SPAN]
_SCENES: dict = {}


def tiny_scene(light: str):
    if light not in _SCENES:
        _SCENES[light] = mi.load_dict(default_scene(width=8, height=8, spp=1, light=light))
    return _SCENES[light]


# ------------------------------------------------------------ valid values
def valid_values(p):
    """A strategy of values ``parse_options`` must accept for property ``p``."""
    if p.name == "method":
        return st.sampled_from(list(METHODS))
    if p.choices is not None:
        return st.sampled_from(p.choices)
    if p.kind == "bool":
        return st.booleans()
    if p.kind == "int":
        lo = int(p.lo) if p.lo is not None else 0
        lo += int(p.lo_open and p.lo == lo)
        hi = int(p.hi) if p.hi is not None else lo + INT_CAP
        hi = min(hi, CAPS.get(p.name, max(lo + INT_CAP, lo)))
        return st.integers(lo, max(lo, hi))
    if p.kind in ("float", "pair"):
        lo = float(p.lo) if p.lo is not None else -FLOAT_SPAN
        hi = float(p.hi) if p.hi is not None else lo + FLOAT_SPAN
        num = st.floats(lo, hi, exclude_min=p.lo_open, allow_nan=False, allow_infinity=False)
        if p.kind == "float":
            return num
        return st.tuples(num, num).map(lambda ab: f"{min(ab)!r}, {max(ab)!r}")
    raise AssertionError(f"no strategy for kind {p.kind!r} of {p.name}")


@st.composite
def valid_sets(draw):
    method = draw(st.sampled_from(READY))
    props = {"method": method}
    for p in properties_for(method):
        if p.name in ("method", "environment") or not draw(st.booleans()):
            continue   # (environment only matters for environment emitters)
        props[p.name] = draw(valid_values(p))
    if method == "pcf":   # cross-property rule: min_samples <= num_samples
        n_min, n_max = props.get("min_samples", 2), props.get("num_samples", 16)
        if n_min > n_max:
            props["min_samples"], props["num_samples"] = n_max, n_min
    if "page_size" in props:   # a power of two, whatever 'virtual' is
        props["page_size"] = max(1 << (int(props["page_size"]).bit_length() - 1), 8)
    if "lod_bias" in props and not props.get("resolution"):   # >= 1 - log2(page_size)
        props["lod_bias"] = max(props["lod_bias"], 1 - math.log2(props.get("page_size", 32)))
    if props.get("virtual"):   # virtual maps: powers of two, no full-map-only properties
        if not _methods.get(method).virtual:
            del props["virtual"]
        else:
            for name in ("fit_frusta", "cull_faces"):
                props.pop(name, None)
            if props.get("antialias") == "always":   # full maps only
                del props["antialias"]
            if props.get("env_lights", 0) > 32:      # a virtual map holds 32 regions
                props["env_lights"] = 32
            props["page_size"] = props.get("page_size", 32)
            if props.get("resolution"):   # (0 is automatic)
                props["resolution"] = max(1 << (int(props["resolution"]).bit_length() - 1),
                                          props["page_size"])
    return props


@given(props=valid_sets(), light=st.sampled_from(["spot", "point", "directional", "area"]),
       seed=st.integers(0, 3))
def test_valid_parameter_sets_render_finite_visibility(props, light, seed):
    try:
        parse_options(props)
        integ = mi.load_dict({"type": "shadowmap", **props})
        img = np.asarray(mi.render(tiny_scene(light), integrator=integ, spp=1, seed=seed))
    except (OptionError, RuntimeError) as e:
        # The only refusal allowed: a memory_budget too small for the maps, named.
        msg = str(e.__cause__ or e)
        assert "memory_budget" in msg and props.get("memory_budget") is not None, msg
        return
    assert np.isfinite(img).all(), props
    if not props.get("visibility_aovs", True):   # the film's channels only
        assert img.shape[-1] == 3, props
        return
    vis = img[..., 3:]
    assert vis.shape[-1] == 1
    assert vis.min() >= 0.0 and vis.max() <= 1.0, props


# ---------------------------------------------------------- invalid values
def wrong_types(p):
    if p.kind == "bool":
        return st.sampled_from([1, 0, "true", 1.0, None.__class__.__name__])
    if p.kind == "int":
        return st.one_of(st.floats(allow_nan=False).filter(lambda x: x != int(x)
                                                             if math.isfinite(x) else True),
                         st.just(2.0), st.text(max_size=5), st.booleans())
    if p.kind == "float":
        return st.one_of(st.text(max_size=5), st.booleans(), st.just([1.0]),
                         st.sampled_from([math.nan, math.inf, -math.inf]))
    if p.kind == "str":
        return st.one_of(st.integers(), st.floats(allow_nan=False), st.booleans())
    if p.kind == "pair":
        return st.one_of(st.just("1"), st.just("a, b"), st.just("1, 2, 3"), st.integers(),
                         st.booleans())
    raise AssertionError(p.kind)


def out_of_range(p):
    if p.choices is not None:
        if p.kind == "str":
            return st.text(min_size=1, max_size=12).filter(lambda s: s not in p.choices)
        return st.integers(-100, 100).filter(lambda v: v not in p.choices)
    vals = []
    if p.lo is not None:
        if p.kind == "int":
            vals.append(st.integers(int(p.lo) - 1000, int(p.lo) - (0 if p.lo_open else 1)))
        else:
            bad_hi = p.lo if p.lo_open else math.nextafter(p.lo, -math.inf)
            vals.append(st.floats(p.lo - 1e6, bad_hi, allow_nan=False))
    if p.hi is not None:
        if p.kind == "int":
            vals.append(st.integers(int(p.hi) + 1, int(p.hi) + 10**6))
        else:
            vals.append(st.floats(math.nextafter(p.hi, math.inf), p.hi + 1e6, allow_nan=False))
    if not vals:
        return None
    s = st.one_of(vals)
    if p.kind == "pair":
        return s.map(lambda x: f"{x!r}, {x!r}")
    return s


@st.composite
def invalid_sets(draw):
    """``(props, needle)``: a parameter set with exactly one bad entry named ``needle``."""
    method = draw(st.sampled_from(READY))
    kind = draw(st.sampled_from(["type", "range", "unknown", "other_method"]))
    own = [p for p in properties_for(method) if p.name != "method"]
    if kind == "unknown":
        name = draw(st.from_regex(r"[a-z][a-z_]{2,15}", fullmatch=True).filter(
            lambda n: n not in {q.name for q in all_properties()} and n != "type"
            and not keyword.iskeyword(n)))
        return {"method": method, name: 1}, name
    if kind == "other_method":
        mine = {q.name for q in properties_for(method)}
        foreign = [p for p in all_properties() if p.name not in mine]
        if not foreign:
            kind = "type"
        else:
            p = draw(st.sampled_from(foreign))
            return {"method": method, p.name: draw(valid_values(p))}, p.name
    if kind == "range":
        ranged = [p for p in own if out_of_range(p) is not None]
        p = draw(st.sampled_from(ranged))
        return {"method": method, p.name: draw(out_of_range(p))}, p.name
    p = draw(st.sampled_from(own + [next(q for q in all_properties() if q.name == "method")]))
    props = {"method": method}
    props[p.name] = draw(wrong_types(p))
    return props, p.name


@given(case=invalid_sets())
def test_invalid_inputs_name_the_property(case):
    props, needle = case
    with pytest.raises(OptionError) as e:
        parse_options(props)
    assert f"'{needle}'" in str(e.value), (props, str(e.value))
    if isinstance(props.get(needle), (list, tuple)):
        return   # not expressible as a Mitsuba property
    with pytest.raises(RuntimeError) as e:
        mi.load_dict({"type": "shadowmap", **props})
    assert needle in str(e.value)


def test_every_property_has_a_strategy():
    """The generators cover every declared property (new ones included)."""
    for p in all_properties():
        valid_values(p)
        wrong_types(p)
    assert set(READY) <= set(METHODS) and "raytraced" in READY
