"""Dr.Jit conditionals that follow the user's Dr.Jit flags.

Dr.Jit 1.5 picks the mode of a ``dr.if_stmt`` or ``dr.while_loop`` left at
``mode=None`` from ``JitFlag.SymbolicConditionals`` / ``JitFlag.SymbolicLoops``,
except inside a symbolic operation (``JitFlag.SymbolicScope``: the body of a
symbolic loop, conditional or call being recorded), where only the symbolic mode
is possible. Two consequences reached users who debug with those flags:

* **A loop inside a symbolic conditional** is recorded symbolically whatever
  ``SymbolicLoops`` says, and Dr.Jit logs ``ad_loop("..."): forcing conditional
  statement to symbolic mode since the operation is nested within another symbolic
  operation`` for it. With ``SymbolicLoops`` off (to ``dr.print`` inside a loop, or
  to find a miscompiled one), every ``hard`` and ``mdsm`` render on virtual maps
  logged it (their page-walk and tap loops sit in a ``dr.if_stmt``), three lines a
  render, and those loops stayed symbolic. :func:`if_stmt` with ``holds_loops``
  runs such a conditional evaluated when ``SymbolicLoops`` is off (and no symbolic
  operation encloses it), so the loops in it are evaluated as asked.
* **A conditional inside a symbolic loop** with ``SymbolicCalls`` off: Dr.Jit 1.5's
  ``ad_cond`` tests ``SymbolicCalls``, not ``SymbolicConditionals``, before it logs
  ``ad_cond("..."): forcing conditional statement to symbolic mode ...``, so a
  conditional nobody asked to evaluate warned, once per conditional and render (681
  lines over the 264 renders of our flag sweep). :func:`if_stmt` gives the mode,
  ``symbolic``, inside a symbolic operation, which Dr.Jit accepts without a word.

Everything else is ``dr.if_stmt``'s: the same values in every mode.
"""
from __future__ import annotations

import drjit as dr


def if_stmt(args, cond, true_fn, false_fn, label: str | None = None,
            holds_loops: bool = False):
    """``dr.if_stmt(args, cond, true_fn, false_fn, label=label)`` in the mode the
    user's flags call for (see the module's docstring).

    Parameter ``holds_loops`` (``bool``):
        A branch runs a ``dr.while_loop``: outside a symbolic operation, with
        ``JitFlag.SymbolicLoops`` off, the conditional runs evaluated so that its
        loops can be too.
    """
    if dr.flag(dr.JitFlag.SymbolicScope):
        mode = "symbolic"           # the only mode here; named, Dr.Jit does not warn
    elif holds_loops and not dr.flag(dr.JitFlag.SymbolicLoops):
        mode = "evaluated"
    else:
        mode = None                 # JitFlag.SymbolicConditionals decides
    return dr.if_stmt(args, cond, true_fn, false_fn, label=label, mode=mode)
