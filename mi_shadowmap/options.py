"""Parsing and validation of the ``shadowmap`` integrator's properties.

This module is the only place that reads plugin properties. Every property
is declared once in :data:`PROPERTIES` with its type, default, allowed range
and the methods that use it; :func:`parse_options` turns a
``mitsuba.Properties`` (or a plain ``dict``, for Python callers) into a frozen
:class:`Options` and raises :class:`OptionError` (a ``ValueError``) naming the
property and the allowed values for anything it does not accept:

* an unknown property name (with the list of valid names),
* a wrong type (``<string name="resolution" .../>``),
* an out-of-range value,
* a property that the chosen ``method`` does not use (so a typo'd sweep
  never silently runs with defaults).

Integers are accepted where floats are expected (XML ``<integer>``), but
never the other way round, and booleans are never numbers.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any, Iterable

#: Every lookup method, in the order they are documented.
METHODS = ("raytraced", "hard", "unshadowed")
#: Methods that read a depth map.
MAP_METHODS = tuple(m for m in METHODS if m not in ("raytraced", "unshadowed"))


class OptionError(ValueError):
    """A property of the ``shadowmap`` integrator was rejected."""


@dataclass(frozen=True)
class Prop:
    name: str
    kind: str                     # 'int' | 'float' | 'bool' | 'str' | 'pair'
    default: Any
    doc: str
    lo: float | None = None       # inclusive lower bound
    hi: float | None = None       # inclusive upper bound
    lo_open: bool = False         # lower bound is exclusive
    choices: tuple | None = None
    methods: tuple | None = None  # None: used by every method

    def describe_range(self) -> str:
        if self.choices is not None:
            return "one of " + ", ".join(repr(c) for c in self.choices)
        parts = []
        if self.lo is not None:
            parts.append(("> " if self.lo_open else ">= ") + repr(self.lo))
        if self.hi is not None:
            parts.append("<= " + repr(self.hi))
        return " and ".join(parts) if parts else "any value"


_ALL = None
_PCF = ("pcf",)
PROPERTIES: tuple[Prop, ...] = (
    Prop("method", "str", "hard",
         "Visibility lookup: 'raytraced' (shadow rays, the ground truth), 'hard' (Williams "
         "1978), 'unshadowed' (visibility 1: the cost baseline of benchmarks).",
         choices=METHODS),
    Prop("resolution", "int", 1024, "Depth-map resolution per map face (texels per side).",
         lo=1, hi=65536),
    Prop("bias", "float", None,
         "Constant depth bias in world units. Default: automatic (0 plus the texel-scaled "
         "slope and normal biases, which are scale-invariant).", lo=0.0),
    Prop("slope_bias", "float", None,
         "Slope-scaled depth bias in texels (multiplied by the texel's world size and "
         "tan(angle to the light)). Default: 1.0 (0 for second_depth).", lo=0.0),
    Prop("normal_bias", "float", None,
         "Offset of the lookup point along the surface normal, in texels. Default: 0.5 "
         "(0 for second_depth).", lo=0.0),
    Prop("shadow_rays", "int", 1, "Shadow rays per camera sample per emitter (raytraced).",
         lo=1, hi=65536, methods=("raytraced",)),
    Prop("hide_emitters", "bool", False, "Hide directly visible emitters."),
    Prop("environment", "str", "error",
         "What to do with environment/constant emitters, which have no finite frustum: "
         "'error' refuses the scene, 'unshadowed' lights with visibility 1 (no shadows).",
         choices=("error", "unshadowed")),
    Prop("max_tan_slope", "float", 20.0,
         "Clamp of tan(angle between normal and light) in the slope bias.", lo=0.0,
         lo_open=True),
    # Reeves et al. 1987 percentage-closer filtering.
    Prop("num_samples", "int", 16, "Samples of the PCF region (Reeves' NumSamples).",
         lo=1, hi=4096, methods=_PCF),
    Prop("min_samples", "int", 2, "Minimum samples per axis (Reeves' MinSamples).",
         lo=1, hi=64, methods=_PCF),
    Prop("res_factor", "float", 1.0, "Scale of the pixel footprint (Reeves' ResFactor).",
         lo=0.0, lo_open=True, methods=_PCF),
    Prop("min_size", "float", 1.0, "Minimum region size in texels per axis (Reeves' MinSize).",
         lo=0.0, methods=_PCF),
    Prop("sampling", "str", "jitter", "Sample placement in the region (Reeves Fig. 3).",
         choices=("jitter", "uniform", "gaussian"), methods=_PCF),
    Prop("bias_range", "pair", None,
         "Stochastic bias [bias0, bias1] in world units, drawn per sample (Reeves).",
         lo=0.0, methods=_PCF),
)
_BY_NAME = {p.name: p for p in PROPERTIES}


class _OptionsBase:
    """Resolved values and helpers shared by every :class:`Options`."""

    # Resolved biases (the automatic defaults are documented in PROPERTIES).
    @property
    def bias_world(self) -> float:
        return 0.0 if self.bias is None else self.bias

    @property
    def slope_bias_texels(self) -> float:
        if self.slope_bias is not None:
            return self.slope_bias
        return 0.0 if self.method == "second_depth" else 1.0

    @property
    def normal_bias_texels(self) -> float:
        if self.normal_bias is not None:
            return self.normal_bias
        return 0.0 if self.method == "second_depth" else 0.5

    @property
    def uses_map(self) -> bool:
        return self.method in MAP_METHODS

    def replace(self, **changes) -> "Options":
        return parse_options({**{k: getattr(self, k) for k in self.given}, **changes})


#: Validated integrator options: one attribute per entry of PROPERTIES, plus
#: ``given`` (the names the user set explicitly).
Options = dataclasses.make_dataclass(
    "Options",
    [(p.name, Any, dataclasses.field(default=p.default)) for p in PROPERTIES]
    + [("given", frozenset, dataclasses.field(default=frozenset()))],
    bases=(_OptionsBase,), frozen=True)


def _type_name(v: Any) -> str:
    return type(v).__name__


def _convert(prop: Prop, value: Any) -> Any:
    where = f"shadowmap: property '{prop.name}'"
    if prop.kind == "bool":
        if not isinstance(value, bool):
            raise OptionError(f"{where} must be a boolean, got {_type_name(value)} {value!r}")
        return value
    if prop.kind == "str":
        if not isinstance(value, str):
            raise OptionError(f"{where} must be a string ({prop.describe_range()}), "
                              f"got {_type_name(value)} {value!r}")
        if prop.choices is not None and value not in prop.choices:
            raise OptionError(f"{where} = {value!r} is not valid; valid values: "
                              + ", ".join(prop.choices))
        return value
    if prop.kind == "int":
        if isinstance(value, bool) or not isinstance(value, int):
            raise OptionError(f"{where} must be an integer ({prop.describe_range()}), "
                              f"got {_type_name(value)} {value!r}")
        _check_range(prop, value)
        return int(value)
    if prop.kind == "float":
        value = _as_float(prop, value)
        _check_range(prop, value)
        return value
    if prop.kind == "pair":
        if isinstance(value, str):
            parts = value.replace(",", " ").split()
        elif isinstance(value, (tuple, list)):
            parts = list(value)
        else:
            raise OptionError(f"{where} must be two numbers 'a, b' with a <= b, "
                              f"got {_type_name(value)} {value!r}")
        if len(parts) != 2:
            raise OptionError(f"{where} must be two numbers 'a, b' with a <= b, got {value!r}")
        try:
            a, b = (float(x) for x in parts)
        except (TypeError, ValueError):
            raise OptionError(f"{where} must be two numbers 'a, b' with a <= b, "
                              f"got {value!r}") from None
        for x in (a, b):
            _check_range(prop, x)
        if a > b:
            raise OptionError(f"{where}: first value {a} must be <= second value {b}")
        return (a, b)
    raise AssertionError(prop.kind)


def _as_float(prop: Prop, value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise OptionError(f"shadowmap: property '{prop.name}' must be a number "
                          f"({prop.describe_range()}), got {_type_name(value)} {value!r}")
    value = float(value)
    if not math.isfinite(value):
        raise OptionError(f"shadowmap: property '{prop.name}' must be finite, got {value!r}")
    return value


def _check_range(prop: Prop, value: float) -> None:
    bad = False
    if prop.lo is not None:
        bad |= value <= prop.lo if prop.lo_open else value < prop.lo
    if prop.hi is not None:
        bad |= value > prop.hi
    if bad:
        raise OptionError(f"shadowmap: property '{prop.name}' = {value!r} is out of range; "
                          f"it must be {prop.describe_range()}")


def _read_raw(props: Any) -> dict:
    """Read the raw values from a mitsuba.Properties or a dict.

    For Properties only the names we know are read, so that Mitsuba keeps
    marking everything else as unreferenced; we raise our own, clearer error
    for those first.
    """
    if isinstance(props, dict):
        return dict(props)
    keys = list(props.keys())
    raw = {}
    for k in keys:
        if k in _BY_NAME:
            raw[k] = props[k]
        else:
            raw[k] = _UNKNOWN
    return raw


_UNKNOWN = object()


def parse_options(props: Any) -> Options:
    """Validate integrator properties (``mi.Properties`` or ``dict``)."""
    raw = _read_raw(props)
    raw.pop("type", None)
    unknown = sorted(k for k in raw if k not in _BY_NAME)
    if unknown:
        raise OptionError(
            "shadowmap: unknown property " + ", ".join(repr(u) for u in unknown)
            + "; valid properties: " + ", ".join(sorted(_BY_NAME)))
    values = {}
    for name, value in raw.items():
        if value is None:   # dict callers may pass None for "default"
            continue
        values[name] = _convert(_BY_NAME[name], value)
    method = values.get("method", _BY_NAME["method"].default)
    for name in values:
        methods = _BY_NAME[name].methods
        if methods is not None and method not in methods:
            raise OptionError(
                f"shadowmap: property '{name}' is not used by method '{method}' "
                f"(it is used by: {', '.join(methods)})")
    return Options(**values, given=frozenset(values))


def properties_for(method: str) -> Iterable[Prop]:
    """The properties that apply to `method`."""
    return [p for p in PROPERTIES if p.methods is None or method in p.methods]


def docs_table() -> str:
    """A Mitsuba-style parameter table for the integrator docstring."""
    rows = ["   * - " + p.name + "\n     - |" + p.kind + "|\n     - " + p.doc
            + f" (default: {p.default!r}; {p.describe_range()}"
            + (f"; methods: {', '.join(p.methods)}" if p.methods else "") + ")"
            for p in PROPERTIES]
    return ".. list-table::\n   :widths: 20 15 65\n\n" + "\n".join(rows)
