"""Render one method and time it: :func:`run_method` and its record, :class:`MethodResult`.

:func:`run_method` renders a scene with one method -- one cold render, then
``repeats`` warm ones -- and returns a :class:`MethodResult` with

* the image and the per-emitter visibility AOVs (``vis_<emitter>``),
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

Metrics against a reference are added by :mod:`mi_shadowmap.ground_truth`.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import drjit as dr
import mitsuba as mi
import numpy as np

from .specs import spec_name, to_mitsuba, validate_spec


@dataclass
class MethodResult:
    """Everything measured for one method on one scene."""
    name: str                       # display name (method plus given params)
    method: str
    params: dict                    # integrator properties given (besides method)
    image: np.ndarray | None        # (H, W, 3) linear RGB (None: reference without image)
    visibility: dict                # emitter label -> (H, W) visibility
    times: dict                     # seconds: cold, warm, build, shading, jit, compile
    spp: int = 0                    # samples per pixel rendered (the sampler's count)
    map_bytes: int = 0
    texels: int = 0
    kernels_compiled: int = 0       # kernels compiled (not cache hits) in the cold render
    metrics: dict = field(default_factory=dict)
    is_reference: bool = False
    #: the reference this result was scored against, where it is not the compare's
    #: first one (a method with its own spp: one at that spp); None: that one
    scored_against: "MethodResult | None" = field(default=None, repr=False, compare=False)
    #: the spp asked for, where the sampler rendered another count (``spp``): a
    #: ``stratified`` sampler renders 2 or 3 as 4; 0: the same as ``spp``
    spp_requested: int = 0

    def reference_in(self, results) -> "MethodResult":
        """The reference this result's metrics, error layers and heat map are against."""
        return self.scored_against if self.scored_against is not None else results[0]

    def vis_stack(self) -> np.ndarray:
        """Visibility AOVs as an (n_emitters, H, W) array, emitters sorted by label."""
        return np.stack([self.visibility[k] for k in sorted(self.visibility)], axis=0)

    def row(self) -> dict:
        """A flat dict for tables and CSV (pooled metrics, per-emitter RMSE)."""
        r = {"name": self.name, "method": self.method, "spp": self.spp,
             "spp_requested": self.spp_requested or self.spp, "reference": self.is_reference}
        r.update({k: list(v) if isinstance(v, tuple) else v for k, v in self.params.items()})
        r.update({f"time_{k}": v for k, v in self.times.items()})
        r.update({"map_bytes": self.map_bytes, "texels": self.texels,
                  "kernels_compiled": self.kernels_compiled})
        r.update({k: v for k, v in self.metrics.items() if not isinstance(v, dict)})
        for label, m in self.metrics.get("per_emitter", {}).items():
            for key in ("rmse", "misclassified", "penumbra_rmse"):
                r[f"vis_{key}[{label}]"] = m.get(key)
        return r


def check_film(scene, sensor: int = 0, what: str = "comparing methods") -> None:
    """Raise ValueError if the film of ``scene``'s sensor ``sensor`` cannot hold the
    visibility AOVs that ``what`` reads: a film with its own channel layout
    (``specfilm``), into which Mitsuba 3.9 writes no integrator AOVs (see
    :func:`mi_shadowmap.integrator._film_takes_aovs`)."""
    sensors = scene.sensors()
    if not 0 <= sensor < len(sensors):
        return
    film = sensors[sensor].film()
    if mi.has_flag(film.flags(), mi.FilmFlags.Special):
        raise ValueError(
            f"shadowmap: the scene's film ({film.class_name()}) has its own channel layout, into which "
            f"Mitsuba 3.9 writes no integrator AOVs (mitsuba3 issue #1189), and {what} "
            "reads visibility AOVs; give the sensor an 'hdrfilm' (a spectral variant "
            "develops it to RGB)")


#: The smallest film side the metrics take (SSIM's 7 x 7 window, :func:`metrics.ssim`).
MIN_SCORED_SIDE = 7


def check_scored_film(scene, sensor: int = 0) -> None:
    """Raise ValueError, before anything renders, if the film of ``scene``'s sensor is
    too small for the metrics every comparison computes (SSIM needs 7 x 7 pixels): a
    6 x 6 comparison used to render every method and then fail, writing nothing. The
    image is the film's crop window; a crop too small is named as such (its advice
    was to enlarge a film that was large enough)."""
    sensors = scene.sensors()
    if not 0 <= sensor < len(sensors):
        return
    film = sensors[sensor].film()
    w, h = (int(c) for c in film.crop_size())
    if min(w, h) >= MIN_SCORED_SIDE:
        return
    W, H = (int(c) for c in film.size())
    if (w, h) != (W, H):     # a crop window: the film is not the problem
        raise ValueError(f"the film's crop window is {w} x {h} pixels (of a {W} x {H} "
                         f"film); comparing methods needs at least {MIN_SCORED_SIDE} x "
                         f"{MIN_SCORED_SIDE} (SSIM's window): set the film's crop_width "
                         f"and crop_height to {MIN_SCORED_SIDE} or more")
    raise ValueError(f"the film is {w} x {h} pixels; comparing methods needs at least "
                     f"{MIN_SCORED_SIDE} x {MIN_SCORED_SIDE} (SSIM's window): set the "
                     f"film's width and height (the CLI's --width, --height) to "
                     f"{MIN_SCORED_SIDE} or more")


def xyz_to_srgb_matrix() -> np.ndarray:
    """Mitsuba's own CIE XYZ to linear sRGB matrix (``mi.xyz_to_srgb`` of the unit
    vectors), for films with ``pixel_format`` ``xyz``/``xyza``: the exact inverse of the
    conversion Mitsuba's film applied."""
    cols = [np.array(mi.xyz_to_srgb(mi.ScalarColor3f(*np.eye(3)[j])), np.float64).ravel()
            for j in range(3)]
    return np.stack(cols, axis=1).astype(np.float32)


def film_is_xyz(scene, sensor: int = 0) -> bool:
    """Whether the film of ``scene``'s sensor develops to CIE XYZ (``pixel_format``
    ``xyz``/``xyza``); read from its developed bitmap's channel names, so after a
    render."""
    sensors = scene.sensors()
    if not 0 <= sensor < len(sensors):
        return False
    try:
        b = sensors[sensor].film().bitmap()
    except Exception:     # nothing developed yet
        return False
    names = [b.struct_()[i].name for i in range(min(b.channel_count(), 3))]
    return names == ["X", "Y", "Z"]


def split_channels(result, aov_names, xyz: bool = False) -> tuple[np.ndarray, dict]:
    """``(image (H, W, 3), {label: visibility (H, W)})`` of a render.

    The film has 3 colour channels in rgb and spectral variants (spectral films
    develop to RGB) and 1 in mono or with ``pixel_format`` ``luminance``, and an
    alpha channel after them if the format has one (``rgba``, ``luminance_alpha``,
    ``xyza``: dropped here; no format has two colour channels); a one-channel image
    is repeated into 3 grey channels so that every metric and output treats all
    variants and formats alike. ``xyz`` (:func:`film_is_xyz`): the 3 colour channels
    are CIE XYZ and become linear sRGB (PNGs and FLIP read sRGB; they were read as X,
    Y, Z).
    """
    arr = np.asarray(result, dtype=np.float32)
    n_film = arr.shape[-1] - len(aov_names)
    if n_film not in (1, 2, 3, 4):
        raise ValueError(f"shadowmap: a render of {arr.shape[-1]} channels with "
                         f"{len(aov_names)} AOVs leaves {n_film} film channels; expected "
                         "1-4 (Y, YA, RGB, RGBA)")
    n_colour = 1 if n_film in (1, 2) else 3
    image = arr[..., :n_colour]
    image = np.repeat(image, 3, axis=-1) if n_colour == 1 else image.copy()
    if xyz and n_colour == 3:
        image = image @ xyz_to_srgb_matrix().T
    vis = {name[len("vis_"):]: arr[..., n_film + k].copy() for k, name in enumerate(aov_names)}
    return image, vis


def root_error(exc: BaseException) -> BaseException:
    """The error ``exc`` wraps: ``mi.render`` re-raises a Python integrator's errors as
    a RuntimeError whose ``__cause__`` (chain) holds them."""
    while exc.__cause__ is not None:
        exc = exc.__cause__
    return exc


def config_error(exc: BaseException, kinds: tuple | None = None) -> str | None:
    """The message of the error of one of ``kinds`` (default: ``OptionError`` and
    ``MethodError``: a configuration the scene cannot render, e.g. a ``resolution`` over
    ``memory_budget``) that ``exc`` is or wraps (``mi.render`` wraps a Python
    integrator's errors); None for any other error."""
    if kinds is None:
        from .methods import MethodError
        from .options import OptionError
        kinds = (OptionError, MethodError)
    e = exc
    while e is not None:
        if isinstance(e, kinds):
            return str(e)
        e = e.__cause__
    return None


def sampler_spp(scene, sensor: int = 0) -> int:
    """The sample count of ``scene``'s sensor's sampler: after a render, the spp that
    render took (``mi.render(..., spp=N)`` sets it, and the sampler rounds it)."""
    sensors = scene.sensors()
    if not 0 <= sensor < len(sensors):
        return 0
    return int(sensors[sensor].sampler().sample_count())


def rendered_spp(scene, spp: int, sensor: int = 0) -> int:
    """The spp that ``mi.render(scene, spp=spp)`` renders: samplers round the count
    they are given (``stratified`` and ``multijitter`` up to a square or a product of
    two near factors, ``ldsampler`` to a power of four, ``orthogonal`` to the square of
    a prime: a ``stratified`` sampler renders 2, 3 and 4 as 4 and 5 to 9 as 9), so a
    requested spp is not what is measured. Found without rendering, on a fork of the
    sensor's sampler (the scene's sampler is left alone), its rounding warning muted."""
    sensors = scene.sensors()
    if not 0 <= sensor < len(sensors):
        return int(spp)
    sampler = sensors[sensor].sampler().fork()
    logger = mi.logger()
    level = logger.log_level() if logger is not None else None
    try:
        if logger is not None:
            logger.set_log_level(mi.LogLevel.Error)
        sampler.set_sample_count(int(spp))
    finally:
        if logger is not None:
            logger.set_log_level(level)
    return int(sampler.sample_count())


def render_timed(scene, integrator, spp, seed):
    """``(image, seconds)`` of one synchronised ``mi.render``."""
    t0 = time.perf_counter()
    img = mi.render(scene, integrator=integrator, spp=spp, seed=seed)
    dr.eval(img)
    dr.sync_thread()
    return img, time.perf_counter() - t0


def compile_stats(history) -> tuple[float, int]:
    """(seconds of codegen + backend compile, kernels compiled) from dr.kernel_history()."""
    secs, n = 0.0, 0
    for k in history:
        if k.get("type") != dr.KernelType.JIT:
            continue
        secs += (k.get("codegen_time", 0.0) + k.get("backend_time", 0.0)) * 1e-3  # ms -> s
        n += not k.get("cache_hit", 0)
    return secs, n


def run_method(scene: mi.Scene, method: str, spp: int = 16, seed: int = 0,
               repeats: int = 1, measure_cached: bool = True, **params) -> MethodResult:
    """Render ``scene`` with one method: one cold and ``repeats`` warm renders.

    Frames are timed with the depth maps rebuilt in every render
    (``cache_maps=False`` unless given), so ``warm`` = ``build`` + ``shading``
    is the cost of a frame whose geometry or lights changed. The result's ``spp`` is
    the count the sampler rendered (:func:`rendered_spp`: it may round ``spp`` up;
    ``spp_requested`` keeps ``spp``). With
    ``measure_cached`` a second integrator re-renders with the map cache on
    (one priming render, then the median of ``repeats``): ``times["cached"]``
    is a re-render with maps and kernels both cached.

    The integrator is validated (properties and scene) before anything renders.
    """
    spec = {"method": method, **params}
    opts = validate_spec(spec)
    props = {"type": "shadowmap", **spec}
    uses_map = opts.record.uses_map
    if uses_map and "cache_maps" not in params:
        props["cache_maps"] = False
    integrator = mi.load_dict(to_mitsuba(props))
    integrator.check_scene(scene)   # clear error before rendering
    check_film(scene)
    had_history = dr.flag(dr.JitFlag.KernelHistory)
    dr.kernel_history()             # drop older entries
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        img, cold = render_timed(scene, integrator, spp, seed)
        compile_s, n_compiled = compile_stats(dr.kernel_history())
        spp_done = sampler_spp(scene) or spp   # the sampler may round spp
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, had_history)
    warm, build = [], []
    for _ in range(max(1, repeats)):
        img, t = render_timed(scene, integrator, spp, seed)
        warm.append(t)
        build.append(integrator.build_seconds)
    warm_t = float(np.median(warm))
    build_t = float(np.median(build))
    image, vis = split_channels(img, integrator.aov_names(), xyz=film_is_xyz(scene))
    maps = [m for m in integrator.maps if m is not None]
    times = {"cold": cold, "warm": warm_t, "build": build_t,
             "shading": max(warm_t - build_t, 0.0), "jit": max(cold - warm_t, 0.0),
             "compile": compile_s}
    if measure_cached:
        if uses_map and "cache_maps" not in params:
            cached_int = mi.load_dict(to_mitsuba({**props, "cache_maps": True}))
            render_timed(scene, cached_int, spp, seed)   # primes the map cache
        else:
            cached_int = integrator
        times["cached"] = float(np.median([render_timed(scene, cached_int, spp, seed)[1]
                                           for _ in range(max(1, repeats))]))
    return MethodResult(
        name=spec_name(spec), method=method, params=dict(params), image=image, visibility=vis,
        times=times, spp=spp_done, map_bytes=sum(m.nbytes for m in maps),
        texels=int(integrator.stats["texels_built"]), kernels_compiled=n_compiled,
        spp_requested=spp)

