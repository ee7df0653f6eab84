"""Point and area lights, projectors and spots of wide cones: six 90-degree faces around the light (:class:`CubeView`).

Face ``2*a + s`` looks along world axis ``a`` with sign ``+`` (s=0) or ``-``
(s=1); its ``u``/``v`` are the axes ``(a+1)%3`` and ``(a+2)%3``. A filter tap
off a face continues on the neighbouring face. Area lights (rectangle, disk,
sphere, mesh) are seen from their shape's bounding-box centre (``hard`` and
the PCF family thus see a point light there); the shape itself never
occludes, and ``light_size`` (for PCSS) comes from :func:`area_light_size`.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

from ..control_flow import if_stmt
from .base import (LightView, axial_texel_size, emitter_frame, opaque_point, position_np, scalar3,
                   divide_by_res, unit_grid, unit_grid_at)


def cube_dir(face, s, t) -> mi.Vector3f:
    """Light-space direction through (s, t) in [-1, 1]^2 on cube face ``face``."""
    axis = face // 2
    sign = dr.select((face & 1) == 0, 1.0, -1.0)
    # component along axis a is `sign`, along (a+1)%3 is s, along (a+2)%3 is t
    x = dr.select(axis == 0, sign, dr.select(axis == 1, t, s))
    y = dr.select(axis == 1, sign, dr.select(axis == 2, t, s))
    z = dr.select(axis == 2, sign, dr.select(axis == 0, t, s))
    # float64 in, float64 out (virtual maps); float32 otherwise
    return (mi.Vector3d if isinstance(s, mi.Float64) else mi.Vector3f)(x, y, z)


def cube_face(d: mi.Vector3f):
    """Inverse of :func:`cube_dir`: face, s, t and |major component|."""
    ax, ay, az = dr.abs(d.x), dr.abs(d.y), dr.abs(d.z)
    is_x = (ax >= ay) & (ax >= az)
    is_y = ~is_x & (ay >= az)
    axis = dr.select(is_x, mi.UInt32(0), dr.select(is_y, mi.UInt32(1), mi.UInt32(2)))
    major_signed = dr.select(is_x, d.x, dr.select(is_y, d.y, d.z))
    major = dr.abs(major_signed)
    face = 2 * axis + dr.select(major_signed < 0, mi.UInt32(1), mi.UInt32(0))
    u_comp = dr.select(is_x, d.y, dr.select(is_y, d.z, d.x))
    v_comp = dr.select(is_x, d.z, dr.select(is_y, d.x, d.y))
    inv = dr.rcp(dr.maximum(major, 1e-30 if not isinstance(major, mi.Float64) else 1e-300))
    return face, u_comp * inv, v_comp * inv, major


def _across_seams(face, xy, ij, in_face, res, real):
    """``(face, i, j)`` of cube-map taps at continuous texel coordinates ``xy`` of
    ``face`` (``ij = floor(xy)``): the tap's own texel where ``in_face``, else the texel
    of the neighbouring face its direction falls on (a cube re-projection in ``xy``'s
    precision; ``real`` converts ``res`` to it). The re-projection runs in a
    symbolic ``dr.if_stmt``, so only vector packets holding a tap off the face pay for
    it (a seam is rare; ``pcf`` on the two-light room, 256^2, 16 spp: render kernel
    81.6 -> 76.8 ms with virtual maps, 65.9 -> 59.0 ms with full maps)."""
    point2 = type(xy)

    def across(face, xy, i, j):
        st = xy * (2.0 / real(res)) - 1.0
        f2, s2, t2, _ = cube_face(cube_dir(face, st.x, st.y))
        ij2 = dr.clip(mi.Point2i(dr.floor(point2(s2 + 1.0, t2 + 1.0) * (0.5 * real(res)))),
                      0, res - 1)
        return mi.UInt32(f2), ij2.x, ij2.y

    def on_face(face, xy, i, j):
        return face, i, j

    return if_stmt((mi.UInt32(face), xy, ij.x, ij.y), ~in_face, across, on_face)


def face_split(face, v):
    """``(major, u, w)``: the components of ``v`` along face ``face``'s axis (signed
    towards the face) and along its ``u`` and ``v`` axes (see :func:`cube_dir`)."""
    axis = face // 2
    sign = dr.select((face & 1) == 0, 1.0, -1.0)
    major = sign * dr.select(axis == 0, v.x, dr.select(axis == 1, v.y, v.z))
    u = dr.select(axis == 0, v.y, dr.select(axis == 1, v.z, v.x))
    w = dr.select(axis == 0, v.z, dr.select(axis == 1, v.x, v.y))
    return major, u, w


def face_uv(face, d):
    """``uv_light`` of direction ``d`` on face ``face`` (off the face too), float32 or
    float64 as ``d`` is."""
    major, u, w = face_split(face, d)
    # The clamp is relative (a point within 1e-7 rad of the face's plane, or behind it,
    # lands 1e7 face widths off the face), so that reverse mode's partials stay finite:
    # an absolute 1e-30 gave 1/major^2 = inf in float32, and zero gradients times it NaN
    # (antialiased silhouette edges reaching behind a cube face, issue 13).
    tiny = 1e-300 if isinstance(major, mi.Float64) else 1e-30
    inv = dr.rcp(dr.maximum(major, dr.maximum(1e-7 * (dr.abs(u) + dr.abs(w)), tiny)))
    point2 = mi.Point2d if isinstance(major, mi.Float64) else mi.Point2f
    return point2(0.5 * (u * inv + 1.0), 0.5 * (w * inv + 1.0))


@dataclass(frozen=True)
class CubeView(LightView):
    """Six 90-degree faces around ``position`` in world axes."""

    projection = "cube"
    rays_from_point = True
    has_seams = True
    tan_half = 1.0

    @property
    def n_faces(self) -> int:
        return 6

    def texel_rays(self, res: int):
        face, s, t = unit_grid(6, res)
        return opaque_point(self.position), dr.normalize(cube_dir(face, s, t))

    def texel_rays_at(self, res: int, idx):
        face, s, t = unit_grid_at(idx, res)
        return opaque_point(self.position), dr.normalize(cube_dir(face, s, t))

    def ray_through(self, face, uv_light: mi.Point2f):
        s = uv_light.x * 2.0 - 1.0
        t = uv_light.y * 2.0 - 1.0
        return opaque_point(self.position), dr.normalize(cube_dir(mi.UInt32(face), s, t))

    def project(self, p_world: mi.Point3f):
        d = mi.Point3f(p_world) - opaque_point(self.position)
        face, s, t, major = cube_face(d)
        uv = mi.Point2f(0.5 * (s + 1.0), 0.5 * (t + 1.0))
        depth = dr.norm(d)
        return face, uv, depth, major > 0

    def uv_on_face(self, face, p_world: mi.Point3f) -> mi.Point2f:
        return mi.Point2f(face_uv(mi.UInt32(face),
                                  mi.Point3f(p_world) - opaque_point(self.position)))

    def texel_world_size(self, res: int, depth, p_world=None, n_world=None):
        """A texel's width across the ray (:meth:`LightView.texel_world_size`) at
        ``p_world``: its *axial* depth along its face's axis (the major component of
        ``p_world - position``) times ``2 tan_half / res``; ``depth`` (the distance from
        the light, up to sqrt(3) times more at a face's corner) only without ``p_world``.
        (A step ``2 / res`` long on the face at ``(s, t)`` is at most ``z 2 / res`` wide
        across the ray, ``z`` the axial depth (sideways to the direction from the face's
        centre; ``z 2 / res / sqrt(1 + s^2 + t^2)`` towards it): the distance overstated
        it, and so the biases, up to 1.73x at a face's corner.)"""
        if p_world is not None:
            d = mi.Point3f(p_world) - opaque_point(self.position)
            depth = dr.maximum(dr.maximum(dr.abs(d.x), dr.abs(d.y)), dr.abs(d.z))
        return depth * divide_by_res(2.0 * self.tan_half, res)

    def texel_parallel_size(self, res: int, face, p_world, texel_world):
        return axial_texel_size(self, res, face, p_world)

    def tap_texel(self, face, xy_texel: mi.Point2f, res: int, cross_seams: bool = True):
        ij = mi.Point2i(dr.floor(xy_texel))
        in_face = (ij.x >= 0) & (ij.x < res) & (ij.y >= 0) & (ij.y < res)
        face = mi.UInt32(face)
        if not cross_seams:
            ij = dr.clip(ij, 0, res - 1)
            return face, ij.x, ij.y, mi.Bool(True)
        f, i, j = _across_seams(face, mi.Point2f(xy_texel), ij, in_face, res, lambda r: r)
        return f, i, j, mi.Bool(True)

    # ------------------------------------------------------------- float64
    supports_virtual = True

    def uv_on_face_f64(self, face, p_world):
        d = mi.Point3d(p_world) - opaque_point(self.position, True)
        return face_uv(mi.UInt32(face), d)

    def uv_differential(self, face, p_world, dp_world):
        face = mi.UInt32(face)
        m, u, w = face_split(face, mi.Point3f(p_world) - opaque_point(self.position))
        dm, du, dw = face_split(face, mi.Vector3f(dp_world))
        inv = dr.rcp(dr.maximum(m, 1e-30))
        return mi.Point2f(0.5 * (du - u * dm * inv) * inv, 0.5 * (dw - w * dm * inv) * inv)

    def project_f64(self, p_world):
        d = mi.Point3d(p_world) - opaque_point(self.position, True)
        face, s, t, major = cube_face(mi.Vector3d(d))
        return face, mi.Point2d(0.5 * (s + 1.0), 0.5 * (t + 1.0)), dr.norm(d), major > 0

    def ray_through_f64(self, face, uv_light):
        s = mi.Float64(uv_light.x * 2.0 - 1.0)
        t = mi.Float64(uv_light.y * 2.0 - 1.0)
        return opaque_point(self.position, True), dr.normalize(cube_dir(mi.UInt32(face), s, t))

    def ray_frame_f64(self, face, uv_light):
        """(:attr:`~.base.LightView.ray_frame_f64`) Central rays: the unnormalised
        direction :func:`cube_dir` ``(face, s, t)``, ``s = 2 u - 1``, is affine in ``uv``."""
        face = mi.UInt32(face)
        base = cube_dir(face, mi.Float64(uv_light.x * 2.0 - 1.0),
                        mi.Float64(uv_light.y * 2.0 - 1.0))
        o = cube_dir(face, mi.Float(0.0), mi.Float(0.0))
        return (True, mi.Vector3f(base), 2.0 * (cube_dir(face, mi.Float(1.0), mi.Float(0.0)) - o),
                2.0 * (cube_dir(face, mi.Float(0.0), mi.Float(1.0)) - o))

    def face_texel_f64(self, face, xy_texel, res):
        """Off the face: the texel of the neighbouring face the direction falls on
        (:func:`_across_seams`, in float64)."""
        xy_texel = mi.Point2d(xy_texel)
        ij = mi.Point2i(dr.floor(xy_texel))
        res = mi.Int32(res)
        in_face = (ij.x >= 0) & (ij.x < res) & (ij.y >= 0) & (ij.y < res)
        f, i, j = _across_seams(mi.UInt32(face), xy_texel, ij, in_face, res, mi.Float64)
        return f, i, j, mi.Bool(True)

    def map_width(self, p_world: np.ndarray) -> float:
        return 2.0 * float(np.linalg.norm(p_world - position_np(self)))

    # --------------------------------------------------------------- culling
    def needs_camera_points(self, opts) -> bool:
        return bool(opts.cull_faces)

    def faces_needed(self, opts, visible, res):
        """With ``cull_faces``: the faces (``2*axis + (sign < 0)``) the camera-visible
        points project into, plus the neighbour across an edge for points within
        ``2 (4 + normal_bias) / res`` of it (normal offsets and sub-pixel camera
        samples may cross it); None (all faces) otherwise."""
        if not opts.cull_faces or visible is None:
            return None
        margin = 2.0 * (4.0 + opts.normal_bias_texels) / res
        need = [False] * 6
        if len(visible) == 0:
            return tuple(need)
        d = visible - position_np(self)
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


def point_view(emitter, label: str) -> CubeView:
    pos = mi.ScalarPoint3f(scalar3(mi.traverse(emitter)["position"]))
    return CubeView("point", pos, mi.ScalarTransform4f(), label=label)


def framed_cube_view(emitter, kind: str, label: str) -> CubeView:
    """Cube faces at the position of an emitter with a frame (``to_world``), that frame
    kept as ``light_from_world`` (multiview's light square, the pose reference): a spot
    of a wide cone, a ``projector``. Its cone or frustum only shades: faces no light
    sample reaches are never read."""
    T = emitter.world_transform()
    pos = mi.ScalarPoint3f(scalar3(T.translation()))
    return CubeView(kind, pos, emitter_frame(T, pos), label=label)


def projector_view(emitter, label: str) -> CubeView:
    """A ``projector`` (a pinhole light: delta position, its image and field of view
    only shade): :func:`framed_cube_view`, kind ``'projector'``."""
    return framed_cube_view(emitter, "projector", label)


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
    from . import emitter_class
    area = float(dr.ravel(shape.surface_area())[0])
    cls = emitter_class(shape)
    mesh = _triangles(shape)
    if mesh is not None:
        proj = float(np.linalg.norm(mesh[2].sum(axis=0)))
        a_proj = max(proj, 0.25 * area)
    elif cls in ("Disk", "Rectangle"):
        a_proj = area
    else:
        a_proj = 0.25 * area
    return math.sqrt(max(a_proj, 0.0))


def _triangles(shape) -> tuple | None:
    """``(v, f, area_vectors)`` of a mesh (float64 vertices, int64 faces, each
    triangle's area times its normal), or None for a shape that is not a mesh."""
    if not (shape.is_mesh() and hasattr(shape, "vertex_positions_buffer")):
        return None
    v = shape.vertex_positions_buffer().numpy().reshape(-1, 3).astype("f8")
    f = shape.faces_buffer().numpy().reshape(-1, 3).astype("i8")
    return v, f, 0.5 * np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])


def area_light_axes(shape) -> tuple | None:
    """The light's two world half-axes ``(e_1, e_2)`` (3-tuples) for PCSS's anisotropic
    kernels (:mod:`~mi_shadowmap.filters.pcss`): the planar light is read as the
    parallelogram ``centre + a e_1 + b e_2``, ``a, b`` in ``[-1, 1]``; None for a shape
    that is not planar (a sphere, a closed or folded mesh), which keeps the square of
    :func:`area_light_size`.

    * a ``rectangle`` (``[-1, 1]^2`` in its frame): its frame's x and y, exact;
    * a ``disk`` (radius 1 in its frame): its frame's x and y times ``sqrt(pi) / 2``, the
      square of the disk's area in its plane (the width :func:`area_light_size` gives, so
      that a disk seen face-on keeps its width; an ellipse from a non-uniform scale keeps
      its axes' ratio);
    * a planar mesh: the rectangle of the same in-plane second moments (a uniform
      rectangle of half-sides ``h`` has variance ``h^2 / 3`` along each side): exact for
      a rectangle, whatever its triangles; where the two in-plane moments agree within
      1e-4 (a square, a regular polygon), the first axis runs along its outline's
      sides (:func:`_outline_axis`), so that a square keeps its sides' directions
      whatever its triangles.

    Why: a strip light 6 x 0.02 was read as the 0.35 square of its area, its penumbra
    along the strip far too narrow and across it far too wide (``benchmarks/
    RESULTS.md``, fifty-third session, helper C: ``pcss`` 1.10 % misclassified, as
    ``hard``)."""
    cls = shape.class_name()
    params = mi.traverse(shape)
    if cls in ("Rectangle", "Disk") and "to_world" in params.keys():
        m = np.array(params["to_world"].matrix, dtype="f8").reshape(-1, 4, 4)[0]
        k = 1.0 if cls == "Rectangle" else 0.5 * math.sqrt(math.pi)
        return tuple(tuple(float(c) for c in k * m[:3, i]) for i in (0, 1))
    mesh = _triangles(shape)
    if mesh is None or len(mesh[1]) == 0:
        return None
    v, f, area_vec = mesh
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    area = np.linalg.norm(area_vec, axis=1)
    total = float(area.sum())
    if not total > 0.0:
        return None
    normal = area_vec.sum(axis=0)
    if np.linalg.norm(normal) < (1.0 - 1e-3) * total:   # not planar (or two-faced)
        return None
    normal /= np.linalg.norm(normal)
    # area-weighted moments of uniform triangles: E[x x^T] = (sum v v^T + s s^T) / 12
    s = a + b + c
    mean = (area[:, None] * s / 3.0).sum(axis=0) / total
    second = sum(np.einsum("n,ni,nj->ij", area, x, x) for x in (a, b, c, s)) / (12.0 * total)
    cov = second - np.outer(mean, mean)
    lam, vec = np.linalg.eigh(cov)            # ascending; the smallest: the normal
    lam1, lam2 = float(lam[2]), float(lam[1])
    ax1 = vec[:, 2]
    if lam1 - lam2 <= 1e-4 * lam1:            # isotropic in its plane: its outline's sides
        edges = [b[0] - a[0], c[0] - b[0], a[0] - c[0]]
        ax1 = min(edges, key=np.linalg.norm)
        ax1 = ax1 - normal * float(ax1 @ normal)
        ax1 = _outline_axis(v, f, normal, ax1 / np.linalg.norm(ax1))
        lam2 = lam1 = 0.5 * (lam1 + lam2)
    ax2 = np.cross(normal, ax1)
    h1, h2 = math.sqrt(3.0 * max(lam1, 0.0)), math.sqrt(3.0 * max(lam2, 0.0))
    return (tuple(float(x) for x in h1 * ax1), tuple(float(x) for x in h2 * ax2))


def _outline_axis(v: np.ndarray, f: np.ndarray, normal: np.ndarray,
                  hint: np.ndarray) -> np.ndarray:
    """A unit in-plane direction along the sides of a planar mesh's outline (its boundary
    edges: those of one triangle, vertices merged by position), for a mesh whose in-plane
    second moments are isotropic (a square, a square ring, a regular polygon), where they
    give no direction: the edges' mean direction modulo 90 degrees (each edge's angle
    times 4, weighted by its length), or the longest boundary edge's where that mean
    vanishes (a regular octagon: any turn is as good); of those four, the one nearest the
    unit ``hint`` (the first triangle's shortest edge), and ``hint`` itself where it lies
    within 1e-3 radians of one (a square quad's side: its axes, and so its image, as
    before, bit for bit).

    Why not the hint alone (6b56d0d): a square split into two triangles has a side for
    its first triangle's shortest edge, but one split as a fan around its centre a
    half-diagonal (and a square ring's first triangle an inner diagonal): that square was
    read as itself turned 45 degrees, 1.41 times as wide along the map's axes."""
    # positions merged on a grid of 2^-20 of the mesh's extent (any scene scale)
    span = max(float(np.ptp(v, axis=0).max()), 1e-300)
    grid = np.round((v - v.min(axis=0)) * (2.0 ** 20 / span))
    key = np.unique(grid, axis=0, return_inverse=True)[1].reshape(-1)
    tri = key[f]
    pairs = np.sort(np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]]), axis=1)
    pairs = pairs[pairs[:, 0] != pairs[:, 1]]
    uniq, count = np.unique(pairs, axis=0, return_counts=True)
    if not count.size:
        return hint
    ends = uniq[count == 1] if np.any(count == 1) else uniq
    pos = np.zeros((int(key.max()) + 1, 3))
    pos[key] = v
    e = pos[ends[:, 1]] - pos[ends[:, 0]]
    t1 = _any_in_plane(normal)
    t2 = np.cross(normal, t1)
    x, y = e @ t1, e @ t2
    length = np.hypot(x, y)
    if not length.max() > 0.0:
        return hint
    z = np.sum(length * np.exp(4j * np.arctan2(y, x)))
    if abs(z) > 1e-6 * length.sum():
        angle = 0.25 * float(np.angle(z))
    else:
        k = int(np.argmax(length))
        angle = math.atan2(y[k], x[k])
    toward = math.atan2(float(hint @ t2), float(hint @ t1))
    off = (toward - angle + 0.25 * math.pi) % (0.5 * math.pi) - 0.25 * math.pi
    if abs(off) < 1e-3:
        return hint
    angle = toward - off
    return math.cos(angle) * t1 + math.sin(angle) * t2


def _any_in_plane(normal: np.ndarray) -> np.ndarray:
    """A unit vector perpendicular to the unit ``normal``."""
    t = np.cross(normal, [1.0, 0.0, 0.0] if abs(normal[0]) < 0.9 else [0.0, 1.0, 0.0])
    return t / np.linalg.norm(t)


def planar_normal(shape):
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


def _unsampled_area_shape(shape) -> str | None:
    """Why Mitsuba 3.9 cannot sample points on the area emitter's shape (None: it can).
    Its ``linearcurve``, ``bsplinecurve`` and ``ellipsoids`` implement no surface area
    (their lights failed inside the light's set-up with "Shape::surface_area(): not
    implemented!"), ``sdfgrid`` has area 0 and samples no position (the light's shadow
    rays and maps read it as shadowed everywhere: a ground it lights rendered black in
    every method, ``raytraced`` included), and an ``ellipsoidsmesh`` light has no shape
    at all (an ``AttributeError`` on ``None``)."""
    if shape is None:
        return "Mitsuba gives the emitter no shape"
    try:
        area = float(dr.ravel(shape.surface_area())[0])
    except RuntimeError as exc:
        return f"Mitsuba cannot sample it: {str(exc).strip()}"
    if not area > 0.0 and shape.class_name() == "SDFGrid":
        # (a light scaled to zero area emits nothing, in Mitsuba's ``direct`` too: black)
        return (f"Mitsuba gives it a surface area of {area:g} and samples no point on it; "
                "its direct integrator reaches it by BSDF sampling alone")
    return None


def area_view(emitter, scene, label: str) -> CubeView:
    shape = emitter.get_shape()
    # get_shape() is typed as the Shape base; the scene's list has the Mesh interface.
    typed = [s for s in scene.shapes() if s.emitter() is emitter] if scene is not None else []
    why = _unsampled_area_shape(shape)
    if why is not None:
        from . import UnsupportedEmitterError
        on = typed[0] if typed else shape
        raise UnsupportedEmitterError(
            f"shadowmap: area emitter '{label}' on a "
            f"{on.class_name() if on is not None else 'shape'} is not supported ({why}); "
            "area lights on rectangle, disk, sphere, cylinder, cube and triangle meshes "
            "(ply, obj, serialized) are")
    bbox = shape.bbox()
    centre = mi.ScalarPoint3f(bbox.center())
    size = area_light_size(typed[0] if typed else shape)
    # (a light moved, turned or scaled through params.update() gets a new view: its
    # axes are read again)
    return CubeView("area", centre, mi.ScalarTransform4f(), light_size=size,
                    ignore_shape=shape, light_normal=planar_normal(shape), label=label,
                    light_axes=area_light_axes(shape))
