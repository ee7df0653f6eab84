"""Depth maps built with Dr.Jit ray queries, and the :class:`ShadowMap` data.

A :class:`ShadowMap` holds, for one emitter, the :class:`LightView` it was
built from and flat ``mi.Float`` arrays of ``n_faces * res * res`` texels
(see :mod:`mi_shadowmap.light_views` for the texel order):

* ``depth`` -- distance to the first surface along each texel's ray
  (``+inf`` where the ray escapes);
* ``second_depth`` -- distance to the second surface (Wang & Molnar), built
  only when a method asks for it;
* ``extra`` -- further per-texel layers (e.g. MDSM min/max depths), built
  only when asked for.

Each map is one ray-query kernel (``scene.ray_intersect_preliminary``,
coherent rays), evaluated once when built.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import drjit as dr
import mitsuba as mi

from .light_views import LightView

_BYTES_PER_TEXEL = 4  # float32


@dataclass
class ShadowMap:
    """Depth layers of one emitter's map faces."""
    view: LightView
    resolution: int
    depth: mi.Float
    second_depth: mi.Float | None = None
    extra: dict = field(default_factory=dict)

    @property
    def n_texels(self) -> int:
        return self.view.n_faces * self.resolution * self.resolution

    @property
    def nbytes(self) -> int:
        layers = 1 + (self.second_depth is not None) + len(self.extra)
        return layers * self.n_texels * _BYTES_PER_TEXEL

    def texel_index(self, face, uv):
        """Flat index of the nearest texel (``floor(uv * res)``, clamped)."""
        res = self.resolution
        ij = dr.clip(mi.Point2i(dr.floor(uv * res)), 0, res - 1)
        return mi.UInt32(face) * (res * res) + mi.UInt32(ij.y) * res + mi.UInt32(ij.x)

    def fetch(self, layer: mi.Float, face, i, j, active=True):
        """Gather ``layer`` at integer texel coordinates (clamped to the face)."""
        res = self.resolution
        i = dr.clip(i, 0, res - 1)
        j = dr.clip(j, 0, res - 1)
        idx = mi.UInt32(face) * (res * res) + mi.UInt32(j) * res + mi.UInt32(i)
        return dr.gather(mi.Float, layer, idx, active)

    def to_numpy(self, layer: str = "depth"):
        """The layer as a ``(n_faces, res, res)`` float32 numpy array (row j, column i)."""
        data = self.depth if layer == "depth" else (
            self.second_depth if layer == "second_depth" else self.extra[layer])
        if data is None:
            raise KeyError(f"layer '{layer}' was not built for emitter '{self.view.label}'")
        return data.numpy().reshape(self.view.n_faces, self.resolution, self.resolution)

    def layers(self) -> list[str]:
        return (["depth"] + (["second_depth"] if self.second_depth is not None else [])
                + list(self.extra))


def _first_hit(scene: mi.Scene, view: LightView, o, d, max_t):
    """Distance to the first surface along (o, d), skipping the light's own shape."""
    ray = mi.Ray3f(o, d)
    pi = scene.ray_intersect_preliminary(ray, coherent=True)
    if view.ignore_shape is None:
        return dr.select(pi.is_valid(), pi.t, dr.inf)
    own = mi.ShapePtr(view.ignore_shape)
    t_acc = mi.Float(0.0)

    # Continue through the emitter's own surface (it must never occlude itself).
    def cond(ray, pi, t_acc):
        return pi.is_valid() & (pi.shape == own)

    def body(ray, pi, t_acc):
        step = pi.t * (1.0 + 1e-5) + 1e-7 * (t_acc + pi.t)
        t_acc = t_acc + step
        ray = mi.Ray3f(ray.o + ray.d * step, ray.d)
        pi = scene.ray_intersect_preliminary(ray, coherent=True)
        return ray, pi, t_acc

    ray, pi, t_acc = dr.while_loop((ray, pi, t_acc), cond, body)
    return dr.select(pi.is_valid(), t_acc + pi.t, dr.inf)


#: Extra layers: ``name -> fn(scene, smap) -> mi.Float`` (``n_texels`` entries).
#: Filters name the layers they need (``filters.LAYERS``); the integrator asks
#: :func:`build_depth_map` for exactly those, so nothing unused is built.
LAYER_BUILDERS: dict = {}


def build_depth_map(scene: mi.Scene, view: LightView, resolution: int,
                    layers=()) -> ShadowMap:
    """Ray-cast the first-surface depth of every texel of ``view``, plus ``layers``."""
    o, d, max_t = view.texel_rays(resolution)
    depth = _first_hit(scene, view, o, d, max_t)
    dr.eval(depth)
    smap = ShadowMap(view=view, resolution=resolution, depth=depth)
    for name in layers:
        if name not in LAYER_BUILDERS:
            raise KeyError(f"unknown depth-map layer '{name}'; known: {sorted(LAYER_BUILDERS)}")
        data = LAYER_BUILDERS[name](scene, smap)
        dr.eval(data)
        if name == "second_depth":
            smap.second_depth = data
        else:
            smap.extra[name] = data
    return smap


def write_exr(smap: ShadowMap, path: str, layer: str = "depth") -> None:
    """Write one layer as a float32 EXR (faces stacked vertically, channel ``Y``)."""
    arr = smap.to_numpy(layer)
    bmp = mi.Bitmap(arr.reshape(-1, smap.resolution))
    bmp.write(str(path))
