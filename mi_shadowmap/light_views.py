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
  cutoff cone (half-angle = ``cutoff_angle``) in the emitter's own frame: the
  rotation of its ``to_world`` (columns normalised, Gram-Schmidt), so +z is
  the spot axis and the map's ``u``/``v`` are the emitter's local x/y.
* **Point and area** (``cube``): six 90-degree faces around the light
  position in world axes. Face ``2*a + s`` looks along axis ``a`` with sign
  ``+`` (s=0) or ``-`` (s=1); its ``u``/``v`` are the axes ``(a+1)%3`` and
  ``(a+2)%3``. Area lights (rectangle, disk, sphere, mesh) are treated as
  their shape's bounding-box centre (``hard`` and the PCF family thus see a
  point light there); the shape itself is never an occluder. Their
  ``light_size`` (used by ``pcss``) is derived from the shape by
  :func:`area_light_size`.
* **Directional** (``orthographic``): one face, aligned with the light
  direction and fitted to the scene's bounding-box corners as seen along
  the light (the tight rectangle of the projected corners, not a bounding
  sphere). A scene without valid bounds (no shapes) gets the box
  ``[-1, 1]^3`` instead -- nothing can cast a shadow there anyway.
* **Directional, cascaded** (``cascaded``, ``cascades`` > 1, see
  :func:`cascaded_view`): ``n_faces`` = cascades orthographic maps sharing the
  light direction and near plane, face ``i`` fitted to the camera-visible
  points of view-depth slice ``i`` (thesis 002, sec. 2.1.6 / 5.1); a point
  uses the face of its camera view depth (:meth:`LightView.cascade_of`).
* **Outside a map** (behind a spot, beyond a directional map's rectangle)
  ``inside`` is False and lookups treat the point as lit (Reeves 1987).
"""
from __future__ import annotations

import math
import dataclasses
from dataclasses import dataclass, field

import drjit as dr
import numpy as np
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
    light_size: float = 0.0        # world-space light width (0: a point)
    ignore_shape: object = None    # the emitter's own shape (area lights)
    label: str = ""
    extra: dict = field(default_factory=dict)

    # ----------------------------------------------------------------- build
    def texel_rays(self, res: int):
        """World-space rays through every texel centre of every face.

        Returns ``(o_world, d_world, max_t)`` with ``n_faces*res*res`` entries
        in flat texel order. ``max_t`` is always ``+inf`` (the maps have no far
        plane) and is not used by the package; it is kept only so that callers
        unpacking three values keep working.
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
        if self.projection == "cascaded":
            cx, cy, hx, hy = self._cascade(face)
            o_light = mi.Point3f(cx + s * hx, cy + t * hy, 0.0)
            return (world_from_light @ o_light, world_from_light @ mi.Vector3f(0, 0, 1),
                    mi.Float(dr.inf))
        # orthographic
        o_light = mi.Point3f(s * self.half_extent[0], t * self.half_extent[1], 0.0)
        return (world_from_light @ o_light, world_from_light @ mi.Vector3f(0, 0, 1),
                mi.Float(dr.inf))

    def ray_through(self, face, uv_light: mi.Point2f):
        """World ray ``(o_world, d_world)`` (unit ``d``) through ``uv_light`` of ``face``.

        The inverse of :meth:`project`: the point at distance ``t`` along it has
        map depth ``t``. Used by the receiver-plane depth of PCSS taps.
        """
        s = uv_light.x * 2.0 - 1.0
        t = uv_light.y * 2.0 - 1.0
        if self.projection == "cube":
            return mi.Point3f(self.position), dr.normalize(_cube_dir(mi.UInt32(face), s, t))
        world_from_light = mi.Transform4f(self.light_from_world.inverse())
        if self.projection == "perspective":
            d_light = mi.Vector3f(s * self.tan_half, t * self.tan_half, 1.0)
            return mi.Point3f(self.position), dr.normalize(world_from_light @ d_light)
        if self.projection == "cascaded":
            cx, cy, hx, hy = self._cascade(mi.UInt32(face))
            o_light = mi.Point3f(cx + s * hx, cy + t * hy, 0.0)
        else:
            o_light = mi.Point3f(s * self.half_extent[0], t * self.half_extent[1], 0.0)
        return (mi.Point3f(world_from_light @ o_light),
                dr.normalize(world_from_light @ mi.Vector3f(0, 0, 1)))

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
        if self.projection == "cascaded":
            face = self.cascade_of(p_world)
            cx, cy, hx, hy = self._cascade(face)
            uv = mi.Point2f(0.5 * ((p_light.x - cx) / hx + 1.0),
                            0.5 * ((p_light.y - cy) / hy + 1.0))
            inside = (uv.x >= 0) & (uv.x <= 1) & (uv.y >= 0) & (uv.y <= 1)
            return face, uv, p_light.z, inside
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
        if self.projection in ("orthographic", "cascaded"):
            fwd = mi.Transform4f(self.light_from_world.inverse()) @ mi.Vector3f(0, 0, 1)
            return dr.dot(p_world - mi.Point3f(self.position), fwd)
        return dr.norm(p_world - mi.Point3f(self.position))

    def texel_world_size(self, res: int, depth, p_world=None):
        """World width of one texel at ``depth`` (perpendicular to the ray).

        Cascaded maps need ``p_world`` (its cascade sets the texel size); without
        it they return the coarsest cascade's texel (a conservative bias).
        """
        if self.projection == "cascaded":
            halves = self.extra["cascade_rects"]
            if p_world is None:
                w = max(max(r[2], r[3]) for r in halves)
                return dr.full(mi.Float, 2.0 * w / res, dr.width(depth))
            _, _, hx, hy = self._cascade(self.cascade_of(p_world))
            return 2.0 * dr.maximum(hx, hy) / res
        if self.projection == "orthographic":
            return dr.full(mi.Float, 2.0 * max(self.half_extent) / res, dr.width(depth))
        return depth * (2.0 * self.tan_half / res)

    def direction_to_light(self, p_world: mi.Point3f) -> mi.Vector3f:
        """Unit vector from ``p_world`` towards the light (its centre)."""
        if self.projection in ("orthographic", "cascaded"):
            fwd = mi.Transform4f(self.light_from_world.inverse()) @ mi.Vector3f(0, 0, 1)
            return -dr.normalize(fwd)
        return dr.normalize(mi.Point3f(self.position) - p_world)

    # ------------------------------------------------------------ cascades
    def cascade_of(self, p_world) -> mi.UInt32:
        """Cascade (face) of ``p_world``: how many split depths its camera view
        depth exceeds (cascaded projection only)."""
        cam_o = mi.Point3f(*self.extra["camera_origin"])
        cam_f = mi.Vector3f(*self.extra["camera_forward"])
        z_view = dr.dot(mi.Point3f(p_world) - cam_o, cam_f)
        face = mi.UInt32(0)
        for split in self.extra["split_depths"][1:-1]:
            face += dr.select(z_view > split, 1, 0)
        return face

    def _cascade(self, face):
        """Per-face ``(cx, cy, hx, hy)`` of the light-space rectangle, gathered."""
        rects = self.extra["cascade_rects"]
        out = []
        for k in range(4):
            table = mi.Float([r[k] for r in rects])
            out.append(dr.gather(mi.Float, table, mi.UInt32(face)))
        return tuple(out)

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
    # The rotation is built at the world origin and translated afterwards: look_at(o, o + f)
    # would recover f as (o + f) - o in float32, which loses ~eps * |o| (1e-3 at 1e4 units)
    # and so breaks scale invariance for far-from-origin lights.
    world_from_light = mi.ScalarTransform4f().translate(mi.ScalarVector3f(origin)) @ \
        mi.ScalarTransform4f().look_at(origin=mi.ScalarPoint3f(0), target=mi.ScalarPoint3f(f),
                                       up=up)
    return world_from_light.inverse()


def _emitter_frame(T, origin) -> mi.ScalarTransform4f:
    """Rigid light_from_world of an emitter's own frame: the rotation of its
    ``to_world`` ``T`` (local z normalised, then local x and y made orthogonal
    to it and to each other, Gram-Schmidt; scale and shear dropped, handedness
    kept), centred at ``origin``."""
    z = np.array([float(c) for c in _scalar3(T @ mi.Vector3f(0, 0, 1))])
    x = np.array([float(c) for c in _scalar3(T @ mi.Vector3f(1, 0, 0))])
    y = np.array([float(c) for c in _scalar3(T @ mi.Vector3f(0, 1, 0))])
    z /= np.linalg.norm(z)
    x -= (x @ z) * z
    if np.linalg.norm(x) < 1e-9:   # degenerate to_world: any x orthogonal to z
        x = np.cross(z, [0.0, 1.0, 0.0] if abs(z[1]) < 0.9 else [1.0, 0.0, 0.0])
    x /= np.linalg.norm(x)
    y -= (y @ z) * z + (y @ x) * x
    if np.linalg.norm(y) < 1e-9:
        y = np.cross(z, x)
    y /= np.linalg.norm(y)
    o = np.array([float(c) for c in origin])
    m = np.eye(4)
    m[0, :3], m[1, :3], m[2, :3] = x, y, z   # rows: world -> light rotation
    m[:3, 3] = -m[:3, :3] @ o
    return mi.ScalarTransform4f(m.tolist())


def _spot_view(emitter, label) -> LightView:
    T = emitter.world_transform()
    pos = mi.ScalarPoint3f(_scalar3(T.translation()))
    cutoff = float(dr.ravel(mi.traverse(emitter)["cutoff_angle"])[0])
    if not (0.0 < cutoff < 90.0):
        # A square perspective frustum cannot cover a cone of >= 90 degrees.
        raise UnsupportedEmitterError(
            f"shadowmap: spot emitter '{label}' has cutoff_angle={cutoff}; a perspective "
            "depth map needs 0 < cutoff_angle < 90 degrees")
    return LightView("spot", "perspective", 1, pos, _emitter_frame(T, pos),
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
                     half_extent=half, label=label)


def area_light_size(shape) -> float:
    """Width of an area light as PCSS sees it (world units).

    The side of the square whose area equals the shape's area *seen from the
    receivers' side*: ``sqrt(A_proj)``, where ``A_proj`` is

    * for meshes (PLY/OBJ, and the built-in ``cube``):
      ``max(|sum_i a_i n_i|, A / 4)`` -- the length of the summed triangle
      area vectors is the area projected along the mesh's mean normal (the
      full area for a planar one-sided light); closed meshes sum to 0 and
      fall back to ``A / 4``, their mean projected area (Cauchy's formula);
    * for a disk or a rectangle (Mitsuba's ``rectangle`` is an analytic
      shape, not a mesh): its area (a disk of radius r gives ``sqrt(pi) r``);
    * for a sphere and any other shape: ``A / 4`` (a sphere gives the area of
      its silhouette disk, ``pi r^2``).

    A square light of side ``a`` thus has size ``a`` exactly, which is what
    the PCSS penumbra estimate ``w = (d_r - d_b) w_light / d_b`` assumes.
    """
    area = float(dr.ravel(shape.surface_area())[0])
    cls = emitter_class(shape)
    if shape.is_mesh() and hasattr(shape, "vertex_positions_buffer"):
        import numpy as np   # set-up time only (never in a kernel)
        v = shape.vertex_positions_buffer().numpy().reshape(-1, 3).astype("f8")
        f = shape.faces_buffer().numpy().reshape(-1, 3)
        area_vectors = 0.5 * np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
        proj = float(np.linalg.norm(area_vectors.sum(axis=0)))
        a_proj = max(proj, 0.25 * area)
    elif cls in ("Disk", "Rectangle"):
        a_proj = area
    else:
        a_proj = 0.25 * area
    return math.sqrt(max(a_proj, 0.0))


def _planar_normal(shape):
    """The emitting normal of a planar shape (all of 64 sampled normals within
    1e-3 of each other), else None (spheres, curved or closed meshes)."""
    k = dr.arange(mi.UInt32, 64)
    u = mi.Point2f((mi.Float(k % 8) + 0.5) / 8, (mi.Float(k // 8) + 0.5) / 8)
    ps = shape.sample_position(0.0, u)
    n = [ps.n.x.numpy(), ps.n.y.numpy(), ps.n.z.numpy()]
    mean = [float(c.mean()) for c in n]
    norm = math.sqrt(sum(c * c for c in mean))
    if norm < 0.999 or any(float(abs(c - m).max()) > 1e-3 for c, m in zip(n, mean)):
        return None
    return tuple(c / norm for c in mean)


def _area_view(emitter, scene, label) -> LightView:
    shape = emitter.get_shape()
    bbox = shape.bbox()
    centre = mi.ScalarPoint3f(bbox.center())
    # get_shape() is typed as the Shape base; the scene's list has the Mesh interface.
    typed = [s for s in scene.shapes() if s.emitter() is emitter] if scene is not None else []
    size = area_light_size(typed[0] if typed else shape)
    extra = {}
    normal = _planar_normal(shape)
    if normal is not None:
        extra["light_normal"] = normal
    return LightView("area", "cube", 6, centre, mi.ScalarTransform4f(), light_size=size,
                     ignore_shape=shape, label=label, extra=extra)


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
        return _area_view(emitter, scene, label)
    raise UnsupportedEmitterError(
        f"shadowmap: emitter '{label}' ({emitter_class(emitter)}) is not supported; "
        f"supported emitter types: {', '.join(SUPPORTED_EMITTERS)}"
        + ("; for environment/constant emitters set environment='unshadowed' to light "
           "them without shadows" if kind == "environment" else ""))


# ------------------------------------------------------------ cascaded maps
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


def cascaded_view(view: LightView, scene, sensor, cascades: int, split_lambda: float,
                  margin_texels: float = 4.0, res: int | None = 1024,
                  points: np.ndarray | None = None) -> LightView:
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
    unchanged for 1 cascade, a non-directional view, or a camera that sees
    nothing.
    """
    if cascades <= 1 or view.projection != "orthographic" or sensor is None:
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
    L = np.array(view.light_from_world.matrix, dtype=np.float64)
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
    extra = dict(view.extra)
    extra.update(cascade_rects=tuple(rects), split_depths=tuple(splits),
                 camera_origin=tuple(float(x) for x in cam_o),
                 camera_forward=tuple(float(x) for x in cam_f))
    return dataclasses.replace(view, projection="cascaded", n_faces=int(cascades), extra=extra)


# ------------------------------------------------------- automatic resolution
def footprint_ratio(scene, sensor, views) -> float:
    """Texel width over camera pixel width at the scene's centre (max over lights).

    Per unit resolution: a spot map spans ``2 tan(cutoff) d`` at distance
    ``d`` from the light, a cube face ``2 d``, an orthographic map its width;
    a cascaded directional map its largest cascade's width (the coarsest
    texels); a perspective camera spans ``2 tan(x_fov / 2) d_cam`` per unit film width.
    ``d`` and ``d_cam`` are measured to the centre of the scene's bounding
    box. Returns 1 when it cannot be computed (no bounds, not a perspective
    camera, a projection this does not know). Used by the automatic
    ``resolution`` (:meth:`~mi_shadowmap.options.Options.map_resolution`).
    """
    bbox = scene.bbox()
    if sensor is None or not bbox.valid():
        return 1.0
    centre = np.array([float(c) for c in bbox.center()])
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
    widths = []
    for v in views:
        if v is None:
            continue
        d = np.linalg.norm(centre - np.array([float(c) for c in v.position]))
        if v.projection == "perspective":
            widths.append(2.0 * v.tan_half * d)
        elif v.projection == "cube":
            widths.append(2.0 * d)
        elif v.projection == "orthographic":
            widths.append(2.0 * max(v.half_extent))
        elif v.projection == "cascaded":
            widths.append(2.0 * max(max(r[2], r[3]) for r in v.extra["cascade_rects"]))
    return max(widths) / cam_width if widths else 1.0


# ------------------------------------------------------------ fitted frusta
def fit_view(view, p_world: np.ndarray, margin: float):
    """``(view fitted to the visible points, texel density gain)``.

    Only the points inside the original map are kept (the others get no
    light from a spot, or are lit by convention). Perspective (spot): a square
    frustum re-aimed at the mean direction of those points, with the smallest
    ``tan_half`` covering them; orthographic (directional): the light-space
    rectangle of their xy, same direction and near plane. Both grow by
    ``margin`` (a fraction of the window) per side for normal offsets and
    filter taps. A caster can only shadow a visible receiver along the light
    ray to it, which crosses the same (u, v): casters are kept (Reeves' and
    Filament's fitting of the frustum to what matters, restricted to what
    the camera sees). The gain is the ratio of texel areas (old / new) at the
    same resolution. The original view is returned (gain 1) if nothing is
    gained or the fit is not possible.
    """
    if len(p_world) == 0 or view.projection not in ("perspective", "orthographic"):
        return view, 1.0
    L = np.array(view.light_from_world.matrix, dtype=np.float64)
    p_l = p_world @ L[:3, :3].T + L[:3, 3]
    pos = np.array([float(c) for c in view.position])
    if view.projection == "perspective":
        z = p_l[:, 2]
        keep = (z > 0) & (np.abs(p_l[:, 0]) <= view.tan_half * z) \
            & (np.abs(p_l[:, 1]) <= view.tan_half * z)
        if not keep.any():
            return view, 1.0
        dirs = p_world[keep] - pos
        dirs /= np.maximum(np.linalg.norm(dirs, axis=1, keepdims=True), 1e-30)
        axis = dirs.mean(axis=0)
        if np.linalg.norm(axis) < 1e-6:
            return view, 1.0
        new_lfw = _look_along_light(pos, axis / np.linalg.norm(axis))
        M = np.array(new_lfw.matrix, dtype=np.float64)
        q = p_world[keep] @ M[:3, :3].T + M[:3, 3]
        if np.any(q[:, 2] <= 1e-9 * np.abs(q).max()):
            return view, 1.0
        tan = float(np.max(np.abs(q[:, :2]) / q[:, 2:3]))
        tan = max(tan * (1.0 + 2.0 * margin), 1e-6 * view.tan_half)
        if tan >= view.tan_half:
            return view, 1.0
        return (dataclasses.replace(view, light_from_world=new_lfw, tan_half=tan),
                (view.tan_half / tan) ** 2)
    hx, hy = view.half_extent
    keep = (np.abs(p_l[:, 0]) <= hx) & (np.abs(p_l[:, 1]) <= hy)
    if not keep.any():
        return view, 1.0
    lo, hi = p_l[keep, :2].min(axis=0), p_l[keep, :2].max(axis=0)
    centre = 0.5 * (lo + hi)
    size = max(hx, hy)
    half = 0.5 * (hi - lo) + 2.0 * margin * np.maximum(0.5 * (hi - lo), 1e-3 * size)
    half = np.maximum(half, 1e-6 * size)
    if max(half) >= max(hx, hy):
        return view, 1.0
    W = np.linalg.inv(L)
    origin = W[:3, :3] @ np.array([centre[0], centre[1], 0.0]) + W[:3, 3]
    fwd = W[:3, :3] @ np.array([0.0, 0.0, 1.0])
    new_lfw = _look_along_light(origin, fwd)
    return (dataclasses.replace(view, position=mi.ScalarPoint3f(*origin),
                                light_from_world=new_lfw,
                                half_extent=(float(half[0]), float(half[1]))),
            (max(hx, hy) / float(max(half))) ** 2)


def _look_along_light(origin, forward):
    return _look_along(mi.ScalarPoint3f(*[float(c) for c in origin]),
                       mi.ScalarVector3f(*[float(c) for c in forward]))


# --------------------------------------------------------- cube-face culling
def camera_visible_points(scene, sensor) -> np.ndarray:
    """World points the camera sees: one ray through every pixel centre, ``(N, 3)``."""
    if sensor is None:
        return np.zeros((0, 3))
    w, h = (int(x) for x in sensor.film().crop_size())
    idx = dr.arange(mi.UInt32, w * h)
    y = idx // w
    x = idx - y * w
    pos = mi.Point2f((mi.Float(x) + 0.5) / w, (mi.Float(y) + 0.5) / h)
    ray, _ = sensor.sample_ray(0.0, 0.5, pos, mi.Point2f(0.5))
    si = scene.ray_intersect(ray)
    p = np.stack([si.p.x.numpy(), si.p.y.numpy(), si.p.z.numpy()], axis=1)
    return p[si.is_valid().numpy()]


def cube_faces_needed(view, p_world: np.ndarray, margin: float) -> tuple:
    """Which of the 6 faces (``2*axis + (sign < 0)``) the points project into.

    A point within ``margin`` (in the face's [-1, 1] coordinates) of a face
    edge also needs the neighbour across that edge (normal offsets and
    sub-pixel camera samples may cross it).
    """
    need = [False] * 6
    if len(p_world) == 0:
        return tuple(need)
    d = p_world - np.array([float(c) for c in view.position])
    a = np.abs(d)
    major = np.argmax(a, axis=1)
    m = np.maximum(a[np.arange(len(d)), major], 1e-30)
    for axis in range(3):
        for sign in (0, 1):
            face_pts = (major == axis) & ((d[:, axis] < 0) == bool(sign))
            need[2 * axis + sign] |= bool(face_pts.any())
            # neighbours: points of other faces within `margin` of this face's direction
            near = (a[:, axis] >= m * (1.0 - margin)) & ((d[:, axis] < 0) == bool(sign))
            need[2 * axis + sign] |= bool(near.any())
    return tuple(need)
