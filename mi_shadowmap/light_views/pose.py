"""Gradients of a light's pose (issue 13): :class:`LightPose` and :func:`light_pose`.

A :class:`~.base.LightView` holds its transforms as scalar constants (kernel
literals, cache keys), so a light view by itself passes no gradient to the
light's position or direction -- and a light that moves at every step of an
optimisation would give every kernel new literals, so every step would
compile anew. When an emitter's pose parameter has gradients enabled,
:func:`light_pose` therefore keeps a *reference view* of that emitter (the
view of the pose it first saw) and returns the pose delta

    ``M = world_from_light(current, attached) @ inverse(world_from_light(reference))``

as Dr.Jit variables (opaque: new values, same kernels). Moving the light by
``M`` is the same as moving the world by ``M^-1``, so with the reference view

* a map texel's ray ``(o, d)`` becomes ``(M o, M d)`` (:meth:`LightPose.ray`),
  and its depth is measured from the current light;
* a receiver ``p_world`` is looked up at ``M^-1 p_world``
  (:meth:`LightPose.to_view`), so its ``uv_light`` and depth are those of the
  current light;
* the silhouette edges of :mod:`mi_shadowmap.antialias` are projected the
  same way, so their coverage follows the light too,

and every one of these carries the pose's derivatives. The reference is
replaced (one compile) when the light has moved more than
:data:`REFERENCE_MOVE` of the scene's size or turned more than
:data:`REFERENCE_TURN` degrees from it (a directional map, fitted to the
scene along the reference direction, must still cover it). Renders without
gradients never come here: their views and values are unchanged.

What of the pose moves the shadows, per emitter (the rest is Mitsuba's shading):

============  ====================================================================
point         ``position``
spot          the translation of ``to_world`` (its position). Turning a spot moves
              its cone, not its shadows: the map's orientation is arbitrary, and
              turning it would move receivers and occluders alike in the map,
              terms that cancel only up to the discretisation (measured: a 25 %
              error on a directional light turned about its near plane)
directional   the rotation of ``to_world``, about the centre of the scene's bounds
              (its translation means nothing; the pivot is free, and at the scene's
              centre the common motion of receivers and occluders is smallest)
area          the translation of the shape's ``to_world`` (rectangle, disk, sphere,
              ...), or of the mean of its ``vertex_positions`` (a mesh): the map is
              seen from the light's centre, its orientation does not enter
============  ====================================================================
"""
from __future__ import annotations

import contextlib
import math
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

#: A reference view serves while the light stays within this fraction of the scene's
#: size of it ...
REFERENCE_MOVE = 0.25
#: ... and turns by at most this many degrees from it.
REFERENCE_TURN = 5.0


@dataclass
class LightPose:
    """The pose delta ``M`` of one emitter (from its reference view) and its inverse."""
    delta: mi.Transform4f
    inverse_delta: mi.Transform4f

    @property
    def attached(self) -> bool:
        """Whether the delta carries the pose's derivatives (a gradient pass), not
        only its value (``mi.render``'s primal pass, see :func:`light_pose`)."""
        return dr.grad_enabled(self.delta.matrix)

    def to_view(self, p_world) -> mi.Point3f:
        """Where the reference view must look ``p_world`` up: ``M^-1 p_world``."""
        return self.inverse_delta @ mi.Point3f(p_world)

    def vector_to_view(self, v_world) -> mi.Vector3f:
        return self.inverse_delta @ mi.Vector3f(v_world)

    def ray(self, o_world, d_world):
        """A reference-view ray moved with the light: ``(M o, M d)``."""
        return self.delta @ mi.Point3f(o_world), self.delta @ mi.Vector3f(d_world)


@dataclass
class _Reference:
    emitter: object            # held, so that its id is not reused while this lives
    view: object
    kind: str
    value: np.ndarray          # position (3,) or world_from_light matrix (4, 4)
    scale: float               # the scene's size (for REFERENCE_MOVE)


#: id(emitter) -> its reference; the oldest are dropped beyond _MAX_REFERENCES.
_REFERENCES: dict = {}
_MAX_REFERENCES = 64


def clear_references() -> None:
    """Forget every light's reference (and the emitter it holds)."""
    _REFERENCES.clear()


def _attached(params, key):
    if key not in params.keys():
        return None
    value = params[key]
    return value if dr.grad_enabled(value) else None


def _pose_value(emitter, kind):
    """``(attached value, kind of value)`` of the emitter's pose, or None when no pose
    parameter has gradients enabled. Kinds: 'translation' (a ``mi.Point3f``) or
    'transform' (a ``mi.Matrix4f``), 'rotation' (a matrix; directional)."""
    params = mi.traverse(emitter)
    if kind == "point":
        p = _attached(params, "position")
        return None if p is None else (mi.Point3f(p), "translation")
    if kind in ("spot", "projector", "directional"):
        t = _attached(params, "to_world")
        if t is None:
            return None
        if kind != "directional":
            return mi.Point3f(mi.Transform4f(t).translation()), "translation"
        return mi.Transform4f(t).matrix, "rotation"
    if kind == "area":
        shape = emitter.get_shape()
        if shape is None:
            return None
        sp = mi.traverse(shape)
        t = _attached(sp, "to_world")
        if t is not None:
            return mi.Point3f(mi.Transform4f(t).translation()), "translation"
        v = _attached(sp, "vertex_positions")
        if v is not None:
            n = dr.width(v) // 3
            idx = dr.arange(mi.UInt32, n) * 3
            return mi.Point3f(*[dr.mean(dr.gather(mi.Float, v, idx + i)) for i in range(3)]), \
                "translation"
    return None


def _numpy(value) -> np.ndarray:
    if isinstance(value, mi.Point3f):
        return np.array([float(dr.detach(value)[k][0]) for k in range(3)])
    m = dr.detach(value)
    return np.array([[float(m[r][c][0]) for c in range(4)] for r in range(4)])


def _angle(rel: np.ndarray) -> float:
    """Degrees of the rotation ``rel`` (3x3)."""
    return math.degrees(math.acos(max(-1.0, min(1.0, (np.trace(rel) - 1.0) / 2.0))))


def light_rotation(view) -> np.ndarray:
    """The 3x3 rotation of ``view.light_from_world`` (numpy)."""
    return np.array(view.light_from_world.matrix, dtype=np.float64)[:3, :3]


def _far(ref: _Reference, value: np.ndarray) -> bool:
    if ref.value.shape != value.shape:
        return True
    if value.shape == (3,):
        return float(np.linalg.norm(value - ref.value)) > REFERENCE_MOVE * ref.scale
    return _angle(value[:3, :3] @ np.linalg.inv(ref.value[:3, :3])) > REFERENCE_TURN


def light_pose(emitter, view, bounds=None, detached: bool = False):
    """``(view, pose)``: the view to build and look up the emitter's map with, and its
    :class:`LightPose`; ``(view, None)`` when no pose parameter of the emitter has
    gradients enabled (or Dr.Jit tracks none here). ``view`` is the emitter's view
    for its current pose; ``bounds`` (``(lo, hi)`` numpy, or None) the scene's:
    its size scales :data:`REFERENCE_MOVE`, its centre is a directional light's
    pivot.

    ``detached``: the pose's value without its derivatives, for a pose parameter
    that has gradients enabled outside the current AD scope -- ``mi.render(scene,
    params)`` renders its primal image under ``dr.suspend_grad()``. That pass then
    uses the same reference view and opaque delta as the gradient pass, instead of
    the current view, whose position would be a kernel literal: every step of an
    optimisation would compile its map build and its render kernel again (measured:
    2 kernels a step, one of 1210 operations, on the point-light problem)."""
    lo, hi = bounds if bounds is not None else (np.zeros(3), np.ones(3))
    scene_size = float(np.linalg.norm(np.asarray(hi) - np.asarray(lo)))
    centre = [float(x) for x in 0.5 * (np.asarray(lo) + np.asarray(hi))]
    if not dr.is_diff_v(mi.Float):
        return view, None
    with dr.resume_grad() if detached else contextlib.nullcontext():
        found = _pose_value(emitter, view.kind)
    if found is None:
        return view, None
    value, how = found
    if detached:
        value = dr.detach(value)
    current = _numpy(value)
    ref = _REFERENCES.get(id(emitter))
    turned = False
    if view.kind == "spot" and ref is not None and ref.kind == "spot":
        # the cone turned or changed (a new cutoff_angle, or a cube of faces from
        # WIDE_SPOT_CUTOFF on): the reference frustum may no longer cover it
        r_now, r_ref = light_rotation(view), light_rotation(ref.view)
        turned = (_angle(r_now @ r_ref.T) > REFERENCE_TURN or type(view) is not type(ref.view)
                  or getattr(view, "tan_half", None) != getattr(ref.view, "tan_half", None)
                  or getattr(view, "tan_half_y", None) != getattr(ref.view, "tan_half_y", None))
    if (ref is None or ref.emitter is not emitter or ref.kind != view.kind or turned
            or _far(ref, current)):
        ref = _Reference(emitter, view, view.kind, current, max(scene_size, 1e-30))
        _REFERENCES.pop(id(emitter), None)
        _REFERENCES[id(emitter)] = ref
        while len(_REFERENCES) > _MAX_REFERENCES:
            _REFERENCES.pop(next(iter(_REFERENCES)))
    if how == "translation":
        offset = mi.Vector3f(value) - mi.Vector3f(*[float(x) for x in ref.value])
        dr.make_opaque(offset)
        return ref.view, LightPose(mi.Transform4f().translate(offset),
                                   mi.Transform4f().translate(-offset))
    if how == "rotation":   # about the scene's centre; no translation
        m = mi.Matrix4f(value)
        for r in range(3):
            m[r][3] = 0.0
        r_ref = ref.value.copy()
        r_ref[:3, 3] = 0.0
        c = centre
        delta = (mi.Matrix4f(np.array(mi.ScalarTransform4f().translate(c).matrix)) @ m
                 @ mi.Matrix4f(np.linalg.inv(r_ref).astype(np.float32))
                 @ mi.Matrix4f(np.array(mi.ScalarTransform4f().translate([-x for x in c]).matrix)))
    dr.make_opaque(delta)
    inverse = dr.rcp(delta)   # the matrix inverse (dr.inverse is deprecated)
    dr.make_opaque(inverse)
    return ref.view, LightPose(mi.Transform4f(delta), mi.Transform4f(inverse))
