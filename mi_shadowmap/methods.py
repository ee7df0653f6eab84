"""The method registry: one :class:`Method` record per shadow method.

Every shadow method -- the built-ins in :mod:`mi_shadowmap.filters` and the
ones users add with :func:`register_method` -- is one record. Everything that
needs to know the methods reads it from here: the property validation of
:mod:`~mi_shadowmap.options` (each method's own properties and bias
defaults), the map manager (the map layers a method needs and how to build
them), the integrator (the lookup, whether it needs the pixel footprint),
the generated documentation table, the harness, the CLI's choices and the
README check.

A record is plain data; nothing here imports Mitsuba, so the registry sits
at the bottom of the package's one-way flow::

    methods -> options -> light views -> depth maps -> filters -> map manager
            -> integrator -> harness -> report / cli

A lookup has the signature of every built-in::

    lookup(smap, lk, opts, active) -> mi.Float   # visibility in [0, 1]

(a record with ``whole_light`` returns ``(visible, above)`` or ``(visible, above,
weight)``, see :class:`Method`).

``smap`` is the emitter's :class:`~mi_shadowmap.depth_maps.ShadowMap` (for a
method with ``uses_map=False``, a :class:`~mi_shadowmap.filters.common.
RayTracedLight`), ``lk`` the :class:`~mi_shadowmap.filters.common.Lookup` of
the shading points, ``opts`` the validated
:class:`~mi_shadowmap.options.Options` (its own properties are attributes of
it) and ``active`` the lanes to evaluate.
"""
from __future__ import annotations

import collections.abc
import functools
import inspect
import math
import re
from dataclasses import dataclass, field
from typing import Any, Callable


class MethodError(ValueError):
    """A method record or a registration was rejected."""


class OptionError(ValueError):
    """A property of the ``shadowmap`` integrator was rejected (re-exported by
    :mod:`~mi_shadowmap.options`, which raises it for every bad property)."""


#: Names no method property may take: Mitsuba's plugin ``type``, the render's ``spp``
#: (a method spec's ``spp`` is the render's, :data:`~mi_shadowmap.specs.RENDER_KEYS`).
RESERVED_PROPERTY_NAMES = frozenset({"type", "id", "spp"})

#: Names of the integrator's shared properties, which a method cannot redeclare
#: (filled by :mod:`~mi_shadowmap.options`, the module that declares them).
SHARED_PROPERTY_NAMES: set = set()


@dataclass(frozen=True)
class Prop:
    """One integrator property: its type, default, allowed values and documentation.

    ``kind`` is ``'int'``, ``'float'``, ``'bool'``, ``'str'`` or ``'pair'`` (two numbers
    ``"a, b"`` with ``a <= b``). A default of None means "automatic" (documented
    in ``doc``). ``lo``/``hi`` are inclusive bounds (``lo_open``: exclusive lower
    bound); ``choices`` lists the only allowed values. ``lights`` names the light
    kinds the property acts on (``'point'``, ``'spot'``, ``'directional'``, ``'area'``,
    ``'projector'``; None: every light): set to other than its default on a scene
    without such a light, a render warns that it changes nothing.
    """
    name: str
    kind: str
    default: Any
    doc: str
    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False
    choices: tuple | None = None
    lights: tuple | None = None

    def __post_init__(self):
        if self.kind not in ("int", "float", "bool", "str", "pair"):
            raise MethodError(f"property '{self.name}': kind must be one of int, float, bool, "
                              f"str, pair; got {self.kind!r}")
        if not re.fullmatch(r"[a-z][a-z0-9_]*", self.name):
            raise MethodError(f"property name {self.name!r} must be snake_case "
                              "(lower-case letters, digits and '_')")
        if self.name in RESERVED_PROPERTY_NAMES:
            raise MethodError(f"property '{self.name}': the name is reserved ('type' is "
                              "the plugin's, 'spp' the render's in specs such as "
                              "'pcf:spp=4'); choose another")
        kinds = ("point", "spot", "directional", "area", "projector")
        if self.lights is not None and (isinstance(self.lights, str) or not self.lights
                                        or not set(self.lights) <= set(kinds)):
            raise MethodError(f"property '{self.name}': lights must be a non-empty tuple of "
                              f"{', '.join(repr(k) for k in kinds)} or None, got "
                              f"{self.lights!r}")
        for bound in ("lo", "hi"):
            v = getattr(self, bound)
            if v is not None and (isinstance(v, bool) or not isinstance(v, (int, float))
                                  or not math.isfinite(v)):
                raise MethodError(f"property '{self.name}': {bound} must be a finite number "
                                  f"or None, got {v!r}")
        if self.lo is not None and self.hi is not None and self.lo > self.hi:
            raise MethodError(f"property '{self.name}': lo = {self.lo!r} > hi = {self.hi!r}: "
                              "no value could be set")

    def describe_range(self) -> str:
        if self.choices is not None:
            return "one of " + ", ".join(repr(c) for c in self.choices)
        parts = []
        if self.lo is not None:
            parts.append(("> " if self.lo_open else ">= ") + repr(self.lo))
        if self.hi is not None:
            parts.append("<= " + repr(self.hi))
        return " and ".join(parts) if parts else "any value"


@dataclass(frozen=True)
class Method:
    """Everything the package needs to know about one shadow method.

    * ``name`` -- the value of the integrator's ``method`` property;
    * ``lookup`` -- ``fn(smap, lk, opts, active) -> mi.Float`` (see the module doc);
    * ``summary`` -- one line for the documentation tables (paper, idea);
    * ``properties`` -- the method's own :class:`Prop` records (shared
      properties such as ``resolution`` or ``bias`` are declared by
      :mod:`~mi_shadowmap.options`); two methods may declare a property of the
      same name and kind, each with its own default;
    * ``layers`` -- ``{name: builder}``: extra per-map data the method reads,
      ``builder(scene, smap) -> mi.Float`` (per texel, or smaller), built by
      the map manager only when the method runs and cached with the map;
    * ``layers_for`` -- ``fn(opts) -> names``: the layers a render with these
      options needs, when not all of ``layers`` (e.g. ``mdsm`` with ``depths=1``);
    * ``layer_cost`` -- ``{name: cost}``: the memory of a layer in float32 arrays of
      a face's size (default 1; a float64 summed-area table costs 2, one value
      per face 0), used to check ``memory_budget`` before anything is built;
    * ``needs_footprint`` -- the lookup reads the camera pixel's footprint
      (``lk.dp_dx``/``dp_dy``), which the integrator then computes;
    * ``needs_curvature`` -- the lookup reads the receiver's shading-normal derivatives
      (``lk.si.dn_du``/``dn_dv``), which the integrator then asks of the camera rays'
      intersections (``mi.RayFlags.dNSdUV``; ``second_depth``'s curved tangent planes),
      and :func:`~.filters.common.receiver_plane` then allows for a concave receiver's
      bend (``pcf``, ``multiview``);
    * ``uses_map`` -- False for methods that read no depth map (``raytraced``,
      ``unshadowed``): no map is built and map-only properties are refused;
    * ``bias_defaults`` -- defaults of the shared texel biases for this method,
      e.g. ``{"slope_bias": 0.0, "normal_bias": 0.0}`` (otherwise 1.0 and 0.5);
    * ``finalize`` -- ``fn(values, given) -> None``: cross-property checks and
      derived defaults, run after every property is validated (raise
      :class:`~mi_shadowmap.options.OptionError` naming the property);
    * ``shadow_rays`` -- the name of a property giving the number of light samples per
      camera sample (``raytraced``), or None for one;
    * ``view_for`` -- ``fn(view, emitter, scene, opts) -> LightView | None``: the view
      the method's maps are built from instead of the emitter's ordinary ``view``
      (None: the ordinary one), asked by the map manager before it plans the maps
      (``multiview``: K views of the light in one map);
    * ``view_properties`` -- names of the method's own properties that only shape the
      views ``view_for`` makes (``multiview``: ``views``, ``lookups``): given other than
      their default on a scene where ``view_for`` made no view (no light with a size), a
      render warns that they change nothing;
    * ``whole_light`` -- the lookup averages over the whole light itself and returns
      ``(visible, above)`` instead of one visibility: the fractions of its light points
      that contribute to the shading point (above its horizon, emitting towards it:
      the converged reference's definition) and are unoccluded, and that contribute.
      The integrator then calls it at every shaded point (not only where its one
      light sample contributes), reports ``visible`` as the visibility AOV and
      weights the light sample by ``visible / above`` (0 where ``above`` is 0), or by
      a third value ``weight`` the lookup returns, ``(visible, above, weight)``: its own
      estimate of ``visible / above`` (``multiview`` with ``lookups`` < ``views``,
      whose subset can hold no point above the horizon, see
      :func:`whole_light_values`);
    * ``virtual`` -- the lookup reads the map only through ``smap.fetch``,
      ``smap.texel_index``, ``smap.depth``/``smap.extra`` gathers at those indices and
      ``smap.view``, with ``smap.resolution`` possibly a per-lane ``mi.Int32``, and its
      layers are among :data:`VIRTUAL_LAYERS` (with ``layers_for``: the layers it
      returns for options with ``virtual`` true, checked when options are parsed): it
      can read virtual maps (``virtual=true``, :mod:`mi_shadowmap.virtual`);
    * ``virtual_margin`` -- ``fn(opts) -> texels`` or ``fn(opts, view) -> texels``
      (``view``: the light's :class:`~mi_shadowmap.light_views.base.LightView`): how far
      from the receiver's texel the lookup's taps reach (its kernel's half-width), so
      that the mark pass of virtual maps builds the pages they read (default 2: a
      nearest-texel lookup, its normal offset and the camera samples' spread within a
      pixel; capped at ``page_size / 2``: taps beyond the 2 x 2 pages a lookup binds
      read their own pages where neighbouring points had them built, else the coarsest
      level);
    * ``virtual_coarse_res`` -- ``fn(opts, view) -> int or None``: the lookup may also
      read levels coarser than its pixel footprint's (a kernel wider than it reads
      well at that level filters a coarser one, through
      :meth:`~mi_shadowmap.virtual.VirtualShadowMap.bind`'s ``level``), down to those of
      this many texels per face side; the mark pass then builds, around each point, the
      tiles within ``virtual_margin`` of it on those levels too (at most
      :data:`~mi_shadowmap.virtual.MAX_COARSER` of them; ``pcss``). None (default): its
      own level only;
    * ``virtual_edge`` -- ``fn(opts) -> texels``: how far across the light's rays the
      lookup may misplace an occluder's edge on the receiver where no texel-scaled
      receiver bias accounts for it (``second_depth``: half a texel, where the lit
      fraction of its virtual samples crosses 1/2). Where the light grazes the receiver
      that is ``1 / cos(theta)`` times as far along it, and a virtual map's level is kept
      fine enough that it stays within ``REACH_PIXELS`` pixel footprints
      (:class:`~mi_shadowmap.filters.common.BiasReach`). None (default): the receiver
      biases' reach alone;
    * ``virtual_footprint`` -- ``fn(opts) -> footprints``, or None (default): the
      lookup's kernel reaches that many halves of the pixel footprint's longer side
      (``pcf``: ``res_factor``), and ``virtual_margin`` bounds it at the footprint's
      level, ``footprints 2^(1 - lod_bias)`` texels
      (:meth:`~mi_shadowmap.virtual.VirtualShadowMap.level_for`). The mark pass then
      widens the kernel where the receiver biases keep a finer level (``footprints``
      times the footprint there), and marks a film-border pixel's point half a footprint
      farther (its samples half a pixel outwards, which no pixel beyond the film marks
      around: the margin leaves those offsets to the neighbouring pixels' marks;
      :func:`~mi_shadowmap.virtual.marks._margins`);
    * ``virtual_per_tap`` -- a hint for virtual maps: each read gathers its own page's
      slot from the page table (cheapest for a lookup that reads a texel or two, as
      ``hard`` does) instead of the 2 x 2 pages' four slots once per lookup (default:
      cheapest for wide kernels). Results are the same either way. Such a lookup runs at
      each lane's wanted level first and again for the lanes whose read found its page
      missing, so it must read the map outside symbolic loops and conditionals and must
      not draw random numbers (:meth:`~mi_shadowmap.virtual.VirtualShadowMap.visibility`;
      either raises a :class:`MethodError` at the first render);
    * ``reads_depth`` -- the lookup reads the first-depth layer (``smap.depth``); False
      (``second_depth``, which compares with its second depths alone, as the paper's
      map holds only them; the record must have the ``second_depth`` layer): its maps
      hold no first depth. A virtual map's pages cast the second depth alone and have
      no ``depth`` pool (:func:`casts_first_depth`,
      :func:`page_pools`), a full map builds its layers
      alone (:func:`builds_first_depth`); ``smap.depth`` is then an empty array, which
      a lookup reading it anyway fails to gather from as its kernel is traced;
    * ``builtin`` -- shipped with the package.
    """
    name: str
    lookup: Callable
    summary: str = ""
    properties: tuple = ()
    layers: dict = field(default_factory=dict)
    layers_for: Callable | None = None
    layer_cost: dict = field(default_factory=dict)
    needs_footprint: bool = False
    needs_curvature: bool = False
    uses_map: bool = True
    bias_defaults: dict = field(default_factory=dict)
    finalize: Callable | None = None
    shadow_rays: str | None = None
    view_for: Callable | None = None
    view_properties: tuple = ()
    whole_light: bool = False
    virtual: bool = False
    virtual_margin: Callable | None = None
    virtual_coarse_res: Callable | None = None
    virtual_edge: Callable | None = None
    virtual_per_tap: bool = False
    virtual_footprint: Callable | None = None
    reads_depth: bool = True
    builtin: bool = False

    def layer_names(self, opts) -> tuple:
        """The layers a render with the validated ``opts`` builds."""
        if self.layers_for is not None:
            return tuple(self.layers_for(opts))
        return tuple(self.layers)

    def property(self, name: str) -> Prop | None:
        return next((p for p in self.properties if p.name == name), None)


def builds_first_depth(record, layer_names) -> bool:
    """Whether a full map of ``record`` (a :class:`Method`) with the layers
    ``layer_names`` is built with its first depths: not where it holds second depths
    for a lookup that reads those alone (``reads_depth`` False; ``second_depth``). A
    virtual map's pages follow the same rule
    (:func:`casts_first_depth`)."""
    return bool(record.reads_depth) or "second_depth" not in layer_names


# ---------------------------------------------- what a virtual map's pages hold
# (plain arithmetic on a method's layers: options checks memory_budget with it,
# map_manager and mi_shadowmap.virtual.store build by it)

def page_layers(opts) -> tuple:
    """The layers a virtual map's pages hold besides depth for ``opts``' method
    (``pcss_near`` is derived from the page table, not stored per page); ``depth`` too
    where a method that reads second depths also reads the first ones
    (:attr:`Method.reads_depth`): its pages cast both, and its
    stores are not the ``second_depth`` method's (:func:`casts_first_depth`)."""
    names = tuple(n for n in opts.record.layer_names(opts) if n != "pcss_near")
    if "second_depth" in names and opts.record.reads_depth:
        names += ("depth",)
    return names


def casts_first_depth(layers: tuple) -> bool:
    """Whether pages holding ``layers`` (:func:`page_layers`) ray-cast first depths: not
    where they hold second depths for a method that reads those alone
    (``second_depth``: Wang & Molnar's Pass 1 discards the front surface). Its lookups
    never read a first depth (measured with that pool filled with NaN: 5 terrain and
    world images bit-identical). Second depths only where a lookup needs them would need first
    depths everywhere else: with the first depth in place of the second, 0-0.4 % of the
    lookups changed (3 terrains, 4 worlds, 256^2), but which tiles those are is not
    known before the second depth is: with +inf (missing) in its place 2.6-99.9 % of
    the lookups changed, in 4-52 % of the tiles. One depth a texel is the least."""
    return "second_depth" not in layers or "depth" in layers


def page_pools(layers: tuple) -> tuple:
    """The pools of pages holding ``layers`` (:func:`page_layers`): ``depth`` first where
    they cast first depths (:func:`casts_first_depth`), then the layers, each once.
    ``second_depth``'s pages hold its second depths alone: no first-depth pool (a lookup
    that read one anyway, through ``smap.depth``, fails as its kernel is traced,
    gathering from an empty array), and a page costs one float32 a texel, not two."""
    return tuple(dict.fromkeys((("depth",) if casts_first_depth(layers) else ())
                               + tuple(layers)))


def page_bytes(opts) -> int:
    """Bytes of one page in the pools (:func:`page_pools` of :func:`page_layers`),
    float32 each: ``memory_budget`` holds twice the pages of ``second_depth``, whose
    pages hold one depth a texel, as those of ``hard``."""
    return opts.page_size ** 2 * 4 * len(page_pools(page_layers(opts)))


#: The layers virtual maps (:mod:`mi_shadowmap.virtual`) can build: per page, ray-cast
#: (``second_depth``), or per face, from the built pages (``pcss_near``).
VIRTUAL_LAYERS = ("second_depth", "pcss_near")

#: name -> Method, in registration order (built-ins first).
_REGISTRY: dict = {}
_BIAS_KEYS = ("slope_bias", "normal_bias")


def _check_record(m: Method) -> None:
    if not isinstance(m.name, str) or not re.fullmatch(r"[a-z][a-z0-9_]*", m.name):
        raise MethodError(f"register_method: name must be a snake_case string, got {m.name!r}")
    if not callable(m.lookup):
        raise MethodError(f"register_method('{m.name}'): lookup must be callable "
                          "fn(smap, lk, opts, active) -> mi.Float, got "
                          f"{type(m.lookup).__name__}")
    props = list(m.properties)
    if not all(isinstance(p, Prop) for p in props):
        raise MethodError(f"register_method('{m.name}'): properties must be "
                          "mi_shadowmap.methods.Prop records")
    names = [p.name for p in props]
    if len(set(names)) != len(names):
        raise MethodError(f"register_method('{m.name}'): duplicate property names {names}")
    shared = sorted(set(names) & SHARED_PROPERTY_NAMES)   # cannot be redeclared
    if shared:
        raise MethodError(f"register_method('{m.name}'): {', '.join(shared)} "
                          "is a shared property of the integrator; choose another name")
    for p in props:   # same name as another method's property: same kind
        for other in _REGISTRY.values():
            q = other.property(p.name)
            if q is not None and q.kind != p.kind and other.name != m.name:
                raise MethodError(f"register_method('{m.name}'): property '{p.name}' is a "
                                  f"{q.kind} in method '{other.name}', not a {p.kind}")
    if not isinstance(m.layers, dict) or not all(
            isinstance(k, str) and callable(v) for k, v in m.layers.items()):
        raise MethodError(f"register_method('{m.name}'): layers must be a dict "
                          "{name: builder(scene, smap) -> mi.Float}")
    if not isinstance(m.layer_cost, dict) or set(m.layer_cost) - set(m.layers) or not all(
            isinstance(c, (int, float)) and not isinstance(c, bool) and math.isfinite(c)
            and c >= 0 for c in m.layer_cost.values()):
        raise MethodError(f"register_method('{m.name}'): layer_cost must map names of its "
                          "layers to numbers >= 0 (float32 arrays of a face's size)")
    if m.virtual and m.layers_for is None and set(m.layers) - set(VIRTUAL_LAYERS):
        raise MethodError(f"register_method('{m.name}'): virtual=True needs layers that "
                          f"virtual maps build ({', '.join(VIRTUAL_LAYERS)}); its layers "
                          f"{', '.join(sorted(set(m.layers) - set(VIRTUAL_LAYERS)))} are "
                          "built on full maps only (set virtual=False, or give layers_for "
                          "returning only those layers when opts.virtual is true)")
    if m.virtual and not m.builtin:
        # virtual maps build these layers with the built-in builders, whatever the record
        builtin = {n: f for r in _REGISTRY.values() if r.builtin
                   for n, f in r.layers.items() if n in VIRTUAL_LAYERS}
        own = sorted(n for n, f in m.layers.items() if n in builtin and f is not builtin[n])
        if own:
            raise MethodError(f"register_method('{m.name}'): virtual maps build the layer(s) "
                              f"{', '.join(own)} themselves, as the built-in methods do; "
                              "give the built-in builder (e.g. mi_shadowmap.depth_maps."
                              "second_depth_layer), name your layer otherwise, or set "
                              "virtual=False")
    if m.virtual and m.whole_light:
        raise MethodError(f"register_method('{m.name}'): whole_light=True lookups read "
                          "full maps only (their lookup averages the whole light over its "
                          "views itself); set virtual=False")
    for flag in ("virtual_per_tap", "virtual", "needs_footprint", "needs_curvature",
                 "uses_map", "whole_light", "reads_depth"):
        if not isinstance(getattr(m, flag), bool):
            raise MethodError(f"register_method('{m.name}'): {flag} must be True or "
                              f"False, got {getattr(m, flag)!r}")
    for name, sig in (("finalize", "fn(values, given) -> None"),
                      ("layers_for", "fn(opts) -> layer names"),
                      ("virtual_coarse_res", "fn(opts, view) -> int or None"),
                      ("virtual_edge", "fn(opts) -> texels"),
                      ("virtual_footprint", "fn(opts) -> footprints")):
        if getattr(m, name) is not None and not callable(getattr(m, name)):
            raise MethodError(f"register_method('{m.name}'): {name} must be callable "
                              f"{sig} or None, got {getattr(m, name)!r}")
    if m.virtual_margin is not None and not callable(m.virtual_margin):
        raise MethodError(f"register_method('{m.name}'): virtual_margin must be callable "
                          "fn(opts) -> texels or fn(opts, view) -> texels")
    if not m.reads_depth and "second_depth" not in m.layers:
        raise MethodError(f"register_method('{m.name}'): reads_depth=False builds maps of "
                          "second depths alone, and its layers have none; give it the "
                          "'second_depth' layer (layers={'second_depth': mi_shadowmap."
                          "depth_maps.second_depth_layer}) or leave reads_depth True")
    if m.view_for is not None and not callable(m.view_for):
        raise MethodError(f"register_method('{m.name}'): view_for must be callable "
                          "fn(view, emitter, scene, opts) -> LightView | None")
    if not isinstance(m.bias_defaults, dict):
        raise MethodError(f"register_method('{m.name}'): bias_defaults must be a dict "
                          f"{{name: texels}} with names among {', '.join(_BIAS_KEYS)}")
    bad = sorted(map(str, set(m.bias_defaults) - set(_BIAS_KEYS)))
    if bad:
        raise MethodError(f"register_method('{m.name}'): bias_defaults keys must be among "
                          f"{', '.join(_BIAS_KEYS)}, got {', '.join(bad)}")
    for k, v in m.bias_defaults.items():
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) \
                or v < 0:
            raise MethodError(f"register_method('{m.name}'): bias_defaults['{k}'] must be a "
                              f"finite number >= 0 (texels), got {v!r}")


def add(method: Method, replace: bool = False) -> Method:
    """Register a :class:`Method` record (see :func:`register_method`)."""
    _check_record(method)
    old = _REGISTRY.get(method.name)
    if old is not None and not replace:
        raise MethodError(f"register_method: a method named '{method.name}' already exists"
                          + (" (a built-in)" if old.builtin else "")
                          + "; pass replace=True to replace it")
    if old is not None and old.builtin and not method.builtin:
        raise MethodError(f"register_method: '{method.name}' is a built-in method and "
                          "cannot be replaced; choose another name")
    _REGISTRY[method.name] = method
    return method


def virtual_margin_of(record, opts, view) -> float:
    """The mark pass's margin (texels) of ``record``'s lookups on ``view``'s map: its
    ``virtual_margin`` called with ``(opts, view)`` when it takes two arguments, else
    ``(opts)``; 2 without one."""
    fn = record.virtual_margin
    if fn is None:
        return 2.0
    return float(fn(opts, view) if _takes_view(fn) else fn(opts))


def virtual_coarse_res_of(record, opts, view):
    """``record``'s ``virtual_coarse_res(opts, view)`` as an int, or None (its lookups
    read their own level only)."""
    fn = getattr(record, "virtual_coarse_res", None)
    if fn is None:
        return None
    res = fn(opts, view)
    return None if res is None else int(res)


@functools.lru_cache(maxsize=256)
def _takes_view(fn) -> bool:
    """Whether a ``virtual_margin`` takes ``(opts, view)`` (read once per function:
    the mark pass asks every frame)."""
    try:
        return len(inspect.signature(fn).parameters) >= 2
    except (TypeError, ValueError):
        return False


def _checked_lookup(name: str, lookup: Callable, whole_light, reads_depth=True) -> Callable:
    """``lookup`` raising a :class:`MethodError` naming the method when it returns
    something other than one visibility per lane (an ``mi.Float`` or a number; a pair
    of them for ``whole_light``): a ``mi.Vector3f`` failed inside Dr.Jit with "Could
    not construct from sequence", naming nothing. With ``reads_depth`` False, also when
    it gathers from the empty first depth (``smap.depth``) as it is traced: Dr.Jit's
    "attempted to gather from an empty array" named neither the method nor the cause."""
    if not callable(lookup):
        return lookup              # refused by name in _check_record

    def ok(v) -> bool:
        import drjit as dr
        if isinstance(v, bool):
            return False
        return isinstance(v, (int, float)) or (dr.is_array_v(v) and dr.depth_v(v) == 1
                                               and not dr.is_mask_v(v))

    def read_no_depth(err) -> bool:
        while err is not None:
            if "gather from an empty array" in str(err):
                return True
            err = err.__cause__ or err.__context__
        return False

    @functools.wraps(lookup)
    def checked(*args, **kwargs):
        try:
            out = lookup(*args, **kwargs)
        except RuntimeError as e:
            if reads_depth is not False or not read_no_depth(e):
                raise
            # (from None: the CLI and the harness report the innermost cause, which
            # was Dr.Jit's message, naming neither the method nor reads_depth)
            raise MethodError(
                f"shadowmap: method '{name}' was registered with reads_depth=False, so its "
                "maps hold no first depth, and its lookup read one (smap.depth, pcss_near; Dr.Jit: "
                "attempted to gather from an empty array); register it with "
                "reads_depth=True") from None
        values = out if whole_light is True and isinstance(out, tuple) \
            and len(out) in (2, 3) else (out,)
        if not all(ok(v) for v in values):
            what = ", ".join(type(v).__name__ for v in values)
            raise MethodError(
                f"shadowmap: method '{name}': its lookup returned {what}; a lookup returns "
                + ("a pair (visible, above) of mi.Float, or (visible, above, weight)"
                   if whole_light is True
                   else "one visibility per lane, an mi.Float in [0, 1]"))
        return out
    return checked


def whole_light_values(out) -> tuple:
    """``(visible, above, weight)`` of a ``whole_light`` lookup's result ``out``:
    ``(visible, above)``, whose light sample weight is ``visible / above`` (0 where
    ``above`` is 0), or ``(visible, above, weight)`` with the lookup's own weight."""
    import drjit as dr
    if len(out) == 3:
        return tuple(out)
    visible, above = out
    return visible, above, dr.select(above > 0, visible / dr.maximum(above, 1e-30), 0.0)


def register_method(name: str, lookup: Callable, properties=None, layers=None,
                    needs_footprint: bool = False, bias_defaults=None, summary: str = "",
                    layers_for: Callable | None = None, finalize: Callable | None = None,
                    uses_map: bool = True, layer_cost=None, view_for: Callable | None = None,
                    view_properties=(), whole_light: bool = False, virtual: bool = False,
                    virtual_margin: Callable | None = None, virtual_per_tap: bool = False,
                    virtual_coarse_res: Callable | None = None,
                    virtual_edge: Callable | None = None,
                    virtual_footprint: Callable | None = None,
                    needs_curvature: bool = False, reads_depth: bool = True,
                    replace: bool = False) -> Method:
    """Register a user-defined shadow method; it is then usable everywhere a built-in is.

    ``lookup(smap, lk, opts, active) -> mi.Float`` has the built-ins' signature
    (see :mod:`mi_shadowmap.methods`); ``properties`` is a list of :class:`Prop`
    (its values arrive as attributes of ``opts``); ``layers`` a dict of extra
    per-map data ``{name: builder(scene, smap) -> mi.Float}`` (read in the
    lookup as ``smap.extra[name]``). Afterwards ``{'type': 'shadowmap',
    'method': name}`` (and XML), :func:`~mi_shadowmap.harness.compare`,
    :func:`~mi_shadowmap.harness.sweep` and the CLI's ``--methods`` accept it,
    in every variant, with the same property validation as the built-ins.
    ``needs_curvature``, ``view_properties``, ``virtual``, ``virtual_margin``,
    ``virtual_coarse_res``, ``virtual_edge``, ``virtual_footprint`` and
    ``virtual_per_tap``: see
    :class:`Method` (a
    lookup that reads the
    map only through ``smap.fetch``/``texel_index``/``view`` works on virtual maps).

    .. pluginparameters::

     * - reads_depth
       - |bool|
       - Whether the lookup reads the first-depth layer, ``smap.depth`` (default: true).
         False for a lookup that reads second depths alone (``smap.second_depth``, as
         the built-in ``second_depth``): it needs the ``second_depth`` layer (a
         :class:`MethodError` naming ``reads_depth`` else), and its maps then hold no
         first depth, so a map costs one float32 a texel, not two (virtual pages cast
         the second depth alone; full maps build that layer alone, except in the AD
         graph or antialiased). A lookup that reads ``smap.depth`` anyway fails as its
         kernel is traced, with a :class:`MethodError` naming it and ``reads_depth``,
         not with a wrong image.

    Returns the :class:`Method` record. Raises :class:`MethodError` for a bad
    record or a name already taken (``replace=True`` replaces a user method).
    """
    from .options import OptionError as _OptionError, _convert
    for arg, value in (("layers", layers), ("layer_cost", layer_cost),
                       ("bias_defaults", bias_defaults)):
        if value is not None and not isinstance(value, dict):
            raise MethodError(f"register_method: method '{name}': {arg} must be a dict or "
                              f"None, got {type(value).__name__} {value!r}")
    if properties is not None and not isinstance(properties, (list, tuple)):
        raise MethodError(f"register_method: method '{name}': properties must be a list of "
                          f"Prop records, got {type(properties).__name__}")
    for prop in properties or ():
        if isinstance(prop, Prop) and prop.default is not None:
            try:       # the default must be a value the property accepts
                _convert(prop, prop.default)
            except _OptionError as e:
                raise MethodError(f"register_method: method '{name}': the default "
                                  f"{prop.default!r} of property '{prop.name}' is not one of "
                                  f"its own valid values ({e})") from None
    own = {p.name for p in properties or () if isinstance(p, Prop)}
    if isinstance(view_properties, str) or not all(
            isinstance(n, str) and n in own for n in view_properties or ()):
        raise MethodError(f"register_method: method '{name}': view_properties must be "
                          f"names of its own properties ({', '.join(sorted(own)) or 'none'}), "
                          f"got {view_properties!r}")
    record = Method(name=name, lookup=_checked_lookup(name, lookup, whole_light, reads_depth),
                    summary=summary,
                    properties=tuple(properties or ()), layers=dict(layers or {}),
                    layers_for=layers_for, layer_cost=dict(layer_cost or {}),
                    needs_footprint=needs_footprint,
                    needs_curvature=needs_curvature,
                    uses_map=uses_map, bias_defaults=dict(bias_defaults or {}),
                    finalize=finalize, view_for=view_for,
                    view_properties=tuple(view_properties or ()), whole_light=whole_light,
                    virtual=virtual, virtual_margin=virtual_margin,
                    virtual_coarse_res=virtual_coarse_res, virtual_edge=virtual_edge,
                    virtual_per_tap=virtual_per_tap, virtual_footprint=virtual_footprint,
                    reads_depth=reads_depth)
    return add(record, replace=replace)


def unregister_method(name: str) -> None:
    """Remove a user-registered method (built-ins cannot be removed)."""
    m = _REGISTRY.get(name)
    if m is None:
        raise MethodError(f"unregister_method: no method named '{name}'")
    if m.builtin:
        raise MethodError(f"unregister_method: '{name}' is a built-in method")
    del _REGISTRY[name]


def get(name: str) -> Method:
    """The record of method ``name``; raises ``OptionError`` naming the valid ones."""
    m = _REGISTRY.get(name)
    if m is None:
        raise OptionError(f"shadowmap: property 'method' = {name!r} is not valid; valid "
                          f"values: {', '.join(_REGISTRY)}")
    return m


def records() -> list:
    """Every registered :class:`Method`, built-ins first."""
    return list(_REGISTRY.values())


class _Names(collections.abc.Sequence):
    """A live, read-only view of the registered method names (optionally filtered)."""

    def __init__(self, keep=lambda m: True):
        self._keep = keep

    def _names(self):
        return tuple(n for n, m in _REGISTRY.items() if self._keep(m))

    def __getitem__(self, i):
        return self._names()[i]

    def __len__(self):
        return len(self._names())

    def __contains__(self, name):
        m = _REGISTRY.get(name)
        return m is not None and self._keep(m)

    def __repr__(self):
        return repr(self._names())


#: Every method name (live: includes methods registered later).
METHODS = _Names()
#: The names of the methods that read a depth map (live).
MAP_METHODS = _Names(lambda m: m.uses_map)
