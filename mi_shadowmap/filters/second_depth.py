"""Second-depth shadow maps with virtual samples (Wang & Molnar 1994).

Y. Wang and S. Molnar, "Second-Depth Shadow Mapping", UNC Chapel Hill
TR94-019, 1994 (``shared/papers/001``). The map stores the depth of the
**second** surface from the light (built by
:func:`mi_shadowmap.depth_maps.second_depth_layer`, layer ``second_depth``,
only when this method is used; virtual maps' pages cast that layer alone: the lookup
reads no first depth, ``reads_depth=False``, and the paper's Pass 1 keeps none either,
"at the end of the pass, the front surface can be discarded";
:func:`mi_shadowmap.methods.casts_first_depth`); the lookup is the per-pixel
algorithm of the paper's Figure 10:

1. compare the camera sample's depth ``z`` with the second depth
   ``z_second`` of every nearby texel (``z <= z_second``: lit);
2. all lit -> 1, all shadowed -> 0;
3. otherwise fit the tangent plane (shading point + its normal), and
   for every nearby texel compute the depth of the **virtual sample** --
   the point of that plane seen through the texel -- and compare it with
   the texel's ``z_second``; return the lit fraction (percentage-closer
   filtering).

The "nearby samples" are the ``sqrt(k) x sqrt(k)`` texels nearest the lookup
point, ``k = pcf_samples`` (default 4, i.e. 2 x 2), counted unweighted as in
the paper's ``VirtIllumCnt / NUM_SAMPLES``.

Deviations from the paper, and why:

* **Depth space.** The paper solves the tangent plane in light *screen*
  coordinates, ``z_L = -(a_L x_L + b_L y_L + d_L) / c_L``. Our maps store the
  distance along each texel's ray (see :mod:`mi_shadowmap.light_views`), so
  the virtual sample's depth is the same point computed directly: the
  texel's own ray (through its centre, moved by ``light_views.base.TEXEL_SAMPLE``,
  about 1/100 texel) meets the plane at
  ``t = n . (p - o) / (n . d)``. ``n . d`` plays the role of ``c_L``.
* **The plane's normal is the geometric one.** The paper fits the plane through the
  pixel's normal, which polygon renderers of its time interpolated for shading. The
  map holds the geometry, though, and an interpolated normal tilts the plane away from
  it: on a flat two-triangle floor whose vertex normals lean 56 degrees, or on a coarse
  smooth-shaded heightfield, the virtual samples of the shading normal's plane fall
  behind the surface and 31-38 % of the pixels were shadowed by the surface itself
  (0.05-0.6 % with the geometric normal, as with ``face_normals``). Where no normals
  are interpolated (analytic shapes, flat-shaded meshes) the two are the same.
* **Guard for c_L -> 0.** The paper computes virtual samples whatever the
  plane's slope: its answer to Figure 9 (a curved surface whose tangent
  plane is nearly parallel to the light ray) is to compute them only where
  the ordinary comparisons disagree, which we do. Only where the division
  itself is meaningless -- the plane within ``1 / _PARALLEL_TAN`` radians
  (1e-4) of the texel's ray, where ``n . d`` is rounding noise -- or where
  the intersection is behind the light, does a tap keep its ordinary
  comparison. The guard is deliberately not ``max_tan_slope`` (the slope
  bias's clamp, 20, i.e. 2.9 degrees): a planar receiver under a grazing
  light is exactly where virtual samples are exact and the ordinary
  comparisons of a non-solid fail (half of the 2 x 2 taps lie in front of
  the receiver), and such a guard left lit floors at visibility 0.5.
* **Equality tolerance.** Sec. 3.3 makes the test ``<=`` so that planar
  non-solids (first = second surface) light themselves. In floating
  point the plane's depth computed from the shading point and the
  ray-traced depth of the same plane differ by rounding (~1e-7 relative),
  so "equal" means within ``_EQ_REL`` (1e-5) of the depth. The ray-traced
  depth's rounding also grows with the plane's own coordinates (a ground 1e4
  wide under a light 4 units above it: up to 2.9e-4 at depths of 4-11), so
  the layer stores a surface that is its own second surface (the first one its ray
  reaches) raised by 16 units in the last place of the hit triangle's largest
  coordinate (:data:`~mi_shadowmap.depth_maps.ROUNDING_ULPS`; such a ground was 27 %
  shadowed by itself, 39 % at 1e6 wide, 0.01 % now; the walls of a sphere room lit
  from inside, whose back faces are their own second surface, 41 %).
  These are rounding tolerances, not biases: closed solids' back faces, stored past
  their front faces, get none (with it, the shadows behind them lost a band 16 ulps
  of the coordinates deep: 0.1 units 1e5 from the origin).
  A tap whose ray grazes the receiver's plane sees every rounding off the plane (the
  camera hit's, up to an ulp of its coordinates; the light's and the texel ray's)
  ``1 / |n . d|`` times deeper along the ray, beyond ``_EQ_REL``: a point light 0.01
  before a wall (``|n . d|`` 0.002-0.009 on the wall) shadowed the wall's lower part by
  its own texels, 1.3 % of a 128^2 view (full 1024^2 map: 1.9 %; a wall turned 30
  degrees 5.1 %). So the compare allows, where it is the larger, ``DEPTH_ULPS`` of the
  larger of the point's largest coordinate and the tap's depth (the margin
  :func:`~.common.receiver` gives other methods' receiver depths) along the plane's
  normal, divided by ``|n . d|`` along the ray (``_PLANE_ULPS``): 0.1 % (0.8 %) now, the
  rest where the floor meets the wall within a texel. Off the plane that is a few ulps
  whatever the slant, so a second surface more than that in front of the plane (an
  occluder) still shadows; along the ray it is at most ``PARALLEL_TAN`` (1e4) times that,
  where the virtual samples stop. (Added to ``_EQ_REL`` rather than the larger of the
  two, it also lit a few taps under solids resting on a ground lit from 40 degrees.)
* **Solids and non-solids** are told apart per shape when the map is
  built (closed, outward-oriented meshes and spheres are solids; see
  :func:`mi_shadowmap.depth_maps.shape_is_solid`): the paper assumes the
  user knows. A non-solid (open or one-sided surface) is its own second
  surface (sec. 3.3), and so is a solid's inside lit by a light within it (a
  room built as a closed shape).
* **Curved surfaces that are their own second surface.** The paper says they
  need a ``bias`` (sec. 3.3): the tangent plane leaves a curved surface, and on
  a concave one (a sphere room lit from inside) its virtual samples lie behind
  it. Instead of a bias, each virtual sample's compare allows the plane's bend,
  ``kappa d^2 / 2`` along the normal at distance ``d`` from the shading point
  (divided by ``|cos|`` of the texel's ray to the normal), ``kappa`` the largest
  curvature with which the surface rises off the plane towards the light, from the
  shading normal's derivatives (``si.dn_du``, ``si.dn_dv``; the integrator asks for
  them, ``needs_curvature``): 0 on planes and where the surface falls away from the
  light (a convex receiver's virtual samples lie in front of it anyway), so those
  keep the paper's exact compare (an unsigned allowance let thin plates over a
  sphere leak light: 0.8 against 0.4 % at a 64^2 map). Measured: a point light
  inside a sphere room shadowed 39-46 % of the pixels, 0.05 % now.
  The curvature bounds how a smooth surface leaves its tangent plane at the point,
  not how a tessellation leaves a facet's plane (the facets are chords, tilted
  against the surface by up to half the angle between neighbours), and a flat-shaded
  tessellation has none to read (0 between its facets). On a mesh hit the bend is
  measured from the face's centroid (:func:`facet_centre`), which covers the chord's
  tilt for smooth-shaded tessellations.
* **Tessellated surfaces that are their own second surface: the neighbouring faces'
  planes.** Where a mesh rises off a face's plane towards the light (a closed shade or
  room lit from inside), a tap whose texel sees a neighbouring face compares that face
  with the plane running behind it, and shadows the point: the more taps the coarser the
  texels against the faces, as on virtual maps, whose level follows the pixel footprint.
  So a mesh hit also takes virtual samples on the planes of the faces that share an edge
  with its face, rise towards the light (folded more than 1e-3 rad off the face's plane,
  on the light's side: the third vertex's height over it against its distance from the
  shared edge) and turn the same side to it
  (:func:`rising_neighbours`, from Mitsuba's directed edges, which the integrator builds
  for this method; a neighbour seen from its other side is in the layer where the
  light's rays leave a solid, as a ridge's far slope over the valley it shadows: with
  those a solid terrain under a low sun was false lit on 2.2 % of a view instead of
  0.7 %): a tap is lit when the surface its texel saw lies at or behind either plane -- the
  paper's virtual samples on the piecewise-planar surface around the point rather than
  on one plane. Where every ordinary compare says shadowed and the face has such a
  neighbour (near a vertex every nearby texel sees faces nearer the light than the
  point), the virtual samples are taken too and counted only if a tap sees a neighbour's
  plane (the paper returns 0 there; a solid resting on the face, whose second surface
  lies in the face's plane, keeps its shadow: counting every tap lit a box's shadow on a
  ground, 6.5 % of a view false instead of 2.2 %). Faces that share positions through
  separate vertices (a mesh split at seams, Mitsuba's ``cube``), faces seen through an
  ``instance`` and taps two faces away (across a vertex) get no such plane. Measured: a
  rough-glass 320-face icosphere (radius 0.6) around a point light, seen from 5 units at
  64^2, flat / smooth-shaded: the image 0.65 / 0.72 of ``raytraced``'s on virtual maps
  (texels 0.03 wide at the shade, a fifth of a face), 0.83-0.92 on 64-256^2 full maps;
  now 0.97 on virtual maps and 0.999-1.000 on full maps. A light inside icosphere rooms
  (20-1280 faces) falsely shadowed 0.3-2.2 % of a 64^2 view, 0.05-0.2 % now; a box room
  of 12 welded faces 0.14 / 0.24 % (virtual / full), 0.05 / 0.09 %, with false light
  unchanged within 0.03 points; an open terrain under a sun or a point light 0.9-2.8 %
  -> 0.1-0.5 %, false light up by at most 0.17 points (shadow edges within a texel of a
  fold). A box room whose walls do not share vertices (``cube``) keeps its corners'
  false shadows (0.14 / 0.24 % there), where one wall's plane runs behind the next;
  ``bias`` removes them. ``slope_bias`` and ``normal_bias`` also default to 0 here and
  are applied like everywhere else (see :func:`~.common.receiver`) when set.
  The fold is measured from the shared edge, not from the shading point: a ramp's faces
  0.2 wide and 40 long (flat-shaded, its slope growing 0.5 degree a face to 5 degrees,
  open, all lit by a sun 6 degrees high) read their 0.5-degree folds as 5e-5 rad from a
  point 36 units along the edge, no neighbour counted, and 186 of 4096 pixels were
  falsely shadowed at 64^2 (314 of 16384 at 128^2; ``hard`` 0): 73 (79) now.
* **Beyond the neighbouring faces: the paper's bias.** The neighbours' planes are one
  ring of faces. Where a level's texels span several faces of a surface that keeps
  rising off every face's plane (the ramp above, its texels 0.8-3.4 units long on it at
  the footprint's levels of pixels 20 units away), a 2 x 2 block's taps see faces up to
  15 folds away, in front of the neighbours' planes too, and the virtual samples shadow
  a lit point: those 73 pixels. That is the paper's own limit (sec. 3.3: a curved
  two-sided surface "will need a bias"; sec. 3.2, Figure 9: the tangent plane leaves a
  curved surface), and its remedy works: ``bias`` 0.1 leaves 15, 0.3 none; so does a
  map whose texels stay within a fold (``lod_bias`` -2: 10; a full 512^2 map: 0).
  A flat-shaded tessellation has no curvature to bend the plane by (above), and an
  isotropic allowance from the folds' angles would also light occluders lying on such
  a surface, so the bias stays the user's (``tests/test_second_depth_extremes.py``).
* **Thin objects** (the paper's Figure 7) remain a failure case where the
  surface is curved: virtual samples remove the false shadows but the
  tangent plane can still miss the surface by more than its thickness
  (measured in ``tests/test_second_depth.py``).
* **Thin objects under a grazing light: between the texel rows.** A plate 1e-3 thick,
  1e-3 over a floor, under a point light 0.01 over the floor 4-7 units away, shadows a
  band of the floor that the light sees within 7e-4 rad of elevation, less than a 1024^2
  cube face's rows are apart (1.7e-3 rad there): the rows pass over and under the plate,
  and the shadow is lit (1012 of 16384 pixels at 128^2 on a full 1024^2 map, 933 on virtual
  maps; a sun 0.05 degrees high: 388 / 408). Sample by sample, 99.6 % (full map) / 95 %
  (virtual) of those lookups' 2 x 2 blocks hold no texel whose ray meets the plate: their
  compares disagree (rows before the plate and far beyond it), and the virtual samples
  on the floor's plane, its own second surface, agree with every tap. ``hard`` reads the
  same rows' first depths and lights the same pixels (1012 on the full map; 699 on
  virtual maps, whose level it keeps finer for its biases' reach; a sun 0.05 degrees
  high 398 / 419). The paper's sec. 4.1: errors occur "if objects in the scene fit
  between depth-map samples ... the only solution is to increase the size of the depth
  map" (4096^2: 856; the sun's 4096^2: 193, ``hard`` 232).
* **Off-map / face borders.** Lookups outside the map are lit; taps are
  clamped to the receiver's face (cube-map seams are not crossed). A block cut by the
  face's border (within ``side / 2`` texels of it; on a face of one texel everywhere)
  does not surround the point: its taps read the border's texels again, all on one side
  of it, so its compares all shadowing the point is no evidence -- an open plane (its
  own second surface) whose depth grows towards the border is farther than each of
  them. The paper's trivial shadow assumes nearby samples around the point; there the
  virtual samples decide, as for a single tap. Measured, full maps of 1 / 2 / 4 / 8 / 16
  / 32 texels a face, a floor with a box, a ball and a post (64^2): under a point light
  43.0 / 22.2 / 10.2 / 5.2 / 2.2 / 1.0 % misclassified, now 2.8 / 3.1 / 3.1 / 2.4 / 1.3
  / 0.7 (``hard`` 2.5 / 2.5 / 2.5 / 2.1 / 1.3 / 0.7); a spot 27.5 / 10.3 / 2.1 at 1-4
  texels, now 27.5 / 1.3 / 1.3. Virtual maps' cube seams too: of the repository scenes
  (128^2, 4 spp) those lit through cube faces (``room_two_points``, ``spectral_point``,
  ``cbox_area``) changed on 15-138 pixels, their visibility RMSE against ``raytraced``
  0.5-25 % lower on virtual and full 256-1024 maps, no more misclassified. Where the
  shadows are large (``scenes.default_scene``, a point light, 2 and 4 texels a face) the
  floor's self-shadow had also covered the ball's shadow, which no sample sees: 14.6 %
  misclassified, now 16.6 / 15.0 (``hard``: 15.0, all lit). Where a
  face's one texel sees an occluder (the spot and a sun above, 22-27 % at 1 texel) its
  one sample is shadowed and the floor behind it is: the method's limit, as sec. 4.1
  says ("the only solution is to increase the size of the depth map"); ``hard`` there
  lights everything (its texel-scaled biases exceed the scene; with them at 0 it
  shadows 47-57 %).
* **Virtual maps where the light grazes the receiver.** The paper's answer to
  under-sampling (an occluder's edge, or a gap between occluder and receiver, finer
  than the map's samples; sec. 5) is a larger map. Virtual maps choose a level per
  pixel footprint, and their anisotropy clamp leaves texels many footprints long along
  a receiver the light grazes; the lit fraction of the virtual samples places an edge
  within half a texel of the map, ``1 / cos(theta)`` times that along the receiver, so
  the method's ``virtual_edge`` (0.5 texel) keeps that within ``REACH_PIXELS`` pixel
  footprints as the other methods' texel-scaled biases do
  (:class:`~.common.BiasReach`). A floor lit through the 0.1-high gap under a cube by a
  light 0.2 over it: 132 of 4096 pixels misclassified, now 4 (full maps 57).
  That level is kept only by the pixels the mark pass probes keep it for
  (:func:`~mi_shadowmap.virtual.marks.marked_points`): a shadow's edge within reach, or
  the receiver's surface in front of its tangent plane where the footprint's level's
  farthest taps meet the plane (a rippled open receiver, whose virtual samples there
  lie behind it: the method's own false shadow, which the finer level's nearer taps
  avoid); elsewhere the footprint's. Kept everywhere, it built 27.5 texels a film pixel
  on ``random_terrain_world(15)`` at 256^2 (a sun 2-5 degrees high; ``hard`` 5.5), 5.6
  probed, with misclassified pixels unchanged on 6 terrains at 128^2.
* ``virtual_samples=false`` skips step 3 (plain percentage-closer
  filtering of the second depths): used to show the paper's Figure 7
  failure on thin objects.
"""
from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi

from ..depth_maps import second_depth_layer
from ..methods import Method, Prop
from ..light_views.base import texel_sample_uv
from .common import (DEPTH_ULPS, PARALLEL_TAN as _PARALLEL_TAN, Lookup,  # noqa: F401
                     bend_along_ray, concavity, nearest_block, taps_loop,
                     virtual_sample_depth)

#: Relative rounding tolerance of the ``<=`` test at virtual samples.
_EQ_REL = 1e-5

#: The rounding a virtual sample's compare allows (where larger than ``_EQ_REL``'s) off
#: the receiver's plane, along its normal, relative to the larger of the point's largest
#: coordinate and the tap's depth (:data:`~.common.DEPTH_ULPS`, the margin
#: :func:`~.common.receiver` gives a receiver depth): the point's, the light's and the
#: texel ray's rounding. Along the tap's ray that is ``1 / |n . d|`` times as much (at
#: most :data:`~.common.PARALLEL_TAN` times, where virtual samples stop).
_PLANE_ULPS = DEPTH_ULPS


def plane_normal(lk: Lookup) -> mi.Vector3f:
    """The normal of the tangent plane the virtual samples lie on: the geometric one
    (see the module doc)."""
    return mi.Vector3f(lk.n_world)


def facet_centre(lk: Lookup, p, n, active) -> mi.Point3f:
    """Where the bend allowance is measured from: ``p``, or on a mesh hit the centroid
    of its face moved into the plane through ``p`` (normal ``n``). A smooth surface
    tessellated into chords rises off a face's plane from the face's middle, not from
    the shading point: near the face's edge the next faces rise by ``kappa rho d``
    (``rho`` the face's size) more than ``kappa d^2 / 2``."""
    si = lk.si
    if si is None or not hasattr(si, "prim_index"):
        return p
    ok = mi.Bool(active) & si.is_valid() & si.shape.is_mesh() \
        & (dr.reinterpret_array(mi.UInt32, si.instance) == 0) \
        & dr.all(dr.detach(mi.Point3f(lk.p_world)) == dr.detach(mi.Point3f(si.p)))
    mesh = mi.MeshPtr(si.shape)
    fa = mesh.face_indices(si.prim_index, ok)
    c = mi.Point3f(0.0)
    for k in range(3):
        c += dr.detach(mesh.vertex_position(fa[k], ok))
    c = c * (1.0 / 3.0)
    c = c - n * dr.dot(n, c - p)
    return dr.select(ok & dr.all(dr.isfinite(c)), c, p)


def rising_neighbours(lk: Lookup, n, to_light, active) -> list:
    """The planes of the mesh faces that share an edge with the hit's face, rise off its
    plane towards the light (folded more than 1e-3 rad across the shared edge, their
    third vertex on the light's side of it) and turn the same side to the light as it
    does: three
    ``(point, normal, valid)``, ``valid`` False for other edges, open edges (and edges
    whose faces share positions but not vertices), non-mesh hits, hits through an
    ``instance`` and lookups at another point than the hit's. Read through Mitsuba's
    directed edges (:func:`~mi_shadowmap.depth_maps.directed_edges`, which the
    integrator builds for ``second_depth``)."""
    si = lk.si
    if si is None or not hasattr(si, "prim_index"):
        return []
    p = dr.detach(mi.Point3f(lk.p_world))
    # the mesh's vertices are in world space: only where the lookup's point is the hit's
    # own (not a light pose's view of it, light_views.pose, nor a pixel centre)
    ok = mi.Bool(active) & si.is_valid() & si.shape.is_mesh() \
        & (dr.reinterpret_array(mi.UInt32, si.instance) == 0) \
        & dr.all(p == dr.detach(mi.Point3f(si.p)))
    mesh = mi.MeshPtr(si.shape)
    toward = dr.select(dr.dot(n, to_light) >= 0, 1.0, -1.0)
    # the hit face's side towards the light, with its vertices' winding (as the
    # neighbours' normals below)
    fa = mesh.face_indices(si.prim_index, ok)
    a = [dr.detach(mesh.vertex_position(fa[c], ok)) for c in range(3)]
    side_a = dr.dot(dr.cross(a[1] - a[0], a[2] - a[0]), to_light)
    out = []
    for e in range(3):
        de = mesh.opposite_dedge(si.prim_index * 3 + e, ok)
        valid = ok & (de < 3 * mesh.face_count())
        fi = mesh.face_indices(de // 3, valid)
        v = [dr.detach(mesh.vertex_position(fi[c], valid)) for c in range(3)]
        nb = dr.normalize(dr.cross(v[1] - v[0], v[2] - v[0]))
        c_opp = (de % 3 + 2) % 3                     # the vertex not on the shared edge
        opp = dr.select(c_opp == 0, v[0], dr.select(c_opp == 1, v[1], v[2]))
        e0 = dr.select(c_opp == 0, v[1], dr.select(c_opp == 1, v[2], v[0]))
        e1 = dr.select(c_opp == 0, v[2], dr.select(c_opp == 1, v[0], v[1]))
        # rising by more than 1e-3 rad (not a coplanar neighbour's rounding): the dihedral
        # angle, the third vertex's height over the plane against its distance from the
        # shared edge (not from p: along a long edge, p 36 units from the third vertex of
        # a ramp's 0.2-wide facet, a 0.5-degree fold read as 5e-5 rad), and turned to the
        # light as the hit face is: a neighbour seen from its other side is in the layer
        # as where the light's rays leave a solid (a ridge's far slope over a valley in its
        # shadow), not as a lit surface
        edge = e1 - e0
        off_edge = dr.norm(dr.cross(opp - e0, edge)) / dr.norm(edge)
        valid &= (toward * dr.dot(n, opp - p) > 1e-3 * off_edge) \
            & (side_a * dr.dot(nb, to_light) > 0) & dr.all(dr.isfinite(nb))
        out.append((mi.Point3f(v[0]), mi.Vector3f(nb), valid))
    return out


def second_depth(smap, lk: Lookup, opts, active=True) -> mi.Float:
    """Wang & Molnar (1994), Figure 10: percent illumination of a shading point."""
    # no rounding margin of the point's coordinates: the layer has it where a surface
    # is its own second surface (see receiver)
    r, active, k, side, i0 = nearest_block(smap, lk, opts, active, coordinate_margin=False)
    res = smap.resolution
    view = smap.view
    layer = smap.second_depth

    def tap_texel(tap):
        return mi.Point2i(i0.x + mi.Int32(tap % side), i0.y + mi.Int32(tap // side))

    def fetch(ij, act):
        ij = smap.clamp_texel(ij)
        return ij, smap.fetch(layer, r.face, ij.x, ij.y, act)

    # 1. ordinary comparisons z_camera <= z_second
    def count_body(tap, n_lit):
        _, z_second = fetch(tap_texel(tap), active)
        return (dr.select(r.depth <= z_second, n_lit + 1, n_lit),)

    (n_lit,) = taps_loop(k, count_body, (mi.UInt32(0),), active)
    # 2. trivial shadow / illumination
    vis = dr.select(n_lit == k, 1.0, 0.0)
    if not opts.virtual_samples:
        return dr.select(r.inside, mi.Float(n_lit) / k, 1.0)
    p = mi.Point3f(lk.p_world)
    n = dr.normalize(plane_normal(lk))
    offset = view.depth_of(p) - r.depth          # the configured biases (0 by default)
    kappa = concavity(lk, view.direction_to_light(p))
    # a mesh face's neighbours that rise towards the light (the facets its plane runs
    # behind), where a compare can disagree
    neighbours = rising_neighbours(lk, n, view.direction_to_light(p), active & (n_lit < k))
    rises = mi.Bool(False)
    for _, _, valid in neighbours:
        rises |= valid
    p_bend = facet_centre(lk, p, n, kappa > 0)
    # 3. virtual samples on the tangent plane where the compares disagree, and where all
    # shadow a mesh face with a rising neighbour (see the module doc)
    # (one tap, pcf_samples=1, never disagrees: its compare of a texel centre's depth
    # shadowed an open plane, its own second surface, about half the time; its virtual
    # sample decides there)
    single = k == 1
    # a block cut by the face's border (its taps clamped onto the border's texels) does
    # not surround the point: its compares shadowing all is no evidence (see the module
    # doc), and its virtual samples decide as a single tap's do
    last = i0 + (side - 1)
    cut = dr.any(smap.clamp_texel(i0) != i0) | dr.any(smap.clamp_texel(last) != last)
    mixed = active & (n_lit < k) & ((n_lit > 0) | rises | (kappa > 0) | single | cut)

    def virt_body(tap, n_virt, n_nb):
        ij, z_second = fetch(tap_texel(tap), mixed)
        z_v, ok = virtual_sample_depth(view, r.face, ij, res, p, n, _PARALLEL_TAN)
        # a curved surface leaves its tangent plane by kappa d^2 / 2 at distance d from
        # the shading point, along the normal; along the texel's ray that is divided by
        # |cos| of the ray to the normal, and corrected for the ray's slant: it reaches
        # the surface where the osculating sphere (radius 1 / kappa, on the light's side)
        # has bent further off the plane (see the module doc and bend_along_ray)
        o, d = view.ray_through(r.face, texel_sample_uv(ij, res))
        q = o + d * z_v
        bend = bend_along_ray(kappa, q - p_bend, d, n)
        z_v = z_v - offset
        # the rounding off the plane, along n, is 1 / |n . d| times that along the tap's
        # ray: a tap grazing the plane (a light just before a wall) read the plane's virtual
        # sample deeper than the surface's own texel by more than _EQ_REL (see the module
        # doc)
        c = dr.maximum(dr.abs(dr.dot(n, d)), 1.0 / _PARALLEL_TAN)
        p_round = _PLANE_ULPS * dr.maximum(dr.max(dr.abs(p)), dr.abs(z_v)) / c
        tol = z_second + dr.maximum(_EQ_REL * dr.abs(z_second), p_round)
        lit_v = z_v <= tol + bend
        on_nb = mi.Bool(False)
        for q_b, n_b, valid in neighbours:     # or on a rising neighbour's plane
            z_b, ok_b = virtual_sample_depth(view, r.face, ij, res, q_b, n_b, _PARALLEL_TAN)
            on_nb |= valid & ok_b & (z_b - offset <= z_second + _EQ_REL * dr.abs(z_second))
        lit = dr.select(ok, lit_v | on_nb, r.depth <= z_second)
        # taps lit only by a neighbour's plane or by the surface's bend (see below)
        n_nb = dr.select(ok & ((on_nb & ~lit_v) | (lit_v & (z_v > tol))), n_nb + 1, n_nb)
        return dr.select(lit, n_virt + 1, n_virt), n_nb

    n_virt, n_nb = taps_loop(k, virt_body, (mi.UInt32(0), mi.UInt32(0)), mixed)
    # where every compare said shadowed, only a tap that sees a neighbour face, or a
    # surface that rises towards the light within the receiver's bend, shows the texels
    # read the receiver's own surface (a solid resting on the face, whose second surface
    # lies in its plane, keeps its shadow: the paper's reason to return 0 there). A
    # concave receiver seen from the light has every compare shadowed where texels are
    # coarse against its curvature: the taps on both sides of the point across its slope
    # are nearer the light (a light 0.1 off the centre of a frosted sphere of radius 0.3,
    # on virtual texels 0.017 wide, left shell points at 0)
    vis = dr.select(mixed & ((n_lit > 0) | (n_nb > 0) | single | cut), mi.Float(n_virt) / k,
                    vis)
    return dr.select(r.inside, vis, 1.0)


METHOD = Method(
    name="second_depth",
    lookup=second_depth,
    summary="Wang & Molnar 1994 second-depth shadow maps with virtual samples",
    properties=(
        Prop("pcf_samples", "int", 4,
             "Percentage-closer taps k: one compare per texel of the sqrt(k) x sqrt(k) "
             "texels nearest the lookup point (4: 2 x 2).", choices=(1, 4, 9, 16, 25)),
        Prop("virtual_samples", "bool", True,
             "Where the neighbourhood compares disagree, compare depths of virtual samples "
             "on the receiver's tangent plane (Wang & Molnar 1994, sec. 3.2), and on the "
             "planes of a mesh face's edge neighbours that rise towards the light; false "
             "keeps the plain compares."),
    ),
    layers={"second_depth": second_depth_layer},
    bias_defaults={"slope_bias": 0.0, "normal_bias": 0.0},
    virtual_margin=lambda o: 2.0 + 0.5 * math.isqrt(o.pcf_samples),
    virtual_edge=lambda o: 0.5,
    needs_curvature=True, virtual=True, reads_depth=False, builtin=True,
)
