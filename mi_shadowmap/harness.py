"""Run shadow methods on a scene side by side and measure them against a reference.

:func:`compare` renders a reference and each method in one process, with
the same seed, and returns one :class:`MethodResult` per method (the
reference first). Each record holds

* the image and the per-emitter visibility AOVs (``vis_<emitter>``),
* metrics against the reference (:mod:`mi_shadowmap.metrics`), pooled over
  all emitters (flat keys ``vis_rmse``, ``img_psnr``, ...) and per emitter
  (``metrics["per_emitter"][label]``),
* timings in seconds: ``cold`` (first render: kernels traced, compiled or
  loaded from Dr.Jit's cache), ``warm`` (median re-render with every kernel
  cached, depth maps rebuilt), ``build`` (depth-map pass of the warm render),
  ``shading`` (warm - build), ``jit`` (cold - warm: the one-off cost, mostly
  compilation), ``compile`` (code generation + LLVM compile time that
  Dr.Jit's kernel history reports for the cold render; 0 when every kernel
  came from the on-disk cache) and ``cached`` (re-render with the depth maps
  and the kernels cached, i.e. only the camera or materials changed),
* the depth-map memory in bytes and the number of texels built per frame
  (every layer).

The reference (``reference="auto"``) is the ``raytraced`` method at the
same spp and seed when every emitter is a delta light (so its visibility
is the exact per-sample ground truth and its own metrics are 0). When the
scene has an area light, the reference is the converged soft-shadow
visibility: :func:`mi_shadowmap.reference.converged_visibility` when that
module exists, otherwise ``raytraced`` with ``ref_shadow_rays`` stratified
shadow rays per camera sample at ``max(spp, ref_spp)`` spp.

:func:`sweep` runs a parameter grid and returns a :class:`SweepTable` with
the Pareto front of time vs error marked and equal-time / equal-error
comparisons against ``raytraced``.

Every method name comes from :data:`mi_shadowmap.options.METHODS`, so new
methods appear here without changes. Every configuration is validated with
:func:`~mi_shadowmap.options.parse_options` before anything renders.
"""
from __future__ import annotations

import csv
import itertools
import json
import math
import os
import re
import time
from dataclasses import dataclass, field

import drjit as dr
import mitsuba as mi
import numpy as np

from . import metrics
from . import options as opt_mod
from .options import OptionError, parse_options
from .reference import converged_visibility

#: Properties (declared for every method) that only affect methods reading a depth map;
#: shared values of these are not passed to ``raytraced``/``unshadowed``.
MAP_ONLY_PROPERTIES = ("resolution", "bias", "slope_bias", "normal_bias", "max_tan_slope",
                       "memory_budget", "cache_maps")
#: Keys of a method spec / sweep grid that are render settings, not integrator properties.
RENDER_KEYS = ("spp",)


# --------------------------------------------------------------------------- records
@dataclass
class MethodResult:
    """Everything measured for one method on one scene."""
    name: str                       # display name (method plus given params)
    method: str
    params: dict                    # integrator properties given (besides method)
    image: np.ndarray | None        # (H, W, 3) linear RGB (None: reference without image)
    visibility: dict                # emitter label -> (H, W) visibility
    times: dict                     # seconds: cold, warm, build, shading, jit, compile
    spp: int = 0
    map_bytes: int = 0
    texels: int = 0
    kernels_compiled: int = 0       # kernels compiled (not cache hits) in the cold render
    metrics: dict = field(default_factory=dict)
    is_reference: bool = False

    def vis_stack(self) -> np.ndarray:
        """Visibility AOVs as an (n_emitters, H, W) array, emitters sorted by label."""
        return np.stack([self.visibility[k] for k in sorted(self.visibility)], axis=0)

    def row(self) -> dict:
        """A flat dict for tables and CSV (pooled metrics, per-emitter RMSE)."""
        r = {"name": self.name, "method": self.method, "spp": self.spp,
             "reference": self.is_reference}
        r.update({k: _plain(v) for k, v in self.params.items()})
        r.update({f"time_{k}": v for k, v in self.times.items()})
        r.update({"map_bytes": self.map_bytes, "texels": self.texels,
                  "kernels_compiled": self.kernels_compiled})
        r.update({k: v for k, v in self.metrics.items() if not isinstance(v, dict)})
        for label, m in self.metrics.get("per_emitter", {}).items():
            for key in ("rmse", "misclassified", "penumbra_rmse"):
                r[f"vis_{key}[{label}]"] = m.get(key)
        return r


def _plain(v):
    return list(v) if isinstance(v, tuple) else v


# --------------------------------------------------------------------------- scenes
def load_scene(scene, **xml_params) -> mi.Scene:
    """An ``mi.Scene`` from a loaded scene, a scene dict, or an XML path.

    ``xml_params`` fill the file's ``$name`` parameters (e.g. ``width=64``);
    a parameter the file does not declare is an error naming it.
    """
    if isinstance(scene, mi.Scene):
        if xml_params:
            raise ValueError("scene parameters (" + ", ".join(xml_params)
                             + ") apply to XML files only, not to a loaded scene")
        return scene
    if isinstance(scene, dict):
        return mi.load_dict(scene)
    path = os.fspath(scene)
    if not os.path.isfile(path):
        raise FileNotFoundError(f"scene file not found: {path}")
    with open(path, encoding="utf-8", errors="replace") as f:
        text = f.read()
    missing = [k for k in xml_params if f"${k}" not in text]
    if missing:
        raise ValueError(f"scene file {path} has no parameter "
                         + ", ".join(f"${k}" for k in missing)
                         + " (declare <default name=... value=.../> to make it settable)")
    return mi.load_file(path, **{k: str(v) for k, v in xml_params.items()})


def emitter_labels(scene: mi.Scene) -> list[str]:
    from .light_views import emitter_label
    return [emitter_label(e, i) for i, e in enumerate(scene.emitters())]


def has_area_lights(scene: mi.Scene) -> bool:
    """True if an emitter is neither a delta light nor an environment (soft shadows)."""
    for e in scene.emitters():
        if e.is_environment():
            continue
        if not (mi.has_flag(e.flags(), mi.EmitterFlags.DeltaPosition)
                or mi.has_flag(e.flags(), mi.EmitterFlags.DeltaDirection)):
            return True
    return False


# --------------------------------------------------------------------------- specs
def method_spec(item, params: dict | None = None) -> dict:
    """Normalise a method item: ``"hard"``, ``{"method": "pcf", "num_samples": 4}`` or
    the string form ``"pcf:num_samples=4,res_factor=2"``.

    ``params`` (shared by every method) are added for the properties the method
    uses; the item's own values win. The result is validated.
    """
    if isinstance(item, str):
        spec = parse_method_string(item)
    elif isinstance(item, dict):
        spec = dict(item)
    else:
        raise OptionError(f"shadowmap: a method must be a name or a dict, got {item!r}")
    if "method" not in spec:
        raise OptionError(f"shadowmap: method spec {item!r} has no 'method'; valid methods: "
                          + ", ".join(opt_mod.METHODS))
    for k, v in (params or {}).items():
        if (k in RENDER_KEYS or uses_property(spec["method"], k)) and k not in spec:
            spec[k] = v
    validate_spec(spec)
    return spec


def uses_property(method: str, name: str) -> bool:
    """Whether a shared value of property ``name`` applies to ``method``: the property
    is declared for it, and it is not a depth-map setting given to a method without a
    map (see :data:`MAP_ONLY_PROPERTIES`)."""
    if name not in {p.name for p in opt_mod.properties_for(method)}:
        return False
    return method in opt_mod.MAP_METHODS or name not in MAP_ONLY_PROPERTIES


def parse_method_string(text: str) -> dict:
    """``"pcf:num_samples=4,res_factor=2"`` -> ``{"method": "pcf", ...}``."""
    name, _, rest = text.partition(":")
    spec = {"method": name.strip()}
    for item in filter(None, (s.strip() for s in rest.split(","))):
        if "=" not in item:
            raise OptionError(f"shadowmap: expected name=value in method spec {text!r}, "
                              f"got {item!r}")
        k, v = item.split("=", 1)
        spec[k.strip()] = parse_value(v.strip())
    return spec


def parse_value(text: str):
    """A command-line value: true/false, int, float, or the string itself."""
    low = text.lower()
    if low in ("true", "false"):
        return low == "true"
    for conv in (int, float):
        try:
            return conv(text)
        except ValueError:
            pass
    return text


def validate_spec(spec: dict) -> opt_mod.Options:
    """Validate one spec (integrator properties plus ``spp``); return its Options."""
    props = {k: v for k, v in spec.items() if k not in RENDER_KEYS}
    if "spp" in spec:
        spp = spec["spp"]
        if isinstance(spp, bool) or not isinstance(spp, int) or spp < 1:
            raise OptionError(f"shadowmap: 'spp' must be an integer >= 1, got {spp!r}")
    return parse_options({"type": "shadowmap", **props})


def validate_property(name: str, value) -> None:
    """Validate one property name and value, whichever method uses it."""
    prop = {p.name: p for p in opt_mod.PROPERTIES}.get(name)
    if prop is None or prop.methods is None or name == "method":
        parse_options({name: value})
    else:
        parse_options({"method": prop.methods[0], name: value})


def check_shared_params(specs: list[dict], params: dict) -> None:
    """A shared parameter that no chosen method uses is an error (typo guard)."""
    for k in params:
        if k in RENDER_KEYS:
            continue
        validate_property(k, params[k])
        if not any(k in s for s in specs):
            users = [m for m in opt_mod.METHODS
                     if k in {p.name for p in opt_mod.properties_for(m)}]
            raise OptionError(
                f"shadowmap: property '{k}' is not used by any of the methods "
                f"{', '.join(s['method'] for s in specs)} (it is used by: {', '.join(users)})")


def spec_name(spec: dict) -> str:
    """Display name: the method plus its given parameters (sorted)."""
    rest = {k: v for k, v in spec.items() if k != "method"}
    return spec["method"] + "".join(f" {k}={_fmt_value(v)}" for k, v in sorted(rest.items()))


def _fmt_value(v):
    if isinstance(v, (tuple, list)):
        return ",".join(str(x) for x in v)
    return str(v)


def available_methods() -> list[str]:
    """Every method of :data:`~mi_shadowmap.options.METHODS`."""
    return list(opt_mod.METHODS)


def default_methods() -> list[str]:
    """Every available method (see :func:`available_methods`) except ``raytraced``."""
    return [m for m in available_methods() if m != "raytraced"]


# --------------------------------------------------------------------------- rendering
def _split(result, aov_names):
    """``(image (H, W, 3), {label: visibility (H, W)})`` of a render.

    The film has 3 colour channels in rgb and spectral variants (spectral films
    develop to RGB) and 1 in mono; a mono image is repeated into 3 grey channels so
    that every metric and output treats all variants alike.
    """
    arr = np.asarray(result, dtype=np.float32)
    n_colour = arr.shape[-1] - len(aov_names)
    image = arr[..., :n_colour]
    image = np.repeat(image, 3, axis=-1) if n_colour == 1 else image.copy()
    vis = {name[len("vis_"):]: arr[..., n_colour + k].copy() for k, name in enumerate(aov_names)}
    return image, vis


def _render_timed(scene, integrator, spp, seed):
    t0 = time.perf_counter()
    img = mi.render(scene, integrator=integrator, spp=spp, seed=seed)
    dr.eval(img)
    dr.sync_thread()
    return img, time.perf_counter() - t0


def _compile_stats(history) -> tuple[float, int]:
    """(seconds of codegen + backend compile, kernels compiled) from dr.kernel_history()."""
    secs, n = 0.0, 0
    for k in history:
        if k.get("type") != dr.KernelType.JIT:
            continue
        secs += (k.get("codegen_time", 0.0) + k.get("backend_time", 0.0)) * 1e-3  # ms -> s
        n += not k.get("cache_hit", 0)
    return secs, n


def _to_mitsuba(props: dict) -> dict:
    """Property values Mitsuba's dict loader accepts ('pair' values as "a, b" strings)."""
    return {k: (", ".join(repr(float(x)) for x in v) if isinstance(v, (tuple, list)) else v)
            for k, v in props.items()}


def run_method(scene: mi.Scene, method: str, spp: int = 16, seed: int = 0,
               repeats: int = 1, measure_cached: bool = True, **params) -> MethodResult:
    """Render ``scene`` with one method: one cold and ``repeats`` warm renders.

    Frames are timed with the depth maps rebuilt in every render
    (``cache_maps=False`` unless given), so ``warm`` = ``build`` + ``shading``
    is the cost of a frame whose geometry or lights changed. With
    ``measure_cached`` a second integrator re-renders with the map cache on
    (one priming render, then the median of ``repeats``): ``times["cached"]``
    is a re-render with maps and kernels both cached.

    The integrator is validated (properties and scene) before anything renders.
    """
    spec = {"method": method, **params}
    validate_spec(spec)
    props = {"type": "shadowmap", **spec}
    cache_prop = method in opt_mod.MAP_METHODS
    if cache_prop and "cache_maps" not in params:
        props["cache_maps"] = False
    integrator = mi.load_dict(_to_mitsuba(props))
    integrator.check_scene(scene)   # clear error before rendering
    had_history = dr.flag(dr.JitFlag.KernelHistory)
    dr.kernel_history()             # drop older entries
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        img, cold = _render_timed(scene, integrator, spp, seed)
        compile_s, n_compiled = _compile_stats(dr.kernel_history())
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, had_history)
    warm, build = [], []
    for _ in range(max(1, repeats)):
        img, t = _render_timed(scene, integrator, spp, seed)
        warm.append(t)
        build.append(integrator.build_seconds)
    warm_t = float(np.median(warm))
    build_t = float(np.median(build))
    image, vis = _split(img, integrator.aov_names())
    maps = [m for m in integrator.maps if m is not None]
    texels = integrator.stats["texels_built"]
    times = {"cold": cold, "warm": warm_t, "build": build_t,
             "shading": max(warm_t - build_t, 0.0), "jit": max(cold - warm_t, 0.0),
             "compile": compile_s}
    if measure_cached:
        if cache_prop and "cache_maps" not in params:
            cached_int = mi.load_dict(_to_mitsuba({**props, "cache_maps": True}))
            _render_timed(scene, cached_int, spp, seed)   # primes the map cache
        else:
            cached_int = integrator
        times["cached"] = float(np.median([_render_timed(scene, cached_int, spp, seed)[1]
                                           for _ in range(max(1, repeats))]))
    return MethodResult(
        name=spec_name(spec), method=method, params=dict(params), image=image, visibility=vis,
        times=times, spp=spp, map_bytes=sum(m.nbytes for m in maps), texels=int(texels),
        kernels_compiled=n_compiled)


def converged_reference(scene: mi.Scene, spp: int = 64, seed: int = 0,
                        shadow_rays: int = 64, n_light: int = 1024) -> MethodResult:
    """The converged soft-shadow reference for scenes with area lights.

    The image is ``raytraced`` with ``shadow_rays`` stratified shadow rays per
    camera sample; the visibility is
    :func:`mi_shadowmap.reference.converged_visibility` (the average of
    ``n_light`` hard shadows from fixed stratified light positions).
    """
    res = run_method(scene, "raytraced", spp=spp, seed=seed, shadow_rays=shadow_rays,
                     measure_cached=False)
    t0 = time.perf_counter()
    vis = converged_visibility(scene, n_light=n_light, seed=seed, spp=spp)
    res.visibility = {k[len("vis_"):]: np.asarray(v, dtype=np.float32) for k, v in vis.items()}
    res.times["converged"] = time.perf_counter() - t0
    res.name = f"reference (converged, {n_light} light samples)"
    return res


def make_reference(scene, reference="auto", spp: int = 16, seed: int = 0, ref_spp: int = 64,
                   ref_shadow_rays: int = 64) -> MethodResult:
    """Render the reference (see the module docstring for ``"auto"``).

    ``reference`` may also be ``"converged"``, a method name / spec dict (rendered
    at ``spp``), or an existing :class:`MethodResult`.
    """
    if isinstance(reference, MethodResult):
        ref = reference
    elif reference == "converged" or (reference == "auto" and has_area_lights(scene)):
        ref = converged_reference(scene, spp=max(spp, ref_spp), seed=seed,
                                  shadow_rays=ref_shadow_rays)
    else:
        spec = method_spec("raytraced" if reference == "auto" else reference)
        spec = dict(spec)
        r_spp = spec.pop("spp", spp)
        ref = run_method(scene, spec.pop("method"), spp=r_spp, seed=seed, **spec)
        ref.name = "reference (" + ref.name + ")"
    ref.is_reference = True
    return ref


# --------------------------------------------------------------------------- metrics
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


# --------------------------------------------------------------------------- compare
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
        Default: every implemented method of ``METHODS`` except ``raytraced``
        (:func:`default_methods`).
    reference : ``"auto"`` | ``"converged"`` | method name | spec dict | MethodResult
        See :func:`make_reference`.
    spp, seed, repeats
        Samples per pixel, seed (shared by all methods) and warm re-renders.
    **params
        Integrator properties shared by every method that uses them (a
        property no listed method uses is an error).

    Everything is validated before the first render.
    """
    specs = [method_spec(m, params) for m in (methods or default_methods())]
    check_shared_params(specs, params)
    if not isinstance(reference, MethodResult) and reference not in ("auto", "converged"):
        method_spec(reference)   # a bad reference spec fails before anything loads
    scene = load_scene(scene, **(scene_params or {}))
    iterator = specs
    if progress:
        from tqdm import tqdm
        iterator = tqdm(specs, desc="methods", unit="method", leave=False)
    ref = make_reference(scene, reference, spp=spp, seed=seed, ref_spp=ref_spp,
                         ref_shadow_rays=ref_shadow_rays)
    results = [ref]
    for spec in iterator:
        spec = dict(spec)
        m_spp = spec.pop("spp", spp)
        r = run_method(scene, spec.pop("method"), spp=m_spp, seed=seed, repeats=repeats,
                       measure_cached=measure_cached, **spec)
        results.append(r)
    for r in results:
        r.metrics = score(r, ref)
    return results


# --------------------------------------------------------------------------- sweep
def expand_grid(grid, default_spp: int = 16) -> list[dict]:
    """Expand a parameter grid into validated, de-duplicated method specs.

    ``grid`` is a dict ``{"method": [...], "resolution": [...], ...}`` (values
    may be scalars or lists; the Cartesian product is taken) or a list of such
    dicts (their union). ``spp`` is a render setting and may be swept too. A
    property is combined only with the methods that use it; a property that no
    method of its sub-grid uses, an unknown property or an invalid value is an
    :class:`~mi_shadowmap.options.OptionError` raised before anything renders.
    """
    subgrids = [grid] if isinstance(grid, dict) else list(grid)
    if not subgrids:
        raise OptionError("shadowmap: the sweep grid is empty")
    specs, seen = [], set()
    for sub in subgrids:
        if not isinstance(sub, dict):
            raise OptionError(f"shadowmap: a sweep grid entry must be a dict, got {sub!r}")
        if "method" not in sub:
            raise OptionError(f"shadowmap: sweep grid entry {sub} has no 'method'; valid "
                              "methods: " + ", ".join(opt_mod.METHODS))
        axes = {k: _grid_values(k, v) for k, v in sub.items()}
        methods = axes.pop("method")
        for m in methods:
            parse_options({"method": m})   # unknown method: error naming the valid ones
        for k in axes:
            if k in RENDER_KEYS:
                continue
            for v in axes[k]:
                validate_property(k, v)   # unknown name or bad value
            if not any(uses_property(m, k) for m in methods):
                users = [m for m in opt_mod.METHODS if uses_property(m, k)]
                raise OptionError(
                    f"shadowmap: property '{k}' in the sweep grid is not used by any of the "
                    f"methods {', '.join(methods)} (it is used by: {', '.join(users)})")
        for m in methods:
            keys = [k for k in axes if k in RENDER_KEYS or uses_property(m, k)]
            for values in itertools.product(*(axes[k] for k in keys)):
                spec = {"method": m, **dict(zip(keys, values))}
                spec.setdefault("spp", default_spp)
                validate_spec(spec)
                key = json.dumps(spec, sort_keys=True, default=str)
                if key not in seen:
                    seen.add(key)
                    specs.append(spec)
    return specs


def _grid_values(key, v) -> list:
    prop = {p.name: p for p in opt_mod.PROPERTIES}.get(key)
    if prop is not None and prop.kind == "pair" and isinstance(v, (list, tuple)) and \
            len(v) == 2 and all(isinstance(x, (int, float)) for x in v):
        return [tuple(v)]
    if isinstance(v, (list, tuple)):
        if not v:
            raise OptionError(f"shadowmap: sweep grid values of '{key}' are empty")
        return [tuple(x) if isinstance(x, list) else x for x in v]
    return [v]


class SweepTable:
    """Rows of a sweep (one dict per configuration) with the analysis columns.

    Columns besides :meth:`MethodResult.row`'s: ``time`` and ``error`` (the
    axes of the trade), ``pareto`` (not dominated in time and error),
    ``rt_error_equal_time`` (lowest error of a ``raytraced`` row that is not
    slower), ``error_ratio_equal_time`` (that / this row's error: > 1 means
    this row is more accurate than ray tracing in the same time),
    ``rt_time_equal_error`` (fastest ``raytraced`` row at least as accurate),
    ``speedup_equal_error`` (that / this row's time: > 1 means faster than ray
    tracing at the same error). ``None`` where no ray-traced row qualifies.
    """

    def __init__(self, rows: list[dict], results: list[MethodResult] | None = None,
                 time_key: str = "time_warm", error_key: str = "vis_rmse",
                 reference: MethodResult | None = None):
        self.rows = rows
        self.results = results or []
        self.time_key, self.error_key = time_key, error_key
        self.reference = reference

    def __len__(self):
        return len(self.rows)

    def __iter__(self):
        return iter(self.rows)

    def __getitem__(self, i):
        return self.rows[i]

    @property
    def columns(self) -> list[str]:
        return list(dict.fromkeys(k for r in self.rows for k in r))

    def front(self) -> list[dict]:
        """The Pareto-optimal rows, fastest first."""
        return sorted((r for r in self.rows if r["pareto"]), key=lambda r: r["time"])

    def to_csv(self, path: str) -> None:
        with open(path, "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=self.columns)
            w.writeheader()
            w.writerows(self.rows)

    def to_json(self, path: str) -> None:
        with open(path, "w") as f:
            json.dump([{k: jsonable(v) for k, v in r.items()} for r in self.rows], f, indent=2)

    def format(self) -> str:
        cols = [("name", "configuration", "{}"), ("error", self.error_key, "{:.4f}"),
                ("time", "time ms", "{:.1f}"), ("pareto", "pareto", "{}"),
                ("error_ratio_equal_time", "err ratio @= time", "{:.2f}"),
                ("speedup_equal_error", "speedup @= error", "{:.2f}")]
        return _table([{**r, "time": r["time"] * 1e3, "pareto": "*" if r["pareto"] else ""}
                       for r in self.rows], cols)

    def __repr__(self):
        return f"SweepTable({len(self.rows)} rows)\n" + self.format()


def analyse(rows: list[dict], time_key="time_warm", error_key="vis_rmse") -> list[dict]:
    """Add ``time``, ``error``, ``pareto`` and the equal-time/equal-error columns."""
    for r in rows:
        r["time"] = float(r[time_key])
        e = r.get(error_key)
        r["error"] = float(e) if e is not None else math.nan
    ok = [i for i, r in enumerate(rows) if math.isfinite(r["error"])]
    mask = np.zeros(len(rows), dtype=bool)
    if ok:
        front = metrics.pareto_front([rows[i]["time"] for i in ok], [rows[i]["error"] for i in ok])
        mask[np.asarray(ok)[front]] = True
    rt = [r for r in rows if r["method"] == "raytraced" and math.isfinite(r["error"])]
    for r, p in zip(rows, mask):
        r["pareto"] = bool(p)
        if r["method"] == "raytraced":   # the comparisons are against ray tracing
            r.update(rt_error_equal_time=None, error_ratio_equal_time=None,
                     rt_time_equal_error=None, speedup_equal_error=None)
            continue
        within = [q["error"] for q in rt if q["time"] <= r["time"]]
        r["rt_error_equal_time"] = min(within) if within else None
        r["error_ratio_equal_time"] = (
            r["rt_error_equal_time"] / r["error"]
            if within and r["error"] > 0 else (math.inf if within else None))
        better = [q["time"] for q in rt if q["error"] <= r["error"]]
        r["rt_time_equal_error"] = min(better) if better else None
        r["speedup_equal_error"] = (r["rt_time_equal_error"] / r["time"]
                                    if better and r["time"] > 0 else None)
    return rows


def default_grid() -> list[dict]:
    """Every map method at three resolutions, and ``raytraced`` at 1..16 spp."""
    return [{"method": list(opt_mod.MAP_METHODS), "resolution": [256, 512, 1024]},
            {"method": "raytraced", "spp": [1, 2, 4, 8, 16]}]


def sweep(scene, grid=None, spp: int = 16, seed: int = 0, repeats: int = 3,
          reference="auto", progress: bool = True, scene_params: dict | None = None,
          ref_spp: int = 64, ref_shadow_rays: int = 64, time_key: str = "time_warm",
          error_key: str = "vis_rmse", keep_images: bool = True,
          measure_cached: bool = False) -> SweepTable:
    """Render every configuration of ``grid`` (see :func:`expand_grid`) and
    analyse the time/error trade (see :class:`SweepTable`).

    The reference is rendered once: ``"auto"`` is ``raytraced`` at
    ``max(ref_spp, every spp of the grid)`` spp for delta lights (so that no
    configuration is compared with a noisier version of itself), and the
    converged reference for area lights (see :func:`make_reference`).

    ``time_key`` is the time axis: ``"time_warm"`` (a frame with the depth maps
    rebuilt: geometry or lights changed) or ``"time_cached"`` (maps reused: only
    the camera or materials changed; implies ``measure_cached``). Rows keep
    every ``time_*`` column, so :func:`analyse` can re-rank a copy of the rows
    on another one.
    """
    measure_cached = measure_cached or time_key == "time_cached"
    specs = expand_grid(default_grid() if grid is None else grid, default_spp=spp)
    scene = load_scene(scene, **(scene_params or {}))
    max_spp = max(s["spp"] for s in specs)
    if reference == "auto" and not has_area_lights(scene):
        reference = {"method": "raytraced", "spp": max(ref_spp, max_spp)}
    ref = make_reference(scene, reference, spp=max(ref_spp, max_spp), seed=seed + 1,
                         ref_spp=ref_spp, ref_shadow_rays=ref_shadow_rays)
    from tqdm import tqdm
    rows, results = [], []
    for spec in tqdm(specs, desc="sweep", unit="config", disable=not progress):
        spec = dict(spec)
        s_spp = spec.pop("spp")
        r = run_method(scene, spec.pop("method"), spp=s_spp, seed=seed, repeats=repeats,
                       measure_cached=measure_cached, **spec)
        r.name = spec_name({"method": r.method, **r.params, "spp": s_spp})
        r.metrics = score(r, ref)
        rows.append(r.row())
        if not keep_images:
            r.image, r.visibility = None, {}
        results.append(r)
    return SweepTable(analyse(rows, time_key, error_key), results, time_key, error_key, ref)


# --------------------------------------------------------------------------- tables
def jsonable(v):
    """A JSON-safe version of a table value (numpy scalars, inf/nan as strings)."""
    if isinstance(v, (np.floating, np.integer, np.bool_)):
        v = v.item()
    if isinstance(v, tuple):
        return [jsonable(x) for x in v]
    if isinstance(v, float) and not math.isfinite(v):
        return str(v)
    return v


def _table(rows: list[dict], cols) -> str:
    body = []
    for row in rows:
        cells = []
        for key, _, fmt in cols:
            v = row.get(key)
            if v is None or (isinstance(v, float) and math.isnan(v)):
                cells.append("-")
            else:
                try:
                    cells.append(fmt.format(v))
                except (ValueError, TypeError):
                    cells.append(str(v))
        body.append(cells)
    head = [c[1] for c in cols]
    widths = [max([len(h)] + [len(r[i]) for r in body]) for i, h in enumerate(head)]
    line = lambda cells: "  ".join(c.ljust(w) for c, w in zip(cells, widths)).rstrip()  # noqa
    return "\n".join([line(head), line(["-" * w for w in widths])] + [line(r) for r in body])


def format_table(results: list[MethodResult]) -> str:
    """A plain-text metrics table (times in ms; rates in %)."""
    cols = [("name", "method", "{}"), ("vis_rmse", "vis RMSE", "{:.4f}"),
            ("vis_penumbra_rmse", "penumbra RMSE", "{:.4f}"),
            ("vis_misclassified", "miscl. %", "{:.2%}"),
            ("vis_false_shadow", "false shd %", "{:.2%}"),
            ("vis_false_lit", "false lit %", "{:.2%}"), ("img_psnr", "PSNR dB", "{:.1f}"),
            ("img_flip", "FLIP", "{:.4f}"),
            ("time_build", "build ms", "{:.1f}"), ("time_shading", "shade ms", "{:.1f}"),
            ("time_warm", "frame ms", "{:.1f}"), ("time_cold", "cold ms", "{:.1f}"),
            ("time_cached", "cached ms", "{:.1f}"),
            ("map_kib", "maps KiB", "{:.0f}")]
    rows = []
    for r in results:
        row = r.row()
        for k in list(row):
            if k.startswith("time_") and row[k] is not None:
                row[k] = row[k] * 1e3
        row["map_kib"] = r.map_bytes / 1024
        rows.append(row)
    return _table(rows, cols)


def safe_name(name: str) -> str:
    """A file-name-safe version of a display name."""
    return re.sub(r"[^A-Za-z0-9_.=,-]+", "_", name).strip("_")
