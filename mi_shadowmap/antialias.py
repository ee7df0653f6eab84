"""Silhouette antialiasing of depth maps, for gradients of shadows (issue 13).

A depth map is piecewise constant in an occluder's position: a texel either
sees the occluder or what is behind it, so moving an outline across the map
changes texels by jumps, and a derivative of the map passes nothing of that
motion on. Worchel & Alexa (*Differentiable Shadow Mapping for Efficient
Inverse Graphics*, CVPR 2023) antialias their rasterised shadow maps with
nvdiffrast's analytic antialiasing (Laine et al., *Modular Primitives for
High-Performance Differentiable Rendering*, 2020), which turns that motion
into continuous coverage. This module does the same for ray-cast maps:

* For every pair of horizontally or vertically adjacent texels of one face
  that see different triangles (or one sees nothing), the *front* texel's
  triangle (the smaller depth) is looked up, and each of its edges that is
  a **silhouette edge** as seen from the light -- a boundary edge, or one
  whose neighbouring triangle faces the light the other way -- is projected
  into the face (through the light view, so through the light's pose too).
* Where such an edge crosses the segment between the two texel centres, at
  distance ``a`` (in texels, ``0 <= a <= 0.5``) from one centre, that
  texel's value moves towards its neighbour's by ``alpha = 0.5 - a``: the
  part of its footprint (along the segment) that lies on the other side of
  the edge. The front surface thus extends continuously into the back
  texel, or the back surface into the front one.
* ``alpha`` is a function of the edge's projected vertices, so it carries
  derivatives with respect to the mesh's vertex positions and ``to_world``,
  and to the light's pose (:mod:`mi_shadowmap.light_views.pose`).

Values blended (:func:`blend`): the depth itself for the depth-reading
methods (``hard``, ``pcf``, ``pcss``, ...; a texel next to nothing keeps its
depth), and each *moment* separately for the prefiltered ones (``vsm``,
``evsm``, ``msm``: ``z`` and ``z^2`` are blended, not ``z`` then squared),
which is what coverage-weighted moments are.

Deviations and limits (biases against ray tracing):

* Only triangle meshes have edges: analytic shapes (``sphere``,
  ``rectangle``, ``disk``, ``cylinder``) and curves keep hard outlines, and
  their shadows' gradients come from depths alone. Use a mesh occluder.
* One edge per texel pair: the silhouette edge the segment reaches first when it is
  walked from the front texel's centre across the mesh's projected triangles (at
  most ``WALK_STEPS`` of them; the front triangle and its three neighbours only,
  before, missed a silhouette two triangles away, e.g. a box side seen nearly
  edge-on; nvdiffrast looks at the front triangle only). The walk costs the
  build about a third more (the occluder scene's cube map: 18 -> 25 ms at 128^2,
  210 -> 280 ms at 512^2). Each edge is used by the pairs of one direction only:
  the horizontal pairs for edges steeper than 45 degrees in the face, the
  vertical pairs for the others, as in nvdiffrast. (Counting an edge in both
  directions adds its swept area twice: gradients came out 2x the finite
  differences.) Pairs across a cube seam are not blended. Near an outline's
  corner a pair whose segment crosses only the other direction's edge gets no
  blend: when a texel centre enters or leaves that corner the value jumps (about
  half a texel's compare), and the derivative misses it (the occluder scene at a
  80^2 map: 4 such jumps in 0.1 units of motion carry 22 % of the loss's change).
* Forward values change at silhouettes, by at most half a texel's worth of
  the depth step: at a 256^2 map this moves a hard shadow's outline by less
  than a texel; the measured effect on the image is in
  ``benchmarks/RESULTS.md``.
* A ``cube`` shape of Mitsuba has 24 unwelded vertices: every edge between
  two of its faces is a boundary, so texels straddling two faces both
  facing the light blend too (depths a fraction of a texel apart; harmless).
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from .light_views.base import TEXEL_SAMPLE

#: ``opposite_dedge`` of an edge with no neighbour (a boundary edge).
NO_EDGE = 0xFFFFFFFF
#: The neighbour steps (di, dj) of a texel, in the order of :func:`silhouette_coverage`.
STEPS = ((-1, 0), (1, 0), (0, -1), (0, 1))
#: At most this many triangles are crossed from the front texel's towards the
#: silhouette edge between a texel pair (:func:`silhouette_coverage`).
WALK_STEPS = 6


#: id(mesh) -> (mesh, face count, vertex count) of the meshes whose edge topology was
#: built (the mesh is held, so its id is not reused); the oldest beyond 256 are dropped.
_EDGES: dict = {}


def prepare_meshes(scene) -> None:
    """Build every mesh's edge topology (``opposite_dedge``) once per mesh and size
    (measured: 16-44 ms for 180 k triangles, at every gradient render without this).
    A mesh whose ``faces`` are replaced by as many other faces keeps its old topology:
    call its ``build_directed_edges()`` after such a change."""
    for shape in scene.shapes():
        if not shape.is_mesh():
            continue
        size = (shape.face_count(), shape.vertex_count())
        entry = _EDGES.get(id(shape))
        if entry is not None and entry[0] is shape and entry[1:] == size:
            continue
        shape.build_directed_edges()
        _EDGES.pop(id(shape), None)
        _EDGES[id(shape)] = (shape, *size)
        while len(_EDGES) > 256:
            _EDGES.pop(next(iter(_EDGES)))


def clear_meshes() -> None:
    """Forget every mesh :func:`prepare_meshes` holds (their topologies stay built)."""
    _EDGES.clear()


def _neighbour(res: int, k, step):
    """Flat index of texel ``k``'s neighbour in direction ``step`` (lane-wise
    ``mi.UInt32`` in 0..3), and whether it is on the same face."""
    face = k // (res * res)
    rem = k - face * (res * res)
    j = rem // res
    i = rem - j * res
    di = dr.select(step == 0, -1, dr.select(step == 1, 1, 0))
    dj = dr.select(step == 2, -1, dr.select(step == 3, 1, 0))
    ni = mi.Int32(i) + mi.Int32(di)
    nj = mi.Int32(j) + mi.Int32(dj)
    inside = (ni >= 0) & (ni < res) & (nj >= 0) & (nj < res)
    kn = face * (res * res) + mi.UInt32(dr.maximum(nj, 0)) * res + mi.UInt32(dr.maximum(ni, 0))
    return kn, inside, face, i, j, mi.Float(di), mi.Float(dj)


def silhouette_coverage(view, res: int, depth, shape, prim, pose=None) -> mi.Float:
    """Four blend weights per texel (flat ``4 k + s`` for the neighbour ``STEPS[s]``).

    ``depth`` (per texel, ``+inf`` for nothing), ``shape`` (``mi.ShapePtr``) and
    ``prim`` (``mi.UInt32``) are the map's first hits; ``pose``: a
    :class:`~mi_shadowmap.light_views.pose.LightPose` or None. Weights are 0
    except next to a silhouette edge (module docstring), and attached to the
    AD graph through the edge's vertices.
    """
    n = view.n_faces * res * res
    lane = dr.arange(mi.UInt32, 4 * n)
    k = lane // 4
    step = lane - k * 4
    kn, inside, face, i, j, di, dj = _neighbour(res, k, step)
    d_a = dr.gather(mi.Float, depth, k)
    d_n = dr.gather(mi.Float, depth, kn, inside)
    sh_a = dr.gather(mi.ShapePtr, shape, k)
    sh_n = dr.gather(mi.ShapePtr, shape, kn, inside)
    pr_a = dr.gather(mi.UInt32, prim, k)
    pr_n = dr.gather(mi.UInt32, prim, kn, inside)
    differ = inside & ((sh_a != sh_n) | (pr_a != pr_n)) & (dr.isfinite(d_a) | dr.isfinite(d_n))
    a_front = d_a <= d_n
    sh_f = dr.select(a_front, sh_a, sh_n)
    pr_f = dr.select(a_front, pr_a, pr_n)
    ok = differ & sh_f.is_mesh()
    mesh = mi.MeshPtr(sh_f)

    horizontal = dj == 0.0
    sign = dr.select(horizontal, di, dj)
    # where the texels' rays cross them (base.TEXEL_SAMPLE: the centre, moved a little)
    cu = dr.select(horizontal, mi.Float(i) + TEXEL_SAMPLE[0], mi.Float(j) + TEXEL_SAMPLE[1])
    cw = dr.select(horizontal, mi.Float(j) + TEXEL_SAMPLE[1], mi.Float(i) + TEXEL_SAMPLE[0])

    def crossing(a, b):
        """``(along, usable)``: where the edge ``a b`` (world points) crosses the
        segment from this texel's centre towards its neighbour, in texels from the
        centre; ``usable``: it crosses, and the pair's direction is the one more
        across the edge (nvdiffrast: an edge counted in both directions adds its
        swept area twice -- measured, 2x gradients)."""
        if pose is not None:
            a, b = pose.to_view(a), pose.to_view(b)
        qa = view.uv_on_face(face, mi.Point3f(a)) * res
        qb = view.uv_on_face(face, mi.Point3f(b)) * res
        ua, wa = dr.select(horizontal, qa.x, qa.y), dr.select(horizontal, qa.y, qa.x)
        ub, wb = dr.select(horizontal, qb.x, qb.y), dr.select(horizontal, qb.y, qb.x)
        den = wb - wa
        steep = dr.select(horizontal, dr.abs(den) >= dr.abs(ub - ua),
                          dr.abs(den) > dr.abs(ub - ua))
        usable = steep & (dr.abs(den) > 1e-12)
        s = (cw - wa) / dr.select(usable, den, 1.0)
        usable &= (s >= 0.0) & (s <= 1.0)
        return (ua + s * (ub - ua) - cu) * sign, usable

    # The search is detached: which silhouette edge crosses each pair (its two vertex
    # indices). Only the chosen edge is then differentiated (two vertex fetches per
    # lane in the AD graph instead of 24: a 26 s backward compile became ~1 s).
    #
    # It walks the segment from the front texel's centre towards the back one across
    # the mesh's projected triangles: from the front texel's triangle, out through the
    # edge the segment leaves it by, into that edge's twin, until the edge left by is a
    # silhouette edge (or the segment ends, or WALK_STEPS triangles were crossed).
    # (The front triangle and its three neighbours only, before: a silhouette two
    # triangles away -- e.g. the lower edge of a box's side seen nearly edge-on, within
    # a texel of the top face -- was missed; those pairs were not blended, the
    # outline's derivative there was lost (the occluder scene's trailing side: 12-24 %
    # of its swept area at 64^2-128^2 maps), and the forward value jumped instead as
    # texel centres crossed it.)
    found = mi.Bool(False)
    v_a = dr.zeros(mi.UInt32, 4 * n)
    v_b = dr.zeros(mi.UInt32, 4 * n)
    with dr.suspend_grad():
        # the segment, front centre -> back centre, along u: the front centre's u and
        # the direction (+1/-1); this lane's centre is the front one or the back one
        u_front = dr.select(a_front, cu, cu + sign)
        to_back = dr.select(a_front, sign, -sign)
        tri = mi.UInt32(pr_f)
        walking = mi.Bool(ok)
        came = dr.full(mi.UInt32, NO_EDGE, 4 * n)    # the directed edge entered by
        for _ in range(WALK_STEPS):
            tri_v = mesh.face_indices(tri, walking)
            n_tri = mesh.face_normal(tri, walking)
            best_t = dr.full(mi.Float, -1.0, 4 * n)
            best_e = mi.UInt32(0)
            for e in range(3):
                a = mesh.vertex_position(tri_v[e], walking)
                b = mesh.vertex_position(tri_v[(e + 1) % 3], walking)
                pa, pb = (pose.to_view(a), pose.to_view(b)) if pose is not None else (a, b)
                qa = view.uv_on_face(face, mi.Point3f(pa)) * res
                qb = view.uv_on_face(face, mi.Point3f(pb)) * res
                ua, wa = dr.select(horizontal, qa.x, qa.y), dr.select(horizontal, qa.y, qa.x)
                ub, wb = dr.select(horizontal, qb.x, qb.y), dr.select(horizontal, qb.y, qb.x)
                den = wb - wa
                s = (cw - wa) / dr.select(dr.abs(den) > 1e-12, den, 1.0)
                crosses = (dr.abs(den) > 1e-12) & (s >= 0.0) & (s <= 1.0) \
                    & (tri * 3 + e != came)
                t = (ua + s * (ub - ua) - u_front) * to_back   # 0 front, 1 back centre
                better = walking & crosses & (t > best_t)
                best_t = dr.select(better, t, best_t)
                best_e = dr.select(better, mi.UInt32(e), best_e)
            # the segment leaves the triangle by best_e (the farthest crossing: a line
            # through a triangle crosses two edges, and it entered by the nearer)
            leaves = walking & (best_t >= 0.0) & (best_t <= 1.0)
            dedge = tri * 3 + best_e
            ia = dr.select(best_e == 0, tri_v[0], dr.select(best_e == 1, tri_v[1], tri_v[2]))
            ib = dr.select(best_e == 0, tri_v[1], dr.select(best_e == 1, tri_v[2], tri_v[0]))
            opp = mesh.opposite_dedge(dedge, leaves)
            boundary = opp == NO_EDGE
            twin = dr.select(boundary, tri, opp // 3)
            n_twin = mesh.face_normal(twin, leaves & ~boundary)
            a = mesh.vertex_position(ia, leaves)
            b = mesh.vertex_position(ib, leaves)
            to_light = view.direction_to_light_on_face(face, mi.Point3f(0.5 * (a + b)))
            silhouette = boundary | ((dr.dot(n_tri, to_light) > 0)
                                     != (dr.dot(n_twin, to_light) > 0))
            stop = leaves & silhouette
            along, usable = crossing(a, b)
            hit = stop & usable & (along >= 0.0) & (along <= 0.5)
            v_a = dr.select(hit, ia, v_a)
            v_b = dr.select(hit, ib, v_b)
            found |= hit
            walking = leaves & ~silhouette
            came = dr.select(walking, opp, came)
            tri = dr.select(walking, twin, tri)
    along, _ = crossing(mesh.vertex_position(v_a, found), mesh.vertex_position(v_b, found))
    return dr.select(found, 0.5 - along, 0.0)


def blend(values, coverage, n_faces: int, res: int, finite_only: bool = False):
    """``values`` (one per texel, ``mi.Float`` or ``mi.Float64``) moved towards each
    neighbour's by its weight in ``coverage``: ``v + sum_s alpha_s (v_s - v)``.
    ``finite_only``: a texel or neighbour at ``+inf`` (nothing) is not blended."""
    cls = type(values)
    n = n_faces * res * res
    k = dr.arange(mi.UInt32, n)
    out = cls(values)
    for s in range(4):
        kn, inside, *_ = _neighbour(res, k, mi.UInt32(s))
        w = cls(dr.gather(mi.Float, coverage, 4 * k + s))
        v_n = dr.gather(cls, values, kn, inside)
        use = inside & (w > 0)
        if finite_only:
            use &= dr.isfinite(values) & dr.isfinite(v_n)
        out = dr.select(use, out + w * (v_n - values), out)
    return out
