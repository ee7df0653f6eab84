"""``visibility_aovs=false``: a render a Mitsuba user writes like any other.

With the visibility AOVs (the default) ``mi.render(scene)`` returns the film's channels
plus one ``vis_<emitter>`` per light, which Mitsuba's ``mi.util.write_bitmap`` writes as
alpha (one light) or refuses for a PNG (two lights: "channel count (5) does not match
pixel format (rgb)"). With the property false the image holds the film's channels only,
the colour unchanged; everything that scores or writes the AOVs refuses it.
"""
import contextlib
import warnings

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

import mi_shadowmap
from mi_shadowmap import cli, harness
from mi_shadowmap.options import OptionError, parse_options
from mi_shadowmap.scenes import default_scene


def two_lights(spp=1, width=24, height=16, **film):
    """The built-in scene with its spot and a point light."""
    d = default_scene(width=width, height=height, spp=spp, light="spot")
    d["point"] = {"type": "point", "position": [2.0, 3.0, 1.0],
                  "intensity": {"type": "rgb", "value": 20.0}}
    d["sensor"]["film"].update(film)
    return mi.load_dict(d)


@contextlib.contextmanager
def one_thread():
    """Kernels on the calling thread (bit-identity). Not around ``write_bitmap``: Mitsuba
    3.9's ``Bitmap.write`` of an EXR hangs under ``dr.set_thread_count(1)`` (a futex
    wait with no CPU time; an 8 x 8 image too, a PNG does not)."""
    before = dr.thread_count()
    dr.set_thread_count(1)
    try:
        yield
    finally:
        dr.set_thread_count(before)


def render_both(scene, method, spp, seed=3, **props):
    """``(default image, image without the AOVs, their integrators)``, maps rebuilt by
    each (``cache_maps=false``: the texels each built are comparable), one thread."""
    props = {"type": "shadowmap", "method": method, **props}
    if method != "raytraced":
        props["cache_maps"] = False
    on = mi.load_dict(props)
    off = mi.load_dict({**props, "visibility_aovs": False})
    with one_thread():
        img_on = np.asarray(mi.render(scene, integrator=on, spp=spp, seed=seed))
        img_off = np.asarray(mi.render(scene, integrator=off, spp=spp, seed=seed))
    return img_on, img_off, on, off


def ulps(a, b) -> np.ndarray:
    """Distance in float32 units in the last place, elementwise (same-sign values)."""
    return np.abs(a.view(np.int32).astype(np.int64) - b.view(np.int32).astype(np.int64))


@pytest.mark.parametrize("method", ["hard", "pcf", "raytraced"])
def test_two_lights_without_aovs_the_film_channels_only(method, tmp_path):
    scene = two_lights()
    img_on, img_off, on, off = render_both(scene, method, spp=1)
    assert img_on.shape[-1] == 5 and on.aov_names() == ["vis_spot", "vis_point"]
    assert img_off.shape[-1] == 3 and off.aov_names() == []
    # one sample a pixel: the colour bit for bit
    assert np.array_equal(img_on[..., :3], img_off)
    if method != "raytraced":   # the same maps built
        assert on.stats["texels_built"] == off.stats["texels_built"] > 0
        assert on.stats["pages_built"] == off.stats["pages_built"]
    # Mitsuba's usual way of writing a render
    img = mi.render(scene, integrator=off, spp=1)
    for name in ("out.png", "out.exr"):
        mi.util.write_bitmap(str(tmp_path / name), img, write_async=False)
    exr = mi.Bitmap(str(tmp_path / "out.exr"))
    assert exr.pixel_format() == mi.Bitmap.PixelFormat.RGB
    assert np.array_equal(np.asarray(exr), np.asarray(img))
    assert mi.Bitmap(str(tmp_path / "out.png")).channel_count() == 3


@pytest.mark.parametrize("spp", [4, 16])
def test_several_samples_a_pixel_colour_within_a_few_ulps(spp):
    """With several samples a pixel Mitsuba 3.9's film sums them in another order when
    its block holds AOV channels: the colours differ by a few float32 ulps (measured
    here: up to 3 ulps, 1.2e-7, in a third to 60 % of the pixels; a Python integrator
    returning Mitsuba's direct's colour with and without two constant AOVs differs
    alike), never more."""
    img_on, img_off, _, _ = render_both(two_lights(spp=spp), "pcf", spp=spp)
    assert ulps(img_on[..., :3], img_off).max() <= 4
    assert np.abs(img_on[..., :3] - img_off).max() <= 3e-7


def test_film_with_alpha_keeps_its_alpha():
    scene = two_lights(pixel_format="rgba")
    img_on, img_off, _, _ = render_both(scene, "hard", spp=1)
    assert img_on.shape[-1] == 6 and img_off.shape[-1] == 4
    assert np.array_equal(img_on[..., :4], img_off)


@pytest.mark.parametrize("variant, colour", [("llvm_ad_mono", 1), ("llvm_ad_spectral", 3)])
def test_mono_and_spectral(variant, colour, tmp_path):
    mi.set_variant(variant)
    d = default_scene(width=24, height=16, spp=1, light="spot")
    d["point"] = {"type": "point", "position": [2.0, 3.0, 1.0], "intensity": {"type": "uniform",
                                                                            "value": 20.0}}
    scene = mi.load_dict(d)
    img_on, img_off, on, off = render_both(scene, "hard", spp=1)
    assert img_on.shape[-1] == colour + 2 and img_off.shape[-1] == colour
    assert np.array_equal(img_on[..., :colour], img_off)
    mi.util.write_bitmap(str(tmp_path / "out.exr"), mi.render(scene, integrator=off, spp=1),
                         write_async=False)
    assert mi.Bitmap(str(tmp_path / "out.exr")).channel_count() == colour


@pytest.mark.parametrize("value", [0, 1, "false", 0.0])
def test_wrong_type_names_the_property(value):
    with pytest.raises(OptionError, match="property 'visibility_aovs' must be a boolean"):
        parse_options({"method": "pcf", "visibility_aovs": value})
    with pytest.raises(RuntimeError, match="visibility_aovs"):
        mi.load_dict({"type": "shadowmap", "visibility_aovs": value})


def test_every_method_takes_it():
    from mi_shadowmap.options import METHODS
    for method in METHODS:
        assert parse_options({"method": method, "visibility_aovs": False}).visibility_aovs \
            is False
        assert parse_options({"method": method}).visibility_aovs is True


def test_nested_in_aov_without_them_warns_nothing():
    """Mitsuba's aov around it: its own channels and the colour, no visibility AOVs and
    no warning that they are missing."""
    scene = two_lights()
    outer = mi.load_dict({"type": "aov", "aovs": "dd:depth",
                          "inner": {"type": "shadowmap", "visibility_aovs": False}})
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with one_thread():
            img = np.asarray(mi.render(scene, integrator=outer, spp=1))
    assert img.shape[-1] == 3 + 1


REFUSED = "property 'visibility_aovs' = false"


def test_the_harness_refuses_it_before_rendering(monkeypatch):
    def no_render(*args, **kwargs):
        raise AssertionError("rendered")
    monkeypatch.setattr(mi, "render", no_render)
    scene = two_lights()
    with pytest.raises(OptionError, match=REFUSED):
        harness.compare(scene, methods=["hard"], visibility_aovs=False)
    with pytest.raises(OptionError, match=REFUSED):
        harness.compare(scene, methods=["hard:visibility_aovs=false"])
    with pytest.raises(OptionError, match=REFUSED):
        harness.sweep(scene, grid={"method": ["hard"], "visibility_aovs": [True, False]})
    with pytest.raises(OptionError, match=REFUSED):
        harness.run_method(scene, "hard", visibility_aovs=False)
    with pytest.raises(OptionError, match=REFUSED):
        harness.render(scene, "hard", visibility_aovs=False)
    with pytest.raises(OptionError, match=REFUSED):
        harness.prepare_maps(scene, ["hard"], visibility_aovs=False)
    with pytest.raises(OptionError, match=REFUSED):
        mi_shadowmap.tune(scene, 0.05, methods=["hard"], visibility_aovs=False)
    # true (the default) is taken as given
    assert harness.method_spec("hard", {"visibility_aovs": True})["visibility_aovs"] is True


def test_cli_refuses_it_in_one_line(tmp_path, capsys):
    out_dir = tmp_path / "never"
    code = cli.main(["compare", "--width", "16", "--height", "16", "--spp", "1",
                     "--set", "visibility_aovs=false", "--out", str(out_dir)])
    err = capsys.readouterr().err
    assert code == 2 and len(err.strip().splitlines()) == 1 and REFUSED in err
    assert not out_dir.exists()


def test_cli_keeps_them_on_over_a_scene_file_that_sets_false(tmp_path, capsys):
    """A scene file's integrator with visibility_aovs=false (for a plain mi.render of the
    file) is not taken by the commands, with a note; its other properties are."""
    xml = tmp_path / "scene.xml"
    xml.write_text("""<scene version="3.0.0">
  <integrator type="shadowmap">
    <boolean name="visibility_aovs" value="false"/>
    <float name="slope_bias" value="1.5"/>
  </integrator>
  <sensor type="perspective"><transform name="to_world"><lookat origin="0, 3, 4"
    target="0, 0, 0" up="0, 1, 0"/></transform>
    <film type="hdrfilm"><integer name="width" value="8"/>
    <integer name="height" value="8"/></film></sensor>
  <shape type="rectangle"/>
  <emitter type="point"><point name="position" x="0" y="2" z="0"/></emitter>
</scene>""")
    scene = mi.load_file(str(xml))
    args = cli.build_parser().parse_args(["compare", str(xml)])
    base = cli.scene_integrator_base(args, scene)
    err = capsys.readouterr().err
    assert base == {"slope_bias": 1.5}
    assert "visibility_aovs=false, not taken" in err
    args = cli.build_parser().parse_args(["maps", str(xml)])
    assert cli.scene_integrator_base(args, scene) == {"slope_bias": 1.5}


def test_camera_moves_without_them_compile_nothing():
    """As at the default (test_virtual's camera-move tests): after the first move (the
    sensor's first ``to_world`` is a kernel literal) moves compile no kernel."""
    from mitsuba import ScalarTransform4f as T
    scene = two_lights(width=32, height=32)
    integ = mi.load_dict({"type": "shadowmap", "method": "pcf", "visibility_aovs": False})
    params = mi.traverse(scene)
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        dr.kernel_history()
        dr.eval(mi.render(scene, integrator=integ, spp=1))
        seen = {k["hash"] for k in dr.kernel_history() if k.get("type") == dr.KernelType.JIT}
        compiled = []
        for x in (0.25, 0.3, 0.35):
            params["sensor.to_world"] = T().look_at(origin=[x, 3.45, 4.85],
                                                    target=[0.3, 0.25, 0.0], up=[0, 1, 0])
            params.update()
            dr.eval(mi.render(scene, integrator=integ, spp=1))
            hashes = {k["hash"] for k in dr.kernel_history()
                      if k.get("type") == dr.KernelType.JIT}
            compiled.append(len(hashes - seen))
            seen |= hashes
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    assert compiled[1:] == [0, 0], "moving the camera compiled a new kernel"
