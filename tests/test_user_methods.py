"""User-defined methods (issue 10): a lookup registered with ``mi_shadowmap.register_method``
is usable everywhere a built-in is -- dict scenes and XML, ``compare``, ``sweep``, the CLI
(``--plugin``), every variant -- with the same property validation."""
import inspect
import json
import subprocess
import sys

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

import mi_shadowmap
from mi_shadowmap import cli, harness, methods
from mi_shadowmap.filters.common import receiver, tap_lit
from mi_shadowmap.options import OptionError
from mi_shadowmap.scenes import default_scene

SMALL = dict(width=32, height=32)


# --------------------------------------------------------------------------- the method
def box4(smap, lk, opts, active):
    """2x2-tap PCF: four nearest-texel compares ``spread`` texels apart, averaged."""
    r = receiver(smap, lk, opts)
    xy = r.uv * smap.resolution
    vis = mi.Float(0.0)
    for dx, dy in ((-0.5, -0.5), (0.5, -0.5), (-0.5, 0.5), (0.5, 0.5)):
        tap = xy + mi.Point2f(dx * opts.spread, dy * opts.spread)
        vis += dr.select(tap_lit(smap, r, r.face, tap, active=active & r.inside), 0.25, 0.0)
    return dr.select(r.inside, vis, 1.0)


SPREAD = mi_shadowmap.Prop("spread", "float", 1.0, "Distance between the taps, in texels.",
                           lo=0.0, hi=16.0)


def copy_hard(smap, lk, opts, active):
    """``hard``, reading the depth from the user layer ``depth_copy``."""
    r = receiver(smap, lk, opts)
    z = dr.gather(mi.Float, smap.extra["depth_copy"], smap.texel_index(r.face, r.uv),
                  active & r.inside)
    return dr.select(~r.inside | (r.depth <= z), 1.0, 0.0)


@pytest.fixture(scope="module", autouse=True)
def user_methods():
    """Registered for this module's tests only; other tests never see them."""
    records = [mi_shadowmap.register_method("box4", box4, properties=[SPREAD],
                                            summary="2x2-tap PCF (a test's user method)"),
               mi_shadowmap.register_method(
                   "copy_hard", copy_hard,
                   layers={"depth_copy": lambda scene, smap: mi.Float(smap.depth)})]
    yield records
    for r in records:
        mi_shadowmap.unregister_method(r.name)
    assert "box4" not in mi_shadowmap.METHODS and "copy_hard" not in harness.available_methods()


def render(scene, **props):
    integrator = mi.load_dict({"type": "shadowmap", **props})
    img = np.asarray(mi.render(scene, integrator=integrator, spp=2, seed=0))
    return img, img[..., -1]   # one emitter: its visibility AOV is the last channel


# --------------------------------------------------------------------------- tests
def test_registered_like_a_builtin(user_methods):
    box = user_methods[0]
    assert isinstance(box, mi_shadowmap.Method) and not box.builtin
    assert methods.get("box4") is box
    assert "box4" in harness.default_methods() and "box4" in harness.map_methods()
    assert harness.users_of("spread") == ["box4"]
    with pytest.raises(ValueError, match="already exists"):
        mi_shadowmap.register_method("box4", box4)
    with pytest.raises(ValueError, match="built-in"):
        mi_shadowmap.register_method("hard", box4, replace=True)


def test_renders_through_a_dict_scene():
    scene = mi.load_dict(default_scene(**SMALL))
    img, vis = render(scene, method="box4", spread=1.5, resolution=128)
    assert img.shape == (32, 32, 4) and np.isfinite(img).all()
    assert 0 <= vis.min() and vis.max() <= 1
    assert 0 < np.mean(vis < 1) < 1                      # a shadow, not everything
    assert np.any((vis > 0) & (vis < 1))                 # filtered: partial visibility
    _, hard = render(scene, method="hard", resolution=128)
    _, box0 = render(scene, method="box4", spread=0.0, resolution=128)
    assert np.mean(np.abs(box0 - hard) > 1e-6) < 0.01    # four taps on one texel: hard


def test_xml_scene():
    scene = mi.load_dict(default_scene(**SMALL))
    integrator = mi.load_string(
        '<integrator type="shadowmap" version="3.0.0">'
        '<string name="method" value="box4"/><float name="spread" value="2"/>'
        '<integer name="resolution" value="64"/></integrator>')
    assert integrator.opts.spread == 2.0 and integrator.opts.record.name == "box4"
    assert np.isfinite(np.asarray(mi.render(scene, integrator=integrator, spp=1))).all()


def test_appears_in_compare():
    scene = mi.load_dict(default_scene(**SMALL))
    results = harness.compare(scene, methods=["hard", "box4", "box4:spread=3"], spp=2,
                              resolution=128, spread=0.5)
    assert [r.name for r in results[1:]] == ["hard resolution=128",
                                             "box4 resolution=128 spread=0.5",
                                             "box4 resolution=128 spread=3"]
    for r in results[1:]:
        assert r.texels == 128 * 128 and r.metrics["vis_misclassified"] < 0.05
    assert "box4 resolution=128 spread=3" in harness.format_table(results)


def test_layers_are_built_and_cached():
    scene = mi.load_dict(default_scene(**SMALL))
    res = harness.compare(scene, methods=["hard", "copy_hard"], spp=1, resolution=64)
    hard, copy = res[1:]
    assert copy.texels == 2 * hard.texels == 2 * 64 * 64   # the depth and its copy
    np.testing.assert_array_equal(copy.visibility["spot"], hard.visibility["spot"])
    maps = harness.prepare_maps(scene, ["copy_hard"], resolution=16)
    assert maps[0].layers() == ["depth", "depth_copy"]
    np.testing.assert_array_equal(maps[0].to_numpy("depth_copy"), maps[0].to_numpy())


def test_sweep():
    scene = mi.load_dict(default_scene(**SMALL))
    table = harness.sweep(scene, [{"method": ["hard", "box4"], "spread": [0.5, 2.0],
                                   "resolution": 64}, {"method": "raytraced", "spp": 1}],
                          spp=1, repeats=1, ref_spp=4, progress=False)
    assert [r["name"] for r in table] == ["hard resolution=64 spp=1",
                                          "box4 resolution=64 spp=1 spread=0.5",
                                          "box4 resolution=64 spp=1 spread=2.0",
                                          "raytraced spp=1"]


@pytest.mark.parametrize("props, match", [
    ({"method": "box4", "sprad": 1.0}, "sprad"),                   # unknown property
    ({"method": "box4", "spread": "wide"}, "spread"),              # wrong type
    ({"method": "box4", "spread": True}, "spread"),                # booleans are no numbers
    ({"method": "box4", "spread": 17.0}, "spread"),                # out of range
    ({"method": "box4", "num_samples": 4}, "num_samples"),         # another method's
    ({"method": "hard", "spread": 1.0}, "used by: box4"),
    ({"method": "box4", "shadow_rays": 2}, "shadow_rays"),
])
def test_bad_input_names_the_property(props, match):
    """The same checks as the built-ins, through every entry point."""
    with pytest.raises(OptionError, match=match):
        mi_shadowmap.options.parse_options(props)
    with pytest.raises(Exception, match=match):
        mi.load_dict({"type": "shadowmap", **props})
    with pytest.raises(OptionError, match=match):   # before the (missing) scene loads
        harness.compare("/nonexistent/scene.xml", methods=[props], spp=1)
    with pytest.raises(OptionError, match=match):
        harness.expand_grid({k: [v] if k != "method" else v for k, v in props.items()})


@pytest.mark.parametrize("variant", ["llvm_ad_mono", "llvm_ad_spectral"])
def test_other_variant(variant):
    if variant not in mi.variants():
        pytest.skip(f"{variant} is not built")
    mi.set_variant(variant)
    scene = mi.load_dict(default_scene(**SMALL))
    img, vis = render(scene, method="box4", spread=1.5, resolution=128)
    n_colour = 1 if variant.endswith("mono") else 3               # spectral films give RGB
    assert img.shape == (32, 32, n_colour + 1) and np.isfinite(img).all()
    results = harness.compare(scene, methods=["box4"], spp=1, resolution=128)
    assert results[1].image.shape == (32, 32, 3)                  # repeated to grey RGB
    assert results[1].metrics["vis_misclassified"] < 0.05


# --------------------------------------------------------------------------- the CLI
def plugin_file(tmp_path, name):
    """A plugin file with :func:`box4`'s source, registering it as ``name``."""
    path = tmp_path / f"{name}.py"
    path.write_text("import drjit as dr\nimport mitsuba as mi\n\nimport mi_shadowmap\n"
                    "from mi_shadowmap.filters.common import receiver, tap_lit\n\n\n"
                    + inspect.getsource(box4)
                    + f"\n\nmi_shadowmap.register_method({name!r}, box4, properties=[\n"
                    "    mi_shadowmap.Prop('spread', 'float', 1.0, 'Tap distance, texels.',"
                    " lo=0.0, hi=16.0)])\n")
    return path


def test_cli_plugin(tmp_path, capsys):
    path = plugin_file(tmp_path, "box4_plugin")
    try:
        code = cli.main(["compare", "--plugin", str(path), "--methods", "hard",
                         "box4_plugin:spread=2", "--width", "24", "--height", "24",
                         "--spp", "1", "--repeats", "1", "--set", "resolution=64",
                         "--out", str(tmp_path / "out")])
        out, err = capsys.readouterr()
        assert code == 0, err
        rows = json.loads((tmp_path / "out" / "metrics.json").read_text())
        assert [r["name"] for r in rows[1:]] == ["hard resolution=64",
                                                "box4_plugin resolution=64 spread=2"]
        assert "box4_plugin" in out
    finally:
        if "box4_plugin" in mi_shadowmap.METHODS:
            mi_shadowmap.unregister_method("box4_plugin")


def test_cli_plugin_fresh_process(tmp_path):
    """As a user runs it: the plugin before the command, the user property in --grid."""
    path = plugin_file(tmp_path, "my_filter")
    p = subprocess.run([sys.executable, "-m", "mi_shadowmap.cli", "--plugin", str(path),
                        "sweep", "--width", "16", "--height", "16", "--spp", "1",
                        "--repeats", "1", "--grid", "method=my_filter spread=0.5,2",
                        "--set", "resolution=32", "--out", str(tmp_path / "sw")],
                       capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stderr
    rows = json.loads((tmp_path / "sw" / "sweep.json").read_text())
    assert [r["name"] for r in rows] == ["my_filter resolution=32 spp=1 spread=0.5",
                                         "my_filter resolution=32 spp=1 spread=2"]
    p = subprocess.run([sys.executable, "-m", "mi_shadowmap.cli", "compare", "--plugin",
                        str(path), "--methods", "my_filter:spred=2"],
                       capture_output=True, text=True, timeout=600)
    assert p.returncode == 2 and p.stderr.count("\n") == 1 and "spred" in p.stderr


@pytest.mark.parametrize("value", [float("nan"), 2.0, -1.0])
def test_a_lookup_outside_zero_one_is_an_error_naming_the_method(value):
    """A user lookup returning NaN (the film dropped those samples: a black image, AOV
    0), more than 1 (the image brighter) or less than 0 rendered without a word. The
    integrator now counts such values in a user method's render and raises after it,
    naming the method; a valid lookup renders as before. Built-in methods skip the
    count (their kernels are unchanged)."""
    name = "constant_visibility"
    mi_shadowmap.register_method(name, lambda smap, lk, opts, active, v=value: mi.Float(v))
    try:
        scene = mi.load_dict(default_scene(**SMALL))
        with pytest.raises(methods.MethodError,
                           match=rf"'{name}' returned \d+ visibility value\(s\) outside \[0, 1\]"):
            harness.render(scene, name, spp=1)
        mi_shadowmap.register_method(name, lambda smap, lk, opts, active: mi.Float(0.25),
                                     replace=True)
        _, img = harness.render(scene, name, spp=1)
        assert np.isfinite(img).all() and img[..., 3].max() == pytest.approx(0.25)
    finally:
        mi_shadowmap.unregister_method(name)


def test_a_lookup_returning_another_type_is_an_error_naming_the_method():
    """A lookup returning a ``mi.Vector3f`` failed inside Dr.Jit ("Could not construct
    from sequence"), naming nothing; a plain number is accepted."""
    name = "colour_visibility"
    mi_shadowmap.register_method(name, lambda smap, lk, opts, active: mi.Vector3f(1.0),
                                 virtual=True)
    try:
        scene = mi.load_dict(default_scene(**SMALL))
        for virtual in (True, False):
            with pytest.raises(methods.MethodError,
                               match=rf"'{name}': its lookup returned Vector3f"):
                harness.render(scene, {"method": name, "virtual": virtual}, spp=1)
        mi_shadowmap.register_method(name, lambda smap, lk, opts, active: 0.5, replace=True)
        _, img = harness.render(scene, name, spp=1)
        assert img[..., 3].max() == pytest.approx(0.5)
    finally:
        mi_shadowmap.unregister_method(name)


@pytest.mark.parametrize("kwargs, match", [
    ({"virtual": "no"}, "virtual must be True or False"),
    ({"uses_map": "false"}, "uses_map must be True or False"),
    ({"finalize": 5}, "finalize must be callable"),
    ({"layers_for": 5}, "layers_for must be callable"),
    ({"virtual_coarse_res": 512}, "virtual_coarse_res must be callable"),
    ({"virtual_edge": 2.0}, "virtual_edge must be callable"),
    ({"virtual_footprint": 1.0}, "virtual_footprint must be callable"),
    ({"bias_defaults": {"slope_bias": "x"}}, r"bias_defaults\['slope_bias'\] must be a finite"),
    ({"bias_defaults": {"normal_bias": float("nan")}}, "normal_bias.*finite"),
    ({"bias_defaults": {"slope_bias": -1.0}}, "slope_bias.*>= 0"),
    ({"bias_defaults": [1]}, "bias_defaults must be a dict"),
    ({"layers": ["a"]}, "layers must be a dict"),
    ({"layers": {"a": lambda scene, smap: None}, "layer_cost": {"a": float("inf")}},
     "layer_cost must map"),
    ({"view_properties": ("views",)}, "view_properties must be names of its own"),
    ({"view_properties": "views"}, "view_properties must be names of its own"),
])
def test_a_bad_record_is_refused_when_registered(kwargs, match):
    """Each was accepted and failed at render (an int called, a string multiplied inside
    a kernel, an overflow), rendered black (NaN biases), or was read as True ("no")."""
    with pytest.raises(methods.MethodError, match=match):
        mi_shadowmap.register_method("bad_record", lambda smap, lk, opts, active: 1.0,
                                     **kwargs)
    assert "bad_record" not in [m.name for m in methods.records()]


@pytest.mark.parametrize("kwargs, match", [
    ({"name": "type"}, "reserved"),
    ({"name": "spp"}, "reserved"),
    ({"name": "taps", "lo": 5, "hi": 1}, "no value could be set"),
    ({"name": "taps", "lo": float("nan")}, "lo must be a finite number"),
    ({"name": "taps", "lights": ("sun",)}, "lights must be .*'directional'"),
    ({"name": "taps", "lights": "point"}, "lights must be"),
])
def test_a_property_that_could_never_be_set_is_refused(kwargs, match):
    with pytest.raises(methods.MethodError, match=match):
        mi_shadowmap.Prop(kind="float", default=None, doc="Taps.", **kwargs)


@pytest.mark.parametrize("prop", [
    mi_shadowmap.Prop("taps", "int", 100, "Taps.", lo=1, hi=10),
    mi_shadowmap.Prop("taps", "int", "abc", "Taps."),
    mi_shadowmap.Prop("mode", "str", "z", "Mode.", choices=("a", "b")),
])
def test_a_property_whose_default_breaks_its_own_rules_is_refused(prop):
    """``register_method`` took a Prop whose default was out of its own range, of the
    wrong type or not among its choices; every spec then validated with it."""
    with pytest.raises(methods.MethodError, match=f"default .* of property '{prop.name}'"):
        mi_shadowmap.register_method("bad_default", lambda smap, lk, opts, active: 1.0,
                                     properties=[prop])
    assert "bad_default" not in [m.name for m in methods.records()]


def test_needs_curvature_gives_the_lookup_the_normals_derivatives():
    """A user lookup registered with ``needs_curvature`` reads ``lk.si.dn_du`` (the
    camera hits are intersected with ``mi.RayFlags.dNSdUV``): 1 / r on a sphere of
    radius 2, seen as the visibility AOV; without it the derivatives are 0."""
    def curv(smap, lk, opts, active):
        k = dr.norm(lk.si.dn_du) / dr.maximum(dr.norm(lk.si.dp_du), 1e-30)
        return dr.clip(k, 0.0, 1.0)
    T = mi.ScalarTransform4f
    scene = mi.load_dict({
        "type": "scene",
        "sensor": {"type": "perspective", "fov": 20, "film": {"type": "hdrfilm", "width": 8,
                                                              "height": 8},
                   "to_world": T().look_at(origin=[0, 0, 10], target=[0, 0, 0], up=[0, 1, 0])},
        "ball": {"type": "sphere", "radius": 2.0},
        "light": {"type": "point", "position": [0, 0, 5]}})
    got = {}
    for flag in (True, False):
        name = f"curv_{str(flag).lower()}"
        methods.register_method(name, curv, needs_curvature=flag, replace=True)
        try:
            img = np.asarray(mi.render(scene, integrator=mi.load_dict(
                {"type": "shadowmap", "method": name, "resolution": 64}), spp=1))
        finally:
            mi_shadowmap.unregister_method(name)
        got[flag] = img[2:6, 2:6, -1]
    assert np.allclose(got[True], 0.5, atol=1e-3) and np.all(got[False] == 0.0)


def test_layers_of_one_name_from_two_builders_are_not_shared_in_the_cache():
    """The map cache kept layers by name: a user method whose layer is also called
    'extra' read another's cached 'extra' (0.25 instead of 0.75), a method registered
    again with replace=True kept its first builder's layer, and a user layer named
    'vsm_m1' turned the built-in vsm black on that scene."""
    def const(value):
        return lambda scene, smap: dr.full(mi.Float, value, dr.width(smap.depth))

    def read_extra(smap, lk, opts, active):
        return dr.gather(mi.Float, smap.extra["extra"], 0, active)

    def read_m1(smap, lk, opts, active):
        return dr.gather(mi.Float, smap.extra["vsm_m1"], 0, active)

    scene = mi.load_dict(default_scene(width=8, height=8))
    integ = {"method": "vsm", "resolution": 64}
    ref = np.asarray(mi.render(scene, integrator=mi.load_dict(
        {"type": "shadowmap", **integ}), spp=1))
    names = []
    try:
        for name, value in (("quarter", 0.25), ("three_quarters", 0.75)):
            names.append(mi_shadowmap.register_method(name, read_extra,
                                                      layers={"extra": const(value)}).name)
        names.append(mi_shadowmap.register_method(
            "moment_copy", read_m1, layers={"vsm_m1": const(0.0)}).name)

        def lit(method):
            img = np.asarray(mi.render(scene, integrator=mi.load_dict(
                {"type": "shadowmap", "method": method, "resolution": 64}), spp=1))
            return img[..., 3][img[..., 3] > 0]      # the points the spot lights

        assert np.allclose(lit("quarter"), 0.25) and np.allclose(lit("three_quarters"), 0.75)
        mi_shadowmap.register_method("quarter", read_extra, layers={"extra": const(0.5)},
                                     replace=True)
        assert np.allclose(lit("quarter"), 0.5)
        mi.render(scene, integrator=mi.load_dict(      # caches its own 'vsm_m1'
            {"type": "shadowmap", "method": "moment_copy", "resolution": 64}), spp=1)
        after = np.asarray(mi.render(scene, integrator=mi.load_dict(
            {"type": "shadowmap", **integ}), spp=1))
        np.testing.assert_array_equal(after, ref)
    finally:
        for n in names:
            mi_shadowmap.unregister_method(n)


def test_a_virtual_method_cannot_give_its_own_builder_for_a_layer_virtual_maps_build():
    """Virtual maps build 'second_depth' and 'pcss_near' themselves: a user's own
    builder of that name was silently replaced by the built-in one on virtual maps
    (and used on full maps)."""
    from mi_shadowmap.depth_maps import second_depth_layer

    def look(smap, lk, opts, active=True):
        return mi.Float(1.0)
    with pytest.raises(methods.MethodError, match="second_depth.*themselves"):
        mi_shadowmap.register_method("own_second", look, virtual=True,
                                     layers={"second_depth": lambda scene, smap: smap.depth})
    rec = mi_shadowmap.register_method("builtin_second", look, virtual=True,
                                       layers={"second_depth": second_depth_layer})
    try:
        assert rec.layers["second_depth"] is second_depth_layer
    finally:
        mi_shadowmap.unregister_method("builtin_second")
    mi_shadowmap.register_method("own_second_full", look, virtual=False,
                                 layers={"second_depth": lambda scene, smap: smap.depth})
    mi_shadowmap.unregister_method("own_second_full")


def test_every_error_a_user_can_catch_is_a_top_level_name():
    """Every exception the package raises at a user (a rejected method record, property,
    emitter, variant, tuner input, missing libLLVM) is importable from ``mi_shadowmap``
    itself: ``except mi_shadowmap.MethodError`` needs no knowledge of the internal module
    that raises it."""
    import importlib
    from mi_shadowmap import light_views, variants, _llvm
    tune = importlib.import_module("mi_shadowmap.tune")   # the name is the function
    expected = {"MethodError": methods.MethodError, "OptionError": methods.OptionError,
                "UnsupportedEmitterError": light_views.UnsupportedEmitterError,
                "UnsupportedVariantError": variants.UnsupportedVariantError,
                "TuneError": tune.TuneError, "LLVMNotFoundError": _llvm.LLVMNotFoundError}
    for name, cls in expected.items():
        assert getattr(mi_shadowmap, name) is cls, name
    with pytest.raises(mi_shadowmap.MethodError):
        mi_shadowmap.register_method("hard", lambda smap, lk, opts, active: mi.Float(1.0))
