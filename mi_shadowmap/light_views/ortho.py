"""Directional lights: one orthographic face fitted to the scene (:class:`OrthoView`).

The face is aligned with the light direction and fitted to the scene's
bounding-box corners as seen along the light (the tight rectangle of the
projected corners, not a bounding sphere). A scene without valid bounds (no
shapes) gets the box ``[-1, 1]^3`` instead -- nothing can cast a shadow
there anyway. Depth is measured from the near plane along the light.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

from .base import (LightView, light_matrix, look_along, look_along_np, scalar3,
                   opaque_light_from_world, opaque_point, opaque_scalar,
                   opaque_world_from_light, divide_by_res, scene_bounds,
                   texel_width_along, transform_f64, unit_grid, world_matrix)


@dataclass(frozen=True)
class OrthoView(LightView):
    """One orthographic face; ``half_extent`` is the half width/height of its rectangle
    and ``position`` the rectangle's centre on the near plane."""
    half_extent: tuple = (1.0, 1.0)

    projection = "orthographic"

    @property
    def n_faces(self) -> int:
        return 1

    def _half(self, double: bool = False):
        """``half_extent`` as opaque JIT scalars (a directional light turned or the
        scene's bounds changed compile no new kernel)."""
        return tuple(opaque_scalar(h, double) for h in self.half_extent)

    def _world_from_light(self):
        return opaque_world_from_light(self)

    def _forward(self):
        return self._world_from_light() @ mi.Vector3f(0, 0, 1)

    def texel_rays(self, res: int):
        _, s, t = unit_grid(1, res)
        hx, hy = self._half()
        o_light = mi.Point3f(s * hx, t * hy, 0.0)
        w = self._world_from_light()
        return w @ o_light, w @ mi.Vector3f(0, 0, 1)

    def ray_through(self, face, uv_light: mi.Point2f):
        s = uv_light.x * 2.0 - 1.0
        t = uv_light.y * 2.0 - 1.0
        hx, hy = self._half()
        o_light = mi.Point3f(s * hx, t * hy, 0.0)
        w = self._world_from_light()
        return mi.Point3f(w @ o_light), dr.normalize(w @ mi.Vector3f(0, 0, 1))

    def project(self, p_world: mi.Point3f):
        p_world = mi.Point3f(p_world)
        p_light = opaque_light_from_world(self) @ p_world
        hx, hy = self._half()
        uv = mi.Point2f(0.5 * (p_light.x / hx + 1.0), 0.5 * (p_light.y / hy + 1.0))
        z = mi.Float(1.0)
        depth = p_light.z
        inside = (z > 0) & (uv.x >= 0) & (uv.x <= 1) & (uv.y >= 0) & (uv.y <= 1)
        return mi.UInt32(0), uv, depth, inside

    # ------------------------------------------------------------- float64
    @property
    def supports_virtual(self):
        return type(self) is OrthoView   # CascadedView says so itself

    def uv_on_face_f64(self, face, p_world):
        p_light = transform_f64(light_matrix(self), mi.Point3d(p_world))
        hx, hy = self._half(True)
        return mi.Point2d(0.5 * (p_light.x / hx + 1.0), 0.5 * (p_light.y / hy + 1.0))

    def uv_differential(self, face, p_world, dp_world):
        dp = opaque_light_from_world(self) @ mi.Vector3f(dp_world)
        hx, hy = self._half()
        return mi.Point2f(0.5 * dp.x / hx, 0.5 * dp.y / hy)

    def depth_differential(self, p_world, dp_world):
        return dr.dot(mi.Vector3f(dp_world), dr.normalize(self._forward()))

    def project_f64(self, p_world):
        p_light = transform_f64(light_matrix(self), mi.Point3d(p_world))
        hx, hy = self._half(True)
        uv = mi.Point2d(0.5 * (p_light.x / hx + 1.0), 0.5 * (p_light.y / hy + 1.0))
        inside = (uv.x >= 0) & (uv.x <= 1) & (uv.y >= 0) & (uv.y <= 1)
        return mi.UInt32(0), uv, p_light.z, inside

    def ray_through_f64(self, face, uv_light):
        s = uv_light.x * 2.0 - 1.0
        t = uv_light.y * 2.0 - 1.0
        W = world_matrix(self)
        hx, hy = self._half(True)
        o = transform_f64(W, mi.Point3d(s * hx, t * hy, 0.0))
        d = transform_f64(W, mi.Vector3d(0.0, 0.0, 1.0), point=False)
        return o, dr.normalize(d)

    def ray_frame_f64(self, face, uv_light):
        """(:attr:`~.base.LightView.ray_frame_f64`) Parallel rays: the origin moves by
        ``2 half_extent`` along the light's x and y per unit of ``uv``."""
        return self._parallel_frame(*self._half())

    def _parallel_frame(self, hx, hy):
        """The parallel ray frame of a rectangle of half sizes ``hx``, ``hy`` (floats or
        per-lane ``mi.Float``) in the light's plane."""
        R = world_matrix(self)[:3, :3]
        d = R[:, 2] / np.linalg.norm(R[:, 2])
        # opaque (opaque_point): a turned light compiles no new kernel
        return (False, mi.Vector3f(opaque_point(d)), mi.Vector3f(opaque_point(2.0 * R[:, 0])) * hx,
                mi.Vector3f(opaque_point(2.0 * R[:, 1])) * hy)

    def depth_of(self, p_world: mi.Point3f) -> mi.Float:
        return dr.dot(p_world - opaque_point(self.position), self._forward())

    def texel_world_size(self, res: int, depth, p_world=None, n_world=None):
        # ``res`` may be per lane (virtual maps' levels)
        zero = dr.zeros(mi.Float, dr.width(depth))
        if n_world is None:
            return zero + divide_by_res(2.0 * opaque_scalar(max(self.half_extent)), res)
        hx, hy = self._half()
        return zero + self._texel_along(divide_by_res(2.0 * hx, res),
                                        divide_by_res(2.0 * hy, res), n_world)

    def _texel_along(self, w_x, w_y, n_world):
        """:func:`~.base.texel_width_along` in this light's image plane."""
        w = self._world_from_light()
        return texel_width_along(w_x, w_y, dr.normalize(w @ mi.Vector3f(1, 0, 0)),
                                 dr.normalize(w @ mi.Vector3f(0, 1, 0)), mi.Vector3f(n_world))

    def texel_parallel_size(self, res: int, face, p_world, texel_world):
        return texel_world

    def texel_parallel_xy(self, res: int, face, p_world, texel_world):
        """The rectangle's texel sides, ``2 half_extent / res`` (None if square)."""
        if self.half_extent[0] == self.half_extent[1]:
            return None
        hx, hy = self._half()
        zero = dr.zeros(mi.Float, dr.width(texel_world))
        return zero + divide_by_res(2.0 * hx, res), zero + divide_by_res(2.0 * hy, res)

    def direction_to_light(self, p_world: mi.Point3f) -> mi.Vector3f:
        return -dr.normalize(self._forward())

    def light_width(self, light_size=None, angular_diameter: float = 0.0):
        return 2.0 * math.tan(math.radians(angular_diameter) * 0.5), True

    def map_width(self, p_world: np.ndarray) -> float:
        return 2.0 * max(self.half_extent)

    # ------------------------------------------------- cascades and fitting
    def needs_camera_points(self, opts) -> bool:
        return opts.cascades > 1 or bool(opts.fit_frusta)

    def planned_faces(self, opts, visible) -> int:
        if opts.cascades > 1 and visible is not None and len(visible) > 0:
            return int(opts.cascades)
        return 1

    def refine_for_footprint(self, opts, scene, sensor, visible):
        if opts.cascades > 1:   # the footprint of the cascades without margin
            from .cascaded import cascaded_view
            return cascaded_view(self, scene, sensor, opts.cascades, opts.split_lambda,
                                 res=None, points=visible)
        return self

    def refine(self, opts, scene, sensor, visible, res):
        view = self
        if opts.cascades > 1 and sensor is not None:
            from .cascaded import cascaded_view
            view = cascaded_view(self, scene, sensor, opts.cascades, opts.split_lambda,
                                 res=res, points=visible)
        if opts.fit_frusta and view.n_faces == 1:
            return view.fit(visible, (8.0 + opts.normal_bias_texels) / res)
        return view, None

    def fit(self, p_world: np.ndarray, margin: float):
        """``(view fitted to the visible points, texel density gain)``: the light-space
        rectangle of the xy of the visible points inside the map (same direction and
        near plane), grown by ``margin`` (a fraction of the window) per side; see
        :meth:`PerspectiveView.fit <mi_shadowmap.light_views.perspective.PerspectiveView.fit>`
        for why casters are kept."""
        if p_world is None or len(p_world) == 0:
            return self, 1.0
        L = light_matrix(self)
        p_l = p_world @ L[:3, :3].T + L[:3, 3]
        hx, hy = self.half_extent
        keep = (np.abs(p_l[:, 0]) <= hx) & (np.abs(p_l[:, 1]) <= hy)
        if not keep.any():
            return self, 1.0
        lo, hi = p_l[keep, :2].min(axis=0), p_l[keep, :2].max(axis=0)
        centre = 0.5 * (lo + hi)
        size = max(hx, hy)
        half = 0.5 * (hi - lo) + 2.0 * margin * np.maximum(0.5 * (hi - lo), 1e-3 * size)
        half = np.maximum(half, 1e-6 * size)
        if max(half) >= max(hx, hy):
            return self, 1.0
        W = np.linalg.inv(L)
        origin = W[:3, :3] @ np.array([centre[0], centre[1], 0.0]) + W[:3, 3]
        fwd = W[:3, :3] @ np.array([0.0, 0.0, 1.0])
        new_lfw = look_along_np(origin, fwd)
        return (dataclasses.replace(self, position=mi.ScalarPoint3f(*origin),
                                    light_from_world=new_lfw,
                                    half_extent=(float(half[0]), float(half[1]))),
                (max(hx, hy) / float(max(half))) ** 2)


def directional_view(emitter, scene, label: str) -> OrthoView:
    """The :class:`OrthoView` of a directional emitter, fitted to ``scene``'s bounds."""
    T = emitter.world_transform()
    d = dr.normalize(scalar3(T @ mi.Vector3f(0, 0, 1)))
    bounds = scene_bounds(scene)      # scene.bbox() misses merged meshes
    if bounds is None:
        bbox = mi.ScalarBoundingBox3f(mi.ScalarPoint3f(-1), mi.ScalarPoint3f(1))
    else:
        bbox = mi.ScalarBoundingBox3f(mi.ScalarPoint3f(*bounds[0]), mi.ScalarPoint3f(*bounds[1]))
    rot = look_along(mi.ScalarPoint3f(0), d)
    lo = [math.inf] * 3
    hi = [-math.inf] * 3
    for k in range(8):
        c = rot @ bbox.corner(k)
        for a in range(3):
            lo[a] = min(lo[a], float(c[a]))
            hi[a] = max(hi[a], float(c[a]))
    size = max(hi[a] - lo[a] for a in range(3))
    size = size if size > 0 else 1.0
    pad = 1e-3 * size   # keep bbox-touching receivers strictly inside
    half = tuple(max(0.5 * (hi[a] - lo[a]) + pad, 1e-6 * size) for a in range(2))
    near = lo[2] - pad
    centre_light = mi.ScalarPoint3f(0.5 * (lo[0] + hi[0]), 0.5 * (lo[1] + hi[1]), near)
    origin = rot.inverse() @ centre_light
    return OrthoView("directional", origin, look_along(origin, d), label=label,
                     half_extent=half)
