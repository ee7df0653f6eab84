"""Issue 11's "reuse the render's own primary hits for the marks": could it pay? One run,
by hand:

    python benchmarks/bench_primary_reuse.py [--scenes large_world room_two_points mesh]
                                             [--image 256] [--spp 16] [--mesh-spp 64]
                                             [--triangles 1000000] [--rounds 9]

Everything on one thread (``dr.set_thread_count(1)``), timed by that thread's CPU time
(``time.thread_time_ns``), every configuration alternated in one process (the order
reversed every other round), medians of ``--rounds`` rounds (spread: min-max). Per scene:

1. ``render``: Mitsuba's C++ render loop (``mi.render``, one megakernel) with
   :class:`Unshadowed`, a Python integrator that traces the camera ray
   (``RayFlags.All``) and shades every emitter's light sample unshadowed, as the
   ``shadowmap`` integrator's ``unshadowed`` method does: camera rays and shading
   alone. ``shadowmap`` itself (``method=unshadowed``) is timed beside it.
2. ``one kernel``: the same image, the render loop driven from Python (the primary rays as
   Mitsuba's C++ loop draws them, ``block.put``, ``film.develop``) in one kernel, as
   Mitsuba's AD integrators drive it.
3. ``split``: the same, as a wavefront in two kernels. Kernel 1 seeds the sampler,
   samples every lane's camera ray, traces ``ray_intersect_preliminary`` and stores the
   hit (``t``, ``prim_uv``, ``prim_index``, ``shape_index``, ``shape``, ``instance``)
   and, for each pixel's first sample, the ray's direction (what a mark needs to rebuild
   its point). Kernel 2 re-seeds the sampler, draws the same rays again, computes the
   surface interaction from the stored hits (``compute_surface_interaction``,
   ``RayFlags.All``) and shades. ``split, 4 fields``: the same storing only ``t``,
   ``prim_uv``, ``prim_index`` and ``shape`` (enough without instances). ``rays alone``:
   kernel 2's drawing of the rays again, by itself (their directions stored).
4. ``marks``: the mark pass's camera rays as it traces them
   (:func:`mi_shadowmap.virtual.marks.camera_hits`: pixel centres in blocks,
   ``RayFlags.Minimal``, one-pixel footprints), a kernel of its own, against ``gather``:
   the same outputs (point, normal facing the camera, shape, footprints, valid) from the
   split's stored hits, one sample a pixel (its first, jittered, not the pixel centre),
   in the marks' lane order.

Checked: the images of 1, 2 and 3 are bit-identical (a box filter; printed). Each part's
JIT kernels' execution time (kernel history) is printed beside its CPU time: the rest is
the host's tracing. The verdict per scene: the split costs ``split - render`` and saves
``marks - gather`` (paired, per round).
"""
from __future__ import annotations

import argparse
import pathlib
import statistics
import sys
import tempfile
import time

from mi_shadowmap import harness  # (first: the LLVM set-up, the registration)
import drjit as dr
import mitsuba as mi
import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent))
from bench_all import heavy_scene  # noqa: E402

from mi_shadowmap.integrator import _light_sample  # noqa: E402
from mi_shadowmap.light_views import pinhole_footprint  # noqa: E402
from mi_shadowmap.virtual.camera import camera_frame  # noqa: E402
from mi_shadowmap.virtual.marks import camera_hits, camera_pixels  # noqa: E402

ROOT = pathlib.Path(__file__).resolve().parents[1]
SCENES = ["large_world", "room_two_points", "mesh"]
HIT_FIELDS = ("t", "prim_uv", "prim_index", "shape_index", "shape", "instance")
#: What a scene without instances needs stored (``shape_index`` and ``instance`` left
#: at their defaults: the same images)
LEAN_FIELDS = ("t", "prim_uv", "prim_index", "shape")


def shade(scene, sampler, ray, si, active):
    """The ``shadowmap`` integrator's ``unshadowed`` shading of the camera hit ``si``:
    the emitter seen, then one light sample of each emitter at visibility 1."""
    valid = active & si.is_valid()
    result = mi.Spectrum(si.emitter(scene, active).eval(si, active))
    bsdf = si.bsdf(ray)
    ctx = mi.BSDFContext()
    lit_here = valid & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth)
    for emitter in scene.emitters():
        u = sampler.next_2d(lit_here)
        _, unshadowed, lit, _ = _light_sample(emitter, si, bsdf, ctx, u, lit_here)
        result += dr.select(lit, unshadowed, 0.0)
    return result, valid


def unshadowed_integrator():
    """:class:`Unshadowed` for the current variant (a class per variant)."""
    class Unshadowed(mi.SamplingIntegrator):
        """Camera ray (``RayFlags.All``) and :func:`shade`, in Mitsuba's render loop."""

        def sample(self, scene, sampler, ray, medium=None, active=True):
            si = scene.ray_intersect(ray, mi.RayFlags.All, False, active)
            result, valid = shade(scene, sampler, ray, si, active)
            return result, valid, []

    return Unshadowed(mi.Properties())


class Wavefront:
    """The render loop of Mitsuba's C++ ``SamplingIntegrator::render`` (JIT variants),
    driven from Python, for a perspective camera and a box filter."""

    def __init__(self, scene, spp: int, seed: int = 0, fields=HIT_FIELDS):
        self.scene, self.sensor, self.fields = scene, scene.sensors()[0], fields
        self.film = self.sensor.film()
        self.sampler = self.sensor.sampler().clone()
        self.sampler.set_sample_count(spp)
        self.sampler.set_samples_per_wavefront(spp)
        self.spp, self.seed = self.sampler.sample_count(), seed
        self.size = [int(x) for x in self.film.crop_size()]
        self.lanes = self.size[0] * self.size[1] * self.spp
        self.hits = self.dirs = None

    def rays(self):
        """The sampler seeded, every lane's camera ray, its weight and splat position."""
        sensor, film, spp = self.sensor, self.film, self.spp
        self.sampler.seed(self.seed, self.lanes)
        idx = dr.arange(mi.UInt32, self.lanes) // dr.opaque(mi.UInt32, spp)
        pos = mi.Vector2u()
        pos.y = idx // self.size[0]
        pos.x = dr.fma(mi.UInt32(mi.Int32(-self.size[0])), pos.y, idx)
        pos += mi.Vector2u(film.crop_offset())
        pos_film = mi.Vector2f(pos) + self.sampler.next_2d()
        scale = dr.rcp(mi.ScalarVector2f(film.crop_size()))
        offset = -mi.ScalarVector2f(film.crop_offset()) * scale
        aperture = mi.Point2f(0.5)
        if sensor.needs_aperture_sample():
            aperture = self.sampler.next_2d()
        when = mi.Float(sensor.shutter_open())
        if sensor.shutter_open_time() > 0:
            when += self.sampler.next_1d() * sensor.shutter_open_time()
        wavelength = self.sampler.next_1d() if mi.is_spectral else mi.Float(0.0)
        ray, weight = sensor.sample_ray_differential(when, wavelength,
                                                     dr.fma(pos_film, scale, offset), aperture)
        ray.scale_differential(mi.Float(float(np.float32(1) / np.sqrt(np.float32(spp)))))
        return ray, weight, mi.Vector2f(pos)

    def develop(self, ray, weight, pos, result, valid):
        """The samples splatted into the film as the C++ loop does (RGB, alpha if the film
        has it, weight 1), developed and evaluated."""
        self.film.prepare([])
        block = self.film.create_block()
        block.set_offset(self.film.crop_offset())
        value = weight * result
        if mi.is_spectral:
            rgb = mi.spectrum_to_srgb(mi.unpolarized_spectrum(value), ray.wavelengths)
        elif mi.is_monochromatic:
            rgb = mi.Color3f(mi.unpolarized_spectrum(value).x)
        else:
            rgb = mi.unpolarized_spectrum(value)
        alpha = ([dr.select(valid, mi.Float(1.0), mi.Float(0.0))]
                 if mi.has_flag(self.film.flags(), mi.FilmFlags.Alpha) else [])
        block.put(pos, [rgb.x, rgb.y, rgb.z, *alpha, mi.Float(1.0)])
        self.film.put_block(block)
        image = self.film.develop()
        dr.eval(image)
        return image

    def one_kernel(self):
        """Camera rays, hits and shading in one kernel, as the C++ loop."""
        ray, weight, pos = self.rays()
        si = self.scene.ray_intersect(ray, mi.RayFlags.All, False, True)
        result, valid = shade(self.scene, self.sampler, ray, si, mi.Bool(True))
        return self.develop(ray, weight, pos, result, valid)

    def kernel1(self):
        """Every lane's closest hit, stored; each pixel's first-sample ray direction."""
        ray, _, _ = self.rays()
        pi = self.scene.ray_intersect_preliminary(ray, False)
        lane = dr.arange(mi.UInt32, self.lanes)
        self.dirs = dr.zeros(mi.Vector3f, self.lanes // self.spp)
        dr.scatter(self.dirs, ray.d, lane // self.spp, active=(lane % self.spp) == 0)
        self.hits = {k: getattr(pi, k) for k in self.fields}
        dr.eval(self.dirs, *self.hits.values())

    def kernel2(self):
        """The same rays again, their surface interactions from the stored hits, shaded."""
        ray, weight, pos = self.rays()
        pi = dr.zeros(mi.PreliminaryIntersection3f, self.lanes)
        for k, v in self.hits.items():
            setattr(pi, k, v)
        pi.valid = self.hits["t"] < dr.inf
        si = pi.compute_surface_interaction(ray, mi.RayFlags.All, True)
        result, valid = shade(self.scene, self.sampler, ray, si, mi.Bool(True))
        return self.develop(ray, weight, pos, result, valid)

    def rays_alone(self):
        """The rays as kernel 2 draws them again, their directions stored (the cost of
        regenerating them, an upper bound: 12 bytes a lane written)."""
        ray, _, _ = self.rays()
        dr.eval(ray.d)

    def mark_gather(self):
        """What :func:`camera_hits` gives the marks, from the stored hits: each pixel's
        first sample, in the marks' lane order, evaluated: ``(p_world, n_world facing the
        camera, shape, dp_dx, dp_dy, valid)``."""
        pixel = camera_pixels(self.sensor)
        pixel = (pixel & 0xFFFF) + (pixel >> 16) * self.size[0]
        lane = pixel * self.spp
        pi = dr.zeros(mi.PreliminaryIntersection3f, dr.width(lane))
        for k, v in self.hits.items():
            setattr(pi, k, dr.gather(type(v), v, lane))
        pi.valid = pi.t < dr.inf
        origin = mi.Point3f(self.sensor.world_transform().translation())
        ray = mi.Ray3f(origin, dr.gather(mi.Vector3f, self.dirs, pixel))
        si = pi.compute_surface_interaction(ray, mi.RayFlags.Minimal, True)
        valid = si.is_valid()
        n = dr.select(dr.dot(si.n, ray.d) > 0, -si.n, si.n)
        dp_dx, dp_dy = pinhole_footprint(si.p, n, camera_frame(self.sensor))
        dr.eval(si.p, n, si.shape, dp_dx, dp_dy, valid)
        return si.p, n, si.shape, dp_dx, dp_dy, valid


def mark_rays(scene):
    """The mark pass's camera hits as it traces them, evaluated."""
    si, dp_dx, dp_dy, valid = camera_hits(scene, scene.sensors()[0], evaluate=False)
    dr.eval(si.p, si.n, si.shape, dp_dx, dp_dy, valid)


def load(name: str, image: int, triangles: int, folder: str):
    if name == "mesh":
        return mi.load_dict(heavy_scene(triangles, image, folder))
    return harness.load_scene(str(ROOT / "scenes_xml" / f"{name}.xml"),
                              width=str(image), height=str(image))


def cpu_ms(f) -> tuple:
    """One thread's CPU ms of ``f()`` (kernels it launches, waited for), and its JIT
    kernels' execution ms (kernel history: the rest is the host's tracing)."""
    dr.sync_thread()
    dr.kernel_history()                         # (emptied: f's from here)
    t0 = time.thread_time_ns()
    f()
    dr.sync_thread()
    cpu = (time.thread_time_ns() - t0) * 1e-6
    return cpu, sum(k.get("execution_time", 0.0) for k in dr.kernel_history()
                    if k["type"] == dr.KernelType.JIT)


def measure(scene, spp: int, rounds: int) -> dict:
    """Per configuration, its one-thread CPU ms in each round; the images compared."""
    plain = unshadowed_integrator()
    shadowmap = mi.load_dict({"type": "shadowmap", "method": "unshadowed"})
    wave = Wavefront(scene, spp)
    lean = Wavefront(scene, spp, fields=LEAN_FIELDS)
    images = {}

    def render(integ, key):
        images[key] = mi.render(scene, integrator=integ, spp=spp, seed=0)
        dr.eval(images[key])

    parts = {
        "render": lambda: render(plain, "render"),
        "shadowmap unshadowed": lambda: render(shadowmap, "shadowmap"),
        "one kernel": lambda: images.__setitem__("one kernel", wave.one_kernel()),
        "kernel 1": wave.kernel1,
        "kernel 2": lambda: images.__setitem__("split", wave.kernel2()),
        "kernel 1, 4 fields": lean.kernel1,
        "kernel 2, 4 fields": lambda: images.__setitem__("split, 4 fields", lean.kernel2()),
        "rays alone": wave.rays_alone,
        "marks": lambda: mark_rays(scene),
        "gather": wave.mark_gather,
    }
    order = list(parts)
    times = {k: [] for k in order}
    kernels = {k: [] for k in order}
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        for r in range(rounds + 1):                  # round 0 compiles
            for k in order if r % 2 == 0 else order[::-1]:
                t, exec_ms = cpu_ms(parts[k])
                if r:
                    times[k].append(t)
                    kernels[k].append(exec_ms)
            if r == 0:
                same = {k: bool(np.array_equal(np.asarray(images["render"]), np.asarray(v)))
                        for k, v in images.items()}
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    for d in (times, kernels):
        d["split"] = [a + b for a, b in zip(d["kernel 1"], d["kernel 2"])]
        d["split, 4 fields"] = [a + b for a, b in zip(d["kernel 1, 4 fields"],
                                                      d["kernel 2, 4 fields"])]
    return {"times": times, "kernels": kernels, "same": same, "lanes": wave.lanes}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter,
                                 epilog=__doc__.split("\n\n", 2)[2])
    ap.add_argument("--scenes", nargs="+", default=SCENES,
                    help="scenes_xml names, or 'mesh' (bench_all's heavy scene)")
    ap.add_argument("--image", type=int, default=256)
    ap.add_argument("--spp", type=int, default=16)
    ap.add_argument("--mesh-spp", type=int, default=64, help="spp of 'mesh'")
    ap.add_argument("--triangles", type=int, default=1_000_000)
    ap.add_argument("--rounds", type=int, default=9)
    args = ap.parse_args(argv)
    threads = dr.thread_count()
    dr.set_thread_count(1)
    try:
        with tempfile.TemporaryDirectory() as tmp:
            for name in args.scenes:
                spp = args.mesh_spp if name == "mesh" else args.spp
                scene = load(name, args.image, args.triangles, tmp)
                report(name, args.image, spp, measure(scene, spp, args.rounds))
    finally:
        dr.set_thread_count(threads)
    return 0


def report(name: str, image: int, spp: int, m: dict) -> None:
    t = m["times"]
    med = {k: statistics.median(v) for k, v in t.items()}
    print(f"\n## {name}, {image}^2, {spp} spp ({m['lanes']:,} samples): one thread's CPU "
          f"ms, medians of {len(t['render'])} rounds (min-max)\n")
    print("| part | ms | min-max | JIT kernels' execution [ms] | images bit-identical to "
          "render |")
    print("|---|---|---|---|---|")
    same = {"render": "render", "shadowmap unshadowed": "shadowmap", "one kernel": "one kernel",
            "kernel 2": "split", "split": "split", "kernel 2, 4 fields": "split, 4 fields",
            "split, 4 fields": "split, 4 fields"}
    for k, v in t.items():
        print(f"| {k} | {med[k]:.1f} | {min(v):.1f}-{max(v):.1f} | "
              f"{statistics.median(m['kernels'][k]):.1f} | {m['same'].get(same.get(k), '')} |")
    print()
    for k in ("split", "split, 4 fields"):
        one = [s - r for s, r in zip(t[k], t["one kernel"])]
        print(f"{k} - one kernel (both driven from Python): {statistics.median(one):+.1f} ms "
              f"({min(one):+.1f} .. {max(one):+.1f}, paired)")
    extra = [s - r for s, r in zip(t["split"], t["render"])]
    saved = [a - b for a, b in zip(t["marks"], t["gather"])]
    print(f"split - render: {statistics.median(extra):+.1f} ms "
          f"({min(extra):+.1f} .. {max(extra):+.1f}, paired); marks - gather: "
          f"{statistics.median(saved):+.1f} ms ({min(saved):+.1f} .. {max(saved):+.1f}); "
          f"net {statistics.median(extra) - statistics.median(saved):+.1f} ms a frame "
          "(positive: the reuse costs more than it saves)", flush=True)


if __name__ == "__main__":
    sys.exit(main())
