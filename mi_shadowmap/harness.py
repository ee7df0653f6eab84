"""Run shadow methods on a scene side by side and measure them against a reference.

:func:`compare` renders the reference and each method in one process, with
the same seed and spp, and returns one :class:`MethodResult` per method
(the reference first): image, per-emitter visibility AOVs, metrics against
the reference, timings (depth-map build, shading, cold = first render with
JIT compilation, warm = re-render with cached kernels) and depth-map memory.
"""
from __future__ import annotations

import os
import time
from dataclasses import dataclass, field

import drjit as dr
import mitsuba as mi
import numpy as np

from . import metrics
from .options import parse_options


@dataclass
class MethodResult:
    """Everything measured for one method on one scene."""
    name: str                       # display name (method plus non-default params)
    method: str
    params: dict
    image: np.ndarray               # (H, W, 3) linear RGB
    visibility: dict                # AOV name -> (H, W) visibility
    times: dict                     # seconds: cold, warm, build, shading
    map_bytes: int = 0
    texels: int = 0
    metrics: dict = field(default_factory=dict)

    def vis_stack(self) -> np.ndarray:
        return np.stack([self.visibility[k] for k in sorted(self.visibility)], axis=0)

    def row(self) -> dict:
        """A flat dict for tables/CSV."""
        r = {"name": self.name, "method": self.method}
        r.update({f"time_{k}": v for k, v in self.times.items()})
        r.update({"map_bytes": self.map_bytes, "texels": self.texels})
        r.update({k: v for k, v in self.metrics.items() if not isinstance(v, dict)})
        return r


def load_scene(scene, **xml_params) -> mi.Scene:
    """An ``mi.Scene`` from a scene, a dict, or an XML path (``$`` params as kwargs)."""
    if isinstance(scene, mi.Scene):
        return scene
    if isinstance(scene, dict):
        return mi.load_dict(scene)
    path = os.fspath(scene)
    if not os.path.isfile(path):
        raise FileNotFoundError(f"scene file not found: {path}")
    return mi.load_file(path, **{k: str(v) for k, v in xml_params.items()})


def _split(result, n_aovs, aov_names):
    arr = np.asarray(result)
    image = arr[..., :3]
    vis = {name[len("vis_"):]: arr[..., 3 + k] for k, name in enumerate(aov_names)}
    return image, vis


def run_method(scene: mi.Scene, method: str, spp: int = 16, seed: int = 0,
               repeats: int = 1, **params) -> MethodResult:
    """Render ``scene`` with one method; time a cold and ``repeats`` warm renders."""
    props = {"type": "shadowmap", "method": method, **params}
    parse_options(props)  # validate before anything is rendered
    integrator = mi.load_dict(props)
    integrator.check_scene(scene)   # clear error before rendering
    t0 = time.perf_counter()
    img = mi.render(scene, integrator=integrator, spp=spp, seed=seed)
    dr.eval(img)
    dr.sync_thread()
    cold = time.perf_counter() - t0
    warm = []
    build = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        img = mi.render(scene, integrator=integrator, spp=spp, seed=seed)
        dr.eval(img)
        dr.sync_thread()
        warm.append(time.perf_counter() - t0)
        build.append(integrator.build_seconds)
    warm_t = float(np.median(warm))
    build_t = float(np.median(build))
    image, vis = _split(img, len(integrator.aov_names()), integrator.aov_names())
    maps = [m for m in integrator.maps if m is not None]
    name = method + "".join(f" {k}={v}" for k, v in sorted(params.items()))
    return MethodResult(
        name=name, method=method, params=dict(params), image=image, visibility=vis,
        times={"cold": cold, "warm": warm_t, "build": build_t, "shading": warm_t - build_t},
        map_bytes=sum(m.nbytes for m in maps), texels=sum(m.n_texels for m in maps))


def score(result: MethodResult, reference: MethodResult) -> dict:
    """Metrics of ``result`` against ``reference`` (visibility pooled over emitters)."""
    m = metrics.visibility_metrics(reference.vis_stack(), result.vis_stack())
    m = {f"vis_{k}": v for k, v in m.items()}
    img = metrics.image_metrics(reference.image, result.image)
    m.update({f"img_{k}": v for k, v in img.items()})
    return m


def compare(scene, methods=("hard",), reference: str | dict = "raytraced", spp: int = 16,
            seed: int = 0, repeats: int = 1, progress: bool = False,
            **params) -> list[MethodResult]:
    """Render ``reference`` and every method; return results, reference first.

    ``methods`` items are method names or dicts ``{"method": ..., **params}``;
    ``params`` apply to every non-reference method.
    """
    scene = load_scene(scene)
    ref_spec = {"method": reference} if isinstance(reference, str) else dict(reference)
    specs = [dict(m) if isinstance(m, dict) else {"method": m, **params} for m in methods]
    for spec in specs:   # validate everything up front: nothing is lost on a typo
        parse_options({"type": "shadowmap", **spec})
    results = []
    iterator = [ref_spec] + specs
    if progress:
        from tqdm import tqdm
        iterator = tqdm(iterator, desc="methods", unit="method")
    for spec in iterator:
        spec = dict(spec)
        method = spec.pop("method")
        results.append(run_method(scene, method, spp=spp, seed=seed, repeats=repeats, **spec))
    ref = results[0]
    for r in results:
        r.metrics = score(r, ref)
    return results


def format_table(results: list[MethodResult]) -> str:
    """A plain-text metrics table."""
    cols = [("name", "method", "{}"), ("vis_rmse", "vis RMSE", "{:.4f}"),
            ("vis_misclassified", "miscl. %", "{:.2%}"), ("vis_false_shadow", "false shd %",
                                                           "{:.2%}"),
            ("vis_false_lit", "false lit %", "{:.2%}"), ("img_psnr", "PSNR dB", "{:.1f}"),
            ("time_build", "build ms", "{:.1f}"), ("time_warm", "frame ms", "{:.1f}"),
            ("time_cold", "cold ms", "{:.1f}")]
    rows = []
    for r in results:
        row = r.row()
        cells = []
        for key, _, fmt in cols:
            v = row.get(key)
            if key.startswith("time_") and v is not None:
                v = v * 1000.0
            cells.append("-" if v is None else fmt.format(v))
        rows.append(cells)
    head = [c[1] for c in cols]
    widths = [max(len(h), *(len(r[i]) for r in rows)) for i, h in enumerate(head)]
    line = lambda cells: "  ".join(c.ljust(w) for c, w in zip(cells, widths))  # noqa: E731
    return "\n".join([line(head), line(["-" * w for w in widths])] + [line(r) for r in rows])
