"""Visibility lookups: (map, world point, normal, footprint) -> visibility in [0, 1].

Every method is a function ``fn(smap, lk, opts, active) -> mi.Float`` where

* ``smap`` is the emitter's :class:`~mi_shadowmap.depth_maps.ShadowMap`
  (or, for ``raytraced``, a :class:`~.common.RayTracedLight`);
* ``lk`` is a :class:`~.common.Lookup`: the shading point ``p_world``, its
  geometric normal ``n_world``, the camera pixel footprint ``dp_dx``/``dp_dy``
  on the surface, the light sample ``ds`` and the ``sampler``;
* ``opts`` are the validated :class:`~mi_shadowmap.options.Options`.

Shared helpers (receiver depth with biases, tap patterns, ...) live once in
:mod:`.common`; each paper's method lives in its own module, which exports

* ``FILTERS`` -- ``{method name: function}``,
* optionally ``NEEDS_FOOTPRINT`` -- methods that read ``dp_dx``/``dp_dy``
  (the integrator computes the footprint only for those),
* optionally ``LAYERS`` -- ``{method: (layer, ...)}`` every extra per-texel
  depth-map layer the method may read (see
  :data:`mi_shadowmap.depth_maps.LAYER_BUILDERS`; what ``mi-shadowmap maps``
  exports),
* optionally ``LAYERS_FOR`` -- ``{method: fn(opts) -> (layer, ...)}`` the
  layers a render with those options builds, when that is not simply
  ``LAYERS[method]``: a subset (``mdsm`` with ``depths=1`` reads none) or
  small non-texel layers (``pcss_near``: one value per face).

:func:`layers_for` gives the layers to build for a render's options.

Depth comparisons happen in the map's depth space (world distance from the
light, see :mod:`mi_shadowmap.light_views`): a receiver at biased depth
``z_r`` is lit by a texel of depth ``z_map`` when ``z_r <= z_map``.
"""
from __future__ import annotations

from . import basic, bilinear, pcf, pcss
from . import mdsm, second_depth
from .common import Lookup, RayTracedLight, Receiver, receiver, shifted_grid_point  # noqa: F401

_MODULES = (basic, pcss, pcf, bilinear)
_MODULES += (second_depth, mdsm)

FILTERS: dict = {}
NEEDS_FOOTPRINT: set = set()
LAYERS: dict = {}
LAYERS_FOR: dict = {}
for _m in _MODULES:
    FILTERS.update(_m.FILTERS)
    NEEDS_FOOTPRINT |= set(getattr(_m, "NEEDS_FOOTPRINT", ()))
    LAYERS.update(getattr(_m, "LAYERS", {}))
    LAYERS_FOR.update(getattr(_m, "LAYERS_FOR", {}))


def layers_for(opts) -> tuple:
    """The extra depth-map layers a render with the validated ``opts`` builds
    (names of :data:`mi_shadowmap.depth_maps.LAYER_BUILDERS`): the method's
    ``LAYERS_FOR`` rule applied to ``opts``, else its ``LAYERS``, else none."""
    rule = LAYERS_FOR.get(opts.method)
    return tuple(rule(opts)) if rule is not None else tuple(LAYERS.get(opts.method, ()))
