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
    variant = variant or mi.variant()
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
    variant, where BSDFs and emitters return Mueller matrices, their ``(0, 0)`` entry;
    elsewhere ``spectrum`` itself.

    Why the shading may work on intensities alone in a polarized variant: every
    Mitsuba emitter is unpolarized (its Mueller matrix is a depolarizer, zero but for
    the ``(0, 0)`` entry), and every term of this integrator's estimate has one
    interaction between the light and the film (a light sample's BSDF, or one delta
    lobe's sample for light seen in a mirror or through glass); a film records the
    intensity (``(0, 0)``) of what arrives. The ``(0, 0)`` entry of ``M L`` with ``L``
    a depolarizer is ``M[0, 0] L[0, 0]``, whatever frames ``M`` is expressed in (Stokes
    frame rotations leave intensities alone), so the image equals ``direct``'s in that
    variant. Light reflected twice (a mirror seen in a mirror) would need the whole
    matrices; the integrator does not trace such paths."""
    return mi.unpolarized_spectrum(spectrum)


def as_spectrum(value):
    """An intensity (``mi.UnpolarizedSpectrum``) as the variant's ``mi.Spectrum``: a
    depolarizer Mueller matrix in a polarized variant (``mi.depolarizer``), else
    ``value`` itself; what ``sample()`` returns."""
    return mi.depolarizer(value)


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
