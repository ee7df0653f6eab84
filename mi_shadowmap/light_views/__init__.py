"""Emitter -> light camera(s): one class per projection behind one interface.

Nothing else in the package knows how a light projects. :func:`make_light_view`
is the one factory; each view class (see :class:`~.base.LightView` for the
interface and the conventions) lives in its own module:

=====================  ===============  ====================================
emitter                view             module
=====================  ===============  ====================================
spot                   PerspectiveView  :mod:`.perspective`
spot, cutoff >= 80     CubeView         :mod:`.cube` (kind ``'spot'``)
directional            OrthoView        :mod:`.ortho`
directional, cascades  CascadedView     :mod:`.cascaded`
point, area            CubeView         :mod:`.cube`
projector              CubeView         :mod:`.cube` (kind ``'projector'``)
any (``multiview``)    MultiView        :mod:`.multi` (K views in one map)
=====================  ===============  ====================================

A virtual map of a light far from the scene (:func:`mi_shadowmap.virtual.layout_for`)
replaces the emitter's view by :func:`~.perspective.box_view`: one perspective face
from the same light, aimed at the scene's box.

Adding a light type means one class (and one line in :func:`make_light_view`).
The helpers below are the camera-side inputs of the map manager: the points
the camera sees (:func:`camera_visible_points`) and the texel-to-pixel
footprint of the automatic resolution (:func:`footprint_ratio`).
"""
from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi
import numpy as np

from .base import LightView, scene_bounds
from .cascaded import CascadedView, cascaded_view, split_depths
from .cube import (CubeView, area_light_axes, area_light_size, area_view, point_view,
                   projector_view)
from .ortho import OrthoView, directional_view
from .perspective import PerspectiveView, box_view, spot_view
from .multi import MultiView, multi_view

__all__ = ["LightView", "PerspectiveView", "OrthoView", "CascadedView", "CubeView", "box_view",
           "MultiView", "multi_view", "make_light_view", "emitter_kind", "emitter_label",
           "emitter_labels", "unique_labels",
           "emitter_class",
           "area_light_axes", "area_light_size", "cascaded_view", "split_depths",
           "camera_visible_points",
           "footprint_ratio", "PIXEL_BLOCK", "block_pixels", "pixel_centres",
           "pixel_ray_differentials",
           "pixel_step", "pixel_steps",
           "is_pinhole", "aims_by_film", "pinhole", "differential_origins", "pinhole_frame",
           "pinhole_footprint",
           "UnsupportedEmitterError", "SUPPORTED_EMITTERS", "check_emitter_values",
           "emitted_value_keys", "emitted_value_owners"]

SUPPORTED_EMITTERS = ("point", "spot", "directional", "area", "projector")
_CLASS_TO_KIND = {
    "PointLight": "point",
    "SpotLight": "spot",
    "DirectionalEmitter": "directional",
    "AreaLight": "area",
    "Projector": "projector",
}


class UnsupportedEmitterError(ValueError):
    """An emitter for which no light view can be built."""


def emitter_class(emitter) -> str:
    """The C++ class name of an emitter (e.g. 'PointLight')."""
    # class_name(), not str(emitter): printing an emitter evaluates its JIT fields
    return emitter.class_name()


def emitter_kind(emitter) -> str:
    """'point' | 'spot' | 'directional' | 'area' | 'projector' | 'environment' | class
    name."""
    if emitter.is_environment():
        return "environment"
    cls = emitter_class(emitter)
    return _CLASS_TO_KIND.get(cls, cls)


def emitter_label(emitter, index: int) -> str:
    """A readable name: the emitter's id if it has one, else its index (not unique:
    :func:`emitter_labels` gives a scene's)."""
    eid = emitter.id()
    return eid if eid else str(index)


def emitter_labels(emitters) -> list:
    """Each emitter's name, unique in the scene: the ``<label>`` of its ``vis_<label>``
    AOV, and the name errors and statistics give it. An emitter's own id where no
    other emitter has it; else, for an area emitter, its shape's id (an XML
    ``<shape id="lamp"><emitter type="area"/>`` gives the emitter no id, and Mitsuba's
    ``load_dict`` ids every nested one ``emitter``) where unique; else the emitter's
    index, or ``<index>_<n>`` where that is another emitter's name (see
    :func:`unique_labels`)."""
    own = [e.id() or None for e in emitters]
    shapes = []
    for e in emitters:
        shape = e.get_shape() if hasattr(e, "get_shape") else None
        shapes.append((shape.id() or None) if shape is not None else None)
    return unique_labels(own, shapes)


def unique_labels(labels: list, second=None) -> list:
    """Unique names for emitters whose own names are ``labels`` (None: none), with
    ``second`` their fallback names (None: none). A name held by one emitter alone is
    kept; the others take their fallback name where it is unique and not another's own
    name; the rest their index, or ``<index>_<n>`` where the index is taken. (An
    unnamed emitter at index 1 beside one whose id is ``'1'`` took ``vis_1`` and sent
    the named one to ``vis_0``; ids ``['1', 'emitter', 'emitter']`` once gave ``vis_1``
    twice, and Mitsuba's film failed with "duplicate channel name".)"""
    second = list(second) if second is not None else [None] * len(labels)
    own = [lab if lab else None for lab in labels]
    out = [lab if lab is not None and own.count(lab) == 1 else None for lab in own]
    taken = {lab for lab in out if lab is not None}
    for i, alt in enumerate(second):
        if out[i] is None and alt and alt not in taken and second.count(alt) == 1 \
                and alt not in own:
            out[i] = alt
            taken.add(alt)
    for i in range(len(out)):
        if out[i] is None:
            cand, n = str(i), 1
            while cand in taken:
                cand, n = f"{i}_{n}", n + 1
            out[i] = cand
            taken.add(cand)
    return out


def make_light_view(emitter, scene, index: int, label: str | None = None) -> LightView:
    """Build the :class:`LightView` of one emitter (the ``index``-th of ``scene``'s), or
    raise naming it. ``label``: its name from :func:`emitter_labels` (computed here if
    not given: callers building every emitter's view pass the scene's once)."""
    if label is None:
        emitters = scene.emitters()
        label = (emitter_labels(emitters)[index] if index < len(emitters)
                 else emitter_label(emitter, index))
    kind = emitter_kind(emitter)
    view = None
    if kind == "spot":
        view = spot_view(emitter, label)
    elif kind == "point":
        view = point_view(emitter, label)
    elif kind == "directional":
        view = directional_view(emitter, scene, label)
    elif kind == "area":
        view = area_view(emitter, scene, label)
    elif kind == "projector":
        view = projector_view(emitter, label)
    if view is not None:
        _check_frame(view, emitter, kind)
        return view
    raise UnsupportedEmitterError(
        f"shadowmap: emitter '{label}' ({emitter_class(emitter)}) is not supported; "
        f"supported emitter types: {', '.join(SUPPORTED_EMITTERS)}, and envmap, "
        "constant and sunsky (environment='shadowed' or 'unshadowed')"
        + ("; for environment/constant emitters set environment='unshadowed' to light "
           "them without shadows" if kind == "environment" else ""))


#: The parameters of an emitter that hold its emitted values (Mitsuba 3.9's names:
#: ``intensity.value``, ``irradiance.d65.values``, ``radiance.data``, an envmap's
#: ``data`` and ``scale``, a spot's ``texture...``); ``*.range`` (a spectrum's wavelengths)
#: and ``*.to_uv`` are not values.
_VALUE_ROOTS = ("intensity", "irradiance", "radiance", "texture", "data", "scale")


def emitted_value_keys(params) -> list:
    """The keys of ``mi.traverse(emitter)`` that hold its emitted values."""
    return [k for k in params.keys() if k.split(".")[0] in _VALUE_ROOTS
            and k.split(".")[-1] not in ("range", "to_uv")]


def emitted_value_owners(params) -> dict:
    """``{key: class name}`` of the objects holding :func:`emitted_value_keys`."""
    return {k: params.properties[k][2].class_name() for k in emitted_value_keys(params)}


def _coefficients(key: str, owner: str, value) -> bool:
    """Whether parameter ``key`` (``value``) of an object of class ``owner`` holds a
    spectral variant's RGB upsampling coefficients (negative ones included), not
    radiances: an RGB colour's ``value`` (``D65Spectrum``, ``SRGB*Spectrum``), the
    ``data`` of an RGB bitmap or an envmap (3 or 4 channels; a one-channel bitmap holds
    plain values)."""
    if not mi.is_spectral:
        return False
    if key.endswith("data"):
        shape = getattr(value, "shape", ())
        return len(shape) > 0 and shape[-1] >= 3
    return owner.startswith(("D65", "SRGB"))


def check_emitter_values(emitter, label: str, values: dict, owners: dict) -> None:
    """Raise naming the emitter and the parameter when an emitted value is not finite or
    is negative. Mitsuba loads both: a NaN or infinite intensity made NaN and infinite
    pixels, a NaN texel of an environment map failed deep in its median cut (numpy's
    "SVD did not converge"), and a negative intensity rendered black (Mitsuba's
    ``direct`` renders negative light; in a spectral variant, where an RGB colour or a
    bitmap holds upsampling coefficients, negative ones included, only the values that
    are radiances: uniform and sampled spectra, an envmap's ``scale``). ``values``:
    ``{key: value}`` of :func:`emitted_value_keys`, ``owners``: ``{key: class name of
    the object holding it}`` (:func:`emitted_value_owners`). Reads evaluated values on
    the host (no kernel). ``emitter``: the emitter or its class name."""
    cls = emitter if isinstance(emitter, str) else emitter_class(emitter)
    for key, value in values.items():
        try:
            a = np.asarray(value.array if hasattr(value, "array") else value, np.float32)
        except (TypeError, ValueError):
            continue
        bad = int(np.count_nonzero(~np.isfinite(a)))
        neg = 0 if _coefficients(key, owners[key], value) else int(np.count_nonzero(a < 0))
        if bad or neg:
            what = (f"{bad} of its {a.size} values are not finite (NaN or inf)" if bad
                    else f"{neg} of its {a.size} values are negative (min {float(a.min()):g})")
            raise UnsupportedEmitterError(
                f"shadowmap: emitter '{label}' ({cls}): parameter "
                f"'{key}': {what}; emitted values must be finite and >= 0")


def _check_frame(view, emitter, kind: str) -> None:
    """Raise naming the emitter when its frame is degenerate: a position or a transform
    that is not finite (a point light at NaN), or a directional light's zero direction
    (Mitsuba loads it, and its frame is NaN: virtual maps crashed the process inside a
    kernel, full maps rendered black)."""
    m = np.array(view.light_from_world.matrix, dtype=np.float64)
    pos = np.array([float(c) for c in view.position])
    if np.all(np.isfinite(m)) and np.all(np.isfinite(pos)) and abs(np.linalg.det(m[:3, :3])) > 0:
        return
    what = {"directional": "its direction is zero or not finite",
            "point": "its position is not finite",
            "area": "its shape's position or transform is not finite"}.get(
        kind, "its position or to_world transform is not finite or degenerate")
    raise UnsupportedEmitterError(
        f"shadowmap: emitter '{view.label}' ({emitter_class(emitter)}) has no valid frame: "
        f"{what}; give it a finite position and a non-zero direction")


def pixel_centres(sensor, blocks: bool = False) -> mi.Point2f:
    """The film position of every pixel centre of ``sensor``'s crop, row by row; with
    ``blocks``, in blocks of ``PIXEL_BLOCK``^2 pixels (row by row), each in Morton (Z)
    order, so that a vector of neighbouring lanes holds a square of pixels rather than a
    run of one row, which a BVH traverses together (the mark pass's camera rays on a
    1M-triangle mesh at 256^2: 4.1-4.3 ms against 6.4-6.7 ms in rows). A crop whose sides
    are not multiples of the block repeats its last column or row to fill the blocks
    (at most ``PIXEL_BLOCK - 1`` of each)."""
    w, h = (int(x) for x in sensor.film().crop_size())
    if not blocks:
        idx = dr.arange(mi.UInt32, w * h)
        y = idx // w
        x = idx - y * w
        return mi.Point2f((mi.Float(x) + 0.5) / w, (mi.Float(y) + 0.5) / h)
    B = PIXEL_BLOCK
    n = -(-w // B) * -(-h // B) * B * B     # whole blocks
    x, y = block_pixels(dr.arange(mi.UInt32, n), w, h, dr.minimum)
    return mi.Point2f((mi.Float(x) + 0.5) / w, (mi.Float(y) + 0.5) / h)


def block_pixels(idx, w: int, h: int, minimum) -> tuple:
    """The film pixel ``(x, y)`` of each lane ``idx`` of :func:`pixel_centres`' blocks
    (``blocks=True``), for Dr.Jit (``mi.UInt32``, ``minimum=dr.minimum``) or numpy
    (integers, ``minimum=np.minimum``) lanes alike: the mark pass reads them on the host
    too (``marks._lane_pixels``)."""
    B = PIXEL_BLOCK
    bw = -(-w // B)
    block, local = idx // (B * B), idx & (B * B - 1)
    by = block // bw
    bx = block - by * bw
    i = j = 0
    for b in range(B.bit_length() - 1):    # even bits of local: i, odd bits: j
        i = i | (((local >> (2 * b)) & 1) << b)
        j = j | (((local >> (2 * b + 1)) & 1) << b)
    return minimum(bx * B + i, w - 1), minimum(by * B + j, h - 1)


#: the side of :func:`pixel_centres`'s blocks (a power of two)
PIXEL_BLOCK = 8


def pixel_ray_differentials(sensor, position: mi.Point2f, time=0.0, aperture=None):
    """The ray of ``sensor`` through film ``position`` (in [0, 1]^2 over its crop) with
    one-pixel ray differentials: the sensor's own, or, for a sensor that gives none
    (Mitsuba's ``batch`` sensor, ``radiancemeter``), its rays through the next pixel
    in x and y, from ``sample_ray`` -- forward or, where the forward ray turns more than
    twice as far as the backward one (the last column of a batch's sub-camera, whose
    next pixel is another camera's), backward, mirrored. ``aperture``: the lens samples
    (``mi.Point2f``, default its centre, 0.5)."""
    aperture = mi.Point2f(0.5) if aperture is None else aperture
    ray, _ = sensor.sample_ray_differential(time, 0.5, position, aperture)
    if ray.has_differentials:
        pin = pinhole(sensor)
        if pin is not None:
            # opaque: a moved camera must not compile a new kernel
            ray.o_x, ray.o_y = differential_origins(ray, dr.opaque(mi.Point3f, pin))
        return ray
    w, h = (int(x) for x in sensor.film().crop_size())

    def neighbour(step):
        fwd, _ = sensor.sample_ray(time, 0.5, position + step, aperture)
        bwd, _ = sensor.sample_ray(time, 0.5, position - step, aperture)
        turn_f = 1.0 - dr.dot(fwd.d, ray.d)      # ~ angle^2 / 2
        turn_b = 1.0 - dr.dot(bwd.d, ray.d)
        shift_f, shift_b = dr.squared_norm(fwd.o - ray.o), dr.squared_norm(bwd.o - ray.o)
        use_fwd = (turn_f <= 4.0 * turn_b + 1e-12) & (shift_f <= 4.0 * shift_b + 1e-30)
        return (dr.select(use_fwd, fwd.o, 2.0 * ray.o - bwd.o),
                dr.select(use_fwd, fwd.d, dr.normalize(2.0 * ray.d - bwd.d)))

    ray.o_x, ray.d_x = neighbour(mi.Vector2f(1.0 / w, 0.0))
    ray.o_y, ray.d_y = neighbour(mi.Vector2f(0.0, 1.0 / h))
    ray.has_differentials = True
    return ray


def aims_by_film(sensor) -> bool:
    """Whether ``sensor`` aims each pixel's rays by its film position: a camera
    (``perspective``, ``thinlens``, ``orthographic``), a ``radiancemeter``, a ``batch`` of
    cameras. False for a sensor that spreads a pixel's rays over a surface or a hemisphere
    with its aperture sample: ``irradiancemeter`` (a shape's irradiance, from the whole
    hemisphere above it) and ``distant`` (a direction's radiance over a target). Such a
    pixel has no footprint and no set of points it sees, so the render takes no pixel
    footprint, and the automatic maps are full maps (see the ``virtual`` property). A
    ``batch`` aims by film when each of its sensors does (one with a ``thinlens`` needs
    aperture samples, and still aims by film)."""
    if sensor is None:
        return False
    if isinstance(sensor, mi.ProjectiveCamera) or not sensor.needs_aperture_sample():
        return True
    if sensor.class_name() == "BatchSensor":
        return all(aims_by_film(s) for s in _child_sensors(sensor))
    return False


class _SensorCollector(mi.TraversalCallback):
    """Collects the sensors among an object's traversed children."""

    def __init__(self):
        super().__init__()
        self.found = []

    def put(self, name, value, *flags):
        if isinstance(value, mi.Sensor):
            self.found.append(value)


def _child_sensors(sensor) -> list:
    """The sensors a ``batch`` sensor holds (from its traversal)."""
    cb = _SensorCollector()
    sensor.traverse(cb)
    return cb.found


def is_pinhole(sensor) -> bool:
    """A ``perspective`` camera (``sample_direction`` gives a point's film position)."""
    # class_name(), not str(sensor): printing a sensor evaluates its JIT fields
    return (isinstance(sensor, mi.ProjectiveCamera) and not sensor.needs_aperture_sample()
            and sensor.class_name() == "PerspectiveCamera")


def pinhole(sensor):
    """The world position of a ``perspective`` camera's pinhole (three floats), else
    None: where :func:`differential_origins` starts its rays' differentials."""
    if sensor is None or not is_pinhole(sensor):
        return None
    t = sensor.world_transform().translation()
    return tuple(float(dr.ravel(t[k])[0]) for k in range(3))


def differential_origins(ray, pin, o_x=None, o_y=None):
    """``(o_x, o_y)``: the origins of ``ray``'s differentials (or the given ones, e.g.
    rescaled), replaced by the pinhole ``pin`` where the ray gives them its own origin.

    Mitsuba's ``perspective`` camera starts each ray on its near plane (``o = pinhole +
    d near_t``) but gives the differentials that same origin (``o_x = o_y = o``) with
    the directions of the neighbouring pixels' rays through the pinhole. Those rays miss
    the neighbours' points: at distance ``t`` from the pinhole the one-pixel footprint
    comes out ``(t - near_t) / t`` of a pixel (on a scene a thousandth the usual size
    with the default ``near_clip`` = 0.01, a fifth: virtual maps then built 38 texels per
    pixel instead of 4.8). Differentials whose origin differs from the ray's (a camera
    that sets them) are kept."""
    o_x = ray.o_x if o_x is None else o_x
    o_y = ray.o_y if o_y is None else o_y
    return (dr.select(dr.all(ray.o_x == ray.o), pin, o_x),
            dr.select(dr.all(ray.o_y == ray.o), pin, o_y))


def pinhole_frame(sensor):
    """``(pinhole, forward, step_x, step_y)`` of a ``perspective`` camera (world space,
    tuples of floats), else None: its pinhole, its unit viewing axis, and the change of a
    ray's direction scaled to unit depth along that axis (``d / (forward . d)``) from one
    pixel of the film's crop to the next in x and in y (the same at every pixel: it is
    affine in the film position), measured across the middle half of the crop in float64.
    What :func:`pinhole_footprint` needs."""
    if sensor is None or not is_pinhole(sensor):
        return None
    w, h = (int(x) for x in sensor.film().crop_size())
    pos = mi.Point2f(mi.Float([0.25, 0.75, 0.5, 0.5]), mi.Float([0.5, 0.5, 0.25, 0.75]))
    ray, _ = sensor.sample_ray(0.0, 0.5, pos, mi.Point2f(0.5))
    matrix = sensor.world_transform().matrix
    # every entry of both evaluated in one kernel, then read: ``np.array`` of each (its
    # own kernel, a ravel, waited for) ran two kernels and two waits, 0.22-0.23 ms
    # against 0.11-0.13 ms (a moved frame's first pass runs this once; same values)
    flat = [ray.d.x, ray.d.y, ray.d.z] + [matrix[r][c] for r in range(4) for c in range(4)]
    dr.eval(*flat)
    d = np.array([a.numpy() for a in flat[:3]], dtype=np.float64)                # (3, 4)
    to_world = np.array([a.numpy()[0] for a in flat[3:]], dtype=np.float64).reshape(4, 4)
    fwd = to_world[:3, :3] @ np.array([0.0, 0.0, 1.0])
    fwd /= np.linalg.norm(fwd)
    unit = d / (fwd @ d)
    step_x = (unit[:, 1] - unit[:, 0]) / (0.5 * w)
    step_y = (unit[:, 3] - unit[:, 2]) / (0.5 * h)
    pin = to_world[:3, 3]
    return tuple(tuple(float(x) for x in v) for v in (pin, fwd, step_x, step_y))


def pinhole_footprint(p_world, n_world, frame):
    """``(dp_dx, dp_dy)``: where the rays from the pinhole through the next pixel in x and
    in y meet the tangent plane of ``p_world`` (normal ``n_world``), minus ``p_world``;
    ``frame`` is :func:`pinhole_frame`'s, as JIT values.

    With ``v = p - pinhole``, ``z = forward . v``, ``a = n . v`` and ``b = z (n . step)``,
    the next pixel's ray ``pinhole + l (v / z + step)`` meets the plane at
    ``p + (a z step - b v) / (a + b)``: the same point as intersecting the camera's ray
    differentials with the plane (a finite difference of one pixel, not a derivative),
    from the pinhole whatever the ``near_clip`` (Mitsuba's ``perspective`` camera gives
    its differentials the near-plane origin, see :func:`differential_origins`), with one
    division per axis and no ray differentials (Mitsuba's ``d_x``, ``d_y`` are then not
    computed at all). A neighbour's ray parallel to the plane gives a huge footprint, as
    intersecting it would."""
    pin, fwd, step_x, step_y = frame
    v = mi.Vector3f(p_world - pin)
    n = mi.Vector3f(n_world)
    z = dr.dot(v, fwd)
    a = dr.dot(n, v)
    tiny = 1e-12 * dr.abs(z)
    out = []
    for step in (step_x, step_y):
        b = z * dr.dot(n, step)
        den = a + b
        den = dr.select(dr.abs(den) > tiny, den, tiny)
        out.append(mi.Vector3f((a * z * step - b * v) / den))
    return tuple(out)


def pixel_steps(sensor):
    """``(angle, offset)``: per pixel of ``sensor``'s crop (row by row, as
    :func:`pixel_centres`), the change of a ray's direction (radians) and origin from
    that pixel's centre to the next pixel's, the mean over x and y
    (:func:`pixel_ray_differentials`), as float32 numpy arrays. The render's footprint
    of a sensor without ray differentials (a ``batch``: its rays in ``sample()`` have
    none) is a cone of its pixel's angle: per pixel, because a batch's cameras differ
    (a 4-degree and a 30-degree camera side by side: one median for both made the
    narrow one's footprints 4x too wide)."""
    ray = pixel_ray_differentials(sensor, pixel_centres(sensor))
    d = dr.normalize(ray.d)
    angle = sum(dr.norm(dr.normalize(dd) - d).numpy() for dd in (ray.d_x, ray.d_y)) / 2
    offset = sum(dr.norm(o - ray.o).numpy() for o in (ray.o_x, ray.o_y)) / 2
    return np.asarray(angle, np.float32), np.asarray(offset, np.float32)


def pixel_step(sensor):
    """``(angle, offset)``: the median over the pixels of ``sensor`` of
    :func:`pixel_steps` (a sensor's typical one-pixel change of a ray's direction, in
    radians, and origin)."""
    angle, offset = pixel_steps(sensor)
    return (float(np.median(angle)) if len(angle) else 0.0,
            float(np.median(offset)) if len(offset) else 0.0)


def camera_visible_points(scene, sensor) -> np.ndarray:
    """World points the camera sees: one ray through every pixel centre, ``(N, 3)``."""
    if sensor is None:
        return np.zeros((0, 3))
    ray, _ = sensor.sample_ray(0.0, 0.5, pixel_centres(sensor), mi.Point2f(0.5))
    si = scene.ray_intersect(ray)
    p = np.stack([si.p.x.numpy(), si.p.y.numpy(), si.p.z.numpy()], axis=1)
    return p[si.is_valid().numpy()]


def footprint_ratio(scene, sensor, views) -> float:
    """Texel width over camera pixel width at the scene's centre (max over lights).

    Per unit resolution a view spans :meth:`LightView.map_width` (a spot map
    ``2 tan(cutoff) d`` at distance ``d`` from the light, a cube face ``2 d``,
    an orthographic map its width, cascades their largest one); a perspective
    camera spans ``2 tan(x_fov / 2) d_cam`` per unit film width, an orthographic
    camera its own width at any distance (before, 1 was taken: its automatic full
    maps were the film's size whatever its zoom, 4x coarser than a perspective
    camera's of the same view). ``d`` and ``d_cam`` are measured to the centre of
    the scene's bounding box. A ``batch`` sensor: the largest of its cameras' ratios,
    each at its own pixels (before, the first camera's field of view was taken from
    the batch's own position, the world origin: a scene 500 units from it got 128^2
    maps where its 4-degree camera alone gets 512^2). Returns 1 when it cannot be
    computed (no bounds, a sensor without a field of view). Used
    by the automatic ``resolution``
    (:meth:`~mi_shadowmap.options.Options.map_resolution`).
    """
    bounds = scene_bounds(scene)     # not scene.bbox(): merged meshes (base.shape_bounds)
    if sensor is None or bounds is None:
        return 1.0
    if sensor.class_name() == "BatchSensor":
        # each camera's ratio at its own pixels: its film is its share of the batch's
        width = int(sensor.film().size()[0])
        ratios = [footprint_ratio(scene, s, views) * int(s.film().size()[0]) / width
                  for s in _child_sensors(sensor) if isinstance(s, mi.ProjectiveCamera)]
        return max(ratios) if ratios else 1.0
    centre = 0.5 * (bounds[0] + bounds[1])
    if sensor.class_name() == "OrthographicCamera":
        # the whole film spans camera x in [-1, 1], scaled by to_world, at any distance
        m = np.array(sensor.world_transform().matrix, dtype=np.float64).reshape(4, 4)
        cam_width = 2.0 * float(np.linalg.norm(m[:3, 0]))
    else:
        params = mi.traverse(sensor)
        key = next((k for k in params.keys() if k.endswith("x_fov")), None)
        if key is None:
            return 1.0
        x_fov = float(dr.ravel(params[key])[0])
        cam = sensor.world_transform().translation()
        cam = np.array([float(dr.ravel(cam[k])[0]) for k in range(3)])
        cam_width = 2.0 * math.tan(math.radians(x_fov) / 2) * np.linalg.norm(centre - cam)
    if not cam_width > 0:
        return 1.0
    widths = [v.map_width(centre) for v in views if v is not None]
    return max(widths) / cam_width if widths else 1.0
