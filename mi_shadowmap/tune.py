"""The error-budget tuner: the fastest method and settings that meet an error budget.

:func:`tune` answers "which method and settings meet my error budget fastest on
this scene?" It is built on the sweep (:mod:`mi_shadowmap.sweep`): every
configuration it renders is a row of a :class:`~mi_shadowmap.sweep.SweepTable`
(time = warm frame with the maps rebuilt, error = the chosen metric), and the
pick is a point of that table's Pareto front.

1. **Reference** (the policy of :func:`~mi_shadowmap.sweep.sweep`, built with
   :mod:`mi_shadowmap.ground_truth`): ``raytraced`` at many spp for delta
   lights, the converged soft-shadow reference
   (:func:`~mi_shadowmap.ground_truth.converged_reference`) for area lights and
   environments, with a seed of its own. Its spp follow from the budget: two 4-spp
   renders of the reference method measure its pixel-sampling noise, and
   the reference gets enough spp for its own noise to be <= a third of the
   budget (at most ``max_ref_spp``), so that a configuration is never
   charged with much of the reference's noise.
2. **Search** on a reduced-size render of the scene (the film scaled to
   ``search_size`` pixels on its long side; map resolutions scaled with it,
   so texels per pixel -- and times -- scale together): every method's main
   parameters (:data:`MAIN_PARAMETERS`; ``resolution`` for every method that
   reads a map; methods not in the table -- user-registered or new ones --
   get ``resolution`` x ``spp``) are screened at two spp; a model
   ``error^2 = bias^2 + noise^2 / spp`` and ``time = t0 + t1 spp`` per
   configuration then proposes the spp that meets the threshold, and
   configurations are rendered in order of predicted time until none is
   predicted to beat the fastest one found; the contenders (within 1.5x of it)
   are then re-timed in interleaved rounds. The threshold at the reduced size
   is ``max_error x (1 - margin)`` times the ratio of the reference method's
   noise at the two sizes (pixel-sampling and edge errors grow as the image
   shrinks).
3. **Verification** at full size: the finalists -- the fastest rows of the
   Pareto front under the threshold (:data:`FINALISTS`, within
   :data:`FINAL_SLACK`) -- are rendered again at the full size (another seed)
   against a full-size reference (another seed). A finalist passes if its
   error is <= ``max_error x (1 - margin)`` and its error plus two standard
   errors (:func:`error_bound`, estimated from the pixels) is <= ``max_error``,
   so that an independent re-measurement meets the budget too; the fastest
   passing one at full size is the pick. If none passes, the threshold is
   lowered below their errors and the search goes on. The pick is always a
   point of the search's Pareto front.
4. The same for ``raytraced`` alone: the ray-traced configuration that meets
   the same budget. The pick and it are then timed again at full size in
   :data:`TIMING_ROUNDS` interleaved rounds (median warm frame), and the speed
   ratio is its time over the pick's (if ``raytraced`` is searched, on the
   front and faster there, it becomes the pick).

Inputs: a scene path (``scene_params`` fill its ``$`` parameters, e.g.
``{"width": 512}``), a scene dict, or a loaded ``mi.Scene``. The reduced size
is set on the loaded scene through ``mi.traverse`` of its first sensor's film
(size, crop) and restored afterwards, so all three work alike (a loaded scene
is modified while :func:`tune` runs).

Errors (:class:`TuneError`, a ``ValueError``): ``max_error`` <= 0, an unknown
``metric`` (naming the valid ones), and a budget that no configuration meets
(within ``time_limit``), naming the best error reached and its configuration. An
error once the search has begun (that one, a bug, a Ctrl-C) carries what was measured
as ``exc.tune_result``: a result marked ``partial`` (see :meth:`_Tuner.partial`) with
the search's rows and the best pick verified so far, if any, which the CLI writes.
"""
from __future__ import annotations

import itertools
import json
import math
import time

import mitsuba as mi
import numpy as np

from . import metrics
from .ground_truth import (check_emitters, converged_reference, has_area_lights,
                           has_soft_lights, make_reference, reference_sizes, score)
from .options import OptionError
from .scenes import load_scene
from .specs import (REFERENCE_METHOD, available_methods, check_run_args, check_shared_params,
                    derived_seed, method_spec,
                    property_record, spec_name, to_mitsuba, uses_property, validate_spec)
from .sweep import ERROR_KEYS, SweepTable, analyse
from .tables import jsonable
from .timing import (MIN_SCORED_SIDE, MethodResult, check_film, check_scored_film, config_error,
                     film_is_xyz, render_timed, rendered_spp, run_method, sampler_spp,
                     split_channels)

#: Error metrics the tuner accepts (lower is better; the sweep's error columns).
METRICS = ERROR_KEYS

#: Main accuracy parameters of the built-in methods and the values searched, besides
#: ``spp`` (every method) and ``resolution`` (every method that reads a depth map).
#: A method not listed here (user-registered, or one added later) is searched over
#: ``resolution`` x ``spp``, like ``hard``.
MAIN_PARAMETERS = {
    "raytraced": {"shadow_rays": (1, 4, 16)},
    "pcf": {"num_samples": (4, 16, 64)},
    "bilinear": {"kernel": (2, 4)},
    "pcss": {"filter_samples": (16, 64)},
    # the light points K of Heckbert & Herf: the bias of K hard shadows falls with K
    # (a fence under a rectangle light, 64^2, 16 spp against the converged reference at
    # the same camera samples: RMSE 0.0080 / 0.0038 / 0.0026 at K = 32 / 128 / 512 on
    # 256^2 maps), a floor that resolution and spp alone do not lower
    "multiview": {"views": (32, 128, 512)},
}
#: (method, parameter) pairs that change nothing under delta lights (searched only
#: when the scene has an area light or an environment, or the spec gives delta lights a
#: size: ``light_size``, ``angular_diameter``).
AREA_ONLY = {("raytraced", "shadow_rays"), ("pcss", "filter_samples")}
#: (method, parameter) pairs that change nothing but for a light with extent: an area
#: light, or a spec that gives delta lights a size (``light_size``, ``angular_diameter``);
#: an environment's regions have no views (searched where ``sized_lights`` or the spec
#: sizes its lights, see :func:`search_grid`).
SIZED_ONLY = {("multiview", "views")}
#: Searched for every method that reads ``env_lights`` where the scene has an environment
#: emitter: the median-cut regions K, each shadowed from one direction, set a floor that
#: resolution and spp alone do not lower (a ball on a plane under a constant sky, 64^2,
#: 16 spp against the converged reference at the same camera samples: ``hard`` RMSE
#: 0.0247 / 0.0096 at K = 16 / 64, ``pcss`` 0.0162 at 16).
ENVIRONMENT_PARAMETERS = {"env_lights": (16, 64)}
#: Shadow rays per camera sample of the reference where the methods give delta lights a
#: size (``raytraced``'s ``light_size`` / ``angular_diameter``): its spp follow from its
#: measured noise anyway.
SIZED_SHADOW_RAYS = 16
#: The spp at which every configuration is screened (the error/time model's two points).
SCREEN_SPP = (1, 8)
#: The reference's own noise is kept <= this fraction of the budget.
REF_NOISE_FRACTION = 1.0 / 3.0
#: A verified error plus this many standard errors (estimated from the pixels) must
#: meet the budget (see :func:`error_bound`).
CONFIDENCE_Z = 2.0
#: Interleaved timing rounds: of the contenders at the reduced size, of the pick and
#: the raytraced configuration at the full size.
TIMING_ROUNDS = 3
#: Finalists verified (and compared) at full size: at most this many rows of the
#: Pareto front under the threshold, within (1 + FINAL_SLACK) of the fastest one's time.
FINALISTS = 3
FINAL_SLACK = 0.5
#: Contenders re-timed before a pick: at most this many configurations whose fastest
#: row under the threshold is within (1 + CONTEST_SLACK) of the fastest one.
CONTENDERS = 4
CONTEST_SLACK = 0.5


class TuneError(ValueError):
    """Bad input of :func:`tune`, or a budget no configuration meets."""


# --------------------------------------------------------------------------- grids
def resolution_ladder(width: int, height: int, max_resolution: int = 8192) -> list[int]:
    """Map resolutions searched for a ``width`` x ``height`` film: the powers of two
    from above half the film's long side up to 8 times it (at most ``max_resolution``)."""
    long = max(int(width), int(height))
    top = min(8 * long, max_resolution)
    out = [2 ** j for j in range(3, 17) if long / 2 < 2 ** j <= top]
    return out or [min(max(8, 2 ** math.ceil(math.log2(max(long, 1)))), max_resolution)]


def search_grid(specs: list[dict], width: int, height: int, area_lights: bool,
                sized_lights: bool | None = None, environment: bool = False) -> list[dict]:
    """The configurations searched (without ``spp``): each spec's method crossed with
    its main parameters (:data:`MAIN_PARAMETERS`, and ``resolution`` from
    :func:`resolution_ladder` where the method reads a map); a property the spec
    fixes is not searched. ``area_lights``: the scene has an area light or an
    environment (:data:`AREA_ONLY` is searched); ``sized_lights``: it has an area light
    (:data:`SIZED_ONLY` is searched; default ``area_lights``), as it is for a spec whose
    ``light_size`` or ``angular_diameter`` is > 0; ``environment``: it has an environment
    emitter (:data:`ENVIRONMENT_PARAMETERS` are searched). Every configuration is
    validated."""
    if sized_lights is None:
        sized_lights = area_lights
    ladder = resolution_ladder(width, height)
    out, seen = [], set()
    for spec in specs:
        m = spec["method"]
        axes = {}
        if uses_property(m, "resolution") and "resolution" not in spec:
            axes["resolution"] = ladder
        for k, values in MAIN_PARAMETERS.get(m, {}).items():
            if k in spec or not uses_property(m, k):
                continue
            gives_size = any((spec.get(p) or 0) > 0 for p in ("light_size", "angular_diameter"))
            if (m, k) in AREA_ONLY and not (area_lights or gives_size):
                continue
            if (m, k) in SIZED_ONLY and not (sized_lights or gives_size):
                continue
            axes[k] = values
        for k, values in (ENVIRONMENT_PARAMETERS.items() if environment else ()):
            if k not in spec and uses_property(m, k):
                axes[k] = values
        for combo in itertools.product(*axes.values()):
            s = {**spec, **dict(zip(axes, combo))}
            key = json.dumps(s, sort_keys=True, default=str)
            if key in seen:
                continue
            validate_spec(s)
            seen.add(key)
            out.append(s)
    return out


def spp_ladder(max_spp: int) -> list[int]:
    """The spp the search proposes: 1, 2, 3, 4, 6, 8, 12, 16, ... (steps of 1.5x and 4/3x)
    up to ``max_spp`` (and ``max_spp`` itself)."""
    out = {2 ** j for j in range(0, 31)} | {3 * 2 ** j for j in range(0, 30)}
    return sorted(s for s in out if s <= max_spp) + ([max_spp] if max_spp not in out else [])


def rendered_ladder(scene, max_spp: int, spp: int | None = None):
    """``(ladder, screening spp)`` in counts the scene's sampler renders
    (:func:`~mi_shadowmap.timing.rendered_spp`): samplers round the spp they are given
    (a ``stratified`` one renders 2, 3 and 4 as 4, 6 and 8 as 9), so the ladder of
    :func:`spp_ladder` holds the distinct counts rendered, those above ``max_spp``
    dropped (unless none is left); with ``spp`` fixed, the count it renders. Every
    spp the tuner measures, reports and writes into ``integrator.xml`` is one of them:
    before, a pick of "spp=3" rendered 4 and two rows of equal error stood at 3 and 4."""
    if spp is not None:
        s = rendered_spp(scene, spp)
        return [s], (s,)
    done = sorted({rendered_spp(scene, s) for s in spp_ladder(max_spp)})
    ladder = [s for s in done if s <= max_spp] or done[:1]
    screen = []
    for s in SCREEN_SPP:
        if s > max_spp:
            continue
        r = rendered_spp(scene, s)
        r = max([x for x in ladder if x <= r], default=ladder[0])   # r itself if kept
        if r not in screen:
            screen.append(r)
    return ladder, tuple(screen) or (ladder[0],)


# --------------------------------------------------------------------------- input
def check_inputs(max_error, metric="vis_rmse", methods=None, time_limit=None,
                 search_size=128, margin=0.05, max_spp=1024, spp=None, params=None):
    """Validate :func:`tune`'s arguments (nothing renders); returns the method specs
    searched (validated, with the shared ``params``) and the ``raytraced`` spec."""
    if isinstance(max_error, bool) or not isinstance(max_error, (int, float)) \
            or not math.isfinite(max_error) or max_error <= 0:
        raise TuneError(f"shadowmap: tune: max_error must be a number > 0, got {max_error!r}")
    if metric not in METRICS:
        raise TuneError(f"shadowmap: tune: unknown metric {metric!r}; valid metrics (lower is "
                        f"better): {', '.join(METRICS)}")
    if time_limit is not None and (isinstance(time_limit, bool)
                                   or not isinstance(time_limit, (int, float))
                                   or not time_limit > 0):
        raise TuneError(f"shadowmap: tune: time_limit must be > 0 seconds (or None), "
                        f"got {time_limit!r}")
    for name, v, lo in (("search_size", search_size, 8), ("max_spp", max_spp, 1)):
        if isinstance(v, bool) or not isinstance(v, int) or v < lo:
            raise TuneError(f"shadowmap: tune: {name} must be an integer >= {lo}, got {v!r}")
    if spp is not None and (isinstance(spp, bool) or not isinstance(spp, int) or spp < 1):
        raise TuneError(f"shadowmap: tune: spp must be an integer >= 1 (or None), got {spp!r}")
    if isinstance(margin, bool) or not isinstance(margin, (int, float)) \
            or not 0 <= margin < 1:
        raise TuneError(f"shadowmap: tune: margin must be in [0, 1), got {margin!r}")
    params = dict(params or {})
    if "spp" in params:
        raise TuneError("shadowmap: tune: give spp as tune(..., spp=N), not as a property")
    if isinstance(methods, (str, dict)):
        methods = [methods]
    items = list(methods) if methods is not None else available_methods()
    if not items:
        raise TuneError("shadowmap: tune: methods is empty; valid methods: "
                        + ", ".join(available_methods()))
    specs = [method_spec(m, params) for m in items]
    for s in specs:
        if "spp" in s:
            raise TuneError(f"shadowmap: tune: spp in method spec {spec_name(s)!r}; give "
                            "spp as tune(..., spp=N)")
    rt = next((s for s in specs if s["method"] == REFERENCE_METHOD), None)
    rt = rt if rt is not None else method_spec(REFERENCE_METHOD, params)
    check_shared_params(specs + [rt], params)
    return specs, rt


def tune_sizes(scene, specs: list[dict]) -> dict:
    """The sizes (``light_size``, ``angular_diameter``; the non-zero ones) that the
    methods tuned give the scene's delta lights, which the reference and the raytraced
    configurations render (:func:`~mi_shadowmap.ground_truth.reference_sizes`). One
    budget measures every method against one reference: methods that give the lights
    different sizes are an error naming them (tune them one size at a time)."""
    main, own = reference_sizes(scene, specs)
    keys = {tuple(sorted(o.items())) for o in own}
    if len(keys) > 1:
        told = "; ".join(f"{spec_name(sp)}: " + ", ".join(f"{k}={v:g}" for k, v in o.items())
                         for sp, o in zip(specs, own))
        raise TuneError("shadowmap: tune: the methods give the lights different sizes "
                        f"({told}); one budget is measured against one reference, whose "
                        "lights have one size: give every method the same light_size / "
                        "angular_diameter (a shared property), or tune them separately")
    return {k: v for k, v in main.items() if v}


# --------------------------------------------------------------------------- film
class _Film:
    """The first sensor's film size (and crop), set through ``mi.traverse``."""

    def __init__(self, scene):
        sensors = scene.sensors()
        if not sensors:
            raise TuneError("shadowmap: tune: the scene has no sensor")
        self.params = mi.traverse(sensors[0])
        if "film.size" not in self.params:
            raise TuneError("shadowmap: tune: the sensor's film size cannot be changed "
                            "(no 'film.size' in mi.traverse)")
        self.full = tuple(int(x) for x in self.params["film.size"])
        self.crop = (tuple(int(x) for x in self.params["film.crop_size"]),
                     tuple(int(x) for x in self.params["film.crop_offset"]))
        self.current = self.full

    def crop_at(self, size) -> tuple[tuple[int, int], tuple[int, int]]:
        """``(crop size, crop offset)`` of the film at ``size``: the full film's crop
        window scaled with it (the whole film where there is no crop)."""
        return scaled_crop(self.full, *self.crop, size)

    def image_size(self, size) -> tuple[int, int]:
        """The size of the image rendered -- and measured -- with the film at ``size``:
        its crop window's."""
        return self.crop_at(size)[0]

    def set(self, size):
        size = tuple(int(x) for x in size)
        if size == self.current:
            return
        w, h = size
        crop, off = self.crop_at(size)
        self.params["film.size"] = mi.ScalarVector2u(w, h)
        self.params["film.crop_size"] = mi.ScalarVector2u(*crop)
        self.params["film.crop_offset"] = mi.ScalarPoint2u(*off)
        self.params.update()
        self.current = size

    def restore(self):
        if self.current == self.full:
            return
        self.params["film.size"] = mi.ScalarVector2u(*self.full)
        self.params["film.crop_size"] = mi.ScalarVector2u(*self.crop[0])
        self.params["film.crop_offset"] = mi.ScalarPoint2u(*self.crop[1])
        self.params.update()
        self.current = self.full


def reduced_size(size, search_size: int) -> tuple[int, int]:
    """``size`` scaled down so that its long side is at most ``search_size``."""
    W, H = size
    k = min(1.0, search_size / max(W, H))
    return max(1, round(W * k)), max(1, round(H * k))


def scaled_crop(full, crop_size, crop_offset, size) -> tuple[tuple[int, int], tuple[int, int]]:
    """``(crop size, crop offset)`` of a ``full``-size film's crop window
    (``crop_size`` at ``crop_offset``) when the film is resized to ``size``: the window
    scales with the film (the whole film where the window is the whole film)."""
    w, h = (int(x) for x in size)
    W, H = (int(x) for x in full)
    (cw, ch), (ox, oy) = crop_size, crop_offset
    if (cw, ch) == (W, H):
        return (w, h), (0, 0)
    crop = (max(1, round(cw * w / W)), max(1, round(ch * h / H)))
    off = (min(round(ox * w / W), w - crop[0]), min(round(oy * h / H), h - crop[1]))
    return crop, off


def check_search_size(scene, search_size: int) -> None:
    """Raise :class:`TuneError`, before anything renders, if ``search_size`` shrinks
    the image the search measures (the first sensor's film scaled by
    :func:`reduced_size`, its crop window with it: :func:`scaled_crop`) below the
    metrics' :data:`~mi_shadowmap.timing.MIN_SCORED_SIDE` pixels (SSIM's 7 x 7 window),
    naming the smallest ``search_size`` that works. :func:`check_inputs` checks only
    ``search_size >= 8``: a 96 x 64 film searched at 8 is 8 x 5, and the search failed
    after its first renders ("ssim needs images of at least 7x7 pixels")."""
    sensors = scene.sensors()
    if not sensors:
        return
    film = sensors[0].film()
    full = tuple(int(x) for x in film.size())
    crop = (tuple(int(x) for x in film.crop_size()), tuple(int(x) for x in film.crop_offset()))

    def image(s):
        return scaled_crop(full, *crop, reduced_size(full, s))[0]

    w, h = image(search_size)
    if min(w, h) >= MIN_SCORED_SIDE:
        return
    ok = next((s for s in range(search_size + 1, max(full) + 1)
               if min(image(s)) >= MIN_SCORED_SIDE), None)
    if ok is None:       # the full-size image is too small: check_scored_film says so
        return
    fw, fh = reduced_size(full, search_size)
    what = (f", and its {crop[0][0]}x{crop[0][1]} crop window to {w}x{h}"
            if crop[0] != full else "")
    raise TuneError(f"shadowmap: tune: search_size = {search_size} (--search-size) scales the "
                    f"{full[0]}x{full[1]} film to {fw}x{fh} pixels for the search{what}; "
                    f"the metrics need at least {MIN_SCORED_SIDE}x{MIN_SCORED_SIDE} "
                    f"(SSIM's window): use search_size >= {ok} (--search-size {ok})")


# --------------------------------------------------------------------------- model
class _Config:
    """One searched configuration (full-size properties, no spp) and its measurements
    at the reduced size: ``points[spp] = (error, seconds)``."""

    def __init__(self, spec: dict, searched: bool):
        self.spec = dict(spec)
        self.method = spec["method"]
        self.key = spec_name(spec)
        self.searched = searched      # a candidate (else: only for the raytraced comparison)
        self.points: dict = {}
        self.failed: str | None = None

    def _fit_error(self):
        pts = [(s, e) for s, (e, _) in self.points.items() if math.isfinite(e)]
        if not pts:
            return None
        s = np.array([p[0] for p in pts], float)
        e2 = np.array([p[1] for p in pts], float) ** 2
        if len(pts) == 1:
            return 0.0, float(e2[0] * s[0])      # noise only (optimistic, then measured)
        a, c = np.linalg.lstsq(np.stack([np.ones_like(s), 1 / s], 1), e2, rcond=None)[0]
        if a < 0:
            a, c = 0.0, float(np.sum(e2 / s) / np.sum(1 / s ** 2))
        if c < 0:
            a, c = float(np.mean(e2)), 0.0
        return float(a), float(c)

    def predict_error(self, spp: int) -> float:
        fit = self._fit_error()
        return math.inf if fit is None else math.sqrt(max(fit[0] + fit[1] / spp, 0.0))

    def predict_time(self, spp: int) -> float:
        pts = sorted((s, t) for s, (_, t) in self.points.items())
        if not pts:
            return math.inf
        s = np.array([p[0] for p in pts], float)
        t = np.array([p[1] for p in pts], float)
        if len(pts) == 1:
            t0, t1 = 0.0, t[0] / s[0]
        else:
            t0, t1 = np.linalg.lstsq(np.stack([np.ones_like(s), s], 1), t, rcond=None)[0]
            if t1 <= 0:   # timing noise: assume half of the largest-spp frame is per sample
                t0, t1 = 0.5 * float(np.min(t)), 0.5 * t[-1] / s[-1]
            t0 = max(float(t0), 0.0)
        below = [tt for ss, tt in pts if ss <= spp]
        return max(t0 + t1 * spp, max(below) if below else 0.0)

    def next_spp(self, tau: float, ladder: list[int]):
        """The smallest untried spp of ``ladder`` predicted to meet ``tau``, between the
        largest spp that missed it and the smallest that met it; where the model predicts
        none there but a measured spp met ``tau``, the middle of that bracket (a
        bisection: a metric the model does not fit, e.g. misclassified pixels, whose
        1- and 8-spp errors predicted a floor above ``tau``, went from 8 straight to the
        1024 a probe measured, 7x slower than the 64 that met it); None if none."""
        missed = [s for s, (e, _) in self.points.items() if not e <= tau]
        met = [s for s, (e, _) in self.points.items() if e <= tau]
        lo, hi = max(missed, default=0), min(met, default=math.inf)
        between = [s for s in ladder if lo < s < hi and s not in self.points]
        for s in between:
            if self.predict_error(s) <= tau:
                return s
        if between and math.isfinite(hi):
            return between[len(between) // 2]
        return None


# --------------------------------------------------------------------------- tuner
class _Tuner:
    def __init__(self, scene, max_error, metric, specs, rt_spec, time_limit, search_size,
                 margin, seed, repeats, max_spp, max_ref_spp, ref_light_samples, spp,
                 progress, sizes=None):
        self.scene = scene
        #: the delta lights' sizes the reference renders (tune_sizes)
        self.sizes = dict(sizes or {})
        self.B, self.metric = float(max_error), metric
        self.margin, self.seed, self.repeats = margin, seed, repeats
        self.max_ref_spp, self.n_light = max_ref_spp, ref_light_samples
        self.ladder, self.screen_spp = rendered_ladder(scene, max_spp, spp)
        self.t0 = time.perf_counter()
        self.deadline = math.inf if time_limit is None else self.t0 + time_limit
        self.search_deadline = (math.inf if time_limit is None
                                else self.t0 + 0.6 * time_limit)
        self.time_limit = time_limit
        self.time_limited = False
        self.film = _Film(scene)
        self.full = self.film.full
        self.small = reduced_size(self.full, search_size)
        self.k = max(self.small) / max(self.full)     # map resolutions scale with the film
        # the images rendered and measured: the film's crop window at each size
        self.full_image = self.film.image_size(self.full)
        self.small_image = self.film.image_size(self.small)
        self.area = has_soft_lights(scene)   # area lights or an environment
        searched = {s["method"] for s in specs}
        # the ladder follows the film's pixels, as the automatic resolution does: a crop
        # window's pixels are the whole film's, so its maps need the film's density
        sized = has_area_lights(scene)      # multiview's views act on these only
        env = any(e.is_environment() for e in scene.emitters())
        grid = search_grid(specs, *self.full, self.area, sized, env)
        if REFERENCE_METHOD not in searched:
            grid += search_grid([rt_spec], *self.full, self.area, sized, env)
        self.configs = {}
        for s in grid:
            c = _Config(s, searched=s["method"] in searched)
            self.configs[c.key] = c
        self.rows: list[dict] = []
        self.verified: dict = {}      # (key, spp) -> full-size MethodResult
        self.refs: dict = {}
        self.pilots: dict = {}
        self.row_of: dict = {}        # (key, spp) -> sweep row
        self.steps: list = []         # every full-size verification
        self.contested: set = set()
        self.tau0 = self.tau = None   # the initial and the current search threshold
        from .progress import bar
        self.bar = bar(total=4 + len(self.configs) * len(self.screen_spp), desc="tune",
                       unit="render", disable=not progress, leave=False)

    # ------------------------------------------------------------- bookkeeping
    def _tick(self, what: str, extra: int = 0):
        self.bar.set_postfix_str(what[:60], refresh=False)
        if self.bar.n + 1 + extra > self.bar.total:
            self.bar.total = self.bar.n + 1 + extra
        self.bar.update(1)

    def _search_time_left(self) -> bool:
        if time.perf_counter() < self.search_deadline:
            return True
        self.time_limited = True
        return False

    def _time_left(self) -> bool:
        if time.perf_counter() < self.deadline:
            return True
        self.time_limited = True
        return False

    # ------------------------------------------------------------- references
    def _ref_render(self, spp: int, seed: int) -> MethodResult:
        """One render of the reference method at the current film size."""
        if self.area:
            shadow_rays = 16 if self.metric.startswith("img_") else 1
            return converged_reference(self.scene, spp=spp, seed=seed, shadow_rays=shadow_rays,
                                       n_light=self.n_light, sizes=self.sizes)
        if self.sizes:     # delta lights given a size: shadow rays to points of them
            return _render_once(self.scene, REFERENCE_METHOD, spp, seed,
                                shadow_rays=SIZED_SHADOW_RAYS, **self.sizes)
        return _render_once(self.scene, REFERENCE_METHOD, spp, seed)

    def _pilot_noise(self, size) -> float:
        """The metric between two independent 4-spp renders of the reference method."""
        if size in self.pilots:
            return self.pilots[size]
        self.film.set(size)
        a = self._ref_render(4, derived_seed(self.seed, 100))
        b = self._ref_render(4, derived_seed(self.seed, 101))
        w, h = self.film.image_size(size)
        self._tick(f"reference noise at {w}x{h}")
        m = score(b, a)
        v = m.get(self.metric)
        if v is None or not math.isfinite(v):
            v = m["vis_rmse"]
        self.pilots[size] = float(v)
        return float(v)

    def reference(self, which: str) -> MethodResult:
        """The reference at size ``which`` ('small' or 'full'), built once."""
        if which == "full" and self.small == self.full:
            which = "small"
        if which in self.refs:
            return self.refs[which]["result"]
        size = self.small if which == "small" else self.full
        m4 = self._pilot_noise(size)
        # noise of one reference at R spp ~ m4 * sqrt(4) / sqrt(2 R) <= B / 3
        need = (m4 * 2.0 / math.sqrt(2.0) / (REF_NOISE_FRACTION * self.B)) ** 2
        spp = int(min(max(64, 16 * math.ceil(need / 16)), self.max_ref_spp))
        seed = derived_seed(self.seed, 1 if which == "small" else 3)
        self.film.set(size)
        ref = make_reference(self.scene, self._ref_render(spp, seed))
        capped = spp == self.max_ref_spp and need > spp
        spp = ref.spp      # the count rendered (the sampler may round it)
        if not self.area:
            ref.name = f"reference (raytraced spp={spp}" + "".join(
                f" {k}={v:g}" for k, v in sorted(self.sizes.items())) + ")"
        w, h = self.film.image_size(size)
        self._tick(f"reference at {w}x{h}")
        noise = m4 * 2.0 / math.sqrt(2.0 * spp)
        self.refs[which] = {"result": ref, "pilot": m4, "info": {
            "name": ref.name, "method": REFERENCE_METHOD if not self.area else "converged",
            "spp": spp, "seed": seed, "size": list(self.film.image_size(size)),
            **({"light_samples": self.n_light} if self.area else {}),
            **({"sizes": dict(self.sizes)} if self.sizes else {}),
            "noise": noise, "capped": capped}}
        return ref

    # ------------------------------------------------------------- measuring
    def _scaled(self, spec: dict) -> dict:
        props = {k: v for k, v in spec.items() if k != "method"}
        if "resolution" in props and self.k != 1.0:
            props["resolution"] = max(8, 8 * round(props["resolution"] * self.k / 8))
        return props

    def measure(self, c: _Config, spp: int):
        """Render ``c`` at ``spp`` at the reduced size: a sweep row."""
        ref = self.reference("small")
        self.film.set(self.small)
        props = self._scaled(c.spec)
        self._tick(f"{c.key} spp={spp}")
        try:
            r = run_method(self.scene, c.method, spp=spp, seed=self.seed, repeats=self.repeats,
                           measure_cached=False, **props)
        except Exception as e:       # e.g. a resolution over memory_budget: skip the config
            c.failed = _option_error(e)
            return None
        r.metrics = score(r, ref)
        row = r.row()
        row["name"] = spec_name({**c.spec, "spp": spp})
        row["config"] = c.key
        if "resolution" in props:
            row["resolution"], row["search_resolution"] = c.spec["resolution"], props["resolution"]
        e = row.get(self.metric)
        e = float(e) if e is not None and math.isfinite(e) else math.nan
        c.points[spp] = (e, float(row["time_warm"]))
        self.rows.append(row)
        self.row_of[(c.key, spp)] = row
        return row

    def contest(self, tau: float, only=None):
        """Re-time the contenders under ``tau`` -- each configuration's fastest row under
        it, if within :data:`CONTEST_SLACK` of the fastest row -- in
        :data:`TIMING_ROUNDS` interleaved rounds at the reduced size; their times become
        the median of every measurement, so that the pick does not rest on one noisy
        frame time of a loaded machine."""
        best = self.best(tau, only)
        if best is None:
            return
        cands = []
        for c in self.configs.values():
            if c.failed or not self._allowed(c, only):
                continue
            pts = [(t, s) for s, (e, t) in c.points.items() if e <= tau]
            if pts and min(pts)[0] <= best[0] * (1.0 + CONTEST_SLACK):
                cands.append((min(pts)[0], c, min(pts)[1]))
        cands = [x for x in sorted(cands, key=lambda x: x[0])[:CONTENDERS]]
        if len(cands) < 2 or all((c.key, s) in self.contested for _, c, s in cands):
            return
        # (warm, build) of every measurement, the row's first
        runs = {(c.key, s): [(t, float(self.row_of[(c.key, s)].get("time_build", 0.0)))]
                for t, c, s in cands}
        self.film.set(self.small)
        for _ in range(TIMING_ROUNDS):
            for _, c, s in cands:
                if not self._search_time_left():
                    break
                self._tick(f"re-time {c.key} spp={s}", extra=1)
                r = run_method(self.scene, c.method, spp=s, seed=self.seed,
                               repeats=self.repeats, measure_cached=False, **self._scaled(c.spec))
                runs[(c.key, s)].append((float(r.times["warm"]), float(r.times["build"])))
        for _, c, s in cands:
            t = retimed(self.row_of[(c.key, s)], runs[(c.key, s)])
            c.points[s] = (c.points[s][0], t)
            self.contested.add((c.key, s))

    def screen(self):
        """Every configuration at the screening spp, the methods interleaved (each
        method's cheapest configurations first), so that a time limit cuts all
        methods' most expensive configurations rather than whole methods."""
        rank, order = {}, []
        for i, c in enumerate(self.configs.values()):
            rank[c.method] = rank.get(c.method, -1) + 1
            order.append((rank[c.method], i, c))
        for _, _, c in sorted(order, key=lambda x: x[:2]):
            for s in self.screen_spp:
                if c.failed or not self._search_time_left():
                    return
                self.measure(c, s)

    def best(self, tau: float, only=None):
        """``(seconds, error, config, spp)`` of the fastest measured row with error <= tau
        (ties: the lower error) among the candidates (or ``only`` these methods)."""
        found = [(t, e, c, s) for c in self.configs.values()
                 if self._allowed(c, only) and not c.failed
                 for s, (e, t) in c.points.items() if e <= tau]
        return min(found, key=lambda x: (x[0], x[1]), default=None)

    @staticmethod
    def _allowed(c: _Config, only) -> bool:
        return c.method in only if only is not None else c.searched

    def search(self, tau: float, only=None):
        """Render the configurations predicted to beat the fastest one under ``tau``
        (fastest prediction first) until none is; returns :meth:`best`."""
        while self._search_time_left():
            best = self.best(tau, only)
            options = []
            for c in self.configs.values():
                if c.failed or not self._allowed(c, only):
                    continue
                s = c.next_spp(tau, self.ladder)
                if s is None:
                    continue
                tp = c.predict_time(s)
                if best is None or tp < best[0]:
                    options.append((tp, c.key, s))
            if not options:
                break
            _, key, s = min(options)
            self.measure(self.configs[key], s)
        return self.best(tau, only)

    def verify(self, c: _Config, spp: int, search_error=math.nan, search_seconds=math.nan,
               tau=math.nan) -> MethodResult | None:
        """``c`` at ``spp`` at full size (another seed) against the full-size reference
        (logged in ``self.steps``)."""
        key = (c.key, spp)
        if key in self.verified:
            return self.verified[key]
        if not self._time_left():
            return None
        ref = self.reference("full")
        self.film.set(self.full)
        self._tick(f"verify {c.key} spp={spp}", extra=1)
        try:
            r = run_method(self.scene, c.method, spp=spp, seed=derived_seed(self.seed, 2),
                           repeats=self.repeats, measure_cached=False,
                           **{k: v for k, v in c.spec.items() if k != "method"})
        except Exception as e:       # e.g. over memory_budget at full size: next row
            c.failed = _option_error(e)
            return None
        r.metrics = score(r, ref)
        r.name = spec_name({**c.spec, "spp": spp})
        self.verified[key] = r
        ef, ub, ok = self.check(r)
        self.steps.append({"name": r.name, "search_error": search_error,
                           "search_seconds": search_seconds, "threshold": tau, "error": ef,
                           "error_bound": ub, "seconds": float(r.times["warm"]), "ok": ok})
        return r

    def error_of(self, r: MethodResult) -> float:
        e = r.metrics.get(self.metric)
        return float(e) if e is not None and math.isfinite(e) else math.nan

    def check(self, r: MethodResult) -> tuple[float, float, bool]:
        """``(error, upper bound, meets the budget)`` of a full-size result: error <=
        max_error x (1 - margin) and error + 2 standard errors <= max_error."""
        ef = self.error_of(r)
        ub = error_bound(r, self.reference("full"), self.metric)
        ok = ef <= self.B * (1.0 - self.margin) and (not math.isfinite(ub) or ub <= self.B)
        return ef, ub, ok

    def front(self, tau: float = math.inf, only=None) -> list:
        """``(seconds, error, config, spp)`` of the rows on the Pareto front of the
        candidates' rows (or ``only`` these methods') with error <= ``tau``, fastest first."""
        pts = [(t, e, c, s) for c in self.configs.values()
               if self._allowed(c, only) and not c.failed
               for s, (e, t) in c.points.items() if math.isfinite(e)]
        if not pts:
            return []
        mask = metrics.pareto_front([p[0] for p in pts], [p[1] for p in pts])
        return sorted((p for p, m in zip(pts, mask) if m and p[1] <= tau),
                      key=lambda p: (p[0], p[1]))

    def on_front(self, c: _Config, spp: int, only=None) -> bool:
        return any(p[2] is c and p[3] == spp for p in self.front(math.inf, only))

    def pick(self, tau: float, only=None):
        """Search under ``tau``; verify the finalists -- the fastest rows of the Pareto
        front under ``tau`` (at most :data:`FINALISTS`, within (1 + :data:`FINAL_SLACK`)
        of the fastest) -- at full size and return the fastest one there that meets the
        budget, as ``((seconds, error, config, spp), result, tau)``. If none does, lower
        ``tau`` below the most accurate finalist's error and go on. None: nothing meets
        the budget (within ``max_spp`` and the time limit)."""
        target = self.B * (1.0 - self.margin)
        while True:
            self.tau = tau
            self.search(tau, only)
            self.contest(tau, only)
            self.search(tau, only)          # the re-timed rows may open new candidates
            fr = self.front(tau, only)
            if not fr:
                return None
            finalists = [p for p in fr if p[0] <= fr[0][0] * (1.0 + FINAL_SLACK)][:FINALISTS]
            passed, last = [], None
            for p in finalists:
                t, e, c, s = p
                r = self.verify(c, s, e, t, tau)
                if r is None:
                    if c.failed:            # e.g. over memory_budget at full size
                        continue
                    break                   # out of time
                ef, ub, ok = self.check(r)
                if ok:
                    passed.append((p, r))
                else:
                    last = (e, ef, ub)
            if passed:
                best = min(passed, key=lambda x: (x[1].times["warm"], x[0][1]))
                return best[0], best[1], tau
            if not self._time_left():
                return None
            if last is None:                # every finalist failed to run: search on
                continue
            e, ef, ub = last
            ratio = min(target / ef if ef > 0 else 0.5,
                        self.B / ub if ub > 0 and math.isfinite(ub) else 1.0)
            ratio = ratio if math.isfinite(ratio) else 0.5
            tau = min(e * ratio, e * 0.95) if e > 0 else -1.0
            if tau < 0:
                return None

    # ------------------------------------------------------------- run
    def run(self) -> dict:
        try:
            result = self._run()
            # the bar's total is an estimate raised as the search goes on: a finished
            # tune closes at its count (its last line in a log read 99 %, or 67 % after
            # a time limit, as if cut short); a stopped one keeps where it stopped
            self.bar.total = self.bar.n
            return result
        except (Exception, KeyboardInterrupt) as e:   # Ctrl-C, a bug, no pick: keep the search
            try:
                e.tune_result = self.partial(e)
            except Exception:    # the error that stopped the tune is the one to raise
                pass
            raise
        finally:
            self.film.restore()
            self.bar.close()

    def partial(self, exc: BaseException) -> dict:
        """What the tuner measured before ``exc`` stopped it, shaped like :meth:`_run`'s
        result and marked ``partial``: the search's rows (``sweep``), the verifications
        (``steps``) and the best verified pick so far -- the fastest configuration verified
        at full size that meets the budget, a faster one may exist -- in ``method``,
        ``params``, ``spp``, ... (None where none is verified yet); ``interrupted`` (a
        Ctrl-C) and ``stopped_by`` (the error). Before, an interrupted tune kept nothing."""
        from .timing import root_error
        cause = root_error(exc)
        interrupted = isinstance(cause, KeyboardInterrupt)
        small = self.refs.get("small")
        full = self.refs.get("full") if self.small != self.full else small
        table = SweepTable(analyse(self.rows, "time_warm", self.metric), None, "time_warm",
                           self.metric, small["result"] if small else None)
        out = {
            "partial": True, "interrupted": interrupted,
            "stopped_by": ("KeyboardInterrupt" if interrupted else
                           f"{type(cause).__name__}: {' '.join(str(cause).split())}"),
            "method": None, "params": None, "spp": None, "name": None, "error": None,
            "error_bound": None, "seconds": None, "integrator": None, "pareto": None,
            "metric": self.metric, "max_error": self.B,
            "reference": full["info"] if full else None,
            "size": list(self.full_image), "film_size": list(self.full),
            "search": {"size": list(self.small_image), "film_size": list(self.small),
                       "error": None, "seconds": None, "threshold": self.tau,
                       "initial_threshold": self.tau0,
                       "reference": small["info"] if small else None,
                       "configurations": len(self.configs), "renders": len(self.rows)},
            "methods": sorted({x.method for x in self.configs.values() if x.searched}),
            "steps": self.steps, "raytraced": None, "speed_ratio": None, "sweep": table,
            "result": None, "time_limited": self.time_limited,
            "elapsed": time.perf_counter() - self.t0}
        passed = [(float(r.times["warm"]), key) for key, r in self.verified.items()
                  if self.configs[key[0]].searched and self.check(r)[2]] if full else []
        if passed:
            seconds, (key, s) = min(passed)
            c, res = self.configs[key], self.verified[(key, s)]
            params = {k: v for k, v in c.spec.items() if k != "method"}
            row = self.row_of.get((key, s), {})
            out.update(method=c.method, params=params, spp=s,
                       name=spec_name({**c.spec, "spp": s}), error=self.error_of(res),
                       error_bound=self.check(res)[1], seconds=seconds,
                       integrator={"type": "shadowmap", "method": c.method, **params},
                       pareto=self.on_front(c, s), result=res)
            out["search"].update(error=row.get(self.metric), seconds=row.get("time_warm"))
        return out

    def _run(self) -> dict:
        target = self.B * (1.0 - self.margin)
        self.reference("small")
        if self.small != self.full:
            p_full = self._pilot_noise(self.full)
            scale = self.refs["small"]["pilot"] / p_full if p_full > 0 else 1.0
            scale = min(max(scale, 0.5), 2.0)
        else:
            scale = 1.0
        tau0 = self.tau0 = self.tau = target * scale
        self.screen()
        found = self.pick(tau0)
        if found is None and self._probe_largest_spp(tau0):
            found = self.pick(tau0)         # the error model was too pessimistic
        if found is None:
            self._fail()
        (t, e, c, s), res, tau = found
        rt_found = found if c.method == REFERENCE_METHOD else \
            self.pick(tau0, only={REFERENCE_METHOD})
        for _ in range(3):   # rows the raytraced search added may dominate the pick
            if self.on_front(c, s):
                break
            again = self.pick(tau)
            if again is None:
                break
            found = again
            (t, e, c, s), res, tau = found
        seconds = {(c.key, s): float(res.times["warm"])}
        if rt_found is not None and (rt_found[0][2].key, rt_found[0][3]) != (c.key, s):
            (rt_t, rt_e, rt_c, rt_s), rt_res, _ = rt_found
            seconds[(rt_c.key, rt_s)] = float(rt_res.times["warm"])
            seconds.update(self.retime([(c, s), (rt_c, rt_s)]))
            # raytraced verified, on the front and faster at full size: it is the pick
            if rt_c.searched and seconds[(rt_c.key, rt_s)] < seconds[(c.key, s)] and \
                    self.on_front(rt_c, rt_s):
                found = rt_found
                (t, e, c, s), res, tau = found
        if c.method == REFERENCE_METHOD:    # the fastest raytraced one is the pick itself
            rt_found = found
        table = SweepTable(analyse(self.rows, "time_warm", self.metric), None, "time_warm",
                           self.metric, self.refs["small"]["result"])
        name = spec_name({**c.spec, "spp": s})
        params = {k: v for k, v in c.spec.items() if k != "method"}
        out = {
            "method": c.method, "params": params, "spp": s,
            "error": self.error_of(res), "seconds": seconds[(c.key, s)],
            "error_bound": self.check(res)[1], "metric": self.metric, "max_error": self.B,
            "name": name,
            "integrator": {"type": "shadowmap", "method": c.method, **params},
            "reference": self.refs["full" if "full" in self.refs else "small"]["info"],
            "size": list(self.full_image), "film_size": list(self.full),
            "search": {"size": list(self.small_image), "film_size": list(self.small),
                       "error": e, "seconds": t, "threshold": tau,
                       "initial_threshold": tau0, "noise_scale": scale,
                       "reference": self.refs["small"]["info"],
                       "configurations": len(self.configs), "renders": len(self.rows)},
            "pareto": self.on_front(c, s),
            "methods": sorted({x.method for x in self.configs.values() if x.searched}),
            "steps": self.steps, "raytraced": None, "speed_ratio": None,
            "sweep": table, "result": res, "partial": False,
        }
        if rt_found is not None:
            (rt_t, rt_e, rt_c, rt_s), rt_res, rt_tau = rt_found
            rt_params = {k: v for k, v in rt_c.spec.items() if k != "method"}
            out["raytraced"] = {
                "method": REFERENCE_METHOD, "params": rt_params, "spp": rt_s,
                "name": spec_name({**rt_c.spec, "spp": rt_s}),
                "error": self.error_of(rt_res), "seconds": seconds[(rt_c.key, rt_s)],
                "error_bound": self.check(rt_res)[1], "search_error": rt_e,
                "search_seconds": rt_t}
            if out["seconds"] > 0:
                out["speed_ratio"] = out["raytraced"]["seconds"] / out["seconds"]
        out["time_limited"] = self.time_limited
        out["elapsed"] = time.perf_counter() - self.t0
        return out

    def retime(self, picks) -> dict:
        """Full-size warm times of ``picks`` (``(config, spp)``), re-measured in
        :data:`TIMING_ROUNDS` interleaved rounds (median), so that the speed ratio is
        not skewed by a change of load between their verifications."""
        runs = {(c.key, s): [] for c, s in picks}
        self.film.set(self.full)
        for _ in range(TIMING_ROUNDS):
            for c, s in picks:
                if not self._time_left():
                    break
                self._tick(f"time {c.key} spp={s}", extra=1)
                r = run_method(self.scene, c.method, spp=s, seed=derived_seed(self.seed, 2),
                               repeats=self.repeats, measure_cached=False,
                               **{k: v for k, v in c.spec.items() if k != "method"})
                runs[(c.key, s)].append(float(r.times["warm"]))
        if any(not v for v in runs.values()):
            return {}
        return {k: float(np.median(v)) for k, v in runs.items()}

    def _probe_largest_spp(self, tau: float) -> bool:
        """Measure the configuration predicted to be the most accurate at the largest
        spp of the ladder (if not measured yet and time permits); True if it meets
        ``tau``. The error model is fitted on few points (the screening spp) and can
        predict a floor above the truth: then nothing is searched although the largest
        spp would do, which this measurement catches."""
        cands = [c for c in self.configs.values() if c.searched and not c.failed and c.points]
        if not cands or not self._search_time_left():
            return False
        s = self.ladder[-1]
        c = min(cands, key=lambda c: c.predict_error(s))
        if s in c.points:
            return False
        self.measure(c, s)
        return s in c.points and c.points[s][0] <= tau

    def _fail(self):
        """Raise :class:`TuneError` naming the best error reached (the largest spp of
        the most accurate configuration is measured first, see
        :meth:`_probe_largest_spp`)."""
        self._probe_largest_spp(-math.inf)
        best, bound = None, ""
        for (key, _), r in self.verified.items():
            e = self.error_of(r)
            if self.configs[key].searched and math.isfinite(e) and (best is None or e < best[0]):
                best = (e, r.name, self.full_image)
                ub = self.check(r)[1]
                # an error under the budget fails on its bound: say so ("best reachable:
                # 0.08568" read as meeting max_error=0.1)
                bound = (f", {self.metric} + 2 standard errors {ub:.4g}, which must be <= "
                         f"{self.B:g} too" if math.isfinite(ub) and ub > self.B else "")
        if best is None:
            for row in self.rows:
                e = row.get(self.metric)
                if self.configs[row["config"]].searched and e is not None and \
                        math.isfinite(e) and (best is None or e < best[0]):
                    best = (float(e), row["name"], self.small_image)
        within = (f" within time_limit={self.time_limit:g} s" if self.time_limited else "")
        what = (f"; best reachable: {self.metric} {best[0]:.4g} with {best[1]} (measured at "
                f"{best[2][0]}x{best[2][1]}{bound})" if best is not None
                else "; no configuration was measured")
        raise TuneError(f"shadowmap: tune: no configuration meets max_error={self.B:g} "
                        f"({self.metric}, with margin {self.margin:g}){within}{what}")


def retimed(row: dict, runs: list) -> float:
    """Set every timing column of a sweep ``row`` re-timed in ``runs`` (``(warm, build)``
    seconds of each measurement, the row's own first) and return its warm time: the
    medians of the warm frames and of the builds, ``shading`` = warm - build (the build
    capped at the warm time, so that ``time_build + time_shading == time_warm``, as
    :func:`~mi_shadowmap.timing.run_method` gives), ``jit`` = cold - warm (the cold
    render and the compile time are the row's first render's), ``time_rounds`` the
    number of measurements. Before, only ``time_warm`` changed: a row of 14.6 ms warm
    kept build + shading = 23.4 ms."""
    warm = float(np.median([w for w, _ in runs]))
    build = min(float(np.median([b for _, b in runs])), warm)
    row.update(time_warm=warm, time_build=build, time_shading=warm - build,
               time_rounds=len(runs))
    if "time_cold" in row:
        row["time_jit"] = max(float(row["time_cold"]) - warm, 0.0)
    return warm


def error_bound(result: MethodResult, reference: MethodResult, metric: str,
                z: float = CONFIDENCE_Z) -> float:
    """``metric`` of ``result`` plus ``z`` standard errors of it, the standard error
    estimated from the spread of the per-pixel terms the metric averages (RMSE, MAE
    and misclassification rates, visibility or image), pixels taken as independent
    (conservative where errors are spatially structured). An independent re-render
    and reference rarely measure more. ``img_relative_mse`` and ``img_flip``: the
    metric itself (the margin of :func:`tune` covers them)."""
    value = result.metrics.get(metric) if result.metrics else None
    if value is None:
        value = score(result, reference).get(metric)
    if value is None or not math.isfinite(value):
        return math.nan
    kind = metric.split("_", 1)[1]
    if kind in ("rmse", "mae", "penumbra_rmse"):
        if metric.startswith("img_"):
            d = (np.asarray(result.image, np.float64) - reference.image).ravel()
        else:
            ref = reference.vis_stack().astype(np.float64)
            d = result.vis_stack() - ref
            if kind == "penumbra_rmse":
                d = d[(ref > 1e-6) & (ref < 1 - 1e-6)]
            d = d.ravel()
        if d.size < 2:
            return float(value)
        terms = np.abs(d) if kind == "mae" else d ** 2
        hi = float(terms.mean() + z * terms.std(ddof=1) / math.sqrt(terms.size))
        return hi if kind == "mae" else math.sqrt(hi)
    if kind in ("misclassified", "false_shadow", "false_lit"):
        n = reference.vis_stack().size
        return float(value + z * math.sqrt(value * (1 - value) / n))
    return float(value)


def _option_error(exc: BaseException) -> str:
    """The message of the :class:`OptionError` that ``exc`` is or wraps (``mi.render``
    wraps the integrator's errors); re-raises ``exc`` if it is no option error."""
    message = config_error(exc, (OptionError,))
    if message is None:
        raise exc
    return message


def _render_once(scene, method: str, spp: int, seed: int, **props) -> MethodResult:
    """One untimed-beyond-one-frame render of a method (for references)."""
    spec = {"method": method, **props}
    validate_spec(spec)
    integrator = mi.load_dict(to_mitsuba({"type": "shadowmap", **spec}))
    integrator.check_scene(scene)
    check_film(scene)
    img, seconds = render_timed(scene, integrator, spp, seed)
    image, vis = split_channels(img, integrator.aov_names(), xyz=film_is_xyz(scene))
    return MethodResult(name=spec_name(spec), method=method, params=dict(props), image=image,
                        visibility=vis, times={"warm": seconds},
                        spp=sampler_spp(scene) or spp, spp_requested=spp)


# --------------------------------------------------------------------------- API
def tune(scene, max_error: float, metric: str = "vis_rmse", methods=None,
         time_limit: float | None = None, *, scene_params: dict | None = None,
         search_size: int = 128, margin: float = 0.05, seed: int = 0, repeats: int = 3,
         max_spp: int = 1024, max_ref_spp: int = 2048, ref_light_samples: int = 256,
         spp: int | None = None, progress: bool = True, **params) -> dict:
    """The fastest configuration whose ``metric`` meets ``max_error`` on ``scene``.

    Parameters
    ----------
    scene : path, dict or mi.Scene
        An XML file (``scene_params`` fill its ``$`` parameters, e.g.
        ``{"width": 512, "height": 512}``: the full size), a scene dict or a loaded
        scene. The search runs on the first sensor's film scaled down through
        ``mi.traverse`` (restored afterwards).
    max_error : float > 0
        The budget on ``metric`` at the full size.
    metric : str
        One of :data:`METRICS` (default ``vis_rmse``: visibility RMSE pooled over emitters).
    methods : list, optional
        Methods searched: names, or specs whose given properties are kept fixed
        (``"pcf:sampling=gaussian"``). Default: every registered method.
        ``raytraced`` is always measured for the comparison.
    time_limit : float, optional
        Seconds. The search stops at 60 % of it, verification at 100 % (checked
        between renders); a pick verified by then is returned (``time_limited``),
        otherwise :class:`TuneError` names the best error reached.
    search_size : int
        Long side of the reduced film, in pixels (no effect on smaller films).
    margin : float
        The pick must meet ``max_error x (1 - margin)`` at the full size (and its
        error plus two standard errors ``max_error``), so that an independent
        re-measurement (other seeds) meets ``max_error``.
    seed, repeats
        Seed of the search renders (references and verification use other seeds);
        warm re-renders per configuration (median).
    max_spp, spp
        Largest spp searched; or ``spp`` fixed (the search then covers the other
        parameters only).
    max_ref_spp, ref_light_samples
        Cap on the reference's spp (a capped reference is noisier: the budget is then
        harder to meet, never easier); light samples of the converged reference of
        area lights and environments.
    **params
        Integrator properties kept fixed for every method that uses them (an unknown
        property, or one no method uses, is an error).

    Returns
    -------
    dict
        ``method``, ``params`` (integrator properties besides ``method``), ``spp``,
        ``error`` and ``seconds`` (full size, verified: warm frame with the maps
        rebuilt), ``reference`` (the full-size reference: name, spp, seed, ...),
        ``raytraced`` (the fastest verified ``raytraced`` configuration meeting the
        same budget: ``params``, ``spp``, ``error``, ``seconds``; None if none within
        ``max_spp``/time), ``speed_ratio`` (its seconds / the pick's), ``integrator``
        (a dict for ``mi.load_dict``), ``size`` (the image measured at full size: the
        film's crop window; ``film_size`` the film's), ``search`` (reduced size --
        the crop window's at the reduced film, ``film_size`` the film's -- threshold, the
        pick's error and seconds there), ``sweep`` (the search's
        :class:`~mi_shadowmap.sweep.SweepTable`), ``pareto`` (the pick is on the Pareto
        front of the searched methods' rows -- with ``methods=None``, of the whole sweep;
        with a list without ``raytraced``, the raytraced rows measured for the comparison
        may dominate it), ``methods`` (the methods searched), ``steps`` (verifications),
        ``time_limited``, ``elapsed``, ``partial`` (False).

    An error once rendering has begun -- a budget no configuration meets, a bug, Ctrl-C --
    carries the search so far as ``exc.tune_result``: the same fields, ``partial`` True,
    ``interrupted`` (a Ctrl-C), ``stopped_by``, ``sweep`` the rows rendered, and the pick
    fields the fastest configuration verified at full size that meets the budget (a
    faster one may exist), or None where none is verified yet.
    """
    specs, rt_spec = check_inputs(max_error, metric, methods, time_limit, search_size, margin,
                                  max_spp, spp, params)
    if isinstance(max_ref_spp, bool) or not isinstance(max_ref_spp, int) or max_ref_spp < 1:
        raise TuneError(f"shadowmap: tune: max_ref_spp must be an integer >= 1, "
                        f"got {max_ref_spp!r}")
    check_run_args(seed=seed, repeats=repeats)
    if spp is not None and spp > max_spp:
        raise TuneError(f"shadowmap: tune: spp = {spp} is more than max_spp = {max_spp}")
    scene = load_scene(scene, **(scene_params or {}))
    check_emitters(scene)
    check_scored_film(scene)
    check_search_size(scene, search_size)
    sizes = tune_sizes(scene, specs)
    rt_spec = {**{k: v for k, v in sizes.items() if k not in rt_spec}, **rt_spec}
    tuner = _Tuner(scene, max_error, metric, specs, rt_spec, time_limit, search_size, margin,
                   seed, repeats, max_spp, max_ref_spp, ref_light_samples, spp, progress,
                   sizes)
    return tuner.run()


# --------------------------------------------------------------------------- outputs
_XML_TYPES = {"int": "integer", "float": "float", "bool": "boolean", "str": "string",
              "pair": "string"}


def _xml_value(kind: str, v) -> str:
    if kind == "bool":
        return "true" if v else "false"
    if kind == "pair":
        return ", ".join(repr(float(x)) for x in v)
    if kind == "float":
        return repr(float(v))
    return str(v)


def integrator_xml(result: dict) -> str:
    """A ready-to-paste ``<integrator type="shadowmap">`` element of the pick, typed
    properties, with comments giving the spp and the measured numbers."""
    m = result["method"]
    W, H = result["size"]
    note = (f"mi-shadowmap tune: {result['metric']} {result['error']:.4g} (budget "
            f"{result['max_error']:g}) at {W}x{H}, {result['seconds'] * 1e3:.1f} ms per frame "
            "with the maps rebuilt")
    rt = result.get("raytraced")
    if rt is not None and result.get("speed_ratio"):
        note += (f"; raytraced at the same budget: {rt['name']}, {rt['seconds'] * 1e3:.1f} ms "
                 f"({result['speed_ratio']:.2f}x)")
    if result.get("partial"):     # an interrupted tune's best verified pick so far
        note = ("PARTIAL, the tune did not finish (" + ("interrupted" if result["interrupted"]
                else "stopped by an error") + "): the best configuration verified so far, "
                "a faster one may exist; " + note)
    lines = [f"<!-- {note.replace('--', '-')} -->",
             f"<!-- render with spp={result['spp']}: <integer name=\"sample_count\" "
             f"value=\"{result['spp']}\"/> in the sensor's sampler -->",
             '<integrator type="shadowmap">',
             f'    <string name="method" value="{m}"/>']
    for k, v in result["params"].items():
        prop = property_record(k)
        kind = prop.kind if prop is not None else ("bool" if isinstance(v, bool) else
                                                   "int" if isinstance(v, int) else
                                                   "float" if isinstance(v, float) else "str")
        lines.append(f'    <{_XML_TYPES[kind]} name="{k}" value="{_xml_value(kind, v)}"/>')
    lines.append("</integrator>")
    return "\n".join(lines) + "\n"


def format_result(result: dict) -> str:
    """The choice as text: the pick, the raytraced configuration at the same budget,
    the speed ratio, the search and the verification steps (of a partial result,
    ``exc.tune_result``: what was searched and the best pick verified so far)."""
    if result.get("partial"):
        return _format_partial(result)
    W, H = result["size"]
    se = result["search"]
    m = result["metric"]
    lines = [f"tune: {m} <= {result['max_error']:g} at {W}x{H}; searched at "
             f"{se['size'][0]}x{se['size'][1]} ({se['renders']} renders of "
             f"{se['configurations']} configurations, threshold {se['threshold']:.4g}; "
             f"{'time limit reached, ' if result['time_limited'] else ''}"
             f"{result['elapsed']:.0f} s)",
             f"pick:      {result['name']}",
             f"           {m} {result['error']:.4g} (+2 s.e.: {result['error_bound']:.4g}), "
             f"{result['seconds'] * 1e3:.1f} ms per frame (maps rebuilt), against "
             f"{result['reference']['name']} (seed {result['reference']['seed']})"]
    rt = result.get("raytraced")
    if rt is None:
        lines.append("raytraced: no configuration meets the budget within the search")
    elif rt["name"] == result["name"]:
        lines.append("raytraced: the pick is ray traced (speed ratio 1)")
    else:
        lines.append(f"raytraced: {rt['name']}: {m} {rt['error']:.4g}, "
                     f"{rt['seconds'] * 1e3:.1f} ms per frame; the pick is "
                     f"{result['speed_ratio']:.2f}x as fast")
    for st in result["steps"]:
        lines.append(f"verified:  {st['name']}: {m} {st['error']:.4g} at full size "
                     f"({st['search_error']:.4g} searched) -> "
                     f"{'meets the budget' if st['ok'] else 'misses it'}")
    return "\n".join(lines)


def _format_partial(result: dict) -> str:
    W, H = result["size"]
    se = result["search"]
    m = result["metric"]
    why = ("interrupted" if result["interrupted"] else
           f"stopped by {result['stopped_by'].split(':')[0]}")   # the error's type
    threshold = (f", threshold {se['threshold']:.4g}" if se["threshold"] is not None else "")
    lines = [f"tune (PARTIAL: {why} after {result['elapsed']:.0f} s): {m} <= "
             f"{result['max_error']:g} at {W}x{H}; {se['renders']} renders of "
             f"{se['configurations']} configurations searched at "
             f"{se['size'][0]}x{se['size'][1]}{threshold}"]
    if result["name"] is None:
        lines.append("pick:      none verified yet")
    else:
        lines += [f"pick:      {result['name']} (the best verified so far; the search had "
                  "not finished: a faster one may exist)",
                  f"           {m} {result['error']:.4g} (+2 s.e.: "
                  f"{result['error_bound']:.4g}), {result['seconds'] * 1e3:.1f} ms per frame "
                  f"(maps rebuilt), against {result['reference']['name']} (seed "
                  f"{result['reference']['seed']})"]
    for st in result["steps"]:
        lines.append(f"verified:  {st['name']}: {m} {st['error']:.4g} at full size "
                     f"({st['search_error']:.4g} searched) -> "
                     f"{'meets the budget' if st['ok'] else 'misses it'}")
    return "\n".join(lines)


def result_json(result: dict) -> dict:
    """``result`` as JSON-safe data: the sweep as its rows, without the render."""
    def conv(v):
        if isinstance(v, SweepTable):
            return [{k: conv(x) for k, x in r.items()} for r in v.rows]
        if isinstance(v, MethodResult):
            return None
        if isinstance(v, dict):
            return {k: conv(x) for k, x in v.items()}
        if isinstance(v, (list, tuple)):
            return [conv(x) for x in v]
        return jsonable(v)
    out = {k: conv(v) for k, v in result.items() if k != "result"}
    return out

