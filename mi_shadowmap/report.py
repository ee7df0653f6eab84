"""Write comparison outputs: float EXR (OpenEXR), PNG previews, CSV and JSON."""
from __future__ import annotations

import csv
import json
import math
import os
import re

import numpy as np


def _safe(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.=-]+", "_", name).strip("_")


def write_exr(path: str, channels: dict) -> None:
    """Write float32 channels (``name -> (H, W)``) to one EXR via OpenEXR."""
    import OpenEXR
    data = {k: np.ascontiguousarray(v, dtype=np.float32) for k, v in channels.items()}
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with OpenEXR.File(header, data) as f:
        f.write(path)


def read_exr(path: str) -> dict:
    import OpenEXR
    with OpenEXR.File(path, separate_channels=True) as f:
        return {k: np.array(v.pixels) for k, v in f.channels().items()}


def tonemap(img: np.ndarray) -> np.ndarray:
    """Linear RGB -> 8-bit sRGB-ish preview (clip, gamma 2.2)."""
    return (np.clip(img, 0, 1) ** (1 / 2.2) * 255 + 0.5).astype(np.uint8)


def write_png(path: str, img: np.ndarray) -> None:
    import matplotlib.image
    arr = img if img.dtype == np.uint8 else tonemap(img)
    matplotlib.image.imsave(path, arr)


def write_results(results, out_dir: str) -> dict:
    """Write every result's image/AOVs/error maps, previews and the metrics tables.

    Returns the paths written, by kind.
    """
    os.makedirs(out_dir, exist_ok=True)
    if not os.access(out_dir, os.W_OK):
        raise PermissionError(f"output folder is not writable: {out_dir}")
    written = {"exr": [], "png": [], "table": []}
    ref = results[0]
    for r in results:
        base = os.path.join(out_dir, _safe(r.name))
        ch = {"R": r.image[..., 0], "G": r.image[..., 1], "B": r.image[..., 2]}
        for label, v in r.visibility.items():
            ch[f"vis_{label}.Y"] = v
            ch[f"err_{label}.Y"] = v - ref.visibility[label]
        write_exr(base + ".exr", ch)
        written["exr"].append(base + ".exr")
        write_png(base + ".png", r.image)
        written["png"].append(base + ".png")
    sheet = os.path.join(out_dir, "contact_sheet.png")
    contact_sheet(results, sheet)
    written["png"].append(sheet)
    rows = [r.row() for r in results]
    keys = list(dict.fromkeys(k for row in rows for k in row))
    with open(os.path.join(out_dir, "metrics.csv"), "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=keys)
        w.writeheader()
        w.writerows(rows)
    with open(os.path.join(out_dir, "metrics.json"), "w") as f:
        json.dump([{k: _jsonable(v) for k, v in row.items()} for row in rows], f, indent=2)
    written["table"] += [os.path.join(out_dir, "metrics.csv"),
                         os.path.join(out_dir, "metrics.json")]
    return written


def _jsonable(v):
    if isinstance(v, (np.floating, np.integer)):
        v = v.item()
    if isinstance(v, float) and not math.isfinite(v):
        return str(v)
    return v


def contact_sheet(results, path: str) -> None:
    """Images (top row) and visibility error heatmaps against the reference (bottom)."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    ref = results[0]
    n = len(results)
    fig, axes = plt.subplots(2, n, figsize=(2.6 * n, 5.4), squeeze=False)
    for c, r in enumerate(results):
        axes[0, c].imshow(tonemap(r.image))
        axes[0, c].set_title(r.name, fontsize=8)
        err = (r.vis_stack() - ref.vis_stack()).mean(axis=0)
        im = axes[1, c].imshow(err, cmap="RdBu", vmin=-1, vmax=1)
        rmse = r.metrics.get("vis_rmse")
        axes[1, c].set_title("vis error" + (f" (RMSE {rmse:.3f})" if rmse is not None else ""),
                             fontsize=8)
        for a in axes[:, c]:
            a.set_xticks([])
            a.set_yticks([])
    fig.colorbar(im, ax=axes[1, :].tolist(), shrink=0.8, label="test - reference visibility")
    fig.savefig(path, dpi=100)
    plt.close(fig)
