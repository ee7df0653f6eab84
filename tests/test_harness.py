"""The comparison harness: records, reference, validation before rendering, sweeps,
tables, and the specs derived from the method registry (public functions only)."""
import json
import math

import mitsuba as mi
import numpy as np
import pytest

from mi_shadowmap import harness, methods, metrics, options, tables
from mi_shadowmap.options import OptionError
from mi_shadowmap.scenes import default_scene

from conftest import SCENES

SMALL = dict(width=32, height=32)
TIME_KEYS = {"cold", "warm", "build", "shading", "jit", "compile", "cached"}


@pytest.fixture(scope="module")
def spot_results():
    scene = mi.load_dict(default_scene(**SMALL))
    return harness.compare(scene, spp=2, resolution=128)


def test_records_have_every_field(spot_results):
    names = harness.default_methods()
    assert [r.method for r in spot_results[1:]] == names   # every registered method
    assert spot_results[0].is_reference and spot_results[0].method == "raytraced"
    for r in spot_results:
        assert r.image.shape == (32, 32, 3) and np.isfinite(r.image).all()
        assert list(r.visibility) == ["spot"]
        v = r.visibility["spot"]
        assert v.shape == (32, 32) and v.min() >= 0 and v.max() <= 1
        assert set(r.times) == TIME_KEYS
        assert all(math.isfinite(t) and t >= 0 for t in r.times.values())
        assert r.times["build"] <= r.times["warm"]   # the build is part of the frame
        assert {"vis_rmse", "vis_misclassified", "vis_false_shadow", "vis_false_lit",
                "vis_penumbra_rmse", "img_psnr", "img_ssim", "img_flip"} <= set(r.metrics)
        assert set(r.metrics["per_emitter"]) == {"spot"}
        record = methods.get(r.method)
        if record.uses_map:   # one perspective face of 128^2 float32 texels, plus layers
            opts = options.parse_options({"method": r.method, "resolution": 128})
            names = record.layer_names(opts)   # (second_depth's: its layer, no first depth)
            if len(names) > (not methods.builds_first_depth(record, names)):
                # extra layers: more values (and bytes)
                assert r.texels > 128 * 128 and r.map_bytes > 4 * 128 * 128
            else:
                assert r.texels == 128 * 128 and r.map_bytes == 4 * r.texels
        else:
            assert r.texels == 0 and r.map_bytes == 0
        row = r.row()
        assert row["name"] == r.name and "vis_rmse[spot]" in row


def test_reference_scores_zero_against_itself(spot_results):
    m = spot_results[0].metrics
    assert m["vis_rmse"] == 0 and m["vis_misclassified"] == 0 and m["img_rmse"] == 0
    assert m["img_psnr"] == math.inf and m["img_ssim"] == pytest.approx(1.0)
    assert m["per_emitter"]["spot"]["rmse"] == 0


def test_unshadowed_never_adds_shadow(spot_results):
    """Visibility 1 everywhere the light contributes: no false shadow, and every
    reference-shadowed pixel that the light reaches is false lit."""
    r = next(r for r in spot_results if r.method == "unshadowed")
    ref = spot_results[0]
    assert r.metrics["vis_false_shadow"] == 0
    assert r.metrics["vis_false_lit"] > 0
    assert r.metrics["vis_false_lit"] == pytest.approx(
        np.mean((ref.vis_stack() < 0.5) & (r.vis_stack() >= 0.5)))


def test_pooled_and_per_emitter_metrics_two_lights():
    path = SCENES / "room_two_points.xml"
    res = harness.compare(str(path), methods=["hard"], spp=2, resolution=128,
                          scene_params=SMALL)
    ref, hard = res
    assert set(hard.visibility) == {"key", "fill"} and hard.texels == 2 * 6 * 128 * 128
    assert hard.map_bytes == 4 * hard.texels
    for label in ("key", "fill"):
        assert ref.metrics["per_emitter"][label]["rmse"] == 0
    per = hard.metrics["per_emitter"]
    # pooled RMSE^2 is the mean of the per-emitter RMSE^2 (same pixel count each)
    assert hard.metrics["vis_rmse"] ** 2 == pytest.approx(
        (per["key"]["rmse"] ** 2 + per["fill"]["rmse"] ** 2) / 2)


def test_per_method_parameters():
    scene = mi.load_dict(default_scene(**SMALL))
    res = harness.compare(scene, methods=[{"method": "hard", "resolution": 64},
                                          "hard:resolution=256"], spp=1)
    assert [r.texels for r in res[1:]] == [64 * 64, 256 * 256]
    assert [r.name for r in res[1:]] == ["hard resolution=64", "hard resolution=256"]
    # a coarser map is no more accurate here than a finer one
    assert res[1].metrics["vis_misclassified"] >= res[2].metrics["vis_misclassified"]


def test_none_means_automatic_in_specs_and_shared_keywords():
    """None (a Python caller's "automatic") reached Mitsuba's dict loader, which crashes
    the interpreter on a None value (a segmentation fault, no message)."""
    scene = mi.load_dict(default_scene(**SMALL))
    res = harness.compare(scene, methods=["hard", {"method": "hard", "resolution": None}],
                          spp=1, bias=None)
    assert res[1].texels == res[2].texels
    assert np.array_equal(res[1].vis_stack(), res[2].vis_stack())


def test_a_methods_own_spp_names_it_and_gets_a_reference_at_that_spp():
    """``hard`` at compare's 8 spp and at its own 4: the second is named with its spp
    (both were named ``hard``, and the second's files overwrote the first's), and it is
    scored against a reference at 4 spp with the same seed, as a compare at 4 spp scores
    it (it was scored against the 8-spp reference, its camera noise counted as error)."""
    scene = mi.load_dict(default_scene(**SMALL))
    res = harness.compare(scene, methods=["hard", "hard:spp=4"], spp=8)
    assert [r.name for r in res[1:]] == ["hard", "hard spp=4"]
    assert res[2].spp == 4 and res[2].metrics["reference_spp"] == 4
    assert "reference_spp" not in res[1].metrics
    alone = harness.compare(scene, methods=["hard"], spp=4)[1]
    for key in ("vis_rmse", "vis_misclassified", "img_rmse"):
        assert res[2].metrics[key] == pytest.approx(alone.metrics[key], rel=1e-6), key


def test_a_reference_with_its_own_spp_is_named_with_it():
    """``reference="raytraced:spp=8"`` was named "reference (raytraced)" in the table and
    its files, like the automatic reference at compare's spp."""
    scene = mi.load_dict(default_scene(width=8, height=8, spp=1))
    res = harness.compare(scene, methods=["hard"], reference="raytraced:spp=8", spp=1,
                          measure_cached=False)
    assert res[0].name == "reference (raytraced spp=8)" and res[0].spp == 8
    assert harness.compare(scene, methods=["hard"], spp=1,
                           measure_cached=False)[0].name == "reference (raytraced)"


def test_written_error_layers_are_against_the_reference_a_method_is_scored_against(tmp_path):
    """A method with its own spp is scored against a reference at that spp; its EXR's
    ``err_*`` and ``img_err`` layers and its heat map were against compare's reference
    (``raytraced:spp=2``: the table said RMSE 0, the layers held 0.0999)."""
    from mi_shadowmap import report
    scene = mi.load_dict(default_scene(**SMALL))
    res = harness.compare(scene, methods=["raytraced:spp=2", "hard"], spp=4)
    report.write_results(res, str(tmp_path))
    for r in res[1:]:
        layers = report.read_exr(str(tmp_path / f"{report.safe_name(r.name)}.exr"))
        err = np.stack([layers[f"err_{k}.Y"] for k in sorted(r.visibility)])
        assert float(np.sqrt(np.mean(err ** 2))) == pytest.approx(r.metrics["vis_rmse"],
                                                                  abs=1e-6), r.name
    assert res[1].metrics["vis_rmse"] == 0.0     # the same renders as its reference


@pytest.mark.parametrize("kwargs, match", [
    ({"methods": ["hard", "nope"]}, "nope"),
    ({"methods": ["hard"], "resolutoin": 64}, "resolutoin"),
    ({"methods": [{"method": "hard", "resolution": -1}]}, "resolution"),
    ({"methods": ["hard"], "shadow_rays": 4}, "shadow_rays"),   # used by no listed method
    ({"methods": [{"resolution": 64}]}, "method"),
    ({"methods": ["hard"], "reference": "raytraced:shadow_rayz=4"}, "shadow_rayz"),
    # a shared 'method' was dropped without a word: every spec has its own method
    ({"methods": ["hard"], "method": "pcf"}, "'method' = 'pcf' is not a shared property"),
])
def test_bad_input_rejected_before_rendering(kwargs, match):
    """Validation happens before the scene is even loaded: a missing scene file
    would otherwise be the error."""
    with pytest.raises(OptionError, match=match):
        harness.compare("/nonexistent/scene.xml", spp=1, **kwargs)


def test_missing_scene_file():
    with pytest.raises(FileNotFoundError, match="scene file not found"):
        harness.compare("/nonexistent/scene.xml", methods=["hard"], spp=1)


def test_has_area_lights():
    assert not harness.has_area_lights(mi.load_dict(default_scene(**SMALL)))
    assert harness.has_area_lights(mi.load_dict(default_scene(light="area", **SMALL)))


def test_environment_light_is_measured_against_the_converged_reference():
    """An environment's visibility AOV is the share of its light that arrives (about 0.45
    on an open floor under a uniform sky: the horizon hides half of it). The automatic
    reference was ``raytraced`` with one shadow ray per sample, whose AOV is then binary
    noise: here ``pcss``'s visibility RMSE against it was 0.21 and ``unshadowed`` looked
    better (0.15). Now an environment gets the converged reference: ``pcss`` 0.029,
    ``unshadowed`` 0.24 (measured, 32^2, 4 spp). (Misclassification at 0.5 means little
    here: the floor's true visibility sits just under it.)"""
    d = default_scene(**SMALL)
    d["sky"] = {"type": "constant", "radiance": 0.05}
    scene = mi.load_dict(d)
    assert harness.has_soft_lights(scene) and not harness.has_area_lights(scene)
    res = harness.compare(scene, methods=["pcss", "unshadowed"], spp=4, measure_cached=False)
    assert "converged" in res[0].name
    sky = [k for k in res[0].visibility if k != "spot"]
    assert len(sky) == 1
    ref = res[0].visibility[sky[0]]
    assert 0.2 < float(np.mean(ref[ref > 0])) < 0.8            # a fraction, not 0 or 1
    assert np.mean((ref > 0.02) & (ref < 0.98)) > 0.5
    pcss, unshadowed = (r.metrics["per_emitter"][sky[0]] for r in res[1:])
    print(f"sky: pcss RMSE {pcss['rmse']:.4f}, unshadowed {unshadowed['rmse']:.4f}")
    assert pcss["rmse"] <= 0.05
    assert unshadowed["rmse"] >= 4 * pcss["rmse"]


def test_expand_grid():
    specs = harness.expand_grid([{"method": ["hard", "raytraced"], "resolution": [64, 128],
                                  "shadow_rays": [1, 4]},
                                 {"method": "hard", "resolution": 64}], default_spp=2)
    hard = [s for s in specs if s["method"] == "hard"]
    rt = [s for s in specs if s["method"] == "raytraced"]
    assert len(hard) == 2 and all("shadow_rays" not in s for s in hard)   # dedup, not used
    # resolution is a depth-map setting: not combined with raytraced
    assert len(rt) == 2 and all("resolution" not in s for s in rt)
    assert all(s["spp"] == 2 for s in specs)


@pytest.mark.parametrize("grid, match", [
    ({"method": ["hard"], "resolutoin": [64]}, "resolutoin"),
    ({"method": ["hard"], "shadow_rays": [2]}, "shadow_rays"),
    ({"method": ["hard"], "resolution": [64, -1]}, "resolution"),
    ({"method": ["nope"]}, "nope"),
    ({"resolution": [64]}, "method"),
    ({"method": "raytraced", "spp": [0]}, "spp"),
    ([], "empty"),
])
def test_bad_grid_rejected_before_rendering(grid, match):
    with pytest.raises(OptionError, match=match):
        harness.sweep("/nonexistent/scene.xml", grid, progress=False)


def test_analyse_known_answers():
    rows = [{"name": n, "method": m, "time_warm": t, "vis_rmse": e} for n, m, t, e in [
        ("rt1", "raytraced", 1.0, 0.4), ("rt2", "raytraced", 2.0, 0.2),
        ("rt4", "raytraced", 4.0, 0.1), ("hard", "hard", 1.5, 0.15),
        ("slow", "hard", 5.0, 0.3), ("fast", "hard", 0.5, 0.5)]]
    by = {r["name"]: r for r in harness.analyse(rows)}
    assert {n for n, r in by.items() if r["pareto"]} == {"rt1", "rt4", "hard", "fast"}
    assert by["hard"]["rt_error_equal_time"] == 0.4
    assert by["hard"]["error_ratio_equal_time"] == pytest.approx(0.4 / 0.15)
    assert by["hard"]["rt_time_equal_error"] == 4.0
    assert by["hard"]["speedup_equal_error"] == pytest.approx(4.0 / 1.5)
    assert by["slow"]["speedup_equal_error"] == pytest.approx(2.0 / 5.0)
    assert by["fast"]["rt_error_equal_time"] is None        # no ray tracing that fast
    assert by["rt2"]["speedup_equal_error"] is None          # no self-comparison


def test_analyse_reads_a_tie_at_zero_error_as_a_tie():
    """A row and ray tracing both at error 0 (misclassified on an easy scene) was an
    error ratio of inf, "infinitely more accurate"; 0 against a positive error is."""
    rows = [{"name": n, "method": m, "time_warm": t, "vis_misclassified": e}
            for n, m, t, e in [("rt1", "raytraced", 0.005, 0.0), ("hard", "hard", 0.01, 0.0),
                               ("rt_bad", "raytraced", 0.001, 0.2), ("pcf", "pcf", 0.002, 0.0),
                               ("bad", "hard", 0.002, 0.1)]]
    by = {r["name"]: r for r in harness.analyse(rows, error_key="vis_misclassified")}
    assert by["hard"]["error_ratio_equal_time"] == 1.0
    assert by["pcf"]["error_ratio_equal_time"] == math.inf     # ray tracing's 0.2 in time
    assert by["bad"]["error_ratio_equal_time"] == pytest.approx(2.0)


def test_analyse_counts_ray_tracing_that_ties_in_time_or_error():
    """``rt_error_equal_time`` is the best ``raytraced`` row *not slower* than a row, and
    ``rt_time_equal_error`` the fastest one *at least as accurate*: a tie counts (timings
    and errors repeat on rows that render alike; mutation audit: ``<`` in place of ``<=``
    went unnoticed)."""
    rows = [{"name": n, "method": m, "time_warm": t, "vis_rmse": e} for n, m, t, e in [
        ("rt1", "raytraced", 1.0, 0.3), ("rt2", "raytraced", 2.0, 0.1),
        ("hard", "hard", 2.0, 0.3)]]
    by = {r["name"]: r for r in harness.analyse(rows)}
    assert by["hard"]["rt_error_equal_time"] == 0.1          # rt2 takes the same time
    assert by["hard"]["error_ratio_equal_time"] == pytest.approx(0.1 / 0.3)
    assert by["hard"]["rt_time_equal_error"] == 1.0          # rt1 has the same error
    assert by["hard"]["speedup_equal_error"] == pytest.approx(0.5)


def test_a_sweeps_reference_has_at_least_the_grids_largest_spp():
    """The automatic reference of a delta light is ``raytraced`` at ``max(ref_spp, every
    spp of the grid)`` (so no row is compared with a noisier render than itself); a
    reference at ``ref_spp`` alone went unnoticed (mutation audit)."""
    scene = mi.load_dict(default_scene(width=8, height=8, spp=1))
    table = harness.sweep(scene, {"method": "raytraced", "spp": [1, 8]}, spp=1, repeats=1,
                          ref_spp=2, progress=False)
    assert table.reference.spp == 8
    assert [r["reference_spp"] for r in table] == [8, 8]


def test_analyse_names_a_column_the_rows_lack():
    """Re-ranking a sweep rendered without ``measure_cached`` on ``time_cached`` (as
    notebooks 04 and 05 do with theirs) failed with "argument 'times' has 3 non-finite
    value(s) (NaN or inf)"; a misspelt error column gave every row a NaN error and no
    Pareto front without a word. A failed row (no columns) is not counted."""
    rows = [{"name": "rt1", "method": "raytraced", "time_warm": 1.0, "vis_rmse": 0.4},
            {"name": "hard", "method": "hard", "time_warm": 1.5, "vis_rmse": 0.15},
            {"name": "big", "method": "hard", "failed": "over memory_budget"}]
    with pytest.raises(ValueError, match=r"2 row\(s\) \(rt1, ...\) have no column "
                                         r"'time_cached' \(.*measure_cached=True.*time_warm"):
        harness.analyse([dict(r) for r in rows], time_key="time_cached")
    with pytest.raises(ValueError, match=r"no column 'vis_rmsee'.*vis_rmse"):
        harness.analyse([dict(r) for r in rows], error_key="vis_rmsee")
    assert [r["pareto"] for r in harness.analyse(rows)] == [True, True, False]


def test_sweep_table(tmp_path):
    scene = mi.load_dict(default_scene(**SMALL))
    table = harness.sweep(scene, [{"method": "hard", "resolution": [64, 256]},
                                  {"method": "raytraced", "spp": [1, 4]}],
                          spp=2, repeats=1, ref_spp=16, progress=False)
    assert len(table) == 4 and table.reference.spp == 16
    assert [r["name"] for r in table] == ["hard resolution=64 spp=2",
                                          "hard resolution=256 spp=2",
                                          "raytraced spp=1", "raytraced spp=4"]
    front = metrics.pareto_front([r["time"] for r in table], [r["error"] for r in table])
    assert [r["pareto"] for r in table] == front.tolist() and any(front)
    rt = [r for r in table if r["method"] == "raytraced"]
    # ray tracing at 4 spp is closer to the 16-spp reference than at 1 spp
    assert rt[1]["error"] < rt[0]["error"]
    for r in table:
        if r["method"] == "raytraced":
            continue
        fits = [q["error"] for q in rt if q["time"] <= r["time"]]
        assert r["rt_error_equal_time"] == (min(fits) if fits else None)
        good = [q["time"] for q in rt if q["error"] <= r["error"]]
        assert r["rt_time_equal_error"] == (min(good) if good else None)
    table.to_csv(tmp_path / "s.csv")
    assert len((tmp_path / "s.csv").read_text().strip().splitlines()) == 5
    assert "pareto" in table.format()


def test_converged_reference_agrees_with_many_shadow_rays():
    """The converged reference and ray tracing with many stratified shadow rays
    estimate the same visibility (two independent estimators)."""
    scene = mi.load_dict(default_scene(light="area", **SMALL))
    ref = harness.converged_reference(scene, spp=16, seed=3, shadow_rays=64)
    fallback = harness.run_method(scene, "raytraced", spp=16, seed=3, shadow_rays=64,
                                  measure_cached=False)
    err = metrics.rmse(ref.vis_stack(), fallback.vis_stack())
    print(f"converged vs 64 shadow rays: visibility RMSE {err:.4f}")
    assert err < 0.03


# --------------------------------------------------------------------------- specs
def test_methods_derive_from_the_registry():
    names = [m.name for m in methods.records()]
    assert harness.available_methods() == names
    assert harness.default_methods() == [n for n in names if n != harness.REFERENCE_METHOD]
    assert harness.map_methods() == [m.name for m in methods.records() if m.uses_map]
    grid = harness.default_grid()
    assert grid[0]["method"] == harness.map_methods()


def test_uses_property_follows_scopes_and_records():
    """A shared value goes to a method when the property applies to it, and a method
    without a map does not get the map settings it merely accepts."""
    for record in methods.records():
        for prop in options.all_properties():
            used = harness.uses_property(record.name, prop.name)
            if prop.name == "method" or not options.applies(record, prop.name):
                assert not used
            elif record.property(prop.name) is not None or record.uses_map:
                assert used
            else:
                assert used == (options.SCOPES[prop.name] != options.ACCEPTED)
    assert not harness.uses_property("no_such_method", "resolution")
    assert not harness.uses_property("hard", "no_such_property")
    assert harness.users_of("shadow_rays") == [m.name for m in methods.records()
                                               if m.property("shadow_rays") is not None]


def test_method_spec_grammar():
    assert harness.parse_method_string("pcf: num_samples=4, sampling=uniform ,"
                                       "receiver_plane=false") == {
        "method": "pcf", "num_samples": 4, "sampling": "uniform", "receiver_plane": False}
    spec = harness.method_spec("raytraced", {"resolution": 64, "shadow_rays": 2, "spp": 3})
    assert spec == {"method": "raytraced", "shadow_rays": 2, "spp": 3}
    assert harness.method_spec({"method": "hard", "resolution": 32}, {"resolution": 64}) == {
        "method": "hard", "resolution": 32}    # the item's own value wins
    assert harness.spec_name({"method": "pcf", "spp": 2, "bias_range": (0.0, 0.1)}) == \
        "pcf bias_range=0.0,0.1 spp=2"
    with pytest.raises(OptionError, match="name=value"):
        harness.parse_method_string("pcf:num_samples")
    with pytest.raises(OptionError, match="spp"):
        harness.validate_spec({"method": "hard", "spp": 0})


@pytest.mark.parametrize("name, value, match", [
    ("resolutoin", 64, "resolutoin"),
    ("num_samples", 0, "num_samples"),
    ("method", "nope", "nope"),
])
def test_validate_property(name, value, match):
    with pytest.raises(OptionError, match=match):
        harness.validate_property(name, value)


def test_validate_property_any_user_accepts():
    for prop in options.all_properties():
        if prop.default is not None and prop.name != "method":
            harness.validate_property(prop.name, prop.default)


def test_with_shared_adds_fixed_axes_where_used():
    grid = harness.with_shared([{"method": "hard"}, {"method": "raytraced"},
                                {"method": "hard", "resolution": [16]}],
                               {"resolution": 32, "shadow_rays": 2})
    assert grid == [{"method": "hard", "resolution": 32},
                    {"method": "raytraced", "shadow_rays": 2},
                    {"method": "hard", "resolution": [16]}]
    with pytest.raises(OptionError, match="shadow_rays"):
        harness.with_shared([{"method": "hard"}], {"shadow_rays": 2})
    with pytest.raises(OptionError, match="'method' = 'pcf' is not a shared property"):
        harness.with_shared([{"method": "hard"}], {"method": "pcf"})   # ignored before
    with pytest.raises(OptionError, match="'method' = 'pcf' is not a shared property"):
        harness.map_specs(["hard"], {"method": "pcf"})


# --------------------------------------------------------------------------- tables
def test_tables(tmp_path):
    rows = [{"name": "a", "x": 1.0, "t": (1, 2)}, {"name": "b", "y": math.inf,
                                                   "z": np.float32(0.5)}]
    assert tables.columns(rows) == ["name", "x", "t", "y", "z"]
    text = tables.text_table(rows, [("name", "N", "{}"), ("x", "X", "{:.2f}")])
    lines = text.splitlines()
    assert lines[0].split() == ["N", "X"] and lines[2].split() == ["a", "1.00"]
    assert lines[3].split() == ["b", "-"]      # missing values print as '-'
    paths = tables.write_tables(rows, str(tmp_path), "t")
    assert [p.rsplit(".", 1)[1] for p in paths] == ["csv", "json"]
    back = json.loads((tmp_path / "t.json").read_text())
    assert back[0]["t"] == [1, 2] and back[1]["y"] == "inf" and back[1]["z"] == 0.5
    assert len((tmp_path / "t.csv").read_text().strip().splitlines()) == 3
    assert tables.safe_name("pcf bias_range=0.0,0.1 / x") == "pcf_bias_range=0.0,0.1_x"


def test_format_table(spot_results):
    text = harness.format_table(spot_results)
    assert text.splitlines()[0].split()[:3] == ["method", "vis", "RMSE"]
    assert len(text.splitlines()) == 2 + len(spot_results)
    assert harness.format_table is tables.format_table


# --------------------------------------------------------------------------- maps
def test_prepare_maps_every_layer():
    """The map manager's maps for several methods, with every layer they use."""
    scene = mi.load_dict(default_scene(**SMALL))
    maps = harness.prepare_maps(scene, ["hard", *harness.map_methods()], resolution=32)
    assert len(maps) == 1 and maps[0].resolution == 32
    expected = {"depth"}
    for m in harness.map_methods():
        opts = options.parse_options({"method": m, "resolution": 32})   # full maps, as built
        expected |= set(methods.get(m).layer_names(opts))
    assert set(maps[0].layers()) == expected
    with pytest.raises(OptionError, match="raytraced"):
        harness.prepare_maps(scene, ["hard", "raytraced"])


def test_methods_with_different_maps_of_one_emitter_keep_both():
    """``multiview`` (K views of an area light) and ``hard`` (a cube map) build different
    maps of one emitter: prepare_maps kept the first method's (by layer count, then as
    listed) and dropped the other's without notice, so the order of the methods chose
    the map. Now prepare_maps refuses, naming both, and emitter_maps gives both, each
    with the methods that read it, whatever the order."""
    scene = mi.load_dict(default_scene(light="area", **SMALL))
    with pytest.raises(ValueError, match=r"multiview and hard build different maps of "
                                         r"emitter 'emitter' \(MultiView"):
        harness.prepare_maps(scene, ["multiview", "hard"], resolution=8)
    kinds = []
    for order in (["multiview", "hard", "pcf"], ["pcf", "hard", "multiview"]):
        maps = harness.emitter_maps(scene, order, resolution=8)
        kinds.append({type(m.map.view).__name__: (m.map.view.n_faces, sorted(m.methods))
                      for m in maps})
        assert {m.label for m in maps} == {"emitter"}
    assert kinds[0] == kinds[1] == {"MultiView": (192, ["multiview"]),
                                    "CubeView": (6, ["hard", "pcf"])}
    # maps at another resolution are other maps too (their layers were merged into the
    # first method's map, of another size)
    maps = harness.emitter_maps(scene, ["vsm:resolution=16", "hard:resolution=8"])
    assert sorted((m.map.resolution, m.methods[0]) for m in maps) == [
        (8, "hard resolution=8"), (16, "vsm resolution=16")]
    assert [m.map.layers() for m in maps if m.map.resolution == 8] == [["depth"]]


def test_prepare_maps_at_defaults_gives_full_maps_with_every_layer():
    """Without ``resolution`` (virtual maps by default in renders) the harness still
    prepares full maps, so several methods' layers line up in one map; virtual maps of
    methods with different layers are refused, naming the layer."""
    from mi_shadowmap.depth_maps import ShadowMap
    scene = mi.load_dict(default_scene(**SMALL))
    maps = harness.prepare_maps(scene, ["pcss", "second_depth"])
    assert isinstance(maps[0], ShadowMap) and "second_depth" in maps[0].layers()
    with pytest.raises(ValueError, match="second_depth"):
        harness.prepare_maps(scene, ["pcss", "second_depth"], virtual=True)


def _layer(smap, name: str) -> np.ndarray:
    return np.asarray((smap.depth if name == "depth" else smap.extra[name]).numpy())


@pytest.mark.parametrize("order", [["second_depth", "mdsm"], ["mdsm", "second_depth"],
                                   ["second_depth", "pcss", "hard"]])
def test_shared_maps_take_the_resolution_of_the_costliest_texels(order):
    """The harness's maps of several methods take the resolution of the method that goes
    first. That was the one with the most layers: ``second_depth`` (one layer) tied with
    ``mdsm`` (one layer, ``mdsm_max``), and went first as listed. Its full maps hold no
    first depth since the fifty-first session (one float32 a texel, ``mdsm``'s two), so
    under a ``memory_budget`` that binds (0.02 MiB, the spot light's one face) its 72^2
    was over ``mdsm``'s budget: an OptionError, where ``["mdsm", "second_depth"]`` gave
    51^2. Now the method whose texels cost most goes first, in any order: each layer
    equals the layer of that method's own maps at that resolution."""
    scene = mi.load_dict(default_scene(**SMALL))
    params = dict(memory_budget=0.02, virtual=False, cache_maps=False)
    shared = harness.prepare_maps(scene, order, **params)[0]
    own = {m: harness.prepare_maps(scene, [m], **params)[0] for m in order}
    res = min(m.resolution for m in own.values())
    assert shared.resolution == res == (51 if "mdsm" in order else 72)
    for m, smap in own.items():
        if smap.resolution != res:
            smap = harness.prepare_maps(scene, [m], resolution=res, **params)[0]
        for layer in smap.layers():     # (pcss_near: a value per face, no to_numpy)
            assert np.array_equal(_layer(shared, layer), _layer(smap, layer)), (m, layer)
    assert set(shared.layers()) == {n for m in own.values() for n in m.layers()}


@pytest.mark.parametrize("variant, fmt, plain", [
    ("llvm_ad_rgb", "rgba", "rgb"), ("llvm_ad_rgb", "luminance_alpha", "luminance"),
    ("llvm_ad_mono", "luminance_alpha", "luminance"),
    ("llvm_ad_spectral", "luminance_alpha", "luminance")])
def test_films_with_alpha_compare_as_without(variant, fmt, plain):
    """A film whose ``pixel_format`` has alpha (``rgba``, ``luminance_alpha``) puts an
    alpha channel before the AOVs; the harness took it for colour (4 channels, which
    FLIP refused, or luminance and alpha as two colours). Now it is dropped: the same
    records as the film without alpha."""
    mi.set_variant(variant)
    out = {}
    for pf in (fmt, plain):
        d = default_scene(**SMALL)
        d["sensor"]["film"]["pixel_format"] = pf
        scene = mi.load_dict(d)
        n = np.asarray(mi.render(scene, integrator=mi.load_dict({"type": "shadowmap"}),
                                 spp=1)).shape[-1]
        assert n == {"rgba": 5, "rgb": 4, "luminance_alpha": 3, "luminance": 2}[pf]
        res = harness.compare(scene, methods=["hard"], spp=2)
        out[pf] = res
        assert res[1].image.shape == (32, 32, 3) and list(res[1].visibility) == ["spot"]
    a, b = out.values()
    for ra, rb in zip(a, b):
        np.testing.assert_array_equal(ra.image, rb.image)
        np.testing.assert_array_equal(ra.visibility["spot"], rb.visibility["spot"])
        assert ra.metrics["vis_rmse"] == rb.metrics["vis_rmse"]


@pytest.mark.parametrize("kwargs, match", [
    (dict(spp=0), r"'spp' must be an integer >= 1, got 0"),
    (dict(spp=2.5), r"'spp' must be an integer >= 1"),
    (dict(seed=-1), r"'seed' must be an integer in \[0, 2\^32\)"),
    (dict(repeats=0), r"'repeats' must be an integer >= 1"),
    (dict(ref_spp=-2), r"'ref_spp' must be an integer >= 1"),
    (dict(methods=[]), r"'methods' is empty"),
])
def test_run_arguments_are_checked_before_rendering(kwargs, match):
    """``spp`` 0 rendered at the sampler's count while the records said 0; a negative
    seed failed inside Mitsuba without naming it; ``repeats`` and ``ref_spp`` took any
    value; ``methods=[]`` ran every method."""
    scene = mi.load_dict(default_scene(**SMALL))
    with pytest.raises(OptionError, match=match):
        harness.compare(scene, **kwargs)


def test_render_checks_its_properties_and_a_string_is_one_method():
    """``harness.render`` ignored unknown and unused properties; ``compare(methods=
    'hard')`` iterated the string's letters."""
    scene = mi.load_dict(default_scene(**SMALL))
    with pytest.raises(OptionError, match="unknown property 'bogus'"):
        harness.render(scene, "hard", bogus=5)
    with pytest.raises(OptionError, match="'num_samples' = 99999 is out of range"):
        harness.render(scene, "pcf", num_samples=99999)
    with pytest.raises(OptionError, match="'resolution' is not used by any of the methods"):
        harness.render(scene, "raytraced", resolution=256)
    with pytest.raises(OptionError, match="'spp' must be an integer >= 1"):
        harness.render(scene, "hard", spp=0)
    res = harness.compare(scene, methods="hard", spp=1, repeats=1, measure_cached=False)
    assert [r.method for r in res] == ["raytraced", "hard"]


def test_the_soft_light_reference_has_the_methods_camera_samples():
    """Under an area light the automatic (converged) reference was rendered at
    ``max(spp, ref_spp)`` = 64 spp, so the methods' camera noise counted as error:
    ``raytraced`` with 256 shadow rays scored 0.044 on a 48^2 cbox_area at 16 spp, no
    knob could bring a soft shadow's error near 0. It now renders at the methods' spp
    and seed, as under delta lights; ``reference="converged"`` keeps its own spp."""
    scene = mi.load_dict(default_scene(width=24, height=24, light="area"))
    res = harness.compare(scene, methods=["raytraced:shadow_rays=256"], spp=4, repeats=1,
                          measure_cached=False)
    assert res[0].spp == 4 and "converged" in res[0].name
    print(f"vis RMSE {res[1].metrics['vis_rmse']:.4f}")
    assert res[1].metrics["vis_rmse"] <= 0.01
    own = harness.compare(scene, methods=["hard"], spp=4, repeats=1, measure_cached=False,
                          reference="converged", ref_spp=8)
    assert own[0].spp == 8


def test_the_reference_row_is_timed_with_the_methods_repeats(monkeypatch):
    """``compare(repeats=3)``'s reference row came from one warm render beside the
    methods' medians of three."""
    from mi_shadowmap import timing
    counts, real = {}, timing.render_timed

    def counted(scene, integrator, spp, seed):
        counts[integrator.opts.method] = counts.get(integrator.opts.method, 0) + 1
        return real(scene, integrator, spp, seed)
    monkeypatch.setattr(timing, "render_timed", counted)
    harness.compare(mi.load_dict(default_scene(**SMALL)), methods=["unshadowed"], spp=1,
                    repeats=3, measure_cached=False)
    assert counts == {"raytraced": 4, "unshadowed": 4}     # one cold, three warm each
    counts.clear()       # under an area light: the converged reference's image render
    harness.compare(mi.load_dict(default_scene(width=8, height=8, light="area")),
                    methods=["unshadowed"], spp=1, repeats=3, measure_cached=False)
    assert counts == {"raytraced": 4, "unshadowed": 4}


def test_a_scene_without_emitters_is_refused_by_name():
    """``compare`` on a scene without lights failed after rendering with numpy's "need
    at least one array to stack"."""
    d = default_scene(**SMALL)
    for k in [k for k, v in d.items() if isinstance(v, dict) and v.get("type") == "spot"]:
        d.pop(k)
    with pytest.raises(ValueError, match="no emitter"):
        harness.compare(mi.load_dict(d), methods=["hard"], spp=1)


def test_a_pair_property_in_the_method_string_form():
    """``pcf:bias_range=0,0.01`` (a pair, written with its comma, as ``spec_name`` prints
    it) was cut at the comma: "expected name=value ... got '0.01'"."""
    spec = harness.method_spec("pcf:bias_range=0,0.01,num_samples=4")
    assert spec["num_samples"] == 4
    assert harness.spec_name(spec) == "pcf bias_range=0,0.01 num_samples=4"
    scene = mi.load_dict(default_scene(**SMALL))
    res = harness.compare(scene, methods=["pcf:bias_range=0,0.01"], spp=1, repeats=1,
                          measure_cached=False)
    assert res[1].params["bias_range"] in ("0,0.01", (0.0, 0.01), [0.0, 0.01])


def test_scene_parameters_of_a_scene_dict_are_refused():
    """``scene_params`` fill an XML file's ``$`` parameters; given with a scene dict they
    were dropped silently (the dict's own size rendered)."""
    with pytest.raises(ValueError, match="XML files only, not to a scene dict"):
        harness.compare(default_scene(**SMALL), methods=["hard"], scene_params={"width": 16})


def test_contact_sheet_error_keeps_each_lights_error():
    """Two lights with opposite errors at a pixel, and a whole error of one light at
    another: the heat map shows the larger error with its sign (the mean over emitters
    showed 0 and 0.5)."""
    from mi_shadowmap.report import largest_error
    diff = np.zeros((2, 1, 2))
    diff[:, 0, 0] = [1.0, -0.6]
    diff[:, 0, 1] = [0.0, -1.0]
    assert largest_error(diff).tolist() == [[1.0, -1.0]]


def test_an_xyz_film_is_compared_in_srgb():
    """A film with ``pixel_format='xyz'`` develops to CIE XYZ: its channels become linear
    sRGB before PNGs and metrics read them (they were read as R, G, B), so the image
    equals an ``rgb`` film's."""
    images = {}
    for fmt in ("rgb", "xyz"):
        d = default_scene(**SMALL)
        d["sensor"]["film"]["pixel_format"] = fmt
        images[fmt] = harness.compare(mi.load_dict(d), methods=["hard"], spp=2)[1].image
    assert np.abs(images["xyz"] - images["rgb"]).max() < 1e-3


# --------------------------------------------------------------------------- spp rendered
def stratified_scene(**size):
    """The spot scene under a ``stratified`` sampler, which rounds the spp it is given
    up to a square (2, 3, 4 -> 4; 5..9 -> 9)."""
    xml = (SCENES / "spot_sphere_box.xml").read_text().replace(
        'type="independent"', 'type="stratified"')
    return mi.load_string(xml, **{k: v for k, v in (size or SMALL).items()})


def test_run_method_records_the_spp_the_sampler_renders():
    scene = stratified_scene()
    r = harness.run_method(scene, "raytraced", spp=3, measure_cached=False)
    assert r.spp == 4 and r.row()["spp"] == 4
    assert r.spp_requested == 3 and r.row()["spp_requested"] == 3
    plain = harness.run_method(mi.load_dict(default_scene(**SMALL)), "raytraced", spp=3,
                               measure_cached=False)
    assert plain.spp == 3 and plain.row()["spp_requested"] == 3
    from mi_shadowmap.timing import rendered_spp
    scene = stratified_scene()
    assert [rendered_spp(scene, s) for s in (1, 2, 3, 4, 5, 8, 10)] == \
        [1, 4, 4, 4, 9, 9, 16]
    assert scene.sensors()[0].sampler().sample_count() == 16   # left alone


def test_compare_names_a_methods_own_spp_by_the_count_rendered():
    """``pcf:spp=3`` under a stratified sampler renders 4 spp: it was named ``pcf spp=3``
    (its row said spp 4) and rendered a second 4-spp reference for the '3'; beside
    ``pcf:spp=4`` both wrote ``pcf_spp=...`` files of one render under two names."""
    scene = stratified_scene()
    res = harness.compare(scene, methods=["hard:spp=3"], spp=4, measure_cached=False)
    assert [r.name for r in res[1:]] == ["hard spp=4"]
    assert res[1].spp == 4 and res[1].spp_requested == 3
    assert "reference_spp" not in res[1].metrics        # compare's own 4-spp reference
    with pytest.raises(OptionError, match=r"'hard spp=4' is listed more than once.*"
                                          r"'hard spp=3' at spp=4"):
        harness.compare(scene, methods=["hard:spp=3", "hard:spp=4"], spp=1)


def test_sweep_rows_give_the_spp_rendered_and_merge_repeats():
    """spp 2, 3, 4, 5 under a stratified sampler render 4, 4, 4, 9: two rows, not four
    rows of which three had the same error at "different" spp."""
    scene = stratified_scene()
    with pytest.warns(UserWarning, match=r"StratifiedSampler.*spp=2, 3, 4 as 4"):
        table = harness.sweep(scene, {"method": "raytraced", "spp": [2, 3, 4, 5]},
                              repeats=1, ref_spp=16, progress=False)
    assert [r["name"] for r in table] == ["raytraced spp=4", "raytraced spp=9"]
    assert [r["spp"] for r in table] == [4, 9]
    assert [r["spp_requested"] for r in table] == [[2, 3, 4], [5]]
    assert [r.spp for r in table.results] == [4, 9]
    assert table.reference.spp == 16


# --------------------------------------------------------------------------- failing configs
#: Two point lights' cube maps at 8192^2: 3 GiB, over the default memory_budget (1 GiB);
#: a face alone fits, so this fails only when the scene's lights are known (rendering).
ROOM = str(SCENES / "room_two_points.xml")
OVER_BUDGET = {"method": ["hard", "pcf"], "resolution": [64, 8192]}


def test_best_row_never_picks_a_failed_configuration():
    """Notebooks 04 and 05 took ``min(rows, key=lambda r: r["error"])``: a failed
    configuration listed first (NaN time and error) stayed the minimum, and its name
    has no result (``by_name[...]``: KeyError)."""
    rows = harness.analyse([
        {"name": "pcss resolution=8192 spp=1", "method": "pcss", "failed": "over budget"},
        {"name": "pcss resolution=64 spp=1", "method": "pcss", "time_warm": 0.02,
         "vis_rmse": 0.09},
        {"name": "pcss resolution=128 spp=1", "method": "pcss", "time_warm": 0.03,
         "vis_rmse": 0.05},
        {"name": "raytraced spp=1", "method": "raytraced", "time_warm": 0.01,
         "vis_rmse": 0.2}])
    assert min(rows, key=lambda r: r["error"])["name"] == rows[0]["name"]   # the trap
    assert harness.best_row(rows)["name"] == "pcss resolution=128 spp=1"
    assert harness.best_row(rows, key="time")["name"] == "raytraced spp=1"
    assert harness.best_row(rows, key="error", largest=True)["name"] == "raytraced spp=1"
    assert harness.best_row(rows[:1]) is None and harness.best_row([]) is None
    assert harness.best_row(rows, key="rt_time_equal_error") is None   # None everywhere


def test_a_configuration_that_fails_is_a_row_and_the_sweep_goes_on():
    """resolution 8192 over memory_budget: the sweep raised at the first such
    configuration and every row rendered before was lost."""
    scene = harness.load_scene(ROOM, **SMALL)
    with pytest.warns(UserWarning, match=r"2 of 4 sweep configurations failed"):
        table = harness.sweep(scene, OVER_BUDGET, spp=2, repeats=1, ref_spp=4,
                              progress=False)
    assert [r["name"] for r in table] == [
        "hard resolution=64 spp=2", "hard resolution=8192 spp=2",
        "pcf resolution=64 spp=2", "pcf resolution=8192 spp=2"]
    bad = [r for r in table if r.get("failed")]
    assert [r["resolution"] for r in bad] == [8192, 8192]
    assert all("memory_budget" in r["failed"] and not r["pareto"] for r in bad)
    assert all(math.isnan(r["time"]) and math.isnan(r["error"]) for r in bad)
    good = [r for r in table if not r.get("failed")]
    assert len(good) == len(table.results) == 2
    assert all(math.isfinite(r["error"]) and r["time"] > 0 for r in good)
    assert any(r["pareto"] for r in good)
    assert "-" in table.format()


def test_every_configuration_failing_is_one_error():
    scene = harness.load_scene(ROOM, **SMALL)
    with pytest.raises(OptionError, match="every configuration of the sweep failed.*8192"):
        harness.sweep(scene, {"method": "hard", "resolution": 8192},
                      spp=2, repeats=1, ref_spp=4, progress=False)


def _disk_full_on_the_second_run(monkeypatch):
    """The sweep's second ``run_method`` raises an error that is not a configuration's."""
    from mi_shadowmap import sweep as sweep_module
    real, calls = sweep_module.run_method, []

    def flaky(*a, **k):
        calls.append(1)
        if len(calls) == 2:
            raise RuntimeError("disk full")
        return real(*a, **k)

    monkeypatch.setattr(sweep_module, "run_method", flaky)


def test_another_error_keeps_the_rows_rendered(monkeypatch):
    _disk_full_on_the_second_run(monkeypatch)
    scene = mi.load_dict(default_scene(**SMALL))
    with pytest.raises(RuntimeError, match="disk full") as e:
        harness.sweep(scene, {"method": "hard", "resolution": [64, 128, 256]}, spp=2,
                      repeats=1, ref_spp=4, progress=False)
    table = e.value.sweep_table
    assert [r["name"] for r in table] == ["hard resolution=64 spp=2"] and table.rows[0]["pareto"]


def test_cli_sweep_writes_the_rows_rendered_before_another_error(tmp_path, capsys,
                                                                 monkeypatch):
    """An error that is not the configuration's (a bug, a full disk, Ctrl-C) stops the
    sweep, but the CLI writes the rows rendered before it (exit 2, one line)."""
    from mi_shadowmap import cli
    _disk_full_on_the_second_run(monkeypatch)
    out = tmp_path / "sweep"
    code = cli.main(["sweep", ROOM, "--width", "32", "--height", "32", "--spp", "2",
                     "--repeats", "1", "--grid", "method=hard resolution=64,128,256",
                     "--out", str(out)])
    _, err = capsys.readouterr()
    assert code == 2 and "disk full" in err and "rows rendered" in err
    rows = json.loads((out / "sweep.json").read_text())
    assert [r["name"] for r in rows] == ["hard resolution=64 spp=2"]


def test_cli_sweep_writes_the_rows_despite_a_failing_configuration(tmp_path, capsys):
    from mi_shadowmap import cli
    out = tmp_path / "sweep"
    code = cli.main(["sweep", ROOM, "--width", "32",
                     "--height", "32", "--spp", "2", "--repeats", "1", "--grid",
                     "method=hard,pcf resolution=64,8192",
                     "--out", str(out)])
    _, err = capsys.readouterr()
    assert code == 0, err
    rows = json.loads((out / "sweep.json").read_text())
    assert len(rows) == 4 and sum(bool(r.get("failed")) for r in rows) == 2
    assert (out / "pareto.png").stat().st_size > 0


def test_methods_given_as_an_iterator_or_one_name_are_all_rendered():
    """``compare(scene, methods=(m for m in ...))`` returned the reference alone: the
    generator was read up by the check that it is not empty. ``emitter_maps`` and
    ``prepare_maps`` read it twice (IndexError), and took one name for its letters
    ("method 'h' is not valid") where ``compare`` takes one name."""
    scene = mi.load_dict(default_scene(width=8, height=8, spp=1))
    res = harness.compare(scene, methods=(m for m in ["hard", "pcf"]), spp=1,
                          measure_cached=False)
    assert [r.name for r in res[1:]] == ["hard", "pcf"]
    maps = harness.emitter_maps(scene, iter(["hard", "vsm"]), resolution=16)
    assert [m.methods for m in maps] == [["hard", "vsm"]]
    assert [m.methods for m in harness.emitter_maps(scene, "hard", resolution=16)] == [["hard"]]
    assert harness.prepare_maps(scene, "hard", resolution=16)[0].resolution == 16


def test_sweep_refuses_an_unknown_time_or_error_key_before_rendering(monkeypatch):
    """``error_key="vis_rmsee"`` gave every row a NaN error and no Pareto front, silently;
    ``time_key="time_warmm"`` rendered every configuration and then failed with
    "argument 'times' has 1 non-finite value(s)"."""
    from mi_shadowmap import sweep as sweep_mod
    scene = mi.load_dict(default_scene(width=8, height=8, spp=1))
    monkeypatch.setattr(sweep_mod, "run_method", lambda *a, **k: pytest.fail("rendered"))
    monkeypatch.setattr(sweep_mod, "make_reference", lambda *a, **k: pytest.fail("rendered"))
    with pytest.raises(OptionError, match=r"unknown error_key 'vis_rmsee'.*vis_misclassified"
                                          r".*vis_rmse\[spot\]"):
        harness.sweep(scene, {"method": "hard"}, spp=1, progress=False, error_key="vis_rmsee")
    with pytest.raises(OptionError, match=r"unknown time_key 'time_warmm'.*time_cached"):
        harness.sweep(scene, {"method": "hard"}, spp=1, progress=False, time_key="time_warmm")
    monkeypatch.undo()
    table = harness.sweep(scene, {"method": "hard", "resolution": [16, 32]}, spp=1, repeats=1,
                          progress=False, error_key="vis_rmse[spot]", time_key="time_cold")
    assert all(math.isfinite(r["error"]) for r in table) and any(r["pareto"] for r in table)


def test_the_largest_seed_works_where_other_seeds_are_derived_from_it():
    """``sweep`` renders its reference with ``seed + 1``: the largest seed it accepts,
    2^32 - 1, failed in Dr.Jit's ``sample_tea_32`` ("incompatible function arguments")
    after the setup; derived seeds wrap within [0, 2^32)."""
    assert harness.derived_seed(2 ** 32 - 1, 1) == 0 and harness.derived_seed(5, 2) == 7
    scene = mi.load_dict(default_scene(width=8, height=8, spp=1))
    table = harness.sweep(scene, {"method": "hard"}, spp=1, seed=2 ** 32 - 1, repeats=1,
                          ref_spp=2, progress=False)
    assert math.isfinite(table[0]["error"])


def test_a_given_reference_of_another_size_or_scene_is_refused_before_rendering(monkeypatch):
    """A reference result rendered at another film size (or from another scene's lights)
    was found out by the scoring, after every method had rendered, as "shape mismatch:
    'test_vis' has shape (1, 24, 32) but 'ref_vis' ..." with nothing returned. Now it is
    refused before a method renders, naming both sizes (or both sets of emitters)."""
    small = harness.load_scene(default_scene(width=24, height=24))
    ref = harness.run_method(small, "raytraced", spp=1, measure_cached=False)
    rendered = []
    monkeypatch.setattr(harness, "run_method",
                        lambda *a, **k: rendered.append(a) or pytest.fail("rendered"))
    wide = harness.load_scene(default_scene(width=32, height=24))
    with pytest.raises(ValueError, match="is 24 x 24 pixels, the scene's film renders 32 x 24"):
        harness.compare(wide, methods=["hard"], reference=ref, spp=1)
    other = harness.load_scene(default_scene(width=24, height=24, light="point"))
    with pytest.raises(ValueError, match="has the emitters spot, the scene point"):
        harness.compare(other, methods=["hard"], reference=ref, spp=1)
    assert not rendered


@pytest.mark.parametrize("light, steps", [("area", ["image: raytraced, 4 spp x 4 shadow "
                                                     "rays", "visibility: 1024 light samples"]),
                                           ("point", ["raytraced spp=4"])])
def test_sweep_shows_its_reference_in_progress(capsys, light, steps):
    """The sweep rendered its reference -- under an area light the converged one, which
    can take longer than the whole grid -- before its bar started, showing nothing all
    that time. It has a bar of its own now, naming each render as it starts (plain lines
    here: stderr is no terminal)."""
    scene = mi.load_dict(default_scene(width=16, height=16, light=light))
    harness.sweep(scene, {"method": "hard", "resolution": 16}, spp=1, repeats=1, ref_spp=4,
                  ref_shadow_rays=4)
    err = capsys.readouterr().err.splitlines()
    first = next(i for i, line in enumerate(err) if line.startswith("sweep:"))
    ref = [line for line in err[:first] if line.startswith("sweep reference:")]
    for what in steps:
        assert any(what in line for line in ref), err
    assert "100%" in ref[-1], err


def test_sweep_does_not_time_its_reference_cached(monkeypatch):
    """The sweep's reference was rendered as compare's is timed -- a cold, a warm and a
    cached frame -- though only its image and visibility are used: one of its three
    image renders (a third of a ray-traced reference's time) was wasted."""
    from mi_shadowmap import timing
    real, calls = timing.render_timed, []

    def counted(*a, **k):
        calls.append(1)
        return real(*a, **k)

    monkeypatch.setattr(timing, "render_timed", counted)
    scene = mi.load_dict(default_scene(width=16, height=16, light="point"))
    harness.sweep(scene, {"method": "hard", "resolution": 16}, spp=1, repeats=1, ref_spp=4,
                  progress=False)
    assert len(calls) == 2 + 2       # reference: cold, warm; hard: cold, warm


def test_the_converged_reference_has_camera_samples_of_its_own():
    """``reference="converged"`` is documented as a reference with its own camera samples,
    independent of the methods', but it was rendered with their seed: at an spp >=
    ``ref_spp`` it had their very samples (``raytraced`` against it: visibility RMSE 1e-8
    at 64 spp, 0.018 at 16 spp on a 48 x 40 scene), so an spp sweep of a compare jumped
    to 0 error where the spp reached ``ref_spp``."""
    scene = mi.load_dict(default_scene(width=24, height=24, light="spot"))
    res = harness.compare(scene, methods=["raytraced"], reference="converged", spp=8,
                          ref_spp=8, repeats=1, measure_cached=False)
    assert res[0].spp == 8
    print(f"raytraced vs converged at its spp: vis RMSE {res[1].metrics['vis_rmse']:.2e}")
    assert res[1].metrics["vis_rmse"] > 1e-3


def test_sweep_rows_name_their_reference(tmp_path):
    """sweep.csv / sweep.json and pareto.png gave errors without saying what they were
    measured against (a ``raytraced`` reference at ``max(ref_spp, the grid's spp)`` with
    a seed of its own, or the converged one): each rendered row now names it
    (``scored_against``) and its ``reference_spp``."""
    from mi_shadowmap import report
    scene = mi.load_dict(default_scene(width=8, height=8, spp=1))
    table = harness.sweep(scene, {"method": "raytraced", "spp": [1, 2]}, spp=1, repeats=1,
                          ref_spp=4, progress=False)
    assert [r["reference_spp"] for r in table] == [4, 4]
    assert all(r["scored_against"] == "reference (raytraced spp=4)" for r in table)
    report.write_sweep(table, str(tmp_path))
    rows = json.loads((tmp_path / "sweep.json").read_text())
    assert rows[0]["scored_against"] == "reference (raytraced spp=4)"


def test_timed_frames_wait_for_the_render():
    """``mi.render`` returns before the LLVM kernels have run (measured: 3 ms for a
    180 ms render, the rest spent in the first read of the image), so a frame is timed up
    to ``dr.sync_thread``. Without it each render's work landed in the next one's time:
    the warm frames still looked right, but the cold frame (kernels compiled already)
    measured only the launch (0.027 s against 0.24 s warm at 64^2 x 256 spp) and ``jit``
    was 0. Cold and warm must both be of the order of an independently synchronised
    render (margin 3x for a shared machine)."""
    import time
    import drjit as dr
    from mi_shadowmap.timing import run_method
    scene = mi.load_dict(default_scene(width=64, height=64, spp=1))
    spp = 256
    run_method(scene, "raytraced", spp=spp, repeats=1, measure_cached=False)  # compiles
    r = run_method(scene, "raytraced", spp=spp, repeats=3, measure_cached=False)
    integ = mi.load_dict({"type": "shadowmap", "method": "raytraced"})
    synced = []
    for _ in range(3):
        t0 = time.perf_counter()
        img = mi.render(scene, integrator=integ, spp=spp)
        np.asarray(img)
        dr.sync_thread()
        synced.append(time.perf_counter() - t0)
    assert r.times["warm"] >= min(synced) / 3.0, (r.times, synced)
    assert r.times["cold"] >= min(synced) / 3.0, (r.times, synced)


def test_a_methods_times_are_its_own_not_the_references():
    """Every time of a method in ``compare`` is that method's renders alone: a reference
    (here given, with every time set to 1000 s) adds nothing to them. Adding the
    reference's warm time to each method's survived every harness test."""
    from mi_shadowmap.timing import run_method
    scene = mi.load_dict(default_scene(width=16, height=16, spp=1))
    ref = run_method(scene, "raytraced", spp=1, measure_cached=False)
    ref.times = {k: 1000.0 for k in ref.times}
    out = harness.compare(scene, methods=["hard:resolution=64"], reference=ref, spp=1)
    r = out[1]
    assert r.method == "hard"
    assert all(v < 100.0 for v in r.times.values()), r.times


def test_compare_raises_the_error_naming_the_property_of_a_map_over_budget():
    """A method whose maps exceed memory_budget fails at its render: compare raised
    Mitsuba's ``RuntimeError`` ("drjit.custom(...): error while performing a custom
    differentiable operation. (see above)"), which names no property and which an
    ``except OptionError`` misses; ``render`` raised the ``OptionError`` already. Now
    compare raises it too, with the results rendered before it."""
    scene = harness.load_scene(ROOM, **SMALL)
    with pytest.raises(OptionError, match=r"'resolution' = 8192.*memory_budget") as info:
        harness.compare(scene, methods=["hard:resolution=64", "hard:resolution=8192"],
                        spp=1, measure_cached=False)
    done = info.value.compare_results
    assert [r.name for r in done[1:]] == ["hard resolution=64"]
    assert all(r.metrics for r in done)        # scored
