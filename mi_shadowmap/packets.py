"""Shadow lookups only in the vector packets that hold a lit sample.

The render kernel shades camera samples in vector packets (8 lanes with AVX2). At 16 spp
a packet is half a pixel's samples, so the samples of the background, of receivers turned
away from the light and of the outside of a spot's cone are unlit together: 53 % of
``far_point``'s packets at 256^2 and 57 % on ``bench_virtual_cost.py``'s 1M-triangle mesh
hold no lit sample (``benchmarks/RESULTS.md``, fiftieth session, helper D).
:func:`in_lit_packets` runs a lookup in a symbolic ``dr.if_stmt`` on its active lanes, so
such a packet skips it; active lanes get the same values. A ``whole_light`` lookup
(``multiview``) is not run so: it looks up at every shaded lane, and on ``cbox_area``, whose
packets are nearly all shaded, the conditional made its render 25 ms of 665 slower.

**Random numbers.** A lookup that draws (``pcf``, ``pcss``) draws inside
the conditional, with the sampler as its state. Mitsuba's samplers advance a lane's random
stream only where a draw's mask is set, but all but ``independent`` (``stratified``,
``multijitter``, ``ldsampler``, ``orthogonal``) also advance a dimension index in every lane
at every draw, and the conditional merges it per lane: a lane that skipped the lookup kept
the old index, so its later draws (the next light's sample) read other dimensions than
without the conditional. The skipping branch therefore makes the same draws with no lane
active (:class:`_Draws`), which advances the index alone: the same numbers everywhere,
for every sampler.

A lookup run here must draw only through ``lk.sampler.next_1d`` / ``next_2d`` with a mask
within its ``active`` lanes (a draw without one is refused: its other lanes' streams
would advance without the conditional and not with it) and outside symbolic loops (as
every lookup, see :class:`~mi_shadowmap.filters.common.Lookup`), and must not read lane
values on the host (``dr.eval``, ``.numpy()``: Dr.Jit refuses inside a conditional). The
built-in methods do; a user's method says so with :func:`lit_packets`.
"""
from __future__ import annotations

import dataclasses

import drjit as dr
import mitsuba as mi

from .control_flow import if_stmt
from .methods import MethodError

#: The attribute :func:`lit_packets` sets on a lookup (kept by ``register_method``'s
#: wrapper, which copies the function's ``__dict__``).
_MARK = "runs_in_lit_packets"


def lit_packets(lookup):
    """Mark a user's ``lookup(smap, lk, opts, active)`` as one the integrator may run only
    in the vector packets that hold an active lane (as it runs the built-in methods'),
    before passing it to :func:`~mi_shadowmap.register_method`::

        @mi_shadowmap.lit_packets
        def my_lookup(smap, lk, opts, active=True):
            u = lk.sampler.next_2d(active)     # masked: the lookup's active lanes
            ...

    The lookup must then draw random numbers only through ``lk.sampler.next_1d`` /
    ``next_2d``, with a mask within ``active`` (a draw without a mask is a
    :class:`~mi_shadowmap.methods.MethodError` at the first render), outside
    ``dr.while_loop`` bodies, and must not read lane values on the host (``dr.eval``,
    ``.numpy()``, a Python ``if`` on a Dr.Jit value). Its images are then the same, bit
    for bit, as without the mark. A method registered with ``virtual_per_tap=True`` is
    run as before on virtual maps (its reads' check for symbolic loops cannot see
    through the conditional), and one with ``whole_light=True`` everywhere (see the
    module's docstring). Returns ``lookup``."""
    if not callable(lookup):
        raise MethodError(f"lit_packets: expected a lookup function, got "
                          f"{type(lookup).__name__}")
    setattr(lookup, _MARK, True)
    return lookup


def runs_in_lit_packets(record) -> bool:
    """Whether the integrator runs ``record``'s lookups only in packets with an active
    lane: a built-in map method, or a user's marked with :func:`lit_packets`; not a
    ``whole_light`` one (see the module's docstring)."""
    return record.uses_map and not record.whole_light and (
        record.builtin or getattr(record.lookup, _MARK, False) is True)


def in_lit_packets(run, lk, active, draws: bool = True):
    """``run(lk)`` -- a lookup's visibility at ``lk`` -- in a symbolic ``dr.if_stmt`` on
    ``active``: a vector packet without an active lane skips it and reads 0. Active lanes
    get what ``run`` gives them (as ``mi.Float``).

    ``draws``: ``run`` may draw from ``lk.sampler`` (then the sampler is the conditional's
    state and the skipping branch makes the same draws with no lane active, see the
    module's docstring); False for a lookup that never draws (a virtual per-tap one).
    ``run`` is called unconditionally where ``lk``'s point or normal tracks gradients, and
    where ``lk.sampler`` is not a ``mi.Sampler`` (a gradient render's recorded or per-pixel
    numbers)."""
    sampler = lk.sampler
    if dr.grad_enabled(lk.p_world, lk.n_world) or not (sampler is None
                                                       or isinstance(sampler, mi.Sampler)):
        return run(lk)
    active = mi.Bool(active)
    state = (sampler,) if draws and sampler is not None else ()
    drawn = []          # the taken branch's draws, for the skipping one

    def taken(*state):
        inner = lk if not state else dataclasses.replace(lk, sampler=_Draws(state[0]))
        vis = mi.Float(run(inner))
        drawn.append(inner.sampler.kinds if state else ())
        return (vis,) + state

    def skipped(*state):
        if not drawn:   # Dr.Jit traces the true branch first, in both modes
            raise RuntimeError("in_lit_packets: the skipping branch was traced first")
        for kind in drawn[-1]:          # advance a sampler's dimension, no lane's stream
            getattr(state[0], kind)(False)
        return (mi.Float(0.0),) + state

    return if_stmt(state, active, taken, skipped,
                   label="shadowmap: lookups in packets with a lit sample", holds_loops=True)[0]


class _Draws:
    """The sampler a lookup sees inside :func:`in_lit_packets`' conditional: the
    conditional's sampler, recording the kind of each draw (``kinds``) for the skipping
    branch; a draw without a mask is refused. Other attributes are the sampler's."""

    def __init__(self, sampler):
        self._sampler, self.kinds = sampler, []

    def _draw(self, kind, active):
        if active is True:
            raise MethodError(
                "shadowmap: a lookup run only in packets with a lit sample (a built-in "
                "method's, or one marked with mi_shadowmap.lit_packets) must draw with its "
                f"active lanes as the mask: lk.sampler.{kind}(active)")
        self.kinds.append(kind)
        return getattr(self._sampler, kind)(active)

    def next_1d(self, active=True):
        return self._draw("next_1d", active)

    def next_2d(self, active=True):
        return self._draw("next_2d", active)

    def __getattr__(self, name):
        return getattr(self._sampler, name)
