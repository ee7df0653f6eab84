"""Shadow rays whose self-intersection offset is relative to the scene (any scale).

:func:`spawn_shadow_ray` replaces Mitsuba's ``si.spawn_ray_to(p)`` in the
ground truth (:func:`mi_shadowmap.filters.raytraced.raytraced`) and in the
converged soft-shadow reference (:mod:`mi_shadowmap.reference`).

Why not Mitsuba's ray
---------------------
``Interaction::spawn_ray_to`` offsets the origin along the geometric normal by
``(1 + max|p|) * RayEpsilon`` (``RayEpsilon = 1500 * 2^-24 ~ 8.9e-5``). The
``1 +`` is an absolute floor of ~1e-4 world units: in a scene of size 1e-4 the
ray starts as far above the surface as the geometry is large, so occluders in
contact vanish; between scale 1 and 1e-4, 7-31 % of the visibility pixels of
the project's scenes changed by more than 0.05 (0.3-1.2 % at 1e-2). Its
``maxt = dist * (1 - ShadowEpsilon)`` is already relative and is kept.

Nor is ``|p|`` alone a scale: the error of a hit point is relative to the
coordinates it was computed *from*, which can be much larger than ``|p|``. A
mesh hit is re-interpolated from the triangle's vertices (``p0 b0 + p1 b1 + p2
b2``), so its error is ``~u max|v_i|`` (``u = 2^-24``): on a large tilted plane
through the origin, points near the origin are off by ``u`` times the plane's
extent. In a stress test (a tilted 2e4-unit plane through the origin, hit
points within 14 units of it, lights 0.01-10 units away) Wächter & Binder's
offset (Ray Tracing Gems, 2019: 256 integer ulps of ``p``, and ``p + n /
65536`` for ``|p| < 1/32``) re-hit the plane on 39 % of the shadow rays, an
offset of 64-1024 ulps of ``max(|p|, |target|)`` on 48-7 %, Mitsuba's on 2 %,
the one below on none. W&B's absolute fallback also drifts with scale (2-13 %
of the pixels change between scale 1 and 1e-4).

The offset used here
--------------------
For a hit on shape ``S`` at ``p``, at distance ``t`` along the camera ray::

    M     = max( sum_j |n_j| |p_j|, sum_j |n_j| max|coordinate j of bbox(S)|, [S not a mesh] * t )
    delta = k * u * M           (k = ORIGIN_ULPS = 16: meshes, spheres;
                                 k = ORIGIN_ULPS_OTHER = 64: disks, cylinders, ...)
    o     = p + delta * n                       (n: geometric normal, turned
                                                 towards the target)
    maxt  = |target - o| - short       (short: target_shortening)
    short = DELTA_ULPS * u * (max|target| + |target - o|)          delta lights
            AREA_ULPS * u * max(max|o|, max|target|, M_light) / |d . n_light|
                                                                 area lights
            max(SHADOW_EPSILON * |target - o|, TARGET_ULPS * u * max|target|)
                                                                 otherwise

* ``max|coordinate j of bbox(S)|`` bounds coordinate j of the vertices a mesh point
  is interpolated from (and a sphere's ``|centre| + radius``); weighted by the
  normal's components it bounds the rounding *off the surface*, the only one that
  makes a ray re-hit it. (The largest coordinate alone, used before, put a shadow ray
  on a flat ground 1e6 wide about 4 units above it, over 1-unit posts: their shadows
  vanished; the ground's height is exact to far better than its width.) It is looked
  up per hit in a small table indexed by the shape's registry id (built from
  ``scene.shapes()`` at each call; a hit through an ``instance``, whose shape group's
  shapes are not in the table, uses the instance's row: its world bounds; other ids
  not in it use the scene's bounding box). Curves (``linearcurve``, ``bsplinecurve``:
  one shape, every strand of a file) have 0 there: their box bounds no one strand's
  hit, which the ``t`` term covers.
* ``sum_j |n_j| |p_j|``: the origin's own rounding (``u |o_j|`` per coordinate) moves it
  off the surface by its component along the normal. (``max|p|``, used before, put a
  shadow ray from a flat ground 1e5 units along x 0.095 above it, 16 ulps of 1e5: a
  plate 0.03 above that ground lost its whole shadow, and unit-sized scenes 1e5 away had
  1.0-4.4 % of a 64^2 view misclassified against themselves at the origin, now 0.5-1.5 %,
  the rest float32's spacing of the geometry; 1e4 away 0.05-0.46 %, now 0.02-0.17 %. A
  stress test as the one below (200 shapes, 0..1e6 from the origin, half of them
  axis-aligned) found the same self-intersections with either term: rectangles 2-4,
  disks 7-8, cubes 2 in 34,000-82,000 rays per kind, spheres and cylinders none.) For a shape's own points it never exceeds the next term; it counts
  where the bounds do not hold ``p`` (curves, below; instances).
* ``t``: in the AD variants Mitsuba's non-mesh shapes (sphere, disk, cylinder,
  curves) return ``si.p = ray(t)``, whose error is relative to the camera
  ray's origin and length, not to the shape. Meshes (``rectangle`` and ``cube``
  are meshes in Mitsuba 3.9) are not affected.
* ``k``: in a stress test (random orientations, shapes of size
  1e-4..1e4 at 0..1e6 from the origin, cameras at 0.5..100 shape sizes,
  targets down to grazing) meshes, rectangles and spheres never
  self-intersected from 4 ulps up, disks from 16. 16 leaves a factor 4 for meshes and
  spheres, 64 the same for the other shapes. (64 for every shape, used before, cost
  the reference its accuracy where a scene sits far from the origin: a unit-sized
  scene 1e5 away had its shadow rays start 0.38 units above the surface, and
  misclassified 2.15 % of the pixels of its own image at the origin, 0.59 % with 16,
  against 0.2-0.3 % for the shadow maps; and a sphere 1.5e-4 wide 94 units from the
  origin was hit by 94 of 4096 of its own shadow rays, whose origins overshot it;
  ``benchmarks/RESULTS.md``, thirty-fourth session.) Cylinders seen
  from afar: Mitsuba's float32 cylinder intersection puts the hit about ``u t^2 / r``
  off the surface, beyond this offset, so a cylinder's hit is first found again from
  near it (:func:`_on_cylinders`).
* End of the ray: only what rounding needs, so an occluder right next to the light
  still counts. Mitsuba's ``ShadowEpsilon`` (8.9e-4 of the distance, used here before
  for every light and still where the caller does not say what the target is) let a
  wall 1e-4 before a light 8 units away vanish: every receiver behind it was lit
  (0.74 % "false shadow" for every map method, which were right; Mitsuba's ``direct``,
  whose ``spawn_ray_to`` ends the same way, lights that region too). A delta light's point is a point in space: the ray
  ends :data:`DELTA_ULPS` roundoffs of ``max|target| + dist`` before it (the
  direction's rounding). An area light's point lies on its surface, which the tracer
  finds again within ``k u M / |cos|`` of it along the ray (``M``: the coordinates the
  hit is computed from, the origin's and the light's; measured ``k`` <= 7):
  :data:`AREA_ULPS` of them; a sphere light's ``ray_test`` adds ``u |o - c|^2 / r``.
  Every term scales with the scene. A gap below ``~u |target - o|`` cannot be resolved
  by a ray from the receiver at all (float32 ``t``): a wall 1e-6 before a light 1e3
  units from the receivers is lost even with no shortening.

Every term is a ratio of coordinates, so a uniform scale of the scene only
changes the rounding (measured: <= 0.01 % of visibility pixels change by more
than 0.05 from scale 1e-4 to 1e4, against 7-31 % with Mitsuba's ray).

Where it deviates from Mitsuba's epsilon, and why: at scale 1 the origin
offset is ~40x smaller than Mitsuba's (1.5e-6..5.8e-6 against 9e-5..4.5e-4 world
units on the built-in scene), because its floor is the hit's own rounding
error, not 1e-4 world units. Samples whose shadow ray grazes an occluder's
silhouette within that difference flip, so ``raytraced`` differs from
Mitsuba's ``direct`` (same samples) by 1e-5..1e-3 relative RMSE, 20-1000x
below the Monte Carlo noise at 64-1024 spp (measured with 64 ulps; 16 or 4 ulps
moved it 4x less than that, i.e. the difference is Mitsuba's larger offset). Offsets
are large where the geometry is: a point of a 1e4-unit mesh is offset by
~0.01 units (16 roundoffs of its coordinates).

The offset and the normal are detached (as in Mitsuba); ``si.p`` and the target
are not, so gradients of continuous parameters flow through the ray (a
``ray_test`` itself has none).
"""
from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi
import numpy as np

from .light_views.base import opaque_point, opaque_scalar, scene_bounds, shape_bounds

#: Unit roundoff of float32, 2^-24. Mitsuba's ray tracing (Embree, OptiX and its
#: own shapes in the AD variants) runs in float32.
UNIT_ROUNDOFF = 2.0 ** -24

#: Origin offset, in unit roundoffs of the hit's coordinate magnitude ``M``: meshes and
#: spheres (:data:`ORIGIN_ULPS`), other analytic shapes (:data:`ORIGIN_ULPS_OTHER`).
ORIGIN_ULPS = 16.0
ORIGIN_ULPS_OTHER = 64.0

#: Shortening before a target of unknown kind (no ``emitter`` given to
#: :func:`spawn_shadow_ray`; infinite emitters), in unit roundoffs of ``max|target|``.
TARGET_ULPS = 64.0

#: Relative shortening before a target of unknown kind: Mitsuba's ``ShadowEpsilon``
#: (``10 * RayEpsilon = 15000 * 2^-24``), already scale-invariant.
SHADOW_EPSILON = 15000.0 * 2.0 ** -24

#: Shortening before a delta light's point (point, spot, projector), in unit roundoffs of
#: ``max|target| + |target - o|``: ``o + d dist`` (``d``, ``dist`` as computed) ends
#: within about 4 of them of the target by the operations' bound (subtraction, norm,
#: division), within 1.7 measured (1.8 M rays, scales 1e-4..1e4, 0..1e5 from the origin).
DELTA_ULPS = 8.0

#: Shortening before an area light's point, in unit roundoffs of ``max(max|o|, max
#: coordinate of the emitter's bounds)`` over ``|cos|`` at the light: where the tracer
#: finds the light's own surface near the sample. Measured: at most 7.0 (rectangles,
#: disks, cubes, spheres; sizes 1e-3..1e3 at 0..1e5 from the origin, receivers 0.1-100
#: sizes away, 360 lights, 7.2 M rays down to grazing); 16 leaves a factor 2.3. (A disk
#: whose ``to_world`` is not orthogonal, e.g. ``rotate`` about an axis not of unit
#: length, which Mitsuba does not normalise, is sampled off the plane it is intersected
#: on: up to 430.)
AREA_ULPS = 16.0

#: ``|cos|`` at the light below which :data:`AREA_ULPS`'s bound is taken at this value.
MIN_COS = 1e-6


def _magnitude(bbox) -> float:
    """Largest absolute coordinate of a scalar bounding box (0 if invalid)."""
    if not bbox.valid():
        return 0.0
    return float(np.max(np.abs([list(bbox.min), list(bbox.max)])))


def _axis_magnitudes(bounds) -> np.ndarray:
    """Largest absolute coordinate per axis of ``(lo, hi)`` bounds (3 values; 0 for
    None)."""
    if bounds is None:
        return np.zeros(3)
    return np.max(np.abs(np.stack(bounds)), axis=0).astype(np.float64)


#: Shapes made of many separate primitives (hair strands), whose bounding box is the
#: whole set's (see :func:`shape_tables`): ``mi.ShapeType`` names.
MANY_PRIMITIVES = ("LinearCurve", "BSplineCurve")


def shape_tables(scene):
    """Per shape, indexed by its registry id (``scene.shapes_dr()``): the largest
    absolute coordinate along each axis (a ``(size, 3)`` float32 array) and whether its
    hit points are computed along the ray (1, analytic shapes) or interpolated (0,
    meshes), and the origin offset's ulps (:data:`ORIGIN_ULPS` for meshes and spheres,
    else :data:`ORIGIN_ULPS_OTHER`). Ids not listed (invalid hits; a shape group's shapes,
    whose hits :func:`spawn_shadow_ray` looks up by their instance's row) get the scene's
    magnitudes and the larger offset. Bounds come from :func:`~mi_shadowmap.light_views.base.shape_bounds`
    (not ``bbox()``: Mitsuba 3.9's merged meshes report wrong boxes)."""
    shapes = scene.shapes()
    fallback = _axis_magnitudes(scene_bounds(scene))
    ids = (dr.reinterpret_array(mi.UInt32, scene.shapes_dr()).numpy().astype(np.int64)
           if shapes else np.zeros(0, np.int64))
    size = int(ids.max()) + 1 if ids.size else 1
    mag_table = np.tile(fallback.astype(np.float32), (size, 1))   # per axis
    along_table = np.ones(size, np.float32)      # hit point computed as ray(t)?
    ulps_table = np.full(size, ORIGIN_ULPS_OTHER, np.float32)
    many = [getattr(mi.ShapeType, n) for n in MANY_PRIMITIVES]
    for i, s in zip(ids, shapes):
        m = _axis_magnitudes(shape_bounds(s))
        mag_table[i] = m if m.any() else fallback
        if s.shape_type() in many:
            # one shape, many strands (or ellipsoids): its box is no bound of the
            # coordinates a hit is computed from (that strand's, near ``p``), and the hit
            # is ``ray(t)``: ``|n| . |p|`` and ``t`` alone (a strand 1000 units off a hair
            # clump 0.05 wide moved every shadow ray 0.004 off its strand, twice the
            # strands' radius: ``raytraced`` lit 2.5 % of a view that ``direct`` shadows)
            mag_table[i] = 0.0
        along_table[i] = 0.0 if s.is_mesh() else 1.0
        if s.is_mesh() or s.class_name() == "Sphere":
            ulps_table[i] = ORIGIN_ULPS
    return mag_table, along_table, ulps_table


def cylinder_flags(scene):
    """Per shape, by registry id (as :func:`shape_tables`): 1 for a ``cylinder`` (a
    ``mi.UInt32`` array), or None if the scene has none. Reads no JIT value (safe inside
    symbolic loops)."""
    shapes = list(scene.shapes())
    if not any(s.shape_type() == mi.ShapeType.Cylinder for s in shapes):
        return None
    ids = dr.reinterpret_array(mi.UInt32, scene.shapes_dr()).numpy().astype(np.int64)
    flags = np.zeros(int(ids.max()) + 1, np.uint32)
    for i, sh in zip(ids, shapes):
        flags[i] = sh.shape_type() == mi.ShapeType.Cylinder
    return flags


#: A camera hit on a cylinder is found again from this fraction of its distance before it.
CYLINDER_RETRACE = 1e-3


def surface_point(si, scene):
    """The point a shadow ray from ``si`` leaves from, before its offset (and the point
    the maps look up): ``si.p``, found again from near it on cylinders and on non-mesh
    hits through instances (:func:`_on_cylinders`). One ``ray_intersect`` where the scene
    has such shapes: a caller tracing several shadow rays from one ``si`` (light samples
    in a loop) computes it once and passes it to :func:`spawn_shadow_ray`."""
    return _on_cylinders(si, scene)


def _on_cylinders(si, scene):
    """``si.p``, found again from near it where it is a cylinder's, or a hit through an
    ``instance`` (see the code for those).

    Mitsuba 3.9's AD variants intersect a cylinder in float32 in its object space
    (radius 1): a camera ray from ``t`` away finds a point off the surface by about
    ``u t^2 / r`` (measured: +-0.003 on a cylinder of radius 1.7 seen from 225 units,
    +-0.017 for radius 7.8 from 1000), some hundred times this module's origin offset.
    Such hits inside the surface sent 29-37 % of the shadow rays from the sunlit side of
    such posts into the post itself (Mitsuba's ``direct``, with its larger offset: none).
    The camera ray is traced again from :data:`CYLINDER_RETRACE` ``t`` before the hit
    (nothing lies between: it was the first hit), where the test is exact to about
    ``u (1e-3 t)^2 / r``; where it finds the same shape, its point is used. Only the
    value moves (the gradient stays ``si.p``'s).
    """
    flags = cylinder_flags(scene)
    instances = any(s.class_name() == "Instance" for s in scene.shapes())
    if flags is None and not instances:
        return si.p
    on = on_cylinder(si, scene, flags)
    if instances:
        # a sphere drawn through an instance that scales it is intersected with a ray
        # direction that is not unit length, and Mitsuba 3.9's step to the plane through
        # its centre then overshoots by the scale's inverse: seen from 39 radii through
        # instances at scale 0.3, its hits lay off it and shadow rays left it speckled
        # (``raytraced`` 5 % of the image off ``direct`` and off the same spheres given
        # as shapes; at scale 0.1 ``direct`` too, 4 %: ``raytraced`` now 0.3 %); found
        # again from near, the hit is on the surface. (At scale 0.01 the camera's own
        # hits are wrong by about the radius: neither integrator renders the spheres.)
        # (a mesh's hit is interpolated from its vertices, exact: not traced again)
        inst = si.is_valid() & (dr.reinterpret_array(mi.UInt32, si.instance) != 0)
        on |= inst & ~si.shape.is_mesh()
    p = dr.detach(si.p)
    d = dr.normalize(-dr.detach(si.to_world(si.wi)))     # the camera ray's direction
    back = CYLINDER_RETRACE * dr.detach(si.t)
    # (maxt positionally after d needs time and wavelengths too: mi.Ray3f(o, d, x) sets
    # the time, and the retrace was unbounded)
    again = scene.ray_intersect(mi.Ray3f(p - d * back, d, 2.0 * back, si.time,
                                         si.wavelengths),
                                mi.RayFlags.Minimal, False, on)
    ok = on & again.is_valid() & (again.shape == si.shape)
    return si.p + dr.select(ok, dr.detach(again.p) - p, 0.0)


#: A shadow ray is intersected (:func:`occluded`) where the scene's bounding diagonal
#: exceeds this many radii of its smallest ``sphere``: from 100 radii Mitsuba's sphere
#: ``ray_test`` errs on 0.02 % of the rays aimed at it, within 0.0012 radii of its outline.
SPHERE_TEST_RADII = 100.0


#: Up to this many spheres :func:`occluded` tests each shadow ray against (which spheres
#: it passes from far); beyond, every ray of the scene is intersected.
MAX_SPHERES_CHECKED = 32


def sphere_test_unsafe(scene) -> tuple:
    """``(spheres, instances)``: the centres and radii (a ``(k, 4)`` float64 array) of
    ``scene``'s own spheres that a ray starting within the scene's bounds may start more
    than :data:`SPHERE_TEST_RADII` radii from (see :func:`occluded`; None without any),
    and whether its shapes include an ``instance`` (whose shape groups' shapes are not
    listed)."""
    shapes = list(scene.shapes())
    instances = any(s.class_name() == "Instance" for s in shapes)
    spheres = []
    for s in shapes:
        if s.class_name() == "Sphere":
            b = shape_bounds(s)
            if b is not None:
                spheres.append(np.r_[0.5 * (b[0] + b[1]), 0.5 * float(np.max(b[1] - b[0]))])
    if not spheres:
        return None, instances
    bounds = scene_bounds(scene)
    diagonal = float(np.linalg.norm(bounds[1] - bounds[0])) if bounds is not None else 0.0
    spheres = np.array([sp for sp in spheres if diagonal > SPHERE_TEST_RADII * sp[3]])
    return (spheres if len(spheres) else None), instances


def occluded(scene, ray, active=True):
    """Whether anything lies on the shadow ray ``ray`` (within its ``maxt``): Mitsuba's
    ``scene.ray_test``, except where the scene holds a ``sphere`` or a ``cylinder``
    (for cylinders see the code).

    Mitsuba 3.9's sphere answers ``ray_test`` with the textbook quadratic in float32 (AD
    variants): ``|o - c|^2 - r^2`` from an origin ``D`` away loses ``r`` once ``u
    (D / r)^2`` nears 1, so a shadow ray that starts a few hundred radii or more from a
    sphere misses it or hits thin air near its outline. Its ``ray_intersect`` moves the
    origin to the plane through the centre first and is exact to ``~u D``. Measured
    (rays aimed within 1.3 radii of the centre, against the float64 answer): ``ray_test``
    wrong on 0.02 % of them from 100 radii, 0.3 % from 300, 2.3 % from 1000 (up to 0.12
    radii from the outline), 47 % from 1e4 (any of them), ``ray_intersect`` on <= 0.01
    %. A 1 mm ball 10 units above a floor under a point light at 20 cast, in
    ``raytraced`` and in Mitsuba's ``direct``, a shadow 3.8x the area of its true one.
    So a ray that passes near (see the code) a sphere more than
    :data:`SPHERE_TEST_RADII` radii from its origin is intersected instead
    (``ray_intersect_preliminary``: its first hit within ``maxt``; 1.5x the time of
    ``ray_test`` on the built-in scene's rays), the others tested (up to
    :data:`MAX_SPHERES_CHECKED` spheres smaller than a hundredth of the scene's diagonal
    checked per ray; with more, every ray is intersected). A sphere inside an
    ``instance`` whose ``to_world`` scales it is intersected in Mitsuba with a ray
    direction that is not unit length, where the same plane step lands off the plane
    and is worse than ``ray_test``; in a scene with instances a hit on an instance's
    shape is therefore left to ``ray_test`` (an intersected hit on the scene's own
    shapes still counts).
    """
    return occlusion(scene)(ray, active)     # as if every ray left a cylinder


def occlusion(scene):
    """:func:`occluded` for ``scene``, prepared: a function ``(ray, active) -> mi.Bool``.
    Everything read from the scene (its cylinders' radii, the maps' copy of it, its
    spheres) is read here, so the function can be called inside symbolic loops."""
    r_min = _smallest_cylinder(scene)
    inside = _occlusion_in(scene)
    if r_min is None:
        return inside
    from .map_scene import DEVIATION, map_scene
    copy = map_scene(scene, who="raytraced's shadow rays")
    if copy is scene:              # kept (instances): Mitsuba's cylinders, with a warning
        return inside
    # Cylinders: Mitsuba 3.9 intersects them in float32 in object space (see
    # map_scene), so a shadow ray that starts hundreds of radii from a thin cylinder
    # misses it: a pole 0.06 wide under a sun 6 degrees high lost its shadow 100 units
    # away on 3.7 % of a view (of 12.5 % shadowed), 200 units away on all of it but 0.5 %
    # (in Mitsuba's ``direct`` too). The ray queries the maps' copy, whose cylinders are
    # prisms within DEVIATION of the scene's diagonal of them (the end shortened by twice
    # that: a tube light's prism); a ray that leaves a cylinder (on_cylinder) queries the
    # scene for its first CYLINDER_NEAR smallest radii, where its own cylinder is
    # exactly as the camera saw it (not its prism, which it may start inside).
    # A ray that leaves its cylinder outwards may start inside that cylinder's own prism
    # (whose vertices lie r tan(pi/2n)^2 outside it) and hit the prism on its way out,
    # beyond CYLINDER_NEAR smallest radii where the smallest is a far thinner cylinder:
    # a tank 10 in radius on a 4 km ground, with a wire 1e-4 in radius elsewhere, was
    # shadowed near its terminator (190 of 7797 lit pixels of a 128^2 view). Its height
    # above its (convex) cylinder grows at least as t cos(angle to the outward normal),
    # so past twice the prism's excess over that it is clear of the prism: the scene
    # itself is queried up to there (shell, per registry id: the excess, negative for a
    # cylinder with flip_normals, whose si.n points inwards).
    shell = mi.Float(_cylinder_shells(scene))
    n_shell = dr.width(shell)
    beyond = _occlusion_in(copy)
    near_t = CYLINDER_NEAR * r_min
    b = scene_bounds(scene)
    margin = 2.0 * DEVIATION * (float(np.linalg.norm(b[1] - b[0])) if b is not None else 0.0)

    def query(ray, active=True, on_cylinder=None, si=None):
        # on_cylinder (per lane, :func:`on_cylinder`): the ray leaves a cylinder; elsewhere
        # the copy alone is queried (None: every lane as if it did); si: the surface
        # interaction it leaves (its shape and normal: the own prism's shell, above)
        split = active if on_cylinder is None else active & on_cylinder
        start = dr.select(split, near_t, 0.0)
        if si is not None:
            idx = dr.reinterpret_array(mi.UInt32, si.shape)
            listed = split & (idx < n_shell)
            excess = dr.gather(mi.Float, shell, dr.select(listed, idx, 0), listed)
            n_out = dr.detach(dr.select(excess < 0.0, -si.n, si.n))
            cos = dr.dot(dr.detach(ray.d), n_out)
            clear = 2.0 * dr.abs(excess) / dr.maximum(cos, 1e-7)
            start = dr.select(listed & (excess != 0.0) & (cos > 0.0),
                              dr.maximum(start, dr.minimum(clear, ray.maxt)), start)
        near = mi.Ray3f(ray.o, ray.d, dr.minimum(ray.maxt, start), ray.time,
                        ray.wavelengths)
        far_active = active & (ray.maxt - margin > start)
        far = mi.Ray3f(ray.o + ray.d * start, ray.d,
                       dr.maximum(ray.maxt - start - margin, 0.0), ray.time, ray.wavelengths)
        return inside(near, split) | beyond(far, far_active)
    return query


def on_cylinder(si, scene, flags=False):
    """Per lane, whether the surface interaction ``si`` is on one of ``scene``'s own
    cylinders (``mi.Bool``; reads no JIT value). ``flags``: :func:`cylinder_flags` of
    ``scene`` where the caller has it."""
    flags = cylinder_flags(scene) if flags is False else flags
    if flags is None:
        return dr.zeros(mi.Bool, dr.width(si.t))
    idx = dr.reinterpret_array(mi.UInt32, si.shape)
    on = si.is_valid() & (idx < len(flags))
    return on & (dr.gather(mi.UInt32, mi.UInt32(flags), dr.select(on, idx, 0), on) == 1)


#: :func:`occluded` queries the scene itself for the first this many radii of the
#: smallest cylinder along a shadow ray, the maps' copy (cylinders as prisms) beyond:
#: from 333 radii Mitsuba's cylinder test still agreed with a near ray on 20,000 rays.
CYLINDER_NEAR = 100.0


def _cylinder_shells(scene) -> np.ndarray:
    """Per registry id (as :func:`shape_tables`), a float32 array: for a cylinder, how
    far its prism in :func:`~mi_shadowmap.map_scene.map_scene`'s copy reaches outside it
    (``r tan(pi / 2n)^2``, ``r`` its larger radial axis), negative where its normals are
    flipped; 0 for other shapes."""
    from .map_scene import _traversal, cylinder_radius, is_cylinder, scene_diagonal, segments
    shapes = list(scene.shapes())
    ids = dr.reinterpret_array(mi.UInt32, scene.shapes_dr()).numpy().astype(np.int64)
    out = np.zeros(int(ids.max()) + 1 if ids.size else 1, np.float32)
    diagonal = scene_diagonal(scene)       # the diagonal map_scene sizes the prisms by
    for i, sh in zip(ids, shapes):
        if is_cylinder(sh):
            m = np.array(_traversal(sh)["to_world"].matrix, np.float64).reshape(4, 4)
            r = max(np.linalg.norm(m[:3, 0]), np.linalg.norm(m[:3, 1]))
            n = segments(cylinder_radius(sh), diagonal)
            excess = r * math.tan(math.pi / (2 * n)) ** 2
            out[i] = -excess if sh.has_flipped_normals() else excess
    return out


def _smallest_cylinder(scene):
    """The smallest radius of ``scene``'s own cylinders, or None without any."""
    from .map_scene import cylinder_radius, is_cylinder
    radii = [cylinder_radius(s) for s in scene.shapes() if is_cylinder(s)]
    return min(radii) if radii else None


def _occlusion_in(scene):
    """:func:`occlusion` within ``scene`` alone (its spheres; see :func:`occluded`)."""
    spheres, instances = sphere_test_unsafe(scene)
    if spheres is not None and len(spheres) <= MAX_SPHERES_CHECKED:
        table = mi.Float(spheres.astype(np.float32).ravel())   # not literals: may move

    def risky(ray, active):
        """The rays that pass near such a sphere from more than
        :data:`SPHERE_TEST_RADII` radii away (only there ``ray_test`` errs)."""
        if len(spheres) > MAX_SPHERES_CHECKED:
            return active
        out = mi.Bool(False)
        o, d = dr.detach(ray.o), dr.detach(ray.d)
        for k in range(len(spheres)):
            c = mi.Point3f(*[dr.gather(mi.Float, table, mi.UInt32(4 * k + j)) for j in range(3)])
            r = dr.gather(mi.Float, table, mi.UInt32(4 * k + 3))
            oc = c - o
            along = dr.dot(oc, d)
            # squared distance of the centre from the ray's line (a cross product: no
            # cancellation) against where ray_test may answer wrongly: its discriminant
            # r^2 - dist^2 is off by about u |oc|^2 (u = 2^-24), so up to dist^2 = r^2 +
            # u |oc|^2 (2.6 radii from 1e4 radii away); 1.5 r and 8 u |oc|^2 here
            dist2 = dr.squared_norm(dr.cross(oc, d))
            oc2 = dr.squared_norm(oc)
            out |= ((dist2 < 2.25 * r * r + 8.0 * UNIT_ROUNDOFF * oc2) & (along > -r)
                    & (along < ray.maxt + r) & (oc2 > (SPHERE_TEST_RADII * r) ** 2))
        return active & out

    def query(ray, active=True, on_cylinder=None, si=None):   # (on_cylinder, si: unused)
        if spheres is None:
            return scene.ray_test(ray, active)
        far = risky(ray, active)
        pi = scene.ray_intersect_preliminary(ray, active=far)
        hit = far & pi.is_valid()
        test = active & ~far
        if instances:
            own = hit & (dr.reinterpret_array(mi.UInt32, pi.instance) == 0)
            hit, test = own, test | (far & ~own)
        return hit | scene.ray_test(ray, test)
    return query


def shape_index(shape_ptr, size: int):
    """The registry id of each lane's shape (``si.shape``) as a ``mi.UInt32`` index into
    :func:`shape_tables`' rows (0 for ids out of range)."""
    idx = dr.reinterpret_array(mi.UInt32, shape_ptr)
    return dr.select(idx < size, idx, 0)


def is_infinite(emitter) -> bool:
    """Whether ``emitter`` is at infinity (``directional``, ``envmap``, ``constant``): its
    sample's ``ds.p`` only gives a direction (see :func:`spawn_shadow_ray`)."""
    return emitter is not None and mi.has_flag(emitter.flags(), mi.EmitterFlags.Infinite)


def target_shortening(o, p_target, dist, d, emitter=None, n_target=None):
    """How far short of ``p_target`` a shadow ray from ``o`` (direction ``d``, ``dist``
    long) ends: only what rounding needs, so occluders just before the light count.

    * ``emitter`` a delta light (``EmitterFlags.DeltaPosition``: point, spot,
      projector): the target is a point in space, no surface to avoid;
      :data:`DELTA_ULPS` roundoffs of ``max|target| + dist``.
    * ``emitter`` on a shape (area lights) and ``n_target`` its normal at the target:
      the target lies on that surface, which the tracer finds within about ``k u M /
      |cos|`` of it along the ray (``M = max(max|o|, the shape's largest coordinate)``,
      ``cos = d . n_target``; ``max|target|`` too): :data:`AREA_ULPS` of them.
    * otherwise (no emitter, infinite ones): Mitsuba's relative ``ShadowEpsilon`` or
      :data:`TARGET_ULPS` roundoffs of ``max|target|``, the larger.

    Every term is a ratio of coordinates (scale-invariant). All arguments detached."""
    u = UNIT_ROUNDOFF
    m_target = dr.max(dr.abs(p_target))
    if emitter is not None and mi.has_flag(emitter.flags(), mi.EmitterFlags.DeltaPosition):
        return (DELTA_ULPS * u) * (m_target + dist)
    shape = emitter.get_shape() if emitter is not None else None
    if shape is not None and n_target is not None:
        bounds = shape_bounds(shape)
        # opaque: moving the light must compile nothing
        m_light = opaque_scalar(float(np.max(_axis_magnitudes(bounds))))
        cos = dr.maximum(dr.abs(dr.dot(d, dr.detach(n_target))), MIN_COS)
        m = dr.maximum(dr.maximum(dr.max(dr.abs(o)), m_target), m_light)
        if shape.class_name() == "Sphere" and bounds is not None:
            # its ray_test solves the quadratic from the origin: the discriminant is off
            # by ~u |o - c|^2, its root (t) by that over r cos; from SPHERE_TEST_RADII
            # radii on the ray is intersected instead (:func:`occluded`), to ~u |o - c|
            # (a sphere light seen from 20 radii was hit 2e-6 beyond maxt by 1 % of the
            # rays to its front)
            centre = opaque_point(0.5 * (bounds[0] + bounds[1]))
            radius = opaque_scalar(0.5 * float(np.max(bounds[1] - bounds[0])))
            far = dr.norm(o - centre)
            m = dr.maximum(m, far * dr.minimum(far / dr.maximum(radius, 1e-30),
                                               SPHERE_TEST_RADII))
        return (AREA_ULPS * u) * m / cos
    return dr.maximum(SHADOW_EPSILON * dist, (TARGET_ULPS * u) * m_target)


def spawn_shadow_ray(si, p_target, scene, infinite: bool = False,
                     p_surface=None, emitter=None, n_target=None) -> "mi.Ray3f":
    """A shadow ray from the surface interaction ``si`` towards ``p_target``.

    ``si`` is a ``mi.SurfaceInteraction3f`` of ``scene`` (``si.p``, ``si.n``,
    ``si.t``, ``si.shape``), ``p_target`` a ``mi.Point3f`` (a light sample's
    ``ds.p``; for a directional light Mitsuba places it beyond the scene's
    bounding sphere). Returns a ``mi.Ray3f`` of the current variant for
    ``scene.ray_test``: origin ``p + delta * n`` and ``maxt`` short of the
    target, both relative to the coordinates involved (formula and
    measurements: the module's documentation). Works in every JIT variant
    (types are looked up when called) and inside ``dr.while_loop`` bodies.

    ``infinite`` (:func:`is_infinite` of the sample's emitter): ``p_target`` only gives
    the direction, and the ray reaches at least twice past the scene's bounds
    (:func:`~mi_shadowmap.light_views.base.scene_bounds`). Mitsuba 3.9 places an
    infinite emitter's sample ``2 R`` from the shading point, ``R`` the radius of
    ``scene.bbox()``'s sphere, and that box leaves out parts of merged meshes (meshes
    sharing a BSDF): measured, a 20-unit billboard 40 units from a 1-unit post under a
    20-degree sun cast no shadow in Mitsuba's own ``direct`` (image mean 0.1075
    against 0.0880 with the meshes kept apart). A ray that long still stops short of
    the target it is given when that is farther.

    ``p_surface``: :func:`surface_point` of ``si``, if the caller has it (default:
    computed here, one more ``ray_intersect`` per call on a scene with cylinders).

    ``emitter`` (the sample's) and ``n_target`` (its ``ds.n``) say what the target is,
    and so how far short of it the ray ends (:func:`target_shortening`): a delta light's
    point only a few roundoffs, an area light's by its surface's rounding over ``|cos|``.
    Without them, Mitsuba's relative ``ShadowEpsilon``, which misses occluders within
    ``8.9e-4 |target - o|`` of the light (a wall 1e-4 before it).
    """
    Float = mi.Float

    mag_table, along_table, ulps_table = shape_tables(scene)
    idx = shape_index(si.shape, len(along_table))
    instance = getattr(si, "instance", None)
    if instance is not None:
        # a hit through an ``instance`` names its shape group's shape, which is in no
        # table (its vertices are in the group's space): the instance's own row, its
        # bounds in the world (rather than the whole scene's)
        inst = dr.reinterpret_array(mi.UInt32, instance)
        idx = dr.select((inst != 0) & (inst < len(along_table)), inst, idx)
    m_axes = dr.gather(mi.Vector3f, Float(mag_table.ravel()), idx)
    along = dr.gather(Float, Float(along_table), idx)
    ulps = dr.gather(Float, Float(ulps_table), idx)

    p = _on_cylinders(si, scene) if p_surface is None else p_surface
    p_d = dr.detach(p)
    n = dr.detach(si.n)
    t_cam = dr.detach(si.t)
    t_cam = dr.select(dr.isfinite(t_cam), t_cam, 0.0)
    # the shape's coordinates weighted by the normal: the rounding of an interpolated
    # point off its plane is that of its coordinates along the normal (a flat ground
    # 1e6 wide is exact in its height, not to 1e6 u); so is the origin's own rounding
    m_shape = dr.dot(dr.abs(n), m_axes)
    mag = dr.maximum(dr.maximum(dr.dot(dr.abs(n), dr.abs(p_d)), m_shape), along * t_cam)
    delta = ulps * UNIT_ROUNDOFF * mag

    n = dr.select(dr.dot(n, dr.detach(p_target) - p_d) < 0, -n, n)   # towards the target
    o = dr.fma(n, delta, p)

    d = p_target - o
    dist = dr.norm(d)
    d = dr.select(dist > 0, d / dist, n)
    short = target_shortening(dr.detach(o), dr.detach(p_target), dr.detach(dist),
                              dr.detach(d), None if infinite else emitter, n_target)
    maxt = dr.maximum(dist - short, 0.0)
    if infinite:
        bounds = scene_bounds(scene)
        if bounds is not None:
            lo, hi = bounds
            # opaque: moving geometry changes them, and must compile nothing
            centre = opaque_point(0.5 * (lo + hi))
            radius = opaque_scalar(0.5 * float(np.linalg.norm(hi - lo)))
            maxt = dr.maximum(maxt, 2.0 * (dr.norm(p_d - centre) + radius))
    return mi.Ray3f(o, d, maxt, si.time, si.wavelengths)
