"""Property parsing: every bad input names the property and the allowed values."""
import mitsuba as mi
import pytest

from mi_shadowmap.options import METHODS, OptionError, parse_options


def load(**props):
    return mi.load_dict({"type": "shadowmap", **props})


def test_defaults():
    o = parse_options({})
    assert o.method == "hard" and o.resolution is None and o.shadow_rays == 1  # None: automatic
    assert o.bias_world == 0.0 and o.slope_bias_texels == 1.0 and o.normal_bias_texels == 0.5


def test_integer_accepted_for_float():
    assert parse_options({"bias": 2}).bias == 2.0


@pytest.mark.parametrize("props, needle", [
    ({"resolutoin": 512}, "resolutoin"),
    ({"method": "shadowvolume"}, "shadowvolume"),
    ({"resolution": 0}, "resolution"),
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
    ({"environment": "ignore"}, "environment"),
    ({"method": "raytraced", "bias": 0.1}, "bias"),
    ({"method": "raytraced", "slope_bias": 2.0}, "slope_bias"),
    ({"method": "unshadowed", "normal_bias": 1.0}, "normal_bias"),
    ({"method": "pcf", "num_samples": 4, "min_samples": 8}, "min_samples.*num_samples"),
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
            parse_options({name: None})


def test_resolution_is_accepted_by_every_method():
    """Scene files pass $resolution whatever the method; non-map methods ignore it."""
    for method in METHODS:
        assert parse_options({"method": method, "resolution": 64}).resolution == 64


def test_every_method_has_a_lookup():
    from mi_shadowmap.filters import FILTERS
    assert set(METHODS) == set(FILTERS)


def test_readme_documents_every_property():
    """The README's property table lists every property the plugin accepts."""
    import pathlib
    from mi_shadowmap.options import PROPERTIES
    readme = (pathlib.Path(__file__).resolve().parents[1] / "README.md").read_text()
    missing = [p.name for p in PROPERTIES if f"| `{p.name}` |" not in readme]
    assert not missing, f"README property table lacks: {missing}"


def test_min_samples_default_follows_num_samples():
    assert parse_options({"method": "pcf", "num_samples": 1}).min_samples == 1
    assert parse_options({"method": "pcf"}).min_samples == 2
