"""``raytraced``: the ground truth, real shadow rays toward the light sample (no map)."""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from ..methods import Method, Prop
from ..rays import is_infinite, on_cylinder, spawn_shadow_ray
from .common import Lookup, RayTracedLight


def raytraced(smap: RayTracedLight, lk: Lookup, opts, active=True) -> mi.Float:
    """Ground truth: one shadow ray from the shading point to the light sample.

    The ray is spawned by :func:`mi_shadowmap.rays.spawn_shadow_ray` (an origin
    offset and an end shortening relative to the coordinates involved), not by
    Mitsuba's ``si.spawn_ray_to``, whose offset has an absolute floor and makes
    the reference drift with the scene's scale.

    With ``light_sample='independent'`` the ray goes to a second light sample of the
    same emitter, drawn independently of the one that is shaded: the expected
    contribution is then ``E[L] * E[V]``, the unshadowed light times the fraction of
    the light that is visible. That is the quantity every shadow-map method
    estimates (its visibility does not depend on which point of an area light was
    sampled), so this is their ideal: the difference between the two settings is
    the error of treating visibility as a factor, which no map can remove. For
    delta lights (point, spot, directional) both settings are the same. A map sees
    no horizon, so the second sample is drawn from the part of the light above the
    receiver's horizon (see :func:`_independent_target`).
    """
    target = lk.ds.p
    if opts.light_sample == "independent":
        target = _independent_target(lk, active, smap.emitter)
    ray = spawn_shadow_ray(lk.si, target, smap.scene, is_infinite(smap.emitter),
                           getattr(smap, "p_surface", None))
    occluded = smap.occlusion(ray, active,     # not ray_test alone: spheres, cylinders
                              on_cylinder(lk.si, smap.scene), lk.si)
    return dr.select(occluded, 0.0, 1.0)


#: Draws of :func:`_independent_target` (rejection of samples below the horizon).
HORIZON_TRIES = 8


def _independent_target(lk: Lookup, active, emitter) -> mi.Point3f:
    """A light point drawn independently of the shaded sample ``lk.ds``, from the part
    of its emitter on the viewer's side of the receiver's surface (where the shaded
    sample lies, as it is shaded): the first of :data:`HORIZON_TRIES` draws that is
    there, else the shaded sample's point (only where the light barely clears the
    horizon). Rejection makes it a sample of the visible part of the light, so the
    visibility estimated is the fraction of *that* part left unoccluded, which is
    what a shadow map's compare measures (it does not count the horizon). The draw
    must also face the receiver, as the shaded sample does (an area light emits from
    its front only): a point on the back of a closed light (a ``cube``) is hidden by
    the light itself, which made the image 37 % too dark under a cube light.
    ``emitter`` is the light's own object, called directly: through the samples'
    emitter pointer every live emitter of the process was traced, and one on a shape
    Mitsuba cannot sample (a curve) in another scene made the render fail."""
    si = lk.si
    infinite = is_infinite(emitter)
    viewer = dr.sign(si.wi.z)
    target, found = mi.Point3f(lk.ds.p), mi.Bool(False)
    for _ in range(HORIZON_TRIES):   # unrolled: the draws stay outside any loop
        ds, _ = emitter.sample_direction(si, lk.sampler.next_2d(active), active)
        ok = active & ~found & (ds.pdf > 0) & (si.to_local(ds.d).z * viewer > 0)
        if not infinite:     # the emitter's front (Mitsuba's area lights are one-sided)
            ok &= dr.dot(ds.d, ds.n) < 0
        target = dr.select(ok, ds.p, target)
        found |= ok
    return target


METHOD = Method(
    name="raytraced",
    lookup=raytraced,
    summary="shadow rays toward each light sample: the ground truth (matches Mitsuba's "
            "'direct')",
    properties=(Prop("shadow_rays", "int", 1,
                     "Shadow rays per camera sample per emitter (stratified light samples).",
                     lo=1, hi=65536),
                Prop("light_sample", "str", "shared",
                     "'shared': the shadow ray goes to the light sample that is shaded "
                     "(Mitsuba's 'direct'; the ground truth). 'independent': to a second, "
                     "independent sample of the same light, so visibility is a factor of "
                     "the unshadowed light, as in every shadow-map method: the ideal those "
                     "methods approximate (differs from 'shared' only for area lights).",
                     choices=("shared", "independent"))),
    uses_map=False,
    shadow_rays="shadow_rays",
    builtin=True,
)
