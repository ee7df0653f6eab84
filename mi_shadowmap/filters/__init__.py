"""The built-in shadow methods: one module per method, each exporting one record.

Every method module defines its lookup ``fn(smap, lk, opts, active) -> mi.Float``
(visibility in [0, 1]; see :mod:`mi_shadowmap.methods` for the call shape),
the helpers only it uses, and ``METHOD``: its
:class:`~mi_shadowmap.methods.Method` record (properties with types,
defaults, ranges and docs; the map layers it needs with their builders;
whether it reads the pixel footprint; its bias defaults). Importing this
package imports every module of it that defines ``METHOD`` and registers the
records (the first ones in the order of :data:`_FIRST`, then the others by
name), so a new method is one new module and nothing else; helpers two or
more methods share live in :mod:`.common`. Users add their own methods the same
way with :func:`mi_shadowmap.register_method`.

Depth comparisons happen in the map's depth space (world distance from the
light, see :mod:`mi_shadowmap.light_views`): a receiver at biased depth
``z_r`` is lit by a texel of depth ``z_map`` when ``z_r <= z_map``.
"""
from __future__ import annotations

import importlib
import pkgutil

from .. import methods as _methods
from .common import Lookup, RayTracedLight, Receiver, receiver, shifted_grid_point  # noqa: F401

#: The documented order of the first built-ins; later modules follow by name.
_FIRST = ("raytraced", "hard", "unshadowed", "pcss", "pcf", "bilinear", "second_depth",
          "mdsm")


def _method_modules() -> list:
    names = [m.name for m in pkgutil.iter_modules(__path__) if m.name != "common"]
    names.sort(key=lambda n: (_FIRST.index(n) if n in _FIRST else len(_FIRST), n))
    modules = [importlib.import_module(f"{__name__}.{n}") for n in names]
    return [m for m in modules if hasattr(m, "METHOD")]


BUILTIN = tuple(_method_modules())
for _module in BUILTIN:
    if _module.METHOD.name not in _methods.METHODS:
        _methods.add(_module.METHOD)
