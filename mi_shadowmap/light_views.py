"""Emitter -> light camera(s): the world->light transforms and projections.

Nothing else in the package knows how a light projects. A :class:`LightView`
describes the map faces of one emitter, and offers three vectorised
(Dr.Jit) operations used by the rest of the package:

* :meth:`LightView.texel_rays` -- one world-space ray per texel centre, used
  to build the depth map;
* :meth:`LightView.project` -- ``p_world`` -> (face, ``uv_light``, depth),
  used by every lookup;
* :meth:`LightView.texel_world_size` -- the world-space width of one texel
  at a given depth, used to express biases and footprints in texels.

Conventions
-----------
* **Depth** is the Euclidean distance from the light position for spot,
  point and area lights, and the distance from the light's near plane along
  the light direction for directional lights. It is the ``t`` of the
  texel's ray, so map values and receiver depths are compared in this one
  space (world units).
* **Texels.** Face ``f`` of resolution ``r`` stores texel ``(i, j)`` at flat
  index ``f*r*r + j*r + i``; its centre is ``uv = ((i+0.5)/r, (j+0.5)/r)``.
  A point looks up the texel ``floor(uv * r)`` (nearest texel).
* **Spot** (``perspective``): one face, a square frustum circumscribing the
  cutoff cone (half-angle = ``cutoff_angle``), +z along the spot axis.
* **Point and area** (``cube``): six 90-degree faces around the light
  position in world axes. Face ``2*a + s`` looks along axis ``a`` with sign
  ``+`` (s=0) or ``-`` (s=1); its ``u``/``v`` are the axes ``(a+1)%3`` and
  ``(a+2)%3``. Area lights are treated as their shape's centre; the shape
  itself is never an occluder.
* **Directional** (``orthographic``): one face, aligned with the light
  direction and fitted to the scene's bounding-box corners as seen along
  the light (the tight rectangle of the projected corners, not a bounding
  sphere).
* **Outside a map** (behind a spot, beyond a directional map's rectangle)
  ``inside`` is False and lookups treat the point as lit (Reeves 1987).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import drjit as dr
import mitsuba as mi

SUPPORTED_EMITTERS = ("point", "spot", "directional", "area")
_CLASS_TO_KIND = {
    "PointLight": "point",
    "SpotLight": "spot",
    "DirectionalEmitter": "directional",
    "AreaLight": "area",
}


class UnsupportedEmitterError(ValueError):
    """An emitter for which no light view can be built."""


def emitter_class(emitter) -> str:
    """The C++ class name of an emitter (e.g. 'PointLight')."""
    return str(emitter).split("[", 1)[0].strip()


def emitter_kind(emitter) -> str:
    """'point' | 'spot' | 'directional' | 'area' | 'environment' | class name."""
    if emitter.is_environment():
        return "environment"
    cls = emitter_class(emitter)
    return _CLASS_TO_KIND.get(cls, cls)


def emitter_label(emitter, index: int) -> str:
    """A readable name: the emitter's id if it has one, else its index."""
    eid = emitter.id()
    return eid if eid else str(index)


@dataclass
class LightView:
    """The map faces of one emitter and how world points project into them."""
    kind: str                      # emitter kind
    projection: str                # 'perspective' | 'cube' | 'orthographic'
    n_faces: int
    position: mi.ScalarPoint3f     # light position (perspective/cube); near-plane centre (ortho)
    light_from_world: mi.ScalarTransform4f  # rigid; +z is the view direction (not used by cube)
    tan_half: float = 1.0          # perspective: tan(half field of view)
    half_extent: tuple = (1.0, 1.0)  # orthographic: half width/height of the map rectangle
    depth_range: float = 1.0       # orthographic: far - near
    light_size: float = 0.0        # world-space light width (0: a point)
    ignore_shape: object = None    # the emitter's own shape (area lights)
    label: str = ""
    extra: dict = field(default_factory=dict)

    # ----------------------------------------------------------------- build
    def texel_rays(self, res: int):
        """World-space rays through every texel centre of every face.

        Returns ``(o_world, d_world, max_t)`` with ``n_faces*res*res`` entries
        in flat texel order.
        """
        idx = dr.arange(mi.UInt32, self.n_faces * res * res)
        face = idx // (res * res)
        rem = idx - face * (res * res)
        j = rem // res
        i = rem - j * res
        inv = 1.0 / res
        s = (mi.Float(i) + 0.5) * (2.0 * inv) - 1.0   # [-1, 1] across the face
        t = (mi.Float(j) + 0.5) * (2.0 * inv) - 1.0
        if self.projection == "cube":
            d_light = _cube_dir(face, s, t)
            o = mi.Point3f(self.position)
            return o, dr.normalize(d_light), mi.Float(dr.inf)
        world_from_light = mi.Transform4f(self.light_from_world.inverse())
        if self.projection == "perspective":
            d_light = mi.Vector3f(s * self.tan_half, t * self.tan_half, 1.0)
            return (mi.Point3f(self.position), dr.normalize(world_from_light @ d_light),
                    mi.Float(dr.inf))
        # orthographic
        o_light = mi.Point3f(s * self.half_extent[0], t * self.half_extent[1], 0.0)
        return (world_from_light @ o_light, world_from_light @ mi.Vector3f(0, 0, 1),
                mi.Float(dr.inf))

    # ---------------------------------------------------------------- lookup
    def project(self, p_world: mi.Point3f):
        """Project world points: returns ``(face, uv_light, depth, inside)``.

        ``uv_light`` is in [0, 1]^2 on the face when ``inside``.
        """
        p_world = mi.Point3f(p_world)   # Point + Vector arithmetic may yield a Vector3f
        if self.projection == "cube":
            d = p_world - mi.Point3f(self.position)
            face, s, t, major = _cube_face(d)
            uv = mi.Point2f(0.5 * (s + 1.0), 0.5 * (t + 1.0))
            depth = dr.norm(d)
            return face, uv, depth, major > 0
        p_light = mi.Transform4f(self.light_from_world) @ p_world
        if self.projection == "perspective":
            z = p_light.z
            inv_z = dr.rcp(dr.maximum(z, 1e-30))
            uv = mi.Point2f(0.5 * (p_light.x * inv_z / self.tan_half + 1.0),
                            0.5 * (p_light.y * inv_z / self.tan_half + 1.0))
            depth = dr.norm(p_world - mi.Point3f(self.position))
        else:
            uv = mi.Point2f(0.5 * (p_light.x / self.half_extent[0] + 1.0),
                            0.5 * (p_light.y / self.half_extent[1] + 1.0))
            z = mi.Float(1.0)
            depth = p_light.z
        inside = (z > 0) & (uv.x >= 0) & (uv.x <= 1) & (uv.y >= 0) & (uv.y <= 1)
        return mi.UInt32(0), uv, depth, inside

    def depth_of(self, p_world: mi.Point3f) -> mi.Float:
        """Map depth of ``p_world`` (same as :meth:`project`'s, without the uv)."""
        if self.projection == "orthographic":
            fwd = mi.Transform4f(self.light_from_world.inverse()) @ mi.Vector3f(0, 0, 1)
            return dr.dot(p_world - mi.Point3f(self.position), fwd)
        return dr.norm(p_world - mi.Point3f(self.position))

    def texel_world_size(self, res: int, depth):
        """World width of one texel at ``depth`` (perpendicular to the ray)."""
        if self.projection == "orthographic":
            return dr.full(mi.Float, 2.0 * max(self.half_extent) / res, dr.width(depth))
        return depth * (2.0 * self.tan_half / res)

    def direction_to_light(self, p_world: mi.Point3f) -> mi.Vector3f:
        """Unit vector from ``p_world`` towards the light (its centre)."""
        if self.projection == "orthographic":
            fwd = mi.Transform4f(self.light_from_world.inverse()) @ mi.Vector3f(0, 0, 1)
            return -dr.normalize(fwd)
        return dr.normalize(mi.Point3f(self.position) - p_world)

    def describe(self) -> str:
        return f"{self.label}: {self.kind} light, {self.projection} map, {self.n_faces} face(s)"


# ------------------------------------------------------------------ cube maps
def _cube_dir(face, s, t) -> mi.Vector3f:
    """Light-space direction through (s, t) in [-1, 1]^2 on cube face ``face``."""
    axis = face // 2
    sign = dr.select((face & 1) == 0, 1.0, -1.0)
    # component along axis a is `sign`, along (a+1)%3 is s, along (a+2)%3 is t
    x = dr.select(axis == 0, sign, dr.select(axis == 1, t, s))
    y = dr.select(axis == 1, sign, dr.select(axis == 2, t, s))
    z = dr.select(axis == 2, sign, dr.select(axis == 0, t, s))
    return mi.Vector3f(x, y, z)


def _cube_face(d: mi.Vector3f):
    """Inverse of :func:`_cube_dir`: face, s, t and |major component|."""
    ax, ay, az = dr.abs(d.x), dr.abs(d.y), dr.abs(d.z)
    is_x = (ax >= ay) & (ax >= az)
    is_y = ~is_x & (ay >= az)
    axis = dr.select(is_x, mi.UInt32(0), dr.select(is_y, mi.UInt32(1), mi.UInt32(2)))
    major_signed = dr.select(is_x, d.x, dr.select(is_y, d.y, d.z))
    major = dr.abs(major_signed)
    face = 2 * axis + dr.select(major_signed < 0, mi.UInt32(1), mi.UInt32(0))
    u_comp = dr.select(is_x, d.y, dr.select(is_y, d.z, d.x))
    v_comp = dr.select(is_x, d.z, dr.select(is_y, d.x, d.y))
    inv = dr.rcp(dr.maximum(major, 1e-30))
    return face, u_comp * inv, v_comp * inv, major


# ----------------------------------------------------------- view creation
def _scalar3(v) -> mi.ScalarVector3f:
    """First entry of a (possibly JIT) 3-vector, as a ScalarVector3f."""
    return mi.ScalarVector3f(*(float(dr.ravel(v[k])[0]) for k in range(3)))


def _look_along(origin, forward) -> mi.ScalarTransform4f:
    """Rigid light_from_world with +z along ``forward`` and origin at ``origin``."""
    f = dr.normalize(mi.ScalarVector3f(forward))
    up = mi.ScalarVector3f(0, 1, 0) if abs(f.y) < 0.9 else mi.ScalarVector3f(1, 0, 0)
    world_from_light = mi.ScalarTransform4f().look_at(
        origin=mi.ScalarPoint3f(origin), target=mi.ScalarPoint3f(origin) + f, up=up)
    return world_from_light.inverse()


def _spot_view(emitter, label) -> LightView:
    T = emitter.world_transform()
    pos = mi.ScalarPoint3f(_scalar3(T.translation()))
    axis = _scalar3(T @ mi.Vector3f(0, 0, 1))
    cutoff = float(dr.ravel(mi.traverse(emitter)["cutoff_angle"])[0])
    if not (0.0 < cutoff < 90.0):
        # A square perspective frustum cannot cover a cone of >= 90 degrees.
        raise UnsupportedEmitterError(
            f"shadowmap: spot emitter '{label}' has cutoff_angle={cutoff}; a perspective "
            "depth map needs 0 < cutoff_angle < 90 degrees")
    return LightView("spot", "perspective", 1, pos, _look_along(pos, axis),
                     tan_half=math.tan(math.radians(cutoff)), label=label)


def _point_view(emitter, label) -> LightView:
    pos = mi.ScalarPoint3f(_scalar3(mi.traverse(emitter)["position"]))
    return LightView("point", "cube", 6, pos, mi.ScalarTransform4f(), label=label)


def _directional_view(emitter, scene, label) -> LightView:
    T = emitter.world_transform()
    d = dr.normalize(_scalar3(T @ mi.Vector3f(0, 0, 1)))
    bbox = scene.bbox()
    if not bbox.valid():
        bbox = mi.ScalarBoundingBox3f(mi.ScalarPoint3f(-1), mi.ScalarPoint3f(1))
    rot = _look_along(mi.ScalarPoint3f(0), d)
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
    return LightView("directional", "orthographic", 1, origin, _look_along(origin, d),
                     half_extent=half, depth_range=hi[2] - near + pad, label=label)


def _area_view(emitter, label) -> LightView:
    shape = emitter.get_shape()
    bbox = shape.bbox()
    centre = mi.ScalarPoint3f(bbox.center())
    ext = bbox.extents()
    # The widest extent of the shape is its size seen edge-on; issue #4 refines it.
    size = float(max(ext[0], ext[1], ext[2]))
    return LightView("area", "cube", 6, centre, mi.ScalarTransform4f(), light_size=size,
                     ignore_shape=shape, label=label)


def make_light_view(emitter, scene, index: int) -> LightView:
    """Build the :class:`LightView` of one emitter, or raise naming it."""
    label = emitter_label(emitter, index)
    kind = emitter_kind(emitter)
    if kind == "spot":
        return _spot_view(emitter, label)
    if kind == "point":
        return _point_view(emitter, label)
    if kind == "directional":
        return _directional_view(emitter, scene, label)
    if kind == "area":
        return _area_view(emitter, label)
    raise UnsupportedEmitterError(
        f"shadowmap: emitter '{label}' ({emitter_class(emitter)}) is not supported; "
        f"supported emitter types: {', '.join(SUPPORTED_EMITTERS)}"
        + ("; for environment/constant emitters set environment='unshadowed' to light "
           "them without shadows" if kind == "environment" else ""))
