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
METHODS = ("raytraced", "hard", "unshadowed", "pcss", "pcf", "bilinear",
           "second_depth", "mdsm")
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
_BYTES_PER_TEXEL = 4   # float32 depth texels (see depth_maps.ShadowMap.nbytes)
_PCF = ("pcf",)
_PCSS = ("pcss",)
PROPERTIES: tuple[Prop, ...] = (
    Prop("method", "str", "hard",
         "Visibility lookup: 'raytraced' (shadow rays, the ground truth), 'hard' (Williams "
         "1978), 'unshadowed' (visibility 1: the cost baseline of benchmarks), 'pcf' "
         "(Reeves et al. 1987 percentage-closer filtering of the pixel footprint), "
         "'bilinear' (Brabec & Seidel fixed-footprint / bilinear PCF, see 'kernel'), "
         "'second_depth' (Wang & Molnar 1994), 'mdsm' (Pagot et al. 2004 multiple-depth "
         "maps), 'pcss' (Fernando 2005 percentage-closer soft shadows).",
         choices=METHODS),
    Prop("resolution", "int", None,
         "Depth-map resolution per map face (texels per side). Default: automatic -- twice "
         "the film's larger side (Reeves et al. 1987 used maps the size of the image up to "
         "twice it) times a camera-footprint factor in [0.5, 4] (texel width over pixel "
         "width at the scene's centre), lowered if needed so that all maps of the scene fit "
         "in memory_budget (see Options.map_resolution). Accepted and ignored by "
         "'raytraced' and 'unshadowed', so that one scene file renders with any method.",
         lo=1, hi=65536),
    Prop("memory_budget", "float", 1024.0,
         "Memory allowed for the depth maps of one render, in MiB (all emitters, faces and "
         "layers, 4 bytes per texel). An explicit resolution that needs more is refused "
         "before anything is allocated; the automatic resolution is capped by it.",
         lo=0.0, lo_open=True),
    Prop("cache_maps", "bool", True,
         "Reuse depth maps across renders while the scene's shapes and emitters are "
         "unchanged (maps are rebuilt after mi.traverse + params.update() changes them)."),
    Prop("cull_faces", "bool", False,
         "Cube maps (point and area lights): build only the faces that camera-visible points "
         "(one camera ray per pixel, plus a few texels of margin) project into; the others "
         "read +inf (lit) and are still allocated (one flat array per map). A camera change "
         "that needs a new face builds only that face. Renders are identical to full cubes. "
         "Off by default: deciding the faces costs one camera ray per pixel in every render "
         "(measured: a cached-map 512^2 frame of an area light went from ~6 to ~18 ms), which "
         "only pays off when maps are rebuilt.",
         methods=MAP_METHODS),
    Prop("fit_frusta", "bool", False,
         "Spot and directional maps: fit the frustum to the camera-visible receivers inside "
         "it (one camera ray per pixel, plus a margin of texels); every caster of a visible "
         "shadow projects into the same window, so casters are kept. Raises the texel "
         "density where the camera sees a small part of the scene; the maps then depend on "
         "the camera (a camera change rebuilds them).", methods=MAP_METHODS),
    Prop("bias", "float", None,
         "Constant depth bias in world units. Default: automatic (0 plus the texel-scaled "
         "slope and normal biases, which are scale-invariant).", lo=0.0,
         methods=MAP_METHODS),
    Prop("slope_bias", "float", None,
         "Slope-scaled depth bias in texels (multiplied by the texel's world size and "
         "tan(angle to the light)). Default: 1.0 (0 for second_depth).", lo=0.0,
         methods=MAP_METHODS),
    Prop("normal_bias", "float", None,
         "Offset of the lookup point along the surface normal, in texels. Default: 0.5 "
         "(0 for second_depth).", lo=0.0, methods=MAP_METHODS),
    Prop("shadow_rays", "int", 1, "Shadow rays per camera sample per emitter (raytraced).",
         lo=1, hi=65536, methods=("raytraced",)),
    Prop("hide_emitters", "bool", False, "Hide directly visible emitters."),
    Prop("environment", "str", "error",
         "What to do with environment/constant emitters, which have no finite frustum: "
         "'error' refuses the scene, 'unshadowed' lights with visibility 1 (no shadows).",
         choices=("error", "unshadowed")),
    Prop("max_tan_slope", "float", 20.0,
         "Clamp of tan(angle between normal and light) in the slope bias.", lo=0.0,
         lo_open=True, methods=MAP_METHODS),
    # Reeves et al. 1987 percentage-closer filtering.
    Prop("num_samples", "int", 16, "Samples of the PCF region (Reeves' NumSamples).",
         lo=1, hi=4096, methods=_PCF),
    Prop("min_samples", "int", 2, "Minimum samples per axis (Reeves' MinSamples); at most "
         "num_samples (the default is min(2, num_samples)).",
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
    Prop("receiver_plane", "bool", True,
         "Compare each PCF tap against the receiver's tangent plane at that texel instead of "
         "the shading point's single depth (receiver-plane depth bias; not in Reeves 1987 or "
         "Brabec & Seidel; false gives their single-depth comparison).",
         methods=("pcf", "bilinear")),
    # Brabec & Seidel: fixed-footprint (bilinear / "fast") PCF.
    Prop("kernel", "int", 2,
         "Footprint of the fixed-footprint PCF in texels per axis: 1 = one nearest-texel "
         "compare (exactly 'hard'), 2 = the 2x2 bilinear hardware PCF, k = k x k texels "
         "(a (k-1) x (k-1) grid of bilinear lookups one texel apart).",
         lo=1, hi=8, methods=("bilinear",)),
    # Wang & Molnar 1994 second-depth maps; Pagot, Comba & Oliveira 2004 multiple-depth maps.
    Prop("pcf_samples", "int", None,
         "Percentage-closer taps k (PCF(k, n) of Pagot et al.): one compare per texel of the "
         "sqrt(k) x sqrt(k) texels nearest the lookup point. Default: 9 for mdsm (the paper's "
         "PCF(9, n)), 4 (2 x 2) for second_depth.",
         choices=(1, 4, 9, 16, 25), methods=("second_depth", "mdsm")),
    Prop("virtual_samples", "bool", True,
         "second_depth: where the neighbourhood compares disagree, compare depths of virtual "
         "samples on the receiver's tangent plane (Wang & Molnar 1994, sec. 3.2); false keeps "
         "the plain compares.", methods=("second_depth",)),
    Prop("depths", "int", 2,
         "Depths n per cell of the multiple-depth map: 1 = standard map, 2 = plus the maximum, "
         "3 = plus maximum and minimum over the 'search' neighbourhood (Pagot et al. 2004).",
         choices=(1, 2, 3), methods=("mdsm",)),
    Prop("search", "int", 3,
         "Side (texels) of the square neighbourhood of the base map searched for the extra "
         "depths of mdsm (q = search^2 samples; the paper's 3 x 3).",
         choices=(1, 3, 5, 7, 9), methods=("mdsm",)),
    # Percentage-closer soft shadows (Fernando 2005; thesis 002, sec. 2.1.5 / 4).
    Prop("blocker_samples", "int", 16, "PCSS blocker-search taps (Fernando's BLOCKER_SEARCH_"
         "NUM_SAMPLES).", lo=1, hi=4096, methods=_PCSS),
    Prop("filter_samples", "int", 16, "PCSS filtering (PCF) taps (Fernando's PCF_NUM_SAMPLES).",
         lo=1, hi=4096, methods=_PCSS),
    Prop("light_size", "float", None,
         "Light width in world units for PCSS. Default: derived from an area emitter's shape "
         "(side of the square of equal projected area, see light_views), 0 for point and "
         "spot lights (hard shadows); > 0 gives point/spot lights a PCSS penumbra.",
         lo=0.0, methods=_PCSS),
    Prop("max_kernel", "float", 64.0,
         "Largest PCSS blocker-search and filter kernel width, in texels of the map.",
         lo=1.0, hi=4096.0, methods=_PCSS),
    Prop("pattern", "str", "stratified",
         "PCSS tap pattern: 'stratified' (square grid, shifted per camera sample) or 'poisson' "
         "(a Poisson disk, rotated per camera sample).",
         choices=("stratified", "poisson"), methods=_PCSS),
    Prop("angular_diameter", "float", 0.0,
         "Apparent diameter of a directional light (sun: about 0.53), in degrees; > 0 gives "
         "directional lights a PCSS penumbra.", lo=0.0, hi=30.0, methods=_PCSS),
    # Parallel-split / cascaded shadow maps (thesis 002, sec. 2.1.6-2.1.7, 5.1).
    Prop("cascades", "int", 1,
         "Directional lights: number of parallel-split maps over the camera's view depth "
         "(each 'resolution' squared, fitted to its slice).", lo=1, hi=4, methods=MAP_METHODS),
    Prop("split_lambda", "float", 0.5,
         "Weight of the uniform split scheme against the logarithmic one (thesis eq. in "
         "sec. 5.1: C_i = lambda*C_uni + (1-lambda)*C_log).", lo=0.0, hi=1.0,
         methods=MAP_METHODS),
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

    @property
    def budget_bytes(self) -> int:
        return int(self.memory_budget * 2**20)

    def map_resolution(self, film_size, face_layers: int, footprint: float = 1.0) -> int:
        """The per-face resolution of one render's maps; checks ``memory_budget``.

        ``face_layers`` is the number of ``res x res`` float32 arrays the render
        needs (sum over emitters of faces x layers). An explicit ``resolution``
        that would need more than ``memory_budget`` raises :class:`OptionError`
        stating the memory needed (nothing has been allocated yet).

        The automatic resolution is ``2 * max(film width, height) * f``
        (Reeves et al. 1987 used maps the size of the image up to twice it),
        where ``f = footprint`` clamped to [0.5, 4] is the camera-footprint
        correction: the world width a map spans per texel column divided by the
        width the camera spans per pixel column, both at the centre of the
        scene's bounds (largest over the lights; computed by the integrator,
        1 when unknown), so that one texel covers at most about half a pixel
        there. It is rounded up to a multiple of 8, capped at 8192, and lowered
        to the largest value whose maps fit in the budget.
        """
        face_layers = max(int(face_layers), 1)
        budget = self.budget_bytes
        if self.resolution is not None:
            need = face_layers * self.resolution ** 2 * _BYTES_PER_TEXEL
            if need > budget:
                raise OptionError(
                    f"shadowmap: property 'resolution' = {self.resolution} would need "
                    f"{_fmt_bytes(need)} ({face_layers} map face(s)/layer(s) of "
                    f"{self.resolution}^2 float32 texels), more than memory_budget = "
                    f"{self.memory_budget:g} MiB; lower 'resolution' or raise 'memory_budget'")
            return self.resolution
        cap = math.isqrt(budget // (_BYTES_PER_TEXEL * face_layers))
        if cap < 1:
            raise OptionError(
                f"shadowmap: property 'memory_budget' = {self.memory_budget:g} MiB cannot hold "
                f"{face_layers} map face(s)/layer(s) even at resolution 1 "
                f"({face_layers * _BYTES_PER_TEXEL} bytes)")
        f = min(max(float(footprint), 0.5), 4.0) if math.isfinite(footprint) else 1.0
        auto = 2.0 * max(int(film_size[0]), int(film_size[1])) * f
        auto = min(8 * math.ceil(auto / 8), 8192)
        return max(1, min(auto, cap))

    def replace(self, **changes) -> "Options":
        return parse_options({**{k: getattr(self, k) for k in self.given}, **changes})


#: Validated integrator options: one attribute per entry of PROPERTIES, plus
#: ``given`` (the names the user set explicitly).
Options = dataclasses.make_dataclass(
    "Options",
    [(p.name, Any, dataclasses.field(default=p.default)) for p in PROPERTIES]
    + [("given", frozenset, dataclasses.field(default=frozenset()))],
    bases=(_OptionsBase,), frozen=True)


def _fmt_bytes(n: int) -> str:
    return f"{n / 2**20:.1f} MiB ({n} bytes)" if n >= 2**20 else f"{n} bytes"


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
    if prop.choices is not None and value not in prop.choices:
        raise OptionError(f"shadowmap: property '{prop.name}' = {value!r} is not valid; valid "
                          f"values: {', '.join(repr(c) for c in prop.choices)}")
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
        if value is None:
            # Python callers may pass None for an automatic default, and only there.
            if _BY_NAME[name].default is None:
                continue
            raise OptionError(f"shadowmap: property '{name}' has no automatic value; give "
                              f"{_BY_NAME[name].describe_range()} or leave it out")
        values[name] = _convert(_BY_NAME[name], value)
    method = values.get("method", _BY_NAME["method"].default)
    for name in values:
        methods = _BY_NAME[name].methods
        if methods is not None and method not in methods:
            raise OptionError(
                f"shadowmap: property '{name}' is not used by method '{method}' "
                f"(it is used by: {', '.join(methods)})")
    given = frozenset(values)
    n_max = values.get("num_samples", _BY_NAME["num_samples"].default)
    if "min_samples" in values:
        if values["min_samples"] > n_max:   # Reeves' CLAMP(n, MinSamples, NumSamples)
            raise OptionError(f"shadowmap: property 'min_samples' = {values['min_samples']} "
                              f"must be <= 'num_samples' = {n_max}")
    elif method == "pcf":   # the default MinSamples (2) never exceeds NumSamples
        values["min_samples"] = min(_BY_NAME["min_samples"].default, n_max)
    res = values.get("resolution")
    budget = values.get("memory_budget", _BY_NAME["memory_budget"].default)
    if res is not None and res * res * _BYTES_PER_TEXEL > budget * 2**20:
        raise OptionError(   # one face already exceeds the budget: refuse at load time
            f"shadowmap: property 'resolution' = {res} would need at least "
            f"{_fmt_bytes(res * res * _BYTES_PER_TEXEL)} per map face, more than "
            f"memory_budget = {budget:g} MiB; lower 'resolution' or raise 'memory_budget'")
    return Options(**values, given=given)


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
