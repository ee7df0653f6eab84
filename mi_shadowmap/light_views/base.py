"""The :class:`LightView` interface every map builder and filter uses, and frame helpers.

A light view is the camera (or cameras: its *faces*) through which one
emitter's depth map is rendered. Every operation that depends on how a light
projects is a method here, implemented once per projection in its own
module; the map manager and the filters call these methods and never ask
which kind of view they hold.

Conventions shared by every view
--------------------------------
* **Depth** is the ``t`` of the texel's ray, in world units: the distance
  from the light position (spot, point, area), or from the light's near
  plane along the light direction (directional). Map values and receiver
  depths are compared in this one space.
* **Texels.** Face ``f`` of resolution ``r`` stores texel ``(i, j)`` at flat
  index ``f*r*r + j*r + i``; its centre is ``uv = ((i+0.5)/r, (j+0.5)/r)``.
  A point looks up the texel ``floor(uv * r)`` (nearest texel).
* **Outside a map** (behind a spot, beyond a directional map's rectangle)
  ``inside`` is False and lookups treat the point as lit (Reeves 1987).
"""
from __future__ import annotations

import collections
import weakref
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np


@dataclass(frozen=True)
class LightView:
    """The map faces of one emitter and how world points project into them.

    Fields shared by every view: ``kind`` (the emitter kind: 'spot', 'point',
    'directional', 'area'), ``position`` (the light position; the near-plane
    centre of a directional light), ``light_from_world`` (rigid, +z along the
    view direction; the identity for cube views), ``light_size`` (world width
    of the light, 0 for a point), ``ignore_shape`` (the emitter's own shape,
    which never occludes it), ``light_normal`` (the emitting normal of a
    planar one-sided area light, else None), ``label`` and ``light_axes`` (a planar
    area light's two world half-axes, :func:`~mi_shadowmap.light_views.area_light_axes`,
    for PCSS's kernels; else None).
    """
    kind: str
    position: mi.ScalarPoint3f
    light_from_world: mi.ScalarTransform4f
    light_size: float = 0.0
    ignore_shape: object = None
    light_normal: tuple | None = None
    label: str = ""
    light_axes: tuple | None = None

    #: A short name of the projection, for messages and file names only.
    projection = "abstract"
    #: Every texel's ray leaves one point, the light's position (perspective and cube
    #: maps): a plane that a ray meets at a distance <= 0 lies behind the light along
    #: it, and the ray never reaches it. Parallel rays (orthographic maps) start on a
    #: plane before the scene: a negative depth is a real one there.
    rays_from_point = False
    #: Whether a face's edge is a seam with a neighbouring face, on which a tap off the
    #: face continues (cube maps, :meth:`tap_texel`); else a tap off a face is off the
    #: map (``inside`` False: lit), also where the view has several faces (cascades, an
    #: environment's regions).
    has_seams = False

    # ----------------------------------------------------------- the interface
    @property
    def n_faces(self) -> int:
        raise NotImplementedError

    def ray_through(self, face, uv_light: mi.Point2f):
        """World ray ``(o_world, d_world)`` (unit ``d``) through ``uv_light`` of ``face``.

        The inverse of :meth:`project`: the point at distance ``t`` along it has
        map depth ``t``.
        """
        raise NotImplementedError

    def ray_plane(self, face, uv_light: mi.Point2f, p_world, n_world, cos_min: float):
        """``(t, cos)``: the map depth ``t`` at which the ray through ``uv_light`` of
        ``face`` meets the plane through ``p_world`` with normal ``n_world``, and
        ``cos = dot(n_world, d)``; where ``|cos| < cos_min`` the division uses
        ``cos_min`` (the caller decides what a near-parallel plane means)."""
        o, d = self.ray_through(face, uv_light)
        c = dr.dot(n_world, d)
        t = dr.dot(n_world, mi.Point3f(p_world) - o) / dr.select(dr.abs(c) >= cos_min, c,
                                                                  cos_min)
        return t, c

    def texel_rays(self, res: int):
        """World rays ``(o_world, d_world)`` through every texel centre of every face,
        ``n_faces * res * res`` entries in flat texel order (the map builders' input)."""
        raise NotImplementedError

    def texel_rays_at(self, res: int, idx):
        """The rays of :meth:`texel_rays` of the texels ``idx`` only (``mi.UInt32`` flat
        texel indices): bit-identical values. This default gathers them out of every
        texel's rays; views whose rays follow from the index compute only these."""
        o, d = self.texel_rays(res)
        if dr.width(o) > 1:
            o = dr.gather(mi.Point3f, o, idx)
        return o, dr.gather(mi.Vector3f, d, idx)

    def built_texels(self, res: int):
        """The texels a build of this view ray-casts, where not all of them:
        ``(idx, faces)``, ``idx`` their flat indices (``mi.UInt32``, maybe unevaluated)
        and ``faces`` how many faces hold at least one; None: every texel. The others
        are +inf and no lookup reads them (:class:`~.multi.MultiView`: the texels
        behind a one-sided light)."""
        return None

    def project(self, p_world: mi.Point3f):
        """``p_world`` -> ``(face, uv_light, depth, inside)``; ``uv_light`` in [0, 1]^2
        on the face when ``inside``."""
        raise NotImplementedError

    def uv_on_face(self, face, p_world: mi.Point3f) -> mi.Point2f:
        """``uv_light`` of ``p_world`` on a *given* face, even off that face.

        Footprints need the projection onto the receiver's face, so that
        ``p + dp`` across a cube seam or a cascade split does not jump to
        another face. Views with one face return :meth:`project`'s uv.
        """
        return self.project(p_world)[1]

    def depth_of(self, p_world: mi.Point3f) -> mi.Float:
        """Map depth of ``p_world`` (:meth:`project`'s, without the uv)."""
        return dr.norm(p_world - opaque_point(self.position))

    def texel_world_size(self, res: int, depth, p_world=None, n_world=None):
        """World width of one texel at ``depth`` (perpendicular to the ray);
        ``p_world`` selects the face where faces differ in size (cascades). Where a
        face's texels are not square (an orthographic rectangle), ``n_world`` (the
        receiver's normal) picks the width along the receiver's depth gradient (see
        :func:`texel_width_along`); without it, the longer side."""
        raise NotImplementedError

    def texel_parallel_size(self, res: int, face, p_world: mi.Point3f, texel_world):
        """World width of a texel at ``p_world`` measured parallel to ``face``'s image
        plane (``texel_world``: :meth:`texel_world_size` there). Similar triangles
        between planes parallel to the light (PCSS) hold in this width."""
        raise NotImplementedError

    def texel_parallel_xy(self, res: int, face, p_world: mi.Point3f, texel_world):
        """``(w_x, w_y)``: a texel's world widths at ``p_world`` along ``face``'s image
        x and y, parallel to its image plane, where its texels are not square (a
        rectangular face: :meth:`texel_parallel_size` is then the width along the
        receiver's depth gradient, which sizes depth biases but not a kernel of a
        world width, PCSS's); None where they are square (this default)."""
        return None

    def direction_to_light(self, p_world: mi.Point3f) -> mi.Vector3f:
        """Unit vector from ``p_world`` towards the light (its centre)."""
        return dr.normalize(opaque_point(self.position) - p_world)

    def direction_to_light_on_face(self, face, p_world: mi.Point3f) -> mi.Vector3f:
        """Unit vector from ``p_world`` towards the light point that ``face``'s map is
        seen from (one light point for every face here; views of several light points
        tell each face's own, :class:`~mi_shadowmap.light_views.multi.MultiView`)."""
        return self.direction_to_light(p_world)

    def tap_texel(self, face, xy_texel: mi.Point2f, res: int, cross_seams: bool = True):
        """Texel hit by a filter tap at continuous texel coordinates ``xy_texel``
        (``uv_light * res``) of ``face``: ``(face, i, j, inside)``.

        A tap off a face with no neighbour is ``inside`` False (lit, blocks
        nothing: Reeves 1987). Views whose faces have neighbours (cube maps)
        continue on the neighbouring face, or with ``cross_seams`` False clamp
        to the face's border texel.
        """
        ij = mi.Point2i(dr.floor(xy_texel))
        in_face = (ij.x >= 0) & (ij.x < res) & (ij.y >= 0) & (ij.y < res)
        return mi.UInt32(face), ij.x, ij.y, in_face

    def light_width(self, light_size=None, angular_diameter: float = 0.0):
        """``(width, angular)`` of the light for soft shadows: its world width
        (``light_size`` when given, else the emitter's own), or for directional
        lights ``2 tan(angular_diameter / 2)`` with ``angular`` True."""
        if light_size is not None:
            return float(light_size), False
        return float(self.light_size), False

    def map_width(self, p_world: np.ndarray) -> float:
        """World width one face spans per unit of resolution near ``p_world`` (numpy):
        the texel width at resolution 1 (the automatic resolution's footprint)."""
        raise NotImplementedError

    # ------------------------------------------------- float64 (virtual maps)
    # Virtual maps (:mod:`mi_shadowmap.virtual`) address up to 2^31 texels per face side,
    # beyond float32's 24 bits: they project and build their texel rays through these
    # float64 forms of project / uv_on_face / ray_through. Views that do not provide
    # them cannot be virtual (``supports_virtual`` False).
    supports_virtual = False
    #: Where the map's depths start along each texel's ray: 0 (from the light) for every
    #: view but a virtual map's local frame of a far light
    #: (:class:`~.local.LocalView`), whose depths start near the scene. A map depth plus
    #: this is the distance from the light.
    depth_origin = 0.0

    def project_f64(self, p_world):
        """:meth:`project` in float64: ``(face, uv_light: Point2d, depth: Float64, inside)``."""
        raise NotImplementedError

    def uv_on_face_f64(self, face, p_world):
        """:meth:`uv_on_face` in float64 (a ``mi.Point2d``)."""
        raise NotImplementedError

    def ray_through_f64(self, face, uv_light):
        """:meth:`ray_through` in float64: ``(o_world: Point3d, d_world: Vector3d)``."""
        raise NotImplementedError

    #: Optional: ``ray_frame_f64(face, uv_light: Point2d) -> (central, base, d_du, d_dv)``,
    #: the rays of ``face`` near ``uv_light`` as an affine function of ``uv`` (float32
    #: world vectors, per unit of ``uv``). ``central`` (a Python bool): every ray starts at
    #: the light's position and its *unnormalised* direction is ``base + du d_du + dv d_dv``
    #: (perspective and cube faces); else every ray has the unit direction ``base`` and its
    #: origin moves by ``du d_du + dv d_dv`` (orthographic). A virtual map's local frame
    #: (:meth:`~.local.LocalView.ray_plane`) then meets a filter tap's ray with the
    #: receiver's plane in float32 relative to the receiver's own ray. None: float64 rays.
    ray_frame_f64 = None

    def uv_differential(self, face, p_world, dp_world) -> mi.Point2f:
        """``d uv_light`` on ``face`` for a small step ``dp_world`` at ``p_world`` (the
        first-order change, in float32: no difference of two nearby float64 ``uv``
        is needed, so it stays accurate however large the virtual resolution). The
        default differentiates :meth:`uv_on_face_f64` numerically."""
        p64 = mi.Point3d(p_world)
        return mi.Point2f(self.uv_on_face_f64(face, p64 + mi.Vector3d(dp_world))
                          - self.uv_on_face_f64(face, p64))

    def depth_differential(self, p_world, dp_world) -> mi.Float:
        """First-order change of the map depth of ``p_world`` for a small step
        ``dp_world`` (float32; for views projecting through a centre, the step along
        the direction from the light)."""
        return dr.dot(mi.Vector3f(dp_world), -self.direction_to_light(p_world))

    def face_texel_f64(self, face, xy_texel, res):
        """A texel at float64 continuous coordinates ``xy_texel`` of ``face`` (resolution
        ``res``, possibly per lane), continued on the neighbouring face where faces have
        neighbours: ``(face, i, j, inside)`` with ``mi.Int32`` texel coordinates (the
        float64 form of :meth:`tap_texel`)."""
        ij = mi.Point2i(dr.floor(xy_texel))
        in_face = (ij.x >= 0) & (ij.x < res) & (ij.y >= 0) & (ij.y < res)
        return mi.UInt32(face), ij.x, ij.y, in_face

    # ------------------------------------------- camera-dependent refinements
    def needs_camera_points(self, opts) -> bool:
        """Whether :meth:`refine` or :meth:`faces_needed` read camera-visible points."""
        return False

    def planned_faces(self, opts, visible) -> int:
        """Faces of the view :meth:`refine` will return (known before the resolution)."""
        return self.n_faces

    def refine(self, opts, scene, sensor, visible, res):
        """The view for this render once the resolution is known: cascades or a
        frustum fitted to the camera-visible points (``opts``), and the texel
        density gain (texel area before / after; None when not fitted)."""
        return self, None

    def refine_for_footprint(self, opts, scene, sensor, visible):
        """The view whose :meth:`map_width` sets the automatic resolution."""
        return self

    def faces_needed(self, opts, visible, res):
        """The faces a render reads (a tuple of bools), or None for all of them."""
        return None

    def describe(self) -> str:
        return f"{self.label}: {self.kind} light, {self.projection} map, {self.n_faces} face(s)"


# ------------------------------------------------------------- frame helpers
def scalar3(v) -> mi.ScalarVector3f:
    """First entry of a (possibly JIT) 3-vector, as a ScalarVector3f."""
    return mi.ScalarVector3f(*(float(dr.ravel(v[k])[0]) for k in range(3)))


def look_along(origin, forward) -> mi.ScalarTransform4f:
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


def look_along_np(origin, forward) -> mi.ScalarTransform4f:
    """:func:`look_along` from numpy/sequence arguments."""
    return look_along(mi.ScalarPoint3f(*[float(c) for c in origin]),
                      mi.ScalarVector3f(*[float(c) for c in forward]))


def emitter_frame(T, origin) -> mi.ScalarTransform4f:
    """Rigid light_from_world of an emitter's own frame: the rotation of its
    ``to_world`` ``T`` (local z normalised, then local x and y made orthogonal
    to it and to each other, Gram-Schmidt; scale and shear dropped, handedness
    kept), centred at ``origin``."""
    z = np.array([float(c) for c in scalar3(T @ mi.Vector3f(0, 0, 1))])
    x = np.array([float(c) for c in scalar3(T @ mi.Vector3f(1, 0, 0))])
    y = np.array([float(c) for c in scalar3(T @ mi.Vector3f(0, 1, 0))])
    if not np.linalg.norm(z) > 0:   # a zero or NaN direction: a NaN frame, which the
        return mi.ScalarTransform4f(np.full((4, 4), np.nan))  # caller refuses by name
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


def pow2_reciprocal(res, float_type=None):
    """``1 / res`` for a per-lane power of two ``res`` (a Dr.Jit integer array, 1 to
    2^126), exactly and without a division: ``2^k`` has the bits ``(bias + k) << m``,
    so ``2^-k`` is ``(2 bias << m)`` minus them (``float_type``: ``mi.Float``, the
    default, or ``mi.Float64``)."""
    if float_type is mi.Float64:
        bits = dr.reinterpret_array(mi.UInt64, mi.Float64(res))
        return dr.reinterpret_array(mi.Float64, mi.UInt64(2046 << 52) - bits)
    bits = dr.reinterpret_array(mi.UInt32, mi.Float(res))
    return dr.reinterpret_array(mi.Float, mi.UInt32(254 << 23) - bits)


def divide_by_res(x, res):
    """``x / res`` for a map resolution ``res``: a full map's (a Python ``int``), or per
    lane a virtual map's level resolution (a Dr.Jit integer array, always a power of
    two: so are ``resolution`` and ``page_size``), as ``x`` times
    :func:`pow2_reciprocal`. The same value: dividing by ``2^k`` and multiplying by
    ``2^-k`` round the same exact quotient. A 16-lane float32 division holds the
    divider for about 10 cycles; the level's divisions were 4 of the 26 divider
    operations a packet of a directional light's virtual ``hard`` lookup (with
    :meth:`~.local.LocalView._to_local_uv`'s; ``benchmarks/RESULTS.md``, 2026-12-06)."""
    if isinstance(res, (int, np.integer)) or not dr.is_integral_v(res):
        return x / res
    return x * pow2_reciprocal(res)


def axial_texel_size(view, res: int, face, p_world):
    """:meth:`LightView.texel_parallel_size` of a view projecting through a centre
    (perspective, cube): the texel width at the point's *axial* depth along the
    face's view axis, ``z_axial * 2 tan_half / res``."""
    o, axis = view.ray_through(face, mi.Point2f(0.5, 0.5))
    z_axial = dr.dot(mi.Point3f(p_world) - o, axis)
    # opaque: a spot's new cutoff compiles no kernel
    return z_axial * divide_by_res(opaque_scalar(2.0 * view.tan_half), res)


def transform_f64(m: np.ndarray, p, point: bool = True):
    """``m @ p`` for a float64 numpy 4x4 ``m`` and a ``mi.Point3d``/``mi.Vector3d`` ``p``
    (the affine part only; rigid and affine light transforms need no division). The
    matrix enters kernels as opaque values (:func:`opaque_matrix64`)."""
    e = opaque_matrix64(m)
    out = []
    for r in range(3):
        v = p[0] * e[r][0] + p[1] * e[r][1] + p[2] * e[r][2]
        out.append(v + e[r][3] if point else v)
    return (mi.Point3d if point else mi.Vector3d)(*out)


#: Per mesh state, for :func:`shape_bounds` and :func:`triangle_magnitudes`:
#: ``{(id(shape), vertex buffer index, face buffer index): [buffers, bounds, per-face]}``.
#: The buffers are held, so their JIT indices cannot be reused by other arrays while
#: the entry lives. Least recently used entries go first beyond
#: :data:`_MESH_MEMO_SIZE` (a scene's every mesh fits: with 64 entries, a scene of 100
#: meshes read every vertex buffer on each call, 70 times slower); emptied by
#: :func:`~mi_shadowmap.map_manager.clear_caches`.
_MESH_MEMO = collections.OrderedDict()
_MESH_MEMO_SIZE = 4096


def remember_latest(memo: collections.OrderedDict, latest: dict, key: tuple, value,
                    limit: int):
    """``memo[key] = value`` for a per-mesh-state memo keyed ``(id(shape), buffer
    indices...)``, keeping only each shape's latest state (``latest``: ``id(shape)`` ->
    its key in ``memo``): an edited mesh's earlier entry, which holds its earlier
    buffers, is dropped. Without that, a mesh deformed every frame kept every frame's
    vertex buffer until ``limit`` entries (a 90k-vertex mesh: +1.1 MB a frame with
    ``hard``, +2 MB with ``second_depth``)."""
    old = latest.get(key[0])
    if old is not None and old != key:
        memo.pop(old, None)
    while len(memo) >= limit:
        gone = memo.popitem(last=False)[0]
        if latest.get(gone[0]) == gone:
            del latest[gone[0]]
    memo[key] = value
    latest[key[0]] = key
    return value


#: ``id(shape)`` -> its latest key in :data:`_MESH_MEMO` (:func:`remember_latest`).
_MESH_LATEST: dict = {}


def _mesh_entry(shape) -> list:
    vbuf, fbuf = shape.vertex_positions_buffer(), shape.faces_buffer()
    key = (id(shape), vbuf.index, fbuf.index)
    hit = _MESH_MEMO.get(key)
    if hit is None:
        hit = remember_latest(_MESH_MEMO, _MESH_LATEST, key, [(vbuf, fbuf), False, None], _MESH_MEMO_SIZE)
    else:
        _MESH_MEMO.move_to_end(key)
    return hit


def clear_memos() -> None:
    """Forget every mesh's remembered bounds and per-face magnitudes, and the opaque
    values of light positions and frames (:func:`opaque_point`, ...)."""
    _MESH_MEMO.clear()
    _MESH_LATEST.clear()
    _OPAQUE.clear()
    _VIEW_MEMO.clear()


def triangle_magnitudes(shape) -> np.ndarray:
    """Per face of a mesh, the largest absolute coordinate of its three vertices
    (float32): the scale of a ray-triangle intersection's rounding there (remembered
    as :func:`shape_bounds`)."""
    entry = _mesh_entry(shape)
    if entry[2] is None:
        v = np.abs(entry[0][0].numpy().reshape(-1, 3)).max(axis=1)
        f = entry[0][1].numpy().reshape(-1, 3)
        entry[2] = (v[f].max(axis=1) if len(f) else np.zeros(0)).astype(np.float32)
    return entry[2]


def shape_bounds(shape):
    """``(lo, hi)`` (numpy float64) of one shape, or None when unknown (an empty mesh, an
    invalid bbox).

    A mesh is bounded by its vertex positions, not its ``bbox()``: Mitsuba 3.9 merges
    meshes that share a BSDF (e.g. every shape given ``{"type": "diffuse"}``) into one
    mesh whose ``bbox()`` is that of only some of its parts (a merged rectangle is left
    out) or invalid, and ``scene.bbox()`` follows it. Measured: a wall of such a scene
    left out of the directional map's box lost its shadow (1.06 % of the pixels
    misclassified). The bounds are remembered per vertex buffer (its JIT index), so an
    unchanged mesh costs a dict lookup; a changed one (``params.update()``) one pass over
    its vertices."""
    if shape.is_mesh() and hasattr(shape, "vertex_positions_buffer"):
        entry = _mesh_entry(shape)
        if entry[1] is False:
            v = entry[0][0].numpy().reshape(-1, 3)
            # vertices that are not finite (an optimizer's step gone wrong) bound nothing:
            # Embree drops their triangles, so no ray (direct's, the maps') hits them, and
            # an infinite box made a directional light's frame NaN (refused as "direction
            # zero or not finite") and a virtual layout's level count NaN (a ValueError)
            v = v[np.isfinite(v).all(axis=1)]
            entry[1] = ((v.min(axis=0).astype(np.float64), v.max(axis=0).astype(np.float64))
                        if len(v) else None)
        return entry[1]
    b = shape.bbox()
    if not b.valid():
        return None
    return (np.array([float(c) for c in b.min]), np.array([float(c) for c in b.max]))


def scene_bounds(scene, exclude=None):
    """``(lo, hi)`` (numpy float64) of every shape of ``scene`` but ``exclude`` (a
    shape, e.g. an area light's own), or None without any.

    Not ``scene.bbox()``: Mitsuba 3.9's merged meshes report wrong boxes, and the scene's
    box follows them (:func:`shape_bounds`)."""
    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
    # the scene's copy of an emitter's shape is another object (Mitsuba 3.9 turns a
    # rectangle into a mesh): matched through its emitter, as cube.area_view does
    own = exclude.emitter() if exclude is not None else None
    for shape in scene.shapes():
        if exclude is not None and (shape == exclude
                                    or (own is not None and shape.emitter() is own)):
            continue
        b = shape_bounds(shape)
        if b is not None:
            lo = np.minimum(lo, b[0])
            hi = np.maximum(hi, b[1])
    return (lo, hi) if np.all(lo <= hi) else None


def light_matrix(view) -> np.ndarray:
    """``light_from_world`` as a float64 numpy 4x4 matrix (read-only: kept per view,
    :func:`view_memo`)."""
    return view_memo(view, "light_matrix", lambda: _read_only(
        np.array(view.light_from_world.matrix, dtype=np.float64)))


def world_matrix(view) -> np.ndarray:
    """The inverse of :func:`light_matrix` (``np.linalg.inv``; read-only, kept per view)."""
    return view_memo(view, "world_matrix",
                     lambda: _read_only(np.linalg.inv(light_matrix(view))))


def opaque_light_from_world(view):
    """:func:`opaque_transform` of the view's ``light_from_world``, kept per view."""
    return view_memo(view, (mi.variant(), "light_from_world"),
                     lambda: opaque_transform(view.light_from_world))


def opaque_world_from_light(view):
    """:func:`opaque_transform` of the inverse of the view's ``light_from_world``, kept
    per view."""
    return view_memo(view, (mi.variant(), "world_from_light"),
                     lambda: opaque_transform(view.light_from_world.inverse()))


#: Per light view (by ``id``; the view held weakly, its entry dropped with it): values
#: derived from its (frozen) fields, :func:`view_memo`.
_VIEW_MEMO: dict = {}


def view_memo(view, name, make):
    """``make()`` for ``view`` and ``name``, computed once per view object. A view is a
    frozen dataclass whose transforms every lookup, mark and page cast reads while it
    is traced: each conversion of a ``ScalarTransform4f`` to numpy, its inverse, and
    :func:`opaque_transform`'s key took 8-20 us, 18-26 of them a camera move's frame
    on large_world's directional light (the render kernel's 13 of them a still
    frame's)."""
    key = id(view)
    slot = _VIEW_MEMO.get(key)
    if slot is None or slot[0]() is not view:
        def drop(ref, key=key):
            if _VIEW_MEMO.get(key, (None,))[0] is ref:
                del _VIEW_MEMO[key]
        slot = _VIEW_MEMO[key] = (weakref.ref(view, drop), {})
    memo = slot[1]
    if name not in memo:
        memo[name] = make()
    return memo[name]


def _read_only(a: np.ndarray) -> np.ndarray:
    a.flags.writeable = False
    return a


def position_np(view) -> np.ndarray:
    return np.array([float(c) for c in view.position])


#: :func:`opaque_point`, :func:`opaque_scalar`, :func:`opaque_transform` and
#: :func:`opaque_matrix64` per (variant, kind, value): at most this many kept.
_OPAQUE: dict = {}
_OPAQUE_SIZE = 256


def _memo(key, make):
    hit = _OPAQUE.get(key)
    if hit is None:
        if len(_OPAQUE) >= _OPAQUE_SIZE:
            del _OPAQUE[next(iter(_OPAQUE))]
        hit = _OPAQUE[key] = make()
    return hit


def opaque_scalar(value: float, double: bool = False):
    """``value`` as an opaque ``mi.Float`` (``mi.Float64`` with ``double``), as
    :func:`opaque_point` (a view's half extent or field of view)."""
    v = float(value)
    return _memo((mi.variant(), "s", bool(double), v),
                 lambda: dr.opaque(mi.Float64 if double else mi.Float, v))


def opaque_transform(t):
    """A scalar transform (``mi.ScalarTransform4f``) as a ``mi.Transform4f`` whose matrix
    and inverse transpose are opaque (the same values as ``mi.Transform4f(t)``, which
    bakes them into the kernels), as :func:`opaque_point`. A JIT transform (a view's
    per-lane frame) is returned as it is, converted."""
    if not isinstance(t, mi.ScalarTransform4f):
        return mi.Transform4f(t)
    M = np.array(t.matrix, dtype=np.float64)
    IT = np.array(t.inverse_transpose, dtype=np.float64)

    def make():
        m, it = (mi.Matrix4f(*[[float(A[r, c]) for c in range(4)] for r in range(4)])
                 for A in (M, IT))
        dr.make_opaque(m, it)
        return mi.Transform4f(m, it)
    return _memo((mi.variant(), "t", M.tobytes(), IT.tobytes()), make)


def opaque_matrix64(m: np.ndarray):
    """The first three rows of a float64 4x4 matrix as opaque ``mi.Float64`` values
    (``[row][column]``), as :func:`opaque_point`."""
    m = np.asarray(m, dtype=np.float64)
    return _memo((mi.variant(), "m64", m[:3].tobytes()),
                 lambda: [[dr.opaque(mi.Float64, float(m[r, c])) for c in range(4)]
                          for r in range(3)])


def opaque_point(value, double: bool = False):
    """``value`` (3 numbers) as an opaque ``mi.Point3f`` (``mi.Point3d`` with
    ``double``): a JIT input of the kernels that read it, not a literal in their code,
    so a light moved through ``params.update()`` compiles no new kernel. The same
    variable serves every call with the same value (the last 256 values are kept). A
    JIT ``value`` (a view's per-lane position, e.g. a multi-view's light points) is
    returned as it is, converted."""
    if dr.is_jit_v(type(value)):
        return (mi.Point3d if double else mi.Point3f)(value)
    # map, not a generator expression: a light view's position is read this way about 30
    # times a frame per light when the lookups and the mark pass are traced (a generator
    # took 2-5 us of a call's 3-11)
    v = tuple(map(float, value))
    return _memo((mi.variant(), "p", bool(double), v),
                 lambda: dr.opaque(mi.Point3d if double else mi.Point3f, v))


#: Where each depth-map ray crosses its texel, in texels from the texel's corner: the
#: centre moved by a fixed sub-texel offset (1/81 and 1/120 of a texel, not a ratio
#: of small integers). Texel centres lie exactly on a face's diagonals (s = +-t),
#: on its axes at odd resolutions, and on lines s = p/q t: planes through the
#: light. Geometry placed symmetrically about the light has mesh edges in those
#: planes (a box centred on a light, a cube's face diagonal under a light above
#: its centre), and Embree, Mitsuba's CPU ray tracer, is not watertight exactly
#: on a shared edge: such rays pass between the two triangles. Measured: a point
#: light at the centre of a closed cube (20 placements, half-sizes 0.1-0.7)
#: lost 0-87 texels each to the floor behind, a line of light across a closed
#: box's shadow; 597 texels in all, 0 with this offset. The offset (~0.01 texel)
#: is far below the depth biases (>= 0.5 texel); every reader of a texel's ray
#: (:func:`unit_grid`, the page builder, receiver planes, virtual samples,
#: silhouette coverage) uses it.
TEXEL_SAMPLE = (0.5 + 1.0 / 81.0, 0.5 + 1.0 / 120.0)


def texel_sample_uv(ij, res: int) -> mi.Point2f:
    """``uv_light`` where the ray of texel ``ij`` (:class:`mi.Point2i` or
    :class:`mi.Point2f` of integers) crosses the face (:data:`TEXEL_SAMPLE`)."""
    return mi.Point2f((mi.Float(ij.x) + TEXEL_SAMPLE[0]) * (1.0 / res),
                      (mi.Float(ij.y) + TEXEL_SAMPLE[1]) * (1.0 / res))


def unit_grid(face_count: int, res: int):
    """``(face, s, t)`` of every texel's ray (its centre moved by
    :data:`TEXEL_SAMPLE`), ``s, t`` in [-1, 1] across the face."""
    return unit_grid_at(dr.arange(mi.UInt32, face_count * res * res), res)


def unit_grid_at(idx, res: int):
    """``(face, s, t)`` of the rays of the texels ``idx`` (``mi.UInt32`` flat texel
    indices), as :func:`unit_grid` gives them: a build of some texels computes their
    rays only (the same values, bit for bit)."""
    face = idx // (res * res)
    rem = idx - face * (res * res)
    j = rem // res
    i = rem - j * res
    inv = 1.0 / res
    s = (mi.Float(i) + TEXEL_SAMPLE[0]) * (2.0 * inv) - 1.0   # [-1, 1] across the face
    t = (mi.Float(j) + TEXEL_SAMPLE[1]) * (2.0 * inv) - 1.0
    return face, s, t


def texel_width_along(w_x, w_y, axis_x, axis_y, n_world):
    """The width of a ``w_x`` x ``w_y`` texel (world units; the face's image-plane axes
    ``axis_x``, ``axis_y``, unit world vectors) along the depth gradient of a receiver
    of normal ``n_world``: the normal's part in the image plane, the direction in which
    a receiver plane's depth changes, ``sqrt((w_x t_x)^2 + (w_y t_y)^2)`` for the unit
    direction ``t`` (``w`` for square texels, as before); the shorter side where the
    normal is along the rays (the depth does not change across the texel). With the
    longer side, a sun 0.5 degrees above a ground 80 wide (a 45:1 rectangle) sized the
    biases at 45 texels across the short axis: 21 % of the pixels misclassified."""
    tx = dr.abs(dr.dot(n_world, axis_x))
    ty = dr.abs(dr.dot(n_world, axis_y))
    norm2 = tx * tx + ty * ty
    along = dr.sqrt((w_x * tx) ** 2 + (w_y * ty) ** 2) / dr.sqrt(dr.maximum(norm2, 1e-30))
    return dr.select(norm2 > 1e-12, along, dr.minimum(w_x, w_y))

