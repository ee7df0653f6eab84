"""A view of a virtual map's level, in coordinates local to each lookup (:class:`LocalView`).

Virtual maps (:mod:`mi_shadowmap.virtual`) address up to ``2^30`` texels per face
side. Continuous texel coordinates that large do not fit a float32 (24 bits),
so every lookup is *bound* to a local frame: its face, its level's resolution
``res_level`` (per lane) and an integer ``origin`` (the first texel of the
2 x 2 pages around the receiver, per lane). Towards the filters, a
:class:`LocalView` is an ordinary :class:`~.base.LightView` whose face has
``res_level`` texels per side and whose ``uv_light * res_level`` are the
texel coordinates *minus* ``origin``: small numbers, exact in float32. It
computes every projection in float64 through the wrapped view's
``*_f64`` methods and knows nothing of any projection itself.

Depths: a far light's pages hold depths measured from ``depth_origin``
along each texel's ray (:attr:`mi_shadowmap.virtual.VirtualLayout.t0`, a box
diagonal before the scene), so every depth a :class:`LocalView` returns
(:meth:`~LocalView.project`, :meth:`~LocalView.depth_of`,
:meth:`~LocalView.ray_plane`) is the float64 distance from the light minus
``depth_origin``, rounded to float32 only then (or, near the bound point, that
rounded depth plus a small float32 step: see :meth:`~LocalView.ray_plane`, whose
receiver-plane depths agree with float64 ones to a few float32 roundoffs; in
float64 a filter's taps cost ``pcf`` up to 0.21 and ``pcss`` up to 0.74 of an
unshadowed frame more, ``benchmarks/RESULTS.md``, 2026-12-03). Measured from the light
itself, a depth 1e9 away would round to 64 units, and the receivers' lowering
below (24 units at 1e8) would lose every shadow of a scene 10 units wide
(``far_point.xml`` before: 2.3 of its 3.1 % shadow lost at 1e7, all at 1e8). The
receiver depth is lowered by ``DEPTH_ULPS`` float32 roundoffs of itself,
because a map depth and a receiver depth are each rounded to float32 once
(relative 2^-24). Filters that need the distance from the light itself
(PCSS's similar triangles) add :attr:`LocalView.depth_origin` back.
"""
from __future__ import annotations

import drjit as dr
import mitsuba as mi

from ..control_flow import if_stmt
from .base import opaque_point, pow2_reciprocal

#: Receiver depths are lowered by this many float32 roundoffs (2^-24 relative) of
#: themselves: the map's and the receiver's float32 roundings together, with margin.
DEPTH_ULPS = 4.0


def _same_point(a, b) -> bool:
    """Whether ``a`` and ``b`` are the same point (the same object, or the same JIT
    variables per component, as ``mi.Point3f(p)`` of a ``Point3f`` gives)."""
    if a is b:
        return True
    try:
        return type(a) is type(b) and all(x.index == y.index and x.index != 0
                                          for x, y in zip(a, b))
    except (AttributeError, TypeError):
        return False


class LocalView:
    """One lookup's local frame of a virtual map's view (see the module doc).

    ``inner``: the emitter's view (with float64 methods); ``face``
    (``mi.UInt32``), ``res_level`` (``mi.Int32``) and ``origin``
    (``mi.Point2i``), per lane.
    """

    projection = "local"

    @property
    def taps_cross_seams(self) -> bool:
        """Whether a filter's tap off the face continues on the neighbouring face (a
        cube map's seam; the filters read it through
        :func:`~mi_shadowmap.filters.common.taps_cross_seams`): False on a view with
        seams (a cube, :attr:`~.base.LightView.has_seams`), where every tap is clamped
        to its face's border texel. The marks build each point's tiles on its own face
        only, so a tap across the seam read the coarsest level there, a texel 4 times as
        wide whose depth lies in front of the receiver's plane: ``pcf`` beside
        cbox_area's seams erred 0.140 against ``raytraced``, 0.061 clamped (full maps
        0.070); building and reading the neighbouring face's tiles (0.073) cost 3.9 %
        more texels and ~8 % of ``pcf``'s render (``benchmarks/RESULTS.md``, fifty-third
        session, helpers A and E). True on a view without seams (spot, sun, a sun's
        cascades, an environment's regions): a tap off its face is off the map, lit, as
        on a full map (cascades, several faces, were clamped too: 131 of 96^2 pixels of
        directional_mesh's wide-kernel ``pcf`` changed, by up to 0.125)."""
        return not self.inner.has_seams

    def __init__(self, inner, face, res_level, origin, bound=None, depth_origin=None,
                 lazy_frame: bool = False):
        self.inner = inner
        self.face = mi.UInt32(face)
        self.res_level = mi.Int32(res_level)
        self.origin = mi.Point2i(origin)
        # (p_world, uv64 on the bound face, depth64, inside) of the point the lookup was
        # bound at: projecting that same point again reuses them (same Python object)
        self._bound = bound
        # mi.Float64 (opaque) where the map's depths start along its rays, or None: from
        # the light (see the module doc)
        self._depth_origin = depth_origin
        # the bound point's ray frame (ray_plane's float32 path), made here: outside the
        # filters' symbolic tap loops (unused, it costs nothing in a kernel). With
        # ``lazy_frame`` (a per-tap lookup's binds: ``hard`` never reads it) it is made
        # where it is first read (:attr:`_frame`): unread, its ~40 operations cost the
        # trace of every frame, twice a ``hard`` lookup (its two binds)
        self._lazy = bool(lazy_frame)
        self._bind_scoped = dr.flag(dr.JitFlag.SymbolicScope)
        self._frame_made = None if self._lazy else self._make_frame()

    def _make_frame(self):
        frame = getattr(self.inner, "ray_frame_f64", None)
        if self._bound is None or frame is None:
            return None
        p0, uv64, depth64, _ = self._bound
        central, base, a, b = frame(self.face, mi.Point2d(uv64))
        return (central, mi.Vector3f(base), mi.Vector3f(a), mi.Vector3f(b),
                self._to_local_uv(uv64), mi.Float(depth64), self._from_origin(depth64))

    @property
    def _frame(self):
        """The bound point's ray frame (see ``__init__``), or None. A lazy frame first
        read inside a symbolic loop or conditional is made there again at every read
        (the same values; kept, its variables would outlive their scope); it is kept
        where both the bind and the read were outside every symbolic operation."""
        if not self._lazy or self._frame_made is not None:
            return self._frame_made
        made = self._make_frame()
        if not self._bind_scoped and not dr.flag(dr.JitFlag.SymbolicScope):
            self._frame_made = made
        return made

    @property
    def depth_origin(self):
        """Where the map's depths start along each texel's ray (``mi.Float``), or 0.0
        (from the light): a depth here plus this is the distance from the light."""
        return 0.0 if self._depth_origin is None else mi.Float(self._depth_origin)

    def _from_origin(self, depth64) -> mi.Float:
        """A float64 distance from the light as this map measures it, in float32."""
        if self._depth_origin is None:
            return mi.Float(depth64)
        return mi.Float(mi.Float64(depth64) - self._depth_origin)

    def __getattr__(self, name):   # kind, position, light_size, light_normal, label, ...
        return getattr(self.inner, name)

    @property
    def n_faces(self) -> int:
        return self.inner.n_faces

    # ------------------------------------------------------ local <-> global
    # Both through the level resolution's exact reciprocal (pow2_reciprocal): the same
    # values as dividing (Dr.Jit divides a Point2d by a Float64 as a product with its
    # reciprocal, 1 / 2^k, exact), without two float64 divisions a 16-lane packet.
    def _to_local_uv(self, uv64) -> mi.Point2f:
        res = mi.Float64(self.res_level)
        xy = mi.Point2d(uv64) * res - mi.Point2d(self.origin)
        return mi.Point2f(xy * pow2_reciprocal(self.res_level, mi.Float64))

    def _to_global_uv(self, uv_local) -> mi.Point2d:
        res = mi.Float64(self.res_level)
        return ((mi.Point2d(uv_local) * res + mi.Point2d(self.origin))
                * pow2_reciprocal(self.res_level, mi.Float64))

    def _lowered(self, depth) -> mi.Float:
        depth = mi.Float(depth)
        return depth - dr.abs(depth) * (DEPTH_ULPS * 2.0 ** -24)

    # ----------------------------------------------------------- interface
    def _near_bound(self, p_world):
        """``(uv_local, depth)`` of ``p_world`` from the bound point's float64
        projection plus the first-order change for the small step between them, in
        float32 (a normal offset of a texel or a pixel footprint: the step is exact in
        float32 as a difference of nearby points, and the second-order term is
        ``(step / distance)^2`` of it)."""
        p0, uv64, depth64, _ = self._bound
        if p_world is p0:
            return self._to_local_uv(uv64), self._from_origin(depth64)
        dp = mi.Point3f(p_world) - mi.Point3f(p0)
        duv = self.inner.uv_differential(self.face, p0, dp)
        return (self._to_local_uv(uv64) + duv,
                self._from_origin(depth64) + self.inner.depth_differential(p0, dp))

    def project(self, p_world):
        """Expressed on the bound face (a point that crossed a cube seam gets
        off-face coordinates there, which :meth:`tap_texel` continues across)."""
        if self._bound is not None:
            uv, depth = self._near_bound(p_world)
            return mi.UInt32(self.face), uv, self._lowered(depth), self._bound[3]
        p64 = mi.Point3d(p_world)
        _, _, depth, inside = self.inner.project_f64(p64)
        uv64 = self.inner.uv_on_face_f64(self.face, p64)
        return (mi.UInt32(self.face), self._to_local_uv(uv64),
                self._lowered(self._from_origin(depth)), inside)

    def uv_on_face(self, face, p_world):
        if self._bound is not None:
            return self._near_bound(p_world)[0]      # the bound face (see project)
        return self._to_local_uv(self.inner.uv_on_face_f64(face, mi.Point3d(p_world)))

    def depth_of(self, p_world) -> mi.Float:
        if self._bound is not None:
            return self._lowered(self._near_bound(p_world)[1])
        return self._lowered(self._from_origin(self.inner.project_f64(mi.Point3d(p_world))[2]))

    def ray_through(self, face, uv_light):
        """In float64; for central rays on the bound face (a one-sided area light's
        front test in PCSS's taps), from the bound point's ray frame in float32 (the
        unnormalised direction there plus the ``uv`` step's, normalised)."""
        frame = self._frame
        if frame is None or not frame[0]:
            return self._ray_through_f64(face, uv_light)
        _, base, a, b, uv0 = frame[:5]
        duv = mi.Point2f(uv_light) - uv0
        o, d = opaque_point(self.inner.position), dr.normalize(base + a * duv.x + b * duv.y)
        if self.inner.n_faces == 1:
            return o, d
        return if_stmt((mi.UInt32(face), mi.Point2f(uv_light), o, d),
                       mi.UInt32(face) != self.face,
                       lambda f, uv, o, d: self._ray_through_f64(f, uv),
                       lambda f, uv, o, d: (o, d), label="LocalView.ray_through: another face")

    def _ray_through_f64(self, face, uv_light):
        o, d = self.inner.ray_through_f64(face, self._to_global_uv(uv_light))
        return mi.Point3f(o), mi.Vector3f(d)

    def ray_plane(self, face, uv_light, p_world, n_world, cos_min: float):
        """Where the ray through ``uv_light`` of ``face`` meets the plane through
        ``p_world`` with normal ``n_world`` (see :meth:`~.base.LightView.ray_plane`).

        For the plane through the bound point (a filter's receiver plane) on the bound
        face, and a wrapped view with :attr:`~.base.LightView.ray_frame_f64`: in float32,
        as the bound point's depth plus the change from its own ray to the tap's
        (:meth:`_plane_step`), exact up to float32 rounding of that change. Else, and
        for lanes of taps that crossed onto another face (a ``dr.if_stmt``), in float64:
        ``p_world - o`` in float32 would lose the light's distance's roundoff."""
        frame = self._frame
        if frame is None or not _same_point(p_world, self._bound[0]):
            return self._ray_plane_f64(face, uv_light, p_world, n_world, cos_min)
        t, c = self._plane_step(uv_light, n_world, cos_min, frame)
        if self.inner.n_faces == 1:
            return t, c
        return if_stmt(
            (mi.UInt32(face), mi.Point2f(uv_light), mi.Vector3f(n_world), t, c),
            mi.UInt32(face) != self.face,
            lambda f, uv, n, t, c: self._ray_plane_f64(f, uv, p_world, n, cos_min),
            lambda f, uv, n, t, c: (t, c), label="LocalView.ray_plane: another face")

    def _ray_plane_f64(self, face, uv_light, p_world, n_world, cos_min: float):
        o, d = self.inner.ray_through_f64(face, self._to_global_uv(uv_light))
        n = mi.Vector3d(n_world)
        c = dr.dot(n, d)
        t = dr.dot(n, mi.Point3d(p_world) - o) / dr.select(dr.abs(c) >= cos_min, c, cos_min)
        return self._lowered(self._from_origin(t)), mi.Float(c)

    def _plane_step(self, uv_light, n_world, cos_min: float, frame=None):
        """:meth:`ray_plane` for the bound point's plane on the bound face, in float32.

        The receiver ``p`` lies on its own ray (through its float64 ``uv``, at its depth
        ``t0``), so only the change to the tap's ray is computed, from the
        ``uv`` step (local coordinates: small and exact in float32) and the view's
        affine ray frame. Parallel rays (unit direction ``d``, origin moved by ``o``):
        ``t = t0 - n.o / n.d``. Central rays (unnormalised directions ``D0`` and
        ``D = D0 + e``): ``t = K |D| / n.D`` with ``K = t0 n.D0 / |D0|``, so
        ``t - t0 = t0 (c0 - c) / c`` with ``c0 - c = (n.D0 (|D| - |D0|) - |D0| n.e) /
        (|D0| |D|)`` and ``|D| - |D0| = (2 D0.e + e.e) / (|D| + |D0|)``: no difference
        of two nearly equal float32 numbers. ``c`` below ``cos_min`` is clamped, as in
        float64."""
        central, base, a, b, uv0, t0_light, t0_local = (self._frame if frame is None
                                                         else frame)
        n = mi.Vector3f(n_world)
        duv = mi.Point2f(uv_light) - uv0
        e = a * duv.x + b * duv.y
        if central:
            D = base + e
            l0, l1 = dr.norm(base), dr.norm(D)
            c = dr.dot(n, D) / l1
            num = dr.dot(n, base) * (2.0 * dr.dot(base, e) + dr.dot(e, e)) / (l1 + l0) \
                - l0 * dr.dot(n, e)
            cc = dr.select(dr.abs(c) >= cos_min, c, cos_min)
            dt = t0_light * (num / (l0 * l1)) / cc
        else:
            c = dr.dot(n, base)
            cc = dr.select(dr.abs(c) >= cos_min, c, cos_min)
            dt = -dr.dot(n, e) / cc
        return self._lowered(t0_local + dt), c

    def texel_world_size(self, res, depth, p_world=None, n_world=None):
        """``depth`` as this view measures it (from :attr:`depth_origin`)."""
        if self._depth_origin is not None:
            depth = depth + self.depth_origin
        return self.inner.texel_world_size(res, depth, p_world, n_world)

    def texel_parallel_size(self, res, face, p_world, texel_world):
        return self.inner.texel_parallel_size(res, face, p_world, texel_world)

    def texel_parallel_xy(self, res, face, p_world, texel_world):
        xy = getattr(self.inner, "texel_parallel_xy", None)
        return None if xy is None else xy(res, face, p_world, texel_world)

    def direction_to_light(self, p_world):
        return self.inner.direction_to_light(p_world)

    def light_width(self, light_size=None, angular_diameter: float = 0.0):
        return self.inner.light_width(light_size, angular_diameter)

    def tap_texel(self, face, xy_texel, res, cross_seams: bool = True):
        """Texel of a tap at local coordinates ``xy_texel``: local ``(i, j)`` (global
        minus ``origin``); off the face, the neighbouring face's texel (cube maps) or
        ``inside`` False, as the wrapped view's :meth:`face_texel_f64` says; with
        ``cross_seams`` False clamped to the face (the filters pass
        :attr:`taps_cross_seams`: False on a cube)."""
        # floor(xy + origin) = floor(xy) + origin: the global texel in integers (the
        # local coordinates are exact in float32); only taps off the face (a symbolic
        # dr.if_stmt: packets with one) go through the wrapped view's float64 continuation
        ij = mi.Point2i(dr.floor(mi.Point2f(xy_texel))) + self.origin
        if not cross_seams:
            ij = dr.clip(ij, 0, self.res_level - 1)
            return mi.UInt32(face), ij.x - self.origin.x, ij.y - self.origin.y, mi.Bool(True)
        res = self.res_level
        in_face = (ij.x >= 0) & (ij.x < res) & (ij.y >= 0) & (ij.y < res)

        def off_face(face, xy, i, j):
            xy64 = mi.Point2d(xy) + mi.Point2d(self.origin)
            f2, i2, j2, inside = self.inner.face_texel_f64(face, xy64, res)
            return mi.UInt32(f2), mi.Int32(i2), mi.Int32(j2), mi.Bool(inside)

        def on_face(face, xy, i, j):
            return face, i, j, mi.Bool(True)

        f2, i, j, inside = if_stmt((mi.UInt32(face), mi.Point2f(xy_texel), ij.x, ij.y),
                                   ~in_face, off_face, on_face)
        return f2, i - self.origin.x, j - self.origin.y, inside

    def describe(self) -> str:
        return "local frame of " + self.inner.describe()
