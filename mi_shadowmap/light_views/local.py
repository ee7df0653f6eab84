"""A view of a virtual map's level, in coordinates local to each lookup (:class:`LocalView`).

Virtual maps (:mod:`mi_shadowmap.pages`) address up to ``2^30`` texels per face
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
along each texel's ray (:attr:`mi_shadowmap.pages.VirtualLayout.t0`, a box
diagonal before the scene), so every depth a :class:`LocalView` returns
(:meth:`~LocalView.project`, :meth:`~LocalView.depth_of`,
:meth:`~LocalView.ray_plane`) is the float64 distance from the light minus
``depth_origin``, rounded to float32 only then. Measured from the light
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

#: Receiver depths are lowered by this many float32 roundoffs (2^-24 relative) of
#: themselves: the map's and the receiver's float32 roundings together, with margin.
DEPTH_ULPS = 4.0


class LocalView:
    """One lookup's local frame of a virtual map's view (see the module doc).

    ``inner``: the emitter's view (with float64 methods); ``face``
    (``mi.UInt32``), ``res_level`` (``mi.Int32``) and ``origin``
    (``mi.Point2i``), per lane.
    """

    projection = "local"

    def __init__(self, inner, face, res_level, origin, bound=None, depth_origin=None):
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
    def _to_local_uv(self, uv64) -> mi.Point2f:
        res = mi.Float64(self.res_level)
        xy = mi.Point2d(uv64) * res - mi.Point2d(self.origin)
        return mi.Point2f(xy / res)

    def _to_global_uv(self, uv_local) -> mi.Point2d:
        res = mi.Float64(self.res_level)
        return (mi.Point2d(uv_local) * res + mi.Point2d(self.origin)) / res

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
        o, d = self.inner.ray_through_f64(face, self._to_global_uv(uv_light))
        return mi.Point3f(o), mi.Vector3f(d)

    def ray_plane(self, face, uv_light, p_world, n_world, cos_min: float):
        """In float64: ``p_world - o`` would lose the light's distance's roundoff."""
        o, d = self.inner.ray_through_f64(face, self._to_global_uv(uv_light))
        n = mi.Vector3d(n_world)
        c = dr.dot(n, d)
        t = dr.dot(n, mi.Point3d(p_world) - o) / dr.select(dr.abs(c) >= cos_min, c, cos_min)
        return self._lowered(self._from_origin(t)), mi.Float(c)

    def texel_world_size(self, res, depth, p_world=None):
        """``depth`` as this view measures it (from :attr:`depth_origin`)."""
        if self._depth_origin is not None:
            depth = depth + self.depth_origin
        return self.inner.texel_world_size(res, depth, p_world)

    def texel_parallel_size(self, res, face, p_world, texel_world):
        return self.inner.texel_parallel_size(res, face, p_world, texel_world)

    def direction_to_light(self, p_world):
        return self.inner.direction_to_light(p_world)

    def light_width(self, light_size=None, angular_diameter: float = 0.0):
        return self.inner.light_width(light_size, angular_diameter)

    def tap_texel(self, face, xy_texel, res, cross_seams: bool = True):
        """Texel of a tap at local coordinates ``xy_texel``: local ``(i, j)`` (global
        minus ``origin``); off the face, the neighbouring face's texel (cube maps) or
        ``inside`` False, as the wrapped view's :meth:`face_texel_f64` says; with
        ``cross_seams`` False clamped to the face."""
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

        f2, i, j, inside = dr.if_stmt((mi.UInt32(face), mi.Point2f(xy_texel), ij.x, ij.y),
                                      ~in_face, off_face, on_face)
        return f2, i - self.origin.x, j - self.origin.y, inside

    def describe(self) -> str:
        return "local frame of " + self.inner.describe()
