"""mi_shadowmap: depth-map shadows for Mitsuba 3, measured against ray tracing.

Importing the package

1. makes sure Dr.Jit's LLVM backend uses a libLLVM >= 16. When the package
   is pip-installed, ``mi_shadowmap_llvm.pth`` already set
   ``DRJIT_LIBLLVM_PATH`` at interpreter start, so ``mitsuba``/``drjit`` may
   be imported before ``mi_shadowmap``; otherwise it is searched and set now
   (unless already set), then the LLVM Dr.Jit loaded is checked (see
   :mod:`mi_shadowmap._llvm`),
2. selects the ``llvm_ad_rgb`` variant if no variant is set yet,
3. registers the ``shadowmap`` integrator for the current variant, and again
   whenever the variant changes.
"""
from __future__ import annotations

import os
import sys

from ._llvm import LLVMNotFoundError, check_loaded_llvm, configure_llvm

__version__ = "0.1.0"
DEFAULT_VARIANT = "llvm_ad_rgb"


def _started_as_command_line() -> bool:
    """True while the package is imported by its command line: the ``mi-shadowmap``
    script, or ``python -m mi_shadowmap`` (runpy sets ``sys.argv[0]`` to ``"-m"`` while
    it imports the package that holds the module to run; ``sys.orig_argv`` names that
    module, so a program of yours run with ``python -m`` whose package imports this one
    gets the exception, as any import from Python does)."""
    argv = getattr(sys, "argv", None) or [""]
    if os.path.basename(argv[0]) in ("mi-shadowmap", "mi-shadowmap.exe"):
        return True
    if argv[0] != "-m":
        return False
    orig = getattr(sys, "orig_argv", None)
    if not orig or len(orig) < len(argv):
        return True
    # python [options] -m MODULE args: sys.argv is ["-m", *args], so MODULE (or
    # "-mMODULE", "-BmMODULE" written as one word) is the word before the args
    word = orig[-len(argv)]
    module = word.split("m", 1)[1] if word.startswith("-") else word
    return module == "mi_shadowmap" or module.startswith("mi_shadowmap.")


def _check_llvm():
    """Configure and check the libLLVM (see :mod:`mi_shadowmap._llvm`). From the command
    line, an unusable LLVM is reported as its message and exit status 2, without the
    traceback of the import that found it (``--debug`` shows it, as for the command
    line's other errors); from Python it raises :class:`LLVMNotFoundError`."""
    drjit_imported_before = "drjit" in sys.modules
    try:
        path = configure_llvm()
        import mitsuba as mi
        return path, check_loaded_llvm(drjit_imported_before, mi.variant())
    except LLVMNotFoundError as err:
        if not _started_as_command_line() or "--debug" in sys.argv:
            raise
        message = str(err).removeprefix("mi_shadowmap: ")
        sys.stderr.write(f"mi-shadowmap: error: {message}\n")
        raise SystemExit(2) from None


LIBLLVM_PATH, LLVM_VERSION = _check_llvm()

import mitsuba as mi  # noqa: E402  (after the LLVM path is configured)

if mi.variant() is None:
    mi.set_variant(DEFAULT_VARIANT)

from . import integrator as _integrator  # noqa: E402


def _on_variant_change(old, new):
    _integrator.register(new)


_integrator.register()
mi.detail.add_variant_callback(_on_variant_change)

from .integrator import integrator_class  # noqa: E402,F401
from .variants import SUPPORTED_VARIANTS, UnsupportedVariantError  # noqa: E402,F401
from .options import METHODS, OptionError  # noqa: E402,F401
from .methods import (Method, MethodError, Prop, register_method,  # noqa: E402,F401
                      unregister_method)
from .light_views import UnsupportedEmitterError  # noqa: E402,F401
from .packets import lit_packets  # noqa: E402,F401
from . import harness, metrics  # noqa: E402,F401
from .harness import compare  # noqa: E402,F401
from .map_manager import clear_caches  # noqa: E402,F401
# ``tune`` is the function (its helpers: ``from mi_shadowmap.tune import ...``)
from .tune import TuneError, tune  # noqa: E402,F401


def __getattr__(name):
    # ``mi_shadowmap.ShadowMapIntegrator``: the current variant's class (one per variant).
    if name == "ShadowMapIntegrator":
        return integrator_class()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
