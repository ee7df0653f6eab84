"""Built-in scenes (:mod:`mi_shadowmap.scenes`): the random scenes of issue 11's two
kinds, and issue 11's targets on them at defaults.

The repository's ``large_world.xml`` and ``far_point.xml`` are one scene of each
kind; :func:`~mi_shadowmap.scenes.random_large_world` and
:func:`~mi_shadowmap.scenes.random_far_point` draw others (camera, light, objects),
so the targets are checked on layouts nobody tuned for. Measured with
``benchmarks/bench_unseen.py`` on seeds 0-9 (2026-12-02): large worlds at 128^2,
16 spp, `hard` / `pcf` misclassify at most 0.85 % / 0.87 % (median 0.35 / 0.37 %);
the far point light at 256^2 at most 0.12 % / 0.13 % at 1e5 and 0.11 / 0.12 % at
1e6 (at 128^2 at most 0.25 %; before the normal offset was scaled by cos(theta), one
case of 40 was over 0.3 % there: `pcf`, seed 3 at 1e5, 0.31 %). The tests
take the first seeds (for time, not chosen). They can fail: with full maps
(``virtual=false``) the first two worlds misclassify 0.8 % and 2.0 %, the first two far
point scenes 1.0 % and 2.4 %.
"""
from __future__ import annotations

import mitsuba as mi
import numpy as np
import pytest

from mi_shadowmap.light_views import emitter_kind
from mi_shadowmap.metrics import misclassified
from mi_shadowmap.scenes import random_far_point, random_large_world, random_terrain_world


def visibility(scene_dict, **props):
    integ = mi.load_dict({"type": "shadowmap", **props})
    img = np.asarray(mi.render(mi.load_dict(scene_dict), integrator=integ, seed=0))
    assert np.isfinite(img).all()
    return img[..., 3]


def test_random_scenes_are_reproducible_and_differ_by_seed():
    a, b = random_large_world(3, width=32), random_large_world(3, width=32)
    assert str(a) == str(b)
    assert str(random_large_world(4, width=32)) != str(a)
    p = random_far_point(3, distance=1e5, width=32)
    q = random_far_point(3, distance=1e6, width=32)
    assert p["light"]["position"] != q["light"]["position"]
    # the same layout at every distance: only the light differs
    assert str({k: v for k, v in p.items() if k != "light"}) == \
        str({k: v for k, v in q.items() if k != "light"})
    shapes = [k for k, v in a.items() if isinstance(v, dict) and v["type"] in
              ("rectangle", "cube", "sphere", "cylinder")]
    assert len(shapes) == 1 + 4 + 6 + 5
    scene = mi.load_dict(random_large_world(0, width=16, spp=1))
    assert [emitter_kind(e) for e in scene.emitters()] == ["directional"]


def test_random_terrain_worlds_are_reproducible_and_vary():
    """``random_terrain_world``: the same seed the same scene (its terrain mesh's
    vertices too); over seeds 0-11 every sun (2-5, 8-40, 80-89.5 degrees high) and every
    view (eye height, a hill, a tower), and scenes with and without instances; each
    loads with one directional light, its camera above the terrain."""
    def vertices(d):
        return np.asarray(mi.traverse(d["ground"])["vertex_positions"])
    a, b = random_terrain_world(3, width=32), random_terrain_world(3, width=32)
    assert str(a) == str(b)      # (meshes print their bounds, not their vertices)
    assert np.array_equal(vertices(a), vertices(b))
    assert not np.array_equal(vertices(a), vertices(random_terrain_world(4, width=32)))
    elevations, towers, instanced = set(), 0, 0
    for seed in range(12):
        d = random_terrain_world(seed, width=16, spp=1)
        sin_e = -d["sun"]["direction"][1] / np.linalg.norm(d["sun"]["direction"])
        elevations.add(int(np.searchsorted([6.5, 60.0], np.degrees(np.arcsin(sin_e)))))
        towers += "tower" in d
        instanced += any(isinstance(v, dict) and v["type"] == "instance" for v in d.values())
        scene = mi.load_dict(d)
        assert [emitter_kind(e) for e in scene.emitters()] == ["directional"]
        origin = np.array(scene.sensors()[0].world_transform().translation())
        ray = mi.Ray3f(mi.Point3f(*origin), mi.Vector3f(0, -1, 0))
        assert scene.ray_intersect(ray).is_valid()[0]     # the ground is below the camera
    assert elevations == {0, 1, 2} and 0 < towers < 12 and 0 < instanced < 12


@pytest.mark.parametrize("distance", [0, -1.0, float("inf"), float("nan"), "1e5"])
def test_random_far_point_refuses_a_bad_distance(distance):
    with pytest.raises(ValueError, match="distance must be a finite number > 0"):
        random_far_point(0, distance=distance)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_random_large_worlds_meet_the_target_at_defaults(seed):
    """Issue 11: `hard` and `pcf` at defaults misclassify <= 1 % on a large world
    (128^2, 16 spp, against `raytraced` with the same camera samples)."""
    _meets_one_percent(random_large_world(seed, width=128, spp=16), f"large world {seed}")


def _meets_one_percent(d: dict, label: str) -> None:
    """`hard` and `pcf` at defaults misclassify <= 1 % of scene ``d`` against
    `raytraced` with the same camera samples."""
    ref = visibility(d, method="raytraced")
    for method in ("hard", "pcf"):
        mis = misclassified(ref, visibility(d, method=method))["misclassified"]
        print(f"{label} {method}: {mis:.3%}")
        assert mis <= 0.01, (label, method, mis)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_random_terrain_worlds_meet_the_target_at_defaults(seed):
    """Issue 11's 1 % on ``random_terrain_world`` (128^2, 16 spp; the first seeds: eye
    height under the sun 2-5, 8-40 and 80-89.5 degrees high; measured at most 0.14 / 0.50
    %, `hard` / `pcf`). It can fail: full maps (``virtual=false``, 4096^2) misclassify
    1.56 / 1.39 % of seed 1's view; without the biases (``slope_bias=0,
    normal_bias=0``) `hard` / `pcf` 24 / 2.3 % of seed 1's, 28 / 4.1 % of seed 2's."""
    _meets_one_percent(random_terrain_world(seed, width=128, spp=16), f"terrain world {seed}")


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("distance", [1e5, 1e6])
def test_random_far_point_lights_meet_the_target_at_defaults(seed, distance):
    """Issue 11: `hard` and `pcf` at defaults misclassify <= 0.3 % under a point light
    1e5 and 1e6 away (256^2, 16 spp; the texel target's film)."""
    d = random_far_point(seed, distance=distance, width=256, spp=16)
    ref = visibility(d, method="raytraced")
    for method in ("hard", "pcf"):
        mis = misclassified(ref, visibility(d, method=method))["misclassified"]
        print(f"far point {distance:g} {seed} {method}: {mis:.3%}")
        assert mis <= 0.003, (seed, distance, method, mis)


INCLUDING_XML = """<scene version="3.0.0">
    <default name="width" value="32"/>
    <default name="height" value="32"/>
    <include filename="parts/sensor.xml"/>
    <shape type="sphere"/>
    <emitter type="point"><point name="position" value="2, 4, 2"/></emitter>
</scene>"""


def _scene_with_included_sensor(tmp_path):
    """A scene whose sensor (with $width, $height) is in a file that an included file
    includes, relative to its own folder, as Mitsuba resolves it."""
    (tmp_path / "parts").mkdir()
    (tmp_path / "parts" / "sensor.xml").write_text(
        '<scene version="3.0.0"><include filename="film.xml"/></scene>')
    (tmp_path / "parts" / "film.xml").write_text(
        '<scene version="3.0.0"><sensor type="perspective"><film type="hdrfilm">'
        '<integer name="width" value="$width"/><integer name="height" value="$height"/>'
        '</film></sensor></scene>')
    main = tmp_path / "main.xml"
    main.write_text(INCLUDING_XML)
    return main


def test_load_scene_sets_parameters_of_included_files(tmp_path):
    """load_scene looked for "$width" in the main file's text only: a sensor in an
    included file gave "scene file ... has no parameter $width, $height"."""
    from mi_shadowmap.scenes import load_scene
    scene = load_scene(_scene_with_included_sensor(tmp_path), width=40, height=24)
    assert list(scene.sensors()[0].film().size()) == [40, 24]
    # a parameter that no file uses is still an error, naming only it
    with pytest.raises(ValueError, match=r"has no parameter \$spp \(neither it nor the "
                                         r"files it includes"):
        load_scene(tmp_path / "main.xml", width=40, spp=4)


def test_readme_scene_table_lists_every_scene_file():
    """Every ``scenes_xml/*.xml`` has a row in the README's scene table, and every row
    names a file there (``spectral_point.xml`` had none)."""
    import pathlib
    import re
    root = pathlib.Path(__file__).resolve().parents[1]
    readme = (root / "README.md").read_text()
    table = readme.split("| scene | lights | what it exercises |", 1)[1].split("\n\n", 1)[0]
    rows = set(re.findall(r"^\| `([\w.]+\.xml)` \|", table, re.M))
    files = {p.name for p in (root / "scenes_xml").glob("*.xml")}
    assert rows == files, (f"README lacks {sorted(files - rows)}; "
                           f"lists missing files {sorted(rows - files)}")


@pytest.mark.parametrize("form", ["xml", "dict"])
def test_load_scene_with_an_exr_texture_under_one_drjit_thread(form):
    """Mitsuba 3.9.1 waits forever reading an EXR after ``dr.set_thread_count(1)`` (a
    setting users debug with): ``load_scene`` of ``sky_sun.xml`` (an ``envmap`` from an
    EXR) never returned. It now loads with two threads and gives the user's one back,
    and the render runs. In a subprocess: a hang must not hang the suite."""
    import pathlib
    import subprocess
    import sys
    root = pathlib.Path(__file__).resolve().parents[1]
    exr = root / "scenes_xml" / "textures" / "sky_sun.exr"
    scene = (repr(str(root / "scenes_xml" / "sky_sun.xml")) + ", width=16, height=16"
             if form == "xml" else
             "{'type': 'scene', 'sky': {'type': 'envmap', 'filename': %r}}" % str(exr))
    code = (
        "import mi_shadowmap, drjit as dr, mitsuba as mi\n"
        "from mi_shadowmap.scenes import load_scene\n"
        "dr.set_thread_count(1)\n"
        f"scene = load_scene({scene})\n"
        "assert dr.thread_count() == 1, dr.thread_count()\n"
        "if scene.sensors():\n"
        "    img = mi.render(scene, spp=1)\n"
        "    assert dr.all(dr.isfinite(img), axis=None)\n"
        "print('loaded', len(scene.emitters()))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=240, cwd=root)
    assert out.returncode == 0, out.stderr[-2000:]
    assert "loaded 1" in out.stdout
