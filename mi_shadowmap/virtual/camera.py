"""A camera's state: whether it moved since the marks were made (a still camera reuses
them), and its pinhole frame as opaque values.
"""
from __future__ import annotations

import collections

import drjit as dr
import mitsuba as mi
import numpy as np

from ..light_views import pinhole_frame


class CameraState:
    """What :func:`camera_state` returns: equal to another exactly when every camera
    parameter is the same JIT variable (or, for a scalar one, the same value). It holds
    references to those variables, so their indices cannot be recycled while it lives
    (a page store keeps its marks' state), and a parameter written in place gets a new
    variable (Dr.Jit copies on write while another reference exists). A camera set
    back to earlier values through new variables compares unequal: the mark pass runs
    again, which is never wrong."""

    __slots__ = ("token", "refs")

    def __init__(self, token: tuple, refs: list):
        self.token, self.refs = token, refs

    def __eq__(self, other):
        return isinstance(other, CameraState) and self.token == other.token

    def __hash__(self):
        return hash(self.token)


def camera_state(sensor) -> CameraState:
    """Everything about ``sensor`` that moves what the camera sees (its
    ``mi.traverse`` parameters: ``to_world``, field of view, ...; the film's crop), as a
    :class:`CameraState`: a render with the same camera state marks the same pages, so
    the mark pass is skipped (a still camera re-rendering, e.g. more spp or another
    seed). Costs a read of each parameter's variable indices (the traversal is kept per
    sensor)."""
    from ..map_manager import ParamWatch
    slot = _CAMERAS.get(id(sensor))
    if slot is None or slot[0] is not sensor:
        params = mi.traverse(sensor)
        slot = _CAMERAS[id(sensor)] = [sensor, ParamWatch(params, sorted(params.keys())),
                                       None]
    _CAMERAS.move_to_end(id(sensor))
    while len(_CAMERAS) > 8:
        _CAMERAS.popitem(last=False)
    _, watch, last = slot
    token, values = watch.read()
    film = sensor.film()
    token += (tuple(film.crop_size()), tuple(film.crop_offset()))
    if last is None or last.token != token:
        last = slot[2] = CameraState(token, watch.held(values))
    return last


#: Per sensor (by ``id``, holding it): ``[sensor, ParamWatch of its parameters, last
#: CameraState]``.
_CAMERAS = collections.OrderedDict()


def camera_frame(sensor, state: CameraState | None = None):
    """:func:`~mi_shadowmap.light_views.pinhole_frame` of ``sensor`` as opaque JIT values
    (a moved camera compiles nothing), or None; kept per camera state
    (:func:`camera_state`), so the render and its mark pass share one, and a still camera
    measures its pixel steps once (a small kernel and a read-back each time).
    ``state``: ``sensor``'s :func:`camera_state` where the caller read it in this render
    (the page planner: its mark pass and the render's own call take it, not a read of
    every camera parameter again each, 40-50 us warm, more in a frame's cold first pass);
    default: read here."""
    if sensor is None:
        return None
    if state is None:
        state = camera_state(sensor)
    slot = _FRAMES.get(id(sensor))
    if slot is None or slot[0] is not sensor or slot[1] != state:
        frame = pinhole_frame(sensor)
        if frame is not None:
            frame = tuple(dr.opaque(mi.Point3f if k == 0 else mi.Vector3f, v)
                          for k, v in enumerate(frame))
        slot = _FRAMES[id(sensor)] = (sensor, state, frame)
        while len(_FRAMES) > 8:
            _FRAMES.pop(next(iter(_FRAMES)))
    return slot[2]


#: Per sensor (by ``id``, holding it): ``(sensor, CameraState, camera_frame)``.
_FRAMES = {}


def has_aperture(sensor) -> bool:
    """Whether ``sensor`` has a lens of positive radius (read from the traversal that
    :func:`camera_state` keeps per sensor); a ``batch`` sensor: whether one of its
    cameras has (its ``sample_ray`` passes the lens sample on to them)."""
    if "Batch" in sensor.class_name():
        from ..light_views import _child_sensors
        return any(has_aperture(s) for s in _child_sensors(sensor))
    if "ThinLens" not in sensor.class_name():
        return False
    slot = _CAMERAS.get(id(sensor))
    params = slot[1].params if slot is not None and slot[0] is sensor else mi.traverse(sensor)
    if "aperture_radius" not in params.keys():
        return False
    return float(np.max(np.asarray(params["aperture_radius"]))) > 0.0


def clear_camera_states() -> None:
    """Forget every sensor's kept traversal, state and frame (:data:`PAGE_CACHE`'s
    ``clear``): the frames held up to 8 sensors, their films' storage with them, after
    ``clear_caches()`` (8 scenes of 1024^2 films: 140 MiB)."""
    _CAMERAS.clear()
    _FRAMES.clear()
