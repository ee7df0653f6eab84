"""Start-up hook of mi_shadowmap: point Dr.Jit at a libLLVM >= 16 before it is imported.

Dr.Jit 1.5 reads ``DRJIT_LIBLLVM_PATH`` once, when ``drjit`` is first imported,
and otherwise may pick a system libLLVM 14/15 that crashes it. The file
``mi_shadowmap_llvm.pth``, installed next to this module in site-packages,
calls :func:`set_default_libllvm` at every interpreter start (not under
``python -S``), so the import order of ``mitsuba``/``drjit``/``mi_shadowmap``
no longer matters.

This module must stay tiny and cheap: it imports only ``os`` and ``sys`` (no
``re``, no ``glob``), never ``mitsuba``/``drjit``/``mi_shadowmap``, and
:func:`set_default_libllvm` never raises. ``mi_shadowmap._llvm`` reuses its
functions for the fuller search done when the package is imported.
"""
import os
import sys

MIN_LLVM_VERSION = 16
ENV_VAR = "DRJIT_LIBLLVM_PATH"

#: The path :func:`set_default_libllvm` put into ``DRJIT_LIBLLVM_PATH`` in this
#: process, or None if it set nothing.
STARTUP_PATH = None


def _int_after(text, marker, suffix=""):
    """First integer right after ``marker`` in ``text`` (and followed by ``suffix``)."""
    i = text.find(marker)
    while i >= 0:
        j = k = i + len(marker)
        while k < len(text) and text[k].isdigit():
            k += 1
        if k > j and text.startswith(suffix, k):
            return int(text[j:k])
        i = text.find(marker, i + 1)
    return None


def llvm_version_from_name(path):
    """Major LLVM version encoded in a library file name, or None.

    ``libLLVM.so.23.1`` -> 23, ``libLLVM-19.so`` -> 19,
    ``libLLVM-14.0.6.so.1`` -> 14, ``libLLVM.17.dylib`` -> 17,
    ``/usr/lib/llvm-17/lib/libLLVM.so`` -> 17.
    """
    name = os.path.basename(path)
    for marker, suffix in (("libLLVM-", ""), ("libLLVM.so.", ""), ("libLLVM.", ".dylib")):
        version = _int_after(name, marker, suffix)
        if version is not None:
            return version
    return _int_after(path, "llvm-")


def _prefixes():
    """``sys.prefix``, the user base if user site-packages are enabled, ``sys.base_prefix``."""
    prefixes = [sys.prefix]
    # ``pip install --user`` puts karellen-llvm-core's libLLVM into <site.USER_BASE>/lib
    # (~/.local/lib). ``site`` is imported already wherever .pth files run; not under -S.
    site = sys.modules.get("site")
    if site is not None and getattr(site, "ENABLE_USER_SITE", False):
        user_base = getattr(site, "USER_BASE", None)
        if user_base:
            prefixes.append(user_base)
    prefixes.append(sys.base_prefix)
    return list(dict.fromkeys(prefixes))


def prefix_libraries():
    """Every ``libLLVM*.so*``/``libLLVM*.dylib`` file in ``<prefix>/lib``, any version.

    Prefixes: ``sys.prefix`` (the virtual environment, where the PyPI wheel
    ``karellen-llvm-core`` installs ``libLLVM.so.N``), the user base when user
    site-packages are enabled (``pip install --user``: ``~/.local``), then
    ``sys.base_prefix``. Within a folder, newest version first.
    """
    found = []
    for prefix in _prefixes():
        folder = os.path.join(prefix, "lib")
        try:
            names = os.listdir(folder)
        except OSError:
            continue
        names = [n for n in names if n.startswith("libLLVM")
                 and (".so" in n or n.endswith(".dylib"))]
        names.sort(key=lambda n: (-(llvm_version_from_name(n) or 0), n))
        found += [p for p in (os.path.join(folder, n) for n in names) if os.path.isfile(p)]
    return found


def set_default_libllvm():
    """Set ``DRJIT_LIBLLVM_PATH`` to the environment's libLLVM >= 16, if it is unset.

    A value already set (by the user) is left untouched. Libraries whose file
    name does not show a version >= 16 are ignored. Returns the path set, or
    None. Never raises.
    """
    global STARTUP_PATH
    try:
        if os.environ.get(ENV_VAR):
            return None
        for path in prefix_libraries():
            if (llvm_version_from_name(path) or 0) >= MIN_LLVM_VERSION:
                os.environ[ENV_VAR] = STARTUP_PATH = path
                return path
    except Exception:
        pass
    return None
