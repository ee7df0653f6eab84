"""Image and visibility error metrics for comparing shadow renderings.

This module is deliberately independent of Mitsuba and Dr.Jit: every function
takes array-likes (converted to ``float64`` NumPy arrays) and returns plain
Python floats, ints, dicts, or NumPy arrays.

All public functions validate their inputs and raise ``ValueError`` with a
message naming the offending argument when

* two arrays that must be compared have different shapes,
* an array contains NaN or infinite values,
* an array is empty.

Images may be ``HxW`` (grayscale) or ``HxWxC``.  Visibility buffers hold
values in ``[0, 1]``: 1 means fully lit, 0 fully shadowed.
"""

import numpy as np
from skimage.metrics import peak_signal_noise_ratio, structural_similarity

__all__ = [
    "rmse", "mae", "relative_mse", "psnr", "ssim", "flip",
    "misclassified", "penumbra_mask", "penumbra_rmse", "visibility_metrics",
    "image_metrics", "distinct_levels", "pareto_front",
]

_SSIM_WIN = 7  # skimage's default SSIM window size


# --------------------------------------------------------------------------- #
# Validation helpers
# --------------------------------------------------------------------------- #
def _as_array(x, name):
    """Convert ``x`` to a non-empty, finite float64 array or raise ValueError."""
    a = np.asarray(x, dtype=np.float64)
    if a.size == 0:
        raise ValueError(f"argument '{name}' is empty (shape {a.shape})")
    n_bad = int(a.size - np.count_nonzero(np.isfinite(a)))
    if n_bad:
        raise ValueError(
            f"argument '{name}' has {n_bad} non-finite value(s) (NaN or inf)")
    return a


def _pair(a, b, name_a="ref", name_b="test"):
    """Validate two arrays and check that their shapes match."""
    a, b = _as_array(a, name_a), _as_array(b, name_b)
    if a.shape != b.shape:
        raise ValueError(
            f"shape mismatch: '{name_b}' has shape {b.shape} but "
            f"'{name_a}' has shape {a.shape}")
    return a, b


def _check_image(a, name):
    if a.ndim not in (2, 3):
        raise ValueError(
            f"argument '{name}' must be an HxW or HxWxC image, got shape {a.shape}")


def _mask(mask, shape):
    """Validate an optional boolean mask of the given shape."""
    if mask is None:
        return np.ones(shape, dtype=bool)
    m = np.asarray(mask)
    if m.shape != shape:
        raise ValueError(
            f"shape mismatch: 'mask' has shape {m.shape} but 'ref_vis' has shape {shape}")
    if m.dtype != bool:
        raise ValueError(f"argument 'mask' must be a boolean array, got dtype {m.dtype}")
    if not m.any():
        raise ValueError("argument 'mask' selects no pixels")
    return m


def _data_range(ref, data_range):
    if data_range is None:
        r = float(ref.max() - ref.min())
        return r if r > 0 else 1.0
    r = float(data_range)
    if not np.isfinite(r) or r <= 0:
        raise ValueError(f"argument 'data_range' must be finite and > 0, got {data_range}")
    return r


# --------------------------------------------------------------------------- #
# Pixel-wise image metrics
# --------------------------------------------------------------------------- #
def rmse(ref, test):
    """Root mean squared error, ``sqrt(mean((test - ref)**2))``.

    Parameters
    ----------
    ref, test : array_like
        Arrays of identical shape (any shape, e.g. HxW or HxWxC).

    Returns
    -------
    float
    """
    ref, test = _pair(ref, test)
    return float(np.sqrt(np.mean((test - ref) ** 2)))


def mae(ref, test):
    """Mean absolute error, ``mean(|test - ref|)``.

    Parameters
    ----------
    ref, test : array_like
        Arrays of identical shape.

    Returns
    -------
    float
    """
    ref, test = _pair(ref, test)
    return float(np.mean(np.abs(test - ref)))


def relative_mse(ref, test, eps=1e-2):
    """Relative MSE, ``mean((test - ref)**2 / (ref**2 + eps))``.

    Parameters
    ----------
    ref, test : array_like
        Arrays of identical shape.
    eps : float, optional
        Positive regulariser that avoids division by zero in dark pixels.

    Returns
    -------
    float
    """
    ref, test = _pair(ref, test)
    if not np.isfinite(eps) or eps <= 0:
        raise ValueError(f"argument 'eps' must be finite and > 0, got {eps}")
    return float(np.mean((test - ref) ** 2 / (ref ** 2 + eps)))


def psnr(ref, test, data_range=None):
    """Peak signal-to-noise ratio in dB (``skimage.metrics.peak_signal_noise_ratio``).

    Parameters
    ----------
    ref, test : array_like
        HxW or HxWxC images of identical shape.
    data_range : float, optional
        Dynamic range of the images.  Defaults to ``ref.max() - ref.min()``,
        or 1.0 if ``ref`` is constant.

    Returns
    -------
    float
        ``10 * log10(data_range**2 / mse)``; ``float('inf')`` for identical
        images (no divide-by-zero warning is emitted).
    """
    ref, test = _pair(ref, test)
    _check_image(ref, "ref")
    dr = _data_range(ref, data_range)
    if np.array_equal(ref, test):
        return float("inf")
    return float(peak_signal_noise_ratio(ref, test, data_range=dr))


def ssim(ref, test, data_range=None):
    """Structural similarity index (``skimage.metrics.structural_similarity``).

    Parameters
    ----------
    ref, test : array_like
        HxW or HxWxC images of identical shape; for HxWxC the last axis is
        treated as channels (``channel_axis=-1``).  Both H and W must be >= 7
        (skimage's default 7x7 window).
    data_range : float, optional
        As for :func:`psnr`.

    Returns
    -------
    float
        Mean SSIM, 1.0 for identical images.
    """
    ref, test = _pair(ref, test)
    _check_image(ref, "ref")
    h, w = ref.shape[:2]
    if min(h, w) < _SSIM_WIN:
        raise ValueError(
            f"ssim needs images of at least {_SSIM_WIN}x{_SSIM_WIN} pixels, "
            f"got 'ref' with shape {ref.shape}")
    kw = {"channel_axis": -1} if ref.ndim == 3 else {}
    return float(structural_similarity(
        ref, test, data_range=_data_range(ref, data_range), **kw))


def _flip_input(a, name, mode):
    _check_image(a, name)
    if a.ndim == 2:
        a = a[:, :, None]
    if a.shape[2] == 1:
        a = np.repeat(a, 3, axis=2)
    elif a.shape[2] != 3:
        raise ValueError(
            f"argument '{name}' must have 1 or 3 channels for FLIP, got shape {a.shape}")
    if mode == "LDR":
        a = np.clip(a, 0.0, 1.0)
    elif a.min() < 0:
        raise ValueError(f"argument '{name}' has negative values; HDR-FLIP needs values >= 0")
    return np.ascontiguousarray(a, dtype=np.float32)


def flip(ref, test, mode="LDR"):
    """NVIDIA FLIP perceptual error via the ``flip_evaluator`` package.

    All arguments are validated *before* calling ``flip_evaluator`` (which
    otherwise calls ``sys.exit`` on bad input).

    Parameters
    ----------
    ref, test : array_like
        HxW, HxWx1 or HxWx3 images of identical shape.  Grayscale images are
        repeated to 3 channels.
    mode : {"LDR", "HDR"}
        ``"LDR"``: inputs are treated as sRGB-encoded display values and are
        **clipped** to [0, 1].  ``"HDR"``: inputs are linear radiance and must
        be non-negative (ValueError otherwise).

    Returns
    -------
    mean_error : float
        Mean FLIP error (0 for identical images, at most 1).
    error_map : numpy.ndarray
        Per-pixel FLIP error, float64, shape HxW.
    """
    if mode not in ("LDR", "HDR"):
        raise ValueError(f"argument 'mode' must be 'LDR' or 'HDR', got {mode!r}")
    ref, test = _pair(ref, test)
    ref, test = _flip_input(ref, "ref", mode), _flip_input(test, "test", mode)
    import flip_evaluator  # local import: compiled extension, only needed here
    err_map, mean, _ = flip_evaluator.evaluate(ref, test, mode, applyMagma=False)
    return float(mean), np.asarray(err_map, dtype=np.float64).reshape(ref.shape[:2])


# --------------------------------------------------------------------------- #
# Visibility (shadow) metrics
# --------------------------------------------------------------------------- #
def misclassified(ref_vis, test_vis, threshold=0.5, mask=None):
    """Fraction of pixels whose lit/shadowed classification differs.

    A pixel is *lit* if its visibility is ``>= threshold`` and *shadowed*
    otherwise.

    Parameters
    ----------
    ref_vis, test_vis : array_like
        Visibility buffers of identical shape (1 = lit, 0 = shadowed).
    threshold : float, optional
        Classification threshold, default 0.5.
    mask : array_like of bool, optional
        Valid pixels (same shape as ``ref_vis``); default all.  Must select
        at least one pixel.

    Returns
    -------
    dict
        ``false_shadow``: fraction lit in ref but shadowed in test (shadow
        acne / over-darkening); ``false_lit``: fraction shadowed in ref but
        lit in test (light leaking / peter-panning); ``misclassified``: their
        sum; ``n_pixels``: number of pixels in the mask (the denominator).
    """
    ref, test = _pair(ref_vis, test_vis, "ref_vis", "test_vis")
    m = _mask(mask, ref.shape)
    ref_lit, test_lit = ref[m] >= threshold, test[m] >= threshold
    n = int(m.sum())
    fs = np.count_nonzero(ref_lit & ~test_lit) / n
    fl = np.count_nonzero(~ref_lit & test_lit) / n
    return {"misclassified": float(fs + fl), "false_shadow": float(fs),
            "false_lit": float(fl), "n_pixels": n}


def penumbra_mask(ref_vis, lo=0.0, hi=1.0, tol=1e-6):
    """Boolean mask of penumbra pixels: ``lo + tol < ref_vis < hi - tol``.

    Parameters
    ----------
    ref_vis : array_like
        Reference visibility buffer.
    lo, hi : float, optional
        Fully-shadowed and fully-lit values.
    tol : float, optional
        Tolerance: values within ``tol`` of ``lo`` or ``hi`` are not penumbra.

    Returns
    -------
    numpy.ndarray of bool
        Same shape as ``ref_vis``.
    """
    ref = _as_array(ref_vis, "ref_vis")
    return (ref > lo + tol) & (ref < hi - tol)


def penumbra_rmse(ref_vis, test_vis, mask=None):
    """RMSE restricted to the reference penumbra (see :func:`penumbra_mask`).

    Parameters
    ----------
    ref_vis, test_vis : array_like
        Visibility buffers of identical shape.
    mask : array_like of bool, optional
        Additional restriction to valid pixels.

    Returns
    -------
    float or None
        ``None`` (never NaN) if there are no penumbra pixels.
    """
    ref, test = _pair(ref_vis, test_vis, "ref_vis", "test_vis")
    pm = penumbra_mask(ref) & _mask(mask, ref.shape)
    if not pm.any():
        return None
    return float(np.sqrt(np.mean((test[pm] - ref[pm]) ** 2)))


def visibility_metrics(ref_vis, test_vis, mask=None):
    """All visibility metrics at once, restricted to ``mask`` if given.

    Returns
    -------
    dict
        ``rmse``, ``mae``, ``misclassified``, ``false_shadow``, ``false_lit``,
        ``n_pixels`` (threshold 0.5, see :func:`misclassified`),
        ``penumbra_rmse`` (float or None) and ``penumbra_fraction`` (fraction
        of masked pixels lying in the reference penumbra).
    """
    ref, test = _pair(ref_vis, test_vis, "ref_vis", "test_vis")
    m = _mask(mask, ref.shape)
    out = {"rmse": rmse(ref[m], test[m]), "mae": mae(ref[m], test[m])}
    out.update(misclassified(ref, test, threshold=0.5, mask=m))
    out["penumbra_rmse"] = penumbra_rmse(ref, test, mask=m)
    out["penumbra_fraction"] = float(penumbra_mask(ref)[m].mean())
    return out


#: :func:`image_metrics` uses HDR-FLIP when more than this fraction of the reference's
#: values exceed 1 (what LDR-FLIP's display values would clip).
HDR_FRACTION = 0.01


def display(x):
    """Display values of a linear image: ``clip(x, 0, 1) ** (1 / 2.2)``."""
    return np.clip(x, 0.0, 1.0) ** (1.0 / 2.2)


def image_metrics(ref_img, test_img):
    """All image metrics at once.

    ``rmse``, ``mae`` and ``relative_mse`` are computed on the linear input values.
    ``psnr`` and ``ssim`` on the display values :func:`display` (data range 1): on
    linear values their range is the reference's brightest pixel, so a visible light
    (18 against a median of 0.025) set PSNR and SSIM alone (``hard`` and ``pcss``:
    35.51 dB both, SSIM 0.9945 / 0.9948, against 0.866 / 0.900 on display values).
    ``flip`` is LDR-FLIP on the display values, or HDR-FLIP on the linear values
    (negatives clipped to 0; its exposures span the reference's range) when more than
    :data:`HDR_FRACTION` of the reference's values exceed 1, which LDR-FLIP would see
    clipped (64 % of a sky-lit scene's pixels).

    Returns
    -------
    dict
        Keys ``rmse``, ``mae``, ``relative_mse``, ``psnr``, ``ssim``, ``flip``.
    """
    ref, test = _pair(ref_img, test_img, "ref_img", "test_img")
    _check_image(ref, "ref_img")
    d_ref, d_test = display(ref), display(test)
    if float(np.mean(ref > 1.0)) > HDR_FRACTION:
        fl = flip(np.maximum(ref, 0.0), np.maximum(test, 0.0), "HDR")[0]
    else:
        fl = flip(d_ref, d_test, "LDR")[0]
    return {"rmse": rmse(ref, test), "mae": mae(ref, test),
            "relative_mse": relative_mse(ref, test),
            "psnr": psnr(d_ref, d_test, data_range=1.0),
            "ssim": ssim(d_ref, d_test, data_range=1.0), "flip": fl}


# --------------------------------------------------------------------------- #
# Misc
# --------------------------------------------------------------------------- #
def distinct_levels(values, decimals=6):
    """Number of distinct values after rounding to ``decimals`` decimals.

    Useful to count the shadow levels produced by a filter (e.g. PCF with
    N taps gives at most N + 1 levels).

    Returns
    -------
    int
    """
    v = _as_array(values, "values")
    return int(np.unique(np.round(v, decimals)).size)


def dilate(mask, margin: int) -> np.ndarray:
    """``mask`` (2-D bool) grown by ``margin`` pixels in every direction (a square
    neighbourhood, clipped at the image's borders): e.g. the pixels near an object on
    screen. (It wrapped around the borders before: an object touching the left edge grew
    the mask along the right one.)"""
    mask = np.asarray(mask, bool)
    if margin <= 0:
        return mask.copy()
    H, W = mask.shape
    out = np.zeros_like(mask)
    rows = np.pad(mask, ((margin, margin), (0, 0)))
    for d in range(2 * margin + 1):          # a square is a row dilation of a column one
        out |= rows[d:d + H]
    cols = np.pad(out, ((0, 0), (margin, margin)))
    out = np.zeros_like(mask)
    for d in range(2 * margin + 1):
        out |= cols[:, d:d + W]
    return out


def pareto_front(times, errors):
    """Mask of Pareto-optimal points (lower time and lower error are better).

    A point is dominated if another point has ``<=`` time and ``<=`` error
    with at least one strict inequality.  Duplicate points do not dominate
    each other.

    Parameters
    ----------
    times, errors : array_like
        1-D arrays of equal length.

    Returns
    -------
    numpy.ndarray of bool
        True for points that are not dominated.
    """
    t, e = _pair(times, errors, "times", "errors")
    if t.ndim != 1:
        raise ValueError(f"argument 'times' must be 1-D, got shape {t.shape}")
    le = (t[None, :] <= t[:, None]) & (e[None, :] <= e[:, None])
    lt = (t[None, :] < t[:, None]) | (e[None, :] < e[:, None])
    return ~np.any(le & lt, axis=1)  # row i: is i dominated by some j?
