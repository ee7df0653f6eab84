"""Find a libLLVM that Dr.Jit 1.5 can use, before any LLVM variant is set.

Dr.Jit's LLVM backend loads a shared ``libLLVM`` at run time. Version 16 or
newer is required: Debian bookworm's preinstalled libLLVM 14/15 crash at the
first kernel (``LLVM ERROR: Cannot select: ... fminimum``), and without
guidance Dr.Jit picks whichever ``libLLVM*.so`` it finds first.

Search order (the first hit wins):

1. ``DRJIT_LIBLLVM_PATH`` if the user already set it. It is respected as it
   is (only checked to exist); we never override a user's choice.
2. The Python environment's own ``lib/`` folder (``sys.prefix`` and
   ``sys.base_prefix``): this is where the PyPI wheel ``karellen-llvm-core``
   (a dependency of this package, no root needed) installs ``libLLVM.so.N``.
3. System libraries of version >= 16: ``/usr/lib/llvm-N/lib``,
   ``/usr/lib/<triplet>/libLLVM-N.so`` (Debian's ``libllvm19`` etc.),
   ``/usr/local/lib`` and ``/opt/homebrew/opt/llvm/lib``.

Candidates whose version (read from the file name) is below 16 are skipped
and reported.

Dr.Jit reads ``DRJIT_LIBLLVM_PATH`` once, when ``drjit`` (or ``mitsuba``) is
first imported. So ``import mi_shadowmap`` must come before ``import
mitsuba``/``import drjit``, unless the variable is set in the environment.
After importing Dr.Jit, :func:`check_loaded_llvm` asks it which LLVM it
actually loaded and refuses one older than 16 with an explanation. When nothing usable is found, :class:`LLVMNotFoundError`
lists every path that was tried and how to fix it.
"""
from __future__ import annotations

import glob
import os
import re
import sys

MIN_LLVM_VERSION = 16
ENV_VAR = "DRJIT_LIBLLVM_PATH"


class LLVMNotFoundError(RuntimeError):
    """No libLLVM >= 16 could be found for Dr.Jit's LLVM backend."""


def llvm_version_from_name(path: str) -> int | None:
    """Major LLVM version encoded in a library file name, or None.

    ``libLLVM.so.23.1`` -> 23, ``libLLVM-19.so`` -> 19,
    ``libLLVM-14.0.6.so.1`` -> 14, ``/usr/lib/llvm-17/lib/libLLVM.so`` -> 17.
    """
    name = os.path.basename(path)
    for pattern in (r"libLLVM-(\d+)", r"libLLVM\.so\.(\d+)", r"libLLVM\.(\d+)\.dylib"):
        m = re.search(pattern, name)
        if m:
            return int(m.group(1))
    m = re.search(r"llvm-(\d+)", path)
    return int(m.group(1)) if m else None


def _candidates() -> list[str]:
    prefixes = []
    for p in (sys.prefix, sys.base_prefix, os.environ.get("VIRTUAL_ENV")):
        if p and p not in prefixes:
            prefixes.append(p)
    found: list[str] = []
    for p in prefixes:
        found += sorted(glob.glob(os.path.join(p, "lib", "libLLVM*.so*")))
        found += sorted(glob.glob(os.path.join(p, "lib", "libLLVM*.dylib")))
    system = (
        glob.glob("/usr/lib/llvm-*/lib/libLLVM*.so*")
        + glob.glob("/usr/lib/*-linux-gnu/libLLVM*.so*")
        + glob.glob("/usr/lib64/libLLVM*.so*")
        + glob.glob("/usr/local/lib/libLLVM*.so*")
        + glob.glob("/opt/homebrew/opt/llvm/lib/libLLVM*.dylib")
    )
    # Newest system version first.
    system.sort(key=lambda s: -(llvm_version_from_name(s) or 0))
    found += system
    return [f for f in dict.fromkeys(found) if os.path.isfile(f)]


def find_libllvm() -> tuple[str, list[str]]:
    """Return (path, report) of the first usable libLLVM, or raise.

    ``report`` is a list of human-readable lines saying what was tried.
    """
    tried: list[str] = []
    for path in _candidates():
        version = llvm_version_from_name(path)
        if version is not None and version < MIN_LLVM_VERSION:
            tried.append(f"{path}: LLVM {version} < {MIN_LLVM_VERSION} (crashes Dr.Jit 1.5), skipped")
            continue
        tried.append(f"{path}: LLVM {version if version else '?'}, used")
        return path, tried
    raise LLVMNotFoundError(
        "mi_shadowmap: no usable libLLVM (version >= %d) found for Dr.Jit's LLVM backend.\n"
        "Tried:\n  %s\n"
        "Fix one of:\n"
        "  * pip install karellen-llvm-core   (no root; installs libLLVM into this environment)\n"
        "  * apt-get install libllvm19        (root; Debian/Ubuntu)\n"
        "  * export %s=/path/to/libLLVM.so (version >= %d)"
        % (MIN_LLVM_VERSION, "\n  ".join(tried) or "(no libLLVM*.so found anywhere)", ENV_VAR,
           MIN_LLVM_VERSION)
    )


def configure_llvm() -> str:
    """Set ``DRJIT_LIBLLVM_PATH`` unless the user did; return the path in use."""
    user = os.environ.get(ENV_VAR)
    if user:
        if not os.path.isfile(user):
            raise LLVMNotFoundError(
                f"mi_shadowmap: {ENV_VAR}={user!r} does not exist. Unset it to let "
                "mi_shadowmap search, or point it at a libLLVM >= %d." % MIN_LLVM_VERSION)
        return user
    path, _ = find_libllvm()
    os.environ[ENV_VAR] = path
    return path


def check_loaded_llvm(drjit_imported_before: bool, variant: str | None) -> tuple:
    """Verify the LLVM version Dr.Jit actually loaded; raise if it is too old.

    Only LLVM variants need it: for a CUDA variant an old LLVM is ignored.
    """
    import drjit as dr
    try:
        version = tuple(dr.detail.llvm_version())
    except Exception:   # backend inactive: no library could be loaded
        version = (0, 0, 0)
    if version[0] >= MIN_LLVM_VERSION or (variant and not variant.startswith("llvm")):
        return version
    if version[0] == 0:
        problem = "Dr.Jit's LLVM backend is inactive (it could not load any libLLVM)"
    else:
        problem = "Dr.Jit loaded LLVM %s, which crashes it (>= %d is needed)" % (
            ".".join(map(str, version)), MIN_LLVM_VERSION)
    why = ("drjit/mitsuba was imported before mi_shadowmap, so Dr.Jit chose its libLLVM "
           "before mi_shadowmap could point it at %s. Import mi_shadowmap first, or set "
           "%s=%s before starting Python." % (os.environ.get(ENV_VAR), ENV_VAR,
                                              os.environ.get(ENV_VAR))
           if drjit_imported_before else
           "%s=%s was set, but Dr.Jit did not use it." % (ENV_VAR, os.environ.get(ENV_VAR)))
    raise LLVMNotFoundError("mi_shadowmap: %s. %s" % (problem, why))
