"""Built-in scenes, as Mitsuba dictionaries (no files needed).

:func:`default_scene` is the scene of the README's main command: a sphere
and a box on a ground plane under a spot light (the same layout as
``scenes_xml/spot_sphere_box.xml``). Every builder takes a uniform ``scale``
applied to geometry, lights and camera together (light intensities are
scaled by ``scale**2`` so the image stays the same), which the scale
invariance tests use. :func:`load_scene` turns any scene argument of the
harness (a loaded scene, a dict, an XML path with ``$`` parameters) into an
``mi.Scene``.
"""
from __future__ import annotations

import os

import drjit as dr
import mitsuba as mi

T = mi.ScalarTransform4f


def camera(origin, target, width, height, spp, fov=40.0, scale=1.0) -> dict:
    """A perspective camera dict (box filter, independent sampler) looking from
    ``origin`` at ``target``, both multiplied by ``scale`` (clip planes too)."""
    return {
        "type": "perspective",
        "fov": fov,
        "near_clip": 1e-2 * scale,
        "far_clip": 1e4 * scale,
        "to_world": T().look_at(origin=[scale * c for c in origin],
                                target=[scale * c for c in target], up=[0, 1, 0]),
        "sampler": {"type": "independent", "sample_count": spp},
        "film": {"type": "hdrfilm", "width": width, "height": height,
                 "rfilter": {"type": "box"}},
    }


def load_scene(scene, **xml_params) -> mi.Scene:
    """An ``mi.Scene`` from a loaded scene, a scene dict, or an XML path.

    ``xml_params`` fill the file's ``$name`` parameters (e.g. ``width=64``);
    a parameter the file does not declare is an error naming it.
    """
    if isinstance(scene, mi.Scene):
        if xml_params:
            raise ValueError("scene parameters (" + ", ".join(xml_params)
                             + ") apply to XML files only, not to a loaded scene")
        return scene
    if isinstance(scene, dict):
        return mi.load_dict(scene)
    path = os.fspath(scene)
    if not os.path.isfile(path):
        raise FileNotFoundError(f"scene file not found: {path}")
    with open(path, encoding="utf-8", errors="replace") as f:
        text = f.read()
    missing = [k for k in xml_params if f"${k}" not in text]
    if missing:
        raise ValueError(f"scene file {path} has no parameter "
                         + ", ".join(f"${k}" for k in missing)
                         + " (declare <default name=... value=.../> to make it settable)")
    return mi.load_file(path, **{k: str(v) for k, v in xml_params.items()})


def mesh(name: str, vertices, faces, to_world=None, bsdf: dict | None = None) -> mi.Mesh:
    """A ``mi.Mesh`` from numpy ``vertices`` ``(V, 3)`` and ``faces`` ``(F, 3)``
    (e.g. :func:`mi_shadowmap.procedural.box`), placed by ``to_world`` (a
    ``mi.ScalarTransform4f``); usable as a value of a ``mi.load_dict`` scene,
    and its ``vertex_positions`` can be optimised (``mi.traverse``)."""
    import numpy as np
    v = np.asarray(vertices, dtype=np.float64)
    if to_world is not None:
        m = np.array(to_world.matrix, dtype=np.float64)
        v = v @ m[:3, :3].T + m[:3, 3]
    f = np.asarray(faces, dtype=np.uint32)
    out = mi.Mesh(name, vertex_count=len(v), face_count=len(f), has_vertex_normals=False)
    params = mi.traverse(out)
    params["vertex_positions"] = dr.ravel(mi.Point3f(v.T.astype(np.float32)))
    params["faces"] = dr.ravel(mi.Vector3u(f.T))
    params.update()
    if bsdf is not None:
        out.set_bsdf(mi.load_dict(bsdf))
    return out


def _diffuse(r, g, b):
    return {"type": "diffuse", "reflectance": {"type": "rgb", "value": [r, g, b]}}


def default_scene(scale: float = 1.0, width: int = 128, height: int = 128, spp: int = 16,
                  light: str = "spot") -> dict:
    """Sphere and box on a ground plane, lit by one ``light``.

    ``light`` is 'spot' (default), 'point', 'directional' or 'area' (a
    0.6-unit square area light).
    """
    S = T().scale(scale)
    scene = {
        "type": "scene",
        "sensor": camera([0.2, 3.5, 4.9], [0.25, 0.25, 0.0], width, height, spp, scale=scale),
        "ground": {"type": "rectangle", "to_world": S @ T().rotate([1, 0, 0], -90).scale(4),
                   "bsdf": _diffuse(0.7, 0.7, 0.7)},
        "sphere": {"type": "sphere",
                   "to_world": S @ T().translate([-0.85, 0.65, -0.6]).scale(0.65),
                   "bsdf": _diffuse(0.75, 0.25, 0.2)},
        "box": {"type": "cube",
                "to_world": S @ T().translate([0.85, 0.5, -0.5]).rotate([0, 1, 0], 30).scale(0.5),
                "bsdf": _diffuse(0.2, 0.4, 0.75)},
    }
    origin, target = [-2.4, 4.0, -3.4], [0.2, 0.0, 0.3]
    if light == "spot":
        scene["spot"] = {"type": "spot", "to_world": S @ T().look_at(origin=origin, target=target,
                                                                    up=[0, 1, 0]),
                         "intensity": {"type": "rgb", "value": 120.0 * scale**2},
                         "cutoff_angle": 35.0, "beam_width": 28.0}
    elif light == "point":
        scene["point"] = {"type": "point", "position": [scale * c for c in origin],
                          "intensity": {"type": "rgb", "value": 60.0 * scale**2}}
    elif light == "directional":
        scene["sun"] = {"type": "directional",
                        "direction": [t - o for t, o in zip(target, origin)],
                        "irradiance": {"type": "rgb", "value": 3.0}}
    elif light == "area":
        scene["area"] = {"type": "rectangle",
                         "to_world": S @ T().look_at(origin=origin, target=target,
                                                     up=[0, 1, 0]).scale(0.3),
                         "emitter": {"type": "area",
                                     "radiance": {"type": "rgb", "value": 40.0}}}
    else:
        raise ValueError(f"default_scene: light={light!r}; valid: spot, point, directional, area")
    return scene
