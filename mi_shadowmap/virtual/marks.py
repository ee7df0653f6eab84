"""The mark pass: the pages and tiles the camera's visible points read, from one camera
ray per pixel centre.
"""
from __future__ import annotations

import functools
import math
import weakref

import drjit as dr
import mitsuba as mi
import numpy as np

from .. import depth_maps
from ..control_flow import if_stmt
from ..light_views import (PIXEL_BLOCK, block_pixels, pinhole_footprint, pixel_centres,
                           pixel_ray_differentials)
from ..light_views.base import opaque_point
from ..map_manager import (MAP_CACHE, ParamWatch, bsdf_flags, flag_changing_bsdfs,
                           scene_lease)
from ..variants import tilts_shading_frame
from .camera import camera_frame, has_aperture
from .layout import MAX_COARSER, NO_KEY, key_fields, page_key, sorted_unique
from .lookup import VirtualShadowMap, effective_lod_bias

#: Texels from its point up to which a point whose level the receiver biases chose finer
#: than its footprint's marks the tiles its pixel's samples read there
#: (:meth:`VirtualShadowMap.level_for`): the pixel's footprint box at that level, whose
#: half-width is the point's ``spread``. The neighbouring points do not fill in beyond
#: it: a footprint the light grazes is long and thin in the map, and along its long axis
#: the next pixel's centre is a whole footprint (``2 spread``) away. Marked up to 4
#: texels (then the method's margin), the boxed light of ``tests/test_virtual.py`` under
#: an orthographic camera (footprints 1.4 x 54 texels at the capped level, rows 27 texels
#: apart) left gaps between rows where no level near the wanted one was built: 0.17 % of
#: the floor's samples walked to the coarsest level and ``hard`` lit 9 pixels of 4096 (a
#: perspective view 0.08 %, 1 pixel); marked up to 32, 0 and 0 (0.02 % of the
#: perspective view's samples, whose level is finer than their pixel centre's), for 8.5 %
#: and 7 % more texels. 32 (a page of the default 32^2) bounds a block's side (9 tiles of
#: 8, 4 bits a side in its key, :func:`shape_bits`; the orthographic view's spreads reach
#: 52, 99 % of them below 30).
MAX_SPREAD = 32.0


#: Keys of candidates that lost their slot in both of :func:`dedupe_many`'s hash tables
#: its kernel keeps per candidate list, or per partition of one (an environment's region:
#: each has its own slots; more: one more kernel gives them all). Per list, not per
#: region, 4096 held fewer than a batch of 8 of sky_sun's regions lost at 256^2: an
#: extra kernel a batch (0.8 ms) and the host reading all its 524 k candidates.
SPILL = 4096

#: :func:`dedupe_many` stores its candidates' keys in its first kernel (8 bytes a
#: candidate, ``NO_KEY`` where not a candidate) when all its lists' candidates together
#: hold at most this many bytes, and its second and third kernels read them back; above
#: it (a ``pcss`` mark under a 16-region sky: 25 lists, 60 MB) those kernels recompute
#: the keys from the mark pass's stored points, as storing and reading every list was
#: bound by memory there. A camera move of room_two_points (two lists of 65,536
#: candidates, 1 MB) read 29 bytes of points a candidate in each of those kernels and
#: recomputed its key (``benchmarks/RESULTS.md``, the fifty-fourth session, helper A).
STORED_KEY_BYTES = 1 << 23


#: The mark pass of a camera with a lens (``thinlens``, ``aperture_radius`` > 0) traces
#: each pixel through ``LENS_GRID``^2 points of its lens (cell centres of a square grid,
#: mapped to the disk as the camera maps its aperture samples). From the lens centre
#: alone, a blurred post 0.8 in front of an aperture of radius 0.8 hid a strip of ground
#: that the rest of the lens sees: its lookups fell to coarse levels (``hard``
#: misclassified 1.49 %, full maps 0.04 %; 4 x 4 points: 0.18 %).
LENS_GRID = 3


#: How many times the height the biases hide at the fallback level a mark's probe
#: reaches along the ray towards the light (:func:`probe_keeps`): the pixel's samples
#: sit up to half a footprint from its centre, and a lookup's normal offset moves its
#: ray. At 1, the probes of 14 % of the capped floor samples of the orthographic boxed
#: light (``tests/test_virtual.py``: a closed box, all of them shadowed) found no wall;
#: at 2 none did (measured on branch ``wip/probe-cap``, 069460b).
PROBE_MARGIN = 2.0


def camera_hits(scene, sensor, evaluate: bool = True, state=None):
    """Camera hits at every pixel centre with their one-pixel footprints (where the next
    pixel's rays meet the tangent plane: a perspective camera's from its pinhole, as the
    render takes them, :func:`~mi_shadowmap.light_views.pinhole_footprint`; other
    sensors' from their ray differentials): ``(si, dp_dx, dp_dy, valid)``; unevaluated
    with ``evaluate=False`` (for a caller that traces them into a kernel of its own; the
    mark pass evaluates them first, see :func:`~.planner.prepare_virtual`). ``state``:
    the sensor's :func:`~.camera.camera_state` if read already (:func:`~.camera.
    camera_frame`)."""
    frame = camera_frame(sensor, state)
    if frame is not None:    # plain rays: the footprints come from the frame, not differentials
        ray, _ = sensor.sample_ray(0.0, 0.5, pixel_centres(sensor, blocks=True),
                                   mi.Point2f(0.5))
    else:
        centres = pixel_centres(sensor, blocks=True)
        k = LENS_GRID if has_aperture(sensor) else 1
        if k == 1:
            ray = pixel_ray_differentials(sensor, centres)
        else:
            # a lens: every pixel through k x k points of it (the render's samples spread
            # over the whole lens, and a near occluder hides different points from each)
            n = dr.width(centres)
            idx = dr.arange(mi.UInt32, n * k * k)
            a = idx // n
            lens = mi.Point2f((mi.Float(a % k) + 0.5) / k, (mi.Float(a // k) + 0.5) / k)
            ray = pixel_ray_differentials(sensor, dr.gather(mi.Point2f, centres, idx % n),
                                          aperture=lens)
    # position and geometric normal are all marking needs (RayFlags.All also computes
    # UVs, shading frames and their derivatives: about half the pass)
    si = scene.ray_intersect(ray, ray_flags=mi.RayFlags.Minimal,
                             coherent=depth_maps.COHERENT_RAYS)
    valid = si.is_valid()
    si.n = dr.select(dr.dot(si.n, ray.d) > 0, -si.n, si.n)    # facing the camera
    if frame is not None:       # as the render takes them (integrator._footprint)
        dp_dx, dp_dy = pinhole_footprint(si.p, si.n, frame)
        if evaluate:
            dr.eval(si.p, si.n, si.shape, dp_dx, dp_dy, valid)
        return si, dp_dx, dp_dy, valid
    n = si.n

    def hit(o, d):
        t = dr.dot(n, si.p - o) / dr.select(dr.abs(dr.dot(n, d)) > 1e-12, dr.dot(n, d), 1e-12)
        return o + d * t

    ok = ray.has_differentials
    dp_dx = mi.Vector3f(dr.select(ok, hit(ray.o_x, ray.d_x) - si.p, 0.0))
    dp_dy = mi.Vector3f(dr.select(ok, hit(ray.o_y, ray.d_y) - si.p, 0.0))
    if evaluate:
        dr.eval(si.p, si.n, dp_dx, dp_dy, valid)
    return si, dp_dx, dp_dy, valid


def camera_pixels(sensor) -> mi.UInt32:
    """The film pixel (``x + 65536 y`` in the crop, as ``Lookup.pixel``) of each of
    :func:`camera_hits`' lanes through a camera without a lens (one a pixel, in
    :func:`~mi_shadowmap.light_views.pixel_centres`' blocks; the blocks' filler lanes
    repeat a pixel)."""
    w, h = (int(x) for x in sensor.film().crop_size())
    pos = pixel_centres(sensor, blocks=True)
    return mi.UInt32(dr.floor(pos.x * w)) + mi.UInt32(dr.floor(pos.y * h)) * 65536


def marked_points(vmap_like, si, dp_dx, dp_dy, valid, active=None) -> tuple:
    """``(face, uv64, act, level, spread, dropped, kept)`` of the camera hits ``si`` a mark
    reads: their face and float64 uv, which of them mark (valid, on a face, in front of a
    one-sided planar light, and ``active(p, n)`` if given), their level
    (:meth:`VirtualShadowMap.level_for`), how far from the point, in its texels, the
    pixel's samples read where that level is finer than the footprint's (0 elsewhere),
    and where the biases' level was dropped: with ``vmap_like.scene`` (a :class:`Marker`
    of a render whose lookups know their film pixel), the points the biases capped whose
    :func:`probe_keeps` does not keep it, and those where the light is behind the
    surface (:func:`_light_behind`: no lookup there, no probe); they mark the level
    without the biases' height, as their pixels' lookups on the same shape read it
    (:meth:`VirtualShadowMap.keeps`); else nowhere (False); and those it keeps."""
    view = vmap_like.view
    p64 = mi.Point3d(si.p)
    face, uv64, _, inside = view.project_f64(p64)
    act = valid & inside
    if view.light_normal is not None:   # behind a one-sided planar light: no light
        act &= dr.dot(si.p - opaque_point(view.position), mi.Vector3f(*view.light_normal)) > 0
    if active is not None:
        act &= active(si.p, si.n)
    scene = getattr(vmap_like, "scene", None)
    if scene is None or getattr(vmap_like, "reach", None) is None:
        level, spread = vmap_like._levels(face, p64, dp_dx, dp_dy, si.n)
        return face, uv64, act, level, spread, mi.Bool(False), mi.Bool(False)
    level, spread, fallback, fb_spread, length, edge = vmap_like._levels(
        face, p64, dp_dx, dp_dy, si.n, probe=True)
    capped = act & (length > 0)
    plane = None
    if vmap_like.reach.edge > 0.0:
        # the method's virtual_edge chose the level: probed as far as it moves an edge,
        # from the tangent plane its virtual samples lie on (see probe_keeps' ``plane``)
        capped = act & ((length > 0) | (edge > 0))
        plane = capped & (length <= 0)
        dp_dx, dp_dy = _edge_probe_frame(view, si.p, si.n, dp_dx, dp_dy, edge)
    # the five probe rays in a conditional: Dr.Jit's LLVM backend skips a branch that no
    # lane of a packet takes, where each masked ray query (all lanes inactive) still
    # cost about 0.7 ms a 256^2 film: far_point's moved frame's mark kernel 4.1 -> 1.8
    # ms (1.5 before the probes); marks, texels and images bit-identical (6 scenes x 5
    # methods, a first frame, a move and back)
    eye = getattr(vmap_like, "eye", None)
    shape = getattr(si, "shape", None)
    # no lookup reads the biases' level where the light is on the surface's far side
    # (_light_behind): the probes are skipped there and the point marks the fallback
    probed = capped & ~_light_behind(scene, view, si.p, si.n, shape, eye, capped)

    def probe(p, n, dx, dy, ln, c, sh, e, pl):
        # (``plane`` passed only where a virtual_edge set it: the biases' probe as before)
        return probe_keeps(scene, view, p, n, dx, dy, ln, c, sh, e,
                           **({} if pl is None else {"plane": pl}))

    keep = dr.if_stmt(
        (si.p, si.n, dp_dx, dp_dy, length, probed, shape, eye, plane),
        probed, probe, lambda p, n, dx, dy, ln, c, sh, e, pl: mi.Bool(False))
    return (face, uv64, act, dr.select(keep, level, fallback),
            dr.select(keep, spread, fb_spread), capped & ~keep, capped & keep)


#: How far either side of a pixel's centre (in units of the ``edge`` of
#: :func:`_edge_probe_frame`) the corners' probes look for a shadow's edge where a method's
#: ``virtual_edge`` chose the level. A lit gap the footprint's level loses is wider than
#: the edge's move: under the grazed gap of ``tests/test_virtual.py`` (64^2,
#: ``second_depth``), 1: 96 pixels misclassified, 1.5: 45, 2: 5 (the edge's level
#: everywhere: 4; the footprint's: 132). At 2 the corners are where the rays of the
#: fallback's farthest taps meet the tangent plane (a 2 x 2 block's texel centres lie
#: within a texel of the point in the map: ``2 edge`` along the receiver for
#: ``second_depth``'s half texel), so the corners' probes from the plane
#: (:func:`probe_keeps`' ``plane``) see what those taps' virtual samples compare.
EDGE_PROBE = 2.0


def _edge_probe_frame(view, p, n, dp_dx, dp_dy, edge):
    """The footprint ``(dp_dx, dp_dy)`` whose corners :func:`probe_keeps` probes, where a
    method's ``virtual_edge`` chose a level finer than the footprint's (``edge`` > 0:
    :meth:`~mi_shadowmap.virtual.lookup.VirtualShadowMap._levels`' ``edge``, how far
    along the receiver towards the light its compares move a shadow's edge at the
    footprint's level). There the footprint stretched along that direction to at least
    ``2 EDGE_PROBE edge`` (its corners :data:`EDGE_PROBE` ``edge`` either side of the
    centre), across it the footprint's own width; elsewhere ``(dp_dx, dp_dy)``.

    A shadow's edge farther than ``edge`` from the pixel is not moved onto it at the
    footprint's level, and a lit gap that level loses has an edge within ``EDGE_PROBE
    edge`` of each of its pixels (measured, :data:`EDGE_PROBE`): where no corner's probe
    disagrees with the centre's, the footprint's level classifies the pixel as the
    edge's does. Unprobed (the edge's level everywhere the light grazes), ``second_depth``
    built 27.5 texels a film pixel on ``random_terrain_world(15)`` at 256^2 (sun 2-5
    degrees), ``hard`` 5.5 (``benchmarks/RESULTS.md``, the forty-seventh session, helper
    F)."""
    nn = dr.normalize(mi.Vector3f(n))
    to_light = view.direction_to_light(p)
    along = to_light - nn * dr.dot(nn, to_light)
    ok = dr.norm(along) > 1e-6
    a = dr.select(ok, dr.normalize(along), dr.normalize(mi.Vector3f(dp_dx)))
    b = dr.cross(nn, a)
    ext_a = dr.abs(dr.dot(dp_dx, a)) + dr.abs(dr.dot(dp_dy, a))
    ext_b = dr.abs(dr.dot(dp_dx, b)) + dr.abs(dr.dot(dp_dy, b))
    on = (edge > 0) & ok
    # across the light's direction the compares move an edge ``edge cos(theta)`` (the
    # map's texels are not stretched there)
    cos_nl = dr.abs(dr.dot(nn, to_light))
    return (dr.select(on, a * dr.maximum(2.0 * EDGE_PROBE * edge, ext_a), dp_dx),
            dr.select(on, b * dr.maximum(2.0 * EDGE_PROBE * edge * cos_nl, ext_b), dp_dy))


#: Emitter kinds whose light reaches a receiver from one point or direction, the one
#: :meth:`~mi_shadowmap.light_views.base.LightView.direction_to_light` gives
#: (:func:`_light_behind`).
DELTA_KINDS = ("point", "spot", "projector", "directional")

#: :func:`_shape_tilts`' memo of each scene (:class:`_TiltWatch`), keyed by its
#: :func:`~mi_shadowmap.map_manager.scene_lease` (weakly: it goes when the package lets the
#: scene go, ``clear_caches()`` too).
_TILTS = weakref.WeakKeyDictionary()


def _light_behind(scene, view, p, n, shape, eye, active) -> mi.Bool:
    """Where the light is behind the surface the camera sees at ``p`` (``n``: its
    geometric normal, facing the camera) so that no lookup there reads a map: light
    from behind a reflecting surface reaches no viewer (the integrator looks up a light
    sample only where the BSDF reaches it, ``variants.bsdf_eval_reaches``). Exact for
    delta lights (one direction, :data:`DELTA_KINDS`) and for area lights whose whole
    bounding box lies behind (the lit cone is convex: its 8 corners decide). Never where
    the shape's BSDF transmits (``BSDFFlags.Transmission``: dielectrics, ``mask``,
    ``null``, blends of those) or perturbs its shading normal (``normalmap``,
    ``bumpmap``), nor for environment lights. A mesh's vertex normals tilt the shading
    frame by at most the largest angle ``a`` between a vertex normal and its face's
    normal (an interpolated normal stays in that cap): there the light must lie more
    than ``a`` below the plane and the camera more than ``a`` above it (a ``twosided``
    BSDF flips a shading frame the camera sees from below, and then reflects the light
    from below), ``eye`` (the camera's pinhole) giving the camera's side; without it
    only untilted shapes. The area light's corners are opaque: a moved light compiles
    no new mark kernel."""
    if shape is None:
        return mi.Bool(False)
    kind = getattr(view, "kind", None)
    if kind in DELTA_KINDS:
        corners = [None]
    elif kind == "area" and view.ignore_shape is not None:
        box = view.ignore_shape.bbox()
        corners = [opaque_point(mi.ScalarPoint3f(
            *[float((box.max if (k >> a) & 1 else box.min)[a]) for a in range(3)]))
            for k in range(8)]
    else:
        return mi.Bool(False)
    table = _shape_tilts(scene)
    idx = dr.reinterpret_array(mi.UInt32, shape)
    inside = idx < dr.width(table)
    s = dr.select(inside, dr.gather(mi.Float, table, idx, active & inside), 2.0)
    behind = mi.Bool(active) & (s <= 1.0)
    for q in corners:
        d = view.direction_to_light(p) if q is None else dr.normalize(q - p)
        behind &= dr.dot(n, d) < -s
    if eye is not None:
        behind &= (s == 0.0) | (dr.dot(n, dr.normalize(eye - p)) > s)
    else:
        behind &= s == 0.0
    return behind


def _shape_tilts(scene) -> mi.Float:
    """Per shape registry index (``si.shape`` as a ``UInt32``), the sine of the largest
    angle its shading normal can tilt from its geometric normal (0: none; 2: never
    drop, :func:`_light_behind`: a transmitting or normal-mapping BSDF; indices of no
    shape the scene's traversal reaches are 2 too). Kept per scene (:data:`_TILTS`)
    while what :func:`_tilt_of` reads that ``params.update()`` may change is unchanged
    (:class:`_TiltWatch`: the meshes' buffers, the flags of BSDFs whose flags change);
    then the shapes whose state changed (:func:`_tilt_state`) are read again, the others
    are not. Before, the table was kept per scene: a mesh's vertex normals bent after
    its first mark were not seen, and the mark dropped the biases' level that its
    lookups then read (a smooth wall lit through its bent normals from just behind its
    plane, posts beside it: 60 of 4096 pixels differed from a fresh integrator's, 53 of
    them across 1/2, ``tests/test_cache_edits.py``). Called by the mark pass only (a
    still camera reuses its marks): one read of the watched parameters' JIT indices."""
    lease = scene_lease(scene)
    memo = _TILTS.get(lease)
    if memo is None:
        memo = _TILTS[lease] = _TiltWatch(scene)
    token, values = memo.read()
    if token == memo.token:
        return memo.table
    keys = [_tilt_state(sh) for _, sh, _ in memo.shapes]
    for k, (i, sh, in_group) in enumerate(memo.shapes):
        if memo.keys is None or keys[k][0] != memo.keys[k][0]:
            memo.tilts[i] = _tilt_of(sh, in_group)
    table = np.full(max(memo.tilts, default=0) + 1, 2.0, np.float32)
    for i, value in memo.tilts.items():
        table[i] = value
    memo.table = mi.Float(table)
    dr.make_opaque(memo.table)
    memo.keys, memo.token = keys, token
    memo.held = memo.watch.held(values)
    return memo.table


class _TiltWatch:
    """:func:`_shape_tilts`' memo of one scene: its shapes as ``(registry id, shape, in a
    shape group)`` (a loaded scene's shapes are fixed), a
    :class:`~mi_shadowmap.map_manager.ParamWatch` of its meshes' ``vertex_positions``,
    ``faces`` and ``vertex_normals`` (read through the map cache's kept traversal; not a
    ``rectangle``'s ``to_world``, a mesh in Mitsuba 3.9: an affine map keeps its normals
    its face's, and collecting a transform's JIT indices took 17-26 us), the BSDFs whose
    flags ``params.update()`` changes
    (:data:`~mi_shadowmap.map_manager.FLAG_CHANGING_BSDFS`), the last token read, each
    shape's :func:`_tilt_state` then, its tilt, the table and the values held (so that
    their JIT indices are not reused while compared). Reading per shape instead (its
    buffers and BSDF flags, :func:`_tilt_state`) took 29-60 us a mark pass on the
    repository's scenes of 5-6 shapes; the watch's read 3-8 us."""

    def __init__(self, scene):
        # the scene's shapes and its shape groups' (an instance's, which the camera's
        # hits name, ``si.shape``, are not in scene.shapes())
        listed = list(scene.shapes())
        grouped = depth_maps._grouped_shapes(scene, listed)
        self.shapes = [(int(dr.reinterpret_array(mi.UInt32, mi.ShapePtr(sh))[0]), sh,
                        k >= len(listed)) for k, sh in enumerate(listed + grouped)]
        params = MAP_CACHE.traverse(scene)
        meshes = {id(sh) for _, sh, _ in self.shapes if sh.is_mesh()}
        self.watch = ParamWatch(params, [
            name for name in params.keys() if id(params.properties[name][2]) in meshes
            and name.rsplit(".", 1)[-1] in ("vertex_positions", "faces", "vertex_normals")])
        self.flagged = flag_changing_bsdfs(sh.bsdf() for _, sh, _ in self.shapes)
        self.token = self.keys = self.table = self.held = None
        self.tilts = {}

    def read(self) -> tuple:
        """``(token, values)``: the watch's, its token with the watched BSDFs' flags."""
        token, values = self.watch.read()
        if self.flagged:
            token = (token, bsdf_flags(self.flagged))
        return token, values


def _tilt_state(shape) -> tuple:
    """``(key, held)``: what :func:`_tilt_of` reads of ``shape`` that ``params.update()``
    may change, and the JIT buffers the key names: its BSDF's flags (Mitsuba's
    ``principled`` gains ``GlossyTransmission`` when its ``spec_trans`` is set above 0:
    light from behind then reaches the camera through it) and a mesh's vertex, face and
    vertex-normal buffers' JIT indices (held with the key: a new index is a new value)."""
    bsdf = shape.bsdf()
    flags = None if bsdf is None else int(bsdf.flags())
    if not shape.is_mesh():
        return (flags,), ()
    held = (shape.vertex_positions_buffer(), shape.faces_buffer(),
            shape.vertex_normals_buffer())
    return (flags,) + tuple(b.index for b in held), held


def _tilt_of(shape, in_group: bool = False) -> float:
    """:func:`_shape_tilts`' value of one shape. ``in_group``: a shape group's, whose
    buffers are in its object space: an ``instance``'s non-uniform scale may widen the
    angle between its vertex and face normals, so only normals equal to their faces'
    (which stay equal) count as untilted there."""
    bsdf = shape.bsdf()
    if bsdf is None or mi.has_flag(bsdf.flags(), mi.BSDFFlags.Transmission):
        return 2.0
    if tilts_shading_frame(bsdf):
        return 2.0
    if not (shape.is_mesh() and shape.has_vertex_normals()):
        return 0.0
    n_faces = int(shape.face_count())
    if n_faces == 0:
        return 0.0
    # one kernel over the faces (numpy took 2.3-3.6 s for a million of them)
    faces, v = shape.faces_buffer(), shape.vertex_positions_buffer()
    vn = shape.vertex_normals_buffer()
    idx = dr.arange(mi.UInt32, n_faces) * 3
    i = [dr.gather(mi.UInt32, faces, idx + k) for k in range(3)]
    p = [dr.gather(mi.Point3f, v, i[k]) for k in range(3)]
    n_face = dr.normalize(dr.cross(p[1] - p[0], p[2] - p[0]))
    cos = mi.Float(1.0)
    for k in range(3):
        cos = dr.minimum(cos, dr.dot(n_face, dr.normalize(dr.gather(mi.Vector3f, vn, i[k]))))
    # a degenerate face (no normal) is never hit; a NaN vertex normal: anything
    bad = dr.isnan(cos) & dr.all(dr.isfinite(n_face))
    lowest = float(dr.min(dr.select(dr.isnan(cos), 1.0, cos))[0])
    if bool(dr.any(bad)[0]) or not lowest > 0.0:
        return 2.0    # a vertex normal at or past 90 degrees from its face: anything
    sin_tilt = math.sqrt(max(0.0, 1.0 - lowest * lowest))
    if in_group and sin_tilt > 1e-4:
        return 2.0
    # (+1e-3: float32's rounding of the normals, here and in the shading frame)
    return min(1.0, sin_tilt + 1e-3)


def probe_keeps(scene, view, p, n, dp_dx, dp_dy, length, active, shape=None, eye=None,
                plane=None):
    """Whether a pixel whose centre ``p`` the biases capped (``active``; ``length``:
    :meth:`VirtualShadowMap._levels`' probe length) keeps the biases' level: its lookups
    and its mark read it (:func:`marked_points`, :meth:`VirtualShadowMap.keeps`). It
    does where its probe towards the light finds an occluder within ``PROBE_MARGIN
    length`` (the biases at the fallback level may hide it), or where a shadow's edge
    crosses the pixel: the shadow rays from the corners of its footprint (``p +- dp_dx /
    2 +- dp_dy / 2``, on the tangent plane) to the light do not all agree with the
    centre's (the fallback's coarser texels move the edges of thin occluders' shadows;
    a probe from the centre alone missed thin posts beside it), or where the ray from the
    centre lifted along its normal by ``PROBE_MARGIN`` times the biases' height at the
    fallback (``length cos(theta)``; the fallback's lookups are lifted by their normal
    offset, at most that height) does not agree with the centre's: that ray meets
    occluders the point's passes (a ball's bottom beside its contact shadow, under a
    light 1e-3 to 0.05 over the floor: ``hard`` falsely shadowed 0.90 % of a 128^2 view
    at the fallback, 0.36 % now, ``raytraced``'s own noise 0.31 %; the forty-seventh
    session, helper D). Elsewhere the fallback level loses no shadow the biases' level
    keeps and adds none. Up to six rays per capped pixel centre, in the mark kernel
    (``ray_intersect_preliminary``); the measurements are in ``benchmarks/RESULTS.md``
    (the forty-second, forty-fourth and forty-seventh sessions).

    ``eye``: the camera's pinhole (opaque), or None. A corner lies on the receiver's
    tangent plane, and where the surface bends up within the footprint (a valley of a
    mesh, a terrain's facets) under that surface: its shadow ray hits the surface right
    there, an edge found where there is none. With ``eye``, a corner whose probe
    disagrees with the centre's is probed again from the point the camera sees through
    it, where that point is on the receiver's own shape (:func:`_surface_corner_differs`;
    another shape, or none: the plane's corner, as before). Only corners that found an
    edge are traced again, so a pixel keeps the level no more often than before. On
    ``random_terrain_world`` seed 22 at 256^2 (a hill's view of rippled terrain, a sun
    8-40 degrees high) 4008 of the 4723 centres that kept the level did so from a lit
    centre through a corner whose hit lay 0.05 footprints from it (median): ``hard``
    10.16 -> 6.64 texels a film pixel, ``pcf`` 12.47 -> 8.48, misclassified at 128^2
    1.07 -> 1.06 % and 1.29 -> 1.24 % (``raytraced`` with another seed 1.25 %; with
    :func:`probe_distance` seeing instances). Of 30 terrain worlds none builds more
    texels or misclassifies more pixels at 128^2 (summed 793 -> 788 ``hard``, 944 -> 924
    ``pcf``; ``benchmarks/RESULTS.md``, the forty-sixth session).

    ``plane`` (per lane, or None: nowhere): the pixels whose level a method's
    ``virtual_edge`` alone capped (:func:`marked_points`, ``second_depth``): their corners
    are not retried from the surface. Those lookups compare the map's depths with
    virtual samples on the receiver's tangent plane (Wang & Molnar), and a corner under
    the surface (a valley, a terrain's facets rising towards the light) is where, at the
    fallback's coarser texels, a tap's ray meets the surface in front of the plane and
    shadows the point: the method's own false shadow on a rippled open receiver, which
    the edge's finer level keeps away (its taps stay nearer the point). Retried from the
    surface, as for the biases' level, those pixels dropped the edge's level and
    ``random_terrain_world`` seed 22 misclassified 273 pixels of 128^2, 259 with the edge's
    level everywhere (``raytraced`` with another seed: 205); from the plane 259, with
    texels at 256^2 9.47 -> 9.32 a film pixel (seed 15: 27.46 -> 5.55; the forty-eighth
    session, helper A).

    ``shape``: the hits' shapes (``si.shape``), or None. Where the light is behind the
    receiver's face (``n`` facing the camera) a probe's hit on the receiver's own shape
    counts as none: such a point is in its own shape's shade, which no level changes,
    and its lookups reach the image only through a shading frame tilted over the
    terminator (and a solid's are 0 there, ``Lookup.solid_back``). Counted, the far
    sides of thin posts grazed by the sun kept the biases' level everywhere
    (``random_large_world`` seed 5 at 256^2: 2166 of the 5803 back-facing capped pixel
    centres kept it, 241 of the 2821 facing the light)."""
    c_nl = dr.dot(n, view.direction_to_light(p))     # cos of the light at the receiver
    own = None
    if shape is not None:
        own = dr.select(c_nl < 0, shape, mi.ShapePtr(None))
    hit0 = probe_distance(scene, view, p, n, active, own)
    keep = mi.Bool(active) & (hit0 < mi.Float(length) * PROBE_MARGIN)
    shadowed = dr.isfinite(hit0)
    surface = eye is not None and shape is not None
    # the fallback's lookups compare along a ray lifted off the point by its normal
    # offset (at most the biases' height, ``length cos``): where that ray meets an
    # occluder the point's misses, or misses one it meets, the fallback moves a shadow's
    # edge onto the pixel (a ball's contact shadow under a light 1e-3 over the floor)
    lift = mi.Float(length) * dr.clip(dr.abs(c_nl), 1e-6, 1.0) * PROBE_MARGIN
    p_lifted = p + n * dr.select(c_nl >= 0, lift, -lift)

    def probe_left(k, keep):
        return (k < 5) & mi.Bool(active) & ~keep

    def probe(k, keep):
        # probe k < 4: corner (-, -), (-, +), (+, -), (+, +) halves of dp_dx and dp_dy;
        # k = 4: the lifted centre. A lane that keeps the level probes no more (keep is
        # the OR of every probe's disagreement: the order changes nothing)
        lifted = k == 4
        a = dr.select(k < 2, mi.Float(-0.5), mi.Float(0.5))
        b = dr.select((k & 1) == 0, mi.Float(-0.5), mi.Float(0.5))
        c = dr.select(lifted, p_lifted, p + dp_dx * a + dp_dy * b)
        corner = probe_distance(scene, view, c, n, active & ~keep, own)
        differs = mi.Bool(active) & ~keep & (dr.isfinite(corner) != shadowed)
        if surface:
            # a corner's disagreement checked from the surface the camera sees (not the
            # lifted centre's). (Nested in marked_points' conditional: control_flow's
            # if_stmt names the symbolic mode, so Dr.Jit does not log forcing it)
            retry = differs & ~lifted if plane is None else differs & ~lifted & ~plane
            differs = if_stmt(
                (c, n, differs, shadowed, own, shape, eye), retry,
                lambda c, n, d, s, o, sh, e: _surface_corner_differs(
                    scene, view, c, n, d, s, o, sh, e),
                lambda c, n, d, s, o, sh, e: d,
                label="virtual marks: a corner's edge from the surface")
        return k + 1, keep | differs

    # the probes in a loop, not unrolled: traced once (marked_points' tracing of a moved
    # far_point frame about a third, the mark kernel 1616 -> 1059 operations, its code
    # generation 0.60 -> 0.36 ms, with the four corners; marks bit-identical)
    mode = "symbolic" if dr.flag(dr.JitFlag.SymbolicScope) else None
    _, keep = dr.while_loop((mi.UInt32(0), keep), probe_left, probe, mode=mode,
                            label="virtual marks: the footprint's corners, the lifted centre")
    return keep


def _surface_corner_differs(scene, view, c, n, differs, shadowed, own, shape, eye):
    """Whether a footprint corner ``c`` (on the receiver's tangent plane) whose probe
    ``differs`` from the centre's (``shadowed``) still does from the surface the camera
    sees through it: where the camera's ray through ``c`` meets the receiver's own
    ``shape`` (not through an ``instance``: a preliminary intersection has no shape
    there), the probe leaves that point, offset along the centre's normal ``n``, the
    centre's ``own`` shape counting as none as for the corners. Elsewhere (another
    shape, an instance, nothing) the plane's corner's answer. A preliminary intersection
    and a point on the ray, not a surface interaction: ``scene.ray_intersect`` here
    traced every shape's ``compute_surface_interaction`` into the mark kernel (4153
    operations against 1594 on ``random_terrain_world`` seed 22) and its host tracing
    cost a moved frame 30-130 ms (256^2)."""
    ray = mi.Ray3f(eye, dr.normalize(c - eye))
    pi = scene.ray_intersect_preliminary(ray, active=differs)
    on_own = differs & pi.is_valid() & (pi.shape == shape)
    t = probe_distance(scene, view, ray(pi.t), n, on_own, own)
    return dr.select(on_own, dr.isfinite(t) != shadowed, differs)


def probe_distance(scene, view, p, n, active, own=None):
    """How far from ``p`` along its ray towards the light the first occluder lies (inf
    where none does: the light's own shape, ``view.ignore_shape``, is none, and nothing
    beyond a point or spot light's position counts). The ray leaves ``p`` offset along
    its normal ``n`` to the light's side as Mitsuba's ``spawn_ray`` offsets it (the
    surface itself is not hit). ``own`` (per lane, may be null): a shape whose hit
    counts as none too."""
    d = view.direction_to_light(p)
    n = mi.Vector3f(n)
    eps = (1.0 + dr.max(dr.abs(p))) * float(dr.epsilon(mi.Float)) * 89.0
    o = p + n * dr.select(dr.dot(n, d) >= 0, eps, -eps)
    ray = mi.Ray3f(o, d)
    if view.rays_from_point and view.projection in ("perspective", "cube"):
        # not beyond the light: what lies behind a point light does not shadow
        ray.maxt = dr.norm(opaque_point(view.position) - o) * (1.0 - 1e-4)
    pi = scene.ray_intersect_preliminary(ray, active=active)
    hit = mi.Bool(active) & pi.is_valid()
    if view.ignore_shape is not None:
        hit &= pi.shape != mi.ShapePtr(view.ignore_shape)
    if own is not None:
        # a hit on an ``instance`` has a null shape in a preliminary intersection (its
        # ``instance`` is set): an occluder, not the lane's own shape, where ``own`` is
        # null too. Compared as ``pi.shape != own`` alone, every probe that passed a
        # shape (the per-pixel probes of every render) was blind to instanced occluders
        # wherever the light is in front of the receiver (``own`` null), and dropped the
        # biases' level under them (``random_terrain_world`` seed 22 at 128^2: a pixel
        # under an instanced post, 0.83 from it along the probe, rendered 0.69 lit by
        # ``hard`` where ``raytraced`` gives 0)
        hit &= (pi.shape != own) | (own == mi.ShapePtr(None))
    return dr.select(hit, pi.t, dr.inf)


def mark_candidates(vmap_like, si, dp_dx, dp_dy, valid, margin: float = 2.0,
                    active=None, points=None, border=None,
                    footprints: float = 0.0) -> tuple:
    """``(keys, oks)``, lists of candidate tile keys per point and whether each is one
    (unevaluated): the tiles the lookups at ``si`` read (see the module doc): at each
    point's level, the tiles (:attr:`VirtualLayout.tile_size` texels wide; keys as
    :func:`page_key` in tile units) overlapping ``margin + max(1, 2^(-1 - lod_bias))``
    texels around it (the method's kernel, plus half a pixel at the level's lower end for
    camera samples off the pixel centre: one texel at the default ``lod_bias``), capped at
    ``page_size / 2`` texels (what :meth:`VirtualShadowMap.bind`'s 2 x 2 pages serve):
    ``ceil(2 m / tile_size) + 1`` tiles per axis at most (2 x 2 for ``hard``'s kernel);
    where the receiver biases chose a level finer than the footprint's, at least the
    pixel's footprint box there, up to :data:`MAX_SPREAD` texels.
    A wider tap (PCSS's kernel up to ``max_kernel / 2``) reads its own page through the
    page table (:meth:`BoundVirtualMap._index`), which the neighbouring points marked
    where the surface goes on, else the coarsest level. (Marking the whole kernel
    instead, 64 texels wide, cast 1.5-1.9x the texels and doubled a camera move's PCSS
    frame for the same error on the soft-shadow scenes.)
    ``active(p, n)``: which points to mark (``n`` the normal facing the camera), or
    None: every point the view sees. ``points``: the points' :func:`marked_points`
    (evaluated: then each key is a few integer operations on them, cheap to recompute
    in every round of :func:`dedupe_many`), or None: computed here. ``border``: the
    film's border pixels; ``footprints``: the kernel's footprints (:func:`_tile_range`)."""
    face, level, act, lo, hi, n_tiles, per_axis = _tile_range(
        vmap_like, si, dp_dx, dp_dy, valid, margin, active, points, border=border,
        footprints=footprints)
    # per_axis^2 candidates per point, all in one kernel; only the valid ones leave
    # Dr.Jit (most points read one tile or two)
    keys, oks = [], []
    for k in range(per_axis * per_axis):
        tx, ty = lo.x + (k % per_axis), lo.y + (k // per_axis)
        oks.append(act & (tx <= hi.x) & (ty <= hi.y) & (tx >= 0) & (ty >= 0)
                   & (tx < n_tiles) & (ty < n_tiles))
        keys.append(page_key(face, level, dr.maximum(tx, 0), dr.maximum(ty, 0)))
    return keys, oks


def _tile_range(vmap_like, si, dp_dx, dp_dy, valid, margin, active, points,
                border=None, footprints: float = 0.0, host_kept: bool = False) -> tuple:
    """``(face, level, act, lo, hi, n_tiles, per_axis)`` of :func:`mark_candidates`: the
    tiles ``lo`` to ``hi`` (per axis, at most ``per_axis`` from ``lo``) around each point
    at its level, of ``n_tiles`` per side there. ``border`` (``mi.Bool`` per point, or
    None): the points of the film's border pixels, which mark ``m_edge``
    (:func:`_margins`) where others mark ``m``. ``footprints``: the method's
    ``virtual_footprint``, how many footprint half-sides its kernel reaches (0: a kernel
    of fixed texels). ``host_kept``: the points that kept the biases' level (where the
    marks decide it per pixel) do not mark here: the host marks their bands
    (:func:`kept_tiles`)."""
    lay = vmap_like.layout
    T = lay.tile_size
    if points is None:
        points = marked_points(vmap_like, si, dp_dx, dp_dy, valid, active)
    face, uv64, act, level = points[:4]
    m, m_block, m_edge = _margins(vmap_like, margin, border is not None)
    if getattr(vmap_like, "reach", None) is not None:
        # a point whose level the biases made finer than its footprint's (level_for):
        # its pixel's samples read anywhere in its footprint's box, ``spread`` texels
        # from it, marked up to MAX_SPREAD (the blocks' size is fixed: a camera move
        # compiles nothing). The samples' kernels reaching beyond the box read the
        # neighbouring pixels' boxes, which those mark; the kernel around the point
        # itself, as everywhere.
        m_lane = mi.Point2d(dr.maximum(m, dr.minimum(points[4], MAX_SPREAD)))
        if getattr(vmap_like, "scene", None) is not None and _kept_by_biases(vmap_like):
            # with the per-pixel decision (marked_points' probe) a point that kept the
            # biases' level marks its own samples' kernels beyond its box (``m +
            # spread``, up to m_block), and pcf's wider kernel at that level: the
            # bounding box of kept_tiles' own band (where a neighbour reads the level,
            # kept_tiles marks the ring too)
            spread = mi.Point2d(points[4])
            kept = mi.Bool(points[6])
            bound = _footprint_texels(vmap_like)
            box = m + spread + footprints * dr.maximum(spread - bound, 0.0)
            m_lane = dr.select(kept, dr.minimum(box, m_block), m_lane)
            if host_kept:
                act = act & ~kept
    else:
        m_lane = m
    if border is not None and m_edge > m:
        # a film-border pixel's samples half a pixel outwards: no pixel beyond the film
        # marks around them (m_edge, _margins)
        m_lane = dr.minimum(m_lane + dr.select(mi.Bool(border), mi.Float64(m_edge - m),
                                               mi.Float64(0.0)), m_block)
    per_axis = int(math.ceil(2.0 * m_block / T)) + 1
    res = mi.Float64(mi.UInt32(lay.res0) >> level)
    xy = uv64 * res
    n_tiles = dr.maximum(mi.Int32(lay.pages_per_side(0)) >> mi.Int32(level), 1) \
        * lay.tiles_per_side
    lo = mi.Point2i(dr.floor((xy - m_lane) / T))
    hi = mi.Point2i(dr.floor((xy + m_lane) / T))
    return face, level, act, lo, hi, n_tiles, per_axis


def _kept_by_biases(vmap_like) -> bool:
    """Whether a point that kept its level (:func:`marked_points`) may have kept it for
    the receiver biases' height, whose level the samples of its uncapped neighbours read
    (its band, :func:`kept_tiles`, marked on the host); False where the method's biases
    have no height (``second_depth`` at its defaults: its ``virtual_edge`` alone caps the
    level).
    An uncapped pixel's centre has the footprint's level there, and its own mark built
    what its samples read before the edge's level was probed (forty-seventh session,
    helper F: far_point's ``second_depth`` at 128^2 97,792 texels before, 109,568 with the
    wider box, 97,152 without)."""
    reach = vmap_like.reach
    return reach.normal > 0.0 or reach.slope > 0.0


def mark_blocks(vmap_like, points, margin: float = 2.0, bits=None, border=None,
                footprints: float = 0.0, host_kept: bool = False) -> tuple:
    """:func:`mark_candidates`' tiles as one block per point: ``(keys, oks)``, one list
    per block shape ``(w, h)`` (``w = c % per_axis + 1``, ``h = c // per_axis + 1`` for
    list ``c``), holding the same key in every list -- the block's first tile (as
    :func:`page_key` in tile units) -- valid in the list of its shape only. Neighbouring
    points mark the same block, so deduplicating blocks (:func:`dedupe_many`, one key
    and hash a point) finds what the ``per_axis^2`` candidate tiles a point would find,
    then :func:`expand_blocks` gives the tiles: the same set as :func:`mark_candidates`'
    valid keys. ``points``: the points' evaluated :func:`marked_points`.

    With ``bits`` (:func:`shape_bits` of the layout and :func:`block_axis`, not None where
    the keys have room for them), one list instead: each block's shape in the top
    ``bits`` bits of its key's tile coordinates, read back by :func:`expand_blocks` with
    the same ``bits``. The ``per_axis^2`` lists were as many hash tables and scatters a
    point in every round of :func:`dedupe_many` (9 for ``hard`` with the biases' marks of
    4 texels, 81 with :data:`MAX_SPREAD`): on a camera move at 256^2 the dedupe kernels took 1.67 ->
    0.63 ms on large_world, 3.19 -> 0.51 ms on cbox_area (``pcss``: 8.05 -> 1.37 ms),
    5.09 -> 1.14 ms on room_two_points (medians of 10 moves each, interleaved).

    ``border``: which points are on the film's border; ``footprints``: the kernel's
    footprints (:func:`_tile_range`). ``host_kept``: the points that kept the biases'
    level left out (:func:`kept_tiles` marks their bands on the host)."""
    face, level, act, lo, hi, n_tiles, per_axis = _tile_range(
        vmap_like, None, None, None, None, margin, None, points, border, footprints,
        host_kept)
    # the valid candidates of mark_candidates: lo + a (a < per_axis) in [0, n_tiles)
    # and at most hi, i.e. the range [max(lo, 0), min(hi, lo + per_axis - 1, n_tiles - 1)]
    sx, sy = dr.maximum(lo.x, 0), dr.maximum(lo.y, 0)
    ex = dr.minimum(dr.minimum(hi.x, lo.x + (per_axis - 1)), n_tiles - 1) - sx
    ey = dr.minimum(dr.minimum(hi.y, lo.y + (per_axis - 1)), n_tiles - 1) - sy
    ok = act & (ex >= 0) & (ey >= 0)
    if bits is not None:
        top = 27 - bits
        return [page_key(face, level, mi.UInt32(sx) | (mi.UInt32(ex) << top),
                         mi.UInt32(sy) | (mi.UInt32(ey) << top))], [ok]
    key = page_key(face, level, sx, sy)
    keys, oks = [], []
    for c in range(per_axis * per_axis):
        keys.append(key)
        oks.append(ok & (ex == c % per_axis) & (ey == c // per_axis))
    return keys, oks


def kept_axes(vmap_like, si, dp_dx, dp_dy, points) -> tuple:
    """``(du_dx, du_dy)``: the pixel footprint's two sides in the map (``d uv_light``,
    ``mi.Point2f`` each, unevaluated) at the camera hits ``si`` whose points
    (:func:`marked_points`) kept the biases' level (the parallelogram whose bounding box
    is their ``spread``, as :meth:`VirtualShadowMap._levels` takes them), 0 elsewhere.
    :func:`kept_tiles` reads them on the host. In a conditional that only the vector
    packets holding a kept point enter (2-8 % of a film's points keep the level, in
    blocks of the film): a view's differentials are not shared with ``_levels``' (its
    opaque position is another variable): 64 more operations in the mark kernel
    (far_point at 64^2: 1205 -> 1269)."""
    view = vmap_like.view

    def sides(p_world, face, dx, dy):
        p_world = mi.Point3f(p_world)
        return view.uv_differential(face, p_world, dx), view.uv_differential(face, p_world,
                                                                             dy)

    return if_stmt((si.p, points[0], dp_dx, dp_dy), mi.Bool(points[6]), sides,
                   lambda p_world, face, dx, dy: (mi.Point2f(0.0), mi.Point2f(0.0)),
                   label="virtual marks: the kept points' footprint sides")


#: How far along its footprint's sides ``a`` and ``b`` (:func:`kept_axes`) from a kept
#: point its band holds its own pixel's samples (:func:`kept_tiles`): ``p + s a + t b``,
#: ``|s|, |t| <= 1/2``, the parallelogram whose bounding box is its ``spread``.
KEPT_SAMPLES = 0.5

#: How far its band holds its neighbours' centres where a neighbour reads its level
#: (:func:`kept_tiles`): ``p + i a + j b``, ``|i|, |j| <= 1``, whose bounding box is
#: ``2 spread``.
KEPT_NEIGHBOURS = 1.0


def kept_tiles(vmap_like, points, axes, read, margin: float, footprints: float = 0.0,
               film=None) -> np.ndarray:
    """The tile keys (``np.uint64``, unsorted, with repeats) of the points that kept the
    biases' level (:func:`marked_points`' ``kept``, evaluated; :func:`mark_blocks` with
    ``host_kept`` leaves them out), computed on the host from their lanes alone (2-8 %
    of a film's points keep the level): each one's band, the tiles its lookups read on
    its tangent plane at that level, not the box around it.

    A pixel's samples lie in the parallelogram ``p + s a + t b``, ``|s|, |t| <= 1/2``
    (``a``, ``b`` its footprint's sides in texels of the level, :func:`kept_axes`; its
    bounding box is ``spread``), and each reads the method's kernel around it: ``m``
    texels (:func:`_margins`), and for a kernel of ``footprints`` footprints (``pcf``'s
    region) ``footprints max(spread - 2^(1 - lod_bias), 0)`` more, as the box
    ``m + spread + ...`` of :func:`_tile_range` holds. Where a neighbouring pixel reads
    the level through the kept point's word (``read``, ``planner._kept_read``), the
    neighbours' centres ``p + i a + j b`` (``|i|, |j| <= 1``) and the kernel ``m``
    around them too: the ring ``m + 2 spread`` was their bounding box. A tile is
    marked where it meets that region, column by column of the box's tiles
    (:func:`_band_rows`). A footprint the light grazes is long and thin in the map, and
    turned to its axes fills little of its box. Only tiles of the box (clamped as there,
    up to ``m_block``) are candidates, so a band is a subset of it; a point with a
    non-finite side keeps its box.

    Measured on ``random_terrain_world(123)`` at 256^2 (2531 kept points):
    ``pcf`` 8.62 -> 7.70 texels a film pixel, ``hard`` 6.00 -> 4.23; terrain 87 ``hard``
    5.46 -> 3.18 (``benchmarks/RESULTS.md``, the fiftieth session, helper A); the host
    time 2.1-3.2 ms a moved frame there. The same tiles as testing every tile of every
    box against the region (separating axes), which took 7.5-14 ms.

    ``axes``: :func:`kept_axes`, evaluated; ``read``: ``mi.Bool`` per lane (or one);
    ``film``: the film's ``(width, height)`` where a film-border pixel's point marks
    ``m_edge`` (:func:`_margins`; the method's ``virtual_footprint`` given), else None."""
    kept = np.asarray(points[6].numpy(), bool).reshape(-1)
    idx = np.flatnonzero(kept)
    if len(idx) == 0:
        return np.zeros(0, np.uint64)
    lay = vmap_like.layout
    T = float(lay.tile_size)
    m, m_block, m_edge = _margins(vmap_like, margin, film is not None)

    def lanes(x, dtype):
        """The kept lanes of ``x`` (a literal, one lane, repeated): ``(n,)``, or ``(2, n)``
        for a point (read per component: a flat array's ``numpy()`` is a view, a point's
        a copy of every lane, 0.4 ms at 256^2)."""
        if dr.depth_v(x) > 1:
            return np.stack([lanes(c, dtype) for c in x])
        v = x.numpy()
        return (v[idx] if len(v) > 1 else np.repeat(v, len(idx))).astype(dtype)

    face, level = lanes(points[0], np.uint64), lanes(points[3], np.int64)
    uv, spread = lanes(points[1], np.float64), lanes(points[4], np.float64)
    ring = lanes(read, bool)
    # in texels of each point's level (as _tile_range and VirtualShadowMap._levels)
    xy = uv * (np.int64(lay.res0) >> level).astype(np.float64)
    scale = float(lay.res0) * np.exp2(-np.clip(level, 0, lay.coarsest).astype(np.float64))
    a, b = (lanes(ax, np.float64) * scale for ax in axes)
    # the box of _tile_range, in its order of operations; the own band's kernel
    wide = footprints * np.maximum(spread - _footprint_texels(vmap_like), 0.0)
    pad = m + wide
    box = m + spread + wide
    box = np.where(ring, np.maximum(box, m + 2.0 * spread), box)
    box = np.minimum(box, m_block)
    extra = np.zeros(len(idx))
    if film is not None and m_edge > m:
        x, y = _lane_pixels(*film)
        w, h = film
        x, y = x[idx], y[idx]
        edge = (x == 0) | (y == 0) | (x == w - 1) | (y == h - 1)
        extra = np.where(edge, m_edge - m, 0.0)
        box = np.minimum(box + extra, m_block)
    per_axis = int(math.ceil(2.0 * m_block / T)) + 1
    lo = np.floor((xy - box) / T).astype(np.int64)
    hi = np.floor((xy + box) / T).astype(np.int64)
    n_tiles = np.maximum(np.int64(lay.pages_per_side(0)) >> level, 1) * lay.tiles_per_side
    start = np.maximum(lo, 0)
    end = np.minimum(np.minimum(hi, lo + (per_axis - 1)), n_tiles - 1)
    size = np.maximum(end - start + 1, 0)
    # each point's columns of tiles in its box, and each column's tiles the band meets
    n_w = size[0]
    k = np.repeat(np.arange(len(idx)), n_w)
    first = np.cumsum(n_w) - n_w
    tx = start[0][k] + (np.arange(len(k)) - np.repeat(first, n_w))
    finite = np.isfinite(a).all(axis=0) & np.isfinite(b).all(axis=0)
    a, b = np.where(finite, a, 0.0), np.where(finite, b, 0.0)
    # the own bands' parallelograms (points 0 .. n - 1), then the rings' (n .. 2n - 1),
    # every column's rows at once (one pass of a few dozen numpy calls: at a few kept
    # points their fixed cost is the time)
    n = len(idx)
    r = np.flatnonzero(ring[k])
    col = np.concatenate([k, k[r] + n])
    tx = np.concatenate([tx, tx[r]])
    t0, t1 = _band_rows(
        tx, col, np.concatenate([xy, xy], axis=1),
        np.concatenate([KEPT_SAMPLES * a, KEPT_NEIGHBOURS * a], axis=1),
        np.concatenate([KEPT_SAMPLES * b, KEPT_NEIGHBOURS * b], axis=1),
        np.concatenate([pad + extra, m + extra + np.zeros((2, 1))], axis=1), T,
        np.concatenate([~finite, ~finite]))
    k = col % n
    t0, t1 = np.maximum(t0, start[1][k]), np.minimum(t1, end[1][k])
    n_h = np.maximum(t1 - t0 + 1, 0)
    c = np.repeat(np.arange(len(n_h)), n_h)
    first = np.cumsum(n_h) - n_h
    ty = t0[c] + (np.arange(len(c)) - np.repeat(first, n_h))
    kc = k[c]
    return page_key(face[kc], level[kc].astype(np.uint64), tx[c].astype(np.uint64),
                    ty.astype(np.uint64))


def _band_rows(tx, k, centre, u, v, kernel, T: float, whole) -> tuple:
    """``(first, last)`` tile row of each tile column ``tx`` (texels ``T tx`` to
    ``T (tx + 1)``) that the parallelogram ``centre + s u + t v`` (``|s|, |t| <= 1``) of
    its point ``k`` widened by ``kernel`` (half sides) meets; ``(2, n)`` arrays per point,
    ``whole``: points whose columns are taken whole (every row). The parallelogram's
    highest point over the column widened by the kernel, widened by the kernel again,
    and likewise its lowest. Its upper edge over ``x`` is the lower of its two sides'
    lines that bound it from above (concave), highest at its top corner ``x*``: over an
    interval, at ``x*`` clamped into it; its lower edge is the upper one turned about
    the centre (``y_lo(x) = -y_hi(-x)``). About 30 array operations a column, where
    clipping its four sides to every column took some 130 (2.7-2.9 against 4.4-4.6 ms
    for ``random_terrain_world(123)``'s kept points at 256^2, the same tiles)."""
    # per point: the x half-range, the top corner, and each side's line over it
    # (``y = c + g x``; none where the side is vertical or the parallelogram flat)
    x_half = np.abs(u[0]) + np.abs(v[0])
    y_half = np.abs(u[1]) + np.abs(v[1])
    x_top = np.where(u[1] < 0, -u[0], u[0]) + np.where(v[1] < 0, -v[0], v[0])
    lines = []
    for p, q in ((u, v), (v, u)):
        nx, ny = -p[1], p[0]                        # the normal of the sides along p
        flip = np.where(ny < 0, -1.0, 1.0)
        nx, ny = nx * flip, ny * flip
        ok = ny > 0
        ny = np.where(ok, ny, 1.0)
        lines.append((np.where(ok, np.abs(nx * q[0] + ny * q[1]) / ny, np.inf),
                      np.where(ok, -nx / ny, 0.0)))
    (c0, g0), (c1, g1) = ((c[k], g[k]) for c, g in lines)
    xh, yh, xt = x_half[k], y_half[k], x_top[k]
    tol = 1e-9 * T
    x0 = tx * T - kernel[0][k] - centre[0][k] - tol
    x1 = (tx + 1) * T + kernel[0][k] - centre[0][k] + tol
    lo_x, hi_x = np.maximum(x0, -xh), np.minimum(x1, xh)
    met = lo_x <= hi_x

    def top(x):
        return np.minimum(np.minimum(c0 + g0 * x, c1 + g1 * x), yh)

    y_hi = top(np.clip(xt, lo_x, hi_x))
    y_lo = -top(np.clip(xt, -hi_x, -lo_x))
    ky = kernel[1][k] + tol
    whole = whole[k]
    cy = centre[1][k]
    first = np.where(whole, -2.0 ** 40, np.where(met, y_lo - ky + cy, 0.0))
    last = np.where(whole, 2.0 ** 40, np.where(met, y_hi + ky + cy, -T))
    return (np.floor(first / T).astype(np.int64), np.floor(last / T).astype(np.int64))


@functools.lru_cache(maxsize=8)
def _lane_pixels(w: int, h: int) -> tuple:
    """The film pixel ``(x, y)`` (``np.int64`` arrays) of each of :func:`camera_hits`'
    lanes through a camera without a lens: :func:`camera_pixels` on the host
    (:func:`~mi_shadowmap.light_views.block_pixels`, whose filler lanes repeat the last
    column or row)."""
    B = PIXEL_BLOCK
    n = -(-w // B) * -(-h // B) * B * B     # whole blocks
    x, y = block_pixels(np.arange(n, dtype=np.int64), w, h, np.minimum)
    x.setflags(write=False)
    y.setflags(write=False)
    return x, y


def block_axis(vmap_like, margin: float, border: bool = False) -> int:
    """The largest block side (tiles) :func:`mark_blocks` gives for ``margin`` (its
    ``per_axis``; ``border``: with its ``border`` given)."""
    m_block = _margins(vmap_like, margin, border)[1]
    return int(math.ceil(2.0 * m_block / vmap_like.layout.tile_size)) + 1


def _margins(vmap_like, margin: float, border: bool = False) -> tuple:
    """``(m, m_block, m_edge)`` in texels: how far around a point its marks reach (the
    method's ``margin`` plus the camera samples' offset from the pixel centre: half a
    pixel, 2^(-1 - lod_bias) texels at the lower end of its level's range, 1 at the
    default ``lod_bias``, since finer levels put a pixel's samples farther from its
    centre in texels; at most half a page), how far a block reaches for any point (up to
    :data:`MAX_SPREAD` with the receiver biases' cap, else ``m_edge``), and how far a
    film-border pixel's point marks (:func:`_tile_range`'s ``border``; ``m`` unless
    ``border``: the method's ``virtual_footprint`` is given).

    A sample off its pixel's centre reads its kernel beside the neighbouring pixel's
    centre, whose marks reach ``m`` from there. A border pixel has no neighbour beyond
    the film: its own marks reach the kernel plus half its footprint's longer side, under
    ``2^(1 - lod_bias)`` texels at its level (:meth:`VirtualShadowMap.level_for`: a
    texel is over ``2^(lod_bias - 1)`` of the footprint's shorter side, or of half its
    longer one, ``ANISO`` 2), 2.83 at the default; ``m_edge`` is ``margin`` plus that."""
    P = vmap_like.layout.page_size
    off = max(1.0, 2.0 ** (-1.0 - effective_lod_bias(vmap_like.lod_bias, P)))
    m = min(float(margin) + off, 0.5 * P)
    m_edge = min(float(margin) + max(off, _footprint_texels(vmap_like)), 0.5 * P) \
        if border else m
    capped = getattr(vmap_like, "reach", None) is not None
    return m, (max(m_edge, MAX_SPREAD) if capped else m_edge), m_edge


def _footprint_texels(vmap_like) -> float:
    """The bound on half a pixel footprint's longer side, in texels of its level:
    ``2^(1 - lod_bias)`` (:meth:`VirtualShadowMap.level_for`: a texel is over
    ``2^(lod_bias - 1)`` of the footprint's shorter side, or of half its longer one,
    ``ANISO`` 2; at level 0 the footprint is smaller still), 2.83 at the default."""
    return 2.0 ** (1.0 - effective_lod_bias(vmap_like.lod_bias, vmap_like.layout.page_size))


def shape_bits(layout, per_axis: int):
    """Bits per axis that hold a block's shape (``0 .. per_axis - 1`` more tiles) above
    its first tile's coordinate in a key's 27-bit field (:func:`mark_blocks`), or None
    where the level-0 tiles leave no room for them (a face of more than ``2^(27 - bits)``
    tiles a side: 2^30 texels in tiles of 8 for ``hard``)."""
    bits = max(int(per_axis - 1).bit_length(), 1)
    n_tiles = layout.pages_per_side(0) * layout.tiles_per_side
    return bits if n_tiles <= (1 << (27 - bits)) else None


def expand_blocks(found: list, per_axis: int, bits=None) -> np.ndarray:
    """The tile keys of :func:`mark_blocks`' blocks: ``found[c]`` the first tiles of the
    blocks of list ``c``'s shape (repeats allowed); with ``bits`` (:func:`shape_bits`:
    :func:`mark_blocks`' one list) ``found[0]`` the keys with their shapes. Unsorted, with
    repeats.

    A block's tile ``(dx, dy)`` from its first is the first's key plus ``dx << 27 | dy``
    (its tiles never leave their level's grid, below ``2^(27 - bits)``: no carry). Most
    blocks are 2 x 2 tiles or less (on a 256^2 camera move 99.7 % of large_world's 8.6 k
    ``hard`` blocks, 99.1 % of room_two_points'): their tiles are the blocks' own keys
    plus, for those 2 wide, tall or both, one offset each (three selections); the others
    expand in two passes of ``np.repeat`` over their sizes (:func:`_expand_repeat`).
    Expanding every block by the repeats took 0.51 ms for large_world's blocks, 1.5-1.7
    ms for each light of room_two_points'; this 0.25 and 0.49-0.53 ms (a loop over the
    ``per_axis^2`` offsets, each a selection of the blocks that reach it, took 3.2 ms for
    6000 random blocks of up to 9 x 9 tiles; the repeats 0.46 ms)."""
    if bits is not None:
        first = np.asarray(found[0], np.uint64)
        if len(first) == 0:
            return np.zeros(0, np.uint64)
        top = np.uint64(27 - bits)
        ones = np.uint64((1 << bits) - 1)
        # the shape's bits (the top ``bits`` of each coordinate's 27) out of the key
        base = first & ~((ones << (top + np.uint64(27))) | (ones << top))
        sx = (first >> (top + np.uint64(27))) & ones     # width - 1
        sy = (first >> top) & ones                       # height - 1
        wide, tall = sx >= 1, sy >= 1
        big = (sx > 1) | (sy > 1)
        parts = [base]
        if big.any():
            small = ~big
            wide &= small
            tall &= small
            parts = [np.compress(small, base)]
        # (one selection and one add per offset: a (blocks, 4) broadcast add of uint64
        # took 0.13 ms for 8.6 k blocks, four 1-d adds 0.02 ms; each selection by
        # np.compress, not a boolean index, as layout.sorted_unique says why)
        one_x = np.uint64(1 << 27)
        parts += [np.compress(wide, base) + one_x, np.compress(tall, base) + np.uint64(1),
                  np.compress(wide & tall, base) + (one_x + np.uint64(1))]
        if big.any():
            parts.append(_expand_repeat(np.compress(big, base),
                                        np.compress(big, sx).astype(np.intp) + 1,
                                        np.compress(big, sy).astype(np.intp) + 1))
        return np.concatenate(parts)
    out = []
    for c, first in enumerate(found):
        if len(first) == 0:
            continue
        dx, dy = np.meshgrid(np.arange(c % per_axis + 1, dtype=np.uint64),
                             np.arange(c // per_axis + 1, dtype=np.uint64))
        offset = (dx.reshape(-1) << np.uint64(27)) + dy.reshape(-1)
        out.append((np.asarray(first, np.uint64)[:, None] + offset[None, :]).reshape(-1))
    return (np.concatenate(out).astype(np.uint64) if out else np.zeros(0, np.uint64))


def block_tiles(found: list, per_axis: int, bits=None) -> np.ndarray:
    """``sorted_unique(expand_blocks(found, per_axis, bits))`` without expanding the
    blocks: each (face, level) of the blocks gets a grid over its blocks' bounding box,
    every block adds +1 / -1 at its four corners (one ``np.bincount`` over all of them)
    and running sums along both axes give how many blocks cover each tile; the covered
    tiles in the grid's row-major order are the sorted keys (a key orders face, level,
    then x, then y). Neighbouring camera points mark overlapping blocks of many sizes
    (the receiver biases' capped levels: blocks up to :data:`MAX_SPREAD` texels wide):
    on a 256^2 camera move under sky_sun's 16 regions ``hard``'s 90 k blocks expanded to
    231 k tiles, 22 k of them distinct, and ``pcss``'s 20 k to 500 k (33 k distinct),
    whose expansion and sort took most of a moved frame's host time. Grids holding more
    than :data:`PAINT_AREA` times the expanded tiles (blocks scattered far apart on a
    level), and blocks of at most :data:`PAINT_TILES` tiles on average, fall back to the
    expansion and the sort."""
    if per_axis <= 2:
        # blocks of at most 2 x 2 tiles (hard's): expand_blocks' three selections and the
        # sort took 4-5 ms for the 90 k blocks above, the grids 6.5-8 ms
        return sorted_unique(expand_blocks(found, per_axis, bits))
    base, w, h = _block_sizes(found, per_axis, bits)
    if len(base) == 0:
        return np.zeros(0, np.uint64)
    n_tiles = int((w * h).sum())
    if n_tiles <= PAINT_TILES * len(base):
        return sorted_unique(expand_blocks(found, per_axis, bits))
    group = (base >> np.uint64(54)).astype(np.intp)      # face and level: < 1024
    M = np.uint64((1 << 27) - 1)
    x = ((base >> np.uint64(27)) & M).astype(np.int64)
    y = (base & M).astype(np.int64)
    n_groups = 1024
    x0 = np.full(n_groups, np.iinfo(np.int64).max)
    y0 = np.full(n_groups, np.iinfo(np.int64).max)
    x1 = np.full(n_groups, -1, np.int64)
    y1 = np.full(n_groups, -1, np.int64)
    np.minimum.at(x0, group, x)
    np.minimum.at(y0, group, y)
    np.maximum.at(x1, group, x + w)
    np.maximum.at(y1, group, y + h)
    used = np.flatnonzero(x1 >= 0)
    # a grid of (W + 1) x (H + 1) corners per group, all groups one after another
    gw, gh = x1[used] - x0[used] + 1, y1[used] - y0[used] + 1
    area = gw * gh
    if int(area.sum()) > PAINT_AREA * n_tiles + (1 << 12):
        return sorted_unique(expand_blocks(found, per_axis, bits))
    start = np.zeros(n_groups, np.int64)
    start[used] = np.cumsum(area) - area
    stride = np.zeros(n_groups, np.int64)
    stride[used] = gh
    st = stride[group]
    # the blocks' corners: +1 at (x, y) and (x + w, y + h), -1 at the other two
    c00 = start[group] + (x - x0[group]) * st + (y - y0[group])
    c10 = c00 + w * st
    total = int(area.sum())
    count = (np.bincount(np.concatenate([c00, c10 + h]), minlength=total)
             - np.bincount(np.concatenate([c10, c00 + h]), minlength=total))
    out = []
    for g, a0, W, H in zip(used.tolist(), start[used].tolist(), gw.tolist(), gh.tolist()):
        grid = count[a0:a0 + W * H].reshape(W, H)[:W - 1, :H - 1]
        ij = np.flatnonzero(np.cumsum(np.cumsum(grid, axis=0), axis=1))
        i, j = np.divmod(ij, H - 1)
        out.append(np.uint64(g << 54) | ((i + int(x0[g])).astype(np.uint64) << np.uint64(27))
                   | (j + int(y0[g])).astype(np.uint64))
    return np.concatenate(out)


#: :func:`block_tiles` paints a (face, level)'s blocks into a grid over their bounding
#: box when the blocks hold more than ``PAINT_TILES`` tiles each on average and the
#: grids together at most ``PAINT_AREA`` times the blocks' tiles (else it expands and
#: sorts them).
PAINT_TILES = 4
PAINT_AREA = 8


def _block_sizes(found: list, per_axis: int, bits=None) -> tuple:
    """``(first, w, h)`` of :func:`mark_blocks`' blocks (as :func:`expand_blocks` reads
    ``found``): each block's first tile key without its shape bits, and its size in
    tiles (``np.int64``)."""
    if bits is not None:
        first = np.asarray(found[0], np.uint64)
        top = np.uint64(27 - bits)
        ones = np.uint64((1 << bits) - 1)
        base = first & ~((ones << (top + np.uint64(27))) | (ones << top))
        w = ((first >> (top + np.uint64(27))) & ones).astype(np.int64) + 1
        h = ((first >> top) & ones).astype(np.int64) + 1
        return base, w, h
    firsts = [np.asarray(f, np.uint64) for f in found]
    n = [len(f) for f in firsts]
    shape = np.repeat(np.arange(len(firsts)), n)
    base = np.concatenate(firsts) if firsts else np.zeros(0, np.uint64)
    return base, shape % per_axis + 1, shape // per_axis + 1


def _expand_repeat(base: np.ndarray, w: np.ndarray, h: np.ndarray) -> np.ndarray:
    """The tiles of blocks whose first tiles are ``base`` (keys without their shapes),
    ``w`` x ``h`` tiles: every block's ``w`` columns (``dx``), then every column's ``h``
    tiles (``dy``), two passes of ``np.repeat`` (no division)."""
    end = np.cumsum(w)
    dx = np.arange(end[-1]) - np.repeat(end - w, w)
    cols = np.repeat(base, w) + (dx.astype(np.uint64) << np.uint64(27))
    h = np.repeat(h, w)
    end = np.cumsum(h)
    dy = np.arange(end[-1]) - np.repeat(end - h, h)
    return np.repeat(cols, h) + dy.astype(np.uint64)


def coarser_levels(layout, level, coarse_res: int):
    """Per point, how many levels coarser than its own ``level`` (``mi.UInt32``) its
    lookups may read for a method with ``virtual_coarse_res = coarse_res``: those of
    resolution ``coarse_res`` or more (down to the coarsest, at most
    :data:`MAX_COARSER`)."""
    log_res = mi.Int32(int(math.log2(layout.res0))) - mi.Int32(level)
    k = log_res - int(math.ceil(math.log2(max(int(coarse_res), 1))))
    k = dr.minimum(k, mi.Int32(layout.coarsest) - mi.Int32(level))
    return mi.UInt32(dr.clip(k, 0, MAX_COARSER))


def mark_coarser(vmap_like, si, dp_dx, dp_dy, valid, coarse_res: int,
                 active=None, points=None) -> tuple:
    """``(keys, oks)`` like :func:`mark_candidates` for the coarser levels a method
    with ``virtual_coarse_res`` may read (:func:`coarser_levels`): at each of them, the
    tile under the point only (one candidate per level: neighbouring points mark the
    same few tiles there); the mark pass then adds the tiles within the method's margin
    of those on the host (:func:`dilate_tiles`)."""
    lay = vmap_like.layout
    T = lay.tile_size
    face, uv64, act, level = (points if points is not None else
                              marked_points(vmap_like, si, dp_dx, dp_dy, valid, active))[:4]
    k_max = coarser_levels(lay, level, coarse_res)
    keys, oks = [], []
    for k in range(1, min(MAX_COARSER, lay.coarsest) + 1):
        lev = dr.minimum(level + k, lay.coarsest)
        res = mi.Float64(mi.UInt32(lay.res0) >> lev)
        t = mi.Point2i(dr.floor(uv64 * res / T))
        n_tiles = dr.maximum(mi.Int32(lay.pages_per_side(0)) >> mi.Int32(lev), 1) \
            * lay.tiles_per_side
        oks.append(act & (k <= k_max) & (t.x >= 0) & (t.y >= 0) & (t.x < n_tiles)
                   & (t.y < n_tiles))
        keys.append(page_key(face, lev, dr.maximum(t.x, 0), dr.maximum(t.y, 0)))
    return keys, oks


#: (key, offset) pairs :func:`dilate_tiles` forms at once. Its margin is not capped (a
#: ``pcss`` of ``max_kernel = 4096``: 2050 texels, 515^2 offsets of 8^2 tiles): one grid
#: of every key and offset held 2.4 GB for 300 coarse-level tiles, and a 256^2 cbox_area
#: frame's 506 tiles made the process 4.4 GB resident (1.2 GB for the loop over offsets
#: the grid replaced); chunks of 2^20 pairs keep the grid's arrays near 40 MB (a frame of
#: the default margin, 506 tiles x 121 offsets, is one chunk).
DILATE_CHUNK = 1 << 20


def dilate_tiles(keys: np.ndarray, layout, margin: float) -> np.ndarray:
    """Tile keys ``keys`` and those within ``margin + 1`` texels of them on their level,
    sorted, distinct. Every offset at once (a key times offset grid: a loop of one
    selection per offset took 3.3 ms for the 506 tiles of a 256^2 cbox_area ``pcss``
    frame, margin 34 texels: 121 offsets; 1.6 ms now, most of it the sort), in chunks of
    keys of at most :data:`DILATE_CHUNK` (key, offset) pairs. Keys of any integer dtype,
    as uint64 (their face and level bits are masked as such)."""
    keys = sorted_unique(np.asarray(keys).astype(np.uint64, copy=False))
    if len(keys) == 0:
        return keys
    T = layout.tile_size
    r = int(math.ceil((float(margin) + 1.0) / T))
    face, level, tx, ty = (f.astype(np.int64) for f in key_fields(keys))
    n = np.maximum(layout.pages_per_side(0) >> level, 1) * layout.tiles_per_side
    d = np.arange(-r, r + 1)
    dx, dy = np.repeat(d, len(d))[None, :], np.tile(d, len(d))[None, :]
    # the face's and level's bits, then the tile's (within its level's grid: in range)
    fl = keys & ~np.uint64((1 << 54) - 1)
    step = max(1, DILATE_CHUNK // dx.size)
    out = []
    for s in range(0, len(keys), step):
        c = slice(s, s + step)
        x, y, nc = tx[c, None] + dx, ty[c, None] + dy, n[c, None]
        ok = (x >= 0) & (y >= 0) & (x < nc) & (y < nc)
        keys_c = fl[c, None] | (x.astype(np.uint64) << np.uint64(27)) | y.astype(np.uint64)
        out.append(sorted_unique(np.compress(ok.reshape(-1), keys_c.reshape(-1))))
    return out[0] if len(out) == 1 else sorted_unique(np.concatenate(out))


def tile_pages(tiles: np.ndarray, layout) -> tuple:
    """``(pages, masks)``: the distinct page keys of tile keys ``tiles`` (sorted) and
    each page's tile mask (bit ``tx + ty * tiles_per_side`` for tile ``(tx, ty)`` of
    the page). By a sort of the pages' keys and one ``np.bitwise_or.reduceat`` over their
    runs (``np.unique(return_inverse=True)``, which hashes in numpy 2.4, and
    ``np.bitwise_or.at`` took 0.29 ms for the 3.4 k tiles of a 256^2 large_world camera
    move, 0.42-0.48 ms for each light of room_two_points' 5-6 k; this 0.17 and 0.23-0.27
    ms)."""
    S = np.uint64(layout.tiles_per_side)
    face, level, tx, ty = key_fields(np.asarray(tiles, np.uint64))
    pk = page_key(face, level, tx // S, ty // S)
    if len(pk) == 0:
        return pk, np.zeros(0, np.int64)
    bit = np.int64(1) << (tx % S + (ty % S) * S).astype(np.int64)
    order = np.argsort(pk, kind="stable")
    pk = pk[order]
    first = np.empty(len(pk), bool)
    first[0] = True
    np.not_equal(pk[1:], pk[:-1], out=first[1:])
    starts = np.flatnonzero(first)
    return pk[starts], np.bitwise_or.reduceat(bit[order], starts)


def dedupe_many(groups: list, bits: int = 14, parts: list | None = None, first=(),
                second=None, late=None) -> list:
    """For each ``(keys, oks)`` of ``groups`` (one per light), most of the keys
    ``keys[i][oks[i]]`` without repeats (neighbouring pixels read the same pages: 4 x
    65 k candidates hold a few thousand keys), so that the host sorts a few thousand keys
    (:func:`sorted_unique`) instead of all candidates: one kernel computes every light's
    keys (from the camera hits) and scatters each list into its hash table of
    ``2^bits`` slots; a second finds the candidates whose key lost its slot to another
    key and scatters them into a second table (another hash); a third finds those that
    lost there too and appends their keys to a buffer of :data:`SPILL` per list and
    partition (an atomic counter: the same kernel whether a frame has any; it had its own
    kernel, launched in about half the frames of a 128^2 camera move on large_world and
    compiled the first time one did). Per group, both tables' keys plus the twice-lost
    candidates are returned (a superset of the distinct keys, with few repeats: with one
    table, about a seventh of 5 k keys lost their slot, and with them 40 k of the 260 k
    candidates, whose ``np.unique`` was a tenth of a camera move's frame). Which key wins
    a slot does not matter: the returned set is the same. The selection is done on the host
    with numpy, so every frame runs the same kernels (a compress and gather would trace
    new ones whenever a frame first has 0, 1 or more lost keys).

    ``parts``: per group, None or ``(part, n)``: its candidates' partition (``mi.UInt32``
    per candidate, below ``n``; an environment's region), each with its own ``2^bits``
    slots of the group's tables (``n 2^bits`` slots), so that one kernel dedupes the
    keys of every region as the region's own tables would (their load, and a region's
    lanes, which run together, touch only its slots). On the host a table's entries
    that repeat the previous table's in the same slot are left out (a group's tables
    share their slots: a key wins the same slot in each), one comparison per slot and
    table (comparing with every earlier table was quadratic in the lists: 300
    comparisons a slot for a 25-list ``pcss`` mark pass).

    ``first``: more variables evaluated in the first round's kernel (the mark pass's
    points, from which the keys are traced unevaluated: one kernel computes them, stores
    them and scatters their keys, where the first round read them back in a kernel of its
    own). ``second``: None, or a function called once the first round is launched, whose
    variables are evaluated in the second round's kernel (the pixels' words,
    ``planner._pixel_keeps``, which gather what the first kernel scattered).

    ``late``: None, or a function called once the first round is launched (after
    ``second``) that gives more groups, whose candidates may read what the first kernel
    scattered (the kept points' rings did, forty-ninth session): the second round
    scatters them into both of their tables (each its own hash) and stores their keys
    and which are candidates, and the third spills those that lost their slot in both,
    so a frame launches no more kernels. Their keys follow the groups' in the result."""
    # one table per candidate list: Dr.Jit puts scatters into different arrays in one
    # kernel (a second scatter into the same array would start a new kernel)
    flat = [(k, ok) for keys, oks in groups for k, ok in zip(keys, oks)]
    parts = [None] * len(groups) if parts is None else list(parts)
    flat_parts = [pt for (keys, _), pt in zip(groups, parts) for _ in keys]

    def slots_of(k, mult, pt):
        s = mi.UInt32((k * mi.UInt64(mult)) >> (64 - bits))
        return s if pt is None else s + (mi.UInt32(pt[0]) << bits)

    def table(pt):
        return dr.full(mi.UInt64, NO_KEY, (1 if pt is None else int(pt[1])) << bits)

    tables = [table(pt) for pt in flat_parts]
    def first_slots(flat):
        return [slots_of(k, 0x9E3779B97F4A7C15, pt) for (k, _), pt in zip(flat, flat_parts)]

    slot = first_slots(flat)
    for t, (k, ok), s in zip(tables, flat, slot):
        dr.scatter(t, k, s, ok)
    # the keys stored by this first kernel (NO_KEY: not a candidate) where they are few
    # (STORED_KEY_BYTES), and read back by the later rounds; else each round recomputes
    # them from their inputs (the mark pass's points: evaluated before, or in this first
    # round's kernel, ``first``), a few integer operations where storing every candidate
    # list (25 of a pcss mark under a 16-region sky, 60 MB) and reading it back twice was
    # bound by memory. (Either way a candidate's key has the same bits in every round:
    # the same operations on the same values.)
    stored = ()
    if 8 * sum(dr.width(k) for k, _ in flat) <= STORED_KEY_BYTES:
        stored = [dr.select(ok, k, mi.UInt64(NO_KEY)) for k, ok in flat]
    dr.eval(*tables, *first, *stored)
    if stored:
        flat = [(k, k != mi.UInt64(NO_KEY)) for k in stored]
        slot = first_slots(flat)
    extra = list(second()) if second is not None else []
    # the second round, in one kernel with the first round's losers
    tables2 = [table(pt) for pt in flat_parts]
    slot2 = [slots_of(k, 0xC2B2AE3D27D4EB4F, pt) for (k, _), pt in zip(flat, flat_parts)]
    lost = [ok & (dr.gather(mi.UInt64, t, s, ok) != k)
            for t, (k, ok), s in zip(tables, flat, slot)]
    for t2, (k, _), s2, lo in zip(tables2, flat, slot2, lost):
        dr.scatter(t2, k, s2, lo)
    # the late groups: both tables in this round (their candidates known only now)
    late = list(late()) if late is not None else []
    flat_late = [(k, mi.Bool(ok)) for keys, oks in late for k, ok in zip(keys, oks)]
    late1 = [table(None) for _ in flat_late]
    late2 = [table(None) for _ in flat_late]
    for t1, t2, (k, ok) in zip(late1, late2, flat_late):
        dr.scatter(t1, k, slots_of(k, 0x9E3779B97F4A7C15, None), ok)
        dr.scatter(t2, k, slots_of(k, 0xC2B2AE3D27D4EB4F, None), ok)
    dr.eval(*tables2, *lost, *extra, *late1, *late2, *(x for pair in flat_late for x in pair))
    lost2 = [lo & (dr.gather(mi.UInt64, t2, s2, lo) != k)
             for t2, (k, _), s2, lo in zip(tables2, flat, slot2, lost)]
    for t1, t2, (k, ok) in zip(late1, late2, flat_late):
        s1, s2 = (slots_of(k, mult, None) for mult in (0x9E3779B97F4A7C15, 0xC2B2AE3D27D4EB4F))
        lost2.append(ok & (dr.gather(mi.UInt64, t1, s1, ok) != k)
                     & (dr.gather(mi.UInt64, t2, s2, ok) != k))
    groups = list(groups) + late
    flat = flat + flat_late
    flat_parts = flat_parts + [None] * len(flat_late)
    tables = tables + late1
    tables2 = tables2 + late2
    # the twice-lost candidates' keys, appended to a small buffer per list in the same
    # kernel: whether a frame has any does not launch (nor, the first time, compile) a
    # kernel of its own (a few candidates in half the frames of a 128^2 camera move)
    counts = [dr.zeros(mi.UInt32, 1) for _ in flat]
    caps = [SPILL * (1 if pt is None else int(pt[1])) for pt in flat_parts]
    spills = [dr.zeros(mi.UInt64, cap) for cap in caps]
    for (k, _), lo2, c, b, cap in zip(flat, lost2, counts, spills, caps):
        at = dr.scatter_inc(c, mi.UInt32(0), lo2)
        # (opaque: batches of other region counts run the same kernel)
        dr.scatter(b, k, at, lo2 & (at < dr.opaque(mi.UInt32, cap)))
    dr.eval(*counts, *spills)
    counts = [int(c.numpy()[0]) for c in counts]
    overflow = None
    if any(n > cap for n, cap in zip(counts, caps)):
        # more than the buffer holds (a table far too small for its keys): every list's
        # twice-lost keys from one more kernel
        overflow = [dr.select(lo2, k, NO_KEY) for (k, _), lo2 in zip(flat, lost2)]
        dr.eval(*overflow)
    out, start = [], 0
    for keys, _ in groups:
        idx = range(start, start + len(keys))
        start += len(keys)
        found = []
        for tabs in (tables, tables2):
            # a group's tables share their hash: a key sits in the same slot in each, so
            # a slot's entries repeat across tables unless different keys won it
            prev = None
            for i in idx:
                row = tabs[i].numpy()
                keep = row != np.uint64(NO_KEY)
                if prev is not None:
                    keep &= row != prev
                found.append(np.compress(keep, row))     # (as sorted_unique)
                prev = row
        for i in idx:
            if overflow is not None and counts[i] > caps[i]:
                row = overflow[i].numpy()
                found.append(row[row != np.uint64(NO_KEY)])
            elif counts[i] > 0:
                found.append(spills[i].numpy()[:counts[i]])
        out.append(np.concatenate(found) if found else np.zeros(0, np.uint64))
    return out


class Marker:
    """The level choice of a :class:`VirtualShadowMap` without a store (mark pass);
    ``view``: the faces marked (default: the layout's view)."""

    def __init__(self, layout, lod_bias: float, view=None, reach=None, scene=None,
                 eye=None):
        self.layout = layout
        self.view = layout.view if view is None else view
        self.lod_bias = float(lod_bias)
        self.reach = reach      # the method's receiver biases (VirtualShadowMap.level_for)
        # the scene the probes of marked_points trace, where the render's lookups know
        # their film pixel (None: the biases' level wherever it applies, no probe)
        self.scene = scene
        # the pinhole of the camera whose pixels are probed (opaque), or None
        self.eye = eye

    level_for = VirtualShadowMap.level_for
    _levels = VirtualShadowMap._levels
