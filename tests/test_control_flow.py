"""Renders under the Dr.Jit flags users debug with (``mi_shadowmap/control_flow.py``).

The image must not change with the flags, Dr.Jit must log nothing about our
kernels, and every flag must be as the user left it after the render. Each test
sets its flags in a ``try/finally`` (:func:`_flags`).
"""
import contextlib

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from mi_shadowmap.scenes import default_scene

SIZE, SPP = 32, 2


@contextlib.contextmanager
def _flags(**values):
    """Set ``dr.JitFlag`` members by name, restoring every flag afterwards."""
    before = {f: dr.flag(f) for f in dr.JitFlag}
    try:
        for name, value in values.items():
            dr.set_flag(getattr(dr.JitFlag, name), value)
        yield
    finally:
        for f, v in before.items():
            dr.set_flag(f, v)


def _render(light, method):
    """A fresh scene and integrator (virtual maps: the default), rendered once, and
    whether the render left every Dr.Jit flag as it found it."""
    scene = mi.load_dict(default_scene(width=SIZE, height=SIZE, spp=SPP, light=light))
    integ = mi.load_dict({"type": "shadowmap", "method": method})
    before = {f: dr.flag(f) for f in dr.JitFlag}
    img = np.array(mi.render(scene, integrator=integ, spp=SPP, seed=5))
    dr.sync_thread()
    return img, before == {f: dr.flag(f) for f in dr.JitFlag}


@pytest.mark.parametrize("method", ["hard", "mdsm"])
def test_evaluated_loops_are_evaluated_without_warnings(method, capfd):
    """``SymbolicLoops`` off: the loops in a conditional (the virtual page walk of a
    ``hard`` lookup whose page is missing, ``mdsm``'s tap loop near a face border) were
    forced symbolic and Dr.Jit logged ``ad_loop("unnamed"): forcing conditional
    statement to symbolic mode ...`` three times a render; those conditionals now run
    evaluated there, their loops too. Same image as with the default flags."""
    reference, _ = _render("point", method)
    capfd.readouterr()
    with _flags(SymbolicLoops=False):
        img, kept = _render("point", method)
    log = capfd.readouterr().err
    assert "forcing" not in log, log
    assert kept
    assert np.array_equal(img, reference)


def test_conditionals_in_loops_do_not_warn_without_symbolic_calls(capfd):
    """``SymbolicCalls`` off: Dr.Jit 1.5 logs ``ad_cond(...): forcing conditional
    statement to symbolic mode ...`` for every ``dr.if_stmt`` left at the default mode
    inside a symbolic loop (its ``ad_cond`` tests ``SymbolicCalls``, not
    ``SymbolicConditionals``): ``pcf`` under a point light (its taps' cube-seam and
    receiver-plane conditionals) logged it on every render. Same image as with the
    default flags."""
    reference, _ = _render("point", "pcf")
    capfd.readouterr()
    with _flags(SymbolicCalls=False):
        img, kept = _render("point", "pcf")
    log = capfd.readouterr().err
    assert "ad_cond" not in log, log
    assert kept
    assert np.array_equal(img, reference)


@pytest.mark.parametrize("light, method", [("spot", "pcss"), ("area", "pcf")])
def test_debug_mode_reports_nothing(light, method, capfd):
    """``JitFlag.Debug`` checks every gather and scatter (page tables, pools, full
    maps): nothing out of bounds, the same image."""
    reference, _ = _render(light, method)
    capfd.readouterr()
    with _flags(Debug=True):
        img, kept = _render(light, method)
    log = capfd.readouterr().err
    assert "drjit" not in log and "out-of-bounds" not in log, log
    assert kept
    assert np.array_equal(img, reference)
