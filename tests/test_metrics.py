"""Tests for mi_shadowmap.metrics (pure NumPy; no Mitsuba needed)."""

import math
import warnings

import numpy as np
import pytest
from skimage.metrics import structural_similarity

from mi_shadowmap import metrics as M


@pytest.fixture
def rng():
    return np.random.default_rng(1234)


# --------------------------------------------------------------------------- #
# Validation
# --------------------------------------------------------------------------- #
@pytest.mark.parametrize("fn", [M.rmse, M.mae, M.relative_mse, M.psnr, M.ssim, M.flip])
def test_shape_mismatch_names_argument(fn):
    with pytest.raises(ValueError, match=r"'test'.*\(8, 9\).*'ref'.*\(8, 8\)"):
        fn(np.zeros((8, 8)), np.zeros((8, 9)))


@pytest.mark.parametrize("fn", [M.rmse, M.mae, M.relative_mse, M.psnr, M.ssim, M.flip])
def test_nan_names_argument_and_count(fn):
    test = np.zeros((8, 8))
    test[0, 0] = np.nan
    test[1, 1] = np.inf
    with pytest.raises(ValueError, match=r"'test' has 2 non-finite"):
        fn(np.zeros((8, 8)), test)
    with pytest.raises(ValueError, match=r"'ref' has 2 non-finite"):
        fn(test, np.zeros((8, 8)))


def test_visibility_validation_names():
    with pytest.raises(ValueError, match="'test_vis'"):
        M.misclassified(np.zeros((2, 2)), np.zeros((2, 3)))
    with pytest.raises(ValueError, match="'ref_vis' has 1 non-finite"):
        M.visibility_metrics(np.array([[np.nan, 0.0]]), np.zeros((1, 2)))
    with pytest.raises(ValueError, match="'mask'"):
        M.misclassified(np.zeros((2, 2)), np.zeros((2, 2)), mask=np.ones((3, 3), bool))
    with pytest.raises(ValueError, match="no pixels"):
        M.misclassified(np.zeros((2, 2)), np.zeros((2, 2)), mask=np.zeros((2, 2), bool))


def test_empty_rejected():
    with pytest.raises(ValueError, match="empty"):
        M.rmse([], [])


# --------------------------------------------------------------------------- #
# Pixel-wise metrics
# --------------------------------------------------------------------------- #
def test_rmse_mae_constant_offset(rng):
    ref = rng.random((5, 6, 3))
    assert M.rmse(ref, ref + 0.1) == pytest.approx(0.1)
    assert M.mae(ref, ref - 0.1) == pytest.approx(0.1)
    assert M.rmse(ref, ref) == 0.0
    assert isinstance(M.rmse(ref, ref), float)


def test_rmse_mae_known_values():
    ref = np.zeros((2, 2))
    test = np.array([[1.0, -1.0], [0.0, 0.0]])
    assert M.rmse(ref, test) == pytest.approx(math.sqrt(0.5))
    assert M.mae(ref, test) == pytest.approx(0.5)


def test_relative_mse_known_value():
    ref = np.array([[1.0, 0.0]])
    test = np.array([[2.0, 0.1]])
    expected = 0.5 * (1.0 / (1.0 + 0.01) + 0.01 / 0.01)
    assert M.relative_mse(ref, test) == pytest.approx(expected)
    assert M.relative_mse(ref, test, eps=1.0) == pytest.approx(0.5 * (0.5 + 0.01))
    with pytest.raises(ValueError, match="eps"):
        M.relative_mse(ref, test, eps=0.0)


# --------------------------------------------------------------------------- #
# PSNR / SSIM
# --------------------------------------------------------------------------- #
def test_psnr_identical_is_inf_without_warning(rng):
    img = rng.random((8, 8))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert M.psnr(img, img) == float("inf")
        assert M.psnr(np.zeros((8, 8)), np.zeros((8, 8))) == float("inf")


def test_psnr_matches_formula(rng):
    ref = rng.random((16, 16, 3)) * 4.0
    test = ref + rng.normal(scale=0.1, size=ref.shape)
    mse = np.mean((test - ref) ** 2)
    dr = ref.max() - ref.min()
    assert M.psnr(ref, test) == pytest.approx(10 * np.log10(dr ** 2 / mse))
    assert M.psnr(ref, test, data_range=1.0) == pytest.approx(10 * np.log10(1.0 / mse))


def test_psnr_constant_ref_uses_unit_range():
    ref = np.full((4, 4), 0.5)
    test = ref + 0.1
    assert M.psnr(ref, test) == pytest.approx(10 * np.log10(1.0 / 0.01))
    with pytest.raises(ValueError, match="data_range"):
        M.psnr(ref, test, data_range=0.0)


def test_ssim_identical_is_one(rng):
    img = rng.random((16, 16))
    assert M.ssim(img, img) == pytest.approx(1.0)
    rgb = rng.random((16, 16, 3))
    assert M.ssim(rgb, rgb) == pytest.approx(1.0)


def test_ssim_matches_skimage(rng):
    ref, test = rng.random((20, 24)), rng.random((20, 24))
    dr = ref.max() - ref.min()
    assert M.ssim(ref, test) == pytest.approx(structural_similarity(ref, test, data_range=dr))
    ref3, test3 = rng.random((20, 24, 3)), rng.random((20, 24, 3))
    dr3 = ref3.max() - ref3.min()
    expected = structural_similarity(ref3, test3, data_range=dr3, channel_axis=-1)
    assert M.ssim(ref3, test3) == pytest.approx(expected)
    assert M.ssim(ref3, test3) < 0.5


def test_ssim_too_small_raises():
    with pytest.raises(ValueError, match="at least 7x7"):
        M.ssim(np.zeros((6, 10)), np.zeros((6, 10)))


# --------------------------------------------------------------------------- #
# FLIP
# --------------------------------------------------------------------------- #
def test_flip_identical_is_zero(rng):
    img = rng.random((16, 16, 3))
    mean, err = M.flip(img, img)
    assert mean == 0.0
    assert err.shape == (16, 16)
    assert np.all(err == 0.0)


def test_flip_known_difference_positive(rng):
    ref = rng.random((16, 16))  # grayscale is promoted to 3 channels
    mean, err = M.flip(ref, 1.0 - ref)
    assert isinstance(mean, float)
    assert 0.0 < mean <= 1.0
    assert err.shape == (16, 16)
    assert mean == pytest.approx(err.mean(), rel=1e-4)


def test_flip_hdr(rng):
    ref = rng.random((16, 16, 3)) * 5.0
    assert M.flip(ref, ref, mode="HDR")[0] == 0.0
    assert M.flip(ref, ref * 2.0, mode="HDR")[0] > 0.0
    with pytest.raises(ValueError, match="negative"):
        M.flip(ref, -ref, mode="HDR")


def test_flip_ldr_clips_inputs(rng):
    ref = rng.random((16, 16, 3))
    # values above 1 / below 0 are clipped, so these compare equal to ref
    over = np.where(ref > 0.5, 1.0, 0.0)
    assert M.flip(over, over * 3.0 - 1.0)[0] == 0.0


@pytest.mark.parametrize("mode", ["ldr", "XYZ", None])
def test_flip_bad_mode_is_valueerror_not_systemexit(mode):
    img = np.zeros((8, 8, 3))
    with pytest.raises(ValueError, match="mode"):
        M.flip(img, img, mode=mode)


def test_flip_bad_channels():
    with pytest.raises(ValueError, match="channels"):
        M.flip(np.zeros((8, 8, 4)), np.zeros((8, 8, 4)))
    with pytest.raises(ValueError, match="HxW"):
        M.flip(np.zeros(8), np.zeros(8))


# --------------------------------------------------------------------------- #
# Visibility metrics
# --------------------------------------------------------------------------- #
def test_misclassified_2x2():
    ref = np.array([[1.0, 1.0], [0.0, 0.0]])
    test = np.array([[0.2, 1.0], [0.9, 0.0]])  # one false shadow, one false lit
    r = M.misclassified(ref, test)
    assert r == {"misclassified": 0.5, "false_shadow": 0.25, "false_lit": 0.25, "n_pixels": 4}


def test_misclassified_threshold_is_inclusive_lit():
    # exactly 0.5 counts as lit
    r = M.misclassified(np.array([0.5, 0.5]), np.array([0.49, 1.0]))
    assert r["false_shadow"] == 0.5 and r["false_lit"] == 0.0


def test_misclassified_mask():
    ref = np.array([[1.0, 1.0], [0.0, 0.0]])
    test = np.array([[0.2, 1.0], [0.9, 0.0]])
    mask = np.array([[True, True], [False, False]])
    r = M.misclassified(ref, test, mask=mask)
    assert r == {"misclassified": 0.5, "false_shadow": 0.5, "false_lit": 0.0, "n_pixels": 2}


def test_penumbra_mask():
    ref = np.array([[0.0, 1e-8, 0.3], [1.0 - 1e-8, 1.0, 0.999]])
    expected = np.array([[False, False, True], [False, False, True]])
    np.testing.assert_array_equal(M.penumbra_mask(ref), expected)


def test_penumbra_rmse():
    ref = np.array([[0.0, 0.5], [1.0, 0.25]])
    test = np.array([[1.0, 0.6], [0.0, 0.55]])  # umbra/lit errors ignored
    assert M.penumbra_rmse(ref, test) == pytest.approx(math.sqrt((0.01 + 0.09) / 2))


def test_penumbra_rmse_none_without_penumbra():
    ref = np.array([[0.0, 1.0]])
    assert M.penumbra_rmse(ref, ref) is None


def test_visibility_metrics():
    ref = np.array([[1.0, 1.0], [0.0, 0.5]])
    test = np.array([[0.0, 1.0], [0.0, 0.5]])
    r = M.visibility_metrics(ref, test)
    assert r["rmse"] == pytest.approx(0.5)
    assert r["mae"] == pytest.approx(0.25)
    assert r["false_shadow"] == 0.25 and r["false_lit"] == 0.0
    assert r["misclassified"] == 0.25 and r["n_pixels"] == 4
    assert r["penumbra_rmse"] == 0.0
    assert r["penumbra_fraction"] == 0.25
    r = M.visibility_metrics(ref, test, mask=np.array([[False, True], [True, False]]))
    assert r["rmse"] == 0.0 and r["misclassified"] == 0.0 and r["n_pixels"] == 2
    assert r["penumbra_rmse"] is None and r["penumbra_fraction"] == 0.0


def test_image_metrics(rng):
    ref = rng.random((16, 16, 3))
    r = M.image_metrics(ref, ref)
    assert set(r) == {"rmse", "mae", "relative_mse", "psnr", "ssim", "flip"}
    assert r["rmse"] == 0.0 and r["psnr"] == float("inf")
    assert r["ssim"] == pytest.approx(1.0) and r["flip"] == 0.0
    test = ref + 0.05
    r = M.image_metrics(ref, test)
    assert r["rmse"] == pytest.approx(0.05)
    tm = lambda x: np.clip(x, 0, 1) ** (1 / 2.2)  # noqa: E731
    assert r["flip"] == pytest.approx(M.flip(tm(ref), tm(test))[0])
    assert r["psnr"] == pytest.approx(M.psnr(tm(ref), tm(test), data_range=1.0))
    assert r["ssim"] == pytest.approx(M.ssim(tm(ref), tm(test), data_range=1.0))
    assert all(isinstance(v, float) for v in r.values())


def test_image_metrics_are_not_set_by_a_bright_light(rng):
    """A visible light (one pixel at 1000 in both images) does not change PSNR, SSIM or
    FLIP: on linear values their range was the light's, and PSNR went from 20.2 to
    86.2 dB and SSIM from 0.944 to 1.000 with the same errors elsewhere."""
    ref = rng.random((32, 32, 3)) * 0.5
    test = ref + rng.normal(0.0, 0.05, ref.shape)
    lit_ref, lit_test = ref.copy(), test.copy()
    lit_ref[0, 0] = lit_test[0, 0] = 1000.0
    a, b = M.image_metrics(ref, test), M.image_metrics(lit_ref, lit_test)
    assert b["psnr"] == pytest.approx(a["psnr"], abs=0.1)
    assert b["ssim"] == pytest.approx(a["ssim"], abs=0.01)
    assert b["flip"] == pytest.approx(a["flip"], abs=0.01)


def test_image_metrics_use_hdr_flip_on_bright_references(rng):
    """A reference with more than 1 % of its values above 1: FLIP is HDR-FLIP on the
    linear values (LDR-FLIP would see them clipped to white)."""
    ref = rng.random((32, 32, 3)) * 4.0
    test = ref * 0.8
    r = M.image_metrics(ref, test)
    assert r["flip"] == pytest.approx(M.flip(ref, test, "HDR")[0])
    assert r["flip"] > 0.01


# --------------------------------------------------------------------------- #
# Misc
# --------------------------------------------------------------------------- #
def test_distinct_levels():
    v = np.array([0.0, 0.25, 0.25 + 1e-9, 0.5, 1.0, 1.0, -0.0])
    assert M.distinct_levels(v) == 4
    assert M.distinct_levels(v, decimals=12) == 5
    assert M.distinct_levels(np.linspace(0, 1, 5).reshape(5, 1)) == 5


def test_pareto_front():
    times = [1.0, 2.0, 2.0, 3.0, 0.5, 1.0]
    errors = [0.5, 0.2, 0.3, 0.2, 1.0, 0.5]
    # (2,0.3) dominated by (2,0.2); (3,0.2) dominated by (2,0.2);
    # (1,0.5) twice: duplicates do not dominate each other
    expected = [True, True, False, False, True, True]
    np.testing.assert_array_equal(M.pareto_front(times, errors), expected)
    with pytest.raises(ValueError, match="'errors'"):
        M.pareto_front([1.0, 2.0], [1.0])


def test_module_has_no_mitsuba_dependency():
    src = open(M.__file__).read()
    for name in ("mitsuba", "drjit"):
        assert f"import {name}" not in src
        assert f"from {name}" not in src


def test_dilate_grows_a_mask_by_the_margin():
    from mi_shadowmap.metrics import dilate
    m = np.zeros((9, 9), bool)
    m[4, 4] = True
    grown = dilate(m, 2)
    assert grown.sum() == 25 and grown[2:7, 2:7].all() and not grown[1, 4]
    assert np.array_equal(dilate(m, 0), m)


def test_dilate_stops_at_the_borders():
    """A mask touching the left edge grows inwards only (before: it wrapped around and
    grew along the right edge too, so inverse.receiver_mask lost the ground there)."""
    from mi_shadowmap.metrics import dilate
    m = np.zeros((6, 8), bool)
    m[0, 0] = True
    grown = dilate(m, 2)
    assert grown.sum() == 9 and grown[:3, :3].all()
    assert not grown[:, -2:].any() and not grown[-2:, :].any()
    rng = np.random.default_rng(3)
    r = rng.random((12, 10)) < 0.1
    brute = np.zeros_like(r)      # against the definition: any set pixel within margin
    for y, x in zip(*np.nonzero(r)):
        brute[max(y - 3, 0):y + 4, max(x - 3, 0):x + 4] = True
    assert np.array_equal(dilate(r, 3), brute)
