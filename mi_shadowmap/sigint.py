"""The process's Ctrl-C (SIGINT) action around a render: read, restored, and told apart
from Mitsuba's own (:class:`~mi_shadowmap.integrator.ShadowMapIntegrator.render`).

Mitsuba's render binding installs a Ctrl-C handler for a render and keeps the one it
replaces in a single static; a Python ``render()`` override enters the binding twice,
so without these its handler stayed installed after every render, bound to the
integrator (a later Ctrl-C aborted the process or was swallowed). POSIX only (through
``sigaction`` and ``dladdr``); elsewhere every function here does nothing.
"""
from __future__ import annotations

_LIBC: list = []      # [the C library, or None where it has no sigaction (Windows)]


def _libc():
    if not _LIBC:
        try:
            import ctypes
            lib = ctypes.CDLL(None)
            lib.sigaction        # noqa: B018  (AttributeError where there is none)
        except (OSError, AttributeError, TypeError):
            lib = None
        _LIBC.append(lib)
    return _LIBC[0]


def sigint_action():
    """The process's SIGINT action (its ``struct sigaction``, as opaque bytes), for
    :func:`set_sigint_action`; None where it cannot be read (no ``sigaction``: Windows,
    where Mitsuba installs no Ctrl-C handler either)."""
    lib = _libc()
    if lib is None:
        return None
    import ctypes
    import signal
    buf = ctypes.create_string_buffer(512)    # larger than any libc's struct sigaction
    return buf if lib.sigaction(int(signal.SIGINT), None, buf) == 0 else None


def outside_mitsuba(action):
    """``action``, unless its handler is one of Mitsuba's (its render binding's, found
    with ``dladdr``): then Python's SIGINT handler's action, as ``signal.signal``
    installs it (``action`` where that cannot be had: not the main thread, a handler
    not set from Python, no ``dladdr``).

    Our render() called inside another render binding's scope (Mitsuba's ``aov``
    rendering this integrator as its child; Mitsuba's default ``render_backward``) finds
    that scope's handler installed, bound to the outer integrator; our own call of the
    binding then overwrote the single static that scope restores from with it, so
    Mitsuba's handler stayed installed after the outer render: a later Ctrl-C, once
    that integrator was freed, aborted the process ("free(): invalid pointer")."""
    lib = _libc()
    if action is None or lib is None or not hasattr(lib, "dladdr"):
        return action
    import ctypes
    import os

    class DlInfo(ctypes.Structure):
        _fields_ = [("dli_fname", ctypes.c_char_p), ("dli_fbase", ctypes.c_void_p),
                    ("dli_sname", ctypes.c_char_p), ("dli_saddr", ctypes.c_void_p)]

    info = DlInfo()
    handler = ctypes.c_void_p.from_buffer(action).value
    if not handler or handler <= 1 or not lib.dladdr(ctypes.c_void_p(handler),
                                                     ctypes.byref(info)):
        return action        # SIG_DFL, SIG_IGN, or not in a loaded library
    fname = os.fsdecode(info.dli_fname or b"")
    if "mitsuba" not in os.path.basename(os.path.dirname(fname)) + os.path.basename(fname):
        return action
    import signal
    import threading
    python = signal.getsignal(signal.SIGINT)
    if python is None or threading.current_thread() is not threading.main_thread():
        return action
    current = sigint_action()
    try:
        signal.signal(signal.SIGINT, python)      # Python's own C handler for it
        return sigint_action()
    except (ValueError, OSError):
        return action
    finally:
        set_sigint_action(current)


def set_sigint_action(action) -> None:
    """Install a SIGINT action read by :func:`sigint_action` (None: leave it)."""
    if action is not None:
        import signal
        _libc().sigaction(int(signal.SIGINT), action, None)
