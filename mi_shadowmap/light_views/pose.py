"""Gradients of a light's pose (issue 13): :class:`LightPose` and :func:`light_pose`.

A :class:`~.base.LightView` holds its transforms as scalar constants (kernel
literals, cache keys), so a light view by itself passes no gradient to the
light's position or direction. When an emitter's pose parameter has
gradients enabled, :func:`light_pose` returns the *pose delta*

    ``M = world_from_light_attached @ inverse(world_from_light_detached)``,

whose value is the identity and whose derivatives are those of the pose.
Moving the light by ``M`` is the same as moving the world by ``M^-1``, so

* a map texel's ray ``(o, d)`` of the detached view becomes ``(M o, M d)``
  (:meth:`LightPose.ray`), and its depth then depends on the pose;
* a receiver ``p_world`` is looked up at ``M^-1 p_world``
  (:meth:`LightPose.to_view`) in the detached view, so its ``uv_light`` and
  depth depend on the pose;
* the silhouette edges of :mod:`mi_shadowmap.antialias` are projected the
  same way, so their coverage depends on the pose.

Every value keeps its detached bits (``dr.replace_grad``): only derivatives
are added, and renders are bit-identical to the detached ones.

Which parameter is the pose, per emitter:

============  ====================================================================
point         ``position``
spot          ``to_world``
directional   ``to_world`` (its rotation, about the map's near-plane centre: the
              translation of a directional light means nothing)
area          the shape's ``to_world`` (rectangle, disk, sphere, ...), or the mean of
              its ``vertex_positions`` (a mesh: a translation)
============  ====================================================================
"""
from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi


@dataclass
class LightPose:
    """The pose delta ``M`` (value: the identity) of one emitter and its inverse."""
    delta: mi.Transform4f
    inverse_delta: mi.Transform4f

    def to_view(self, p_world) -> mi.Point3f:
        """``p_world`` with the derivatives of ``M^-1 p_world`` (where the detached
        view must look it up)."""
        p_world = mi.Point3f(p_world)
        return dr.replace_grad(p_world, self.inverse_delta @ p_world)

    def vector_to_view(self, v_world) -> mi.Vector3f:
        v_world = mi.Vector3f(v_world)
        return dr.replace_grad(v_world, self.inverse_delta @ v_world)

    def ray(self, o_world, d_world):
        """A detached view's ray moved with the light: ``(M o, M d)``, values unchanged."""
        o_world, d_world = mi.Point3f(o_world), mi.Vector3f(d_world)
        return (dr.replace_grad(o_world, self.delta @ o_world),
                dr.replace_grad(d_world, self.delta @ d_world))


def _attached(params, key):
    if key not in params.keys():
        return None
    value = params[key]
    return value if dr.grad_enabled(value) else None


def _from_transform(t_att, pivot=None, rotation_only=False) -> LightPose:
    t_att = mi.Transform4f(t_att)
    m_att = t_att.matrix
    m_det = dr.detach(m_att)
    if rotation_only:   # keep the 3x3 part; rotate about ``pivot``
        m_att = mi.Matrix4f(m_att)
        m_det = mi.Matrix4f(m_det)
        for r in range(3):
            m_att[r][3] = 0.0
            m_det[r][3] = 0.0
    delta = m_att @ dr.inverse(m_det)
    if pivot is not None:
        c = mi.Matrix4f(mi.ScalarTransform4f().translate(pivot).matrix)
        ci = mi.Matrix4f(mi.ScalarTransform4f().translate([-x for x in pivot]).matrix)
        delta = c @ delta @ ci
    return LightPose(mi.Transform4f(delta), mi.Transform4f(dr.inverse(delta)))


def _translation(offset) -> LightPose:
    offset = mi.Vector3f(offset)
    delta = mi.Transform4f().translate(offset)
    return LightPose(delta, mi.Transform4f().translate(-offset))


def light_pose(emitter, view) -> LightPose | None:
    """The pose delta of ``emitter`` (whose detached view is ``view``), or None when no
    pose parameter of it has gradients enabled (or Dr.Jit tracks none here)."""
    if not dr.is_diff_v(mi.Float):
        return None
    kind = view.kind
    params = mi.traverse(emitter)
    if kind == "point":
        p = _attached(params, "position")
        if p is None:
            return None
        p = mi.Point3f(p)
        return _translation(p - dr.detach(p))
    if kind == "spot":
        t = _attached(params, "to_world")
        return None if t is None else _from_transform(t)
    if kind == "directional":
        t = _attached(params, "to_world")
        if t is None:
            return None
        return _from_transform(t, pivot=[float(x) for x in view.position], rotation_only=True)
    if kind == "area":
        shape = emitter.get_shape()
        if shape is None:
            return None
        sp = mi.traverse(shape)
        t = _attached(sp, "to_world")
        if t is not None:
            return _from_transform(t)
        v = _attached(sp, "vertex_positions")
        if v is not None:
            n = dr.width(v) // 3
            idx = dr.arange(mi.UInt32, n) * 3
            mean = mi.Vector3f(*[dr.mean(dr.gather(mi.Float, v, idx + i)) for i in range(3)])
            return _translation(mean - dr.detach(mean))
    return None
