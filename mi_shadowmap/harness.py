"""Run shadow methods on a scene side by side and measure them against a reference.

:func:`compare` renders a reference and each method in one process, with the
same seed, and returns one :class:`MethodResult` per method (the reference
first): image, per-emitter visibility AOVs, metrics against the reference
(pooled over all emitters -- flat keys ``vis_rmse``, ``img_psnr``, ... -- and
per emitter, ``metrics["per_emitter"][label]``), timings and depth-map memory.
:func:`prepare_maps` gives the depth maps (with every layer) that the map
manager builds for a list of methods, one per emitter; :func:`emitter_maps` every
distinct map, where methods' maps of an emitter differ (``mi-shadowmap maps``).

This module is the user-facing facade of the comparison code; each job lives
in its own module, and every name below is importable from here too:

==========================================  ==================================================
module                                      job
==========================================  ==================================================
:mod:`~mi_shadowmap.specs`                  method specs (``"pcf:num_samples=4"``), validation
:mod:`~mi_shadowmap.timing`                 :func:`run_method`: render one method, timed
:mod:`~mi_shadowmap.ground_truth`           the reference policy, :func:`score`
:mod:`~mi_shadowmap.sweep`                  grids, :func:`sweep`, Pareto front, :func:`analyse`
:mod:`~mi_shadowmap.tables`                 text, CSV and JSON tables (shared with the report)
==========================================  ==================================================

Every method comes from the method registry (:mod:`mi_shadowmap.methods`),
so methods registered with :func:`mi_shadowmap.register_method` are compared
and swept like the built-ins. Every configuration is validated with
:func:`~mi_shadowmap.options.parse_options` before anything renders.
"""
from __future__ import annotations

import dataclasses

import mitsuba as mi
import numpy as np

from .ground_truth import (converged_reference, has_area_lights, has_soft_lights,  # noqa: F401
                           reference_follows_spp, reference_sizes,
                           make_reference, score)
from . import map_manager
from .options import OptionError
from .virtual import VirtualShadowMap
from .scenes import load_scene
from .specs import (RENDER_KEYS, REFERENCE_METHOD, available_methods,  # noqa: F401
                    check_run_args, check_shared_params, check_unique, default_methods,
                    derived_seed,
                    map_methods, method_spec, parse_method_string, parse_value, spec_name,
                    users_of, uses_property, to_mitsuba, validate_property, validate_spec)
from .sweep import (SweepTable, analyse, best_row, default_grid, expand_grid,  # noqa: F401
                    grid_values, sweep, with_shared)
from .tables import format_table, jsonable, safe_name  # noqa: F401
from .timing import (MethodResult, check_scored_film, rendered_spp, root_error,  # noqa: F401
                     run_method)


def compare(scene, methods=None, reference="auto", spp: int = 16, seed: int = 0,
            repeats: int = 1, progress: bool = False, scene_params: dict | None = None,
            ref_spp: int = 64, ref_shadow_rays: int = 64, measure_cached: bool = True,
            **params) -> list[MethodResult]:
    """Render the reference and every method; return the results, reference first.

    Parameters
    ----------
    scene : mi.Scene, dict or path
        A loaded scene, a scene dict, or an XML file (``scene_params`` fill its
        ``$`` parameters, e.g. ``{"width": 64}``).
    methods : list
        Items are method names (``"hard"``), dicts (``{"method": "pcf",
        "num_samples": 4, "spp": 4}``) or strings ``"pcf:num_samples=4"``.
        Default: every registered method except ``raytraced``
        (:func:`~mi_shadowmap.specs.default_methods`).
    reference : ``"auto"`` | ``"converged"`` | method name | spec dict | MethodResult
        See :func:`~mi_shadowmap.ground_truth.make_reference`. The automatic and the
        converged reference give delta lights the size the methods give them
        (``light_size``, ``angular_diameter``): each method is scored against the light
        it models, so methods that give it different sizes (``multiview:light_size=0.5``
        and ``pcss``, whose default is no size) get one reference each, rendered with
        that size (``raytraced`` with ``ref_shadow_rays`` shadow rays); a method without
        the property (``hard``) is scored against the first size a method gives
        (:func:`~mi_shadowmap.ground_truth.reference_sizes`). The reference of the
        first size given (no size where none is) comes first in the results; a method
        scored against another has it as ``scored_against`` (its metrics'
        ``reference_spp`` says its spp). Give a reference (a spec or a result) to score
        every method against one light.
    spp, seed, repeats
        Samples per pixel, seed (shared by all methods) and warm re-renders.
    **params
        Integrator properties shared by every method that uses them (a
        property no listed method uses is an error).

    Everything is validated before the first render, but what depends on the scene's
    maps (a ``resolution`` whose maps exceed ``memory_budget``) fails at the method's
    render: the error (and a Ctrl-C) then carries the results rendered before it,
    scored, as ``exc.compare_results`` (reference first), which the CLI writes; an
    error of the configuration (:class:`~mi_shadowmap.options.OptionError`, a
    ``ValueError``) is raised itself, not the ``RuntimeError`` ``mi.render`` wraps it in.
    """
    methods = _method_list(methods)           # one method; an iterator read once, here
    check_run_args(methods=methods, spp=spp, seed=seed, repeats=repeats, ref_spp=ref_spp,
                   ref_shadow_rays=ref_shadow_rays)
    specs = [method_spec(m, params) for m in (methods if methods is not None
                                              else default_methods())]
    check_shared_params(specs, params)
    check_unique(specs)
    if not isinstance(reference, MethodResult) and reference not in ("auto", "converged"):
        method_spec(reference)   # a bad reference spec fails before anything loads
    scene = load_scene(scene, **(scene_params or {}))
    check_scored_film(scene)
    # a method's own spp is the count the scene's sampler renders (a ``stratified``
    # sampler renders 3 as 4): it is named, and gets its reference, by that count
    rendered = {s["spp"]: rendered_spp(scene, s["spp"]) for s in specs if "spp" in s}
    check_unique([{**s, "spp": rendered[s["spp"]]} if "spp" in s else s for s in specs],
                 rounded=[f"{spec_name(s)!r} at spp={rendered[s['spp']]}" for s in specs
                          if "spp" in s and rendered[s["spp"]] != s["spp"]])
    iterator = specs
    if progress:
        from .progress import bar
        iterator = bar(specs, desc="methods", unit="method", leave=False)
    # the sizes each method gives the delta lights: its reference renders them so
    sized = isinstance(reference, str) and reference in ("auto", "converged")
    main_sizes, own_sizes = (reference_sizes(scene, specs) if sized
                             else ({}, [{} for _ in specs]))
    ref = make_reference(scene, reference, spp=spp, seed=seed, ref_spp=ref_spp,
                         ref_shadow_rays=ref_shadow_rays, repeats=repeats,
                         measure_cached=measure_cached, sizes=main_sizes)
    # a reference that shares the methods' camera samples (reference_follows_spp) holds
    # no camera noise in their errors; a method with its own spp gets one at its spp; a
    # method that gives the lights another size, one with that size
    base_spp = rendered_spp(scene, spp)    # the spp the sampler renders
    per_key = {(base_spp, _size_key(main_sizes)): ref}
    matched = reference_follows_spp(scene, reference)
    results, scored = [ref], [(ref, ref)]
    try:
        for spec, sizes in zip(iterator, own_sizes):
            spec = dict(spec)
            own_spp = "spp" in spec
            m_spp = spec.pop("spp", spp)
            r = run_method(scene, spec.pop("method"), spp=m_spp, seed=seed, repeats=repeats,
                           measure_cached=measure_cached, **spec)
            if own_spp:         # told apart from the same method at compare's spp
                r.name = spec_name({"method": r.method, **r.params, "spp": r.spp})
            key = (r.spp if matched else base_spp, _size_key(sizes))
            if key not in per_key:
                per_key[key] = make_reference(scene, reference, spp=m_spp if matched else spp,
                                              seed=seed, ref_spp=ref_spp,
                                              ref_shadow_rays=ref_shadow_rays,
                                              repeats=repeats, measure_cached=measure_cached,
                                              sizes=sizes)
            r_ref = per_key[key]
            results.append(r)
            scored.append((r, r_ref))
    except (Exception, KeyboardInterrupt) as e:
        # a method the scene cannot render (a map over memory_budget), a bug, Ctrl-C: the
        # results rendered so far, scored, go with the error (the CLI writes them)
        try:
            _score(scored, ref)
        except Exception:    # the error that stopped the comparison is the one to raise
            pass
        e.compare_results = results
        root = root_error(e)
        if root is not e and isinstance(root, (ValueError, TypeError)):
            # mi.render wraps the integrator's error (a map over memory_budget) in a
            # RuntimeError ("error while performing a custom differentiable operation");
            # the error naming the property is raised, as render() raises it
            root.compare_results = results
            raise root from None
        raise
    _score(scored, ref)
    return results


def _size_key(sizes: dict) -> tuple:
    """A hashable key of a reference's light sizes (0 and None alike: no size)."""
    return tuple(sorted((k, float(v)) for k, v in sizes.items() if v))


def _score(scored, ref) -> None:
    """Score each ``(result, its reference)`` of :func:`compare`."""
    for r, r_ref in scored:
        r.metrics = score(r, r_ref)
        if r_ref is not ref:
            r.metrics["reference_spp"] = r_ref.spp
            r.scored_against = r_ref     # its error layers and heat map too


def render(scene, method="hard", spp: int = 16, seed: int = 0, **params):
    """Render ``scene`` once with one ``shadowmap`` configuration: ``method`` as in
    :func:`compare` (a name, a dict or ``"pcf:num_samples=4"``) plus ``params``.

    Returns ``(integrator, image)``: the integrator after the render (its ``maps``,
    ``views``, ``stats``) and the image as a numpy array (colour channels, then one
    visibility AOV per emitter). Validated before anything loads.
    """
    check_run_args(spp=spp, seed=seed)
    spec = method_spec(method, params)
    check_shared_params([spec], params)
    validate_spec(spec)
    spec = dict(spec)
    spp = spec.pop("spp", spp)
    scene = load_scene(scene)
    integ = mi.load_dict({"type": "shadowmap", **to_mitsuba(spec)})
    integ.check_scene(scene)      # clear error before rendering
    try:
        img = mi.render(scene, integrator=integ, spp=spp, seed=seed)
    except RuntimeError as e:     # mi.render wraps a Python integrator's errors
        root = root_error(e)
        if root is not e and isinstance(root, (ValueError, TypeError)):
            raise root from None
        raise
    return integ, np.asarray(img)


def remeasure(scene, reference_info: dict, spec: dict, metric: str, seed: int) -> float:
    """``spec``'s ``metric`` measured again independently of whoever measured it first
    (e.g. :func:`mi_shadowmap.tune`): a fresh reference of the kind and spp that
    ``reference_info`` describes (its ``method``: ``"converged"``, the converged
    reference with its ``light_samples``, as for area lights and environments; else
    ``raytraced``; its ``sizes``, the delta lights' ``light_size`` / ``angular_diameter``,
    if any) and a fresh render, with seeds ``seed + 1`` and ``seed``."""
    sizes = reference_info.get("sizes") or {}   # delta lights given a size (tune_sizes)
    if reference_info.get("method") == "converged":
        ref = converged_reference(scene, spp=reference_info["spp"], seed=derived_seed(seed, 1),
                                  shadow_rays=1, n_light=reference_info["light_samples"],
                                  sizes=sizes)
    else:
        rays = {"shadow_rays": 16} if sizes else {}    # tune.SIZED_SHADOW_RAYS
        ref = run_method(scene, "raytraced", spp=reference_info["spp"], seed=derived_seed(seed, 1),
                         measure_cached=False, **sizes, **rays)
    out = compare(scene, methods=[spec], reference=ref, seed=seed, measure_cached=False)
    return float(out[1].metrics[metric])


# --------------------------------------------------------------------------- maps
def _method_list(methods) -> list | None:
    """``methods`` as a list: one method (a name, ``"pcf:num_samples=4"`` or a dict) as a
    list of one (a name was taken for its letters, "method 'h' is not valid"), an
    iterator read once; None stays None."""
    if methods is None:
        return None
    if isinstance(methods, (str, dict)):
        return [methods]
    return list(methods)


def map_specs(methods=None, params: dict | None = None) -> list[dict]:
    """Validated specs of ``methods`` (default: every method that reads a map) with the
    shared ``params``; a method that reads no depth map is an error naming it."""
    params = params or {}
    specs = [method_spec(m, params) for m in (_method_list(methods) or map_methods())]
    check_shared_params(specs, params)
    no_map = [s["method"] for s in specs if not validate_spec(s).record.uses_map]
    if no_map:
        raise OptionError(f"shadowmap: method {', '.join(repr(m) for m in no_map)} reads no "
                          f"depth map; methods with maps: {', '.join(map_methods())}")
    return specs


def prepare_maps(scene, methods=None, sensor=None, **params) -> list:
    """The depth maps the map manager prepares for ``scene`` (one
    :class:`~mi_shadowmap.depth_maps.ShadowMap` per emitter, None for environment
    emitters), holding every layer that one of ``methods`` uses (default: every
    method that reads a map; items as in :func:`compare`). Full maps, unless
    ``virtual=true`` is given (then one method's :class:`~mi_shadowmap.virtual.VirtualShadowMap`;
    several methods whose layers differ are refused).

    Each method's maps come from :func:`mi_shadowmap.map_manager.prepare_maps`
    (the map cache shares the depth between them, unless ``cache_maps=False``);
    the method whose texels cost most memory (first depth and layers,
    :func:`~mi_shadowmap.map_manager.texel_cost`) goes first and its resolution (given,
    or automatic within ``memory_budget``) is used for all, so the layers line up.

    Methods whose maps of one emitter differ (another view -- ``multiview``'s K views
    of an area light against the cube map of ``hard`` --, another resolution or other
    depths) cannot share one map per emitter: that is a ValueError naming them;
    :func:`emitter_maps` gives every distinct map.
    """
    out = []
    for groups in _map_groups(scene, methods, sensor, params):
        if len(groups) > 1:
            a, b = groups[0], groups[1]
            raise ValueError(
                f"prepare_maps: methods {', '.join(a.methods)} and {', '.join(b.methods)} "
                f"build different maps of emitter '{a.map.view.label}' ({describe_map(a.map)}"
                f" vs {describe_map(b.map)}); prepare them separately, or take every map "
                "with harness.emitter_maps (the CLI's 'maps' writes each)")
        out.append(groups[0].map if groups else None)
    return out


@dataclasses.dataclass
class EmitterMap:
    """One depth map of :func:`emitter_maps`: the emitter's ``index`` in
    ``scene.emitters()`` and ``label``, the map, and the ``methods`` that read it
    (names as listed, e.g. ``"pcf num_samples=4"``, in the order given)."""
    index: int
    label: str
    map: object
    methods: list


def emitter_maps(scene, methods=None, sensor=None, **params) -> list[EmitterMap]:
    """Every distinct depth map that ``methods`` read (arguments as in
    :func:`prepare_maps`), in emitter order: one per emitter where the methods' maps
    line up (their layers merged), more where they differ (``multiview``'s K views of
    an area light beside the cube map of ``hard``; another resolution), each with the
    methods that read it. Environment emitters without a map are left out."""
    return [g for groups in _map_groups(scene, methods, sensor, params) for g in groups]


def describe_map(smap) -> str:
    """``"CubeView, 6 face(s) of 32^2"``: a map's view and size, for messages (a map
    that holds second depths alone says so: ``second_depth``'s, virtual or full)."""
    res = getattr(smap, "resolution", None)
    store = getattr(smap, "store", None)      # a virtual map's pages: which depths
    if store is not None:
        pages = "" if store.casts_depth else ", pages of second depths only"
    else:
        pages = "" if getattr(smap, "has_depth", True) else ", second depths only"
    return (f"{type(smap.view).__name__}, {smap.view.n_faces} face(s)"
            + (f" of {res}^2" if res is not None else "") + pages)


def _same_map(a, b) -> bool:
    """Whether two methods' maps of one emitter are the same map (their layers can be
    merged): the same view (every field), resolution and depths (virtual maps: first
    depths cast in both or neither; ``second_depth``'s pages hold none)."""
    if type(a) is not type(b) or getattr(a, "resolution", None) != getattr(
            b, "resolution", None):
        return False
    if map_manager.view_fingerprint(a.view) != map_manager.view_fingerprint(b.view):
        return False
    if isinstance(a, VirtualShadowMap):   # (second_depth's pages hold no first depth)
        return a.store.casts_depth == b.store.casts_depth
    if not (a.has_depth and b.has_depth):   # (second_depth's full map: its layers alone)
        return True
    return a.depth is b.depth or np.array_equal(np.asarray(a.depth.numpy()),
                                                np.asarray(b.depth.numpy()))


def _map_groups(scene, methods, sensor, params) -> list[list[EmitterMap]]:
    """Per emitter, its distinct maps (see :func:`emitter_maps`)."""
    methods = _method_list(methods)   # read twice below: an iterator was empty the second time
    specs = map_specs(methods, params)
    opts = [validate_spec(s) for s in specs]
    # named as listed, without the shared params
    names = [spec_name(method_spec(m)) for m in (methods or map_methods())]
    scene = load_scene(scene)
    # full maps unless virtual=true is given (the automatic virtual would give each
    # method its own page pool, whose layers cannot be merged)
    opts = [o.replace(virtual=False) if o.uses_map and o.virtual and "virtual" not in o.given
            else o for o in opts]
    # the method whose texels cost most goes first: its resolution fits every method's
    # budget (second_depth's full maps hold no first depth, one array as hard's, unless
    # the scene is differentiated: map_manager.holds_first_depth)
    diff = map_manager.differentiated(scene)
    cost = [map_manager.full_texel_cost(o, diff) for o in opts]
    order = sorted(range(len(opts)), key=lambda k: (-cost[k],
                                                    -len(opts[k].record.layer_names(opts[k]))))
    groups, res = None, None
    for k in order:
        o = opts[k]
        if res is not None and o.resolution is None and not o.virtual:
            o = o.replace(resolution=res)
        prepared = map_manager.prepare_maps(scene, sensor, o)
        if groups is None:
            groups, res = [[] for _ in prepared.maps], prepared.resolution
        for i, theirs in enumerate(prepared.maps):
            if theirs is None:
                continue
            mine = next((g for g in groups[i] if _same_map(g.map, theirs)), None)
            if mine is None:       # the first map of the emitter, or another one
                if not isinstance(theirs, VirtualShadowMap):   # merged into below: a copy
                    theirs = dataclasses.replace(theirs, extra=dict(theirs.extra))
                groups[i].append(EmitterMap(i, theirs.view.label, theirs, [names[k]]))
                continue
            mine.methods.append(names[k])
            if not getattr(mine.map, "has_depth", True) and theirs.has_depth:
                mine.map.depth = theirs.depth     # (second_depth's map went first)
            missing = [n for n in theirs.extra if n not in mine.map.extra]
            if missing and isinstance(mine.map, VirtualShadowMap):
                raise ValueError(f"prepare_maps: the virtual map of '{mine.label}' holds "
                                 f"only its own method's layers, not {', '.join(missing)} of "
                                 f"method '{o.method}'; prepare each method's virtual maps "
                                 "separately, or leave 'virtual' out (full maps)")
            for name in missing:
                mine.map.extra[name] = theirs.extra[name]
    for g in (g for gs in groups or [] for g in gs):   # the methods in the order given
        g.methods.sort(key=names.index)
    return groups or []
