"""Directional lights, cascaded: parallel-split orthographic maps (:class:`CascadedView`).

``n_faces`` = cascades orthographic maps sharing the light direction and near
plane, face ``i`` fitted to the camera-visible points of view-depth slice
``i`` (thesis 002, sec. 2.1.6 / 5.1); a point uses the face of its camera view
depth (:meth:`CascadedView.cascade_of`).

The cascades' camera-dependent values (rectangles, split depths, the camera's
origin and axis) enter kernels as data, never as literals. With ``virtual=true``
each cascade is a virtual face (:mod:`mi_shadowmap.virtual`, the float64 methods
below): pages of it are built where lookups read them, at their pixel
footprint's level, and, as the cascades follow the camera, rebuilt when it
moves, with no new kernel. (Full-map cascades still compile kernels after a move
when their automatic resolution follows the camera: full maps hold it as a
literal.)
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

from .base import light_matrix, divide_by_res, transform_f64, unit_grid, world_matrix
from .ortho import OrthoView


def _opaque(cls, scalar, values):
    """``cls(*values)`` as opaque Dr.Jit variables (data, not kernel literals)."""
    return cls(*(dr.opaque(scalar, float(v)) for v in values))


@dataclass(frozen=True)
class CascadedView(OrthoView):
    """Cascades of an :class:`OrthoView`: per face, the light-space rectangle
    ``(cx, cy, hx, hy)`` in ``rects``; ``split_depths`` are the camera view depths
    ``C_0 < ... < C_m`` separating them, measured from ``camera_origin`` along
    ``camera_forward``."""
    rects: tuple = ()
    split_depths: tuple = ()
    camera_origin: tuple = (0.0, 0.0, 0.0)
    camera_forward: tuple = (0.0, 0.0, 1.0)
    #: the last face is the whole scene-fitted rectangle, read by points outside their
    #: cascade's rectangle (virtual maps: :func:`with_catch_all`)
    catch_all: bool = False

    projection = "cascaded"

    @property
    def n_faces(self) -> int:
        return len(self.rects)

    def cascade_of(self, p_world) -> mi.UInt32:
        """Cascade (face) of ``p_world``: how many split depths its camera view depth
        exceeds."""
        return self._slice_of(mi.Point3f(p_world), mi.Float)

    def _cascade_of_f64(self, p64) -> mi.UInt32:
        """:meth:`cascade_of` in float64 (what virtual maps mark and bind by)."""
        return self._slice_of(mi.Point3d(p64), mi.Float64)

    def _slice_of(self, p, scalar) -> mi.UInt32:
        """:meth:`cascade_of` of ``p`` in the precision of ``scalar``."""
        vector = mi.Vector3f if scalar is mi.Float else mi.Vector3d
        cam_o = _opaque(type(p), scalar, self.camera_origin)
        cam_f = _opaque(vector, scalar, self.camera_forward)
        z_view = dr.dot(p - cam_o, cam_f)
        face = mi.UInt32(0)
        for split in self.split_depths[1:-1]:
            face += dr.select(z_view > dr.opaque(scalar, split), 1, 0)
        return face

    def _rect(self, face, dtype=mi.Float):
        """Per-face ``(cx, cy, hx, hy)`` of the light-space rectangle, gathered."""
        table = dtype([x for r in self.rects for x in r])   # one upload, never a literal
        base = mi.UInt32(face) * 4
        return tuple(dr.gather(dtype, table, base + k) for k in range(4))

    def texel_rays(self, res: int):
        face, s, t = unit_grid(self.n_faces, res)
        cx, cy, hx, hy = self._rect(face)
        o_light = mi.Point3f(cx + s * hx, cy + t * hy, 0.0)
        w = self._world_from_light()
        return w @ o_light, w @ mi.Vector3f(0, 0, 1)

    def ray_through(self, face, uv_light: mi.Point2f):
        s = uv_light.x * 2.0 - 1.0
        t = uv_light.y * 2.0 - 1.0
        cx, cy, hx, hy = self._rect(mi.UInt32(face))
        o_light = mi.Point3f(cx + s * hx, cy + t * hy, 0.0)
        w = self._world_from_light()
        return mi.Point3f(w @ o_light), dr.normalize(w @ mi.Vector3f(0, 0, 1))

    def _uv_in(self, face, p_light):
        cx, cy, hx, hy = self._rect(face)
        return mi.Point2f(0.5 * ((p_light.x - cx) / hx + 1.0),
                          0.5 * ((p_light.y - cy) / hy + 1.0))

    def _face_uv(self, face, p_light, uv_in):
        """``(face, uv, inside)`` of a point whose cascade is ``face``: with
        ``catch_all``, a point outside that cascade's rectangle moves to the last face."""
        uv = uv_in(face, p_light)
        inside = (uv.x >= 0) & (uv.x <= 1) & (uv.y >= 0) & (uv.y <= 1)
        if self.catch_all:
            last = mi.UInt32(self.n_faces - 1)
            uv_all = uv_in(last, p_light)
            face = dr.select(inside, face, last)
            uv = dr.select(inside, uv, uv_all)
            inside = inside | ((uv_all.x >= 0) & (uv_all.x <= 1) & (uv_all.y >= 0)
                               & (uv_all.y <= 1))
        return face, uv, inside

    def project(self, p_world: mi.Point3f):
        p_world = mi.Point3f(p_world)
        p_light = mi.Transform4f(self.light_from_world) @ p_world
        face, uv, inside = self._face_uv(self.cascade_of(p_world), p_light, self._uv_in)
        return face, uv, p_light.z, inside

    def uv_on_face(self, face, p_world: mi.Point3f) -> mi.Point2f:
        p_light = mi.Transform4f(self.light_from_world) @ mi.Point3f(p_world)
        return self._uv_in(mi.UInt32(face), p_light)

    # ------------------------------------------------------------- float64
    supports_virtual = True     # each cascade a virtual face
    follows_camera = True       # its virtual pages are dropped when the camera moves

    def _uv_in_f64(self, face, p_light):
        cx, cy, hx, hy = self._rect(face, mi.Float64)
        return mi.Point2d(0.5 * ((p_light.x - cx) / hx + 1.0),
                          0.5 * ((p_light.y - cy) / hy + 1.0))

    def project_f64(self, p_world):
        p64 = mi.Point3d(p_world)
        p_light = transform_f64(light_matrix(self), p64)
        face, uv, inside = self._face_uv(self._cascade_of_f64(p64), p_light,
                                         self._uv_in_f64)
        return face, uv, p_light.z, inside

    def uv_on_face_f64(self, face, p_world):
        p_light = transform_f64(light_matrix(self), mi.Point3d(p_world))
        return self._uv_in_f64(mi.UInt32(face), p_light)

    def uv_differential(self, face, p_world, dp_world):
        dp = mi.Transform4f(self.light_from_world) @ mi.Vector3f(dp_world)
        _, _, hx, hy = self._rect(mi.UInt32(face))
        return mi.Point2f(0.5 * dp.x / hx, 0.5 * dp.y / hy)

    def ray_through_f64(self, face, uv_light):
        s = uv_light.x * 2.0 - 1.0
        t = uv_light.y * 2.0 - 1.0
        cx, cy, hx, hy = self._rect(mi.UInt32(face), mi.Float64)
        W = world_matrix(self)
        o = transform_f64(W, mi.Point3d(cx + s * hx, cy + t * hy, 0.0))
        d = transform_f64(W, mi.Vector3d(0.0, 0.0, 1.0), point=False)
        return o, dr.normalize(d)

    def ray_frame_f64(self, face, uv_light):
        """Each cascade's parallel rays (:meth:`OrthoView.ray_frame_f64`, its own
        rectangle's half sizes)."""
        _, _, hx, hy = self._rect(mi.UInt32(face))
        return self._parallel_frame(hx, hy)

    def texel_world_size(self, res: int, depth, p_world=None, n_world=None):
        """Needs ``p_world`` (its cascade sets the texel size); without it, the
        coarsest cascade's texel (a conservative bias). ``n_world``: the width along
        the receiver's depth gradient (:meth:`OrthoView.texel_world_size`)."""
        if p_world is None:
            w = max(max(r[2], r[3]) for r in self.rects)
            return dr.full(mi.Float, divide_by_res(2.0 * w, res), dr.width(depth))
        face = self.project(p_world)[0] if self.catch_all else self.cascade_of(p_world)
        _, _, hx, hy = self._rect(face)
        if n_world is None:
            return divide_by_res(2.0 * dr.maximum(hx, hy), res)
        return self._texel_along(divide_by_res(2.0 * hx, res), divide_by_res(2.0 * hy, res),
                                 n_world)

    def texel_parallel_xy(self, res: int, face, p_world, texel_world):
        """Each cascade's own rectangle's texel sides (None if all are square)."""
        if all(r[2] == r[3] for r in self.rects):
            return None
        _, _, hx, hy = self._rect(mi.UInt32(face))
        return divide_by_res(2.0 * hx, res), divide_by_res(2.0 * hy, res)

    def map_width(self, p_world: np.ndarray) -> float:
        return 2.0 * max(max(r[2], r[3]) for r in self.rects)

    def planned_faces(self, opts, visible) -> int:
        return self.n_faces

    def refine(self, opts, scene, sensor, visible, res):
        return self, None


def with_catch_all(view):
    """``view`` (a :class:`CascadedView`) with one more face, the whole scene-fitted
    rectangle of its :class:`OrthoView`, read by points outside their cascade's rectangle
    (camera samples off the pixel centres beyond the farthest or nearest visible point,
    e.g. towards the horizon). Virtual maps build its pages only where such points read
    them; a full map would spend a whole face on it. Any other view: unchanged."""
    if not isinstance(view, CascadedView) or view.catch_all:
        return view
    hx, hy = view.half_extent
    return dataclasses.replace(view, rects=view.rects + ((0.0, 0.0, float(hx), float(hy)),),
                               catch_all=True)


def split_depths(z_near: float, z_far: float, cascades: int, split_lambda: float) -> list:
    """Split positions ``C_0 = z_near < C_1 < ... < C_m = z_far`` (thesis sec. 5.1).

    ``C_i = lambda * (z_n + (z_f - z_n) i / m) + (1 - lambda) * z_n (z_f / z_n)^(i / m)``:
    the uniform scheme weighted by ``split_lambda``, the logarithmic one by
    ``1 - split_lambda`` (Zhang et al.'s practical split scheme).
    """
    m = int(cascades)
    z_near = max(float(z_near), 1e-6 * max(abs(float(z_far)), 1e-30))
    z_far = max(float(z_far), z_near * (1.0 + 1e-6))
    out = []
    for i in range(m + 1):
        uni = z_near + (z_far - z_near) * i / m
        log = z_near * (z_far / z_near) ** (i / m)
        out.append(split_lambda * uni + (1.0 - split_lambda) * log)
    out[0], out[-1] = z_near, z_far
    return out


def cascaded_view(view: OrthoView, scene, sensor, cascades: int, split_lambda: float,
                  margin_texels: float = 4.0, res: int | None = 1024,
                  points: np.ndarray | None = None) -> OrthoView:
    """Parallel-split (cascaded) maps for a directional ``view`` (thesis 2.1.6, 5.1).

    The camera's view depth range -- the nearest and farthest camera-visible
    surface points along the camera's forward axis, one ray per pixel centre
    of ``sensor``'s film -- is split with :func:`split_depths`. Cascade ``i``
    is an orthographic map (same light direction and near plane as ``view``,
    so casters between the scene's bounds and a receiver are all in it: a
    caster that can shadow a receiver lies on the light ray through it, at
    the same light-space (x, y)) whose rectangle is the light-space (x, y)
    bounding box of the visible points of slice ``i`` (slices overlap by 2 %
    of their length), grown by ``margin_texels`` texels of ``res`` (the real
    per-face resolution; ``res=None``: no margin, e.g. to measure the
    cascades' footprint before the resolution is chosen). ``points``: the
    camera-visible points if already computed (:func:`camera_visible_points`).
    A lookup uses the cascade of its point's view depth. Returns ``view``
    unchanged for 1 cascade, no sensor, or a camera that sees nothing.
    """
    from . import camera_visible_points
    if cascades <= 1 or sensor is None:
        return view
    p = camera_visible_points(scene, sensor) if points is None else points
    if len(p) == 0:
        return view
    T = sensor.world_transform()
    cam_o = np.array([float(dr.ravel(T.translation()[k])[0]) for k in range(3)])
    fwd_v = T @ mi.Vector3f(0, 0, 1)
    cam_f = np.array([float(dr.ravel(fwd_v[k])[0]) for k in range(3)])
    cam_f /= np.linalg.norm(cam_f)
    z_view = (p - cam_o) @ cam_f
    splits = split_depths(max(float(z_view.min()), 1e-6), float(z_view.max()), cascades,
                          split_lambda)
    L = light_matrix(view)
    p_l = p @ L[:3, :3].T + L[:3, 3]
    rects = []
    for i in range(cascades):
        lo_z, hi_z = splits[i], splits[i + 1]
        pad_z = 0.02 * (hi_z - lo_z)
        sel = (z_view >= lo_z - pad_z) & (z_view <= hi_z + pad_z)
        if not sel.any():
            sel = np.argsort(np.abs(z_view - 0.5 * (lo_z + hi_z)))[:1]
        lo = p_l[sel, :2].min(axis=0)
        hi = p_l[sel, :2].max(axis=0)
        half = np.maximum(0.5 * (hi - lo), 1e-6 * max(view.half_extent))
        if res is not None:
            grow = 2.0 * margin_texels / res
            half = half * (1.0 + grow) + grow * half.max()
        c = 0.5 * (lo + hi)
        rects.append((float(c[0]), float(c[1]), float(half[0]), float(half[1])))
    return CascadedView(view.kind, view.position, view.light_from_world,
                        light_size=view.light_size, ignore_shape=view.ignore_shape,
                        light_normal=view.light_normal, label=view.label,
                        half_extent=view.half_extent, rects=tuple(rects),
                        split_depths=tuple(splits),
                        camera_origin=tuple(float(x) for x in cam_o),
                        camera_forward=tuple(float(x) for x in cam_f))
