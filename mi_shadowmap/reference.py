"""The converged soft-shadow reference for the visibility AOVs.

:func:`converged_visibility` returns, per emitter, the visibility AOV that
the ``shadowmap`` integrator would produce with infinitely many light
samples: at every camera sample, the average of ``n_light`` hard shadows
cast from *fixed* positions on the light (the protocol of Guennebaud et al.
2006 and Forest et al. 2006: "the average of 1024 hard shadows"). The
positions are a jittered grid of ``n`` equal-area cells over the emitter's
sample square (:func:`light_sample_pattern`), jittered by a ``numpy`` generator seeded with ``seed`` and
identical for every pixel, mapped to the light by
``emitter.sample_direction`` (uniform on the area for rectangles and meshes;
on the visible cone for spheres; through the texture's importance sampling for a
textured radiance). Every sample is a real shadow ray
(``scene.ray_test``), inside one ``dr.while_loop`` per emitter, so 1024 light
samples cost one kernel.

Definition of visibility (the same as the integrator's AOV): the fraction
of light samples that both *contribute* (the emitter sample has a positive
pdf and the BSDF times the emitted radiance is > 0, i.e. the light point is
above the receiver's horizon and faces it) and are unoccluded; light samples
below the receiver's horizon therefore count as shadowed. Pixels whose
camera ray misses or hits a non-smooth BSDF have visibility 0, as in the
integrator. Camera sampling (``spp`` samples per pixel, the scene's sampler
and reconstruction filter) is Mitsuba's, so with the ``box`` filter the
result is bit-identical for a given ``seed`` and thread count.
"""
from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi
import numpy as np

from .rays import is_infinite, occlusion, on_cylinder, spawn_shadow_ray, surface_point
from .variants import bsdf_eval_reaches, unpolarized, variant_class


def light_sample_pattern(n_light: int, seed: int = 0) -> np.ndarray:
    """``(n_light, 2)`` stratified (jittered-grid) points in ``[0, 1)^2``, one per
    equal-area cell for any ``n``.

    ``rows = round(sqrt(n))`` rows, row ``r`` of ``n_r`` cells (``n // rows`` or one
    more) of width ``1 / n_r`` and height ``n_r / n``; one uniformly jittered point per
    cell, row-major, in its own ``1 / n``-high band of the row (a permutation per row),
    so that ``y`` alone is stratified in ``n`` strata (a mesh light's triangle is picked
    from ``y``). For ``n = 1024``: a 32 x 32 jittered grid. Deterministic given
    ``seed``. (A ``ceil(sqrt(n))``-column grid, before, filled only the first ``n``
    cells: part of the light was never sampled for a non-square ``n``, each point still
    weighing ``1 / n``; ``n = 1000`` was off by up to 0.026 on contact_hardening, 1024
    and 992 by 0.001.)
    """
    if not isinstance(n_light, int) or n_light < 1:
        raise ValueError(f"converged_visibility: n_light must be an integer >= 1, got {n_light!r}")
    rows = max(1, int(round(math.sqrt(n_light))))
    jitter = np.random.default_rng(seed).random((n_light, 2))
    xs, ys, start = [], [], 0
    for r in range(rows):
        n_r = n_light // rows + (1 if r < n_light % rows else 0)
        j = jitter[start:start + n_r]
        xs.append((np.arange(n_r) + j[:, 0]) / n_r)
        # each cell's point in its own 1/n-high band of the row (a random one): y alone
        # is then stratified in n strata, as a mesh light's triangle is picked from y
        # (Mitsuba's sample_position; jittered over the whole row, a cube light's faces
        # got 164..175 of 1024 points instead of 170.7 each, 36..48 of 256 instead of 42.7;
        # now 170 or 171, 42 or 43)
        band = np.random.default_rng([seed, r]).permutation(n_r)
        ys.append((start + band + j[:, 1]) / n_light)
        start += n_r
    pts = np.stack([np.concatenate(xs), np.concatenate(ys)], axis=1).astype(np.float32)
    return np.clip(pts, np.float32(0.0), np.nextafter(np.float32(1.0), np.float32(0.0)))


class _ConvergedVisibilityMixin:
    """Visibility AOVs only (RGB = mean visibility over emitters, for convenience)."""

    def __init__(self, labels, pattern: np.ndarray, occlusion: bool = True):
        self._mi_base.__init__(self, mi.Properties())
        self.occlusion = bool(occlusion)
        self.labels = list(labels)
        self.n_light = len(pattern)
        self.ux = mi.Float(pattern[:, 0])
        self.uy = mi.Float(pattern[:, 1])

    def aov_names(self):
        return [f"vis_{lab}" for lab in self.labels]

    def sample(self, scene, sampler, ray, medium=None, active=True):
        si = scene.ray_intersect(mi.Ray3f(ray), active)
        bsdf = si.bsdf(ray)
        shade = active & si.is_valid() & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth)
        ctx = mi.BSDFContext()
        n = self.n_light
        aovs = []
        query = occlusion(scene) if self.occlusion else None   # outside the loops
        on_cyl = on_cylinder(si, scene)
        # once, not per light sample: on cylinders it is one more ray_intersect
        p_surface = surface_point(si, scene) if self.occlusion else None
        for emitter in scene.emitters():
            k = mi.UInt32(0)
            n_vis = mi.Float(0.0)
            any_lit = mi.Bool(False)

            def cond(k, n_vis, any_lit):
                return shade & (k < n)

            def body(k, n_vis, any_lit, emitter=emitter):
                u = mi.Point2f(dr.gather(mi.Float, self.ux, k), dr.gather(mi.Float, self.uy, k))
                ds, w = emitter.sample_direction(si, u, shade)
                lit = shade & (ds.pdf > 0)
                w = unpolarized(w)
                _, reaches = bsdf_eval_reaches(bsdf, ctx, si, si.to_local(ds.d), lit)
                lit = reaches & (dr.max(w) > 0)
                if self.occlusion:
                    occluded = query(    # not ray_test alone: spheres, cylinders
                        spawn_shadow_ray(si, ds.p, scene, is_infinite(emitter), p_surface,
                                         emitter, ds.n),
                        lit, on_cyl, si)
                else:
                    occluded = mi.Bool(False)
                n_vis = dr.select(lit & ~occluded, n_vis + 1.0, n_vis)
                return k + 1, n_vis, any_lit | lit

            k, n_vis, any_lit = dr.while_loop((k, n_vis, any_lit), cond, body)
            aovs.append(dr.select(any_lit, n_vis / n, 0.0))
        mean = sum(aovs, mi.Float(0.0)) / max(len(aovs), 1)
        return mi.depolarizer(mi.UnpolarizedSpectrum(mean)), shade, aovs


def converged_visibility(scene: mi.Scene, n_light: int = 1024, seed: int = 0, spp: int = 16,
                         sensor: int = 0, occlusion: bool = True) -> dict:
    """Converged visibility per emitter: ``{'vis_<label>': (H, W) float32 array}``.

    ``n_light`` fixed stratified light positions (>= 1024 for a reference,
    per Guennebaud 2006 / Forest 2006), ``spp`` camera samples per pixel,
    both deterministic given ``seed``. The keys are the integrator's AOV
    names, so the arrays compare directly with a ``shadowmap`` render's AOVs
    of the same scene and sensor (same ``spp`` averages the same pixel
    footprint; camera noise is the same for both when ``seed`` is too).
    Emitters the integrator refuses (environment maps) raise the same error.

    ``occlusion=False`` traces no shadow rays: the result is then the fraction
    of the light above the receiver's horizon (and facing it), e.g. to mask
    the pixels where a light straddles the horizon -- there a one-light-sample
    method's AOV is binary noise around the right mean whatever its shadows.
    """
    from .integrator import integrator_class
    from .scenes import load_scene
    from .timing import check_film
    if not isinstance(scene, mi.Scene):
        scene = load_scene(scene)   # a dict or a path; another variant's scene is named
    if not isinstance(spp, int) or spp < 1:
        raise ValueError(f"converged_visibility: spp must be an integer >= 1, got {spp!r}")
    check_film(scene, sensor, what="converged_visibility")
    labeller = integrator_class()(mi.Properties())   # same AOV labels as the integrator
    labeller.check_scene(scene)
    labels = [name[len("vis_"):] for name in labeller.aov_names()]
    cls = variant_class(_ConvergedVisibilityMixin, name="ConvergedVisibilityIntegrator")
    integ = cls(labels, light_sample_pattern(n_light, seed), occlusion)
    img = np.asarray(mi.render(scene, integrator=integ, sensor=sensor, spp=spp, seed=seed))
    n_colour = img.shape[-1] - len(labels)   # 3 (rgb, spectral) or 1 (mono)
    return {name: img[..., n_colour + i].astype(np.float32)
            for i, name in enumerate(integ.aov_names())}
