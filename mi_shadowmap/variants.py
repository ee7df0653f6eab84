"""Mitsuba variants: which ones the package supports, and classes defined per variant.

``mi.SamplingIntegrator`` (like every ``mi.*`` type) is the *current*
variant's class. A Python integrator derived from it while ``llvm_ad_rgb`` is
set stays an rgb integrator: registered again after ``mi.set_variant(
'llvm_ad_spectral')`` it makes ``mi.render`` fail with a bare
``AssertionError``. So, like Mitsuba's own Python integrators, every
integrator class of this package is created per variant
(:func:`variant_class`), from a variant-independent implementation (a mixin
whose code looks up ``mi.Float``, ``mi.Spectrum``, ... when it runs).
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

#: Variants the package supports (JIT): every colour mode, polarized or not, LLVM and CUDA.
SUPPORTED_VARIANTS = tuple(f"{backend}_ad_{colour}" for backend in ("llvm", "cuda")
                           for colour in ("rgb", "mono", "spectral", "mono_polarized",
                                          "spectral_polarized"))


class UnsupportedVariantError(RuntimeError):
    """The Mitsuba variant cannot run the ``shadowmap`` integrator."""


def check_variant(variant: str | None = None) -> str:
    """Return ``variant`` (default: the current one), or raise naming it and the supported ones.

    Scalar variants run a Python integrator once per ray (see :func:`unpolarized` for
    the polarized ones).
    """
    variant = mi.variant() if variant is None else variant   # '': named, not the current
    if variant in SUPPORTED_VARIANTS:
        return variant
    if variant is None:
        why = "no Mitsuba variant is set"
    elif variant.startswith("scalar"):
        why = ("a Python integrator in a scalar variant runs once per ray, so it needs a JIT "
               "(llvm_ad_* or cuda_ad_*) variant")
    else:
        why = "it is not one of the supported JIT variants"
    raise UnsupportedVariantError(
        f"shadowmap: the Mitsuba variant '{variant}' is not supported ({why}); supported "
        f"variants: {', '.join(SUPPORTED_VARIANTS)} (cuda_ad_* where a CUDA GPU exists)")


def unpolarized(spectrum):
    """The intensity of ``spectrum`` (``mi.unpolarized_spectrum``): in a polarized
    variant, where spectra are Mueller matrices, their ``(0, 0)`` entry; elsewhere
    ``spectrum`` itself. For tests and masks (whether a term contributes at all)."""
    return mi.unpolarized_spectrum(spectrum)


def bsdf_eval_reaches(bsdf, ctx, si, wo_local, active):
    """``(value, reaches)`` of ``bsdf`` at ``si`` towards local direction ``wo_local``:
    its value (as ``bsdf.eval``) and whether light from there reaches the viewer at all
    -- the value is non-zero, or the BSDF's pdf is (the horizon test of the visibility
    AOVs). A black receiver, or one whose reflectance is zero at the sampled
    wavelengths (a narrow-band spectrum in a spectral variant), is still above the
    horizon: read from the value alone, its lit points had visibility 0."""
    value, pdf = bsdf.eval_pdf(ctx, si, wo_local, active)
    return value, mi.Bool(active) & ((dr.max(unpolarized(value)) > 0) | (pdf > 0))


#: Mitsuba BSDFs that tilt the shading frame per point
#: (:attr:`~mi_shadowmap.filters.common.Lookup.tilted`).
TILTING_BSDFS = frozenset({"NormalMap", "BumpMap"})


def tilts_shading_frame(bsdf) -> bool:
    """Whether ``bsdf`` is or nests (in its ``mi.traverse`` hierarchy) one of
    :data:`TILTING_BSDFS`: it then evaluates light in a shading frame tilted per point."""
    nodes = mi.traverse(bsdf).hierarchy
    names = {bsdf.class_name()} | {n.class_name() for n in nodes if hasattr(n, "class_name")}
    return bool(names & TILTING_BSDFS)


def bsdf_to_world(si, value, wo_local):
    """A BSDF value (or sample weight) at ``si`` for light arriving from local direction
    ``wo_local`` and leaving along ``si.wi``, with its Mueller matrix in world space
    (``si.to_world_mueller``, as Mitsuba's ``direct`` and ``path`` do); unchanged in
    unpolarized variants.

    In a polarized variant every spectrum is a Mueller matrix and the shading composes
    them as Mitsuba does: a term is ``bsdf_to_world(f) * emitter weight`` (the light's
    Stokes vector enters on the right), so the polarization that a reflection gives
    reaches the film (Mitsuba's ``stokes`` integrator records it); a film of intensities
    reads the ``(0, 0)`` entry. A shadow map scales a term by a visibility, which does
    not polarize."""
    return si.to_world_mueller(value, -wo_local, si.wi)


_CLASSES: dict = {}


def variant_class(mixin: type, base: str = "SamplingIntegrator", name: str | None = None):
    """``class name(mi.<base>)`` of the current variant with ``mixin``'s body, created
    once per variant and cached.

    Nanobind types take a single base, so the mixin's attributes are copied into
    the new class; its methods reach the Mitsuba base through ``self._mi_base``
    (not ``super()``, whose class cell is the mixin). Raises
    :class:`UnsupportedVariantError` for a variant the package does not support.
    """
    variant = check_variant()
    key = (mixin, base, variant)
    cls = _CLASSES.get(key)
    if cls is None:
        name = name or mixin.__name__.removesuffix("Mixin")
        mi_base = getattr(mi, base)
        body = {k: v for k, v in vars(mixin).items() if k not in ("__dict__", "__weakref__")}
        body.update(__qualname__=name, _mi_base=mi_base, variant=variant)
        cls = type(name, (mi_base,), body)
        _CLASSES[key] = cls
    return cls
