"""K views of one light in one map (:class:`MultiView`): accumulated multi-view maps.

Heckbert & Herf (1997) render a soft shadow as the average of hard shadows
cast from many points of the light. A :class:`MultiView` holds the depth maps
of ``K`` such *light points* in one tensor: sub-view ``k`` is the emitter's
ordinary view (its *template*, :attr:`MultiView.sub`) moved to light point
``k``, and owns the faces ``k * F .. k * F + F - 1`` of the map (``F`` the
template's faces, texel order as in :mod:`.base`). The points are fixed per
map -- stratified samples of a fixed seed -- so maps are cached like all
others:

===============  =====================================================  ================
emitter          light points (``K`` stratified samples ``u_k``)         sub-views
===============  =====================================================  ================
area             the emitter's own ``sample_position(u_k)``, with their  cube maps
                 normals: the shape's, uniform by area, or for a
                 textured radiance the texture's importance sampling
                 (where the converged reference's samples lie)
point            ``light_size`` > 0: uniform on the sphere of diameter   cube maps
                 ``light_size`` (a sphere light), with their normals
spot,            ``light_size`` > 0: a square of side ``light_size``     the light's own
projector        across the light's axis (same axis and cone)            (perspective or
                                                                         cube maps)
directional      ``angular_diameter`` > 0: ``K`` directions in the       orthographic maps
                 disk of that angular diameter, each fitted to the
                 scene's bounds like the ordinary map
===============  =====================================================  ================

A light point with a normal (area lights, sized point lights) emits only
into its front half-space (:meth:`MultiView.emits_towards`). A sphere light that
Mitsuba samples in the cone it subtends (uniform radiance; a sized point light
likewise) weights its points, which are uniform by area, per receiver by the solid
angle each stands for, ``cos(theta_k) / d_k^2`` (:meth:`MultiView.weight`). Per-view
positions, rotations and normals live in small JIT tables gathered by the view
index, so one kernel serves every ``k`` (:meth:`MultiView.sub_view`). The
samples ``u_k`` (:func:`stratified_points`) are equal-area jittered strata
of ``[0, 1)^2`` for any ``K``, ordered along a Hilbert curve, so any run of
consecutive views covers a compact part of the light (the lookups' subsets).
"""
from __future__ import annotations

import dataclasses
import functools
import math
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

from ..variants import unpolarized
from .base import (LightView, look_along_np, opaque_point, opaque_scalar, position_np,
                   unit_grid_at)

#: Seed of the light points' jitter: fixed, so the views (and maps) are cacheable.
SEED = 0


# ------------------------------------------------------------------ light points
def _hilbert_index(x: np.ndarray, y: np.ndarray, order: int) -> np.ndarray:
    """Index along the Hilbert curve of the ``2^order`` grid cell ``(x, y)`` (numpy)."""
    n = 1 << order
    x, y = x.astype(np.int64).copy(), y.astype(np.int64).copy()
    d = np.zeros_like(x)
    s = n >> 1
    while s > 0:
        rx = (x & s) > 0
        ry = (y & s) > 0
        d += s * s * ((3 * rx) ^ ry)
        # rotate the quadrant (Wikipedia's xy2d)
        flip = ~ry
        mx = np.where(flip & rx, n - 1 - x, x)
        my = np.where(flip & rx, n - 1 - y, y)
        x, y = np.where(flip, my, mx), np.where(flip, mx, my)
        s >>= 1
    return d


def stratified_points(n: int, seed: int = SEED) -> np.ndarray:
    """``(n, 2)`` jittered points of ``[0, 1)^2``, one per equal-area stratum, for any ``n``.

    ``rows = round(sqrt(n))`` rows; row ``r`` holds ``n_r`` (``n // rows`` or one more)
    cells of width ``1 / n_r`` and has height ``n_r / n``, so every cell has area
    ``1 / n`` (a plain ``ceil(sqrt(n))``-column grid leaves part of its last row empty
    for non-square ``n``). One uniform point per cell (``numpy`` generator seeded
    with ``seed``), in its own ``1/n``-high band of the row, so that ``y`` alone is
    stratified in ``n`` strata (a mesh light picks its triangle from ``y``); the points
    are those of :func:`~mi_shadowmap.reference.light_sample_pattern`, ordered along a
    Hilbert curve.
    """
    rows = max(1, int(round(math.sqrt(n))))
    counts = [n // rows + (1 if r < n % rows else 0) for r in range(rows)]
    rng = np.random.default_rng(seed)
    pts, y0 = [], 0.0
    for r, n_r in enumerate(counts):
        h = n_r / n
        j = rng.random((n_r, 2))
        x = (np.arange(n_r) + j[:, 0]) / n_r
        # each cell's point in its own 1/n-high band of the row (a random one), so that
        # y alone is stratified in n strata too: a mesh light picks its triangle from y
        # (Mitsuba's sample_position), and with y jittered over the whole row a cube
        # light's faces got 36..48 of 256 points instead of 42.7 each (the bottom 36: the
        # AOV under it 0.016 below raytraced's); now each face gets 42 or 43. The bands
        # are the converged reference's (reference.light_sample_pattern): the same points
        band = np.random.default_rng([seed, r]).permutation(n_r)
        pts.append(np.stack([x, y0 + (band + j[:, 1]) / n], axis=1))
        y0 += h
    p = np.clip(np.concatenate(pts), 0.0, np.nextafter(1.0, 0.0))
    order = 10
    cells = np.minimum((p * (1 << order)).astype(np.int64), (1 << order) - 1)
    return p[np.argsort(_hilbert_index(cells[:, 0], cells[:, 1], order), kind="stable")]


def stratified_cell(u, n: int):
    """Index of the stratum of :func:`stratified_points` (``n`` points) that holds ``u``
    (in the strata's construction order, row by row: before the Hilbert sort), for a
    ``numpy`` ``(m, 2)`` array or a ``mi.Point2f``. O(1): the first ``n % rows`` rows
    hold ``n // rows + 1`` cells, the others ``n // rows``, all cells of area ``1 / n``."""
    rows = max(1, int(round(math.sqrt(n))))
    q, m = n // rows, n % rows
    if isinstance(u, np.ndarray):
        x, t = u[:, 0], u[:, 1] * n
        r = np.where(t < m * (q + 1), np.floor(t / (q + 1)),
                     m + np.floor((t - m * (q + 1)) / q))
        r = np.clip(r, 0, rows - 1).astype(np.int64)
        n_r = q + (r < m)
        c = np.clip(np.floor(x * n_r).astype(np.int64), 0, n_r - 1)
        return r * q + np.minimum(r, m) + c
    x, t = u.x, u.y * n
    r = dr.select(t < m * (q + 1), dr.floor(t / (q + 1)), m + dr.floor((t - m * (q + 1)) / q))
    r = mi.UInt32(dr.clip(r, 0.0, rows - 1.0))
    n_r = dr.select(r < m, mi.UInt32(q + 1), mi.UInt32(q))
    c = dr.minimum(mi.UInt32(dr.maximum(dr.floor(x * mi.Float(n_r)), 0.0)), n_r - 1)
    return r * q + dr.minimum(r, m) + c


def _sphere_cells(u: np.ndarray, p: np.ndarray, centre, radius: float):
    """``(sphere, cells)`` of :attr:`MultiView.sphere` and :attr:`MultiView.cells` for
    light points ``p`` made from the samples ``u`` on the sphere ``(centre, radius)``
    (by ``square_to_uniform_sphere``, possibly rotated: Mitsuba's sphere shape applies
    its ``to_world`` rotation to the positions), or ``((), ())`` where the points do not
    invert to their own strata."""
    K = len(u)
    c = np.asarray(centre, dtype=np.float64)
    w = mi.warp.square_to_uniform_sphere(mi.Point2f(mi.Float(u[:, 0]), mi.Float(u[:, 1])))
    local = np.stack([a.numpy() for a in w], axis=1).astype(np.float64)
    # (p - c) / r = local @ A; world -> the warp's frame: @ inv(A)
    A = np.linalg.lstsq(local, (p - c) / radius, rcond=None)[0]
    if not np.allclose(local @ A, (p - c) / radius, atol=1e-4):
        return (), ()
    inv = np.linalg.inv(A)
    cells = stratified_cell(u, K)
    back = stratified_cell(np.stack([a.numpy() for a in mi.warp.uniform_sphere_to_square(
        mi.Vector3f(*[mi.Float(col) for col in (((p - c) / radius) @ inv).T]))],
        axis=1).astype(np.float64), K)
    if sorted(cells.tolist()) != list(range(K)) or np.mean(back == cells) < 0.99:
        return (), ()
    table = np.empty(K, dtype=np.int64)
    table[cells] = np.arange(K)
    return ((*map(float, c), float(radius), *map(float, inv.ravel())),
            tuple(int(k) for k in table))


# --------------------------------------------------------------------- the view
@dataclass(frozen=True)
class MultiView(LightView):
    """``K`` copies of the template view ``sub`` at the light points, in one map.

    * ``positions`` -- ``K`` world positions (a directional sub-view's near-plane centre);
    * ``rotations`` -- ``K`` world-to-light rotations (9 numbers, row-major), or ``()``:
      every sub-view keeps ``sub``'s. Sub-view ``k``'s ``light_from_world`` is that
      rotation about its position (cube maps ignore it: world axes);
    * ``normals`` -- ``K`` emitting normals (one, shared, for a planar light), or ``()``
      (light points emit everywhere);
    * ``samples`` -- the ``K`` samples ``u_k`` the points were made from;
    * ``radiant`` -- per point, whether it emits at all (an area light's radiance there
      is > 0: a textured light can be black in places), or ``()``: all do;
    * ``count_all`` -- the visibility's denominator is all the points looked up (a
      point that does not emit towards the receiver counts as shadowed, as the
      reference counts a light sample Mitsuba draws there: lights sampled by area, or
      by their texture), else only the points that emit towards it (a sphere, which
      Mitsuba samples in the cone it subtends, so that no sample lies on its back);
    * ``cone`` -- True for a sphere light sampled in the cone it subtends (a uniform
      sphere area light, a point light with ``light_size``): its points, uniform by
      area, are weighted per receiver by the solid angle each stands for,
      ``cos(theta_k) / d_k^2`` (:meth:`weight`; ``theta_k`` the angle at the light
      between its normal and the receiver, ``d_k`` the distance), so that the average
      over the facing ones is the average over the cone (unweighted it is the average
      over the visible cap's area, which over-weights its rim);
    * ``inside_only`` -- ``(centre, radius)`` of a sphere light with ``flip_normals``,
      which emits inwards only: a receiver outside it sees none of its points (their
      light would cross the sphere itself, which the maps skip as the light's own
      shape), else None;
    * ``sphere`` -- a ``cone`` light's sphere: centre (3), radius and the 3 x 3 matrix
      (row-major) taking ``(p - centre) / radius`` to the ``square_to_uniform_sphere``
      frame its points were made in, or ``()``; with ``cells`` -- the ``K`` views by
      stratum (:func:`stratified_cell`): ``cells[i]`` is the view whose sample lies in
      stratum ``i``. Lookups of a subset draw points in the cone the sphere subtends
      and test the view of each one's stratum (:meth:`cone_view`).
    * ``dark`` -- an area light whose radiance is 0 at every point while its value tracks
      gradients: ``radiant`` then holds every valid point (the derivative image it lights
      reads them as a lit light's), and the lookup's visibility AOV is 0.
    * ``lookup_reach`` -- ``(offset, taps)`` in texels of a one-sided planar light's cube
      sub-views: the lookup's largest normal offset and how far its taps reach beyond the
      nearest texel; the build then skips the texels no lookup reads, those behind the
      light's plane (:meth:`built_texels`). None: every texel is built.
    """
    sub: LightView | None = None
    positions: tuple = ()
    rotations: tuple = ()
    normals: tuple = ()
    samples: tuple = ()
    radiant: tuple = ()
    count_all: bool = False
    cone: bool = False
    inside_only: tuple | None = None
    sphere: tuple = ()
    cells: tuple = ()
    dark: bool = False
    lookup_reach: tuple | None = None

    projection = "multi-view"

    @property
    def rays_from_point(self) -> bool:
        return self.sub.rays_from_point

    @property
    def has_seams(self) -> bool:
        return self.sub.has_seams

    @property
    def n_views(self) -> int:
        return len(self.positions)

    @property
    def faces_per_view(self) -> int:
        return self.sub.n_faces

    @property
    def n_faces(self) -> int:
        return self.n_views * self.sub.n_faces

    # ---------------------------------------------------------- per-view tables
    @functools.cached_property
    def _tables(self) -> dict:
        """The per-view data as JIT arrays (built once per view object)."""
        # every table is opaque: a one-view table (a delta light's, as_multi_view) would
        # otherwise be a literal, and a moved light would compile new kernels
        def cols(rows, n):
            a = np.asarray(rows, dtype=np.float64).reshape(len(rows), n)
            if len(a) == 1:
                return [dr.opaque(mi.Float, float(a[0, c])) for c in range(n)]
            out = [mi.Float(np.ascontiguousarray(a[:, c], dtype=np.float32)) for c in range(n)]
            dr.make_opaque(*out)
            return out
        t = {"pos": mi.Point3f(*cols(self.positions, 3))}
        if self.rotations:
            t["rot"] = cols(self.rotations, 9)
        else:       # shared by every view
            R = np.array(self.sub.light_from_world.matrix, dtype=np.float64)[:3, :3]
            t["rot_shared"] = cols([R.ravel()], 9)
        if self.radiant and not all(self.radiant):
            t["radiant"] = mi.Bool(list(self.radiant))
            dr.make_opaque(t["radiant"])
        if len(self.normals) == 1:
            t["normal"] = mi.Vector3f(*cols([self.normals[0]], 3))
        elif self.normals:
            t["normal"] = mi.Vector3f(*cols(self.normals, 3))
        if self.sphere:
            t["sphere_inv"] = [opaque_scalar(v) for v in self.sphere[4:]]
            t["cells"] = mi.UInt32(np.asarray(self.cells, dtype=np.uint32))
            dr.make_opaque(t["cells"])
        return t

    def lane(self, k) -> LightView:
        """The template view moved to light point ``k`` (``mi.UInt32`` per lane): its
        ``position`` (and ``light_from_world``) are JIT values gathered by ``k``."""
        t = self._tables
        k = mi.UInt32(k)
        p = dr.gather(mi.Point3f, t["pos"], k)
        R = (t["rot_shared"] if "rot_shared" in t
             else [dr.gather(mi.Float, c, k) for c in t["rot"]])
        # light_from_world = [R | -R p]; Transform4f also stores its inverse transpose,
        # [[R, 0], [p^T, 1]] (the inverse of a rigid [R | -R p] is [R^T | p]).
        tr = [-(R[3 * i] * p.x + R[3 * i + 1] * p.y + R[3 * i + 2] * p.z) for i in range(3)]
        m = mi.Matrix4f(R[0], R[1], R[2], tr[0], R[3], R[4], R[5], tr[1],
                        R[6], R[7], R[8], tr[2], 0.0, 0.0, 0.0, 1.0)
        inv_t = mi.Matrix4f(R[0], R[1], R[2], 0.0, R[3], R[4], R[5], 0.0,
                            R[6], R[7], R[8], 0.0, p.x, p.y, p.z, 1.0)
        return dataclasses.replace(self.sub, position=p,
                                   light_from_world=mi.Transform4f(m, inv_t))

    def sub_view(self, k) -> "SubView":
        """Sub-view ``k`` addressing the faces of the shared map (:class:`SubView`)."""
        k = mi.UInt32(k)
        return SubView(self.kind, self.position, self.light_from_world, self.light_size,
                       self.ignore_shape, self.light_normal, self.label,
                       inner=self.lane(k), offset=k * self.sub.n_faces)

    def emits_towards(self, k, p_world: mi.Point3f) -> mi.Bool:
        """Whether light point ``k`` emits towards ``p_world``: in front of its normal
        (always True for points without one) and with radiance there (``radiant``)."""
        t = self._tables
        k = mi.UInt32(k)
        out = mi.Bool(True)
        if self.radiant and not all(self.radiant):
            out = dr.gather(mi.Bool, t["radiant"], k)
        if self.inside_only is not None:
            c, r = self.inside_only        # opaque: a moved light compiles nothing
            out &= (dr.squared_norm(mi.Point3f(p_world) - opaque_point(c))
                    < opaque_scalar(r * r))
        if "normal" not in t:
            return out
        n = t["normal"] if len(self.normals) == 1 else dr.gather(mi.Vector3f, t["normal"], k)
        return out & (dr.dot(n, mi.Point3f(p_world) - dr.gather(mi.Point3f, t["pos"], k)) > 0)

    def weight(self, k, p_world: mi.Point3f) -> mi.Float:
        """Weight of light point ``k`` at ``p_world`` where it emits towards it (see
        ``cone``): ``cos(theta_k) / d_k^2``, the solid angle per unit area of the light
        at the receiver (the density of Mitsuba's cone sampling over the sphere's area,
        up to a factor shared by all the points), or 1 for lights without ``cone``."""
        if not self.cone:
            return mi.Float(1.0)
        t = self._tables
        k = mi.UInt32(k)
        d = mi.Point3f(p_world) - dr.gather(mi.Point3f, t["pos"], k)
        n = t["normal"] if len(self.normals) == 1 else dr.gather(mi.Vector3f, t["normal"], k)
        d2 = dr.squared_norm(d)
        return dr.maximum(dr.dot(n, d), 0.0) * dr.rsqrt(d2) / d2

    def cone_view(self, p_world: mi.Point3f, u: mi.Point2f):
        """A point of the sphere (``sphere``) drawn as Mitsuba draws a light sample of
        it from ``p_world`` -- uniformly in the cone it subtends, ``u`` in ``[0, 1)^2`` --
        and the view of its stratum: ``(k, d, outside)``, ``d`` the unit direction from
        ``p_world`` to the point, ``outside`` False where ``p_world`` is inside the
        sphere (which lights it from no point). Each view ``k`` is so drawn with the
        probability of the solid angle its stratum subtends: averaging the views' hard
        shadows over such draws estimates the cone's visibility without the
        ratio-of-sums bias of a weighted subset."""
        t = self._tables
        sp = self.sphere
        c, r = opaque_point(sp[:3]), opaque_scalar(sp[3])
        p = mi.Point3f(p_world)
        dc = c - p
        d2 = dr.squared_norm(dc)
        outside = d2 > r * r
        inv_dist = dr.rsqrt(dr.maximum(d2, 1e-30))
        sin_a = dr.minimum(r * inv_dist, 1.0)
        cos_a = dr.safe_sqrt(1.0 - sin_a * sin_a)
        d = mi.Frame3f(dc * inv_dist).to_world(mi.warp.square_to_uniform_cone(u, cos_a))
        b = dr.dot(d, dc)
        dist = b - dr.safe_sqrt(r * r - (d2 - b * b))     # the near hit
        q = (p + dist * d - c) / r
        M = t["sphere_inv"]
        local = mi.Vector3f(q.x * M[0] + q.y * M[3] + q.z * M[6],
                            q.x * M[1] + q.y * M[4] + q.z * M[7],
                            q.x * M[2] + q.y * M[5] + q.z * M[8])
        cell = stratified_cell(mi.warp.uniform_sphere_to_square(dr.normalize(local)),
                               self.n_views)
        return dr.gather(mi.UInt32, t["cells"], cell), d, outside

    def _split(self, face):
        face = mi.UInt32(face)
        k = face // self.sub.n_faces
        return k, face - k * self.sub.n_faces

    # ------------------------------------------------------------ the interface
    def texel_rays(self, res: int):
        return self.texel_rays_at(res, dr.arange(mi.UInt32, self.n_faces * res * res))

    def texel_rays_at(self, res: int, idx):
        face, s, t = unit_grid_at(idx, res)
        k, f = self._split(face)
        return self.lane(k).ray_through(f, mi.Point2f(0.5 * (s + 1.0), 0.5 * (t + 1.0)))

    def built_texels(self, res: int):
        """The texels the lookup can read, where not all (:meth:`LightView.built_texels`):
        for a one-sided planar light's cube sub-views (``lookup_reach``), the texels in
        front of its plane, the same in every sub-view (:func:`front_texels`).

        Why no lookup reads the others: ``multiview`` looks view ``k`` up only where its
        point emits towards the receiver ``p`` (:meth:`emits_towards`: ``n . (p - x_k) >
        0``, ``n`` the shared normal, ``x_k`` the point). In face coordinates ``(s, t)`` of
        cube face ``f`` the direction ``cube_dir(f, s, t)`` has ``A_f(s, t) = n .
        cube_dir(f, s, t)``, affine in ``(s, t)`` with a gradient of norm <= 1. The
        receiver moved by its normal offset (at most ``offset`` texels of ``2 m / res``,
        ``m`` the major component of ``p - x_k``) projects where ``A_f > -2 offset / (res
        - 2 offset)``; a tap of ``taps`` texels more lies at most ``2 taps / res`` farther
        (off the face, re-projected onto a neighbour: ``A`` divided by a major >= 1,
        nearer 0). A texel whose corners all have ``A_f <= -eta`` (that bound plus
        1e-4 for rounding) is never read, and is not traced (+inf)."""
        if self.lookup_reach is None:
            return None
        F = self.sub.n_faces
        local, faces = front_texels(self.normals[0], res, *self.lookup_reach)
        if len(local) == F * res * res:
            return None
        K, T = self.n_views, len(local)
        table = mi.UInt32(local)
        q = dr.arange(mi.UInt32, K * T)
        k = q // T
        return k * (F * res * res) + dr.gather(mi.UInt32, table, q - k * T), K * faces

    def ray_through(self, face, uv_light: mi.Point2f):
        k, f = self._split(face)
        return self.lane(k).ray_through(f, uv_light)

    def project(self, p_world: mi.Point3f):
        """The projection into sub-view 0 (lookups project into each
        :meth:`sub_view` themselves)."""
        return self.sub_view(0).project(p_world)

    def uv_on_face(self, face, p_world: mi.Point3f) -> mi.Point2f:
        k, f = self._split(face)
        return self.lane(k).uv_on_face(f, p_world)

    def direction_to_light(self, p_world: mi.Point3f) -> mi.Vector3f:
        """Towards the template's light (the centre; a directional light's axis)."""
        return self.sub.direction_to_light(p_world)

    def direction_to_light_on_face(self, face, p_world: mi.Point3f) -> mi.Vector3f:
        """Towards the light point of ``face``'s view (an environment region's own
        direction, a multi-view light point), not the template's."""
        k, _ = self._split(face)
        return self.lane(k).direction_to_light(p_world)

    def texel_world_size(self, res: int, depth, p_world=None, n_world=None):
        return self.sub.texel_world_size(res, depth, p_world, n_world)

    def texel_parallel_size(self, res: int, face, p_world, texel_world):
        k, f = self._split(face)
        return self.lane(k).texel_parallel_size(res, f, p_world, texel_world)

    def tap_texel(self, face, xy_texel: mi.Point2f, res: int, cross_seams: bool = True):
        k, f = self._split(face)
        f2, i, j, inside = self.lane(k).tap_texel(f, xy_texel, res, cross_seams)
        return mi.UInt32(f2) + k * self.sub.n_faces, i, j, inside

    def light_width(self, light_size=None, angular_diameter: float = 0.0):
        return self.sub.light_width(light_size, angular_diameter)

    def map_width(self, p_world: np.ndarray) -> float:
        return self.sub.map_width(p_world)

    # Camera-independent: no fitting, no cascades, no face culling. ``cull_faces`` would
    # decide the faces of K views per render (K passes over the camera's points, which
    # costs more than a cached frame); the K views are built but for the texels behind a
    # one-sided light, which no camera's lookup reads (:meth:`built_texels`).
    def needs_camera_points(self, opts) -> bool:
        return False

    def planned_faces(self, opts, visible) -> int:
        return self.n_faces

    def describe(self) -> str:
        return (f"{self.label}: {self.kind} light, {self.n_views} x {self.sub.projection} "
                f"map ({self.n_faces} face(s))")


@dataclass(frozen=True)
class SubView(LightView):
    """View ``k`` of a :class:`MultiView`: ``inner`` (the template moved to light point
    ``k``) reading and returning the faces of the shared map (``offset = k * F``), so
    that every filter helper works on it unchanged."""
    inner: LightView | None = None
    offset: object = 0

    projection = "sub-view"

    @property
    def rays_from_point(self) -> bool:
        return self.inner.rays_from_point

    @property
    def has_seams(self) -> bool:
        return self.inner.has_seams

    @property
    def n_faces(self) -> int:
        return self.inner.n_faces

    def ray_through(self, face, uv_light: mi.Point2f):
        return self.inner.ray_through(mi.UInt32(face) - self.offset, uv_light)

    def texel_rays(self, res: int):
        return self.inner.texel_rays(res)

    def project(self, p_world: mi.Point3f):
        face, uv, depth, inside = self.inner.project(p_world)
        return mi.UInt32(face) + self.offset, uv, depth, inside

    def uv_on_face(self, face, p_world: mi.Point3f) -> mi.Point2f:
        return self.inner.uv_on_face(mi.UInt32(face) - self.offset, p_world)

    def depth_of(self, p_world: mi.Point3f) -> mi.Float:
        return self.inner.depth_of(p_world)

    def texel_world_size(self, res: int, depth, p_world=None, n_world=None):
        return self.inner.texel_world_size(res, depth, p_world, n_world)

    def texel_parallel_size(self, res: int, face, p_world, texel_world):
        return self.inner.texel_parallel_size(res, mi.UInt32(face) - self.offset, p_world,
                                              texel_world)

    def direction_to_light(self, p_world: mi.Point3f) -> mi.Vector3f:
        return self.inner.direction_to_light(p_world)

    def tap_texel(self, face, xy_texel: mi.Point2f, res: int, cross_seams: bool = True):
        f2, i, j, inside = self.inner.tap_texel(mi.UInt32(face) - self.offset, xy_texel, res,
                                                cross_seams)
        return mi.UInt32(f2) + self.offset, i, j, inside

    def light_width(self, light_size=None, angular_diameter: float = 0.0):
        return self.inner.light_width(light_size, angular_diameter)


def as_multi_view(view: LightView) -> MultiView:
    """``view`` itself if it is a :class:`MultiView`, else a one-view MultiView of it
    (its one light point is the light's own position), so that a lookup can treat
    every map as ``K`` views."""
    if isinstance(view, MultiView):
        return view
    return MultiView(view.kind, view.position, view.light_from_world, view.light_size,
                     view.ignore_shape, view.light_normal, view.label, sub=view,
                     positions=(tuple(float(c) for c in view.position),),
                     samples=((0.5, 0.5),))


# --------------------------------------------------- texels in front of the light
#: Added to :func:`front_texels`' bound (in units of ``A``, a cube face's half width):
#: float32 rounding of the lookup's projection and of its emission test, about 1e-6.
FRONT_SLACK = 1e-4


@functools.lru_cache(maxsize=4)
def front_texels(normal: tuple, res: int, offset: float, taps: float):
    """``(local, faces)``: the flat indices (``numpy`` uint32, read-only) of the texels
    of a cube view's six faces that a lookup of a light point emitting along ``normal``
    can read (:meth:`MultiView.built_texels`), and how many faces hold any. A texel is
    kept where the largest ``A_f = normal . cube_dir(f, s, t)`` at its corners exceeds
    ``-(2 offset / (res - 2 offset) + 2 taps / res +`` :data:`FRONT_SLACK` ``)``
    (``offset``, ``taps``: :attr:`MultiView.lookup_reach`); every texel where ``res <=
    2 offset``. The face looking behind the light (``A_f`` < 0 at its four corners)
    holds none, its four sides about half."""
    n = res * res
    if res <= 2.0 * offset:
        return np.arange(6 * n, dtype=np.uint32), 6
    eta = 2.0 * offset / (res - 2.0 * offset) + 2.0 * taps / res + FRONT_SLACK
    nrm = np.asarray(normal, dtype=np.float64)
    edges = np.arange(res + 1, dtype=np.float64) * (2.0 / res) - 1.0   # texel corners
    kept = []
    for f in range(6):
        a, sign = f // 2, 1.0 if f % 2 == 0 else -1.0
        n_s, n_t = nrm[(a + 1) % 3], nrm[(a + 2) % 3]
        # A_f is affine in (s, t): its largest corner value, per column and per row
        best_s = np.maximum(n_s * edges[:-1], n_s * edges[1:])
        best_t = np.maximum(n_t * edges[:-1], n_t * edges[1:])
        kept.append((sign * nrm[a] + best_t[:, None] + best_s[None, :]).ravel() > -eta)
    local = np.flatnonzero(np.concatenate(kept)).astype(np.uint32)
    local.setflags(write=False)
    return local, int(sum(bool(k.any()) for k in kept))


# ------------------------------------------------------------------ the factory
class _Direction:
    """A stand-in emitter for :func:`~.ortho.directional_view`, which reads only
    ``world_transform()``: light travelling along ``d``."""

    def __init__(self, d):
        self._T = look_along_np((0.0, 0.0, 0.0), d).inverse()

    def world_transform(self):
        return mi.Transform4f(self._T.matrix)


def _normals(n: np.ndarray) -> tuple:
    """The normals field: one shared normal when all agree (a planar light)."""
    if np.all(np.abs(n - n[0]) <= 1e-6):
        return (tuple(float(c) for c in n[0]),)
    return tuple(map(tuple, n.tolist()))


#: Largest tan(half field of view) of a planar area light's perspective sub-views; wider
#: scenes get cube maps. One face of tan t holds the centre's texel density of a cube
#: face at t x the resolution, i.e. t^2 faces' texels: cheaper than 6 faces up to ~2.4.
MAX_TAN = 2.0


def _shape_points(shape):
    """Points whose convex hull holds ``shape``: a mesh's vertices (exact; Mitsuba's
    merged meshes even report an invalid bbox), else its bbox corners; None if
    neither is known."""
    if shape.is_mesh() and hasattr(shape, "vertex_positions_buffer"):
        return shape.vertex_positions_buffer().numpy().reshape(-1, 3).astype(np.float64)
    b = shape.bbox()
    if not b.valid():
        return None
    lo, hi = [float(c) for c in b.min], [float(c) for c in b.max]
    return np.array([[(hi if (c >> a) & 1 else lo)[a] for a in range(3)] for c in range(8)])


#: The last :func:`_frustum_tan` answer: (key, buffers kept alive, tan).
_TAN_MEMO: list = [None, None, None]


def _frustum_tan(scene, own_shape, light_from_world, points: np.ndarray):
    """tan of the half field of view of a square frustum along ``light_from_world``'s
    +z that, from every one of the light ``points`` (all in the light's plane), covers
    every shape but the light's own (their vertices or bbox corners: ``|x - x_k| / z``
    is largest at a vertex), grown by 2 %; None when a shape reaches the light's plane
    or needs more than :data:`MAX_TAN` (then cube maps). O(vertices), remembered for
    unchanged vertex buffers (JIT indices) and light points."""
    own = own_shape.emitter()
    shapes = [sh for sh in scene.shapes() if own is None or sh.emitter() is not own]
    buffers = [sh.vertex_positions_buffer() if sh.is_mesh()
               and hasattr(sh, "vertex_positions_buffer") else None for sh in shapes]
    M = np.array(light_from_world.matrix, dtype=np.float64)
    key = (tuple(M.ravel()), points.tobytes(),
           tuple((id(sh), b.index if b is not None else repr(sh.bbox()))
                 for sh, b in zip(shapes, buffers)))
    if _TAN_MEMO[0] == key:
        return _TAN_MEMO[2]
    R, t = M[:3, :3], M[:3, 3]
    pl = points @ R.T + t                       # light points in the light frame
    lo, hi, z_top = pl[:, :2].min(axis=0), pl[:, :2].max(axis=0), pl[:, 2].max()
    tan, scale = 0.0, float(np.max(np.abs(pl))) + 1e-30
    for sh in shapes:
        v = _shape_points(sh)
        if v is None:
            tan = math.inf
            break
        if len(v) == 0:
            continue
        q = v @ R.T + t
        z = q[:, 2] - z_top
        scale = max(scale, float(np.max(np.abs(q))))
        if np.any(z <= 1e-3 * scale):
            tan = math.inf
            break
        lateral = np.maximum(np.abs(q[:, :2] - lo), np.abs(q[:, :2] - hi)).max(axis=1)
        tan = max(tan, float(np.max(lateral / z)))
    tan = 1.02 * tan if 0.0 < tan <= MAX_TAN / 1.02 else None
    _TAN_MEMO[:] = [key, buffers, tan]
    return tan


def _radiant(emitter, ps) -> tuple:
    """Per light point of ``ps`` (positions on an area emitter's shape): whether its
    front side emits (a valid sample, ``pdf`` > 0, with radiance > 0 at some of a few
    wavelengths: in spectral variants eight fixed ones and, where the emitter can
    sample them (``sample_wavelengths``; a ``checkerboard`` cannot), four drawn from its
    own spectrum at the point. The fixed ones alone missed a narrow-band emitter (an
    ``irregular`` spectrum between 400 and 440 nm): ``multiview`` rendered it black,
    its AOV 0, where ``raytraced`` read 0.23)."""
    si = dr.zeros(mi.SurfaceInteraction3f, dr.width(ps.p))
    si.p, si.n, si.uv, si.time = ps.p, ps.n, ps.uv, ps.time
    si.sh_frame = mi.Frame3f(ps.n)
    si.wi = mi.Vector3f(0.0, 0.0, 1.0)            # leaving the front side
    lit = np.zeros(dr.width(ps.p), bool)
    waves = [(450.0, 550.0, 650.0, 750.0), (400.0, 500.0, 600.0, 700.0)] \
        if mi.is_spectral else [None]
    if mi.is_spectral:
        try:
            drawn, _ = emitter.sample_wavelengths(si, dr.full(mi.Float, 0.5, dr.width(ps.p)))
            waves.append(drawn)
        except RuntimeError:   # a texture that cannot sample its spectrum
            pass
    for w in waves:
        if w is not None:
            si.wavelengths = w if not isinstance(w, tuple) else type(si.wavelengths)(*w)
        value = unpolarized(emitter.eval(si))
        lit |= (dr.max(value) > 0).numpy() if dr.width(value) else False
    lit &= np.broadcast_to(ps.pdf.numpy() > 0, lit.shape)
    return tuple(bool(x) for x in lit)


def _tracks_gradients(emitter) -> bool:
    """Whether any of ``emitter``'s emitted values (``radiance``, ``intensity``,
    ``irradiance`` and their textures' parameters) has gradients enabled, whatever the
    AD scope (the primal pass of ``mi.render(scene, params)`` runs under
    ``dr.suspend_grad()``, and must see the views the derivative pass sees)."""
    params = mi.traverse(emitter)
    with dr.resume_grad():
        return any(dr.grad_enabled(params[k]) for k in params.keys()
                   if k.split(".")[0] in ("intensity", "radiance", "irradiance"))


def multi_view(view: LightView, emitter, scene, views: int, light_size=None,
               angular_diameter: float = 0.0, lookup_reach=None) -> MultiView | None:
    """The :class:`MultiView` of ``views`` light points of an emitter whose ordinary
    view is ``view`` (see the module doc), or None for a light without extent
    (point/spot/projector with ``light_size`` 0 or None, directional with
    ``angular_diameter`` 0): its ordinary map is then the one view. ``lookup_reach``
    (``(offset, taps)`` in texels, see :attr:`MultiView.lookup_reach`): kept for a
    planar area light (one normal, which every area emitter of Mitsuba 3.9 emits along
    only: it has no two-sided one) with cube sub-views, whose build then skips what is
    behind it; other lights (spheres, curved or closed meshes: their points' views are
    read behind their normals) build every texel."""
    from .ortho import directional_view
    K = int(views)
    u = stratified_points(K)
    base = dict(kind=view.kind, position=view.position,
                light_from_world=view.light_from_world, light_size=view.light_size,
                ignore_shape=view.ignore_shape, light_normal=view.light_normal,
                label=view.label)
    samples = tuple(tuple(float(c) for c in s) for s in u)
    if view.kind == "area":
        # The emitter's own position sampling: the shape's by area, or, for a textured
        # (spatially varying) radiance, the texture's importance sampling mapped onto the
        # shape -- exactly where Mitsuba's sample_direction puts such a light's samples
        # (never on a black texel, more on bright ones).
        ps, _ = emitter.sample_position(0.0, mi.Point2f(mi.Float(u[:, 0]),
                                                        mi.Float(u[:, 1])))
        textured = mi.has_flag(emitter.flags(), mi.EmitterFlags.SpatiallyVarying)
        p = np.stack([c.numpy() for c in ps.p], axis=1).astype(np.float64)
        n = np.stack([c.numpy() for c in ps.n], axis=1).astype(np.float64)
        sub = view
        if view.light_normal is not None:   # planar: one perspective face if it covers all
            lfw = look_along_np(position_np(view), view.light_normal)
            tan = _frustum_tan(scene, emitter.get_shape(), lfw, p)
            if tan is not None:
                from .perspective import PerspectiveView
                sub = dataclasses.replace(PerspectiveView(**base, tan_half=tan),
                                          light_from_world=lfw)
        shape = emitter.get_shape()
        sphere = shape.class_name() == "Sphere"
        if sphere:
            # Mitsuba's Sphere::sample_position rotates its points by the shape's
            # to_world but returns the unrotated normals: a rotated sphere light's
            # points then emitted (and were weighted) as if they lay elsewhere on it
            # (rotated 70 degrees about z: the AOV 0.0134 above raytraced's). The
            # normal of a sphere's point is its direction from the centre.
            b = shape.bbox()
            n = p - np.array([float(c) for c in b.center()])
            n /= np.linalg.norm(n, axis=1, keepdims=True)
            if shape.has_flipped_normals():
                n = -n
        inside = None
        if sphere and shape.has_flipped_normals():
            b = shape.bbox()
            inside = (tuple(float(c) for c in b.center()),
                      0.5 * float(b.max[0] - b.min[0]))
        # Mitsuba samples a uniform sphere light in the cone it subtends from a receiver
        # outside it (uniformly by area from inside: a flipped sphere's receivers, which
        # are all inside, keep equal weights); a textured one through its texture.
        cone_sampled = sphere and not textured
        cone = cone_sampled and inside is None
        sp, cells = ((), ())
        if cone:
            b = shape.bbox()
            sp, cells = _sphere_cells(u, p, tuple(float(c) for c in b.center()),
                                      0.5 * float(b.max[0] - b.min[0]))
        radiant = _radiant(emitter, ps)
        dark = not any(radiant) and _tracks_gradients(emitter)
        if dark:   # a tracked 0: every valid point, for the derivative image
            radiant = tuple(bool(x) for x in np.broadcast_to(ps.pdf.numpy() > 0, (K,)))
        normals = _normals(n)
        # (a light of zero area has no normal: NaN; it keeps every texel, as before)
        planar_cube = (len(normals) == 1 and not sphere and sub.projection == "cube"
                       and sub.n_faces == 6 and np.all(np.isfinite(normals[0]))
                       and abs(np.linalg.norm(normals[0]) - 1.0) < 1e-3)
        return MultiView(**base, sub=sub, positions=tuple(map(tuple, p.tolist())),
                         normals=normals, samples=samples, radiant=radiant, dark=dark,
                         count_all=not cone_sampled,
                         cone=cone, inside_only=inside, sphere=sp, cells=cells,
                         lookup_reach=(None if lookup_reach is None or not planar_cube
                                       else tuple(float(x) for x in lookup_reach)))
    if view.kind in ("point", "spot", "projector"):
        size = float(light_size or 0.0)
        if size <= 0.0:
            return None
        centre = position_np(view)
        if view.kind == "point":   # uniform on the sphere of diameter `size`
            w = mi.warp.square_to_uniform_sphere(mi.Point2f(mi.Float(u[:, 0]),
                                                             mi.Float(u[:, 1])))
            n = np.stack([c.numpy() for c in w], axis=1).astype(np.float64)
            p = centre + 0.5 * size * n
            sp, cells = _sphere_cells(u, p, tuple(float(c) for c in centre), 0.5 * size)
            return MultiView(**base, sub=view, positions=tuple(map(tuple, p.tolist())),
                             normals=tuple(map(tuple, n.tolist())), samples=samples,
                             cone=True, sphere=sp, cells=cells)
        # spot, projector: a square of side `size` across the axis, same frame otherwise
        R = np.array(view.light_from_world.matrix, dtype=np.float64)[:3, :3]
        offsets = np.stack([u[:, 0] - 0.5, u[:, 1] - 0.5, np.zeros(K)], axis=1) * size
        p = centre + offsets @ R   # rows of R are the light axes in world space
        return MultiView(**base, sub=view, positions=tuple(map(tuple, p.tolist())),
                         samples=samples)
    if view.kind == "directional":
        if angular_diameter <= 0.0:
            return None
        L = np.array(view.light_from_world.matrix, dtype=np.float64)[:3, :3]
        t = math.tan(math.radians(angular_diameter) * 0.5)
        disk = mi.warp.square_to_uniform_disk_concentric(mi.Point2f(mi.Float(u[:, 0]),
                                                                    mi.Float(u[:, 1])))
        dirs = np.stack([disk.x.numpy() * t, disk.y.numpy() * t, np.ones(K)], axis=1) @ L
        dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
        subs = [directional_view(_Direction(d), scene, view.label) for d in dirs]
        half = tuple(max(v.half_extent[a] for v in subs) for a in range(2))
        template = dataclasses.replace(subs[0], half_extent=half)
        return MultiView(**base, sub=template,
                         positions=tuple(tuple(position_np(v).tolist()) for v in subs),
                         rotations=tuple(tuple(np.array(v.light_from_world.matrix,
                                                        dtype=np.float64)[:3, :3].ravel())
                                         for v in subs),
                         samples=samples)
    return None
