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


def test_readme_method_table_is_methods_table():
    """The README says ``options.methods_table()`` prints its method table: the built-in
    rows are that table's, in its order (msm and evsm were in another order)."""
    import pathlib
    from mi_shadowmap import methods
    from mi_shadowmap.options import methods_table
    readme = (pathlib.Path(__file__).resolve().parents[1] / "README.md").read_text()
    builtin = {m.name for m in methods.records() if m.builtin}
    lines = methods_table().splitlines()
    lines = lines[:2] + [ln for ln in lines[2:] if ln.split("`")[1] in builtin]
    assert "\n".join(lines) + "\n" in readme


def test_min_samples_default_follows_num_samples():
    assert parse_options({"method": "pcf", "num_samples": 1}).min_samples == 1
    assert parse_options({"method": "pcf"}).min_samples == 2


def test_resolution_zero_means_automatic():
    """Scene files pass ``$resolution``; a default of 0 leaves it to the integrator."""
    assert parse_options({"resolution": 0}).resolution is None
    assert parse_options({"resolution": 0, "virtual": True}).resolution is None


def test_automatic_full_map_resolution_rounds_up_to_a_multiple_of_8():
    """``Options.map_resolution``: twice the film's larger side times the footprint
    factor (clamped to [0.5, 4]), rounded *up* to a multiple of 8, capped at 8192 and by
    the budget (mutation audit: rounding down went unnoticed, the suite's films being
    multiples of 4)."""
    opts = parse_options({"virtual": False})
    assert opts.map_resolution((33, 20), 1) == 72          # 66 -> 72
    assert opts.map_resolution((33, 20), 1, footprint=0.1) == 40   # 33 -> 40
    assert opts.map_resolution((33, 20), 1, footprint=100.0) == 264
    assert opts.map_resolution((5000, 20), 1) == 8192
    assert opts.map_resolution((33, 20), 6, budget=6 * 4 * 50 * 50) == 50   # the budget


# ------------------------------------------------------- the README's table against the code
_README_TYPES = {"string": "str", "integer": "int", "float": "float", "boolean": "bool"}
_README_AUTOMATIC = ("automatic", "derived", "none")


def _readme_property_rows() -> dict:
    """``{name: (type cell, default cell, meaning cell)}`` of the README's table of the
    integrator's properties."""
    import pathlib
    readme = (pathlib.Path(__file__).resolve().parents[1] / "README.md").read_text()
    rows, inside = {}, False
    for line in readme.splitlines():
        if line.startswith("| property | type | default | meaning |"):
            inside = True
            continue
        if inside and not line.startswith("|"):
            break
        if inside and not line.startswith("|---"):
            name, kind, default, meaning = [c.strip() for c in
                                            line.strip().strip("|").split(" | ", 3)]
            rows[name.strip("`")] = (kind, default, meaning)
    return rows


def _readme_value(text: str):
    text = text.strip().strip("`")
    if text in _README_AUTOMATIC:
        return None
    if text in ("true", "false"):
        return text == "true"
    try:
        return float(text)
    except ValueError:
        return text


def _readme_defaults(cell: str) -> dict:
    """A default cell, ``2`` or ``1 (`msm`, `evsm`), 2 (`vsm`)``: ``{method or None:
    value}`` (None: every method not named)."""
    import re
    out = {}
    for m in re.finditer(r"\s*([^,()]+?)\s*(?:\(([^)]*)\))?\s*(?:,|$)", cell):
        if not m.group(1):
            continue
        value = _readme_value(m.group(1))
        who = [w.strip().strip("`") for w in m.group(2).split(",")] if m.group(2) else [None]
        for w in who:
            assert w not in out, f"default cell {cell!r} names {w} twice"
            out[w] = value
    return out


def _code_default(method: str, prop):
    """The default of ``prop`` for ``method``: its declared one (None: automatic), the
    method's resolved texel biases, the integrator's own ``method``."""
    resolved = {"bias": "bias_world", "slope_bias": "slope_bias_texels",
                "normal_bias": "normal_bias_texels"}
    if prop.name == "method":
        return parse_options({}).method
    if prop.name in resolved:
        return getattr(parse_options({"method": method}), resolved[prop.name])
    return prop.default


def _num(x: float) -> str:
    return f"{x:g}".replace("e+0", "e").replace("e+", "e")


def test_readme_property_table_matches_the_parser():
    """Every row of the README's property table gives each method that accepts the
    property its type and default as the options parser has them, and its allowed values
    (choices, ranges). The table once gave ``slope_bias`` 1.0 / ``normal_bias`` 0.5 but
    for ``multiview``, where ``vsm`` and ``evsm`` default to 0.5 / 0.25 and
    ``second_depth`` to 0 / 0, and listed no ``vsm``, ``evsm``, ``msm`` as a ``method``."""
    from mi_shadowmap import methods
    from mi_shadowmap.options import all_properties, properties_for
    rows = _readme_property_rows()
    builtin = [m.name for m in methods.records() if m.builtin]
    problems = []
    for prop in all_properties():
        if prop.name not in rows:
            problems.append(f"{prop.name}: no row")
            continue
        kind, default, meaning = rows[prop.name]
        words = kind.split()
        want = "pair" if words[0] == "string" and len(words) > 1 else _README_TYPES.get(words[0])
        if want != prop.kind:
            problems.append(f"{prop.name}: README type {kind!r}, code {prop.kind!r}")
        defaults = _readme_defaults(default)
        for m in builtin:
            own = {p.name: p for p in properties_for(m)}
            if prop.name not in own:
                continue
            p = own[prop.name]
            doc = defaults.get(m, defaults.get(None, "missing"))
            code = _code_default(m, p)
            if isinstance(code, (int, float)) and not isinstance(code, bool) \
                    and isinstance(doc, float):
                same = abs(doc - code) <= 1e-12 * max(1.0, abs(code))
            else:
                same = doc == code
            if not same:
                problems.append(f"{prop.name} ({m}): README default {doc!r}, code {code!r}")
            if p.choices is not None:
                listed = [f"`{c}`" if isinstance(c, str) else str(c) for c in p.choices]
                missing = [c for c in listed if c not in meaning]
                if missing:
                    problems.append(f"{prop.name}: README lacks choices {missing}")
            elif p.kind in ("int", "float", "pair") and p.lo is not None:
                lo = _num(p.lo)
                if p.hi is not None:
                    hi = _num(p.hi) if p.hi < 2**20 else None
                    forms = ([f"{lo}..{hi}"] if not p.lo_open else []) + \
                        [f"> {lo} and <= {hi}"]
                    ok = hi is None or any(f in meaning for f in forms)
                else:
                    forms = [f"> {lo}"] if p.lo_open else [f">= {lo}", f"{lo} <="]
                    ok = any(f in meaning for f in forms)
                if not ok:
                    problems.append(f"{prop.name}: README gives no range {forms}")
    method_row = rows["method"][2]
    problems += [f"method: README lacks `{m}`" for m in builtin if f"`{m}`" not in method_row]
    problems = list(dict.fromkeys(problems))
    assert not problems, "README property table vs options:\n  " + "\n  ".join(problems)


def test_plugin_docstring_gives_each_methods_texel_bias_defaults():
    """The plugin docstring's table (``docs_table``) gives ``slope_bias`` and
    ``normal_bias`` defaults every method renders with: it said "1.0 (0 for
    second_depth)" and "0.5 (0 for second_depth)", where ``vsm`` and ``evsm`` use 0.5 /
    0.25 and ``multiview`` 2.0 / 0."""
    import re
    from mi_shadowmap import methods
    from mi_shadowmap.options import docs_table
    from mi_shadowmap.integrator import ShadowMapIntegratorMixin
    table = docs_table()
    assert table in ShadowMapIntegratorMixin.__doc__
    rows = {blk.split("\n", 1)[0]: blk for blk in table.split("   * - ")[1:]}
    for name, attr in (("slope_bias", "slope_bias_texels"),
                       ("normal_bias", "normal_bias_texels")):
        m = re.search(r"\(default: ([0-9.]+)(?: \(([^)]*)\))?;", rows[name])
        assert m, rows[name]
        own = dict(item.split(": ") for item in m.group(2).split(", ")) if m.group(2) else {}
        for rec in methods.records():
            if not rec.uses_map:
                continue
            code = getattr(parse_options({"method": rec.name}), attr)
            doc = float(own.get(rec.name, m.group(1)))
            assert doc == code, f"{name} of {rec.name}: docstring {doc}, code {code}"


def test_docs_name_the_methods_with_virtual_maps():
    """The README's ``virtual`` row and the property's docstring name exactly the
    built-in methods whose records read virtual maps."""
    import re
    from mi_shadowmap import methods
    from mi_shadowmap.options import _GENERAL
    builtin = {m.name for m in methods.records() if m.builtin}
    want = {m.name for m in methods.records() if m.builtin and m.virtual}
    row = _readme_property_rows()["virtual"][2]
    assert set(re.findall(r"`(\w+)`", row)) & builtin == want
    assert set(re.findall(r"\w+", _GENERAL["virtual"].doc)) & builtin == want


# ------------------------------------------------ the plugin docstring's table against the code
#: Values a documented bound needs beside it, as the docstring says: a virtual
#: resolution up to 2^30 (full maps stop at 65536), ``lod_bias`` -8 with 512^2 pages,
#: ``min_samples`` up to ``num_samples``.
_BOUND_COMPANIONS = {("resolution", "hi"): {"virtual": True},
                     ("lod_bias", "lo"): {"page_size": 512},
                     ("min_samples", "hi"): {"num_samples": 64}}


def _docstring_rows() -> list:
    """``[(name, kind, default text, range text, method or None)]`` of the parameter
    table in the integrator's own docstring (None: a shared row)."""
    import re
    from mi_shadowmap.integrator import ShadowMapIntegratorMixin
    doc = ShadowMapIntegratorMixin.__doc__
    assert ".. list-table::" in doc, "the plugin docstring has no parameter table"
    rows = []
    for blk in doc.split(".. list-table::", 1)[1].split("   * - ")[1:]:
        name, kind = blk.split("\n")[0].strip(), blk.split("\n")[1].strip()
        tail = blk[blk.rfind("(default: "):]     # the generated end of the row
        m = re.fullmatch(r"\(default: (.*?); ([^;]*?)(?:; (map methods|method: (\w+)))?\)\s*",
                         tail, re.S)
        assert m, f"row {name!r} of the plugin docstring gives no default and range"
        rows.append((name, kind.strip("-| "), m.group(1), m.group(2), m.group(4)))
    return rows


def _doc_value(kind: str, text: str):
    import ast
    return None if text == "automatic" else ast.literal_eval(text)


def test_plugin_docstring_table_matches_the_parser():
    """The parameter table of the integrator's docstring (Mitsuba plugin style) lists
    every property each method accepts, no other, and for each the type, default and
    allowed values that ``parse_options`` enforces: the default is what a method left at
    its defaults gets, both ends of a documented range are accepted and the values past
    them refused (naming the property), every documented choice is accepted and another
    refused, and a value of another type is refused."""
    import re
    from mi_shadowmap import methods
    from mi_shadowmap.options import GENERAL_PROPERTIES, SCOPES, EVERY, properties_for
    rows = _docstring_rows()
    general = {p.name for p in GENERAL_PROPERTIES}
    problems = []
    # which (property, method) pairs the table documents, against the parser's
    documented = set()
    for name, kind, dflt, rng, method in rows:
        if method is None:
            assert name in general, f"shared row {name!r} is no shared property"
            documented |= {(name, m.name) for m in methods.records()
                           if SCOPES[name] == EVERY or name in
                           {p.name for p in properties_for(m.name)}}
        else:
            documented.add((name, method))
    accepted = {(p.name, m.name) for m in methods.records() for p in properties_for(m.name)}
    problems += [f"{n} of {m}: accepted, not in the docstring" for n, m in accepted - documented]
    problems += [f"{n} of {m}: in the docstring, refused" for n, m in documented - accepted]
    for name, kind, dflt, rng, method in rows:
        targets = [method] if method else [m.name for m in methods.records()
                                           if (name, m.name) in accepted]
        own = {}
        mo = re.fullmatch(r"(\S+) \((.*)\)", dflt)
        if mo:      # "1.0 (second_depth: 0.0, vsm: 0.5)": per-method defaults
            dflt = mo.group(1)
            own = {k: float(v) for k, v in (i.split(": ") for i in mo.group(2).split(", "))}
        for m in targets:
            want = own.get(m, _doc_value(kind, dflt))
            if want is None:        # automatic: resolved per scene or method
                continue
            got = getattr(parse_options({"method": m} if name != "method" else {}), name)
            if name in ("slope_bias", "normal_bias"):
                got = getattr(parse_options({"method": m}), name + "_texels")
            if got != want:
                problems.append(f"{name} of {m}: docstring default {want!r}, parsed {got!r}")
        m0 = "hard" if "hard" in targets else targets[0]   # a map method for shared rows

        def ok(value, extra=()):
            try:
                parse_options({"method": m0, name: value, **dict(extra)})
                return True
            except OptionError as e:
                assert name in str(e), f"{name}={value!r}: the error does not name it: {e}"
                return False
        if name == "method":
            continue
        if rng.startswith("one of "):
            choices = [_doc_value(kind, c) for c in rng[len("one of "):].split(", ")]
            problems += [f"{name} of {m0}: choice {c!r} refused" for c in choices if not ok(c)]
            other = "not-a-choice" if kind == "str" else max(choices) + 1
            if ok(other):
                problems.append(f"{name} of {m0}: {other!r} accepted, not a documented choice")
            continue
        for op, bound in re.findall(r"(>=|>|<=) (\S+)", rng):
            b = float(bound) if kind in ("float", "pair") else int(bound)
            side = "lo" if op[0] == ">" else "hi"
            extra = _BOUND_COMPANIONS.get((name, side), {})
            step = 1 if kind == "int" else max(abs(b) * 1e-3, 1e-3)
            inside, past = (b, b - step) if op == ">=" else (b + step, b) if op == ">" else \
                (b, b + step)
            value = (lambda x: (x, x)) if kind == "pair" else (lambda x: x)
            if not ok(value(inside), extra.items()):
                problems.append(f"{name} of {m0}: {inside!r} refused, the docstring says {rng}")
            if ok(value(past), extra.items()):
                problems.append(f"{name} of {m0}: {past!r} accepted, the docstring says {rng}")
        wrong = {"int": "1", "float": "x", "bool": 1, "str": 3, "pair": "x"}[kind]
        if ok(wrong):
            problems.append(f"{name} of {m0}: {wrong!r} accepted for a {kind}")
    assert not problems, "plugin docstring vs options:\n  " + "\n  ".join(problems)


def test_plugin_docstring_prose_names_real_properties():
    """The hand-written part of the integrator's docstring names properties, methods and
    ``name=value`` settings: each property it names exists and each setting parses
    (a renamed or removed option fails here, not in a user's scene file)."""
    import re
    from mi_shadowmap import methods
    from mi_shadowmap.integrator import ShadowMapIntegratorMixin
    from mi_shadowmap.options import docs_table, known_names, methods_using
    prose = ShadowMapIntegratorMixin.__doc__.replace(docs_table(), "")
    mitsuba = {"emitter_samples", "bsdf_samples", "sampling_weight", "cutoff_angle"}
    record_fields = {f for f in methods.Method.__dataclass_fields__}
    names = {m.name for m in methods.records()}
    problems = []
    for token in re.findall(r"``([^`]+)``", prose):
        for item in re.split(r",\s*", token):
            m = re.fullmatch(r"(\w+)(?:=(.+))?", item.strip())
            if m is None or m.group(1) in names | mitsuba | record_fields:
                continue
            name, value = m.groups()
            if name not in known_names():
                if "_" in name:
                    problems.append(f"``{token}``: {name!r} is no property")
                continue
            if value is not None:
                value = value.strip("'")
                value = {"true": True, "false": False}.get(value, value)
                users = list(methods_using(name)) or ["hard"]
                try:
                    parse_options({"method": "hard" if "hard" in users else users[0],
                                   name: value})
                except OptionError as e:
                    problems.append(f"``{token}``: {e}")
    assert not problems, "plugin docstring prose:\n  " + "\n  ".join(problems)
