"""Parsing and validation of the ``shadowmap`` integrator's properties.

This module is the only place that reads plugin properties. The shared
properties (``resolution``, the biases, ``cascades``, ...) are declared once
in :data:`GENERAL_PROPERTIES`; each method's own properties are declared in
its :class:`~mi_shadowmap.methods.Method` record (:mod:`mi_shadowmap.filters`,
or a user's :func:`~mi_shadowmap.methods.register_method`).
:func:`parse_options` turns a ``mitsuba.Properties`` (or a plain ``dict``, for
Python callers) into a frozen :class:`Options` and raises :class:`OptionError`
(a ``ValueError``) naming the property and the allowed values for anything it
does not accept:

* an unknown property name (with the list of valid names),
* a wrong type (``<string name="resolution" .../>``),
* an out-of-range value,
* a property that the chosen ``method`` does not use (so a typo'd sweep
  never silently runs with defaults).

Integers are accepted where floats are expected (XML ``<integer>``), but
never the other way round, and booleans are never numbers.
"""
from __future__ import annotations

import math
from typing import Any

from . import methods as _methods
from .methods import METHODS, MAP_METHODS, OptionError, Prop  # noqa: F401  (re-exported)
from .methods import page_bytes, page_layers, page_pools


#: Scopes of the shared properties: used by every method; accepted by every method but
#: used only by map methods (so one scene file renders with any method); map methods only.
EVERY, ACCEPTED, MAP = "every", "accepted", "map"

_BYTES_PER_TEXEL = 4   # float32 depth texels (see depth_maps.ShadowMap.nbytes)
#: The properties every method shares (each method's own are in its record).
GENERAL_PROPERTIES: tuple[Prop, ...] = (
    Prop("method", "str", "hard",
         "Visibility lookup: one of the registered methods (see the method table; "
         "'raytraced' traces shadow rays and is the ground truth)."),
    Prop("resolution", "int", None,
         "Depth-map resolution per map face (texels per side); giving it selects full "
         "maps when virtual is automatic (left out). Default: automatic -- twice "
         "the film's larger side (Reeves et al. 1987 used maps the size of the image up to "
         "twice it) times a camera-footprint factor in [0.5, 4] (texel width over pixel "
         "width at the scene's centre), lowered if needed so that all maps of the scene fit "
         "in memory_budget (see Options.map_resolution). Accepted and ignored by "
         "'raytraced' and 'unshadowed', so that one scene file renders with any method. "
         "With virtual maps: the virtual resolution of the finest level per face, a power "
         "of two from page_size to 2^30 (default: automatic, 2^24 texels across the "
         "scene's extent as the light sees it, see mi_shadowmap.virtual); full maps take at "
         "most 65536. 0 means automatic too (for scene files whose $resolution default "
         "should leave the choice to the integrator).",
         lo=0, hi=2**30),
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
         "only pays off when maps are rebuilt."),
    Prop("fit_frusta", "bool", False,
         "Spot and directional maps: fit the frustum to the camera-visible receivers inside "
         "it (one camera ray per pixel, plus a margin of texels); every caster of a visible "
         "shadow projects into the same window, so casters are kept. Raises the texel "
         "density where the camera sees a small part of the scene; the maps then depend on "
         "the camera (a camera change rebuilds them)."),
    Prop("virtual", "bool", None,
         "Virtual shadow maps (after UE5; mi_shadowmap.virtual): each face is a huge map "
         "split into pages; a mark pass (one camera ray per pixel) builds only the pages "
         "visible points read, at the mip level matching their pixel footprint, and keeps "
         "them across camera moves. Methods: hard, pcf, bilinear, pcss, second_depth, "
         "mdsm, vsm, evsm, msm; an environment's median-cut regions are the faces of one "
         "virtual map (up to 32 regions; more keep full maps). false: one full map "
         "per face. Default: "
         "automatic -- true for those methods (and user methods registered with "
         "virtual=True) unless a full-map property is set (resolution > 0, cascades > 1, "
         "fit_frusta, cull_faces, antialias='always'; one that applies to none of the "
         "scene's lights still counts, with a warning) or memory_budget cannot hold a "
         "virtual cube map's coarsest level (or, at the render, every light's coarsest "
         "virtual level together); a scene with shape or emitter gradients "
         "enabled then gets full maps (built in the AD graph), and so does a sensor that "
         "spreads each pixel's rays over a surface or a hemisphere (irradiancemeter, "
         "distant: no pixel footprint to mark pages by; 1024^2 automatic maps; "
         "virtual=true is refused there). virtual=true with "
         "cascades > 1: one virtual face per cascade."),
    Prop("page_size", "int", 32,
         "Virtual maps: texels per side of a page, a power of two. Filter taps within "
         "page_size / 2 texels read the 2 x 2 pages a lookup binds; wider taps read "
         "their own pages where neighbouring points had them built, else the coarsest "
         "level; taps are clamped to their cube face. "
         "Pages are ray-cast in tiles of max(8, page_size / 4) texels "
         "per side, only those the lookups read.", lo=8, hi=1024),
    Prop("lod_bias", "float", -0.5,
         "Virtual maps: each lookup reads level floor(log2(w) + lod_bias), w its pixel "
         "footprint in finest-level texels: 0 puts texels of 0.5-1 footprint, -0.5 "
         "(default) 0.35-0.7, -1 0.25-0.5 (each step of -0.5: twice the texels in theory; "
         "1.45-1.7x the texels and 1.4-1.6x the pages built, measured on the built-in "
         "scene at 64^2-128^2, whose tiles and coarsest level do not scale). At least "
         "1 - log2(page_size) with the automatic resolution (an error below: a pixel would "
         "span more than page_size texels of its level, more than the mark pass builds "
         "around its centre); with a resolution given, finer levels are not read.",
         lo=-8.0, hi=8.0),
    Prop("antialias", "str", "gradients",
         "Silhouette antialiasing of full maps (Worchel & Alexa 2023, after nvdiffrast; "
         "mi_shadowmap.antialias): texels next to an occluder mesh's outline blend towards "
         "their neighbour by the fraction the outline covers, so shadows pass gradients "
         "to an outline's motion. 'gradients' (default): only maps built for gradients "
         "(a shape's or emitter's parameter has gradients enabled); 'always': every map "
         "(so a primal render, or finite differences, see the same function as the "
         "gradients); 'never': none (gradients from depths only).",
         choices=("gradients", "always", "never")),
    Prop("gradient_at", "str", "pixel_centre",
         "Where a gradient render (a shape's or emitter's parameter has gradients enabled, "
         "maps in the AD graph) takes the visibility's derivative. 'pixel_centre' "
         "(default): at the surface point under the centre of the camera sample's pixel "
         "(ray differentials; a perspective camera, other sensors at the sample), "
         "times the light's unshadowed contribution averaged over "
         "gradient_light_samples stratified light samples, as Worchel & Alexa's "
         "rasteriser evaluates one point per pixel: the value is unchanged, the "
         "derivative loses the pixel position's and the light sample's noise (measured: "
         "gradient spread 9-14x lower for vsm, pcf and bilinear; pcss's and jittered pcf's "
         "taps are drawn per film pixel there, pcss 12x). 'sample': "
         "the plain derivative of each sample.",
         choices=("pixel_centre", "sample")),
    Prop("gradient_light_samples", "int", 16,
         "Stratified light samples that average the unshadowed contribution multiplying "
         "the visibility's derivative, with gradient_at='pixel_centre' (delta lights: 1).",
         lo=1, hi=1024),
    Prop("bias", "float", None,
         "Constant depth bias in world units. Default: automatic (0 plus the texel-scaled "
         "slope and normal biases, which are scale-invariant).", lo=0.0),
    Prop("slope_bias", "float", None,
         "Slope-scaled depth bias in texels (multiplied by the texel's world size and "
         "tan(angle to the light)). Default: 1.0, or the method's own "
         "(Method.bias_defaults, listed below).", lo=0.0),
    Prop("normal_bias", "float", None,
         "Offset of the lookup point along the surface normal (turned towards the light), "
         "in texels, times cos(theta), theta the angle between the normal and the light "
         "(so the offset does not shift shadows sideways on surfaces the light grazes; "
         "the full offset where tan(theta) > max_tan_slope clamps the slope bias, at "
         "least 0.5 texel there when slope_bias > 0). A texel's width is taken along the "
         "receiver's slope (a low sun's stretched map: its short side on the ground). "
         "Default: 0.5, or the method's own (Method.bias_defaults, listed below).",
         lo=0.0),
    Prop("hide_emitters", "bool", False, "Hide directly visible emitters."),
    Prop("visibility_aovs", "bool", True,
         "Append one visibility AOV per emitter (vis_<emitter>) to the rendered image, "
         "after the film's own channels. false: the image holds the film's channels only "
         "(RGB, or Y in a mono variant, plus alpha if the film's pixel_format has it), as "
         "Mitsuba's direct integrator's does, so mi.util.write_bitmap(path, mi.render(scene)) "
         "writes the picture to a PNG or an EXR; the colour is the default render's (bit for "
         "bit at one sample a pixel; with more, to a few float32 ulps: Mitsuba's film sums "
         "a pixel's samples in another order when it holds AOV channels). "
         "Comparisons, sweeps, tune and the command line score the visibility AOVs and "
         "refuse false."),
    Prop("environment", "str", "shadowed",
         "What to do with environment/constant emitters: 'shadowed' splits them into "
         "env_lights median-cut regions (Debevec 2005), each shadowed by an orthographic "
         "map along its centroid (raytraced: real shadow rays, = direct; see "
         "mi_shadowmap.environment), 'unshadowed' lights them with visibility 1 (no "
         "shadows), 'error' refuses the scene.",
         choices=("shadowed", "unshadowed", "error")),
    Prop("env_lights", "int", 16,
         "environment='shadowed', map methods: number K of median-cut regions of an "
         "environment/constant emitter, each with its own orthographic map (virtual maps: "
         "the K faces of one virtual map, for K <= 32; full maps: all in one tensor, K x "
         "resolution^2 texels).", lo=1, hi=1024),
    Prop("max_tan_slope", "float", 20.0,
         "Clamp of tan(angle between normal and light) in the slope bias.", lo=0.0,
         lo_open=True),
    Prop("cascades", "int", 1,
         "Directional lights: number of parallel-split maps over the camera's view depth "
         "(each 'resolution' squared, fitted to its slice). With virtual=true each "
         "cascade is a virtual face (pages rebuilt when the camera moves, as the "
         "cascades follow it); the automatic virtual maps need no cascades: their "
         "levels follow the pixel footprint.", lo=1, hi=4, lights=("directional",)),
    Prop("split_lambda", "float", 0.5,
         "Weight of the uniform split scheme against the logarithmic one (thesis eq. in "
         "sec. 5.1: C_i = lambda*C_uni + (1-lambda)*C_log); acts with cascades > 1.",
         lo=0.0, hi=1.0, lights=("directional",)),
)
#: Scope of each shared property (see EVERY, ACCEPTED, MAP).
SCOPES = {"method": EVERY, "hide_emitters": EVERY, "visibility_aovs": EVERY,
          "environment": EVERY, "env_lights": MAP,
          "resolution": ACCEPTED, "memory_budget": ACCEPTED, "cache_maps": ACCEPTED,
          "cull_faces": MAP, "fit_frusta": MAP, "virtual": MAP, "page_size": MAP, "lod_bias": MAP, "antialias": MAP,
          "gradient_at": MAP, "gradient_light_samples": MAP, "bias": MAP, "slope_bias": MAP,
          "normal_bias": MAP, "max_tan_slope": MAP, "cascades": MAP, "split_lambda": MAP}
_GENERAL = {p.name: p for p in GENERAL_PROPERTIES}
assert set(SCOPES) == set(_GENERAL)
_methods.SHARED_PROPERTY_NAMES.update(_GENERAL)
_DEFAULT_BIAS = {"slope_bias": 1.0, "normal_bias": 0.5}


class Options:
    """Validated integrator options: one attribute per property that applies to the
    method (the shared ones, then the method's own), plus

    * ``given`` -- the names the user set explicitly,
    * ``record`` -- the method's :class:`~mi_shadowmap.methods.Method`,

    and the resolved values below. Reading a property of another method raises
    ``AttributeError`` naming it. Frozen; :meth:`replace` returns a new one.
    """
    __slots__ = ("_values", "given", "record")

    def __init__(self, values: dict, given: frozenset, record):
        object.__setattr__(self, "_values", dict(values))
        object.__setattr__(self, "given", frozenset(given))
        object.__setattr__(self, "record", record)

    def __getattr__(self, name):
        values = object.__getattribute__(self, "_values")
        try:
            return values[name]
        except KeyError:
            raise AttributeError(f"shadowmap: property '{name}' does not apply to method "
                                 f"'{values.get('method')}'") from None

    def __setattr__(self, name, value):
        raise AttributeError("Options are frozen; use Options.replace(...)")

    def __eq__(self, other):
        return (isinstance(other, Options) and self._values == other._values
                and self.given == other.given)

    def __hash__(self):
        return hash((tuple(sorted((k, repr(v)) for k, v in self._values.items())),
                     self.given))

    def __repr__(self):
        return "Options(" + ", ".join(f"{k}={v!r}" for k, v in self._values.items()) + ")"

    def as_dict(self) -> dict:
        """Every property value (defaults filled in)."""
        return dict(self._values)

    # Resolved biases (the automatic defaults are documented in GENERAL_PROPERTIES and
    # in the method's record).
    @property
    def bias_world(self) -> float:
        return 0.0 if self.bias is None else self.bias

    def _texel_bias(self, name: str) -> float:
        value = self._values.get(name)
        if value is not None:
            return value
        return self.record.bias_defaults.get(name, _DEFAULT_BIAS[name])

    @property
    def slope_bias_texels(self) -> float:
        return self._texel_bias("slope_bias")

    @property
    def normal_bias_texels(self) -> float:
        return self._texel_bias("normal_bias")

    @property
    def uses_map(self) -> bool:
        return self.record.uses_map

    @property
    def budget_bytes(self) -> int:
        return int(self.memory_budget * 2**20)

    def map_resolution(self, film_size, face_layers: int, footprint: float = 1.0,
                       budget: int | None = None) -> int:
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

        ``budget``: the bytes these maps may use (default: ``memory_budget``; less
        where virtual maps of the same render hold the rest).
        """
        face_layers = max(int(face_layers), 1)
        budget = self.budget_bytes if budget is None else int(budget)
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
            if any(isinstance(x, bool) or not isinstance(x, (int, float, str)) for x in parts):
                raise TypeError
            a, b = (float(x) for x in parts)
        except (TypeError, ValueError):
            raise OptionError(f"{where} must be two numbers 'a, b' with a <= b, "
                              f"got {value!r}") from None
        for x in (a, b):
            if not math.isfinite(x):
                raise OptionError(f"{where} must be two finite numbers 'a, b' with a <= b, "
                                  f"got {value!r}")
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


def known_names() -> set:
    """Every property name any registered method accepts (shared and own)."""
    return set(_GENERAL) | {p.name for m in _methods.records() for p in m.properties}


def _read_raw(props: Any) -> dict:
    """Read the raw values from a mitsuba.Properties or a dict.

    For Properties only the names we know are read, so that Mitsuba keeps
    marking everything else as unreferenced; we raise our own, clearer error
    for those first.
    """
    if isinstance(props, dict):
        return dict(props)
    known = known_names()
    return {k: (props[k] if k in known else _UNKNOWN) for k in props.keys()}


_UNKNOWN = object()


def applies(record, name: str) -> bool:
    """Whether property ``name`` is accepted by the method of ``record``."""
    if name in _GENERAL:
        return SCOPES[name] != MAP or record.uses_map
    return record.property(name) is not None


def properties_for(method: str) -> list:
    """The properties that apply to ``method``: the shared ones it accepts, then its own."""
    record = _methods.get(method)
    return [p for p in GENERAL_PROPERTIES if applies(record, p.name)] + list(record.properties)


def methods_using(name: str) -> tuple:
    """The names of the methods that accept property ``name``."""
    return tuple(m.name for m in _methods.records() if applies(m, name))


def all_properties() -> list:
    """Every property, once per name: the shared ones, then each method's own (a name
    declared by two methods appears with the first one's record)."""
    out = {p.name: p for p in GENERAL_PROPERTIES}
    for m in _methods.records():
        for p in m.properties:
            out.setdefault(p.name, p)
    return list(out.values())


def _method_of(raw: dict):
    """The record of the requested method (validated first: the other checks need it)."""
    value = raw.get("method", _GENERAL["method"].default)
    if value is None:
        raise OptionError("shadowmap: property 'method' has no automatic value; give one of "
                          + ", ".join(METHODS) + " or leave it out")
    if not isinstance(value, str):
        raise OptionError(f"shadowmap: property 'method' must be a string (one of "
                          f"{', '.join(repr(m) for m in METHODS)}), got "
                          f"{_type_name(value)} {value!r}")
    return _methods.get(value)   # raises, listing the valid methods


def parse_options(props: Any) -> Options:
    """Validate integrator properties (``mi.Properties`` or ``dict``)."""
    raw = _read_raw(props)
    raw.pop("type", None)
    known = known_names()
    unknown = sorted(k for k in raw if k not in known)
    if unknown:
        raise OptionError(
            "shadowmap: unknown property " + ", ".join(repr(u) for u in unknown)
            + "; valid properties: " + ", ".join(sorted(known)))
    record = _method_of(raw)
    own = {p.name: p for p in properties_for(record.name)}
    values = {}
    for name, value in raw.items():
        if name not in own:
            raise OptionError(
                f"shadowmap: property '{name}' is not used by method '{record.name}' "
                f"(it is used by: {', '.join(methods_using(name))})")
        prop = own[name]
        if value is None:
            # Python callers may pass None for an automatic default, and only there.
            if prop.default is None:
                continue
            raise OptionError(f"shadowmap: property '{name}' has no automatic value; give "
                              f"{prop.describe_range()} or leave it out")
        values[name] = _convert(prop, value)
    given = frozenset(values)
    values = {**{name: p.default for name, p in own.items()}, **values}
    if "env_lights" in given and values["environment"] != "shadowed":
        raise OptionError(   # a region count nothing would use
            f"shadowmap: property 'env_lights' is used only with environment='shadowed' "
            f"(environment={values['environment']!r} has no regions); leave it out or "
            "set environment='shadowed'")
    if record.finalize is not None:
        record.finalize(values, given)
    if values.get("resolution") == 0:      # 0: automatic, as if not given
        values["resolution"] = None
    if values.get("virtual", False) is None:
        values["virtual"] = _automatic_virtual(record, values)
    res = values.get("resolution")
    budget = values["memory_budget"]
    page = values.get("page_size")
    if page is not None and page & (page - 1):
        raise OptionError(f"shadowmap: property 'page_size' = {page} must be a power of two "
                          "(8 to 1024)")
    if values.get("virtual"):
        _check_virtual(record, values, given)
        return Options(values, given, record)
    if res is not None and res > 65536:
        raise OptionError(f"shadowmap: property 'resolution' = {res} is above 65536, the "
                          "largest full map; virtual=true takes virtual resolutions up to "
                          "2^30")
    if res is not None and res * res * _BYTES_PER_TEXEL > budget * 2**20:
        raise OptionError(   # one face already exceeds the budget: refuse at load time
            f"shadowmap: property 'resolution' = {res} would need at least "
            f"{_fmt_bytes(res * res * _BYTES_PER_TEXEL)} per map face, more than "
            f"memory_budget = {budget:g} MiB; lower 'resolution' or raise 'memory_budget'")
    return Options(values, given, record)


#: Properties that pin full maps: given (with these values excepted), the automatic
#: ``virtual`` is false.
FULL_MAP_PROPERTIES = {"resolution": None, "cascades": 1, "fit_frusta": False,
                       "cull_faces": False}


def _automatic_virtual(record, values: dict) -> bool:
    """The automatic ``virtual``: virtual maps for the methods that read them (the
    record's ``virtual``), unless a full-map property is set to other than its default
    (an explicit ``resolution`` keeps its full-map meaning, so scene files and sweeps
    that pin one compare the same maps as before; ``cascades=1`` from a scene file's
    ``$cascades`` default does not count), ``antialias='always'`` is set, or
    ``memory_budget`` cannot hold the coarsest level of a virtual cube map."""
    if not record.virtual or values.get("antialias") == "always":
        return False
    if not _holds_virtual_cube(record, values):
        return False
    return all(values.get(name, off) == off for name, off in FULL_MAP_PROPERTIES.items())


def virtual_lost_to_budget(opts) -> bool:
    """Whether the automatic ``virtual`` chose full maps for ``memory_budget`` alone: it
    cannot hold a virtual cube map's coarsest level (:func:`_holds_virtual_cube`), and
    virtual maps would have come with a budget that does (``virtual`` not given, a
    method that reads them, no full-map property set)."""
    if opts.record is None or "virtual" in opts.given or opts.virtual:
        return False
    values = opts.as_dict()
    return (_automatic_virtual(opts.record, {**values, "memory_budget": float("inf")})
            and not _holds_virtual_cube(opts.record, values))


#: Properties that fit full maps to the camera, each to some lights' views (the views
#: say whether they use them: ``needs_camera_points``), with their defaults.
CAMERA_FIT_PROPERTIES = {"cascades": 1, "fit_frusta": False, "cull_faces": False}


def camera_fit_pins(opts) -> list:
    """The camera-fitting properties (``cascades`` > 1, ``fit_frusta``, ``cull_faces``)
    set in ``opts`` that alone turned the automatic ``virtual`` off, as ``"'name' =
    value"``; [] where ``virtual`` was given or full maps come anyway (a ``resolution``,
    ``antialias='always'``, a method without virtual maps, a small ``memory_budget``)."""
    if "virtual" in opts.given or opts.record is None:
        return []
    values = opts.as_dict()
    named = [n for n, off in CAMERA_FIT_PROPERTIES.items() if values.get(n, off) != off]
    if not named or not _automatic_virtual(opts.record, {**values, **CAMERA_FIT_PROPERTIES}):
        return []
    return [f"'{n}' = " + (str(values[n]).lower() if isinstance(values[n], bool)
                           else str(values[n])) for n in named]


def unused_light_properties(opts, kinds) -> list:
    """The properties of ``opts`` given with other than their default whose
    ``Prop.lights`` hold none of the light ``kinds`` (a scene's), as ``"'name' =
    value (lights: ...)"``: e.g. ``angular_diameter`` in a scene without a directional
    light, which changes nothing."""
    if opts.record is None:
        return []
    # a camera-fitting property that turned the automatic virtual maps off gets its own
    # warning when no light uses it (map_manager.plan_maps)
    pinned = {pin.split("'")[1] for pin in camera_fit_pins(opts)}
    out = []
    for p in properties_for(opts.record.name):
        if p.lights is None or p.name not in opts.given or p.name in pinned:
            continue
        value = getattr(opts, p.name)
        if (p.name == "split_lambda" and value != p.default and opts.cascades == 1
                and "directional" in kinds):
            out.append(f"'split_lambda' = {value:g} (it weighs the splits of cascades > 1; "
                       "cascades = 1)")
        elif value != p.default and not set(p.lights) & set(kinds):
            out.append(f"'{p.name}' = {value:g} (it acts on {', '.join(p.lights)} lights)"
                       if isinstance(value, float) else
                       f"'{p.name}' = {value} (it acts on {', '.join(p.lights)} lights)")
    return out


def virtual_map_bytes(opts, n_faces: int) -> int:
    """Bytes the virtual maps of ``opts`` (validated, its ``virtual`` true) need at least
    for a light of ``n_faces`` faces: its coarsest level (one page a face, always built)
    and its empty page, each of :func:`~mi_shadowmap.methods.page_bytes` (the layers
    the method's pages hold: one float32 a texel for ``hard`` and ``second_depth``, two
    for a method that reads first and second depths)."""
    return (n_faces + 1) * page_bytes(opts)


def virtual_cube_bytes(opts) -> int:
    """Bytes of the coarsest level of a virtual cube map of ``opts``' method, its empty
    page included (:func:`virtual_map_bytes` of 6 faces), whatever ``opts.virtual``."""
    return virtual_map_bytes(_as_virtual(opts), 6)


def _as_virtual(opts):
    """``opts`` with ``virtual`` true (its pages' layers), not validated again: a
    ``memory_budget`` that cannot hold them stays."""
    if opts.virtual:
        return opts
    return Options({**opts.as_dict(), "virtual": True}, opts.given, opts.record)


def _holds_virtual_cube(record, values: dict) -> bool:
    """Whether ``values['memory_budget']`` holds the coarsest level of a virtual cube map
    of ``record`` with ``values`` (:func:`virtual_cube_bytes`)."""
    opts = Options({**values, "virtual": True}, frozenset(), record)
    return values["memory_budget"] * 2**20 >= virtual_cube_bytes(opts)


def _check_virtual(record, values: dict, given) -> None:
    """``virtual=true``: the method must read virtual maps, the resolution and the page
    size must be powers of two, and the full-map-only properties must stay off."""
    if not record.virtual:
        ok = ", ".join(m.name for m in _methods.records() if m.virtual)
        raise OptionError(f"shadowmap: property 'virtual' = true is not supported by method "
                          f"'{record.name}' (it reads full maps); methods with virtual maps: "
                          f"{ok}; or set virtual=false")
    extra = set(record.layer_names(Options(values, given, record))) - set(
        _methods.VIRTUAL_LAYERS)
    if extra:
        raise OptionError(f"shadowmap: method '{record.name}' with these options reads "
                          f"layers built on full maps only ({', '.join(sorted(extra))}); "
                          f"virtual maps build {', '.join(_methods.VIRTUAL_LAYERS)}; "
                          "set virtual=false")
    page = values["page_size"]
    res = values.get("resolution")
    if res is not None and (res & (res - 1) or res < page):
        raise OptionError(f"shadowmap: property 'resolution' = {res} must be a power of two "
                          f"from page_size = {page} to 2^30 with virtual=true (the virtual "
                          "resolution of the finest level)")
    if "virtual" in given and values.get("env_lights", 16) > 32:
        # environment.MAX_VIRTUAL_REGIONS: a virtual map's page keys hold 32 faces; more
        # regions got full maps, silently, although virtual=true was asked for
        raise OptionError(f"shadowmap: property 'env_lights' = {values['env_lights']} with "
                          "virtual=true: a virtual map holds at most 32 environment regions; "
                          "set env_lights <= 32, or virtual=false (full maps)")
    if values.get("antialias") == "always":
        raise OptionError("shadowmap: property 'antialias' = 'always' applies to full maps "
                          "only (virtual pages are not antialiased); use 'gradients' or "
                          "'never', or set virtual=false")
    for name, off in (("fit_frusta", False), ("cull_faces", False)):
        if values.get(name, off) != off:
            raise OptionError(f"shadowmap: property '{name}' applies to full maps only; "
                              "virtual=true builds only the pages the camera reads, at "
                              "each lookup's pixel footprint (remove it or set "
                              "virtual=false)")
    lod = values.get("lod_bias")
    if lod is not None and res is None and lod < 1.0 - math.log2(page):
        # levels finer than that are never read (virtual.lookup.effective_lod_bias: a
        # pixel would span more than page_size texels, beyond what the mark pass builds
        # around its centre); with the automatic resolution finer levels always exist
        raise OptionError(f"shadowmap: property 'lod_bias' = {lod:g} needs larger pages: "
                          f"with page_size = {page} it must be >= {1.0 - math.log2(page):g} "
                          f"(1 - log2(page_size): a pixel then spans up to page_size "
                          "texels of its level; -8 needs page_size >= 512); raise "
                          "'page_size' or 'lod_bias'")
    if not _holds_virtual_cube(record, values):
        opts = Options(values, given, record)
        raise OptionError(f"shadowmap: property 'memory_budget' = "
                          f"{values['memory_budget']:g} MiB cannot hold the coarsest level of "
                          f"a virtual cube map ({cube_pages_text(opts)}): at least "
                          f"{mib_up(virtual_cube_bytes(opts))} MiB; raise it, lower "
                          "'page_size' or set virtual=false (full maps)")


def cube_pages_text(opts) -> str:
    """What a virtual cube map's coarsest level of ``opts`` holds, for messages."""
    n = len(page_pools(page_layers(_as_virtual(opts))))
    return (f"6 pages of {opts.page_size}^2 texels and an empty page, {n} float32 layer"
            f"{'s' if n > 1 else ''} a texel")


def mib_up(n_bytes: int) -> str:
    """``n_bytes`` in MiB rounded up to 3 decimals (a need is never understated)."""
    return f"{math.ceil(n_bytes / 2 ** 20 * 1000) / 1000:g}"


def _default_text(p: Prop) -> str:
    """The default a docs row gives: the declared one, or for the texel biases the
    shared one and each method's own (its record's ``bias_defaults``)."""
    if p.name in _DEFAULT_BIAS:
        own = [f"{m.name}: {m.bias_defaults[p.name]!r}" for m in _methods.records()
               if p.name in m.bias_defaults]
        return repr(_DEFAULT_BIAS[p.name]) + (f" ({', '.join(own)})" if own else "")
    return "automatic" if p.default is None else repr(p.default)


def _row(p: Prop, where: str) -> str:
    return ("   * - " + p.name + "\n     - |" + p.kind + "|\n     - " + p.doc
            + f" (default: {_default_text(p)}; {p.describe_range()}{where})")


def docs_table() -> str:
    """A Mitsuba-style parameter table (the shared properties, then each method's own),
    generated from :data:`GENERAL_PROPERTIES` and the method records."""
    rows = [_row(p, "" if SCOPES[p.name] == EVERY else "; map methods")
            for p in GENERAL_PROPERTIES]
    rows += [_row(p, f"; method: {m.name}") for m in _methods.records() for p in m.properties]
    return ".. list-table::\n   :widths: 20 15 65\n\n" + "\n".join(rows)


def methods_table() -> str:
    """A Markdown table of the registered methods (name, summary, own properties)."""
    lines = ["| method | what | its properties |", "|---|---|---|"]
    for m in _methods.records():
        own = ", ".join(f"`{p.name}`" for p in m.properties) or "-"
        lines.append(f"| `{m.name}` | {m.summary} | {own} |")
    return "\n".join(lines)
