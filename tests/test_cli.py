"""The ``mi-shadowmap`` command line: outputs on tiny scenes, one-line errors."""
import csv
import json
import os
import subprocess
import sys

import numpy as np
import pytest

import mi_shadowmap
from mi_shadowmap import cli, harness, methods, options
from mi_shadowmap.report import read_exr, read_exr_header

from conftest import SCENES

TINY = ["--width", "32", "--height", "32", "--spp", "2", "--set", "resolution=128"]


def run(argv, capsys):
    code = cli.main([str(a) for a in argv])
    out, err = capsys.readouterr()
    return code, out, err


def test_compare_default_scene(tmp_path, capsys):
    out_dir = tmp_path / "out"
    code, out, err = run(["compare", *TINY, "--out", out_dir], capsys)
    assert code == 0, err
    methods = harness.default_methods()
    rows = json.loads((out_dir / "metrics.json").read_text())
    assert [r["method"] for r in rows] == ["raytraced"] + methods
    assert rows[0]["reference"] and rows[0]["vis_rmse"] == 0
    with open(out_dir / "metrics.csv") as f:
        assert len(list(csv.DictReader(f))) == len(rows)
    for name in ("contact_sheet.png", "pareto.png"):
        assert (out_dir / name).stat().st_size > 0
    assert "vis RMSE" in out and "hard" in out        # the printed table
    # per-method EXR: image, visibility AOV and error maps that match the JSON metrics
    ref = read_exr(str(out_dir / (harness.safe_name(rows[0]["name"]) + ".exr")))
    for row in rows:
        ch = read_exr(str(out_dir / (harness.safe_name(row["name"]) + ".exr")))
        assert {"R", "G", "B", "vis_spot.Y", "err_spot.Y", "img_err.R"} <= set(ch)
        assert ch["vis_spot.Y"].shape == (32, 32)
        np.testing.assert_allclose(ch["err_spot.Y"], ch["vis_spot.Y"] - ref["vis_spot.Y"],
                                   atol=1e-6)
        assert np.sqrt(np.mean(ch["err_spot.Y"] ** 2)) == pytest.approx(row["vis_rmse"],
                                                                        abs=1e-5)
        assert (out_dir / (harness.safe_name(row["name"]) + ".png")).exists()


def test_no_command_runs_compare_on_xml(tmp_path, capsys):
    code, out, err = run([SCENES / "room_two_points.xml", *TINY, "--methods", "hard",
                          "--out", tmp_path], capsys)
    assert code == 0, err
    rows = json.loads((tmp_path / "metrics.json").read_text())
    assert [r["method"] for r in rows] == ["raytraced", "hard"]
    assert {"vis_rmse[key]", "vis_rmse[fill]"} <= set(rows[1])


@pytest.mark.parametrize("argv, match", [
    (["compare", "/no/such/scene.xml"], "not found"),
    (["compare", "--methods", "nope"], "nope"),
    (["compare", "--set", "resolutoin=64"], "resolutoin"),
    (["compare", "--set", "resolution=-3"], "resolution"),
    (["compare", "--set", "resolution"], "name=value"),
    (["sweep", "--grid", "method=hard resolutoin=64"], "resolutoin"),
    (["sweep", "--grid", "{bad json"], "JSON"),
    (["sweep", "--grid", "missing.json"], "not found"),
    (["maps", "--methods", "nope"], "nope"),
    (["maps", "--methods", "raytraced"], "no depth map"),
    # a scene file brings its own lights (--light was ignored)
    (["compare", str(SCENES / "far_point.xml"), "--light", "area"], "--light area"),
    (["compare", "--plugin", "/no/such/plugin.py"], "plugin file not found"),
    (["--plugin", "/no/such/plugin.py", "sweep"], "/no/such/plugin.py"),
    (["maps", "--plugin"], "--plugin"),
    (["sweep", "--grid", "method=hard", "--set", "shadow_rays=4"], "shadow_rays"),
    (["sweep", "--grid", "[1, 2]"], "dict"),
    (["sweep", "--error", "img_psnr"], "img_psnr"),        # higher-is-better: not a choice
    (["compare", "--spp", "many"], "spp"),               # argparse error, one line too
    # rendered at the sampler's count / failed in Mitsuba / accepted, before:
    # (named as the harness's parameters, 'ref_spp', before: the option as typed now)
    (["compare", "--spp", "0"], "argument --spp: must be an integer >= 1, got '0'"),
    (["compare", "--seed", "-1"], "argument --seed: must be an integer in [0, 2^32)"),
    (["compare", "--seed", str(2 ** 32)], "argument --seed: must be an integer in [0, 2^32)"),
    (["compare", "--repeats", "0"], "argument --repeats: must be an integer >= 1"),
    (["compare", "--ref-spp", "-2"], "argument --ref-spp: must be an integer >= 1"),
    (["compare", "--ref-shadow-rays", "0"], "argument --ref-shadow-rays: must be an integer >= 1"),
    (["sweep", "--spp", "0"], "argument --spp: must be an integer >= 1"),
    (["tune", "--max-error", "0"], "argument --max-error: must be a number > 0, got '0'"),
    (["tune", "--max-error", "nan"], "argument --max-error: must be a number > 0"),
    (["tune", "--max-error", "0.02", "--max-spp", "0"],
     "argument --max-spp: must be an integer >= 1"),
    (["tune", "--max-error", "0.02", "--search-size", "4"],
     "argument --search-size: must be an integer >= 8"),
    (["tune", "--max-error", "0.02", "--margin", "1"],
     "argument --margin: must be a number in [0, 1)"),
    (["tune", "--max-error", "0.02", "--time-limit", "0"],
     "argument --time-limit: must be a number > 0"),
    # duplicates overwrote each other's files / the last one won, before:
    (["compare", "--methods", "hard", "pcf:num_samples=4", "pcf: num_samples = 4"],
     "'pcf num_samples=4' is listed more than once"),
    (["compare", "--methods", "pcf:num_samples=4,num_samples=8"], "given twice"),
    (["sweep", "--grid", "method=hard resolution=256 resolution=512"], "given twice"),
    # failed with "got multiple values for keyword argument 'spp'" / after rendering
    # everything (SSIM) / after making the output folder, before:
    (["compare", "--set", "spp=4"], "--set spp=4: compare's samples per pixel are --spp"),
    (["compare", "--width", "6", "--height", "6"], "the film is 6 x 6 pixels"),
    (["sweep", "--width", "8", "--height", "5"], "the film is 8 x 5 pixels"),
    (["tune", "--max-error", "0.02", "--repeats", "0"],
     "argument --repeats: must be an integer >= 1"),
    (["tune", "--max-error", "0.02", "--seed", "-1"],
     "argument --seed: must be an integer in [0, 2^32)"),
    # --set method=... was ignored without a word (every method rendered, or the grid's)
    (["compare", "--set", "method=pcf"], "'method' = 'pcf' is not a shared property"),
    (["sweep", "--grid", "method=hard", "--set", "method=pcf"], "--methods"),
    (["maps", "--set", "method=pcf"], "'method' = 'pcf' is not a shared property"),
    (["tune", "--max-error", "0.02", "--set", "method=pcf"], "not a shared property"),
])
def test_bad_input_one_line_error(argv, match, tmp_path, capsys):
    out_dir = tmp_path / "never"
    code, out, err = run(argv + ["--out", out_dir], capsys)
    assert code == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1 and match in lines[0] and "Traceback" not in err
    assert lines[0].startswith("mi-shadowmap")
    assert not out_dir.exists()     # rejected before anything was rendered or written


def test_unwritable_out_dir(tmp_path, capsys):
    blocker = tmp_path / "file.txt"
    blocker.write_text("not a folder")
    code, out, err = run(["compare", *TINY, "--out", blocker / "sub"], capsys)
    assert code == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "output folder" in lines[0]


def test_out_dir_that_is_a_file_is_named_so(tmp_path, capsys):
    """``--out`` naming an existing file said "output folder is not writable" (of a
    writable file); the report writers too."""
    from mi_shadowmap import report
    blocker = tmp_path / "file.txt"
    blocker.write_text("not a folder")
    code, out, err = run(["compare", *TINY, "--out", blocker], capsys)
    assert code == 2 and "is a file, not a folder" in err
    with pytest.raises(PermissionError, match="is a file, not a folder"):
        report.check_out_dir(str(blocker))


def test_out_dir_probe_catches_what_os_access_lets_through(monkeypatch, tmp_path):
    from mi_shadowmap import report
    """As root ``os.access`` says yes to ``/proc``; the probe (a folder made and removed
    in the nearest existing parent, a file in an existing folder) says no. Simulated
    without root: ``os.access`` always true, and the probe's ``mkdtemp`` / ``mkstemp``
    failing where they would."""
    import tempfile
    monkeypatch.setattr(os, "access", lambda *a, **k: True)
    if os.path.isdir("/proc/self"):
        with pytest.raises(PermissionError, match="cannot create output folder /proc/x"):
            report.check_out_dir("/proc/x", create=False)
    locked = tmp_path / "locked"
    locked.mkdir()

    def refuse(*args, dir=None, **kwargs):
        if dir is not None and os.path.abspath(dir) == str(locked):
            raise PermissionError(13, "Permission denied")
        return real[kind](*args, dir=dir, **kwargs)
    real = {"d": tempfile.mkdtemp, "s": tempfile.mkstemp}
    kind = "d"
    monkeypatch.setattr(tempfile, "mkdtemp", refuse)
    with pytest.raises(PermissionError, match="no folder can be made in .*Permission denied"):
        report.check_out_dir(str(locked / "a" / "b"), create=False)
    assert os.listdir(locked) == []
    kind = "s"
    monkeypatch.setattr(tempfile, "mkdtemp", real["d"])
    monkeypatch.setattr(tempfile, "mkstemp", refuse)
    with pytest.raises(PermissionError, match="output folder is not writable"):
        report.check_out_dir(str(locked), create=False)
    with pytest.raises(PermissionError, match="output folder is not writable"):
        report.check_out_dir(str(locked))
    monkeypatch.setattr(tempfile, "mkstemp", real["s"])
    # a writable folder: the probes leave nothing behind
    assert report.check_out_dir(str(locked), create=False) == str(locked)
    assert report.check_out_dir(str(locked / "new"), create=False) == str(locked / "new")
    assert os.listdir(locked) == []


def test_cli_out_dir_fails_before_rendering(monkeypatch, tmp_path, capsys):
    """``--out`` where no folder can be made: one line, status 2, nothing rendered."""
    import tempfile
    monkeypatch.setattr(os, "access", lambda *a, **k: True)

    def refuse(*args, **kwargs):
        raise PermissionError(13, "Permission denied")
    monkeypatch.setattr(tempfile, "mkdtemp", refuse)

    err = _refused_before_rendering(monkeypatch, capsys, tmp_path / "out")
    assert "cannot create output folder" in err and "Permission denied" in err



def _refused_before_rendering(monkeypatch, capsys, out) -> str:
    """``compare`` with ``--out out``: status 2 and one line of error (returned), with
    ``harness.compare`` failing the test if it is reached (nothing renders)."""
    def no_compare(*args, **kwargs):
        raise AssertionError("rendered")
    monkeypatch.setattr(harness, "compare", no_compare)
    code, _, err = run(["compare", *TINY, "--methods", "hard", "--out", out], capsys)
    assert code == 2 and len(err.strip().splitlines()) == 1
    return err

def test_out_dir_through_a_broken_symlink_fails_before_rendering(monkeypatch, tmp_path,
                                                                 capsys):
    """``--out`` that is (or passes through) a symlink to nothing: ``os.path.exists`` says
    no, so the check probed the link's folder, said yes, and the comparison rendered in
    full before ``os.makedirs`` failed ("File exists", "No such file or directory"), as
    ``mkdir -p`` does. Refused before rendering, naming the link; a link to a folder
    still works."""
    from mi_shadowmap import report
    dangling = tmp_path / "dangling"
    dangling.symlink_to(tmp_path / "missing")
    for out in (dangling, dangling / "sub"):
        with pytest.raises(PermissionError, match="broken symbolic link"):
            report.check_out_dir(str(out), create=False)
        with pytest.raises(PermissionError, match="cannot create output folder"):
            report.check_out_dir(str(out))

    err = _refused_before_rendering(monkeypatch, capsys, dangling / "sub")
    assert "broken symbolic link" in err and str(dangling) in err
    assert sorted(os.listdir(tmp_path)) == ["dangling"]
    # a link to a folder, and a new folder below it
    (tmp_path / "real").mkdir()
    (tmp_path / "link").symlink_to(tmp_path / "real")
    assert report.check_out_dir(str(tmp_path / "link"), create=False)
    assert report.check_out_dir(str(tmp_path / "link" / "a" / "b"), create=False)
    assert os.listdir(tmp_path / "real") == []


def test_debug_shows_traceback(capsys):
    with pytest.raises(Exception, match="nope"):
        cli.main(["compare", "--methods", "nope", "--debug"])


def test_sweep_set_applies_where_used(tmp_path, capsys):
    """--set values join the sub-grids whose methods use them, and only those."""
    code, out, err = run(["sweep", "--width", "24", "--height", "24", "--spp", "1",
                          "--repeats", "1", "--grid", "method=hard", "--grid",
                          "method=raytraced", "--set", "resolution=32", "--set",
                          "shadow_rays=2", "--error", "vis_misclassified",
                          "--out", tmp_path], capsys)
    assert code == 0, err
    rows = json.loads((tmp_path / "sweep.json").read_text())
    assert [r["name"] for r in rows] == ["hard resolution=32 spp=1",
                                         "raytraced shadow_rays=2 spp=1"]
    assert all(r["error"] == r["vis_misclassified"] for r in rows)


def test_sweep_inline_and_json_grids(tmp_path, capsys):
    grid_file = tmp_path / "grid.json"
    grid_file.write_text(json.dumps({"method": "raytraced", "spp": [1, 2]}))
    code, out, err = run(["sweep", "--width", "32", "--height", "32", "--spp", "2",
                          "--repeats", "1",
                          "--grid", "method=hard resolution=64,128",
                          "--grid", grid_file,
                          "--grid", '{"method": "unshadowed"}',
                          "--out", tmp_path / "sw"], capsys)
    assert code == 0, err
    with open(tmp_path / "sw" / "sweep.csv") as f:
        rows = list(csv.DictReader(f))
    assert [r["name"] for r in rows] == ["hard resolution=64 spp=2", "hard resolution=128 spp=2",
                                         "raytraced spp=1", "raytraced spp=2",
                                         "unshadowed spp=2"]
    assert any(r["pareto"] == "True" for r in rows)
    assert (tmp_path / "sw" / "pareto.png").stat().st_size > 0
    assert "pareto" in out


def test_maps_exports_every_emitter(tmp_path, capsys):
    code, out, err = run(["maps", SCENES / "room_two_points.xml", "--set", "resolution=32",
                          "--out", tmp_path], capsys)
    assert code == 0, err
    for label in ("key", "fill"):   # point lights: 6 cube faces stacked vertically
        ch = read_exr(str(tmp_path / f"{label}.exr"))
        depth = ch["depth.Y"]
        assert depth.shape == (6 * 32, 32)
        # inside the room every texel sees a surface within the room's diagonal
        finite = depth[np.isfinite(depth)]
        assert finite.size > 0 and finite.min() > 0 and finite.max() < 8


def test_help_via_entry_point():
    """The installed module runs as a program and documents every command."""
    p = subprocess.run([sys.executable, "-m", "mi_shadowmap.cli", "--help"],
                       capture_output=True, text=True, timeout=120)
    assert p.returncode == 0
    for word in ("compare", "sweep", "maps", "--debug"):
        assert word in p.stdout
    p = subprocess.run([sys.executable, "-m", "mi_shadowmap.cli", "sweep", "--help"],
                       capture_output=True, text=True, timeout=120)
    assert p.returncode == 0 and "--grid" in p.stdout and "name=v1,v2" in p.stdout


def test_python_dash_m_package_runs_the_command_line(tmp_path):
    """``python -m mi_shadowmap ...`` said "No module named mi_shadowmap.__main__;
    'mi_shadowmap' is a package and cannot be directly executed" (a venv whose scripts
    folder is not on PATH has no other short way to the CLI); it now runs it."""
    p = subprocess.run([sys.executable, "-m", "mi_shadowmap", "--help"],
                       capture_output=True, text=True, timeout=120)
    assert p.returncode == 0 and "compare" in p.stdout and "tune" in p.stdout, p.stderr
    p = subprocess.run([sys.executable, "-m", "mi_shadowmap", "compare",
                        str(tmp_path / "missing.xml")], capture_output=True, text=True,
                       timeout=120)
    assert p.returncode == 2 and "scene file not found" in p.stderr, p.stderr


def test_maps_default_scene_every_layer(tmp_path, capsys):
    """Without --methods every layer any map method uses (with default properties) is
    exported; the second surface is never in front of the first (equal, to rounding,
    on open surfaces, which are their own second surface)."""
    code, out, err = run(["maps", "--set", "resolution=32", "--out", tmp_path], capsys)
    assert code == 0, err
    ch = read_exr(str(tmp_path / "spot.exr"))
    header = read_exr_header(str(tmp_path / "spot.exr"))
    layers = {"depth"} | {layer for m in methods.records() if m.uses_map for layer in
                          m.layer_names(options.parse_options({"method": m.name,
                                                               "resolution": 32}))}
    # images as channels, the few-values-per-map layers as header attributes
    assert {c[:-len(".Y")] for c in ch} | (layers & set(header)) == layers
    assert "depth.Y" in ch and all(c.shape == (32, 32) for c in ch.values())
    assert ch["depth.Y"].shape == (32, 32)
    if "second_depth.Y" in ch:
        d, d2 = ch["depth.Y"], ch["second_depth.Y"]
        ok = np.isfinite(d)
        assert ok.any() and np.all(d2[ok] >= d[ok] * (1 - 1e-5))


def test_maps_only_the_chosen_methods_layers(tmp_path, capsys):
    code, out, err = run(["maps", "--methods", "hard", "--set", "resolution=16",
                          "--out", tmp_path], capsys)
    assert code == 0, err
    assert set(read_exr(str(tmp_path / "spot.exr"))) == {"depth.Y"}
    assert "spot" in out and "16^2" in out


@pytest.mark.parametrize("method, virtual", [("misread_depth", "true"),
                                             ("misread_depth", "false"),
                                             ("misread_near", "false")])
def test_a_method_reading_the_first_depth_it_gave_up_is_named(tmp_path, capsys, method,
                                                              virtual):
    """A plugin's method registered with ``reads_depth=False`` (its maps hold second
    depths alone) whose lookup reads ``smap.depth`` (``hard``'s), or whose layer is built
    from it (``pcss_near``): the CLI printed the innermost error, Dr.Jit's "attempted to
    gather from an empty array", naming neither the method nor ``reads_depth`` (the
    MethodError naming both was raised from it). Now the one line names both."""
    plugin = tmp_path / "misread.py"
    plugin.write_text(
        "import mi_shadowmap\nfrom mi_shadowmap import methods\n"
        "from mi_shadowmap.depth_maps import second_depth_layer\n"
        "sd = {'second_depth': second_depth_layer}\n"
        "mi_shadowmap.register_method('misread_depth', methods.get('hard').lookup, "
        "layers=sd, virtual=True, reads_depth=False, replace=True)\n"
        "mi_shadowmap.register_method('misread_near', methods.get('second_depth').lookup, "
        "layers={**sd, **methods.get('pcss').layers}, reads_depth=False, replace=True, "
        "properties=methods.get('second_depth').properties)\n")
    try:
        code, out, err = run(["compare", "--plugin", plugin, "--methods", method,
                              "--reference", "raytraced", *TINY, "--set",
                              f"virtual={virtual}", "--out", tmp_path / "out"], capsys)
    finally:
        for name in ("misread_depth", "misread_near"):
            if name in methods.METHODS:
                mi_shadowmap.unregister_method(name)
    lines = [ln for ln in err.strip().splitlines() if "error:" in ln]
    print(lines)
    assert code == 2 and len(lines) == 1
    assert f"'{method}' was registered with reads_depth=False" in lines[0]


def test_broken_plugin_is_one_line(tmp_path, capsys):
    plugin = tmp_path / "broken.py"
    plugin.write_text("import mi_shadowmap\nmi_shadowmap.register_method('Bad Name', len)\n")
    code, out, err = run(["compare", "--plugin", plugin, "--out", tmp_path / "never"], capsys)
    assert code == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1 and str(plugin) in lines[0] and "Bad Name" in lines[0]
    assert "Traceback" not in err and not (tmp_path / "never").exists()
    plugin.write_text("def broken(:\n")
    code, out, err = run(["maps", "--plugin", plugin], capsys)
    assert code == 2 and "SyntaxError" in err and len(err.strip().splitlines()) == 1


def test_maps_into_a_used_folder_warns_about_an_earlier_runs_maps(tmp_path, capsys):
    """``maps`` of one scene, then of another, into one folder: the first one's maps
    (``spot.exr``) stayed beside the second's without a word (``compare`` warns so)."""
    out = tmp_path / "maps"
    code, _, err = run(["maps", "--light", "spot", "--methods", "hard", "--set",
                        "resolution=16", "--out", out], capsys)
    assert code == 0 and (out / "spot.exr").exists()
    with pytest.warns(UserWarning, match=r"did not write.*spot\.exr"):
        code, _, _ = run(["maps", "--light", "point", "--methods", "hard", "--set",
                          "resolution=16", "--out", out], capsys)
    assert code == 0 and (out / "point.exr").exists()


def test_plugin_in_help():
    p = subprocess.run([sys.executable, "-m", "mi_shadowmap.cli", "compare", "--help"],
                       capture_output=True, text=True, timeout=120)
    assert p.returncode == 0 and "--plugin" in p.stdout
    for name in harness.available_methods():   # the choices come from the registry
        assert name in p.stdout


def test_reused_out_dir_warns_about_an_earlier_runs_images(tmp_path, capsys):
    """A second compare into the same folder with other methods: the first run's images
    stay (nothing is deleted), and a warning names them (they were left silently next to
    a metrics.csv that no longer lists them)."""
    out = tmp_path / "out"
    base = ["compare", "--width", "16", "--height", "16", "--spp", "1", "--out", str(out)]
    code, _, _ = run(base + ["--methods", "hard"], capsys)
    assert code == 0
    with pytest.warns(UserWarning, match=r"did not write.*hard\.exr"):
        code, _, _ = run(base + ["--methods", "pcf"], capsys)
    assert code == 0 and (out / "hard.exr").exists() and (out / "pcf.exr").exists()


def test_an_error_during_rendering_starts_its_own_line(tmp_path, capsys):
    """An unsupported emitter found while the methods' progress bar runs: the error's
    line was appended to the unfinished bar."""
    scene = tmp_path / "darea.xml"
    scene.write_text("""<scene version="3.0.0">
      <sensor type="perspective"><film type="hdrfilm"><integer name="width" value="16"/>
        <integer name="height" value="16"/></film></sensor>
      <shape type="rectangle"><emitter type="directionalarea"/></shape>
      <shape type="sphere"/></scene>""")
    code, out, err = run(["compare", scene, "--spp", "1", "--methods", "hard",
                          "--out", tmp_path / "out"], capsys)
    assert code == 2
    line = next(s for s in err.splitlines() if "error:" in s)
    assert line.startswith("mi-shadowmap: error:") and "not supported" in line, err


NO_EMITTER_XML = """<scene version="3.0.0">
  <sensor type="perspective"><transform name="to_world">
    <lookat origin="0, 2, 5" target="0, 0.5, 0" up="0, 1, 0"/></transform>
    <film type="hdrfilm"><integer name="width" value="8"/><integer name="height" value="8"/>
    </film></sensor>
  <shape type="sphere"/>
</scene>"""


@pytest.mark.parametrize("command", [["compare"], ["sweep"], ["tune", "--max-error", "0.05"],
                                     ["maps"]])
def test_a_scene_without_emitters_is_one_line_and_no_output_folder(tmp_path, capsys,
                                                                   command):
    """``tune`` said numpy's "need at least one array to stack" and ``maps`` wrote
    nothing and exited 0; every command now names the missing light before it makes
    ``--out``."""
    scene = tmp_path / "dark.xml"
    scene.write_text(NO_EMITTER_XML)
    code, out, err = run([command[0], scene, *command[1:], "--out", tmp_path / "o"], capsys)
    assert code == 2
    assert "the scene has no emitter" in err and "add a light" in err
    assert not (tmp_path / "o").exists()


def _three_lights_xml(key="key", point_id=None):
    """A ground, sphere and cube under a spot (id ``key``), a point light (id
    ``point_id``, or none) and a directional light ``sun``; film $width x $height."""
    point = f' id="{point_id}"' if point_id else ""
    return f"""<scene version="3.0.0">
  <default name="width" value="16"/><default name="height" value="16"/>
  <sensor type="perspective"><transform name="to_world">
    <lookat origin="0.2, 3.5, 4.9" target="0.25, 0.25, 0" up="0, 1, 0"/></transform>
    <film type="hdrfilm"><integer name="width" value="$width"/>
      <integer name="height" value="$height"/></film></sensor>
  <shape type="rectangle"><transform name="to_world"><scale value="4"/>
    <rotate x="1" angle="-90"/></transform></shape>
  <shape type="sphere"><point name="center" value="-0.85, 0.65, -0.6"/>
    <float name="radius" value="0.65"/></shape>
  <shape type="cube"><transform name="to_world"><scale value="0.5"/>
    <translate value="0.85, 0.5, -0.5"/></transform></shape>
  <emitter type="spot" id="{key}"><transform name="to_world">
    <lookat origin="-2.4, 4.0, -3.4" target="0.2, 0.0, 0.3" up="0, 1, 0"/></transform>
    <rgb name="intensity" value="120"/></emitter>
  <emitter type="point"{point}><point name="position" value="2, 4, 2"/>
    <rgb name="intensity" value="30"/></emitter>
  <emitter type="directional" id="sun"><vector name="direction" value="1, -2, 0.5"/>
    <rgb name="irradiance" value="1"/></emitter>
</scene>"""


def test_maps_of_emitters_whose_ids_differ_in_punctuation_get_their_own_files(tmp_path,
                                                                              capsys):
    """Ids "lamp a" (the spot) and "lamp_a" (the point light) both became lamp_a.exr:
    the spot's map was overwritten, exit 0. Now the id that is a file name keeps it, the
    other gets lamp_a_2.exr; the output lines and each file's ``emitter`` header say
    which emitter a file holds."""
    scene = tmp_path / "s.xml"
    scene.write_text(_three_lights_xml(key="lamp a", point_id="lamp_a"))
    code, out, err = run(["maps", scene, "--methods", "hard", "--set", "resolution=16",
                          "--out", tmp_path / "m"], capsys)
    assert code == 0, err
    files = sorted(p.name for p in (tmp_path / "m").iterdir())
    assert files == ["lamp_a.exr", "lamp_a_2.exr", "sun.exr"]
    point, spot = (read_exr(str(tmp_path / "m" / f)) for f in ("lamp_a.exr", "lamp_a_2.exr"))
    assert point["depth.Y"].shape == (6 * 16, 16) and spot["depth.Y"].shape == (16, 16)
    assert read_exr_header(str(tmp_path / "m" / "lamp_a.exr"))["emitter"] == "lamp_a"
    assert read_exr_header(str(tmp_path / "m" / "lamp_a_2.exr"))["emitter"] == "lamp a"
    assert "lamp_a_2.exr: lamp a (" in out and "lamp_a.exr: lamp_a (" in out


def test_unique_file_stems():
    from mi_shadowmap.report import unique_file_stems
    assert unique_file_stems(["lamp a", "lamp_a", "sun"]) == ["lamp_a_2", "lamp_a", "sun"]
    # one file on case-insensitive file systems; a taken "_2" is skipped
    assert unique_file_stems(["Key", "key", "key 2", "key_2"]) == ["Key", "key_3", "key_2_2",
                                                                   "key_2"]


@pytest.mark.parametrize("order", [["multiview", "hard"], ["hard", "multiview"]])
def test_maps_writes_each_view_of_an_area_light(tmp_path, capsys, order):
    """``--methods multiview hard`` wrote the 192-face multiview map and ``--methods hard
    multiview`` the 6-face cube map, to the same light.exr, the other dropped without
    notice. Now both are written, named after their methods, in either order."""
    code, out, err = run(["maps", SCENES / "cbox_area.xml", "--methods", *order,
                          "--set", "resolution=8", "--out", tmp_path], capsys)
    assert code == 0, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["light_hard.exr",
                                                          "light_multiview.exr"]
    assert read_exr(str(tmp_path / "light_hard.exr"))["depth.Y"].shape == (6 * 8, 8)
    assert read_exr(str(tmp_path / "light_multiview.exr"))["depth.Y"].shape == (192 * 8, 8)
    assert "MultiView, 192 face(s) of 8^2), layers depth; read by multiview" in out


def test_width_and_height_reach_a_sensor_in_an_included_file(tmp_path, capsys):
    """--width/--height were refused ("has no parameter $width, $height") when the
    sensor was in an <include>d file."""
    (tmp_path / "sensor.xml").write_text(
        '<scene version="3.0.0"><sensor type="perspective"><transform name="to_world">'
        '<lookat origin="0.2, 3.5, 4.9" target="0.25, 0.25, 0" up="0, 1, 0"/></transform>'
        '<film type="hdrfilm"><integer name="width" value="$width"/>'
        '<integer name="height" value="$height"/></film></sensor></scene>')
    text = _three_lights_xml()
    start, end = text.index("  <sensor"), text.index("</sensor>") + len("</sensor>")
    scene = tmp_path / "s.xml"
    scene.write_text(text[:start] + '  <include filename="sensor.xml"/>' + text[end:])
    code, out, err = run(["compare", scene, "--methods", "hard", "--spp", "1", "--width",
                          "12", "--height", "9", "--repeats", "1", "--out", tmp_path / "o"],
                         capsys)
    assert code == 0, err
    assert read_exr(str(tmp_path / "o" / "hard.exr"))["R"].shape == (9, 12)


@pytest.mark.parametrize("case", ["no_sensor", "tune_spp", "maps_resolution", "render_error"])
def test_errors_after_validation_leave_no_output_folder(tmp_path, capsys, case):
    """--out was created before these errors and left empty: a scene without a sensor
    (Mitsuba's "No sensor specified!" mid-render; now named before rendering), tune's
    --spp above --max-spp, a map resolution over the memory budget, an error while
    rendering. The folder is now made only when something is written."""
    scene = tmp_path / "s.xml"
    text = _three_lights_xml()
    if case == "no_sensor":
        text = text[:text.index("  <sensor")] + text[text.index("</sensor>") + 9:]
    if case == "render_error":    # found while rendering (see the test above)
        text = text.replace("</scene>", '<shape type="rectangle"><emitter '
                            'type="directionalarea"/></shape></scene>')
    scene.write_text(text)
    out = tmp_path / "deep" / "o"
    argv = {"no_sensor": ["compare", scene, "--methods", "hard", "--spp", "1"],
            "tune_spp": ["tune", scene, "--max-error", "0.05", "--spp", "2048"],
            "maps_resolution": ["maps", scene, "--set", "resolution=9000"],
            "render_error": ["compare", scene, "--methods", "hard", "--spp", "1"]}[case]
    code, _, err = run(argv + ["--out", out], capsys)
    assert code == 2 and "error:" in err
    if case == "no_sensor":
        assert "the scene has no sensor" in err
    assert not (tmp_path / "deep").exists(), err


def test_maps_help_lists_only_methods_with_maps(capsys):
    """maps --help listed raytraced and unshadowed, which maps refuses."""
    assert cli.main(["maps", "--help"]) == 0
    text = " ".join(capsys.readouterr().out.split())
    for name in harness.map_methods():
        assert name in text
    assert "raytraced" not in text and "unshadowed" not in text
    # renders default to virtual maps, but maps writes full ones unless told: it said not
    assert "full maps" in text and "virtual=true" in text
    assert "*_span, is a header attribute" in text    # listed among the layers it prints


@pytest.mark.parametrize("argv, match", [
    (["compar", "scene.xml"], "unknown command 'compar' (did you mean 'compare'?); "
                              "commands: compare, sweep, maps, tune"),
    (["swep"], "unknown command 'swep' (did you mean 'sweep'?)"),
    (["--plugin", "/no/such.py", "tunee", "--max-error", "1"], "unknown command 'tunee'"),
    (["frobnicate"], "unknown command 'frobnicate'; commands:"),
])
def test_a_mistyped_command_is_named(argv, match, capsys):
    """'mi-shadowmap compar scene.xml' ran compare on a scene 'compar' and said
    "unrecognized arguments: scene.xml"."""
    code, out, err = run(argv, capsys)
    assert code == 2 and len(err.strip().splitlines()) == 1
    assert err.startswith("mi-shadowmap: error: ") and match in err, err


def test_a_missing_scene_file_is_still_not_a_command(capsys):
    code, out, err = run(["missing_scene.xml", "--out", "/nonexistent/x"], capsys)
    assert code == 2 and "scene file not found: missing_scene.xml" in err


def test_the_stale_file_warning_is_one_clean_line(tmp_path):
    """The warning about an earlier run's images printed Python's default format: the
    file and line that warned, then that source line (``warnings.warn(f"{out_dir}
    holds ...``) under the message."""
    out = tmp_path / "out"
    base = [sys.executable, "-m", "mi_shadowmap.cli", "compare", "--width", "8", "--height",
            "8", "--spp", "1", "--repeats", "1", "--out", str(out), "--methods"]
    assert subprocess.run(base + ["hard"], capture_output=True, timeout=300).returncode == 0
    p = subprocess.run(base + ["pcf"], capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr
    lines = [ln for ln in p.stderr.splitlines() if "did not write" in ln or "warn" in ln]
    assert len(lines) == 1, p.stderr
    assert lines[0].startswith("mi-shadowmap: warning: ") and "hard.exr" in lines[0]
    assert "report.py" not in p.stderr and "warnings.warn" not in p.stderr


SCENE_INTEGRATOR = ('<integrator type="shadowmap"><string name="method" value="pcf"/>'
                    '<integer name="resolution" value="24"/><float name="bias" value="0.3"/>'
                    '<integer name="num_samples" value="8"/></integrator>')


def _with_integrator(tmp_path, integrator=SCENE_INTEGRATOR, name="own.xml"):
    text = _three_lights_xml()
    scene = tmp_path / name
    scene.write_text(text.replace("  <sensor", integrator + "\n  <sensor", 1))
    return scene


def _compare_rows(argv, out, capsys):
    code, _, err = run(["compare", *argv, "--spp", "1", "--repeats", "1", "--out", out],
                       capsys)
    assert code == 0, err
    return {r["name"]: r for r in json.loads((out / "metrics.json").read_text())}, err


def test_compare_takes_the_scene_files_shadowmap_integrator_properties(tmp_path, capsys):
    """The scene's <integrator type="shadowmap"> properties were ignored without a word
    (hard: vis RMSE 0.0327 at the package defaults vs 0.0643 with its resolution=64,
    bias=0.3), and so was tune's pasted integrator.xml. They are now the base of every
    method that uses them, as --set is: equal to --set, under --set and method strings,
    named in a note; --ignore-scene-integrator leaves them out."""
    own = _with_integrator(tmp_path)
    bare = tmp_path / "bare.xml"
    bare.write_text(_three_lights_xml())
    rows, err = _compare_rows([own, "--methods", "hard", "pcf"], tmp_path / "a", capsys)
    assert set(rows) == {"reference (raytraced)", "hard bias=0.3 resolution=24",
                         "pcf bias=0.3 num_samples=8 resolution=24"}
    assert "note: the scene's shadowmap integrator gives bias=0.3, num_samples=8, " \
           "resolution=24 to every method that uses it" in err
    same, _ = _compare_rows([bare, "--methods", "hard", "pcf", "--set", "resolution=24",
                             "--set", "bias=0.3", "--set", "num_samples=8"], tmp_path / "b",
                            capsys)
    # equal up to the film's accumulation order: Dr.Jit's parallel scatter-adds of the
    # samples sum in a varying order (the exact compare failed 1 run in 5 by 2.5e-10)
    for name in rows:
        assert rows[name]["vis_rmse"] == pytest.approx(same[name]["vis_rmse"], rel=1e-6,
                                                       abs=1e-9), name
    # --set over the scene, the method string over both; a property no method uses: a note
    rows, err = _compare_rows([own, "--methods", "hard:resolution=16", "--set", "bias=0.1"],
                              tmp_path / "c", capsys)
    assert set(rows) == {"reference (raytraced)", "hard bias=0.1 resolution=16"}
    assert "num_samples=8: used by none of the methods, ignored" in err
    rows, err = _compare_rows([own, "--methods", "hard", "--ignore-scene-integrator"],
                              tmp_path / "d", capsys)
    bare_rows, _ = _compare_rows([bare, "--methods", "hard"], tmp_path / "e", capsys)
    assert set(rows) == {"reference (raytraced)", "hard"} and "note" not in err
    assert rows["hard"]["vis_rmse"] == pytest.approx(bare_rows["hard"]["vis_rmse"],
                                                     rel=1e-6, abs=1e-9)


def test_a_scene_property_some_method_refuses_is_not_taken_with_a_note(tmp_path, capsys):
    """A scene integrator with ``virtual=true`` (Mitsuba renders it) made ``compare`` with
    ``multiview`` among the methods fail: multiview uses ``virtual`` but refuses true. It
    is now left out, with a note naming the method; tune leaves it out of that method."""
    own = _with_integrator(tmp_path, '<integrator type="shadowmap">'
                           '<boolean name="virtual" value="true"/></integrator>')
    rows, err = _compare_rows([own, "--methods", "hard", "multiview"], tmp_path / "a", capsys)
    assert set(rows) == {"reference (raytraced)", "hard", "multiview"}
    assert "virtual=True, which multiview cannot take: not taken" in err
    from mi_shadowmap.cli import build_parser, tune_methods
    from mi_shadowmap.scenes import load_scene
    args = build_parser().parse_args(["tune", str(own), "--max-error", "0.1",
                                      "--methods", "hard", "multiview"])
    items = tune_methods(args, load_scene(str(own)), {})
    assert [i.get("virtual") for i in items] == [True, None]
    assert "which multiview cannot take: not taken for it" in capsys.readouterr().err


def test_another_scene_integrator_is_not_used_with_a_note(tmp_path, capsys):
    scene = _with_integrator(tmp_path, '<integrator type="path"/>')
    rows, err = _compare_rows([scene, "--methods", "hard"], tmp_path / "o", capsys)
    assert set(rows) == {"reference (raytraced)", "hard"}
    assert "note: the scene's integrator (PathIntegrator) is not 'shadowmap'" in err


def test_maps_and_sweep_take_the_scene_integrator_properties(tmp_path, capsys):
    own = _with_integrator(tmp_path)
    code, out, err = run(["maps", own, "--methods", "hard", "--out", tmp_path / "m"], capsys)
    assert code == 0, err
    assert read_exr(str(tmp_path / "m" / "key.exr"))["depth.Y"].shape == (24, 24)
    code, out, err = run(["sweep", own, "--grid", "method=hard resolution=16",
                          "--grid", "method=raytraced", "--spp", "1", "--repeats", "1",
                          "--out", tmp_path / "s"], capsys)
    assert code == 0, err
    names = {r["name"] for r in json.loads((tmp_path / "s" / "sweep.json").read_text())}
    assert "hard bias=0.3 resolution=16 spp=1" in names      # the sweep's axis wins


def test_tune_fixes_the_scene_integrator_properties_it_does_not_search(tmp_path, capsys):
    """tune searches resolution and each method's main parameters (pcf's num_samples)
    from the package defaults; the scene's other properties (bias) are fixed in every
    method that uses them, below --set and the method strings."""
    import argparse
    from mi_shadowmap.scenes import load_scene
    own = _with_integrator(tmp_path)
    args = argparse.Namespace(scene=str(own), methods=["hard", "pcf", "raytraced"],
                              ignore_scene_integrator=False, command="tune")
    items = cli.tune_methods(args, load_scene(own), {})
    assert items == [{"method": "hard", "bias": 0.3}, {"method": "pcf", "bias": 0.3},
                     {"method": "raytraced"}]
    err = capsys.readouterr().err
    assert "gives bias=0.3 to every method that uses it, fixed" in err
    assert "sets num_samples=8, resolution=24, which tune searches" in err
    args.methods = ["pcf:bias=0.2"]
    assert cli.tune_methods(args, load_scene(own), {}) == ["pcf:bias=0.2"]   # nothing fixed
    args.methods = ["hard"]
    assert cli.tune_methods(args, load_scene(own), {"bias": 0.1}) == ["hard"]


def test_ctrl_c_in_a_render_is_interrupted_not_an_error(tmp_path, capsys, monkeypatch):
    """mi.render wraps a Ctrl-C raised in a Python integrator as a RuntimeError: the
    command printed 'mi-shadowmap: error: KeyboardInterrupt' with status 2, not the
    'interrupted' and 130 of a Ctrl-C elsewhere."""
    def interrupted(*a, **k):
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt as e:
            raise RuntimeError("render failed") from e
    monkeypatch.setattr(harness, "compare", interrupted)
    code, out, err = run(["compare", *TINY, "--methods", "hard", "--out", tmp_path / "o"],
                         capsys)
    assert code == 130 and err.strip().splitlines()[-1] == "mi-shadowmap: interrupted", err


def test_compare_keeps_the_methods_rendered_before_one_that_fails(tmp_path, capsys):
    """A method whose maps exceed memory_budget fails at its render, after the reference
    and the methods before it rendered: the command wrote nothing (3 renders lost); now
    it writes those, with their metrics, and still reports the error (status 2)."""
    out_dir = tmp_path / "out"
    code, out, err = run(["compare", "--width", "16", "--height", "16", "--spp", "1",
                          "--repeats", "1", "--light", "point", "--methods",
                          "hard:resolution=32", "pcf:resolution=8192", "--out", out_dir],
                         capsys)
    assert code == 2 and "memory_budget" in err.strip().splitlines()[-1], err
    assert "stopped after 1 of 2 methods" in err, err
    rows = json.loads((out_dir / "metrics.json").read_text())
    assert [r["name"] for r in rows] == ["reference (raytraced)", "hard resolution=32"]
    assert rows[0]["vis_rmse"] == 0 and rows[1]["vis_rmse"] >= 0
    assert (out_dir / "hard_resolution=32.exr").exists()
    assert "hard resolution=32" in out       # the table of what was rendered


PARAM_SCENE = """<scene version="3.0.0">
  <sensor type="perspective">
    <transform name="to_world"><lookat origin="0,3,4" target="0,0,0" up="0,1,0"/></transform>
    <sampler type="independent"><integer name="sample_count" value="1"/></sampler>
    <film type="hdrfilm"><integer name="width" value="16"/><integer name="height" value="16"/></film>
  </sensor>
  <shape type="rectangle"><transform name="to_world"><rotate x="1" angle="-90"/><scale value="3"/></transform></shape>
  <shape type="sphere"><point name="center" x="0" y="$ypos" z="0"/><float name="radius" value="0.3"/></shape>
  <emitter type="point"><point name="position" x="0" y="3" z="0"/><rgb name="intensity" value="10"/></emitter>
</scene>"""


def test_a_scene_parameter_without_default_is_given_with_param(tmp_path, capsys):
    """A scene file's $ypos without a <default> could not be given on the command line
    (only $width and $height had options): Mitsuba's "undefined parameter: $ypos" was the
    end of it. --param fills any $ parameter; the error says so."""
    scene = tmp_path / "user scene.xml"
    scene.write_text(PARAM_SCENE)
    base = ["compare", scene, "--methods", "hard:resolution=32", "--spp", "1",
            "--repeats", "1"]
    code, out, err = run(base + ["--out", tmp_path / "a"], capsys)
    assert code == 2 and "--param ypos=VALUE" in err, err
    assert not (tmp_path / "a").exists()
    code, out, err = run(base + ["--param", "ypos=0.8", "--out", tmp_path / "b"], capsys)
    assert code == 0, err
    assert len(json.loads((tmp_path / "b" / "metrics.json").read_text())) == 2
    code, out, err = run(base + ["--param", "ypos=0.8", "--param", "yposs=1", "--out",
                                 tmp_path / "c"], capsys)
    assert code == 2 and "$yposs" in err, err
    code, out, err = run(["compare", "--param", "ypos=1", "--out", tmp_path / "d"], capsys)
    assert code == 2 and "built-in scene" in err, err


@pytest.mark.parametrize("command", [
    ["compare"], ["sweep"], ["maps"], ["tune", "--max-error", "0.05"]])
def test_param_method_is_not_dropped_without_a_word(command, tmp_path, capsys):
    """Every scene of scenes_xml/ takes $method, the method of its shadowmap integrator,
    which the commands do not take (--methods, a sweep grid choose): ``--param
    method=pcf`` then rendered every method without a word. Without --methods (--grid)
    it is an error naming them; with them, $method changes nothing that is rendered."""
    scene = SCENES / "spot_sphere_box.xml"
    out_dir = tmp_path / "never"
    code, out, err = run(command + [scene, "--param", "method=pcf", "--out", out_dir],
                         capsys)
    lines = err.strip().splitlines()
    assert code == 2 and len(lines) == 1, err
    assert "--param method=pcf" in lines[0], err
    assert ("--grid" if command[0] == "sweep" else "--methods pcf") in lines[0], err
    assert not out_dir.exists()
    # named: the file's $method is filled and the named methods render
    small = ["--width", "16", "--height", "16", "--spp", "1", "--repeats", "1"]
    named = {"compare": small + ["--methods", "hard"],
             "sweep": small + ["--grid", "method=hard resolution=32"],
             "maps": ["--methods", "hard", "--set", "resolution=32"]}.get(command[0])
    if named is not None:    # (tune's search is the longest; compare stands for it)
        code, out, err = run([command[0], scene, "--param", "method=pcf", *named,
                              "--out", tmp_path / "ok"], capsys)
        assert code == 0, err


def test_progress_in_a_log_is_lines(tmp_path, capsys):
    """stderr that is not a terminal (a log, a pipe; capsys here): tqdm drew its bar with
    carriage returns there too, every redraw on one line of the log, and a bar that does
    not stay (compare's) left a line of blanks. Now: plain lines, the last one kept."""
    code, out, err = run(["sweep", "--grid", "method=hard resolution=32", "--width", "16",
                          "--height", "16", "--spp", "1", "--repeats", "1",
                          "--out", tmp_path / "s"], capsys)
    assert code == 0, err
    assert "\r" not in err and "sweep: 100%" in err, repr(err)
    code, out, err = run(["compare", "--methods", "hard:resolution=32", "pcf:resolution=32",
                          "--width", "16", "--height", "16", "--spp", "1", "--repeats", "1",
                          "--out", tmp_path / "c"], capsys)
    assert code == 0, err
    assert "\r" not in err and "methods: 100%" in err, repr(err)
    assert all(line.strip() for line in err.splitlines()), repr(err)


def test_a_log_gets_each_progress_count_once(monkeypatch):
    """A bar whose last update came after the log interval printed its last line, and
    its close printed it again (compare's 'methods: 100%|...| 1/1' twice in a log after a
    14 s method). Each count is one line now, the last one kept."""
    import io
    from mi_shadowmap import progress
    monkeypatch.setattr(progress, "LOG_INTERVAL", 0.0)     # every update printed
    buf = io.StringIO()
    for _ in progress.bar(range(3), desc="x", file=buf):
        pass
    lines = buf.getvalue().splitlines()
    counts = [ln.split("[")[0].split("|")[-1].strip() for ln in lines]
    assert counts == ["0/3", "1/3", "2/3", "3/3"], lines


def test_a_log_keeps_a_progress_line_that_names_the_next_step(monkeypatch):
    """The de-duplication of a count's lines (above) must not drop a line whose postfix
    changed at the same count: the sweep's reference bar says which render runs next
    (``set_postfix_str`` after ``update``), and the log kept the line of the render just
    done, naming the finished render while the converged visibility ran for minutes."""
    import io
    from mi_shadowmap import progress
    monkeypatch.setattr(progress, "LOG_INTERVAL", 0.0)     # every update printed
    buf = io.StringIO()
    b = progress.bar(total=2, desc="ref", unit="render", leave=False, postfix="image",
                     file=buf)
    b.update(1)
    b.set_postfix_str("visibility")
    b.update(1)
    b.close()
    lines = buf.getvalue().splitlines()
    tails = [(ln.split("[")[0].split("|")[-1].strip(), ln.rstrip("]").split(", ")[-1])
             for ln in lines]
    assert tails == [("0/2", "image"), ("1/2", "image"), ("1/2", "visibility"),
                     ("2/2", "visibility")], lines


def test_variant_before_the_command(tmp_path, capsys):
    """``--variant`` is taken before the command too, as ``--plugin`` and ``--debug``:
    ``mi-shadowmap --variant llvm_ad_mono maps ...`` ran ``compare`` on a scene file
    named "maps" ("scene file not found: maps"), and with a scene file said
    "unrecognized arguments: scene.xml"."""
    import mitsuba as mi
    code, out, err = run(["--variant", "llvm_ad_mono", "maps", "--methods", "hard",
                          "--set", "resolution=16", "--out", tmp_path], capsys)
    assert code == 0, err
    assert mi.variant() == "llvm_ad_mono"
    assert list(tmp_path.glob("*.exr"))


def test_an_abbreviated_variant_after_the_command_is_used(tmp_path, capsys):
    """argparse takes ``--varia`` for ``--variant`` after the command; since the variant
    was taken by the pre-parse only (whole names), such an abbreviation was parsed and
    then dropped: ``maps ... --varia llvm_ad_mono`` rendered in llvm_ad_rgb."""
    import mitsuba as mi
    mi.set_variant("llvm_ad_rgb")
    code, out, err = run(["maps", "--methods", "hard", "--set", "resolution=16",
                          "--out", tmp_path, "--varia", "llvm_ad_mono"], capsys)
    assert code == 0, err
    assert mi.variant() == "llvm_ad_mono"


def test_a_scene_with_several_sensors_says_which_one_renders(tmp_path, capsys):
    """compare, sweep, tune and maps use a scene's first sensor only; a user's file with
    two cameras (ids cam_main, cam_top) had the second dropped without a word. A note
    now names the one rendered and those left out; one sensor: no note."""
    top = ('  <sensor type="perspective" id="cam_top"><transform name="to_world">\n'
           '    <lookat origin="0, 6, 0.01" target="0, 0, 0" up="0, 1, 0"/></transform>\n'
           '    <film type="hdrfilm"><integer name="width" value="12"/>'
           '<integer name="height" value="12"/></film></sensor>\n')
    text = _three_lights_xml().replace('<sensor type="perspective">',
                                       '<sensor type="perspective" id="cam_main">', 1)
    scene = tmp_path / "two_cams.xml"
    scene.write_text(text.replace("  <shape", top + "  <shape", 1))
    rows, err = _compare_rows([scene, "--methods", "hard"], tmp_path / "a", capsys)
    assert ("note: the scene has 2 sensors; this command renders the first one, "
            "'cam_main', only (not 'cam_top')") in err, err
    code, _, err = run(["maps", scene, "--methods", "hard", "--out", tmp_path / "m"], capsys)
    assert code == 0 and "the first one, 'cam_main', only (not 'cam_top')" in err, err
    one = tmp_path / "one_cam.xml"
    one.write_text(_three_lights_xml())
    rows, err = _compare_rows([one, "--methods", "hard"], tmp_path / "b", capsys)
    assert "sensors" not in err, err


def test_compare_and_sweep_render_the_scene_files_sample_count(tmp_path, capsys):
    """compare and sweep rendered 16 spp whatever the scene file's sampler said: a
    user's file with sample_count 4, or 'compare spot_sphere_box.xml --param spp=2',
    rendered and reported 16 (metrics.json spp 16). Without --spp they now render the
    file's count, with a note; --spp overrides it; 16 stays the count for a file that
    says 16 (every scene of scenes_xml), without a note."""
    scene = tmp_path / "four.xml"
    scene.write_text(_three_lights_xml().replace(
        '<sensor type="perspective">',
        '<sensor type="perspective"><sampler type="independent">'
        '<integer name="sample_count" value="3"/></sampler>', 1))
    code, _, err = run(["compare", scene, "--methods", "hard", "--repeats", "1",
                        "--out", tmp_path / "a"], capsys)
    assert code == 0, err
    rows = json.loads((tmp_path / "a" / "metrics.json").read_text())
    assert [r["spp"] for r in rows] == [3, 3]
    assert "rendering 3 spp, the sample_count of the scene's sampler" in err, err
    code, _, err = run(["compare", scene, "--methods", "hard", "--repeats", "1",
                        "--spp", "1", "--out", tmp_path / "b"], capsys)
    rows = json.loads((tmp_path / "b" / "metrics.json").read_text())
    assert code == 0 and [r["spp"] for r in rows] == [1, 1] and "sample_count" not in err
    code, _, err = run(["sweep", scene, "--grid", "method=hard", "--repeats", "1",
                        "--out", tmp_path / "s"], capsys)
    assert code == 0, err
    assert [r["spp"] for r in json.loads((tmp_path / "s" / "sweep.json").read_text())] == [3]
    code, _, err = run(["compare", SCENES / "spot_sphere_box.xml", "--param", "spp=2",
                        "--width", "16", "--height", "16", "--methods", "hard",
                        "--repeats", "1", "--out", tmp_path / "c"], capsys)
    rows = json.loads((tmp_path / "c" / "metrics.json").read_text())
    assert code == 0 and [r["spp"] for r in rows] == [2, 2], err


def test_cuda_variant_without_a_gpu_says_so(capsys):
    """``--variant cuda_ad_rgb`` without a CUDA GPU passed on Dr.Jit's advice for C++ users,
    "Make sure to call jit_init(JitBackend::CUDA) to properly initialize this backend"."""
    import drjit as dr
    if dr.has_backend(dr.JitBackend.CUDA):
        pytest.skip("a CUDA GPU is present")
    code, out, err = run(["--variant", "cuda_ad_mono", "--methods", "hard"], capsys)
    assert code == 2 and "Traceback" not in err and "jit_init" not in err
    assert "'cuda_ad_mono' cannot be set on this machine" in err
    assert "no CUDA GPU" in err and "llvm_ad_mono" in err


def test_ref_shadow_rays_sets_the_converged_references_image_only(capsys):
    """``--ref-shadow-rays`` said "shadow rays of the converged reference"; they are its
    image's: the visibility AOVs every vis_* metric is scored on average 1024 light
    samples whatever it is. The help now says so, and it holds."""
    from mi_shadowmap import scenes
    scene = harness.load_scene(scenes.default_scene(width=16, height=16, light="area"))
    runs = [harness.compare(scene, methods=["hard:resolution=64"], spp=2, repeats=1,
                            measure_cached=False, ref_shadow_rays=n) for n in (1, 16)]
    assert runs[0][1].metrics["vis_rmse"] == runs[1][1].metrics["vis_rmse"]
    assert runs[0][1].metrics["img_rmse"] != runs[1][1].metrics["img_rmse"]
    assert cli.main(["compare", "--help"]) == 0
    text = " ".join(capsys.readouterr().out.split())
    assert "--ref-shadow-rays" in text
    help_ = text.rsplit("--ref-shadow-rays REF_SHADOW_RAYS", 1)[1]   # its entry, not usage
    assert "image" in help_ and "visibility AOVs average 1024 light samples" in help_


def test_every_option_says_what_it_does():
    """Each option of each command has a help text (``sweep --seed`` and ``tune --seed``
    had none: ``--seed SEED`` alone in ``--help``)."""
    parser = cli.build_parser()
    sub = next(a for a in parser._actions if a.choices and "compare" in a.choices)
    bare = [f"{name} {opt.option_strings[-1]}" for name, p in sub.choices.items()
            for opt in p._actions if opt.option_strings and not opt.help]
    assert not bare, f"options without help: {bare}"
