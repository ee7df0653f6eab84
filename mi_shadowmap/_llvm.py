"""Find a libLLVM that Dr.Jit 1.5 can use, and check the one it loaded.

Dr.Jit's LLVM backend loads a shared ``libLLVM`` at run time. Version 16 or
newer is required: Debian bookworm's preinstalled libLLVM 14/15 crash at the
first kernel (``LLVM ERROR: Cannot select: ... fminimum``), and without
guidance Dr.Jit picks whichever ``libLLVM*.so`` it finds first.

Dr.Jit reads ``DRJIT_LIBLLVM_PATH`` once, when ``drjit`` (or ``mitsuba``) is
first imported. When the package is pip-installed (``pip install .`` or
``pip install -e .``), the file ``mi_shadowmap_llvm.pth`` in site-packages
runs :func:`_mi_shadowmap_llvm.set_default_libllvm` at interpreter start: if
the variable is unset, it is set to the environment's own libLLVM >= 16
(``<sys.prefix>/lib``, where the dependency ``karellen-llvm-core`` installs
``libLLVM.so.N``; then the user base's ``lib`` after ``pip install --user``, then
``<sys.base_prefix>/lib``). So ``mitsuba``/``drjit``
may be imported before ``mi_shadowmap``.

On ``import mi_shadowmap``, :func:`configure_llvm` fills the variable if it
is still unset (no .pth ran: ``python -S``, or the source tree is used
without installing), searching in order (the first hit wins):

1. ``DRJIT_LIBLLVM_PATH`` if already set (by the user or the start-up hook).
   It is respected as it is (only checked to exist); a user's choice is never
   overridden.
2. The Python environment's own ``lib/`` folder (``sys.prefix`` and
   ``sys.base_prefix``).
3. System libraries of version >= 16: ``/usr/lib/llvm-N/lib``,
   ``/usr/lib/<triplet>/libLLVM-N.so`` (Debian's ``libllvm19`` etc.),
   ``/usr/local/lib`` and ``/opt/homebrew/opt/llvm/lib``.

Candidates whose version (read from the file name) is below 16 are skipped
and reported. That late setting only helps if ``drjit`` was not imported yet.

After importing Dr.Jit, :func:`check_loaded_llvm` asks it which LLVM it
actually loaded and refuses one older than 16 with an explanation: the cases
the package cannot fix are a ``DRJIT_LIBLLVM_PATH`` forced to an old library,
and ``drjit`` imported first without the start-up hook (``python -S``, not
installed). When nothing usable is found, :class:`LLVMNotFoundError` lists
every path that was tried and how to fix it.
"""
from __future__ import annotations

import glob
import os
import sys

# The start-up hook's module (top level, installed with this package) holds the
# shared parts: it must not import this package, which imports mitsuba.
import _mi_shadowmap_llvm as _startup
from _mi_shadowmap_llvm import ENV_VAR, MIN_LLVM_VERSION, llvm_version_from_name  # noqa: F401


class LLVMNotFoundError(RuntimeError):
    """No libLLVM >= 16 could be found for Dr.Jit's LLVM backend."""


def _candidates() -> list[str]:
    found = _startup.prefix_libraries()
    venv = os.environ.get("VIRTUAL_ENV")
    if venv and venv not in (sys.prefix, sys.base_prefix):
        found += sorted(glob.glob(os.path.join(venv, "lib", "libLLVM*.so*")))
        found += sorted(glob.glob(os.path.join(venv, "lib", "libLLVM*.dylib")))
    # The lib/ folder of every environment whose site-packages is on sys.path
    # (karellen-llvm-core installs at <site-packages>/../../): under ``python -S``
    # sys.prefix is not the venv's, but the venv's site-packages may be on sys.path.
    for entry in sys.path:
        if os.path.basename(os.path.normpath(entry or ".")) in ("site-packages", "dist-packages"):
            lib = os.path.normpath(os.path.join(entry, "..", ".."))
            found += sorted(glob.glob(os.path.join(lib, "libLLVM*.so*")),
                            key=lambda s: -(llvm_version_from_name(s) or 0))
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


#: The path :func:`configure_llvm` put into ``DRJIT_LIBLLVM_PATH``, or None.
_SET_BY_CONFIGURE: str | None = None


def configure_llvm() -> str:
    """Set ``DRJIT_LIBLLVM_PATH`` unless already set; return the path in use."""
    global _SET_BY_CONFIGURE
    user = os.environ.get(ENV_VAR)
    if user:
        # A bare file name (no "/") is looked up by the dynamic loader (LD_LIBRARY_PATH,
        # ld.so.cache), not in the current folder: check_loaded_llvm checks what Dr.Jit loaded.
        if os.sep in user and not os.path.isfile(user):
            what = ("is a directory, not a library file" if os.path.isdir(user)
                    else "does not exist")
            raise LLVMNotFoundError(
                f"mi_shadowmap: {ENV_VAR}={user!r} {what}. Unset it to let "
                "mi_shadowmap search, or point it at a libLLVM >= %d." % MIN_LLVM_VERSION)
        return user
    path, _ = find_libllvm()
    os.environ[ENV_VAR] = _SET_BY_CONFIGURE = path
    return path


def check_loaded_llvm(drjit_imported_before: bool, variant: str | None) -> tuple:
    """Verify the LLVM version Dr.Jit actually loaded; raise if it is too old.

    Only LLVM variants need it: for a CUDA variant an old LLVM is ignored.
    The error says why, for the cases the package cannot fix: a
    ``DRJIT_LIBLLVM_PATH`` set (outside mi_shadowmap) to an old library, or
    ``drjit`` imported first while the start-up hook did not run.
    """
    import drjit as dr
    try:
        version = tuple(dr.detail.llvm_version())
    except Exception:   # backend inactive: no library could be loaded
        version = (0, 0, 0)
    if version[0] >= MIN_LLVM_VERSION or (variant and not variant.startswith("llvm")):
        return version
    if version[0] <= 0:   # Dr.Jit 1.5 reports an inactive backend as (-1, -1, -1)
        problem = "Dr.Jit's LLVM backend is inactive (it could not load any libLLVM)"
        named = llvm_version_from_name(os.environ.get(ENV_VAR) or "")
        if named is not None and named < MIN_LLVM_VERSION:
            problem = ("Dr.Jit's LLVM backend is inactive: it refused LLVM %d (>= %d is "
                       "needed)" % (named, MIN_LLVM_VERSION))
    else:
        problem = "Dr.Jit loaded LLVM %s, which crashes it (>= %d is needed)" % (
            ".".join(map(str, version)), MIN_LLVM_VERSION)
    value = os.environ.get(ENV_VAR)
    if drjit_imported_before and (not value or value == _SET_BY_CONFIGURE):
        why = ("drjit/mitsuba was imported before mi_shadowmap while %s was unset, so Dr.Jit "
               "chose its own libLLVM. mi_shadowmap's start-up hook (mi_shadowmap_llvm.pth in "
               "site-packages), which sets the variable at interpreter start, did not run: "
               "Python was started with -S, or mi_shadowmap is not pip-installed in this "
               "environment (pip install -e .). Import mi_shadowmap first, or set %s=%s "
               "before starting Python." % (ENV_VAR, ENV_VAR, value or "/path/to/libLLVM.so"))
    elif value and value in (_SET_BY_CONFIGURE, _startup.STARTUP_PATH):
        why = "mi_shadowmap set %s=%s, but Dr.Jit did not use it." % (ENV_VAR, value)
    else:
        why = ("%s=%s was set outside mi_shadowmap (Dr.Jit uses the value it had when drjit "
               "was first imported). Unset it to let mi_shadowmap choose, or point it at a "
               "libLLVM >= %d." % (ENV_VAR, value, MIN_LLVM_VERSION))
    raise LLVMNotFoundError("mi_shadowmap: %s. %s" % (problem, why))
