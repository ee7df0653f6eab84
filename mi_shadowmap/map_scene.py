"""The scene the shadow maps' rays query: the scene itself, or, where it holds
cylinders, a copy in which every cylinder is a fine triangle mesh.

Why: in Mitsuba 3.9's AD variants (``llvm_ad_*``, ``cuda_ad_*``) a ``cylinder``'s ray
intersection is solved in float32, in the cylinder's object space (radius 1). A ray
that starts ``D`` away from a cylinder of radius ``r`` solves a quadratic whose terms
are about ``(D / r)^2``; the radius's own term, 1, drowns in their rounding long
before the ray reaches the cylinder. Measured (20,000 rays aimed within 1.3 radii of a
cylinder of radius 0.03, against the same rays started 1 unit away): 19 rays hit where
they miss, or miss where they hit, from 10 units away; 2,561 from 100; 8,262 from 1,000
(depth errors up to 0.39, 13 radii). Spheres and disks are exact to 1e-6 of ``D``.
Camera rays and ``raytraced``'s shadow rays start near what they hit; a shadow map's
rays start at the light, or at the bounds of the scene (a directional light), so thin
cylinders -- posts, poles, trunks -- came out in the maps with holes and phantom
depths: on a 4 km ground under a low sun with posts 0.06 wide 2-1500 units away,
``hard`` misclassified 1.8-2.7 % of a 128^2 image where the same posts as boxes gave
0.8-0.9 % (``raytraced`` with another seed: 0.6-0.9 %). The posts' own sunlit sides read
as shadowed (a phantom depth 0.3-0.8 units in front of them).

What it does: every cylinder among the scene's shapes becomes an open prism of
:func:`segments` sides (Mitsuba's cylinders have no caps) with the cylinder's
``to_world``, its vertices at ``r / cos(pi / (2 n))^2`` so that the prism's faces lie
within ``+- r tan(pi / (2 n))^2`` of the true surface; meshes are intersected in
world space by Embree, exactly to float32. The copy holds the scene's other shapes
themselves (the same objects, so an area light's own shape is still recognised; a
cylinder that is an area light has its prism recognised instead, :func:`stand_in`), is
kept while the scene's shapes and their buffers are unchanged, and is used only for
the maps' depths (first and second); the render's camera rays, the reference's shadow
rays and the mark pass query the scene itself.

A cylinder that is an area light (a tube light) is replaced too: it is an occluder in
every other light's maps (kept as Mitsuba's cylinder, a tube 0.02 wide beside a ground
1e3 wide threw phantom shadows of the sun over 10 % of a 64^2 view, ``hard`` against
``raytraced``), and its own maps skip its prism (:func:`stand_in`).

Not replaced (the maps keep Mitsuba's cylinder there):

* cylinders inside an ``instance`` (a copy of the scene cannot hold the scene's
  instances: Mitsuba refuses to add an existing ``instance`` to another scene), so a
  scene with instances and cylinders keeps its cylinders, a warning says so (also
  where the only cylinders are inside shape groups: posts drawn through instances
  under a low sun over a 4 km ground, ``hard`` 13 % misclassified against 0.24 % for
  the same posts as shapes). The maps' depths (first and second) of such a scene take
  its own cylinders' prisms all the same, from a copy of its shapes but the instances
  (:func:`own_shapes_copy`); ``raytraced``'s shadow rays keep them;
* maps built with gradients or antialiased outlines (:func:`~mi_shadowmap.depth_maps.
  first_hit`'s ``differentiable``, ``return_hit``): their derivatives and outlines
  belong to the scene's own shapes.
"""
from __future__ import annotations

import math
import warnings

import drjit as dr
import mitsuba as mi
import numpy as np

#: Largest deviation of a prism's face from its cylinder, relative to the scene's
#: bounding-box diagonal (float32 holds a coordinate to 6e-8 of its magnitude).
DEVIATION = 1e-6
#: Sides of a prism: at least, at most.
MIN_SEGMENTS, MAX_SEGMENTS = 32, 2048

# id(scene) -> (scene, key, map scene or the scene itself, held buffers,
#               {id(replaced area-light cylinder): its prism}); at most 4
_MEMO: dict = {}
_MAX_SCENES = 4


def segments(radius: float, diagonal: float) -> int:
    """Sides of the prism standing for a cylinder of ``radius`` in a scene of bounding
    diagonal ``diagonal``: the fewest (a power of two, 32-2048) whose faces lie within
    ``DEVIATION * diagonal`` of the cylinder, i.e. ``r tan(pi / (2 n))^2`` (about
    ``r (pi / n)^2 / 4``) at most that."""
    if not (radius > 0.0 and diagonal > 0.0):
        return MIN_SEGMENTS
    n = math.pi / (2.0 * math.atan(math.sqrt(DEVIATION * diagonal / radius)))
    n = 2 ** math.ceil(math.log2(max(n, 1.0)))
    return int(min(max(n, MIN_SEGMENTS), MAX_SEGMENTS))


def is_cylinder(shape) -> bool:
    return shape.shape_type() == mi.ShapeType.Cylinder


def cylinder_radius(shape) -> float:
    """A cylinder's radius: the length of its ``to_world``'s first column (Mitsuba's
    cylinder has radius 1 in its object space)."""
    m = np.array(_traversal(shape)["to_world"].matrix, np.float64).reshape(4, 4)
    return float(np.linalg.norm(m[:3, 0]))


def cylinder_prism(shape, n: int) -> mi.Mesh:
    """An open prism of ``n`` sides standing for the cylinder ``shape`` (see the module
    doc), as a Mitsuba mesh without BSDF-relevant data (only its depths are read)."""
    to_world = np.array(_traversal(shape)["to_world"].matrix, np.float64).reshape(4, 4)
    phi = 2.0 * np.pi * np.arange(n) / n
    rho = 1.0 / math.cos(math.pi / (2 * n)) ** 2   # vertices and faces r tan^2 off, out and in
    ring = np.stack([rho * np.cos(phi), rho * np.sin(phi)], 1)
    local = np.concatenate([np.c_[ring, np.zeros(n), np.ones(n)],
                            np.c_[ring, np.ones(n), np.ones(n)]])     # z = 0, then 1
    world = (local @ to_world.T)[:, :3]
    i = np.arange(n, dtype=np.uint32)
    j = (i + 1) % n
    faces = np.concatenate([np.stack([i, j, j + n], 1), np.stack([i, j + n, i + n], 1)])
    mesh = mi.Mesh(f"{shape.id() or 'cylinder'} (prism of {n})", 2 * n, 2 * n,
                   has_vertex_normals=False)
    params = mi.traverse(mesh)
    params["vertex_positions"] = mi.Float(world.astype(np.float32).ravel())
    params["faces"] = mi.UInt32(faces.ravel())
    params.update()
    return mesh


# id(cylinder) -> (cylinder, its mi.traverse); cleared beyond _MAX_TRAVERSALS, and
# kept only for the cylinders of the scenes in _MEMO (_remember): the entry holds the
# cylinder, its BSDF and textures, which outlived their scene otherwise
_TRAVERSALS: dict = {}
_MAX_TRAVERSALS = 4096


def _traversal(shape):
    """``mi.traverse(shape)``, kept per shape (its values are read live)."""
    hit = _TRAVERSALS.get(id(shape))
    if hit is None or hit[0] is not shape:
        if len(_TRAVERSALS) >= _MAX_TRAVERSALS:
            _TRAVERSALS.clear()
        hit = _TRAVERSALS[id(shape)] = (shape, mi.traverse(shape))
    return hit[1]


def _key(shapes) -> tuple:
    """What the copy depends on: the shapes, meshes' buffers (JIT indices; the buffers
    are held with the copy so their indices are not reused), cylinders' ``to_world``
    (their prisms are baked from it; a cylinder tilted about its centre the other way
    keeps its bounds), others' bounds (Embree's bounds of them: the copy holds the
    shapes themselves, which intersect with their current parameters)."""
    key, held = [], []
    for sh in shapes:
        if sh.is_mesh():
            v, f = sh.vertex_positions_buffer(), sh.faces_buffer()
            held += [v, f]
            key.append((id(sh), v.index, f.index))
        elif is_cylinder(sh):
            # its matrix's JIT variables (held), read through a traversal kept per
            # cylinder: a new traversal and a read-back per cylinder and call made a
            # kept copy of 500 cylinders cost 56 ms a call (about 8 ms this way)
            entries = [type(v)(v) for row in _traversal(sh)["to_world"].matrix
                       for v in row]
            held += entries
            key.append((id(sh), tuple(v.index for v in entries)))
        else:
            b = sh.bbox()
            key.append((id(sh), tuple(b.min), tuple(b.max)))
    return tuple(key), held


def map_scene(scene: mi.Scene, who: str = "the scene's shadow maps") -> mi.Scene:
    """The scene the maps' rays query (see the module doc): ``scene`` itself unless it
    holds cylinders. ``who``: the rays that query it, as a scene kept with Mitsuba's
    cylinders warns (``raytraced``'s shadow rays, :func:`~mi_shadowmap.rays.occlusion`:
    its warning named the maps, which in a scene with instances take the scene's own
    cylinders as prisms, :func:`own_shapes_copy`)."""
    hit = _MEMO.get(id(scene))
    if hit is not None and hit[0] is scene and hit[2] is scene and hit[1] is None:
        return scene                           # no cylinder: decided once per scene
    shapes = list(scene.shapes())
    cylinders = [sh for sh in shapes if is_cylinder(sh)]
    if not cylinders:
        if grouped_cylinders(scene):       # only inside instances: kept, with a warning
            return _keep(scene, None, [], "a copy of the scene with the cylinders as "
                         "meshes cannot hold its instances", who)
        _remember(scene, None, scene, [])
        return scene
    key, held = _key(shapes)
    if hit is not None and hit[0] is scene and hit[1] == key:
        return hit[2]
    if any(sh.class_name() == "Instance" for sh in shapes):
        return _keep(scene, key, held, "a copy of the scene with the cylinders as meshes "
                     "cannot hold its instances", who)
    try:
        copy, stand_ins = _copy(scene, shapes)
    except RuntimeError as exc:      # a shape Mitsuba does not add to a second scene
        return _keep(scene, key, held, f"Mitsuba did not copy the scene: {exc}", who)
    _remember(scene, key, copy, held, stand_ins)
    return copy


def _copy(scene, shapes) -> tuple:
    """A scene of ``shapes`` (none an ``instance``) with every cylinder a prism, and
    ``{id(area-light cylinder): its prism}``. Raises Mitsuba's ``RuntimeError`` for a
    shape it does not add to a second scene."""
    diagonal = scene_diagonal(scene)
    entries, stand_ins = {}, {}
    for k, sh in enumerate(shapes):
        if is_cylinder(sh):
            entries[f"shape_{k}"] = cylinder_prism(sh, segments(cylinder_radius(sh),
                                                                 diagonal))
            if sh.is_emitter():
                stand_ins[id(sh)] = entries[f"shape_{k}"]
        else:
            entries[f"shape_{k}"] = sh
    # Mitsuba's load_dict gives every object it is handed the id of its key: the
    # scene's own shapes came back as 'shape_<k>', so after the first render of a scene
    # with a cylinder mi.traverse(scene) named its parameters 'shape_2.to_world' (not
    # 'lamp.to_world'), and two area lights whose emitters share an id changed their
    # AOVs from vis_<shape id> to vis_shape_<k> at the second render; the ids restored
    ids = [(sh, sh.id()) for sh in entries.values()]
    try:
        return mi.load_dict({"type": "scene", **entries}), stand_ins
    finally:
        for sh, name in ids:
            sh.set_id(name)


# id(scene) -> (scene, key, (copy of its own shapes, stand-ins) or None, held buffers);
# at most _MAX_SCENES (own_shapes_copy)
_OWN: dict = {}


def own_shapes_copy(scene: mi.Scene):
    """For a scene with ``instance``s and cylinders among its own shapes (which
    :func:`map_scene` keeps, as a copy cannot hold the instances): ``(copy,
    stand_ins)``, a scene of its own shapes but the instances, every cylinder a prism
    (as :func:`map_scene`'s copy), and ``{id(area-light cylinder): its prism}``; None for
    any other scene (and where Mitsuba does not copy a shape, with :func:`map_scene`'s
    warning). The maps' rays (:func:`~mi_shadowmap.depth_maps.first_hit`,
    :func:`~mi_shadowmap.depth_maps.second_depth_along`) take a hit in the copy, and in
    the scene the first hit inside an instance before it: the instances come from the
    scene, its own cylinders from their prisms. Before it, such a scene's
    maps read Mitsuba's float32 cylinders, posts too (a random 4 km world with posts
    as cylinders and as instanced boxes, rocks instanced, the sun 8-40 degrees high:
    ``hard`` misclassified 1.91 % of a 128^2 view against ``raytraced``, 0.35 % with the
    cylinders as boxes; ``raytraced`` with another seed 0.74 %). Cylinders inside shape
    groups stay Mitsuba's (warned about)."""
    hit = _OWN.get(id(scene))
    if hit is not None and hit[0] is scene and hit[1] is None:
        return None                         # decided once per scene without both
    shapes = list(scene.shapes())
    own = [sh for sh in shapes if sh.class_name() != "Instance"]
    if len(own) == len(shapes) or not any(is_cylinder(sh) for sh in own):
        _OWN[id(scene)] = (scene, None, None, [])
        _trim(_OWN)
        return None
    key, held = _key(shapes)
    if hit is not None and hit[0] is scene and hit[1] == key:
        return hit[2]
    if grouped_cylinders(scene):
        warnings.warn("shadowmap: the scene's shadow maps keep Mitsuba's float32 cylinder "
                      "intersection for the cylinders inside its shape groups, which "
                      "misses or invents hits on cylinders far thinner than their "
                      "distance from the light (a copy of the scene with the cylinders as "
                      "meshes cannot hold its instances; see mi_shadowmap.map_scene)",
                      RuntimeWarning, stacklevel=3)
    try:
        entry = _copy(scene, own)
    except RuntimeError:
        entry = None
        map_scene(scene)                    # its warning: the scene is kept
    _OWN.pop(id(scene), None)
    _OWN[id(scene)] = (scene, key, entry, held)
    _trim(_OWN)
    return entry


def _trim(memo: dict) -> None:
    while len(memo) > _MAX_SCENES:
        memo.pop(next(iter(memo)))
    _drop_traversals()


def scene_diagonal(scene: mi.Scene) -> float:
    """The diagonal of ``scene.bbox()``, which sizes the prisms (:func:`segments`)."""
    b = scene.bbox()
    return float(dr.norm(mi.ScalarVector3f(b.max) - mi.ScalarVector3f(b.min)))


def stand_in(scene: mi.Scene, shape):
    """The shape that stands for ``shape`` (a light's own shape, or None) in
    :func:`map_scene` of ``scene``: its prism where it is a replaced area-light cylinder,
    else ``shape`` itself. Call after :func:`map_scene`."""
    if shape is None:
        return None
    hit = _MEMO.get(id(scene))
    if hit is None or hit[0] is not scene:
        return shape
    return hit[4].get(id(shape), shape)


def grouped_cylinders(scene: mi.Scene) -> int:
    """How many cylinders ``scene``'s shape groups hold (drawn through ``instance``s;
    :meth:`mi.Scene.shapes` lists the instances, not them)."""
    from .depth_maps import _grouped_shapes      # (depth_maps imports this module)
    return sum(1 for sh in _grouped_shapes(scene, list(scene.shapes())) if is_cylinder(sh))


def _keep(scene, key, held, why: str, who: str = "the scene's shadow maps") -> mi.Scene:
    """Keep ``scene`` for its maps' rays, with a warning (once per scene state) naming
    ``who`` queries it."""
    warnings.warn(f"shadowmap: {who} keep Mitsuba's float32 cylinder "
                  "intersection, which misses or invents hits on cylinders far thinner "
                  f"than their distance from the light ({why}; see "
                  "mi_shadowmap.map_scene)", RuntimeWarning, stacklevel=4)
    _remember(scene, key, scene, held)
    return scene


def _remember(scene, key, copy, held, stand_ins=None) -> None:
    _MEMO.pop(id(scene), None)
    _MEMO[id(scene)] = (scene, key, copy, held, stand_ins or {})
    _trim(_MEMO)


def _drop_traversals() -> None:
    # the kept traversals of cylinders in no remembered scene go with it (they held
    # every cylinder rendered, its BSDF and its textures, up to 4096 cylinders: 16
    # scenes of one post with a 1024^2 texture kept 449 MiB of JIT storage, 225 MiB
    # before the traversals were kept)
    kept = {id(sh) for memo in (_MEMO, _OWN) for entry in memo.values()
            for sh in entry[0].shapes()}
    for k in [k for k in _TRAVERSALS if k not in kept]:
        del _TRAVERSALS[k]


def clear() -> None:
    """Forget every copy (and the scenes they were made for)."""
    _MEMO.clear()
    _OWN.clear()
    _TRAVERSALS.clear()
