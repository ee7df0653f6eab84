"""Property parsing: every bad input names the property and the allowed values."""
import mitsuba as mi
import pytest

from mi_shadowmap.options import METHODS, OptionError, parse_options


def load(**props):
    return mi.load_dict({"type": "shadowmap", **props})


def test_defaults():
    o = parse_options({})
    assert o.method == "hard" and o.resolution is None   # None: automatic
    assert parse_options({"method": "raytraced"}).shadow_rays == 1
    assert o.bias_world == 0.0 and o.slope_bias_texels == 1.0 and o.normal_bias_texels == 0.5


def test_integer_accepted_for_float():
    assert parse_options({"bias": 2}).bias == 2.0


@pytest.mark.parametrize("props, needle", [
    ({"resolutoin": 512}, "resolutoin"),
    ({"method": "shadowvolume"}, "shadowvolume"),
    ({"resolution": -1}, "resolution"),
    ({"resolution": -5}, "resolution"),
    ({"resolution": 512.0}, "resolution"),
    ({"resolution": "512"}, "resolution"),
    ({"bias": -1.0}, "bias"),
    ({"bias": "small"}, "bias"),
    ({"bias": float("nan")}, "bias"),
    ({"slope_bias": True}, "slope_bias"),
    ({"hide_emitters": 1}, "hide_emitters"),
    ({"shadow_rays": 0}, "shadow_rays"),
    ({"method": "hard", "shadow_rays": 4}, "shadow_rays"),
    ({"method": "raytraced", "light_sample": "indep"}, "light_sample.*shared, independent"),
    ({"method": "raytraced", "light_sample": 1}, "light_sample"),
    ({"method": "pcf", "light_sample": "independent"}, "light_sample"),
    ({"environment": "ignore"}, "environment"),
    ({"method": "raytraced", "bias": 0.1}, "bias"),
    ({"method": "raytraced", "slope_bias": 2.0}, "slope_bias"),
    ({"method": "unshadowed", "normal_bias": 1.0}, "normal_bias"),
    ({"method": "pcf", "num_samples": 4, "min_samples": 8}, "min_samples.*num_samples"),
    ({"method": "pcf", "bias_range": "nan, nan"}, "bias_range.*finite"),
    ({"method": "pcf", "bias_range": "0, nan"}, "bias_range.*finite"),
    ({"method": "pcf", "bias_range": "0, inf"}, "bias_range.*finite"),
    ({"method": "pcf", "bias_range": "0, 1e400"}, "bias_range.*finite"),
])
def test_bad_values_name_the_property(props, needle):
    with pytest.raises(OptionError, match=needle):
        parse_options(props)
    with pytest.raises(RuntimeError, match=needle):   # and through Mitsuba's loader
        load(**props)


def test_unknown_method_lists_valid_ones():
    with pytest.raises(OptionError) as e:
        parse_options({"method": "nope"})
    for m in METHODS:
        assert m in str(e.value)


def test_unknown_property_in_xml():
    xml = """<scene version="3.0.0"><integrator type="shadowmap">
             <integer name="max_depth" value="3"/></integrator></scene>"""
    with pytest.raises(RuntimeError, match="max_depth"):
        mi.load_string(xml)


def test_xml_types_arrive_checked():
    xml = """<scene version="3.0.0"><integrator type="shadowmap">
             <string name="resolution" value="256"/></integrator></scene>"""
    with pytest.raises(RuntimeError, match="resolution.*integer"):
        mi.load_string(xml)


def test_none_only_where_a_default_is_automatic():
    assert parse_options({"resolution": None, "bias": None}).resolution is None
    for name in ("method", "shadow_rays", "hide_emitters", "environment"):
        with pytest.raises(OptionError, match=f"'{name}' has no automatic value"):
            parse_options({"method": "raytraced", name: None} if name != "method"
                          else {name: None})


def test_a_pair_takes_numbers_only():
    assert parse_options({"method": "pcf", "bias_range": "0, 0.5"}).bias_range == (0.0, 0.5)
    assert parse_options({"method": "pcf", "bias_range": (0, 1)}).bias_range == (0.0, 1.0)
    for bad in [(True, True), (0.0, float("inf")), (None, 1.0), ([0], 1)]:
        with pytest.raises(OptionError, match="bias_range"):
            parse_options({"method": "pcf", "bias_range": bad})


def test_resolution_is_accepted_by_every_method():
    """Scene files pass $resolution whatever the method; non-map methods ignore it."""
    for method in METHODS:
        assert parse_options({"method": method, "resolution": 64}).resolution == 64


def test_every_method_has_a_lookup():
    from mi_shadowmap import methods
    assert all(callable(methods.get(m).lookup) for m in METHODS)
    assert {"raytraced", "hard", "pcf", "pcss", "second_depth", "mdsm"} <= set(METHODS)


def test_reading_another_methods_property_names_it():
    with pytest.raises(AttributeError, match="'num_samples'.*'hard'"):
        parse_options({"method": "hard"}).num_samples


def test_per_method_defaults_of_a_shared_name():
    """pcf_samples is declared by second_depth (default 4) and mdsm (default 9)."""
    assert parse_options({"method": "second_depth"}).pcf_samples == 4
    assert parse_options({"method": "mdsm"}).pcf_samples == 9
    assert parse_options({"method": "second_depth"}).slope_bias_texels == 0.0
    assert parse_options({"method": "hard"}).slope_bias_texels == 1.0


def test_readme_documents_every_property():
    """The README's property table lists every property the plugin accepts."""
    import pathlib
    from mi_shadowmap.options import all_properties
    readme = (pathlib.Path(__file__).resolve().parents[1] / "README.md").read_text()
    missing = [p.name for p in all_properties() if f"| `{p.name}` |" not in readme]
    assert not missing, f"README property table lacks: {missing}"


def test_readme_has_a_row_for_every_builtin_method():
    """The README's method table has one row per built-in method record."""
    import pathlib
    from mi_shadowmap import methods
    readme = (pathlib.Path(__file__).resolve().parents[1] / "README.md").read_text()
    missing = [m.name for m in methods.records() if m.builtin
               and f"| `{m.name}` |" not in readme]
    assert not missing, f"README method table lacks: {missing}"


def test_min_samples_default_follows_num_samples():
    assert parse_options({"method": "pcf", "num_samples": 1}).min_samples == 1
    assert parse_options({"method": "pcf"}).min_samples == 2


def test_resolution_zero_means_automatic():
    """Scene files pass ``$resolution``; a default of 0 leaves it to the integrator."""
    assert parse_options({"resolution": 0}).resolution is None
    assert parse_options({"resolution": 0, "virtual": True}).resolution is None
