"""Parameter sweeps: grids of method specs, the Pareto front of time vs error, and the
equal-time / equal-error comparisons against ray tracing.

* :func:`expand_grid` turns a grid (``{"method": [...], "resolution": [...]}``,
  or a list of such sub-grids) into validated method specs; a property is
  crossed only with the methods that use it
  (:func:`~mi_shadowmap.specs.uses_property`).
* :func:`sweep` renders every spec against one reference and returns a
  :class:`SweepTable`; :func:`analyse` adds the trade-off columns to rows
  (and re-ranks rows on another time axis).

Method names come from the registry, so user methods
(:func:`mi_shadowmap.register_method`) sweep like built-ins.
"""
from __future__ import annotations

import itertools
import json
import math
import warnings

import numpy as np

from . import metrics
from .ground_truth import (has_soft_lights, make_reference, reference_sizes, score,
                           sized_labels)
from .options import OptionError, parse_options
from .scenes import load_scene
from .specs import (REFERENCE_METHOD, RENDER_KEYS, available_methods, check_run_args,
                    check_no_shared_method, derived_seed, map_methods,
                    property_record, spec_name, users_of, uses_property, validate_property,
                    validate_spec)
from .tables import columns, format_sweep, write_csv, write_json
from .timing import (MethodResult, check_scored_film, config_error, rendered_spp,
                     run_method)


#: Error columns a sweep can trade against time (lower is better; ``error_key``), besides
#: the per-emitter ``vis_rmse[<label>]``, ``vis_misclassified[<label>]`` and
#: ``vis_penumbra_rmse[<label>]``.
ERROR_KEYS = ("vis_rmse", "vis_mae", "vis_misclassified", "vis_false_shadow",
              "vis_false_lit", "vis_penumbra_rmse", "img_rmse", "img_mae",
              "img_relative_mse", "img_flip")
#: Time columns of every row (``time_key``; ``time_cached`` implies ``measure_cached``).
TIME_KEYS = tuple(f"time_{k}" for k in ("warm", "cached", "cold", "build", "shading", "jit",
                                         "compile"))


def check_keys(scene, time_key: str, error_key: str) -> None:
    """Raise OptionError, before anything renders, for a ``time_key`` or ``error_key``
    that is no time or error column of a sweep of ``scene`` (a misspelt one made every
    row's error NaN, no row on the Pareto front, and a misspelt time key failed after
    every configuration had rendered)."""
    if time_key not in TIME_KEYS:
        raise OptionError(f"shadowmap: unknown time_key {time_key!r}; valid: "
                          + ", ".join(TIME_KEYS))
    if error_key in ERROR_KEYS:
        return
    from .light_views import emitter_labels
    labels = emitter_labels(scene.emitters())
    per = [f"{k}[{label}]" for label in labels
           for k in ("vis_rmse", "vis_misclassified", "vis_penumbra_rmse")]
    if error_key not in per:
        raise OptionError(f"shadowmap: unknown error_key {error_key!r}; valid (lower is "
                          f"better): {', '.join(ERROR_KEYS)}, or per emitter "
                          f"{', '.join(per[:3])}, ...")


# --------------------------------------------------------------------------- grids
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
                              "methods: " + ", ".join(available_methods()))
        axes = {k: grid_values(k, v) for k, v in sub.items()}
        methods = axes.pop("method")
        for m in methods:
            parse_options({"method": m})   # unknown method: error naming the valid ones
        for k in axes:
            if k in RENDER_KEYS:
                continue
            for v in axes[k]:
                validate_property(k, v)   # unknown name or bad value
            if not any(uses_property(m, k) for m in methods):
                raise OptionError(
                    f"shadowmap: property '{k}' in the sweep grid is not used by any of the "
                    f"methods {', '.join(methods)} (it is used by: "
                    f"{', '.join(users_of(k)) or 'no method'})")
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


def grid_values(key, v) -> list:
    """The values of one grid axis: a list, or a scalar (one value). A 'pair'
    property's two numbers (``[0.0, 0.1]``) are one value, not two."""
    prop = property_record(key)
    if prop is not None and prop.kind == "pair" and isinstance(v, (list, tuple)) and \
            len(v) == 2 and all(isinstance(x, (int, float)) for x in v):
        return [tuple(v)]
    if isinstance(v, (list, tuple)):
        if not v:
            raise OptionError(f"shadowmap: sweep grid values of '{key}' are empty")
        return [tuple(x) if isinstance(x, list) else x for x in v]
    return [v]


def default_grid() -> list[dict]:
    """Every map method at three resolutions, and ``raytraced`` at 1..16 spp."""
    return [{"method": map_methods(), "resolution": [256, 512, 1024]},
            {"method": REFERENCE_METHOD, "spp": [1, 2, 4, 8, 16]}]


def with_shared(grid, params: dict) -> list[dict]:
    """``grid`` (a dict or a list of sub-grids) with the shared ``params`` added as
    fixed axes of every sub-grid that has a method using them (a sub-grid's own
    axis wins). A shared property that no method of the grid uses is an error, and so
    is a shared ``method`` (the grid's own axis names the methods)."""
    check_no_shared_method(params)
    subgrids = [grid] if isinstance(grid, dict) else list(grid)
    out = []
    for g in subgrids:
        if isinstance(g, dict):
            ms = g.get("method", [])
            ms = [ms] if isinstance(ms, str) else list(ms)
            g = {**{k: v for k, v in params.items()
                    if k not in g and (k in RENDER_KEYS
                                       or any(uses_property(m, k) for m in ms))}, **g}
        out.append(g)
    for k, v in params.items():
        if k in RENDER_KEYS:
            continue
        validate_property(k, v)
        if not any(isinstance(g, dict) and k in g for g in out):
            raise OptionError(f"shadowmap: property '{k}' is not used by any method of the "
                              f"grid (it is used by: {', '.join(users_of(k)) or 'no method'})")
    return out


# --------------------------------------------------------------------------- Pareto
def analyse(rows: list[dict], time_key="time_warm", error_key="vis_rmse") -> list[dict]:
    """Add ``time``, ``error``, ``pareto`` and the equal-time/equal-error columns
    (see :class:`SweepTable`) to ``rows``, in place; returns them.

    A ``time_key`` or ``error_key`` that a rendered row (one without ``failed``) does
    not have is a ValueError naming it (every row's time was NaN, and the Pareto front
    failed with "argument 'times' has 3 non-finite value(s)"; an unknown error column
    gave every row a NaN error): ``time_cached`` is a column of sweeps rendered with
    ``measure_cached=True`` only."""
    for key in (time_key, error_key):
        lacking = [r.get("name", "?") for r in rows if not r.get("failed") and key not in r]
        if lacking:
            have = sorted({k for r in rows for k in r if k.startswith(("time_", "vis_", "img_"))})
            why = (" (a sweep has it with measure_cached=True or time_key='time_cached')"
                   if key == "time_cached" else "")
            raise ValueError(f"shadowmap: analyse: {len(lacking)} row(s) ({lacking[0]}, ...) "
                             f"have no column {key!r}{why}; their time and error columns: "
                             + ", ".join(have))
    for r in rows:
        t = r.get(time_key)       # none: a configuration that failed (column 'failed')
        r["time"] = float(t) if t is not None else math.nan
        e = r.get(error_key)
        r["error"] = float(e) if e is not None else math.nan
    ok = [i for i, r in enumerate(rows) if math.isfinite(r["error"])]
    mask = np.zeros(len(rows), dtype=bool)
    if ok:
        front = metrics.pareto_front([rows[i]["time"] for i in ok], [rows[i]["error"] for i in ok])
        mask[np.asarray(ok)[front]] = True
    rt = [r for r in rows if r["method"] == REFERENCE_METHOD and math.isfinite(r["error"])]
    for r, p in zip(rows, mask):
        r["pareto"] = bool(p)
        if r["method"] == REFERENCE_METHOD:   # the comparisons are against ray tracing
            r.update(rt_error_equal_time=None, error_ratio_equal_time=None,
                     rt_time_equal_error=None, speedup_equal_error=None)
            continue
        within = [q["error"] for q in rt if q["time"] <= r["time"]]
        r["rt_error_equal_time"] = min(within) if within else None
        r["error_ratio_equal_time"] = _ratio(r["rt_error_equal_time"], r["error"]) \
            if within else None
        better = [q["time"] for q in rt if q["error"] <= r["error"]]
        r["rt_time_equal_error"] = min(better) if better else None
        r["speedup_equal_error"] = (r["rt_time_equal_error"] / r["time"]
                                    if better and r["time"] > 0 else None)
    return rows


def best_row(rows, key: str = "error", largest: bool = False) -> dict | None:
    """The row of ``rows`` with the lowest (``largest``: the highest) ``key``, among those
    where it is a finite number; None if no row has one. A configuration that failed
    (column ``failed``) has NaN ``time`` and ``error`` and is never picked: ``min(rows,
    key=...)`` could return it (NaN compares false, so a failed first row stays the
    minimum), and then no result of the sweep has its name."""
    ok = [r for r in rows if isinstance(r.get(key), (int, float, np.number))
          and not isinstance(r.get(key), bool) and math.isfinite(r[key])]
    if not ok:
        return None
    return (max if largest else min)(ok, key=lambda r: r[key])


def _ratio(rt_error: float, error: float) -> float:
    """Ray tracing's error over a row's: 1 where both are 0 (a tie: a row that ties
    with ray tracing at 0 read as infinitely more accurate), inf where only the row's
    is."""
    if error > 0:
        return rt_error / error
    return 1.0 if rt_error == 0 else math.inf


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
    A rendered row of :func:`sweep` also names its reference: ``scored_against``
    (e.g. ``"reference (raytraced spp=64)"``) and ``reference_spp``.
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
        return columns(self.rows)

    def front(self) -> list[dict]:
        """The Pareto-optimal rows, fastest first."""
        return sorted((r for r in self.rows if r["pareto"]), key=lambda r: r["time"])

    def to_csv(self, path) -> None:
        write_csv(self.rows, path)

    def to_json(self, path) -> None:
        write_json(self.rows, path)

    def format(self) -> str:
        return format_sweep(self.rows, self.error_key)

    def __repr__(self):
        return f"SweepTable({len(self.rows)} rows)\n" + self.format()


# --------------------------------------------------------------------------- sweep
def rendered_specs(scene, specs: list[dict]) -> tuple[list[dict], list[list[int]]]:
    """``specs`` with their ``spp`` replaced by the count the scene's sampler renders
    (:func:`~mi_shadowmap.timing.rendered_spp`), those that then repeat an earlier one
    merged into it; and, per spec kept, the spp asked for that it renders. A merge is
    warned about: a sweep over spp 2, 3, 4, 5 under a ``stratified`` sampler rendered
    4, 4, 4 and 9 spp, and showed three rows of equal error at "different" spp (one of
    them on the Pareto front by timing noise alone)."""
    out, asked, index = [], [], {}
    cache: dict = {}
    for spec in specs:
        s_spp = spec["spp"]
        if s_spp not in cache:
            cache[s_spp] = rendered_spp(scene, s_spp)
        done = {**spec, "spp": cache[s_spp]}
        key = json.dumps(done, sort_keys=True, default=str)
        if key in index:
            asked[index[key]].append(s_spp)
            continue
        index[key] = len(out)
        out.append(done)
        asked.append([s_spp])
    merged = [(spec, a) for spec, a in zip(out, asked) if len(a) > 1 or a[0] != spec["spp"]]
    if merged:
        sensors = scene.sensors()
        sampler = sensors[0].sampler().class_name() if len(sensors) else "sampler"
        what = "; ".join(f"spp={', '.join(map(str, a))} as {spec['spp']} "
                         f"({spec_name({k: v for k, v in spec.items() if k != 'spp'})})"
                         for spec, a in merged)
        warnings.warn(f"shadowmap: the scene's sampler ({sampler}) rounds the sample count: "
                      f"it renders {what}; rows give the spp rendered (column spp) and the "
                      "spp asked for (spp_requested), one row per spp rendered",
                      stacklevel=3)
    return out, asked


def sweep(scene, grid=None, spp: int = 16, seed: int = 0, repeats: int = 3,
          reference="auto", progress: bool = True, scene_params: dict | None = None,
          ref_spp: int = 64, ref_shadow_rays: int = 64, time_key: str = "time_warm",
          error_key: str = "vis_rmse", keep_images: bool = True,
          measure_cached: bool = False) -> SweepTable:
    """Render every configuration of ``grid`` (see :func:`expand_grid`; default
    :func:`default_grid`) and analyse the time/error trade (see :class:`SweepTable`).

    The reference is rendered once: ``"auto"`` is ``raytraced`` at
    ``max(ref_spp, every spp of the grid)`` spp for delta lights (so that no
    configuration is compared with a noisier version of itself), and the
    converged reference for area lights and environments (see
    :func:`~mi_shadowmap.ground_truth.make_reference`). As in
    :func:`~mi_shadowmap.harness.compare`, ``"auto"`` and ``"converged"`` give delta
    lights the size the configurations give them (``light_size``,
    ``angular_diameter``; :func:`~mi_shadowmap.ground_truth.reference_sizes`): each
    row is scored against the light it models, rendered with ``ref_shadow_rays``
    shadow rays, one reference per size (a grid of ``pcss:light_size=0.5`` was scored
    against the hard shadow); a method without the property (``hard``) takes the
    first size given. The reference of that first size is the table's
    ``reference``; each row's ``scored_against`` names its own.

    ``time_key`` is the time axis: ``"time_warm"`` (a frame with the depth maps
    rebuilt: geometry or lights changed) or ``"time_cached"`` (maps reused: only
    the camera or materials changed; implies ``measure_cached``). Rows keep
    every ``time_*`` column, so :func:`analyse` can re-rank a copy of the rows
    on another one.

    Rows are named by, and their ``spp`` is, the count the scene's sampler renders
    (:func:`~mi_shadowmap.timing.rendered_spp`); configurations that differ only in an
    spp the sampler rounds to the same count (a ``stratified`` sampler renders 2, 3
    and 4 as 4) are rendered once, as one row, whose ``spp_requested`` lists the
    counts asked for (a warning names them).

    A configuration the scene cannot render -- an :class:`~mi_shadowmap.options.OptionError`
    or :class:`~mi_shadowmap.methods.MethodError` at render time, e.g. a ``resolution``
    over ``memory_budget`` -- does not end the sweep: it is a row with its error
    (column ``failed``; no time, no error, never on the Pareto front), and a warning
    names it; if every configuration fails, an ``OptionError`` names them all. Any
    other error is raised with the rows rendered so far attached, as
    ``exc.sweep_table`` (a :class:`SweepTable`), so that nothing rendered is lost.
    """
    check_run_args(spp=spp, seed=seed, repeats=repeats, ref_spp=ref_spp,
                   ref_shadow_rays=ref_shadow_rays)
    measure_cached = measure_cached or time_key == "time_cached"
    specs = expand_grid(default_grid() if grid is None else grid, default_spp=spp)
    scene = load_scene(scene, **(scene_params or {}))
    check_scored_film(scene)
    check_keys(scene, time_key, error_key)
    specs, asked = rendered_specs(scene, specs)
    max_spp = max(s["spp"] for s in specs)
    # the sizes each configuration gives the delta lights: its reference renders them so
    sized = isinstance(reference, str) and reference in ("auto", "converged")
    main_sizes, own_sizes = (reference_sizes(scene, specs) if sized
                             else ({}, [{} for _ in specs]))
    auto_spec = reference == "auto" and not has_soft_lights(scene)

    def reference_of(sizes: dict, step=None) -> MethodResult:
        given = reference
        if auto_spec:
            given = {"method": REFERENCE_METHOD, "spp": max(ref_spp, max_spp)}
            if sized_labels(scene, sizes):
                given.update({k: v for k, v in sizes.items() if v},
                             shadow_rays=ref_shadow_rays)
        return make_reference(scene, given, spp=max(ref_spp, max_spp),
                              seed=derived_seed(seed, 1), ref_spp=ref_spp,
                              ref_shadow_rays=ref_shadow_rays, step=step,
                              measure_cached=False,    # its times are not used
                              sizes=None if auto_spec else sizes)
    from .progress import bar
    # the reference (the converged one of area lights and environments can take longer
    # than the whole grid) in a bar of its own: it rendered before the sweep's bar began,
    # with nothing shown for that long
    converged = not isinstance(reference, (dict, MethodResult)) and (
        reference == "converged" or (reference == "auto" and has_soft_lights(scene)))
    ref_bar = []      # made at the first render, so that its first line names it

    def step(what: str) -> None:
        if not ref_bar:
            ref_bar.append(bar(total=2 if converged else 1, desc="sweep reference",
                               unit="render", leave=False, disable=not progress,
                               postfix=what))
            return
        ref_bar[0].update(1)         # the previous render is done
        ref_bar[0].set_postfix_str(what)

    try:
        ref = reference_of(main_sizes, step)
        if ref_bar:
            ref_bar[0].update(ref_bar[0].total - ref_bar[0].n)
    finally:
        if ref_bar:
            ref_bar[0].close()
    per_size = {_size_key(main_sizes): ref}
    rows, results, failed = [], [], []
    try:
        for spec, spp_asked, sizes in bar(list(zip(specs, asked, own_sizes)), desc="sweep",
                                          unit="config", disable=not progress):
            spec = dict(spec)
            s_spp = spec.pop("spp")
            method = spec.pop("method")
            try:
                r = run_method(scene, method, spp=s_spp, seed=seed, repeats=repeats,
                               measure_cached=measure_cached, **spec)
            except Exception as e:
                message = config_error(e)
                if message is None:
                    raise
                name = spec_name({"method": method, **spec, "spp": s_spp})
                rows.append({"name": name, "method": method, "spp": s_spp,
                             "spp_requested": spp_asked, "reference": False,
                             **{k: list(v) if isinstance(v, tuple) else v
                                for k, v in spec.items()}, "failed": message})
                failed.append(f"{name}: {message}")
                continue
            r.name = spec_name({"method": r.method, **r.params, "spp": r.spp})
            if _size_key(sizes) not in per_size:
                per_size[_size_key(sizes)] = reference_of(sizes)
            r_ref = per_size[_size_key(sizes)]
            r.metrics = score(r, r_ref)
            if r_ref is not ref:
                r.scored_against = r_ref     # its error layers and heat map too
            row = r.row()
            row["spp_requested"] = spp_asked
            # what every error is against: sweep.csv/json did not say (its spp, kind)
            row["scored_against"], row["reference_spp"] = r_ref.name, r_ref.spp
            rows.append(row)
            if not keep_images:
                r.image, r.visibility = None, {}
            results.append(r)
    except (Exception, KeyboardInterrupt) as e:   # the rows rendered so far are kept
        e.sweep_table = SweepTable(analyse(rows, time_key, error_key), results, time_key,
                                   error_key, ref)
        raise
    if failed and len(failed) == len(rows):
        raise OptionError("shadowmap: every configuration of the sweep failed: "
                          + "; ".join(failed))
    if failed:
        warnings.warn(f"shadowmap: {len(failed)} of {len(rows)} sweep configurations failed "
                      "and are rows with their error (column 'failed'): " + "; ".join(failed),
                      stacklevel=2)
    return SweepTable(analyse(rows, time_key, error_key), results, time_key, error_key, ref)


def _size_key(sizes: dict) -> tuple:
    """A hashable key of a reference's light sizes (0 and None alike: no size), as
    :func:`~mi_shadowmap.harness.compare` keys its references."""
    return tuple(sorted((k, float(v)) for k, v in sizes.items() if v))
