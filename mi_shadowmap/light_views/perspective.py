"""Spot lights: one perspective face covering the cutoff cone (:class:`PerspectiveView`).

The face is a square frustum circumscribing the cone (half-angle
``cutoff_angle``) in the emitter's own frame: the rotation of its
``to_world`` (columns normalised, Gram-Schmidt), so +z is the spot axis and
the map's ``u``/``v`` are the emitter's local x/y. A ``to_world`` that scales
or shears the cone (Mitsuba applies the cutoff in local space) gets the frustum
that holds the cone's image in world space (:func:`_world_cone_tan`).
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

from .base import (LightView, axial_texel_size, emitter_frame, light_matrix, look_along_np,
                   opaque_light_from_world, opaque_point, opaque_scalar,
                   opaque_world_from_light, divide_by_res, position_np, scalar3,
                   texel_width_along, transform_f64, unit_grid, world_matrix)


@dataclass(frozen=True)
class PerspectiveView(LightView):
    """One perspective face; ``tan_half`` is tan(half its field of view), along the
    light's x; ``tan_half_y`` along its y where the face is a rectangle (None: square).
    Rectangular faces come from :func:`box_view` (x the longer side), so ``tan_half`` is
    the larger of the two wherever one number stands for the face (map width, virtual
    resolution)."""
    tan_half: float = 1.0
    tan_half_y: float | None = None

    projection = "perspective"
    rays_from_point = True

    @property
    def n_faces(self) -> int:
        return 1

    def _world_from_light(self):
        return opaque_world_from_light(self)

    @property
    def _tan_y(self) -> float:
        return self.tan_half if self.tan_half_y is None else self.tan_half_y

    def _tans(self, double: bool = False):
        """``(tan_half, tan_half_y)`` as opaque JIT scalars, as :class:`OrthoView`'s
        half extents: a spot's new cutoff angle or a far light's moved face
        (:func:`box_view` refits ``tan_half`` to the scene's box) compiles no new kernel."""
        return opaque_scalar(self.tan_half, double), opaque_scalar(self._tan_y, double)

    def texel_rays(self, res: int):
        _, s, t = unit_grid(1, res)
        tx, ty = self._tans()
        d_light = mi.Vector3f(s * tx, t * ty, 1.0)
        return opaque_point(self.position), dr.normalize(self._world_from_light() @ d_light)

    def ray_through(self, face, uv_light: mi.Point2f):
        s = uv_light.x * 2.0 - 1.0
        t = uv_light.y * 2.0 - 1.0
        tx, ty = self._tans()
        d_light = mi.Vector3f(s * tx, t * ty, 1.0)
        return opaque_point(self.position), dr.normalize(self._world_from_light() @ d_light)

    def project(self, p_world: mi.Point3f):
        p_world = mi.Point3f(p_world)   # Point + Vector arithmetic may yield a Vector3f
        p_light = opaque_light_from_world(self) @ p_world
        z = p_light.z
        # relative clamp (as cube.face_uv): reverse mode's partials stay finite for
        # points at or behind the light's plane
        inv_z = dr.rcp(dr.maximum(z, dr.maximum(1e-7 * (dr.abs(p_light.x) + dr.abs(p_light.y)),
                                                1e-30)))
        tx, ty = self._tans()
        uv = mi.Point2f(0.5 * (p_light.x * inv_z / tx + 1.0),
                        0.5 * (p_light.y * inv_z / ty + 1.0))
        depth = dr.norm(p_world - opaque_point(self.position))
        inside = (z > 0) & (uv.x >= 0) & (uv.x <= 1) & (uv.y >= 0) & (uv.y <= 1)
        return mi.UInt32(0), uv, depth, inside

    # ------------------------------------------------------------- float64
    supports_virtual = True

    def _light_f64(self, p_world) -> mi.Point3d:
        """``light_from_world @ p_world`` in float64 as the rotation of ``p_world - position``:
        the matrix's own translation is float32, ``-R position`` rounded to 2^-24 of the
        light's distance (64 units at 1e9), which a view fitted to a far scene
        (:func:`box_view`, a face a few units wide there) cannot afford."""
        rel = mi.Point3d(p_world) - opaque_point(self.position, True)
        return transform_f64(light_matrix(self), rel, point=False)

    def uv_on_face_f64(self, face, p_world):
        p_light = self._light_f64(p_world)
        inv_z = dr.rcp(dr.maximum(p_light.z, 1e-300))
        tx, ty = self._tans(True)
        return mi.Point2d(0.5 * (p_light.x * inv_z / tx + 1.0),
                          0.5 * (p_light.y * inv_z / ty + 1.0))

    def uv_differential(self, face, p_world, dp_world):
        L = opaque_light_from_world(self)
        p = L @ mi.Point3f(p_world)
        dp = L @ mi.Vector3f(dp_world)
        inv_z = dr.rcp(dr.maximum(p.z, 1e-30))
        kx, ky = opaque_scalar(0.5 / self.tan_half), opaque_scalar(0.5 / self._tan_y)
        return mi.Point2f(kx * (dp.x - p.x * dp.z * inv_z) * inv_z,
                          ky * (dp.y - p.y * dp.z * inv_z) * inv_z)

    def project_f64(self, p_world):
        p_world = mi.Point3d(p_world)
        p_light = self._light_f64(p_world)
        uv = self.uv_on_face_f64(0, p_world)
        depth = dr.norm(p_world - opaque_point(self.position, True))
        inside = (p_light.z > 0) & (uv.x >= 0) & (uv.x <= 1) & (uv.y >= 0) & (uv.y <= 1)
        return mi.UInt32(0), uv, depth, inside

    def ray_through_f64(self, face, uv_light):
        s = uv_light.x * 2.0 - 1.0
        t = uv_light.y * 2.0 - 1.0
        tx, ty = self._tans(True)
        d_light = mi.Vector3d(s * tx, t * ty, 1.0)
        d = transform_f64(world_matrix(self), d_light, point=False)
        return opaque_point(self.position, True), dr.normalize(d)

    def ray_frame_f64(self, face, uv_light):
        """(:attr:`~.base.LightView.ray_frame_f64`) Central rays: the unnormalised
        direction ``R (s tan_half, t tan_half_y, 1)``, ``s = 2 u - 1``, is affine in ``uv``."""
        W = world_matrix(self)
        s = uv_light.x * 2.0 - 1.0
        t = uv_light.y * 2.0 - 1.0
        tx, ty = self._tans(True)
        base = transform_f64(W, mi.Vector3d(s * tx, t * ty, 1.0), point=False)
        R = W[:3, :3]
        kx, ky = 2.0 * self.tan_half, 2.0 * self._tan_y
        # opaque (opaque_point): a turned light compiles no new kernel
        return (True, mi.Vector3f(base), mi.Vector3f(opaque_point(kx * R[:, 0])),
                mi.Vector3f(opaque_point(ky * R[:, 1])))

    def texel_world_size(self, res: int, depth, p_world=None, n_world=None):
        """At ``p_world``: its axial depth (along the spot's axis) times ``2 tan_half /
        res``, a texel's width across the ray (see :meth:`CubeView.texel_world_size`;
        the distance ``depth`` overstated it by ``1 / cos`` of the angle off the axis,
        2x at the edge of a 60-degree cone); ``depth`` only without ``p_world``. A
        rectangular face (``tan_half_y``): with ``n_world``, the width along the
        receiver's depth gradient (:func:`~.base.texel_width_along`, as an orthographic
        rectangle's), else the longer side."""
        if p_world is not None:
            depth = dr.abs((opaque_light_from_world(self) @ mi.Point3f(p_world)).z)
        if self.tan_half_y is None or n_world is None:
            return depth * divide_by_res(opaque_scalar(2.0 * self.tan_half), res)
        # the light's axes in the world: the rows of light_from_world's rotation (the
        # opaque matrix project() reads; tan_half_y a Python float, as tan_half: a numpy
        # float times a JIT array asks numpy to convert it, which a symbolic lookup refuses)
        m = opaque_light_from_world(self).matrix
        return texel_width_along(depth * divide_by_res(opaque_scalar(2.0 * self.tan_half), res),
                                 depth * divide_by_res(opaque_scalar(2.0 * self._tan_y), res),
                                 dr.normalize(mi.Vector3f(m[0][0], m[0][1], m[0][2])),
                                 dr.normalize(mi.Vector3f(m[1][0], m[1][1], m[1][2])),
                                 mi.Vector3f(n_world))

    def texel_parallel_size(self, res: int, face, p_world, texel_world):
        if self.tan_half_y is not None:   # a rectangle: along the depth gradient, as
            return texel_world            # an orthographic rectangle's (its axial depth)
        return axial_texel_size(self, res, face, p_world)

    def texel_parallel_xy(self, res: int, face, p_world, texel_world):
        """A rectangle's texels (``tan_half_y``): its axial depth times ``2 tan_half /
        res`` along x, ``2 tan_half_y / res`` along y; None for a square face."""
        if self.tan_half_y is None:
            return None
        w_x = axial_texel_size(self, res, face, p_world)
        return w_x, w_x * opaque_scalar(self.tan_half_y / self.tan_half)

    def map_width(self, p_world: np.ndarray) -> float:
        return 2.0 * self.tan_half * float(np.linalg.norm(p_world - position_np(self)))

    # ------------------------------------------------------------- fitting
    def needs_camera_points(self, opts) -> bool:
        return bool(opts.fit_frusta)

    def refine(self, opts, scene, sensor, visible, res):
        if not opts.fit_frusta:
            return self, None
        return self.fit(visible, (8.0 + opts.normal_bias_texels) / res)

    def fit(self, p_world: np.ndarray, margin: float):
        """``(view fitted to the visible points, texel density gain)``.

        Only the points inside the cone's frustum are kept (the others get no
        light from the spot). A square frustum re-aimed at the mean direction
        of those points, with the smallest ``tan_half`` covering them, grown by
        ``margin`` (a fraction of the window) per side for normal offsets and
        filter taps. A caster can only shadow a visible receiver along the
        light ray to it, which crosses the same (u, v): casters are kept
        (Reeves' and Filament's fitting of the frustum to what matters,
        restricted to what the camera sees). The gain is the ratio of texel
        areas (old / new) at the same resolution; the view itself (gain 1) is
        returned if nothing is gained or the fit is not possible.
        """
        if p_world is None or len(p_world) == 0:
            return self, 1.0
        L = light_matrix(self)
        p_l = p_world @ L[:3, :3].T + L[:3, 3]
        pos = position_np(self)
        z = p_l[:, 2]
        keep = (z > 0) & (np.abs(p_l[:, 0]) <= self.tan_half * z) \
            & (np.abs(p_l[:, 1]) <= self._tan_y * z)
        if not keep.any():
            return self, 1.0
        dirs = p_world[keep] - pos
        dirs /= np.maximum(np.linalg.norm(dirs, axis=1, keepdims=True), 1e-30)
        axis = dirs.mean(axis=0)
        if np.linalg.norm(axis) < 1e-6:
            return self, 1.0
        aimed = _aimed_frustum(pos, axis, p_world[keep], margin)
        if aimed is None:
            return self, 1.0
        new_lfw, tan = aimed
        tan = max(tan, 1e-6 * self.tan_half)
        if tan >= self.tan_half:
            return self, 1.0
        return (dataclasses.replace(self, light_from_world=new_lfw, tan_half=tan,
                                    tan_half_y=None),
                self.tan_half * self._tan_y / tan ** 2)


def _aimed_extents(pos, axis, p_world: np.ndarray, margin: float):
    """``(light_from_world, tan_x, tan_y)``: the frame from ``pos`` along ``axis`` (numpy,
    :func:`look_along_np`) and the largest ``|x / z|``, ``|y / z|`` of ``p_world`` (``(N,
    3)``) in it, widened by ``margin`` of the width per side; None if a point lies at or
    behind the light's plane. The points are rotated relative to ``pos`` in float64 (the
    float32 matrix's own translation would round to 2^-24 of the light's distance)."""
    lfw = look_along_np(pos, axis / np.linalg.norm(axis))
    R = np.array(lfw.matrix, dtype=np.float64)[:3, :3]
    q = (np.asarray(p_world, np.float64) - pos) @ R.T
    if np.any(q[:, 2] <= 1e-9 * np.abs(q).max()):
        return None
    grow = 1.0 + 2.0 * margin
    x, y = (float(np.max(np.abs(q[:, k]) / q[:, 2])) * grow for k in (0, 1))
    return lfw, x, y


def _aimed_frustum(pos, axis, p_world: np.ndarray, margin: float):
    """``(light_from_world, tan_half)`` of the square frustum from ``pos`` along ``axis``
    that holds ``p_world``, as :func:`_aimed_extents`; None as there."""
    aimed = _aimed_extents(pos, axis, p_world, margin)
    return None if aimed is None else (aimed[0], max(aimed[1], aimed[2]))


def box_view(view: LightView, lo, hi, margin: float = 0.05):
    """A :class:`PerspectiveView` from ``view``'s light aimed at the box ``[lo, hi]``
    (numpy) whose frustum covers its 8 corners, a rectangle where its sides differ by
    more than ``ANISO`` (:func:`_aimed_rectangle`), else a square, widened by ``margin``
    of its width per side (normal offsets and filter taps at the box's edge); None if the
    light is inside the box's cone (a corner at or behind the light's plane). Every
    field but the projection is ``view``'s (kind, position, light size and normal,
    ignored shape, label, a planar area light's half-axes).

    For a light far from the scene: a cube face (90 degrees) or a wide spot cone then
    spends its texels on directions where nothing is, and a virtual map's finest level
    (``virtual.MAX_VIRTUAL_RES`` texels a side) is wider than the scene's details (a
    point light 1e9 from a 12-unit scene: 1.9-unit texels). Aimed at the box, the
    face's texels all fall on the scene, whatever its distance."""
    pos = position_np(view)
    centre = 0.5 * (np.asarray(lo, np.float64) + np.asarray(hi, np.float64))
    if not np.linalg.norm(centre - pos) > 0:
        return None
    corners = np.array([[(lo, hi)[k >> a & 1][a] for a in range(3)] for k in range(8)],
                       np.float64)
    aimed = _aimed_rectangle(pos, centre - pos, corners, margin)
    if aimed is None:
        return None
    lfw, tan_x, tan_y = aimed
    from ..virtual.layout import ANISO       # (the virtual package imports this module)
    # a rectangle only where its sides differ by more than the level choice's anisotropy
    # (see _aimed_rectangle): within it the square's level already resolves the short
    # side, with more texels across
    rect = tan_y * ANISO < tan_x
    # (the light's half-axes too: a far planar area light's virtual map read the square
    # of its area where its full map read its own shape)
    return PerspectiveView(view.kind, view.position, lfw, light_size=view.light_size,
                           ignore_shape=view.ignore_shape, light_normal=view.light_normal,
                           label=view.label, tan_half=max(tan_x, 1e-300),
                           tan_half_y=max(tan_y, 1e-300) if rect else None,
                           light_axes=view.light_axes)


def _aimed_rectangle(pos, axis, p_world: np.ndarray, margin: float):
    """``(light_from_world, tan_x, tan_y)``, ``tan_y <= tan_x``: the frustum of
    :func:`_aimed_frustum` (its frame, up to a quarter turn that puts the longer side
    along x), with its own extent along each axis.

    Why a rectangle: a light far from a flat scene (a point light 1e5 away, 5 degrees
    above a ground) sees the scene foreshortened along one axis. A square face spends
    its texels evenly over both, so its texels on the ground were ``1 / sin`` as long
    along the light's direction as across it, and the level choice (which keeps a
    footprint anisotropy of at most :data:`~mi_shadowmap.virtual.layout.ANISO`) could
    not make them shorter: contact shadows were lost to the slope bias. The rectangle
    makes the face what a sun's orthographic map is, fitted to the scene's rectangle.
    Measured (``hard`` against the same samples of ``raytraced``, 128^2, 16 spp): a
    y-up yard of posts and crates under a point light 1e5 away at 5 / 10 / 30 degrees,
    1.50 / 0.75 / 0.32 % misclassified with the square, 1.01 / 0.78 / 0.40 % with the
    rectangle, 1.07 / 0.84 / 0.41 % under a sun from there (at 30 degrees the square's
    level, capped at ``ANISO``, had twice the texels across the light's direction that
    the rectangle's footprint asks for); ``random_far_point`` seeds 0-7 with the light
    moved to 5 / 10 / 20 / 40 degrees, mean 0.20 / 0.22 / 0.17 / 0.14 % -> 0.15 / 0.18 /
    0.16 / 0.16 %, texels per pixel (median) 2.1 / 2.7 / 3.5 / 3.6 -> 3.2 / 3.8 / 3.4 /
    3.4. So :func:`box_view` keeps the square where the sides differ by less than
    ``ANISO`` (the yard at 30 degrees, 0.52; ``random_far_point`` at 20-40 degrees and
    ``far_point.xml``, 0.83, whose still frame the rectangle made about 0.1 of an
    unshadowed frame slower): then 1.01 / 0.78 / 0.32 % on the yard and a mean of 0.15 /
    0.18 / 0.17 / 0.14 % on ``random_far_point``. The frame is not turned to the smallest rectangle (tried: about as good on
    average, but a turned grid lays staircases along the shadows of vertical edges,
    and a turned row rounded to float32 moves a point 1e9 away by tens of units).
    """
    aimed = _aimed_extents(pos, axis, p_world, margin)
    if aimed is None:
        return None
    lfw, x, y = aimed
    if y > x:    # a quarter turn (exact: rows swapped, one negated): x the longer side
        m = np.array(lfw.matrix, dtype=np.float64)
        m[[0, 1]] = m[[1, 0]]
        m[1] = -m[1]
        return mi.ScalarTransform4f(m.tolist()), y, x
    return lfw, x, y


#: Spot lights whose ``cutoff_angle`` (degrees) is at least this get a cube of faces
#: around the light (:class:`~.cube.CubeView`, kind ``'spot'``) instead of one
#: perspective face: a square frustum cannot cover a cone of 90 degrees or more, and
#: short of that its texels stretch by ``1 / cos^2`` towards the rim.
WIDE_SPOT_CUTOFF = 80.0


def spot_view(emitter, label: str):
    """The light view of a spot emitter: a :class:`PerspectiveView` covering the cutoff
    cone, or, for ``cutoff_angle >= WIDE_SPOT_CUTOFF`` (Mitsuba allows any angle; 90 and
    more light a hemisphere or beyond), a :class:`~.cube.CubeView` at the spot's
    position keeping its frame (the cone only shades: outside it no light sample is
    taken, so no face there is read)."""
    from . import UnsupportedEmitterError
    from .cube import framed_cube_view
    params = mi.traverse(emitter)
    cutoff = float(dr.ravel(params["cutoff_angle"])[0])
    if not cutoff > 0.0:
        raise UnsupportedEmitterError(
            f"shadowmap: spot emitter '{label}' has cutoff_angle={cutoff}; it must be > 0 "
            "degrees (a spot with no cone lights nothing)")
    if "beam_width" in params:
        # Mitsuba loads any beam_width: NaN made `direct` render NaN inside the cone
        # (and every method here black, visibility AOV 0), inf black.
        beam = float(dr.ravel(params["beam_width"])[0])
        if not math.isfinite(beam):
            raise UnsupportedEmitterError(
                f"shadowmap: spot emitter '{label}' has beam_width={beam}; it must be a "
                "finite angle in degrees (at most cutoff_angle; larger is the cutoff)")
    if cutoff >= WIDE_SPOT_CUTOFF:
        return framed_cube_view(emitter, "spot", label)
    T = emitter.world_transform()
    pos = mi.ScalarPoint3f(scalar3(T.translation()))
    frame = emitter_frame(T, pos)
    tan_half = _world_cone_tan(T, frame, math.tan(math.radians(cutoff)))
    if tan_half is None:   # a sheared or scaled cone reaching 80 degrees off the axis
        return framed_cube_view(emitter, "spot", label)
    return PerspectiveView("spot", pos, frame, label=label, tan_half=tan_half)


def _world_cone_tan(T, frame, tan_cutoff: float, n: int = 1024):
    """``tan_half`` of the square frustum in ``frame`` (the rigid part of the spot's
    ``to_world`` ``T``) that holds the spot's cone in world space, or None if that
    needs ``WIDE_SPOT_CUTOFF`` or more (a cube view then).

    Mitsuba's spot takes its cone in local space (``to_world``'s inverse applied to the
    direction), so a scale or a shear in ``to_world`` turns the world cone into the
    image of the local one under ``to_world``'s linear part: ``scale([3, 1, 1])`` with a
    20-degree cutoff lights 47.5 degrees off the axis along x. The frame drops scale and
    shear; this widens (or narrows) the frustum to the image of the cone's rim, sampled
    at ``n`` angles (plus 0.1 %). A rigid or uniformly scaled ``to_world`` keeps
    ``tan_cutoff`` exactly."""
    M = np.array([[float(c) for c in scalar3(T @ mi.Vector3f(*(float(x) for x in e)))]
                  for e in np.eye(3)]).T
    R = np.array(frame.matrix, dtype=np.float64)[:3, :3]
    A = R @ M
    A /= np.linalg.norm(A[:, 2])
    if np.allclose(A.T @ A, np.eye(3), rtol=0.0, atol=1e-6):
        return tan_cutoff               # a rotation (times a uniform scale)
    phi = np.linspace(0.0, 2.0 * np.pi, n, endpoint=False)
    rim = np.stack([tan_cutoff * np.cos(phi), tan_cutoff * np.sin(phi), np.ones(n)])
    q = A @ rim
    limit = math.tan(math.radians(WIDE_SPOT_CUTOFF))
    if not np.all(q[2] > 0):
        return None
    tan = float(np.max(np.abs(q[:2]) / q[2])) * 1.001
    return tan if tan < limit else None
