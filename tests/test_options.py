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
