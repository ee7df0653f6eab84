"""Per-scene memos under ``params.update()``: a scene edited between two renders of one
integrator renders as a fresh integrator renders the edited scene (bit-identical), and a
still frame after the edit reads nothing again.

The memos keyed by the scene alone went stale: the mark pass's tilt table
(:func:`mi_shadowmap.virtual.marks._shape_tilts`, a mesh's vertex normals bent after its
first mark), the lookups' table of smooth solid faces
(:func:`mi_shadowmap.depth_maps.solid_face_tables`, a mesh's normals smoothed) and a page
store's marks under a ``principled`` BSDF given transmission (its flags change). The other
edits (vertices, ``to_world``, BSDF values, emitters, an environment's bitmap) are checked
the same way."""
from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

import mi_shadowmap
from mi_shadowmap import procedural
from mi_shadowmap.scenes import default_scene
from mi_shadowmap.virtual import marks

from conftest import SCENE_FILES

T = mi.ScalarTransform4f

#: A point light low behind the wall's far side (``n . l`` -0.08 at its centre)
LIGHT = {"type": "point", "position": [-0.5, 0.5, -6],
         "intensity": {"type": "rgb", "value": 10.0}}


def _wall_normals(tilt_deg: float) -> mi.Float:
    """The wall's four vertex normals, tilted ``tilt_deg`` from its face's (+x) towards
    the light (-z)."""
    t = math.radians(tilt_deg)
    return mi.Float(np.tile([math.cos(t), 0.0, -math.sin(t)], 4).astype(np.float32))


def _wall_scene(wall: dict | None = None):
    """A 2-high wall in the ``x = 0`` plane seen from its ``+x`` side (64^2), thin posts
    0.05 behind it on the light's side: ``wall`` (a shape's dict), default a two-triangle
    mesh whose vertex normals are its face's."""
    if wall is None:
        mesh = mi.Mesh("wall", 4, 2, has_vertex_normals=True)
        params = mi.traverse(mesh)
        params["vertex_positions"] = mi.Float(np.array(
            [[0, 0, 4], [0, 0, -4], [0, 2, -4], [0, 2, 4]], np.float32).ravel())
        params["faces"] = mi.UInt32([0, 1, 2, 0, 2, 3])
        params["vertex_normals"] = _wall_normals(0.0)
        params.update()
        wall = mesh
    return mi.load_dict({
        "type": "scene",
        "sensor": {"type": "perspective", "fov": 40,
                   "to_world": T().look_at(origin=[3, 1.2, 4], target=[0, 1, -1],
                                           up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": 64, "height": 64,
                            "rfilter": {"type": "box"}}},
        "floor": {"type": "rectangle", "to_world": T().rotate([1, 0, 0], -90).scale(10)},
        "wall": wall,
        **{f"post{i}": {"type": "cube", "to_world": T().translate([-0.05, 1, -3 + 1.5 * i])
                        .scale([0.02, 1, 0.05])} for i in range(4)},
        "light": LIGHT})


def _integrator(method: str, **props):
    return mi.load_dict({"type": "shadowmap", "method": method, **props})


def _render(scene, integ, spp: int = 4, seed: int = 1) -> np.ndarray:
    return np.asarray(mi.render(scene, integrator=integ, spp=spp, seed=seed))


def _kept_and_fresh(scene, method: str, edit, **props) -> tuple:
    """(before, kept, fresh): ``scene`` rendered by one integrator before and after
    ``edit(params)``, and the edited scene by a fresh integrator after
    ``clear_caches()`` (every memo of the package empty)."""
    mi_shadowmap.clear_caches()
    integ = _integrator(method, **props)
    before = _render(scene, integ)
    edit(mi.traverse(scene))
    kept = _render(scene, integ)
    mi_shadowmap.clear_caches()
    fresh = _render(scene, _integrator(method, **props))
    mi_shadowmap.clear_caches()
    return before, kept, fresh


@pytest.mark.parametrize("method", ["hard", "pcf"])
def test_vertex_normals_bent_after_the_first_mark_are_seen(method, monkeypatch):
    """A smooth wall lit from just behind its plane through vertex normals bent 15
    degrees after its first render: its pixels now read the map, and where the posts'
    shadows are near the biases' reach they keep the biases' level. The tilt table was
    kept per scene (normals as loaded, flat): the mark dropped that level, and ``hard``
    rendered 60 of 4096 pixels differently from a fresh integrator (53 across 1/2;
    ``pcf`` 189). Now bit-identical, and bit-identical to the marks without the rule
    (``_light_behind`` never true): the rule stays exact."""
    def bend(params):
        params["wall.vertex_normals"] = _wall_normals(15.0)
        params.update()

    scene = _wall_scene()
    before, kept, fresh = _kept_and_fresh(scene, method, bend)
    assert not np.array_equal(before, kept)              # the wall is lit now
    np.testing.assert_array_equal(kept, fresh)
    with monkeypatch.context() as m:
        m.setattr(marks, "_light_behind", lambda *a, **k: mi.Bool(False))
        mi_shadowmap.clear_caches()
        np.testing.assert_array_equal(fresh, _render(scene, _integrator(method)))
    mi_shadowmap.clear_caches()


def test_a_principled_wall_given_transmission_is_marked_again():
    """Mitsuba's ``principled`` gains ``GlossyTransmission`` when its ``spec_trans`` is
    set above 0 (``params.update()`` changes its flags; every other BSDF plugin's flags
    are fixed): light from behind then reaches the camera through the wall, and the
    mark pass may no longer drop the biases' level there. A still camera reused its
    marks (a BSDF is no part of the scene state) and the tilt table kept the old flags:
    ``pcf`` rendered 1 pixel unlike a fresh integrator."""
    def transmit(params):
        params["wall.bsdf.spec_trans.value"] = 0.9
        params.update()

    wall = {"type": "rectangle",
            "to_world": T().translate([0, 1, 0]).rotate([0, 1, 0], 90).scale([4, 1, 1]),
            "bsdf": {"type": "principled", "spec_trans": 0.0, "roughness": 0.6}}
    before, kept, fresh = _kept_and_fresh(_wall_scene(wall), "pcf", transmit)
    assert not np.array_equal(before, kept)
    np.testing.assert_array_equal(kept, fresh)


def _ball_scene(normals: bool = True):
    """A flat-shaded icosphere (every face its own vertices, normals its face's, or no
    normals) on a floor, a point light low at its side, the terminator in view."""
    v, f = procedural._icosphere(2)
    vf, ff, flat = procedural._flat(v, f)
    mesh = mi.Mesh("ball", len(vf), len(ff), has_vertex_normals=normals)
    params = mi.traverse(mesh)
    params["vertex_positions"] = mi.Float((vf * 0.8 + [0, 0.8, 0]).astype(np.float32).ravel())
    params["faces"] = mi.UInt32(ff.astype(np.uint32).ravel())
    if normals:
        params["vertex_normals"] = mi.Float(flat.astype(np.float32).ravel())
    params.update()
    scene = mi.load_dict({
        "type": "scene",
        "sensor": {"type": "perspective", "fov": 40,
                   "to_world": T().look_at(origin=[0, 2.0, 4.5], target=[0, 0.6, 0],
                                           up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": 64, "height": 64,
                            "rfilter": {"type": "box"}}},
        "floor": {"type": "rectangle", "to_world": T().rotate([1, 0, 0], -90).scale(4)},
        "ball": mesh,
        "light": {"type": "point", "position": [4, 1.2, 0.5],
                  "intensity": {"type": "rgb", "value": 30.0}}})
    return scene, procedural._normalize(vf)


@pytest.mark.parametrize("method", ["hard", "second_depth"])
def test_a_balls_normals_smoothed_are_seen_by_the_solid_faces_table(method):
    """The lookups' table of smooth solid faces (``depth_maps.solid_face_tables``: a
    face that faces away from the light but whose interpolated normal reaches it is
    shadowed by its own solid) was kept by vertices and faces alone: a flat-shaded ball
    smoothed through ``params.update()`` kept its empty table, and its terminator was
    lit (``hard``: 20 pixels unlike a fresh integrator; misclassified against
    ``raytraced`` 14, fresh 4)."""
    scene, smooth = _ball_scene()

    def smoothen(params):
        params["ball.vertex_normals"] = mi.Float(smooth.astype(np.float32).ravel())
        params.update()

    before, kept, fresh = _kept_and_fresh(scene, method, smoothen)
    assert not np.array_equal(before, kept)
    np.testing.assert_array_equal(kept, fresh)


def test_a_mesh_given_vertex_normals_is_seen_by_the_solid_faces_table():
    """A ball loaded without vertex normals, given smooth ones through ``params.update()``
    (Mitsuba allows it): the candidates of the solid faces' table
    (``depth_maps._solid_candidates``) were kept by the scene's shapes alone, so the ball
    stayed a mesh without normals, no table, and its terminator was lit (``hard``: 20
    pixels unlike a fresh integrator)."""
    scene, smooth = _ball_scene(normals=False)

    def smoothen(params):
        params["ball.vertex_normals"] = mi.Float(smooth.astype(np.float32).ravel())
        params.update()

    before, kept, fresh = _kept_and_fresh(scene, "hard", smoothen)
    assert not np.array_equal(before, kept)
    np.testing.assert_array_equal(kept, fresh)


def test_vertex_normals_removed_render_as_a_fresh_integrator_does():
    """A ``cube``'s vertex normals removed through ``params.update()`` (an empty buffer;
    ``has_vertex_normals()`` is then False): the kept candidates still listed it for its
    normals, and ``solid_face_tables`` indexed the empty buffer (``IndexError`` in the
    render). Now the candidates are found again and the kept integrator renders as a
    fresh one."""
    def remove(params):
        params["box.vertex_normals"] = mi.Float([])
        params.update()

    scene = _edit_scene("point")
    _, kept, fresh = _kept_and_fresh(scene, "hard", remove)
    assert not [sh for sh in scene.shapes() if sh.id() == "box"][0].has_vertex_normals()
    np.testing.assert_array_equal(kept, fresh)


def _glass_ball_scene():
    """A flat-shaded ``principled`` icosphere (opaque: ``spec_trans`` 0, no vertex
    normals) beside a point light, seen from its far side (as
    ``test_second_depth.py``'s glass solid lit from outside)."""
    v, f = procedural._icosphere(2)
    props = mi.Properties()
    props["bsdf"] = mi.load_dict({"type": "principled", "spec_trans": 0.0, "roughness": 0.3})
    mesh = mi.Mesh("ball", len(v), len(f), props)
    params = mi.traverse(mesh)
    params["vertex_positions"] = mi.Float((0.6 * np.asarray(v)).astype(np.float32).ravel())
    params["faces"] = mi.UInt32(np.asarray(f).astype(np.uint32).ravel())
    params.update()
    return mi.load_dict({
        "type": "scene",
        "sensor": {"type": "perspective", "fov": 40,
                   "to_world": T().look_at(origin=[-4, 0.5, 0.9], target=[0, 0, 0.7],
                                           up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": 48, "height": 48,
                            "rfilter": {"type": "box"}}},
        "ball": mesh,
        "floor": {"type": "rectangle",
                  "to_world": T().translate([0, -0.7, 0]).rotate([1, 0, 0], -90).scale(4)},
        "light": {"type": "point", "position": [3, 1, 0],
                  "intensity": {"type": "rgb", "value": 20.0}}})


def test_a_principled_ball_given_transmission_is_a_glass_solid():
    """A ``principled`` ball given ``spec_trans`` 0.9 through ``params.update()``
    transmits: its far side, seen by the camera, is shaded by light from behind its
    faces, which its near side shadows (``raytraced``). The solid faces' candidates were
    kept by the scene's shapes alone (the ball opaque and without normals: no table),
    and ``second_depth``, which finds the far side as the light's second surface, lit it:
    312 of 2304 pixels unlike a fresh integrator, 283 misclassified against
    ``raytraced`` (a fresh integrator 1)."""
    def transmit(params):
        params["ball.bsdf.spec_trans.value"] = 0.9
        params.update()

    scene = _glass_ball_scene()
    _, kept, fresh = _kept_and_fresh(scene, "second_depth", transmit)
    np.testing.assert_array_equal(kept, fresh)
    ref = _render(scene, _integrator("raytraced"))
    mi_shadowmap.clear_caches()
    # the visibility AOV (the last channel): the far side is dark, as in raytraced
    assert np.sum((ref[..., -1] >= 0.5) != (kept[..., -1] >= 0.5)) <= 4


def _scale(value, k: float):
    return type(value)(value) * k


#: Edits through ``params.update()`` that no memo may miss: ``(scene, parameter, new
#: value from the old one)``; the scene ``"sky_sun"`` is ``scenes_xml/sky_sun.xml``, the
#: others ``default_scene``'s light.
EDITS = {
    "mesh_vertices": ("spot", "box.vertex_positions", lambda v: _scale(v, 1.3)),
    "mesh_normals": ("spot", "box.vertex_normals", lambda v: _scale(v, -1.0)),
    "shape_to_world": ("spot", "sphere.to_world",
                       lambda v: mi.Transform4f().translate([0.4, 0.0, 0.3]) @ v),
    "bsdf_value": ("spot", "ground.bsdf.reflectance.value",
                   lambda v: mi.Color3f(0.1, 0.8, 0.2)),
    "spot_to_world": ("spot", "spot.to_world",
                      lambda v: mi.Transform4f().translate([0.5, 0.0, 0.4]) @ v),
    "spot_cutoff": ("spot", "spot.cutoff_angle", lambda v: 24.0),
    "spot_intensity": ("spot", "spot.intensity.value", lambda v: _scale(v, 0.5)),
    "point_position": ("point", "point.position", lambda v: mi.Point3f(-2.0, 3.0, -1.0)),
    "point_intensity": ("point", "point.intensity.value", lambda v: _scale(v, 2.0)),
    "sun_direction": ("directional", "sun.to_world",
                      lambda v: mi.Transform4f().rotate([0, 1, 0], 40.0) @ v),
    "sun_irradiance": ("directional", "sun.irradiance.value", lambda v: _scale(v, 0.5)),
    "area_to_world": ("area", "area.to_world",
                      lambda v: mi.Transform4f().translate([0.6, 0.0, 0.3]) @ v),
    "area_radiance": ("area", "area.emitter.radiance.value", lambda v: _scale(v, 0.5)),
    "sky_bitmap": ("sky_sun", "sky.data",
                   lambda v: mi.TensorXf(np.roll(np.array(v), 40, axis=1))),
    "sky_scale": ("sky_sun", "sky.scale", lambda v: _scale(v, 0.5)),
    "sky_to_world": ("sky_sun", "sky.to_world",
                     lambda v: mi.Transform4f().rotate([0, 1, 0], 60.0) @ v),
}


def _edit_scene(name: str):
    if name == "sky_sun":
        path = [p for p in SCENE_FILES if p.stem == "sky_sun"][0]
        return mi.load_file(str(path), width=32, height=32)
    return mi.load_dict(default_scene(width=32, height=32, light=name))


@pytest.mark.parametrize("edit", list(EDITS))
def test_an_edited_scene_renders_as_a_fresh_integrator_renders_it(edit):
    """Every kind of ``params.update()`` edit (geometry, ``to_world``, a BSDF's value,
    an emitter's pose, angles and radiance, an environment's bitmap, scale and
    rotation), the default virtual maps: one integrator's render after the edit equals
    a fresh integrator's (every memo empty) bit for bit, and differs from the render
    before it (the edit is seen)."""
    scene_name, key, new = EDITS[edit]

    def apply(params):
        params[key] = new(params[key])
        params.update()

    before, kept, fresh = _kept_and_fresh(_edit_scene(scene_name), "hard", apply)
    assert not np.array_equal(before, kept), f"{edit}: the edit is not visible"
    if edit == "sky_to_world":
        # the median cut is kept in the emitter's frame and rotated with it
        # (environment.emitter_regions); a fresh cut of the rotated sky evaluates its
        # texels through the rotation: directions 9e-8, region weights 6e-7 apart, the
        # image 8e-6 (relative), visibility 1e-6
        np.testing.assert_allclose(kept, fresh, rtol=1e-5, atol=1e-6)
        return
    np.testing.assert_array_equal(kept, fresh)


def _launched(scene, integ, seed: int) -> list:
    """The JIT kernels one render of ``scene`` launches: ``(hash, compiled)`` each."""
    dr.kernel_history()
    had = dr.flag(dr.JitFlag.KernelHistory)
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        dr.eval(mi.render(scene, integrator=integ, spp=4, seed=seed))
        dr.sync_thread()
        return [(k["hash"], not k.get("cache_hit", 1)) for k in dr.kernel_history()
                if k["type"] == dr.KernelType.JIT]
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, had)


def test_the_tilt_table_is_read_again_only_after_an_edit(monkeypatch):
    """A still frame reads no shape's tilt and launches the kernels a still frame
    launched before (none compiled); a moved camera's mark pass compares the shapes'
    buffers and flags and reads no tilt either; after the wall's normals are bent, only
    the wall's tilt is read again, once, and the next still frame launches the kernels
    of a still frame before the edit."""
    read = []
    real = marks._tilt_of
    monkeypatch.setattr(marks, "_tilt_of", lambda sh, *a: read.append(sh.id()) or real(sh, *a))
    mi_shadowmap.clear_caches()
    scene = _wall_scene()
    integ = _integrator("hard")
    _launched(scene, integ, 1)
    assert sorted(read) == sorted(sh.id() for sh in scene.shapes())
    read.clear()
    params = mi.traverse(scene)
    params["sensor.to_world"] = mi.ScalarTransform4f().look_at(
        origin=[3.2, 1.3, 4.1], target=[0, 1, -1], up=[0, 1, 0])
    params.update()
    _launched(scene, integ, 2)                  # the mark pass runs: no tilt read
    assert read == []
    still = _launched(scene, integ, 3)
    assert read == [] and not any(compiled for _, compiled in still)
    params["wall.vertex_normals"] = _wall_normals(15.0)
    params.update()
    _launched(scene, integ, 4)
    assert read == ["wall"]
    read.clear()
    after = _launched(scene, integ, 5)
    assert read == [] and after == still
    mi_shadowmap.clear_caches()
