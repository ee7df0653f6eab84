"""Depth maps built with Dr.Jit ray queries, and the :class:`ShadowMap` data.

A :class:`ShadowMap` holds, for one emitter, the :class:`LightView` it was
built from and flat ``mi.Float`` arrays of ``n_faces * res * res`` texels
(see :mod:`mi_shadowmap.light_views` for the texel order):

* ``depth`` -- distance to the first surface along each texel's ray
  (``+inf`` where the ray escapes);
* ``extra`` -- further layers a method declares in its record
  (:class:`~mi_shadowmap.methods.Method` ``layers``), built only when that
  method runs: e.g. ``second_depth``, the distance to the second surface
  (Wang & Molnar; built here, :func:`second_depth_layer`), or MDSM's min/max
  depths (built in :mod:`mi_shadowmap.filters.mdsm` from the first depth).

The first depth is one ray-query kernel (``scene.ray_intersect_preliminary``,
:data:`COHERENT_RAYS`), evaluated once when built; the map manager
(:mod:`mi_shadowmap.map_manager`) decides which maps and layers a render
needs and caches them.
"""
from __future__ import annotations

import collections
from itertools import compress
from dataclasses import dataclass, field

import drjit as dr
import numpy as np
import mitsuba as mi

from .light_views import LightView
from .light_views.base import remember_latest
from .map_scene import map_scene, own_shapes_copy, stand_in
from .options import _BYTES_PER_TEXEL   # the one definition (float32 texels)


def _coherent_rays_default() -> bool:
    """Whether this CPU has AVX-512 (``avx512f``): Dr.Jit's LLVM backend then runs 16
    lanes a packet, and Embree's coherent mode traces the map builds' and the mark
    pass's rays faster; on AVX2 (8 lanes) it traced them more slowly. Measured
    (``benchmarks/RESULTS.md``, kernel times, coherent against incoherent):

    * AVX2, 2026-12-03: the mark pass's 65,536 camera rays on a 1M-triangle mesh
      17.5 against 9.6 ms, room_two_points' 1024^2 cube maps 296 against 246 ms; only a
      sphere-and-box spot map was 5-8 % faster;
    * AVX-512, 2026-12-05: virtual page casts 22-49 % faster on the 1M-triangle mesh
      and four repository scenes, full maps 8-42 % faster, the mark pass the same or
      15-30 % faster.

    The hits are the same either way. Where the CPU's features cannot be read:
    incoherent."""
    try:        # numpy's runtime CPU dispatch table (numpy >= 2, then 1.x)
        from numpy._core._multiarray_umath import __cpu_features__ as features
    except ImportError:
        try:
            from numpy.core._multiarray_umath import __cpu_features__ as features
        except ImportError:
            features = None
    if features is not None:
        return bool(features.get("AVX512F", False))
    try:
        with open("/proc/cpuinfo", encoding="ascii", errors="replace") as f:
            return any(line.startswith("flags") and " avx512f" in line for line in f)
    except OSError:
        return False


#: ``coherent`` of the map builds' and the mark pass's ray queries: Embree's coherent
#: mode on CPUs with AVX-512, incoherent elsewhere (:func:`_coherent_rays_default`).
COHERENT_RAYS = _coherent_rays_default()


def array_nbytes(x) -> int:
    """Bytes of one layer array: 4 a value, 8 for float64 (summed-area tables)."""
    return dr.width(x) * (8 if dr.type_v(x) == dr.VarType.Float64 else _BYTES_PER_TEXEL)


@dataclass
class ShadowMap:
    """Depth layers of one emitter's map faces. ``depth``: the first depths, or an empty
    array where the method reads none (:func:`~mi_shadowmap.methods.builds_first_depth`:
    ``second_depth``'s map holds its second depths alone; a lookup reading ``depth``
    then fails as its kernel is traced)."""
    view: LightView
    resolution: int
    depth: mi.Float
    extra: dict = field(default_factory=dict)
    #: Silhouette antialiasing (:mod:`mi_shadowmap.antialias`), else None: four
    #: blend weights per texel, and the depths before blending (``depth`` holds the
    #: blended ones; the prefiltered methods blend their moments from these).
    coverage: mi.Float | None = None
    raw_depth: mi.Float | None = None
    #: The light's pose delta (:mod:`mi_shadowmap.light_views.pose`) when its
    #: pose has gradients enabled, else None; lookups go through it.
    pose: object = None
    #: What the build ray-cast (:func:`build_depth_map`): faces holding a traced texel
    #: and texels traced; None for a map made otherwise (culled, cached).
    faces_built: int | None = None
    texels_built: int | None = None
    #: The faces the map was built for where not all (``cull_faces``: a bool per face),
    #: else None: the ``second_depth`` layer traces those alone (+inf in the others).
    faces: tuple | None = None

    @property
    def second_depth(self) -> mi.Float | None:
        """The ``second_depth`` layer, or None when it was not built."""
        return self.extra.get("second_depth")

    @property
    def has_depth(self) -> bool:
        """Whether the first depths were built (not for a method that reads none)."""
        return dr.width(self.depth) > 0

    @property
    def n_texels(self) -> int:
        return self.view.n_faces * self.resolution * self.resolution

    @property
    def nbytes(self) -> int:
        """Bytes of every layer held (small layers, e.g. one value per face, as they are;
    float64 layers, e.g. summed-area tables, at 8 bytes a value)."""
        return sum(array_nbytes(x) for x in (self.depth, *self.extra.values()))

    def texel_index(self, face, uv):
        """Flat index of the nearest texel (``floor(uv * res)``, clamped)."""
        res = self.resolution
        ij = dr.clip(mi.Point2i(dr.floor(uv * res)), 0, res - 1)
        return mi.UInt32(face) * (res * res) + mi.UInt32(ij.y) * res + mi.UInt32(ij.x)

    def fetch(self, layer: mi.Float, face, i, j, active=True):
        """Gather ``layer`` at integer texel coordinates (clamped to the face)."""
        res = self.resolution
        i = dr.clip(i, 0, res - 1)
        j = dr.clip(j, 0, res - 1)
        idx = mi.UInt32(face) * (res * res) + mi.UInt32(j) * res + mi.UInt32(i)
        return dr.gather(mi.Float, layer, idx, active)

    def clamp_texel(self, ij):
        """Integer texel coordinates clamped to the face (``fetch`` clamps the same way)."""
        return dr.clip(ij, 0, self.resolution - 1)

    def to_numpy(self, layer: str = "depth"):
        """The layer as a ``(n_faces, res, res)`` float32 numpy array (row j, column i)."""
        data = (self.depth if self.has_depth else None) if layer == "depth" \
            else self.extra.get(layer)
        if data is None:
            raise KeyError(f"layer '{layer}' was not built for emitter '{self.view.label}'; "
                           f"built: {', '.join(self.layers())}")
        return data.numpy().reshape(self.view.n_faces, self.resolution, self.resolution)

    def layers(self) -> list[str]:
        return ["depth"] * self.has_depth + list(self.extra)


def first_hit(scene: mi.Scene, view: LightView, o, d, differentiable: bool = False,
              pose=None, return_hit: bool = False):
    """Distance to the first surface along (o, d), skipping the light's own shape.

    At most 32 skipped hits (own shape, hits at the light) per ray; a ray
    still skipping after that stores +inf (lit) -- only a light inside more
    than 32 layers of its own shape could get there.

    Hits closer to the origin than ``1e-6 * max|o|`` (about 8 float ulps of
    the light position) are skipped too: they are numerically *at* the light,
    e.g. the floor under a light placed exactly on it, whose rounding puts
    the origin a hair below the plane so that every upward ray "hits" it at
    t ~ 1e-8 and the whole face reads depth 0 (issue 6). Scale-invariant.

    ``differentiable`` (issue 13): the returned depths carry gradients with
    respect to the shapes' parameters (mesh vertex positions, ``to_world``
    transforms). The skip loop stays detached (``ray_intersect_preliminary``
    has no derivatives); the final hit is then re-intersected differentiably
    (``pi.compute_surface_interaction``, checked in Mitsuba 3.9 to give
    ``dt/d(vertex positions)`` and ``dt/d(to_world)`` for meshes and
    spheres, as ``scene.ray_intersect`` does) and only its *gradient* is
    used (``dr.replace_grad``), so the depth values are bit-identical to the
    detached build's. The skipped distance (the light's own shape, hits at
    the light) carries no gradient. False (the default): one detached
    kernel, exactly as before. ``pose`` (a
    :class:`~mi_shadowmap.light_views.pose.LightPose`, with ``differentiable``):
    the rays of ``view`` (its reference view) are moved with the light, and
    depths also carry the light pose's derivatives. ``return_hit``: also return the hit's
    ``(shape, prim_index)`` (null shape where nothing is hit), for
    :mod:`mi_shadowmap.antialias`.
    """
    own_shape = view.ignore_shape
    own_copy = None
    if not (differentiable or return_hit):
        own_copy = own_shapes_copy(scene)   # instances and cylinders: prisms beside them
        if own_copy is None:
            original, scene = scene, map_scene(scene)   # cylinders as meshes (map_scene)
            own_shape = stand_in(original, own_shape)   # a tube light's prism
    o_ad = d_ad = None
    if pose is not None:
        o_ad, d_ad = pose.ray(o, d)
        o, d = dr.detach(o_ad), dr.detach(d_ad)
    ray = mi.Ray3f(o, d)
    query = (scene.ray_intersect_preliminary if own_copy is None else
             _own_and_instanced(scene, *own_copy, own_shape))
    pi = query(ray, coherent=COHERENT_RAYS)
    own = mi.ShapePtr(own_shape) if own_shape is not None else None
    eps_o = 1e-6 * dr.max(dr.abs(mi.Vector3f(o)))
    t_acc = mi.Float(0.0)
    it = dr.zeros(mi.UInt32, dr.width(pi.t))

    def skip(pi, t_acc):
        s = pi.is_valid() & (t_acc + pi.t <= eps_o)
        if own is not None:   # the emitter's own surface must never occlude itself
            s |= pi.is_valid() & (pi.shape == own)
        return s

    def cond(ray, pi, t_acc, it):
        return skip(pi, t_acc) & (it < 32)

    def body(ray, pi, t_acc, it):
        # The 1e-6 * max|o| term (~8 float ulps of the origin) guarantees the origin
        # moves: rays start ON the light's surface, whose re-hits at t ~ 1e-7 would
        # otherwise round to no move and loop forever (issue 6). Scale-invariant.
        step = (pi.t * (1.0 + 1e-5) + 1e-7 * (t_acc + pi.t)
                + 1e-6 * dr.max(dr.abs(mi.Vector3f(ray.o))))
        t_acc = t_acc + step
        ray = mi.Ray3f(ray.o + ray.d * step, ray.d)
        pi = query(ray, coherent=COHERENT_RAYS)
        return ray, pi, t_acc, it + 1

    ray, pi, t_acc, it = dr.while_loop((ray, pi, t_acc, it), cond, body)
    t_hit = pi.t
    if differentiable:   # value of pi.t, derivatives of the re-intersected hit
        ray_ad = ray if pose is None else mi.Ray3f(o_ad + d_ad * t_acc, d_ad)
        si = pi.compute_surface_interaction(ray_ad, mi.RayFlags.Minimal)
        t_hit = dr.replace_grad(t_hit, si.t)
    hit = pi.is_valid() & ~skip(pi, t_acc)
    depth = dr.select(hit, t_acc + t_hit, dr.inf)
    if return_hit:
        return (depth, dr.select(hit, pi.shape, dr.zeros(mi.ShapePtr, dr.width(hit))),
                dr.select(hit, pi.prim_index, 0))
    return depth


#: Hits on the scene's own shapes passed per ray looking for an instance's hit in front of
#: the copy's (:func:`_own_and_instanced`): phantom hits on its float32 cylinders, or its
#: surfaces rounding in front of their copies'.
OWN_HITS_PASSED = 4


def _own_and_instanced(scene, copy, stand_ins, own_shape, surface: bool = False):
    """``ray_intersect_preliminary`` (``surface``: ``ray_intersect``'s minimal surface
    interaction) for a scene with instances and cylinders of its own
    (:func:`~mi_shadowmap.map_scene.own_shapes_copy`): the first hit in ``copy`` (the
    scene's own shapes, cylinders as prisms), unless the scene has a hit inside an
    ``instance`` in front of it (the scene's first such hit, passing at most
    :data:`OWN_HITS_PASSED` hits on its own shapes, which the copy holds). The light's
    own shape (``own_shape``, a tube light's prism in the copy) is passed in the scene
    like every own shape and reported as the copy's ``stand_ins`` entry, for the
    caller's skip."""
    own = stand_ins.get(id(own_shape)) if own_shape is not None else None
    if own is not None:
        own_ptr, prism_ptr = mi.ShapePtr(own_shape), mi.ShapePtr(own)

    def query(ray, coherent=True, active=True):
        pc = copy.ray_intersect_preliminary(ray, coherent=coherent, active=active)
        limit = dr.select(pc.is_valid(), pc.t, ray.maxt)
        # (maxt: mi.Ray3f(o, d, x) would set the time)
        r = mi.Ray3f(ray.o, ray.d, limit, ray.time, ray.wavelengths)
        pi = scene.ray_intersect_preliminary(r, coherent=coherent, active=active)
        t_acc = mi.Float(0.0)
        k = dr.zeros(mi.UInt32, dr.width(limit))

        def passing(r, pi, t_acc, k):
            return pi.is_valid() & (dr.reinterpret_array(mi.UInt32, pi.instance) == 0) \
                & (k < OWN_HITS_PASSED)

        def past(r, pi, t_acc, k):
            step = (pi.t * (1.0 + 1e-5) + 1e-7 * (t_acc + pi.t)
                    + 1e-6 * dr.max(dr.abs(mi.Vector3f(r.o))))
            t_acc = t_acc + step
            r = mi.Ray3f(r.o + r.d * step, r.d, dr.maximum(r.maxt - step, 0.0), r.time,
                         r.wavelengths)
            return r, scene.ray_intersect_preliminary(r, coherent=coherent), t_acc, k + 1

        r, pi, t_acc, k = dr.while_loop((r, pi, t_acc, k), passing, past)
        inside = pi.is_valid() & (dr.reinterpret_array(mi.UInt32, pi.instance) != 0) \
            & (t_acc + pi.t < limit)
        if surface:
            out = dr.select(inside, pi.compute_surface_interaction(r, mi.RayFlags.Minimal),
                            pc.compute_surface_interaction(ray, mi.RayFlags.Minimal))
        else:
            out = dr.select(inside, pi, pc)
        out.t = dr.select(inside, t_acc + pi.t, pc.t)
        if own is not None:       # the caller skips its light's own shape by the scene's
            out.shape = dr.select(out.shape == prism_ptr, own_ptr, out.shape)
        return out

    return query


def shape_is_solid(shape) -> bool:
    """Whether ``shape`` bounds a solid with outward normals (set-up time, numpy).

    Meshes: watertight and consistently oriented once coincident vertices
    are welded, with a positive signed volume
    (:func:`mi_shadowmap.procedural.check_closed`); Mitsuba's ``sphere``:
    yes; every other shape (rectangle, disk, open cylinder, ...): no -- it is a
    two-sided non-solid for :func:`second_depth_layer`. (An ``instance`` is none itself:
    its hits name its shape group's shapes, which :func:`_face_tables` classifies.) A
    shape with ``flip_normals`` has inward normals, so it is no solid either (its hits'
    normals, which tell a back face, point inwards), nor is an ``ellipsoidsmesh``, whose
    back faces no ray hits (:func:`_culls_back_faces`).
    """
    if shape.has_flipped_normals():
        return False
    if shape.is_mesh():
        solid = face_solidity(shape)      # all its parts solid: the whole mesh is
        return bool(len(solid) and solid.all())
    return shape.class_name() == "Sphere"


#: A second depth is raised by this many units in the last place (2^-24, float32's unit
#: roundoff) of the hit triangle's largest coordinate: 16, about five times the largest
#: rounding measured (see :func:`second_depth_layer`).
ROUNDING_ULPS = 16.0

#: A second-depth ray continues this many units in the last place (2^-24) of the hit's
#: coordinates (and 1e-6 of its depth) past each hit it passes (doubled on hitting the
#: same face of the same instance again).
STEP_ULPS = 4.0


_UNLISTED = -1000000


#: The last :func:`_face_magnitudes` answer: ``[key, tables]`` (the key holds the meshes'
#: buffers, so their JIT indices are not reused while it lives).
_FACE_MEMO: list = [None, None]


def _face_magnitudes(scene: mi.Scene) -> tuple:
    """:func:`_face_tables`, remembered while the scene's shapes and their buffers are
    the same: a virtual map builds pages every camera move, and the tables of a
    1M-triangle mesh are 5 MB to upload."""
    key = tuple((id(sh), sh.vertex_positions_buffer(), sh.faces_buffer())
                if sh.is_mesh() and hasattr(sh, "faces_buffer") else (id(sh), repr(sh.bbox()))
                for sh in scene.shapes())
    idx = tuple(tuple(x.index if hasattr(x, "index") else x for x in k) for k in key)
    if _FACE_MEMO[0] is None or _FACE_MEMO[0][0] != idx:
        _FACE_MEMO[:] = [(idx, key), _face_tables(scene)]
    return _FACE_MEMO[1]


def _face_tables(scene: mi.Scene) -> tuple:
    """``(offset, magnitude, solid)`` tables for :func:`second_depth_along`'s hits (the
    rounding of their depth, and whether they bound a solid, :func:`face_solidity`): ``offset[id]`` (``mi.Int32``, by shape registry id) is a mesh's first row in
    ``magnitude`` (its faces' :func:`~mi_shadowmap.light_views.base.triangle_magnitudes`,
    indexed by the hit's ``prim_index``), ``-2 - row`` for another shape (its one row: its
    largest coordinate), or :data:`_UNLISTED` for an id the scene does not list. A
    triangle's own vertices, not its mesh's: a mesh Mitsuba merged (one BSDF) spans a
    1e5-wide ground and a small plate above it, and the ground's rounding (0.1 at 1e5) let
    the plate's shadow leak. The shapes of a ``shapegroup`` (hit through an ``instance``,
    whose hits name them) get rows too, for their solidity (an instance maps a solid's
    outside to its outside, mirrored or not, and Mitsuba turns the normals with it), with
    magnitude -1: their vertices are in the group's space, so the hit point's own world
    coordinates are used (instanced cubes were no solids: second_depth misclassified
    1.23 % of a point-lit view, 0.20 % for the same cubes as meshes)."""
    from .light_views.base import shape_bounds, triangle_magnitudes
    shapes = list(scene.shapes())
    ids = (dr.reinterpret_array(mi.UInt32, scene.shapes_dr()).numpy().astype(np.int64)
           if shapes else np.zeros(0, np.int64))
    grouped = _grouped_shapes(scene, shapes)
    if grouped:
        gids = dr.reinterpret_array(mi.UInt32, mi.ShapePtr(grouped)).numpy().astype(np.int64)
        ids = np.concatenate([ids, gids])
    offset = np.full(int(ids.max()) + 1 if ids.size else 1, _UNLISTED, np.int64)
    parts, solid, n = [], [], 0
    for k, (i, shape) in enumerate(zip(ids, shapes + grouped)):
        in_group = k >= len(shapes)
        if shape.is_mesh() and hasattr(shape, "faces_buffer"):
            sol = face_solidity(shape)
            m = (np.full(len(sol), -1.0, np.float32) if in_group
                 else triangle_magnitudes(shape))
            offset[i] = n
        else:
            b = shape_bounds(shape)
            m = np.array([-1.0 if in_group else
                          np.abs(np.stack(b)).max() if b is not None else 0.0], np.float32)
            sol = np.array([shape_is_solid(shape)])
            offset[i] = -2 - n
        parts.append(m)
        solid.append(sol)
        n += len(m)
    mag = np.concatenate(parts) if parts else np.zeros(1, np.float32)
    sol = np.concatenate(solid) if solid else np.zeros(1, bool)
    return (mi.Int32(offset.astype(np.int32)),
            mi.Float(np.maximum(mag, -1.0).astype(np.float32)), mi.Bool(sol))


def _grouped_shapes(scene: mi.Scene, listed) -> list:
    """The shapes of the scene's ``shapegroup``s (which ``scene.shapes()`` does not list:
    it lists their ``instance``s), found through ``mi.traverse``; [] without instances."""
    if not any(sh.class_name() == "Instance" for sh in listed):
        return []
    seen = {id(sh) for sh in listed}
    out = []
    for value in mi.traverse(scene).properties.values():
        node = value[2] if len(value) > 2 else None
        if (isinstance(node, mi.Shape) and id(node) not in seen
                and node.class_name() not in ("Instance", "ShapeGroup")):
            seen.add(id(node))
            out.append(node)
    return out


#: :func:`face_solidity` per mesh state (as light_views.base's bounds memo).
_SOLID_MEMO = collections.OrderedDict()
_SOLID_MEMO_SIZE = 4096
#: ``id(shape)`` -> its latest key in :data:`_SOLID_MEMO` (an edited mesh's earlier
#: state is dropped: ``light_views.base.remember_latest``).
_SOLID_LATEST: dict = {}


def _weld(v: np.ndarray, decimals: int = 5) -> tuple:
    """``(index per vertex, count)`` of the distinct vertices of ``v`` at ``decimals``
    decimals of the mesh's size where it is under a unit (its bounding box's largest
    side; of a world unit otherwise), numbered in lexicographic order: ``np.unique(...,
    axis=0, return_inverse=True)``'s numbers, from one ``lexsort`` of the columns (the
    row ``unique`` took 1.3-2.3 s of a 2M-triangle mesh's 2.3-3.6 s solidity; this
    0.5 s). (At 5 decimals of a world unit whatever the size, the repository's terrain
    scaled by 1e-4 welded its 31,746 vertices into 2,964 and only 832 of its 63,232
    faces stayed solid: ``second_depth`` misclassified 0.65 % of the view instead of
    0.48 %, against the README's scale invariance.)"""
    v = np.asarray(v, np.float64).reshape(-1, 3)
    finite = v[np.all(np.isfinite(v), axis=1)]
    size = float(np.max(np.ptp(finite, axis=0))) if len(finite) else 1.0
    unit = size if 0.0 < size < 1.0 else 1.0
    r = np.round(v * (10.0 ** decimals / unit))
    if not len(r):
        return np.zeros(0, np.int64), 0
    order = np.lexsort((r[:, 2], r[:, 1], r[:, 0]))
    rs = r[order]
    ids = np.concatenate([[0], np.cumsum(np.any(rs[1:] != rs[:-1], axis=1))])
    weld = np.empty(len(r), np.int64)
    weld[order] = ids
    return weld, int(ids[-1]) + 1


def _welded_parts(v: np.ndarray, f: np.ndarray, decimals: int = 5) -> tuple:
    """``(welded faces, connected part per face, number of parts, number of welded
    vertices)`` of a mesh: faces joined by vertices equal at ``decimals`` decimals."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    weld, m = _weld(v, decimals)
    fw = weld[f]
    g = coo_matrix((np.ones(2 * len(fw)), (np.concatenate([fw[:, 0], fw[:, 1]]),
                                            np.concatenate([fw[:, 1], fw[:, 2]]))),
                   shape=(m, m))
    n_parts, label = connected_components(g, directed=False)
    return fw, label[fw[:, 0]], n_parts, m


def _solid_parts(v: np.ndarray, f: np.ndarray, decimals: int = 5) -> tuple:
    """``(solid, part)`` per face: does its connected part bound a solid with outward
    normals (watertight, consistently oriented once coincident vertices are welded,
    positive volume; as :func:`~mi_shadowmap.procedural.check_closed`)? A mesh that is
    such a solid as a whole is solid everywhere (a hollow solid: its inner shell, turned
    inwards, has a negative volume of its own). ``part``: the face's connected part
    (``int32``, for :func:`_shells`). One pass over the edges for every part (a loop
    over 5000 parts took 244 s; 0.14 s)."""
    v = np.asarray(v, np.float64)
    fw, part, n_parts, m = _welded_parts(v, f, decimals)
    ok = (fw[:, 0] != fw[:, 1]) & (fw[:, 1] != fw[:, 2]) & (fw[:, 2] != fw[:, 0])
    gf, gp = fw[ok], part[ok]
    e = np.concatenate([gf[:, [0, 1]], gf[:, [1, 2]], gf[:, [2, 0]]])
    # a directed edge is unmatched or repeated unless its undirected edge is used exactly
    # twice, once each way (one sort: np.isin of the reversed edges, numpy 2.4, took
    # 15.5 s of a 2M-triangle mesh's 30 s first second_depth frame; this function
    # 13-19 s -> 4-5 s there)
    undirected = np.minimum(e[:, 0], e[:, 1]) * m + np.maximum(e[:, 0], e[:, 1])
    _, group, uses = np.unique(undirected, return_inverse=True, return_counts=True)
    forward = np.bincount(group, weights=(e[:, 0] < e[:, 1]).astype(float),
                          minlength=len(uses))
    bad = ~((uses == 2) & (forward == 1))[group]
    six_vol = np.einsum("ij,ij->i", v[f[:, 0]], np.cross(v[f[:, 1]], v[f[:, 2]]))
    part32 = part.astype(np.int32)
    if not bad.any() and six_vol.sum() > 0:
        return np.ones(len(f), bool), part32
    open_part = np.bincount(np.concatenate([gp] * 3), weights=bad.astype(float),
                            minlength=n_parts) > 0
    volume = np.bincount(part, weights=six_vol, minlength=n_parts)
    return (~open_part & (volume > 0))[part], part32


def clear_memos() -> None:
    """Forget every mesh's remembered per-face solidity (:func:`face_solidity`), the
    last face tables (:func:`_face_magnitudes`) and the scenes' copies with cylinders as
    meshes (:mod:`~mi_shadowmap.map_scene`)."""
    _SOLID_MEMO.clear()
    _SOLID_LATEST.clear()
    _FACE_MEMO[:] = [None, None]
    _SOLID_TABLES_MEMO[:] = [None, None]
    _PART_BOUNDS[:] = [None, None, None]
    _CANDIDATES[:] = [None, None, None]
    _OUTSIDE_MEMO.clear()
    _EDGES_MEMO.clear()
    from . import map_scene as ms
    ms.clear()


def _culls_back_faces(shape) -> bool:
    """Whether rays never hit ``shape``'s back faces: Mitsuba 3.9's ``ellipsoidsmesh``
    (closed, outward-facing icosahedra, but a ray from inside one finds none of its
    faces), so no second-depth ray ever leaves it through a back face: a solid there
    stored the surface behind it, and ``second_depth`` lost its shadows (3.9 % of a view
    false lit under a sun, against 0.2 % for ``hard``)."""
    return shape.shape_type() == getattr(mi.ShapeType, "EllipsoidsMesh", None)


def face_solidity(shape) -> np.ndarray:
    """Per face of a mesh: does it bound a solid with outward normals? Each connected
    part of the mesh (faces joined by welded vertices) is classified as
    :func:`shape_is_solid` classifies a whole shape: Mitsuba 3.9 merges meshes that share
    a BSDF into one, so a closed trough merged with an open floor made the trough a
    non-solid (misclassified 0.33 -> 0.67 %). Remembered per mesh state."""
    return _face_solidity_entry(shape)[1]


def _face_solidity_entry(shape) -> tuple:
    """:func:`face_solidity`'s memo entry: ``(buffers, solid, part)``, ``part`` the
    connected part of each face (:func:`_solid_parts`; None where no face is solid)."""
    vbuf, fbuf = shape.vertex_positions_buffer(), shape.faces_buffer()
    key = (id(shape), vbuf.index, fbuf.index)
    hit = _SOLID_MEMO.get(key)
    if hit is not None:
        _SOLID_MEMO.move_to_end(key)
        return hit
    f = fbuf.numpy().reshape(-1, 3).astype(np.int64)
    out, part = np.zeros(len(f), bool), None
    if len(f) and not shape.has_flipped_normals() and not _culls_back_faces(shape):
        out, part = _solid_parts(vbuf.numpy().reshape(-1, 3), f)
    return remember_latest(_SOLID_MEMO, _SOLID_LATEST, key, ((vbuf, fbuf), out, part),
                           _SOLID_MEMO_SIZE)


#: The last :func:`solid_face_tables` answer: ``[key, tables]`` (as :data:`_FACE_MEMO`).
_SOLID_TABLES_MEMO: list = [None, None]


def _transmits(shape) -> bool:
    """Whether a shape's BSDF transmits light (glass, a frosted shade, ...)."""
    bsdf = shape.bsdf()
    return bsdf is not None and mi.has_flag(bsdf.flags(), mi.BSDFFlags.Transmission)


def _two_sided(shape) -> bool:
    """Whether a shape's BSDF reflects light on the back side of its faces too
    (Mitsuba's ``twosided``; not ``principled``, whose flags name a back side it does not
    reflect on): a closed mesh of it may be seen from inside (a room), where its faces
    are lit from behind their geometric face. Its faces enter :func:`solid_face_tables`
    (flat ones too; for ``second_depth`` alone, :func:`solid_face_tables`'s
    ``two_sided``: the other methods' first depths shadow the room's inside already,
    and the tables' per-hit test cost 2-6 % of a room's frame) so that the integrator's
    ``_into_solid`` takes them as occluded where the light is outside their part."""
    bsdf = shape.bsdf()
    return (bsdf is not None and bsdf.class_name() != "Principled"
            and mi.has_flag(bsdf.flags(), mi.BSDFFlags.BackSide))


#: ``[key, answer, watched]`` of the last :func:`_solid_candidates` (the answer holds the
#: shapes: their ids, in the key, are not reused while it lives; ``watched``: what
#: ``params.update()`` may change of the answer, :func:`_candidates_edited`).
_CANDIDATES: list = [None, None, None]


def _solid_candidates(scene: mi.Scene, two_sided: bool = False) -> tuple:
    """``(shapes, use, glass, n_listed)`` for :func:`solid_face_tables`: the scene's shapes
    (``scene.shapes()``, ``n_listed`` of them, then a shapegroup's meshes, which an
    instance's hits name: as in _face_tables, an instance maps a solid's outside to its
    outside, and Mitsuba turns the normals), whether each is a mesh with vertex normals
    or a BSDF that transmits (``use``), and whether that BSDF transmits (``glass``).
    Remembered while the scene lists the same shapes and none of what ``params.update()``
    may change of it has changed (:func:`_candidates_edited`): every render of every map
    method asks, and the shapegroups' meshes take a ``mi.traverse`` of the scene (a warm
    frame of 300 cubes and an instance: 25k Python calls against 7.6k before every map
    method asked). Keyed by the shapes alone, a mesh given vertex normals through
    ``params.update()`` stayed flat (its smoothed terminator lit: 20 of 4096 pixels unlike
    a fresh integrator), a ``principled`` mesh given ``spec_trans`` stayed opaque
    (``second_depth`` lit a glass ball's far side behind its near side: 283 of 2304
    pixels misclassified against ``raytraced``, a fresh integrator 1), and a mesh whose
    normals were removed
    raised an ``IndexError`` (``tests/test_cache_edits.py``)."""
    listed = list(scene.shapes())
    key = (id(scene), tuple(id(sh) for sh in listed), two_sided)
    if _CANDIDATES[0] != key or (_CANDIDATES[2] and _candidates_edited(*_CANDIDATES[2])):
        from .map_manager import bsdf_flags, flag_changing_bsdfs
        shapes = listed + _grouped_shapes(scene, listed)
        meshes = [sh.is_mesh() and hasattr(sh, "faces_buffer") for sh in shapes]
        # every face of a transmitting mesh, and with ``two_sided`` (second_depth) of a
        # mesh whose BSDF reflects on both sides (a room built as a closed twosided
        # mesh: seen from inside, its faces are lit only from behind their geometric face,
        # which a light outside the room cannot reach; see _two_sided); a shapegroup's
        # too (listed alone, a room drawn through an instance under a sun read lit from
        # inside: 99.7 % of a 32^2 view misclassified, 0 now; its parts' lights are
        # tested in every instance's placement, lights_outside)
        glass = [m and (_transmits(sh) or (two_sided and _two_sided(sh)))
                 for sh, m in zip(shapes, meshes)]
        use = [m and (g or sh.has_vertex_normals())
               for sh, m, g in zip(shapes, meshes, glass)]
        flagged = flag_changing_bsdfs(sh.bsdf() for sh, m in zip(shapes, meshes) if m)
        plain = [sh for sh, m, u in zip(shapes, meshes, use) if m and not u]
        _CANDIDATES[:] = [key, (shapes, use, glass, len(listed)),
                          (plain, flagged, bsdf_flags(flagged)) if plain or flagged else ()]
    return _CANDIDATES[1]


def _candidates_edited(plain: list, flagged: list, flags: tuple) -> bool:
    """Whether ``params.update()`` changed what :func:`_solid_candidates` answered from:
    a mesh it found without vertex normals or a transmitting BSDF (``plain``) now has
    normals, or a BSDF whose flags an update changes (``flagged``, their ``flags`` then,
    ``map_manager.flag_changing_bsdfs``: ``principled`` given ``spec_trans``) has other
    flags. A call per such mesh and BSDF a render, none where there are none (the
    repository's scenes: their meshes have normals); a mesh whose normals are removed is
    seen by :func:`solid_face_tables`, whose key holds its normals' buffer."""
    from .map_manager import bsdf_flags     # (map_manager imports this module)
    return (any(sh.has_vertex_normals() for sh in plain)
            or bsdf_flags(flagged) != flags)


def _held_buffers(shapes, use, glass) -> tuple:
    """``(held, key)`` of :func:`solid_face_tables`: each used shape with its vertex,
    face and vertex-normal buffers, and the memo's key (their ids and buffer indices,
    and whether the shape takes every face, ``glass``)."""
    held = [(sh, sh.vertex_positions_buffer(), sh.faces_buffer(), sh.vertex_normals_buffer())
            for sh, m in zip(shapes, use) if m]
    key = tuple((id(sh), v.index, f.index, n.index, g)
                for (sh, v, f, n), g in zip(held, compress(glass, use)))
    return held, key


def solid_face_tables(scene: mi.Scene, two_sided: bool = False):
    """``(offset, solid, part, shells)`` tables of the faces that bound a solid with
    outward normals (:func:`face_solidity`) among the scene's meshes with vertex normals
    or a BSDF that transmits (less the flat-shaded faces of a BSDF that does not
    transmit, :func:`_flat_shaded_faces`: their shading frame is their geometric one,
    though they still bound their part's shell), with ``two_sided`` also every face of a
    closed mesh whose BSDF reflects on both sides (:func:`_two_sided`), or None where no
    such face exists:
    ``offset[id]``
    (``mi.Int32``, by shape registry id) is a mesh's first row in ``solid`` (``mi.Bool``,
    indexed by ``prim_index``), -1 for other shapes; ``part`` (``mi.Int32`` by row, or
    None where no transmitting mesh has such faces) numbers the closed parts of the
    solid faces (-1 elsewhere; and for the meshes of a ``shapegroup`` whose BSDF does
    not transmit, see below), whose geometry ``shells`` holds for
    :func:`lights_outside`.

    Only interpolated normals let a BSDF that does not transmit reflect light arriving
    from behind the hit's geometric face (a smooth-shaded mesh's terminator): a camera
    hit on the outside of a solid's face whose geometric normal looks away from the
    light is lit there by Mitsuba's ``direct``'s BSDF, while its shadow ray, which
    leaves the surface on the light's side, starts inside the solid and is occluded by
    it; the maps' biases (and ``second_depth``'s second surface, which such a face is)
    let that light through (the integrator's ``_into_solid``), unless the light is inside
    that part of the solid: then the shadow ray reaches it inside (a point light just
    inside a smooth icosahedron lights a band of its outside in ``direct``; with the
    part taken as occluding, every map method was black there). A BSDF that transmits
    shades light from behind any face, flat ones too: there the shadow ray is occluded
    by the solid unless the light is inside it. Both are decided per closed part
    (:func:`lights_outside`; a shapegroup's transmitting mesh, hit through instances, in
    every instance's placement; a shapegroup's mesh that does not transmit is taken as
    occluding: its instances' placements are read every render). Remembered while the
    candidates (:func:`_solid_candidates`) and their vertex, face and vertex-normal
    buffers are the same."""
    shapes, use, glass, n_listed = _solid_candidates(scene, two_sided)
    # the vertex normals too: which faces are flat-shaded (_flat_shaded_faces) follows
    # them (kept by vertices and faces alone, a ball's normals smoothed through
    # params.update() kept its flat faces' empty table, and the terminator's faces
    # facing away from a point light were lit: 14 of 4096 pixels misclassified against
    # raytraced, a fresh integrator 4; tests/test_cache_edits.py)
    # and which of them take every face (``glass``: a transmitting mesh, or with
    # ``two_sided`` a twosided one): kept by the buffers alone, a room's cube (vertex
    # normals, so listed either way) kept the tables of a ``hard`` render before, without
    # its flat faces, and second_depth read the room lit (99.7 % of a view misclassified)
    held, key = _held_buffers(shapes, use, glass)
    if _SOLID_TABLES_MEMO[0] is not None and _SOLID_TABLES_MEMO[0][0] == key:
        return _SOLID_TABLES_MEMO[1]
    if any(n.index == 0 and not g for (_, _, _, n), g in zip(held, compress(glass, use))):
        # a mesh listed for its normals has none now (params.update() removed them:
        # _flat_shaded_faces indexed the empty buffer, an IndexError): the candidates again
        _CANDIDATES[0] = None
        shapes, use, glass, n_listed = _solid_candidates(scene, two_sided)
        held, key = _held_buffers(shapes, use, glass)
    tables = None
    if held:
        ids = dr.reinterpret_array(mi.UInt32, mi.ShapePtr(shapes)).numpy().astype(np.int64)
        offset = np.full(int(ids.max()) + 1, -1, np.int64)
        parts, labels, shells, n, n_parts = [], [], [], 0, 0
        for k, (i, shape, m, g) in enumerate(zip(ids, shapes, use, glass)):
            entry = _face_solidity_entry(shape) if m else None
            sol = entry[1] if entry is not None else None
            # a face whose vertex normals are its geometric normal (a cube's) reflects no
            # light from behind it: no per-hit test there (the table), though its closed
            # part still bounds the shell a light may be inside of
            tested = (sol & ~_flat_shaded_faces(shape)
                      if sol is not None and not g else sol)
            if tested is not None and tested.any():
                offset[i] = n
                parts.append(tested)
                lab = np.full(len(sol), -1, np.int64)
                grouped = k >= n_listed
                if g or not grouped:
                    shell = _shells(shape, sol, n_parts, entry[2])
                    shell["grouped"] = grouped
                    lab[sol] = shell["label"]
                    n_parts += shell["count"]
                    shells.append(shell)
                labels.append(lab)
                n += len(sol)
        if parts:
            part = (mi.Int32(np.concatenate(labels).astype(np.int32)) if shells else None)
            tables = (mi.Int32(offset.astype(np.int32)), mi.Bool(np.concatenate(parts)),
                      part, shells)
    _SOLID_TABLES_MEMO[:] = [(key, held), tables]   # held: their buffers' indices stay unused
    return tables


def _flat_shaded_faces(shape) -> np.ndarray:
    """Per face of a mesh with vertex normals: are its three vertex normals its
    geometric normal (a ``cube``'s or a ``rectangle``'s faces, a mesh exported flat)?
    Its shading frame is then its geometric one, so a BSDF that does not transmit
    reflects no light from behind the face and such a face needs no entry in
    :func:`solid_face_tables` (whose per-hit test every map method's lookup pays)."""
    f = shape.faces_buffer().numpy().reshape(-1, 3).astype(np.int64)
    v = shape.vertex_positions_buffer().numpy().reshape(-1, 3).astype(np.float64)
    n = shape.vertex_normals_buffer().numpy().reshape(-1, 3).astype(np.float64)
    tri = v[f]
    n_face = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n_face /= np.maximum(np.linalg.norm(n_face, axis=1, keepdims=True), 1e-300)
    n_vert = n[f]
    n_vert = n_vert / np.maximum(np.linalg.norm(n_vert, axis=2, keepdims=True), 1e-300)
    cos = np.einsum("fj,fkj->fk", n_face, n_vert)
    return np.all(cos >= 1.0 - 1e-6, axis=1)


def _shells(shape, solid: np.ndarray, first: int, part=None) -> dict:
    """The closed parts of a mesh's solid faces (``solid``, :func:`face_solidity`), for
    :func:`lights_outside`: ``label`` (per solid face, numbered from ``first``),
    ``count``, their vertices ``v`` (float64, world space or the shapegroup's) and
    triangles ``f`` (``int32`` rows of ``v``), whether a part is turned inwards
    (``inward``: a hollow solid's inner shell) and its bounds. ``part``: each face's
    connected part (:func:`_solid_parts`, whose parts a solid face's are: found
    again where not given)."""
    v = shape.vertex_positions_buffer().numpy().reshape(-1, 3).astype(np.float64)
    f = shape.faces_buffer().numpy().reshape(-1, 3).astype(np.int64)[solid]
    if part is None:
        _, part, _, _ = _welded_parts(v, f)
    else:
        part = part[solid]
    uniq, local = np.unique(part, return_inverse=True)
    tri = v[f]
    six_vol = np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2]))
    count = len(uniq)
    lo = np.full((count, 3), np.inf)
    hi = np.full((count, 3), -np.inf)
    for ax in range(3):
        np.minimum.at(lo[:, ax], local, tri[:, :, ax].min(axis=1))
        np.maximum.at(hi[:, ax], local, tri[:, :, ax].max(axis=1))
    # the vertices and faces, not the triangles' corners (72 bytes a face, held as long
    # as the tables: every smooth solid mesh has shells)
    return {"label": local + first, "local": local, "count": count, "v": v,
            "f": f.astype(np.int32),
            "inward": np.bincount(local, weights=six_vol, minlength=count) < 0,
            "lo": lo, "hi": hi}


def _light_points(emitter):
    """Where ``emitter``'s light samples lie, for :func:`lights_outside`: None for an
    infinitely distant light (directional, environment), an ``(n, 3)`` array of points
    (a delta-position light's position; 64 points spread over an area light's shape),
    or False where that is unknown."""
    flags = emitter.flags()
    if mi.has_flag(flags, mi.EmitterFlags.Infinite):
        return None
    if mi.has_flag(flags, mi.EmitterFlags.DeltaPosition):
        it = dr.zeros(mi.Interaction3f)
        ds, _ = emitter.sample_direction(it, mi.Point2f(0.5))
        return np.asarray(ds.p.numpy(), np.float64).reshape(3, -1).T[:1]
    shape = emitter.get_shape()
    if shape is None:
        return False
    g = (np.arange(8) + 0.5) / 8
    u, w = np.meshgrid(g, g)
    ps = shape.sample_position(0.0, mi.Point2f(u.ravel(), w.ravel()))
    return np.asarray(ps.p.numpy(), np.float64).reshape(3, -1).T


#: At most this many light points times instances are tested against a shapegroup's
#: meshes (:func:`lights_outside`); beyond, their parts keep the old answer (lit).
MAX_INSTANCED_POINTS = 4096


def _instance_placements(scene, n_points: int):
    """The ``to_world`` matrices of the scene's instances, ``(n, 4, 4)`` float64, or None
    where ``n * n_points`` exceeds :data:`MAX_INSTANCED_POINTS`."""
    instances = [sh for sh in scene.shapes() if sh.class_name() == "Instance"]
    if len(instances) * n_points > MAX_INSTANCED_POINTS:
        return None
    out = [np.array(mi.traverse(sh)["to_world"].matrix, np.float64).reshape(4, 4)
           for sh in instances]
    return np.array(out).reshape(-1, 4, 4)


def _light_bounds(emitter, view=None):
    """``(lo, hi)`` (float64) around where ``emitter``'s light samples lie, read without
    a kernel, or None: a delta-position light's position from its map's ``view`` (not
    a posed one: the caller passes None), an area light's shape bounds."""
    from .light_views.base import position_np, shape_bounds
    if mi.has_flag(emitter.flags(), mi.EmitterFlags.DeltaPosition):
        if view is None or getattr(view, "position", None) is None:
            return None
        p = position_np(view)
        return p, p
    shape = emitter.get_shape()
    return shape_bounds(shape) if shape is not None else None


#: ``[shells, lo, hi]`` of the last :func:`_part_bounds` (the shells held: their id is
#: not reused while this lives).
_PART_BOUNDS: list = [None, None, None]


def _part_bounds(shells: list) -> tuple:
    """``(lo, hi)``: every part's bounds of ``shells``, widened by the margin
    :func:`_outside` takes for its mesh, one row a part (remembered for the last
    ``shells``: asked every render, for every light)."""
    if _PART_BOUNDS[0] is not shells:
        margin = [np.full(sh["count"], 1e-4 * (np.abs(sh["lo"]).max()
                                                + np.abs(sh["hi"]).max() + 1.0))
                  for sh in shells]
        margin = np.concatenate(margin)[:, None] if margin else np.zeros((0, 1))
        lo = (np.concatenate([sh["lo"] for sh in shells]) if shells
              else np.zeros((0, 3))) - margin
        hi = (np.concatenate([sh["hi"] for sh in shells]) if shells
              else np.zeros((0, 3))) + margin
        _PART_BOUNDS[:] = [shells, lo, hi]
    return _PART_BOUNDS[1], _PART_BOUNDS[2]


def lights_outside(shells: list, emitter, scene=None, view=None) -> np.ndarray:
    """Per part of ``shells`` (:func:`solid_face_tables`): does every light sample of
    ``emitter`` lie on the side its normals face (outside it; in the cavity of a hollow
    solid's inner shell)? Then a shadow ray from the outside of one of its faces to a
    light sample behind that face must cross the part again: it is occluded. Decided
    by the winding number of the part around the emitter's points (:func:`_light_points`;
    an area light's 64 points over its shape: a light crossing a part's surface counts
    as inside when one of them is inside); a point outside the mesh's whole solid (all
    its parts' windings summing to 0: the cavity of a hollow solid) is outside each of
    its parts too (a ray into the material must leave it). A shapegroup's mesh (its
    vertices in the group's space) is tested with the points brought into the group's
    space by every instance of ``scene`` (which instances draw which group is not known
    here: the light must be outside the part in all their placements; beyond
    :data:`MAX_INSTANCED_POINTS` points the old answer). An infinitely distant light
    is outside every part; an emitter of unknown kind inside every part (the old
    answer: lit). ``view``: the light's map's view, whose position a delta-position
    light's is: a light whose bounds (:func:`_light_bounds`) meet no part's is outside
    every part without its points being sampled (a kernel a light and render: every
    scene with a smooth solid mesh asks)."""
    count = sum(sh["count"] for sh in shells)
    if mi.has_flag(emitter.flags(), mi.EmitterFlags.Infinite):
        return np.ones(count, bool)
    bounds = _light_bounds(emitter, view)
    if bounds is not None and not any(sh["grouped"] for sh in shells):
        lo, hi = _part_bounds(shells)
        if not np.any(np.all((bounds[1] >= lo) & (bounds[0] <= hi), axis=1)):
            return np.ones(count, bool)
    points = _light_points(emitter)
    if points is None:
        return np.ones(count, bool)
    if points is False or not len(points):
        return np.zeros(count, bool)
    local = None
    if scene is not None and any(sh["grouped"] for sh in shells):
        placements = _instance_placements(scene, len(points))
        # a flattened (singular) placement: the old answer
        if placements is not None and np.all(np.abs(np.linalg.det(placements)) > 1e-30):
            inv = np.linalg.inv(placements)
            local = (np.einsum("nij,pj->npi", inv[:, :3, :3], points)
                     + inv[None, :, :3, 3].transpose(1, 0, 2)).reshape(-1, 3)
    # every render asks again: lights (and instances) move
    key = (id(shells), points.tobytes(), None if local is None else local.tobytes())
    hit = _OUTSIDE_MEMO.get(key)
    if hit is not None:
        return hit[1]
    out = np.concatenate(_outside(shells, points, local))
    while len(_OUTSIDE_MEMO) >= 64:
        _OUTSIDE_MEMO.popitem(last=False)
    _OUTSIDE_MEMO[key] = (shells, out)       # shells held: their id is not reused
    return out


#: :func:`lights_outside` answers: ``{(id(shells), points): (shells, answer)}``.
_OUTSIDE_MEMO = collections.OrderedDict()


def _outside(shells: list, points: np.ndarray, local) -> list:
    """:func:`lights_outside` of ``points`` (``local``: in the shapegroups' space, or
    None): one boolean array per mesh of ``shells``."""
    out = []
    for sh in shells:
        if sh["grouped"] and local is None:
            out.append(np.zeros(sh["count"], bool))
            continue
        ok = np.ones(sh["count"], bool)
        margin = 1e-4 * (np.abs(sh["lo"]).max() + np.abs(sh["hi"]).max() + 1.0)
        for p in (local if sh["grouped"] else points):
            if not ok.any():       # inside every part already
                break
            near = np.all((p >= sh["lo"] - margin) & (p <= sh["hi"] + margin), axis=1)
            wind = np.zeros(sh["count"])
            if near.any():
                rows = near[sh["local"]]
                t = sh["v"][sh["f"][rows]] - p
                a, b, c = t[:, 0], t[:, 1], t[:, 2]
                la, lb, lc = (np.linalg.norm(x, axis=1) for x in (a, b, c))
                num = np.einsum("ij,ij->i", a, np.cross(b, c))
                den = (la * lb * lc + np.einsum("ij,ij->i", a, b) * lc
                       + np.einsum("ij,ij->i", a, c) * lb + np.einsum("ij,ij->i", b, c) * la)
                wind = np.bincount(sh["local"][rows], minlength=sh["count"],
                                   weights=np.arctan2(num, den) / (2 * np.pi))
            # on the part's normals' side (winding 0 about an outward part, -1 in an
            # inward shell's cavity), or outside the mesh's whole solid (winding 0 about
            # all its parts: in a hollow solid's cavity)
            ok &= (np.abs(wind + sh["inward"]) < 0.25) | (abs(wind.sum()) < 0.25)
        out.append(ok)
    return out


#: The meshes :func:`directed_edges` built edges for: ``{id(mesh): faces buffer}`` (the
#: buffers held, so their JIT indices are not reused while remembered).
_EDGES_MEMO: dict = {}


def directed_edges(scene: mi.Scene) -> None:
    """Build Mitsuba's directed-edge table (``Mesh.build_directed_edges``, read through
    ``MeshPtr.opposite_dedge``) of every mesh of ``scene`` whose faces changed since it
    was last built here: ``second_depth``'s lookup finds a camera hit's neighbouring
    faces with it. Vertices are matched by index, so faces that share a position through
    separate vertices (a mesh split at its seams, Mitsuba's ``cube``) are no neighbours
    there. An ``instance``'s shapes are not built (the lookup skips them)."""
    for shape in scene.shapes():
        if not shape.is_mesh() or not hasattr(shape, "faces_buffer"):
            continue
        faces = shape.faces_buffer()
        held = _EDGES_MEMO.get(id(shape))
        if held is not None and held.index == faces.index:
            continue
        shape.build_directed_edges()
        _EDGES_MEMO[id(shape)] = faces
    while len(_EDGES_MEMO) > _SOLID_MEMO_SIZE:
        _EDGES_MEMO.pop(next(iter(_EDGES_MEMO)))


def second_depth_layer(scene: mi.Scene, smap: "ShadowMap") -> mi.Float:
    """Wang & Molnar (1994) second-depth layer: the second surface from the light.

    The paper's "front-face culling" construction (sec. 3.4, Pass 1), done
    with ray queries: one ``dr.while_loop`` (one kernel) per texel ray
    continues past hits until it stores

    * the first **back-facing** hit of a **solid** (``dot(n, d) > 0`` with
      the geometric normal ``n``): for closed solids this is where the ray
      leaves the first solid it entered -- the second surface from the
      light. Front-facing hits of solids are skipped (culled);
    * or the first hit of a **non-solid** (an open or one-sided surface,
      either side): the paper treats non-solids as "solids with
      infinitesimal thickness -- the first and second surface are the
      same" (sec. 3.3) and renders a two-sided surface's side facing away
      from the light in Pass 1, so the surface itself is stored;
    * a stored surface that is its own second surface -- the first surface the ray
      reaches: a non-solid, or a solid's inside lit by a light within it -- is raised
      by its rounding, :data:`ROUNDING_ULPS` units in the last place of the hit
      triangle's largest coordinate (or the ray origin's): it is compared with its own
      depth, and the ray-traced depth of a plane 1e4 units wide, seen from a light 4
      units above it, is off by up to 3.4 such units (2.9e-4) where the depth is 4-11
      (measured; the lookup's relative tolerance, 1e-5 of the depth, is ten times
      smaller there, and ``second_depth`` shadowed 27 % of such a ground, 39 % at 1e6
      wide; a point light inside a sphere room shadowed 41 % of its walls). A surface
      stored past a solid's front face (its back face, or a non-solid inside it) is
      another surface than any lit receiver, and is stored as it is: the paper's
      compare needs no bias there, and the margin lit the shadows' edges behind
      solids where it is large (16 ulps of 1e5 is 0.1 units: a unit scene 1e5 from
      the origin had 0.71 % of a view false lit, 0.07-0.12 % without it);
    * ``+inf`` where the ray escapes without either (no hit at all); a ray
      that escapes after entering a solid without leaving it (a broken
      solid) stores its first hit, like a non-solid.

    Solids are found per connected part of each shape at build time
    (:func:`face_solidity`, :func:`shape_is_solid`), so
    a closed solid standing in front of an open floor and an open surface
    in front of a solid both work; interpenetrating solids are fine (the
    ray leaves the first solid it entered at its back face). The emitter's
    own shape (area lights) and hits numerically at the light (as in
    :func:`first_hit`) are skipped (the own shape from the ray's own point ``ray(t)``:
    a sliver triangle's interpolated ``si.p`` lies far off a ray starting on it).
    Continuation rays start a relative step
    (:data:`STEP_ULPS` ulps of ``max|p|`` and ``1e-6 z``, doubled each time the same face
    of the same instance is hit again from the same side) past the hit (Mitsuba's
    ``spawn_ray`` offset has an absolute floor that broke scale invariance); at most 64
    hits per texel:
    a ray that has not stored a second surface after 64 hits keeps ``+inf``
    (lit), which only a texel ray crossing more than 64 surfaces (e.g. 32
    nested closed shells or 64 stacked open sheets) can reach.

    A map built for some faces only (``smap.faces``, ``cull_faces``) gets its second
    depths on those faces, +inf (lit) on the others, as its first depths.
    """
    if smap.faces is None:
        o, d = smap.view.texel_rays(smap.resolution)
        return second_depth_along(scene, smap.view, o, d)
    n = smap.resolution ** 2            # the faces culled: +inf there, nothing traced
    out = dr.full(mi.Float, dr.inf, smap.view.n_faces * n)
    if any(smap.faces):
        idx = _face_texels(smap.faces, n)
        o, d = smap.view.texel_rays_at(smap.resolution, idx)
        dr.scatter(out, second_depth_along(scene, smap.view, o, d), idx)
    return out


def second_depth_along(scene: mi.Scene, view: LightView, o, d) -> mi.Float:
    """:func:`second_depth_layer` for given texel rays ``(o, d)`` (unit ``d``): the
    distance along each ray to its second surface (the virtual maps' pages use it)."""
    own_copy = own_shapes_copy(scene)   # instances and cylinders: prisms beside them
    if own_copy is None:
        original, scene = scene, map_scene(scene)   # cylinders as meshes (map_scene)
        own_shape = stand_in(original, view.ignore_shape)   # a tube light's prism
        intersect = scene.ray_intersect
    else:
        own_shape = view.ignore_shape
        query = _own_and_instanced(scene, *own_copy, own_shape, surface=True)

        def intersect(ray, flags, coherent, active):   # (a prism's hit: no face table)
            return query(ray, coherent, active)
    own = mi.ShapePtr(own_shape) if own_shape is not None else None
    eps_o = 1e-6 * dr.max(dr.abs(mi.Vector3f(o)))
    face_offset, face_mag, face_solid = _face_magnitudes(scene)
    # a stored depth's rounding (see second_depth_layer), at least the ray origins'
    round_o = (ROUNDING_ULPS * 2.0 ** -24) * dr.max(dr.abs(mi.Vector3f(o)))
    ray = mi.Ray3f(o, d)
    n = dr.width(d)
    z_first = dr.full(mi.Float, dr.inf, n)
    z_second = dr.full(mi.Float, dr.inf, n)
    it = dr.zeros(mi.UInt32, n)
    active = dr.full(mi.Bool, True, n)
    entered = dr.zeros(mi.Bool, n)      # a solid's front face passed: inside a solid
    # the last hit (its shape, instance, face and side) and the step's growth on hitting
    # it again
    last = (dr.full(mi.UInt32, 0xFFFFFFFF, n), dr.zeros(mi.UInt32, n), dr.zeros(mi.UInt32, n),
            dr.zeros(mi.Bool, n))
    grow = dr.full(mi.Float, 1.0, n)

    def cond(ray, z_first, z_second, it, active, entered, last, grow):
        return active

    def body(ray, z_first, z_second, it, active, entered, last, grow):
        si = intersect(ray, mi.RayFlags.Minimal, True, active)
        hit = active & si.is_valid()
        hit_own = (hit & (si.shape == own)) if own is not None else mi.Bool(False)
        z = dr.dot(si.p - o, d)
        # Hits within ~8 ulps of the light position are AT the light (see first_hit).
        counted = hit & ~hit_own & (z > eps_o)
        # the hit face's row in the face tables (_face_magnitudes): its solidity and its
        # largest |coordinate| (a shape's, if not a scene mesh's; for a shape group's
        # shapes and ids not listed, the hit point's coordinates; unlisted: no solid)
        raw = dr.reinterpret_array(mi.UInt32, si.shape)
        listed = counted & (raw < dr.width(face_offset))
        off = dr.gather(mi.Int32, face_offset, dr.select(listed, raw, 0), listed)
        known = listed & (off != _UNLISTED)
        row = mi.UInt32(dr.maximum(dr.select(off >= 0, off + mi.Int32(si.prim_index),
                                             -off - 2), 0))
        known &= row < dr.width(face_solid)
        is_solid = known & dr.gather(mi.Bool, face_solid, row, known)
        back = dr.dot(si.n, d) > 0
        store = counted & (back | ~is_solid)
        mag = dr.gather(mi.Float, face_mag, row, known)
        # -1: a shape group's shape (vertices in the group's space): the hit's coordinates
        m_hit = dr.select(known & (mag >= 0), mag, dr.max(dr.abs(mi.Vector3f(si.p))))
        rounding = dr.maximum((ROUNDING_ULPS * 2.0 ** -24) * m_hit, round_o)
        # only a surface that is its own second surface (the first one the ray reaches)
        # gets the margin: past a solid's front face the stored surface is another one
        # than any lit receiver, and the paper's compare needs no bias there
        z_second = dr.select(store, z + dr.select(entered, 0.0, rounding), z_second)
        z_second = dr.select(active & ~hit, z_first, z_second)   # escaped
        z_first = dr.select(counted & dr.isinf(z_first), z + rounding, z_first)
        it = it + 1
        entered |= counted & ~store
        active = active & hit & ~store & (it < 64)
        # Continue a relative step past the hit (not si.spawn_ray: its offset has an
        # absolute floor, (1 + max|p|) * eps, which broke scale invariance, issue 6):
        # STEP_ULPS units in the last place of the hit's coordinates and 1e-6 of its
        # depth (a hit found from far away is off along the ray by more: a sun's rays
        # start a scene radius away), doubled each time the ray hits the same face from
        # the same side again (a ray grazing the face, or an origin that rounded back
        # onto it). 1e-6 of the coordinates (16.8 ulps), before, was a unit at 1e6 from
        # the origin: it passed through unit boxes' back faces and their shadows were
        # lost (10.6 % of a view false lit). (STEP_ULPS of the depth too shadowed
        # large_world's crates' edges: 0.25 -> 0.32 % false shadow.) The same face is
        # the same instance's too: a shape group's instances share their shapes' faces,
        # and 24 instances of a cube nested in each other doubled the step on every shell
        # (0.1 units by the 16th) and the rays jumped over the innermost's back face.
        inst = dr.reinterpret_array(mi.UInt32, si.instance)
        same = (raw == last[0]) & (inst == last[1]) & (si.prim_index == last[2]) \
            & (back == last[3])
        grow = dr.select(hit & same, grow * 2.0, 1.0)
        last = (raw, inst, si.prim_index, back)
        # The light's own surface is passed from the ray's own point, not from si.p: a
        # mesh's si.p is interpolated from its barycentrics, which a sliver triangle
        # (a rectangle light 4 x 2e-4) gives with large errors for a ray starting on it,
        # and si.p then lay up to 0.42 off the ray (median 4e-4): the continued ray
        # hit the receivers beside their own points, some in front of them, and
        # ``second_depth`` falsely shadowed 19 % of such a light's view (hard 1.5 %).
        p = dr.select(hit_own, ray.o + ray.d * si.t, si.p)
        step = grow * ((STEP_ULPS * 2.0 ** -24) * dr.max(dr.abs(mi.Vector3f(p)))
                       + 1e-6 * dr.abs(z))
        ray = dr.select(active, mi.Ray3f(p + d * step, d), ray)
        return ray, z_first, z_second, it, active, entered, last, grow

    state = dr.while_loop((ray, z_first, z_second, it, active, entered, last, grow),
                          cond, body)
    return state[2]


def build_layer(scene: mi.Scene, smap: ShadowMap, name: str, builder) -> mi.Float:
    """Build (and evaluate) the extra layer ``name`` of ``smap`` with ``builder``
    (``fn(scene, smap) -> mi.Float``, from the method's record)."""
    data = builder(scene, smap)
    dr.eval(data)
    return data


def build_depth_map(scene: mi.Scene, view: LightView, resolution: int,
                    layers: dict | None = None, differentiable: bool = False,
                    pose=None, antialias: bool = False) -> ShadowMap:
    """Ray-cast the first-surface depth of every texel of ``view``, plus ``layers``
    (``{name: builder}``, e.g. a method record's ``layers``); ``differentiable``:
    depths attached to the AD graph (:func:`first_hit`), moving with the light's
    ``pose`` if given; ``antialias``: silhouettes antialiased
    (:mod:`mi_shadowmap.antialias`). A view that no lookup reads whole
    (:meth:`LightView.built_texels`: a one-sided light's cube maps) has only the
    texels it names traced, the others +inf (antialiased maps: all of them, as the
    coverage reads every neighbour)."""
    n_faces, n = view.n_faces, resolution * resolution
    part = None if antialias else view.built_texels(resolution)
    if part is not None:
        idx, faces = part
        depth = trace_texels(scene, view, resolution, idx, differentiable, pose)
        smap = ShadowMap(view=view, resolution=resolution, depth=depth, pose=pose,
                         faces_built=faces, texels_built=dr.width(idx))
    elif not antialias:
        o, d = view.texel_rays(resolution)
        depth = first_hit(scene, view, o, d, differentiable, pose)
        dr.eval(depth)
        smap = ShadowMap(view=view, resolution=resolution, depth=depth, pose=pose,
                         faces_built=n_faces, texels_built=n_faces * n)
    else:
        from . import antialias as aa
        o, d = view.texel_rays(resolution)
        aa.prepare_meshes(scene)
        raw, shape, prim = first_hit(scene, view, o, d, differentiable, pose, return_hit=True)
        cov = aa.silhouette_coverage(view, resolution, dr.detach(raw), shape, prim, pose)
        depth = aa.blend(raw, cov, view.n_faces, resolution, finite_only=True)
        dr.eval(raw, cov, depth)
        smap = ShadowMap(view=view, resolution=resolution, depth=depth, coverage=cov,
                         raw_depth=raw, pose=pose, faces_built=n_faces,
                         texels_built=n_faces * n)
    for name, builder in (layers or {}).items():
        smap.extra[name] = build_layer(scene, smap, name, builder)
    return smap


def trace_texels(scene, view, res: int, idx, differentiable: bool = False,
                 pose=None) -> mi.Float:
    """First-surface depth of the texels ``idx`` of ``view`` (``mi.UInt32`` flat
    indices, maybe unevaluated), +inf in the others: only their rays are computed
    (:meth:`LightView.texel_rays_at`), traced by :func:`first_hit` and scattered into a
    map of every texel, in one kernel. ``differentiable``, ``pose``: as in
    :func:`first_hit`."""
    o, d = view.texel_rays_at(res, idx)
    depth = dr.full(mi.Float, dr.inf, view.n_faces * res * res)
    dr.scatter(depth, first_hit(scene, view, o, d, differentiable, pose), idx)
    dr.eval(depth)
    return depth


def build_culled_depth(scene, view, res: int, faces, differentiable: bool = False,
                       pose=None) -> mi.Float:
    """First-surface depth of the ``faces`` of a cube view; +inf in the others.

    Only the needed faces' texel rays are computed and traced (:func:`trace_texels`).
    No face needed: all +inf, no ray traced. ``differentiable``: as in
    :func:`first_hit`.
    """
    n = res * res
    if not any(faces):
        return dr.full(mi.Float, dr.inf, view.n_faces * n)
    idx = _face_texels(faces, n)
    depth = trace_texels(scene, view, res, idx, differentiable, pose)
    dr.sync_thread()
    return depth


def _face_texels(faces, n: int) -> mi.UInt32:
    """Flat indices of every texel of the ``faces`` (a bool per face) with ``n`` each."""
    return mi.UInt32(np.concatenate([np.arange(f * n, (f + 1) * n, dtype=np.uint32)
                                     for f, on in enumerate(faces) if on]))


def write_exr(smap: ShadowMap, path: str, layer: str = "depth") -> None:
    """Write one layer as a float32 EXR (faces stacked vertically, channel ``Y``).

    Written with the ``OpenEXR`` package, not ``mi.Bitmap``: Mitsuba 3.9.1's EXR
    reader and writer wait forever for their OpenEXR tasks after
    ``dr.set_thread_count(1)`` (one Dr.Jit thread, a setting users debug with), so
    this call never returned there."""
    import OpenEXR
    arr = np.ascontiguousarray(smap.to_numpy(layer).reshape(-1, smap.resolution),
                               dtype=np.float32)
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with OpenEXR.File(header, {"Y": arr}) as f:
        f.write(str(path))


# ------------------------------------------------------------- prefiltered layers
def summed_area_table(layer, n_faces: int, res: int) -> mi.Float64:
    """Inclusive summed-area table of a per-texel ``layer`` (float64, per face).

    Entry ``(f, j, i)`` (flat ``f*res*res + j*res + i``) holds the sum of the
    layer over texels ``(i', j')`` of face ``f`` with ``i' <= i`` and
    ``j' <= j``. Float64: the box sums of :func:`box_mean` are differences of
    large sums, which float32 would cancel away on large maps. Two contiguous
    row prefix sums with a transposing gather in between (and back): Dr.Jit
    1.5's ``prefix_reduce`` along a non-contiguous axis runs one loop lane per
    element, ``res^3`` steps per face (a 1024^2 face took 15 s; this way 6 x
    1024^2 takes well under a second). Gathers and prefix sums are
    differentiable, so prefiltered moments can carry gradients.
    """
    n = n_faces * res * res
    t = mi.TensorXf64(mi.Float64(layer), (n_faces, res, res))
    t = dr.prefix_reduce(dr.ReduceOp.Add, t, axis=2, exclusive=False)
    k = dr.arange(mi.UInt32, n)
    f = k // (res * res)
    rem = k - f * (res * res)
    row = rem // res
    swap = f * (res * res) + (rem - row * res) * res + row     # (f, j, i) <-> (f, i, j)
    t = mi.TensorXf64(dr.gather(mi.Float64, t.array, swap), (n_faces, res, res))
    t = dr.prefix_reduce(dr.ReduceOp.Add, t, axis=2, exclusive=False)
    return dr.gather(mi.Float64, t.array, swap)


def _sat_corner(sat, res: int, face, a, b, active):
    """Integral of the layer over ``[0, a] x [0, b]`` texels of ``face`` for integer
    corners ``a, b`` in ``[0, res]`` (0 on the lower edges)."""
    ok = active & (a > 0) & (b > 0)
    idx = mi.UInt32(face) * (res * res) + mi.UInt32(dr.maximum(b - 1, 0)) * res \
        + mi.UInt32(dr.maximum(a - 1, 0))
    return dr.select(ok, dr.gather(mi.Float64, sat, idx, ok), 0.0)


def _sat_integral(sat, res: int, face, x, y, active):
    """Integral over ``[0, x] x [0, y]`` for continuous ``x, y`` in ``[0, res]``: the
    bilinear interpolation of the corner integrals, exact for a piecewise-constant
    layer."""
    a = dr.clip(mi.Int32(dr.floor(x)), 0, res - 1)
    b = dr.clip(mi.Int32(dr.floor(y)), 0, res - 1)
    fx = mi.Float64(x - mi.Float(a))
    fy = mi.Float64(y - mi.Float(b))
    c00 = _sat_corner(sat, res, face, a, b, active)
    c10 = _sat_corner(sat, res, face, a + 1, b, active)
    c01 = _sat_corner(sat, res, face, a, b + 1, active)
    c11 = _sat_corner(sat, res, face, a + 1, b + 1, active)
    return dr.lerp(dr.lerp(c00, c10, fx), dr.lerp(c01, c11, fx), fy)


def box_mean(sat, res: int, face, lo: mi.Point2f, hi: mi.Point2f, active=True) -> mi.Float64:
    """Mean of a layer over the box ``[lo, hi]`` of continuous texel coordinates
    (``uv_light * res``) of ``face``, from its :func:`summed_area_table`: O(1)
    whatever the box size (16 gathers). The box is clipped to the face and made
    at least ``1e-3`` texels wide; texels count by their covered fraction."""
    lo = dr.clip(mi.Point2f(lo), 0.0, float(res))
    hi = dr.clip(mi.Point2f(hi), 0.0, float(res))
    hi = dr.maximum(hi, dr.minimum(lo + 1e-3, float(res)))
    lo = dr.minimum(lo, hi - 1e-3)
    active = mi.Bool(active)
    s = (_sat_integral(sat, res, face, hi.x, hi.y, active)
         - _sat_integral(sat, res, face, lo.x, hi.y, active)
         - _sat_integral(sat, res, face, hi.x, lo.y, active)
         + _sat_integral(sat, res, face, lo.x, lo.y, active))
    area = mi.Float64(hi.x - lo.x) * mi.Float64(hi.y - lo.y)
    return s / area
