"""``raytraced`` with a delta light given a size (``light_size``, ``angular_diameter``): the
soft ground truth. Against closed forms (a sun's and a sphere light's penumbra under a
straight edge), Mitsuba's own sampling of a real ``sphere`` emitter, ``multiview`` with
many views; defaults unchanged, bad values named, mono and spectral; ``compare``'s
reference renders the size the methods give. Small: films of 64 x 4 and 48^2."""
import warnings

import mitsuba as mi
import numpy as np
import pytest

from mi_shadowmap import harness
from mi_shadowmap.options import OptionError, parse_options
from mi_shadowmap.reference import converged_visibility
from mi_shadowmap.scenes import default_scene
from mi_shadowmap.specs import derived_seed
from mi_shadowmap.timing import run_method

from conftest import render_np

T = mi.ScalarTransform4f
#: The edge's height over the ground, and the sphere light's centre height and radius.
H, H_LIGHT, RADIUS = 1.0, 2.0, 0.25
#: The film: 64 columns across the edge (x), 4 rows along it.
W = 64


def edge_scene(light: dict, half_width: float, scale: float = 1.0, offset=(0.0, 0.0, 0.0)):
    """A ground (z = 0) under a thin horizontal occluder at height ``H`` covering x < 0,
    seen straight down by an orthographic camera between the two (the occluder is behind
    it) spanning ``x`` in ``[-half_width, half_width]``; every length times ``scale``,
    the whole moved by ``offset``."""
    o = np.asarray(offset, dtype=float)
    move = T().translate(o.tolist()).scale(scale)
    return mi.load_dict({
        "type": "scene",
        "cam": {"type": "orthographic",
                "to_world": T().look_at((o + [0, 0, 0.5 * H * scale]).tolist(), o.tolist(),
                                        [0, 1, 0]).scale([half_width * scale,
                                                          half_width * scale, 1]),
                "near_clip": 1e-3 * H * scale, "far_clip": 2 * H * scale,
                "film": {"type": "hdrfilm", "width": W, "height": 4,
                         "rfilter": {"type": "box"}},
                "sampler": {"type": "independent"}},
        "ground": {"type": "rectangle", "to_world": move @ T().scale(4)},
        "edge": {"type": "rectangle",
                 "to_world": move @ T().translate([-2, 0, H]).scale([2, 4, 1])},
        "light": light})


def columns_x(half_width: float) -> np.ndarray:
    """The ground x of each film column's centre (the camera's x runs against the film's:
    checked against Mitsuba's ``position`` AOV when written)."""
    return -half_width + (np.arange(W) + 0.5) * (2 * half_width / W)


def cone_visibility(x, axis_of, half_angle_of, n=300) -> float:
    """Fraction of the directions uniform in solid angle in a cone (``axis_of(x)``,
    ``half_angle_of(x)``) from the ground point ``(x, 0, 0)`` that pass the edge: they
    cross z = H at x' >= 0 (midpoint quadrature, n^2 directions, float64)."""
    axis = np.asarray(axis_of(x), dtype=float)
    axis /= np.linalg.norm(axis)
    cos_max = np.cos(half_angle_of(x))
    c = cos_max + (1 - cos_max) * (np.arange(n) + 0.5) / n
    phi = (np.arange(n) + 0.5) / n * 2 * np.pi
    s = np.sqrt(1 - c ** 2)
    t = np.cross(axis, [0.0, 1.0, 0.0] if abs(axis[1]) < 0.9 else [1.0, 0.0, 0.0])
    t /= np.linalg.norm(t)
    b = np.cross(axis, t)
    d = (c[:, None, None] * axis + (s[:, None] * np.cos(phi))[..., None] * t
         + (s[:, None] * np.sin(phi))[..., None] * b).reshape(-1, 3)
    return float(np.mean(x + H * d[:, 0] / d[:, 2] >= 0))


def pixel_average(f, half_width: float, sub: int = 16) -> np.ndarray:
    """``f(x)`` averaged over each column's width (a box filter)."""
    dx = 2 * half_width / W
    offsets = ((np.arange(sub) + 0.5) / sub - 0.5) * dx
    return np.array([np.mean([f(x + o) for o in offsets]) for x in columns_x(half_width)])


def sun_truth(angular_diameter: float, half_width: float) -> np.ndarray:
    half = np.radians(angular_diameter) / 2
    return pixel_average(lambda x: cone_visibility(x, lambda _: (0, 0, 1), lambda _: half),
                         half_width, sub=8)


def sphere_truth(half_width: float) -> np.ndarray:
    """A sphere light seen from the ground: uniform in the cone it subtends (no point
    behind its silhouette), as Mitsuba samples a sphere."""
    return pixel_average(lambda x: cone_visibility(
        x, lambda x: (-x, 0, H_LIGHT), lambda x: np.arcsin(RADIUS / np.hypot(x, H_LIGHT))),
        half_width, sub=8)


def aov(scene, spp=32, **props) -> np.ndarray:
    """The visibility AOV averaged along the edge (over the film's rows)."""
    _, aovs = render_np(scene, {"type": "shadowmap", **props}, spp=spp)
    return next(iter(aovs.values())).mean(axis=0)


def rmse(a, b) -> float:
    return float(np.sqrt(np.mean((np.asarray(a) - np.asarray(b)) ** 2)))


SUN = {"type": "directional", "direction": [0, 0, -1], "irradiance": 1.0}
POINT = {"type": "point", "position": [0, 0, H_LIGHT], "intensity": 1.0}


def test_columns_run_as_the_position_aov_says():
    """The film columns' ground x (:func:`columns_x`), checked against Mitsuba."""
    scene = edge_scene(SUN, 0.25)
    img = np.asarray(mi.render(scene, integrator=mi.load_dict(
        {"type": "aov", "aovs": "p:position"}), spp=64))
    assert np.allclose(img[..., 0].mean(axis=0), columns_x(0.25), atol=1e-3)


def test_a_sun_s_penumbra_under_an_edge_is_the_closed_form():
    """A 10-degree sun over a straight edge at height 1: the penumbra is 2 tan(5 deg)
    wide and the visible fraction of the sun's cone across it is known. ``raytraced``
    with ``angular_diameter`` follows it (measured RMSE 0.0027 at 64 shadow rays, 32
    spp); its hard shadow does not."""
    truth = sun_truth(10.0, 0.25)
    scene = edge_scene(SUN, 0.25)
    soft = aov(scene, method="raytraced", angular_diameter=10.0, shadow_rays=64)
    hard = aov(scene, method="raytraced")
    print(f"sun: RMSE soft {rmse(soft, truth):.4f}, hard {rmse(hard, truth):.4f}")
    assert rmse(soft, truth) < 0.008 and np.abs(soft - truth).max() < 0.03
    assert rmse(hard, truth) > 0.05


def test_a_tiny_sun_keeps_its_penumbra():
    """A 0.02-degree sun (half-angle 1.7e-4 rad: its cosine rounds to 1 in float32, which
    made Mitsuba's cone warp return the axis alone): the penumbra, 3.5e-4 wide, is still
    the closed form's."""
    half_width = 4e-4
    truth = sun_truth(0.02, half_width)
    soft = aov(edge_scene(SUN, half_width), method="raytraced", angular_diameter=0.02,
               shadow_rays=64)
    print(f"tiny sun: RMSE {rmse(soft, truth):.4f}")
    assert rmse(soft, truth) < 0.01


@pytest.mark.parametrize("scale, offset", [(1.0, 0.0), (1e-4, 0.0), (1e4, 0.0), (1.0, 1e4)])
def test_a_sphere_light_s_penumbra_is_the_closed_form_at_any_scale(scale, offset):
    """A point light given ``light_size`` is a sphere of that diameter sampled in the
    cone it subtends: under the edge its visible fraction is the closed form's, at scales
    1e-4 and 1e4 and moved 1e4 from the origin too."""
    truth = sphere_truth(0.5)
    light = {**POINT, "position": (np.array([0.0, 0.0, H_LIGHT]) * scale + offset).tolist()}
    soft = aov(edge_scene(light, 0.5, scale, (offset,) * 3), method="raytraced",
               light_size=2 * RADIUS * scale, shadow_rays=64)
    print(f"sphere at scale {scale:g}, offset {offset:g}: RMSE {rmse(soft, truth):.4f}")
    assert rmse(soft, truth) < 0.01


def test_a_real_sphere_emitter_sees_the_same_fraction():
    """Mitsuba's own ``sphere`` area emitter of the same diameter, its visibility the
    converged reference's (1024 of Mitsuba's light samples per camera sample): the same
    fraction as ``raytraced`` with a point light of that ``light_size``."""
    sphere = {"type": "sphere", "center": [0, 0, H_LIGHT], "radius": RADIUS,
              "emitter": {"type": "area", "radiance": 1.0}}
    real = converged_visibility(edge_scene(sphere, 0.5), n_light=1024, spp=8)
    real = next(iter(real.values())).mean(axis=0)
    sized = aov(edge_scene(POINT, 0.5), spp=8, method="raytraced", light_size=2 * RADIUS,
                shadow_rays=256)
    print(f"real sphere vs sized point: RMSE {rmse(real, sized):.4f}; real vs closed form "
          f"{rmse(real, sphere_truth(0.5)):.4f}")
    assert rmse(real, sized) < 0.01


@pytest.mark.parametrize("light, props", [("point", {"light_size": 1.0}),
                                          ("spot", {"light_size": 1.0}),
                                          ("directional", {"angular_diameter": 10.0})])
def test_multiview_with_many_views_converges_to_it(light, props):
    """``multiview`` (256 views) gives the sized light the same soft shadow as
    ``raytraced`` with that size (measured RMSE 0.015 / 0.016 / 0.018 at 48^2, 4 spp;
    the hard one is 0.057-0.076 from it)."""
    scene = mi.load_dict(default_scene(light=light, width=48, height=48))
    _, aovs = render_np(scene, {"type": "shadowmap", "method": "multiview", "views": 256,
                                "resolution": 256, **props}, spp=4)
    many = next(iter(aovs.values()))
    _, aovs = render_np(scene, {"type": "shadowmap", "method": "raytraced",
                                "shadow_rays": 256, **props}, spp=4)
    soft = next(iter(aovs.values()))
    _, aovs = render_np(scene, {"type": "shadowmap", "method": "raytraced"}, spp=4)
    hard = next(iter(aovs.values()))
    print(f"{light}: RMSE to multiview soft {rmse(soft, many):.4f}, hard {rmse(hard, many):.4f}")
    assert rmse(soft, many) < 0.025 and rmse(soft, many) < 0.4 * rmse(hard, many)


def test_no_size_is_today_s_ground_truth():
    """``light_size`` 0 and ``angular_diameter`` 0 are the light itself, bit for bit; a
    size no light of the scene takes changes nothing (and warns, as for multiview)."""
    scene = mi.load_dict(default_scene(light="spot", width=32, height=32))
    base = {"type": "shadowmap", "method": "raytraced", "shadow_rays": 4}
    ref, _ = render_np(scene, base, spp=2)
    for props in ({"light_size": 0.0}, {"angular_diameter": 0.0}):
        img, _ = render_np(scene, {**base, **props}, spp=2)
        assert np.array_equal(img, ref)
    with pytest.warns(RuntimeWarning, match="'angular_diameter' = 5 .*directional"):
        img, _ = render_np(scene, {**base, "angular_diameter": 5.0}, spp=2)
    assert np.array_equal(img, ref)


def test_area_lights_keep_their_shape_and_warn():
    """An area light keeps its own shape: ``light_size`` changes nothing there and warns
    as ``multiview`` does."""
    scene = mi.load_dict(default_scene(light="area", width=32, height=32))
    base = {"type": "shadowmap", "method": "raytraced", "shadow_rays": 4}
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        ref, _ = render_np(scene, base, spp=2)
    with pytest.warns(RuntimeWarning, match="'light_size' = 0.5 .*point, spot, projector"):
        img, _ = render_np(scene, {**base, "light_size": 0.5}, spp=2)
    assert np.array_equal(img, ref)


@pytest.mark.parametrize("props, pattern", [
    ({"light_size": -0.1}, "'light_size'.*>= 0"),
    ({"light_size": "big"}, "'light_size'"),
    ({"angular_diameter": -1.0}, "'angular_diameter'.*>= 0"),
    ({"angular_diameter": 45.0}, "'angular_diameter'.*<= 30"),
])
def test_bad_values_name_the_property(props, pattern):
    with pytest.raises(OptionError, match=pattern):
        parse_options({"method": "raytraced", **props})
    with pytest.raises(RuntimeError, match=pattern):   # through Mitsuba's loader
        mi.load_dict({"type": "shadowmap", "method": "raytraced", **props})


@pytest.mark.parametrize("variant", ["llvm_ad_mono", "llvm_ad_spectral"])
def test_mono_and_spectral(variant):
    """The closed form in mono and spectral too."""
    mi.set_variant(variant)
    truth = sun_truth(10.0, 0.25)
    soft = aov(edge_scene(SUN, 0.25), spp=16, method="raytraced", angular_diameter=10.0,
               shadow_rays=64)
    print(f"{variant}: RMSE {rmse(soft, truth):.4f}")
    assert rmse(soft, truth) < 0.01
    truth = sphere_truth(0.5)
    soft = aov(edge_scene(POINT, 0.5), spp=16, method="raytraced", light_size=2 * RADIUS,
               shadow_rays=64)
    assert rmse(soft, truth) < 0.012


def test_compare_scores_each_method_against_the_light_it_models():
    """``compare``'s reference gives the lights the methods' size: ``multiview`` and a
    hard method beside it are scored against the soft truth; ``pcss`` at its default
    (no size) beside ``multiview`` with one gets the hard reference, multiview its own."""
    scene = mi.load_dict(default_scene(light="point", width=32, height=32))
    mv = {"method": "multiview", "light_size": 0.5, "views": 32, "resolution": 128}
    res = harness.compare(scene, ["hard", mv], spp=2)
    assert "light_size=0.5" in res[0].name and "shadow_rays=64" in res[0].name
    assert all(r.scored_against is None for r in res)
    soft_error = res[2].metrics["vis_rmse"]
    res = harness.compare(scene, ["pcss", mv], spp=2)
    assert "light_size" not in res[0].name
    assert res[1].scored_against is None
    assert "light_size=0.5" in res[2].scored_against.name
    assert res[2].metrics["vis_rmse"] == soft_error
    against_hard = harness.compare(scene, [mv], spp=2, reference="raytraced")
    print(f"multiview light_size=0.5: RMSE {soft_error:.4f} against the soft truth, "
          f"{against_hard[1].metrics['vis_rmse']:.4f} against the hard one")
    assert soft_error < 0.5 * against_hard[1].metrics["vis_rmse"]


def test_the_converged_reference_takes_the_size_for_delta_lights():
    """In a scene with an area light and a point light, the converged reference keeps
    the area light's converged visibility and gives the point light the size."""
    d = default_scene(light="point", width=24, height=24)
    d["lamp"] = {"type": "rectangle", "emitter": {"type": "area", "radiance": 2.0},
                 "to_world": T().look_at(origin=[2, 4, 1], target=[0, 0, 0],
                                         up=[0, 1, 0]).scale(0.3)}
    scene = mi.load_dict(d)
    hard = harness.make_reference(scene, "auto", spp=2)
    soft = harness.make_reference(scene, "auto", spp=2, sizes={"light_size": 0.5})
    assert "light_size=0.5" in soft.name
    labels = sorted(soft.visibility)
    assert len(labels) == 2
    changed = [lab for lab in labels
               if not np.array_equal(soft.visibility[lab], hard.visibility[lab])]
    assert len(changed) == 1


def test_tune_renders_the_methods_size_or_names_a_disagreement():
    """``tune`` measures every method against one reference: the size the methods give
    the lights (the raytraced configurations get it too, with their ``shadow_rays``
    searched), and methods giving different sizes are an error naming them."""
    from mi_shadowmap.tune import TuneError, search_grid, tune, tune_sizes
    scene = mi.load_dict(default_scene(light="point", width=32, height=32))
    mv = "multiview:light_size=0.5"
    assert tune_sizes(scene, [harness.method_spec(m) for m in ("hard", mv)]) == \
        {"light_size": 0.5}
    assert tune_sizes(scene, [harness.method_spec("pcss")]) == {}
    with pytest.raises(TuneError, match=r"different sizes .*pcss: light_size=0.*"
                                        r"multiview light_size=0.5: light_size=0.5"):
        tune(scene, 0.05, methods=["pcss", mv])
    grid = search_grid([{"method": "raytraced", "light_size": 0.5}], 32, 32, area_lights=False)
    assert {g["shadow_rays"] for g in grid} == {1, 4, 16}
    assert all("shadow_rays" not in g
               for g in search_grid([{"method": "raytraced"}], 32, 32, area_lights=False))


def test_the_part_of_a_sphere_light_below_the_horizon_is_not_counted():
    """A sized point light just over a floor (a sphere of radius 0.5 at height 0.2: a part
    of it is below every floor point's horizon, and rays there cross a second plane under
    the floor): its points are drawn above the receiver's horizon, as an area light's are
    with ``light_sample='independent'``, so the unoccluded floor reads 1 (min 0.84
    where the rays to the part below counted)."""
    floor = {"type": "rectangle", "to_world": T().scale(4)}
    scene = mi.load_dict({
        "type": "scene",
        "cam": {"type": "orthographic",
                "to_world": T().look_at([0, 0, 0.1], [0, 0, 0], [0, 1, 0]).scale([2, 2, 1]),
                "film": {"type": "hdrfilm", "width": 32, "height": 4,
                         "rfilter": {"type": "box"}}},
        "floor": floor, "under": {"type": "rectangle",
                                  "to_world": T().translate([0, 0, -0.1]).scale(4)},
        "light": {**POINT, "position": [0, 0, 0.2]}})
    v = aov(scene, spp=4, method="raytraced", light_size=1.0, shadow_rays=16)
    print(f"floor under a low sphere light: min {v.min():.4f}")
    assert v.min() > 0.999


def penumbra_errors(scene, rays, spp=32, **props) -> list:
    """The visibility AOV's RMSE, over the penumbra's pixels, of ``raytraced`` with each
    count of ``rays`` sized shadow rays against 2048 of them at the same camera samples."""
    def vis(n):
        _, aovs = render_np(scene, {"type": "shadowmap", "method": "raytraced",
                                    "shadow_rays": n, **props}, spp=spp, seed=5)
        return next(iter(aovs.values()))
    ref = vis(2048)
    penumbra = (ref > 0.02) & (ref < 0.98)
    return [rmse(vis(n)[penumbra], ref[penumbra]) for n in rays]


@pytest.mark.parametrize("light, half_width, props", [
    (POINT, 0.5, {"light_size": 2 * RADIUS}),
    (SUN, 0.25, {"angular_diameter": 10.0}),
])
def test_sized_shadow_rays_are_stratified(light, half_width, props):
    """The sized shadow rays are drawn in the strata of the integrator's stratified light
    samples (``Lookup.u_light``), each jittered in its cell: the penumbra's error falls
    about as rays^(-3/4) (16 -> 256 rays: 7.7x, measured), not as rays^(-1/2) (4x: the
    independent draws, 4.1-4.8x measured; the grid's shifted points without the jitter,
    4.8x)."""
    e16, e256 = penumbra_errors(edge_scene(light, half_width), (16, 256), **props)
    print(f"{props}: RMSE 16 rays {e16:.5f}, 256 rays {e256:.5f}, ratio {e16 / e256:.2f}")
    assert e16 / e256 > 6.0


def test_a_sweep_scores_each_row_against_the_light_it_models():
    """``sweep``'s automatic reference gives the lights the size the rows give them, as
    ``compare``'s does: ``pcss:light_size=0.5``, ``multiview:light_size=0.5`` and ``hard``
    (no such property: the first size given) against a sized ``raytraced``, ``pcss``
    without a size against the hard one. The sized reference is ``raytraced`` with the
    size at the sweep's reference spp and seed, bit for bit."""
    scene = mi.load_dict(default_scene(light="point", width=32, height=32))
    mv = {"method": "multiview", "light_size": 0.5, "views": 32, "resolution": 128}
    table = harness.sweep(scene, [{"method": "pcss", "light_size": [0.5, 0.0]}, mv,
                                  {"method": "hard"}], spp=16, repeats=1, ref_spp=16,
                          ref_shadow_rays=16, progress=False)
    by_name = {row["name"]: row for row in table.rows}
    assert "light_size=0.5" in table.reference.name
    assert "shadow_rays=16" in table.reference.name
    unsized = next(r for r in table.results
                   if r.method == "pcss" and not r.params.get("light_size"))
    hard_ref = unsized.scored_against
    assert hard_ref is not None and "light_size" not in hard_ref.name
    assert by_name[unsized.name]["scored_against"] == hard_ref.name
    for r in table.results:
        if r is not unsized:
            assert by_name[r.name]["scored_against"] == table.reference.name, r.name
    # the reference is raytraced with the size, at the sweep's reference spp and seed
    sized_ref = run_method(scene, "raytraced", spp=16, seed=derived_seed(0, 1),
                           light_size=0.5, shadow_rays=16)
    assert all(np.array_equal(sized_ref.visibility[k], v)
               for k, v in table.reference.visibility.items())
    multiview = next(r for r in table.results if r.method == "multiview")
    assert multiview.metrics["vis_rmse"] == harness.score(multiview, sized_ref)["vis_rmse"]
    own = multiview.metrics["vis_penumbra_rmse"]
    against_hard = harness.score(multiview, hard_ref)["vis_penumbra_rmse"]
    print(f"multiview light_size=0.5: penumbra RMSE {own:.4f} against its reference, "
          f"{against_hard:.4f} against the hard one")
