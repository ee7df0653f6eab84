"""The reference policy of comparisons and sweeps, and scoring against it.

:func:`make_reference` renders what every method is measured against:

* ``"auto"``: the ``raytraced`` method at the same spp and seed when every
  emitter is a delta light (so its visibility is the exact per-sample ground
  truth and its own metrics are 0); when the scene has an area light or an
  environment (:func:`has_soft_lights`), the converged soft-shadow reference
  (:func:`converged_reference`), also at the same spp and seed: the methods' camera
  samples, so that their errors hold no camera noise (at ``max(spp, ref_spp)``, before,
  ``raytraced`` with 256 shadow rays scored a visibility RMSE of 0.044 on a 48^2
  ``cbox_area`` at 16 spp, 0.0025 against a reference with its camera samples);
* ``"converged"``: :func:`converged_reference` in any scene, at ``max(spp, ref_spp)``
  spp (its own camera samples: a reference independent of the methods');
* a method name or spec (rendered at the given spp), or an existing
  :class:`~mi_shadowmap.timing.MethodResult`.

Delta lights given a size: where the methods compared give a point, spot or projector
light a ``light_size`` or a directional light an ``angular_diameter``
(:func:`reference_sizes`), the automatic and the converged reference render those lights
with that size (``raytraced``'s own ``light_size`` / ``angular_diameter``, with
``ref_shadow_rays`` shadow rays per camera sample): the soft truth, not the hard one.

:func:`converged_reference` renders the image with ``raytraced`` and many
stratified shadow rays and takes the visibility from
:func:`mi_shadowmap.reference.converged_visibility` (the average of many hard
shadows from fixed positions on the light). :func:`score` computes the
metrics of a result against the reference (:mod:`mi_shadowmap.metrics`).
"""
from __future__ import annotations

import time

import mitsuba as mi
import numpy as np

from . import metrics
from . import methods as methods_mod
from .reference import converged_visibility
from .specs import REFERENCE_METHOD, derived_seed, method_spec, spec_name
from .timing import MethodResult, run_method

#: The properties that give a delta light a size (``raytraced``'s, ``multiview``'s,
#: ``pcss``'s): the automatic reference renders a light with the size the methods give it.
SIZE_PROPERTIES = ("light_size", "angular_diameter")


def has_area_lights(scene: mi.Scene) -> bool:
    """True if an emitter is neither a delta light nor an environment (soft shadows)."""
    for e in scene.emitters():
        if e.is_environment():
            continue
        if not (mi.has_flag(e.flags(), mi.EmitterFlags.DeltaPosition)
                or mi.has_flag(e.flags(), mi.EmitterFlags.DeltaDirection)):
            return True
    return False


def has_soft_lights(scene: mi.Scene) -> bool:
    """True if an emitter is an area light or an environment (``envmap``, ``constant``):
    a light whose visibility is a fraction, not 0 or 1. One shadow ray per camera sample
    gives it only as binary noise, so comparisons measure against the converged
    reference there (an environment's ``vis_`` AOV is the share of its light that
    arrives: on an open floor under a uniform sky about 0.5)."""
    return has_area_lights(scene) or any(e.is_environment() for e in scene.emitters())


def converged_reference(scene: mi.Scene, spp: int = 64, seed: int = 0,
                        shadow_rays: int = 64, n_light: int = 1024, repeats: int = 1,
                        measure_cached: bool = False, step=None,
                        sizes: dict | None = None) -> MethodResult:
    """The converged soft-shadow reference for scenes with area lights.

    The image is ``raytraced`` with ``shadow_rays`` stratified shadow rays per
    camera sample (timed as :func:`~mi_shadowmap.timing.run_method` times a method:
    ``repeats``, ``measure_cached``); the visibility is
    :func:`mi_shadowmap.reference.converged_visibility` (the average of
    ``n_light`` hard shadows from fixed stratified light positions). ``step``, if
    given, is called with a description before each of the two (a progress bar's).

    ``sizes`` (``{"light_size": w, "angular_diameter": a}``, :func:`reference_sizes`)
    give delta lights a size: the image is ``raytraced`` with them, and the visibility
    of each light they size is that render's (``shadow_rays`` shadow rays to points of
    the sized light), the converged visibility's being of the light without a size.
    """
    sizes = {k: v for k, v in (sizes or {}).items() if v}
    if step is not None:
        step(f"image: raytraced, {spp} spp x {shadow_rays} shadow rays")
    res = run_method(scene, REFERENCE_METHOD, spp=spp, seed=seed, shadow_rays=shadow_rays,
                     repeats=repeats, measure_cached=measure_cached, **sizes)
    own = dict(res.visibility)
    if step is not None:
        step(f"visibility: {n_light} light samples x {spp} spp")
    t0 = time.perf_counter()
    vis = converged_visibility(scene, n_light=n_light, seed=seed, spp=spp)
    res.visibility = {k[len("vis_"):]: np.asarray(v, dtype=np.float32) for k, v in vis.items()}
    for label in sized_labels(scene, sizes):
        res.visibility[label] = own[label]
    res.times["converged"] = time.perf_counter() - t0
    res.name = f"reference (converged, {n_light} light samples" + "".join(
        f", {k}={v:g}" for k, v in sorted(sizes.items())) + ")"
    return res


def sized_labels(scene, sizes: dict | None) -> list:
    """The labels of ``scene``'s emitters that ``sizes`` (``light_size``,
    ``angular_diameter``) give a size, as ``raytraced`` reads them
    (:func:`~mi_shadowmap.filters.raytraced.sized_shape`)."""
    from types import SimpleNamespace
    from .filters.raytraced import sized_shape
    from .light_views import emitter_labels
    if not sizes:
        return []
    opts = SimpleNamespace(**{k: sizes.get(k) for k in SIZE_PROPERTIES})
    emitters = list(scene.emitters())
    return [label for e, label in zip(emitters, emitter_labels(emitters))
            if sized_shape(e, opts) is not None]


def size_opinion(scene, spec: dict) -> dict:
    """The sizes the method of ``spec`` gives ``scene``'s delta lights:
    ``{name: value}`` for each of :data:`SIZE_PROPERTIES` its method has (the spec's
    value, else the property's default; None counts as 0), 0 where the scene has no
    light that ``raytraced``'s property of that name acts on (its ``Prop.lights``:
    ``pcss``'s ``light_size`` on an area light gives the reference nothing, area lights
    keep their shape). A method without the property (``hard``) has no opinion on it."""
    from .light_views import emitter_kind
    record = next((m for m in methods_mod.records() if m.name == spec["method"]), None)
    reference = next(m for m in methods_mod.records() if m.name == REFERENCE_METHOD)
    kinds = {emitter_kind(e) for e in scene.emitters()}
    out = {}
    for name in SIZE_PROPERTIES:
        prop = record.property(name) if record is not None else None
        if prop is None:
            continue
        value = float(spec.get(name, prop.default) or 0.0)
        out[name] = value if set(reference.property(name).lights) & kinds else 0.0
    return out


def reference_sizes(scene, specs: list[dict]) -> tuple[dict, list[dict]]:
    """``(main, per_spec)``: the sizes (``{name: value}`` for :data:`SIZE_PROPERTIES`,
    0: no size) of the compare's first reference, and of each spec's.

    Each method is scored against the light it models: a spec's own values
    (:func:`size_opinion`; ``multiview`` and ``pcss`` at their default model the light
    without a size), and for a property its method does not have (``hard``, ``pcf``)
    the first value a compared method gives. ``main`` holds those first values (0 where
    no method has the property). Methods that disagree get one reference per size."""
    opinions = [size_opinion(scene, spec) for spec in specs]
    main = {name: next((o[name] for o in opinions if name in o), 0.0)
            for name in SIZE_PROPERTIES}
    return main, [{name: o.get(name, main[name]) for name in SIZE_PROPERTIES}
                  for o in opinions]


def reference_follows_spp(scene, reference="auto") -> bool:
    """Whether :func:`make_reference` renders ``reference`` at the ``spp`` (and seed) it is
    given, so that it shares a method's camera samples at that spp: the automatic one
    and a method without its own ``spp``; not ``"converged"`` (at ``max(spp, ref_spp)``),
    a spec with its own ``spp``, or a given result."""
    if isinstance(reference, MethodResult) or reference == "converged":
        return False
    if reference == "auto":
        return True
    return "spp" not in method_spec(reference)


def check_emitters(scene, what: str = "shadow to measure") -> None:
    """Raise ValueError if ``scene`` has no emitter (``compare``, ``sweep``, ``tune`` and
    the CLI's ``maps`` call it before they render or make an output folder)."""
    if len(scene.emitters()) == 0:
        raise ValueError(f"shadowmap: the scene has no emitter, so there is no {what}; "
                         "add a light (point, spot, directional, area, projector or an "
                         "environment)")


def check_given_reference(scene, ref: MethodResult) -> None:
    """Raise ValueError, before a method renders, if ``ref`` (a reference given as a
    result) cannot score renders of ``scene``: other emitters, or another image size (every
    method rendered, then scoring failed with "shape mismatch: 'test_vis' has shape (3, 32,
    40) but 'ref_vis' has shape (3, 32, 32)" and nothing was returned)."""
    from .light_views import emitter_labels
    labels = sorted(emitter_labels(scene.emitters()))
    if sorted(ref.visibility) != labels:
        raise ValueError(f"shadowmap: the reference given ({ref.name!r}) has the emitters "
                         f"{', '.join(sorted(ref.visibility)) or 'none'}, the scene "
                         f"{', '.join(labels)}: give a reference rendered from this scene")
    sensors = scene.sensors()
    if not len(sensors):
        return
    w, h = (int(c) for c in sensors[0].film().crop_size())
    shapes = sorted({tuple(np.shape(v)) for v in ref.visibility.values()})
    if shapes != [(h, w)]:
        got = " and ".join(f"{s[1]} x {s[0]}" if len(s) == 2 else str(s) for s in shapes)
        raise ValueError(f"shadowmap: the reference given ({ref.name!r}) is {got} pixels, "
                         f"the scene's film renders {w} x {h}: give a reference rendered "
                         "at the scene's film size")


def make_reference(scene, reference="auto", spp: int = 16, seed: int = 0, ref_spp: int = 64,
                   ref_shadow_rays: int = 64, repeats: int = 1,
                   measure_cached: bool = True, step=None,
                   sizes: dict | None = None) -> MethodResult:
    """Render the reference (see the module docstring).

    ``reference`` is ``"auto"`` (at ``spp``), ``"converged"`` (rendered at ``max(spp,
    ref_spp)`` spp with ``ref_shadow_rays``), a method name / spec dict
    (rendered at ``spp`` unless it has its own), or an existing
    :class:`~mi_shadowmap.timing.MethodResult`. A method's render is timed as
    :func:`~mi_shadowmap.timing.run_method` times it (``repeats``, ``measure_cached``),
    so the reference's row of :func:`~mi_shadowmap.harness.compare`'s table is timed as
    its methods' are. ``step``, if given, is called with a description before each
    render (two for the converged reference: its image and its visibility; one
    otherwise): :func:`~mi_shadowmap.sweep.sweep` shows them in a progress bar.

    ``sizes`` (``{"light_size": w, "angular_diameter": a}``, :func:`reference_sizes`)
    give the automatic and the converged reference's delta lights a size: ``raytraced``
    renders them so, with ``ref_shadow_rays`` shadow rays (a reference given as a method
    or a result is used as it is).
    """
    check_emitters(scene)
    sizes = {k: float(v) for k, v in (sizes or {}).items() if v}
    if isinstance(reference, MethodResult):
        check_given_reference(scene, reference)
        ref = reference
    elif reference == "converged" or (reference == "auto" and has_soft_lights(scene)):
        # "converged" has camera samples of its own (another seed): at the methods' seed
        # and spp >= ref_spp it rendered their very samples (raytraced scored 1e-8 against
        # it at 64 spp, 0.018 at 16 spp)
        ref = converged_reference(scene, spp=spp if reference == "auto" else max(spp, ref_spp),
                                  seed=seed if reference == "auto" else derived_seed(seed, 1),
                                  shadow_rays=ref_shadow_rays, repeats=repeats,
                                  measure_cached=measure_cached, step=step, sizes=sizes)
    else:
        spec = dict(method_spec(REFERENCE_METHOD if reference == "auto" else reference))
        if reference == "auto" and sized_labels(scene, sizes):
            spec.update(sizes, shadow_rays=ref_shadow_rays)
        own_spp = "spp" in spec
        r_spp = spec.pop("spp", spp)
        if step is not None:
            step(spec_name({**spec, "spp": r_spp}))
        ref = run_method(scene, spec.pop("method"), spp=r_spp, seed=seed, repeats=repeats,
                         measure_cached=measure_cached, **spec)
        if own_spp:     # named with it ("raytraced:spp=64" was "reference (raytraced)")
            ref.name = spec_name({"method": ref.method, **ref.params, "spp": ref.spp})
        ref.name = "reference (" + ref.name + ")"
    ref.is_reference = True
    return ref


def score(result: MethodResult, reference: MethodResult) -> dict:
    """Metrics of ``result`` against ``reference``: pooled over emitters (flat
    ``vis_*`` and ``img_*`` keys) and per emitter (``per_emitter[label]``)."""
    if sorted(result.visibility) != sorted(reference.visibility):
        raise ValueError(f"emitters differ: {sorted(result.visibility)} vs reference "
                         f"{sorted(reference.visibility)}")
    pooled = metrics.visibility_metrics(reference.vis_stack(), result.vis_stack())
    m = {f"vis_{k}": v for k, v in pooled.items()}
    m["per_emitter"] = {label: metrics.visibility_metrics(reference.visibility[label],
                                                          result.visibility[label])
                        for label in sorted(reference.visibility)}
    if reference.image is not None and result.image is not None:
        img = metrics.image_metrics(reference.image, result.image)
        m.update({f"img_{k}": v for k, v in img.items()})
    return m
