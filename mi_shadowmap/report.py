"""Write comparison outputs: float EXR (OpenEXR), PNG previews, plots, CSV and JSON.

* :func:`write_results` -- the outputs of :func:`mi_shadowmap.harness.compare`:
  one EXR per method (``R,G,B``, ``vis_<emitter>.Y``, the visibility error
  ``err_<emitter>.Y`` = method - reference and the image error
  ``img_err.R/G/B``), a tonemapped PNG per method, ``contact_sheet.png``
  (images over visibility-error heat maps), ``pareto.png`` (frame time vs
  visibility RMSE), ``metrics.csv`` and ``metrics.json``.
* :func:`write_sweep` -- the outputs of :func:`mi_shadowmap.harness.sweep`:
  ``sweep.csv``, ``sweep.json``, ``pareto.png``.
* :func:`write_maps` -- every depth-map layer of every emitter as one EXR per
  emitter (faces stacked vertically, one channel per layer; layers of a few
  values per map as header attributes).

The CSV/JSON tables are written by :mod:`mi_shadowmap.tables`, the module the
harness formats its text tables with.
"""
from __future__ import annotations

import math
import os

import numpy as np

from .tables import safe_name, write_tables


# --------------------------------------------------------------------------- files
def check_out_dir(out_dir: str, create: bool = True) -> str:
    """Create ``out_dir`` if needed; raise PermissionError if it cannot be written.

    ``create=False`` only checks, creating nothing: ``out_dir`` is a writable folder,
    or its nearest existing parent is one (so that the writers, which create it, can);
    the CLI checks so before it renders and leaves no empty folder behind an error.
    Either way a probe is made there and removed (:func:`_probe_writable`):
    ``os.access`` says yes to root almost everywhere, and ``--out /proc/x`` as root
    passed it, rendered the whole comparison and failed only then, at the folder.
    A broken symbolic link on the way is an error (:func:`_broken_link`)."""
    broken = _broken_link(os.path.abspath(out_dir))
    if broken is not None:
        raise PermissionError(f"cannot create output folder {out_dir}: {broken} is a broken "
                              f"symbolic link (to {os.readlink(broken)})")
    if not create:
        path = os.path.abspath(out_dir)
        if os.path.exists(path):
            if not os.path.isdir(path):      # was "is not writable", of a file
                raise PermissionError(f"output folder {out_dir} is a file, not a folder")
            if not os.access(path, os.W_OK | os.X_OK):
                raise PermissionError(f"output folder is not writable: {out_dir}")
            _probe_writable(path, f"output folder is not writable: {out_dir}")
            return out_dir
        parent = os.path.dirname(path)
        while not os.path.exists(parent) and os.path.dirname(parent) != parent:
            parent = os.path.dirname(parent)
        if not os.path.isdir(parent):
            raise PermissionError(f"cannot create output folder {out_dir}: {parent} is not "
                                  "a folder")
        if not os.access(parent, os.W_OK | os.X_OK):
            raise PermissionError(f"cannot create output folder {out_dir}: {parent} is not "
                                  "writable")
        _probe_writable(parent, f"cannot create output folder {out_dir}: no folder can "
                                f"be made in {parent}", make_folder=True)
        return out_dir
    if os.path.exists(out_dir) and not os.path.isdir(out_dir):
        raise PermissionError(f"output folder {out_dir} is a file, not a folder")
    try:
        os.makedirs(out_dir, exist_ok=True)
    except OSError as e:
        raise PermissionError(f"cannot create output folder {out_dir}: "
                              f"{e.strerror or e}") from None
    if not os.path.isdir(out_dir) or not os.access(out_dir, os.W_OK | os.X_OK):
        raise PermissionError(f"output folder is not writable: {out_dir}")
    _probe_writable(out_dir, f"output folder is not writable: {out_dir}")
    return out_dir


def _broken_link(path: str) -> str | None:
    """The first of ``path`` and its parents that is a symbolic link to nothing, or None.
    ``os.path.exists`` says no of such a link, so the check above probed the folder
    holding it and said yes, and ``os.makedirs`` failed only after the render ("File
    exists" of the link itself, "No such file or directory" below it), as ``mkdir -p``
    does."""
    while True:
        if os.path.islink(path) and not os.path.exists(path):
            return path
        parent = os.path.dirname(path)
        if parent == path:
            return None
        path = parent


def _probe_writable(folder: str, message: str, make_folder: bool = False) -> None:
    """Make a temporary file in ``folder`` (``make_folder``: a temporary folder, as the
    writers will make the output folder there) and remove it; a PermissionError of
    ``message`` and the system's reason if that fails. ``os.access`` alone reads the
    permission bits (and a read-only mount), which root passes even where nothing can
    be made (``/proc``)."""
    import tempfile
    try:
        if make_folder:
            os.rmdir(tempfile.mkdtemp(prefix=".mi-shadowmap-probe-", dir=folder))
        else:
            fd, probe = tempfile.mkstemp(prefix=".mi-shadowmap-probe-", dir=folder)
            os.close(fd)
            os.remove(probe)
    except OSError as e:
        raise PermissionError(f"{message} ({e.strerror or e})") from None


def write_exr(path: str, channels: dict, attributes: dict | None = None) -> None:
    """Write float32 channels (``name -> (H, W)``) to one scanline EXR via OpenEXR;
    ``attributes`` (``name -> float32 array``, or a string) go into its header as float
    vectors (strings as strings)."""
    import OpenEXR
    data = {k: np.ascontiguousarray(v, dtype=np.float32) for k, v in channels.items()}
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    header.update({k: v if isinstance(v, str) else
                   np.ascontiguousarray(v, dtype=np.float32).ravel()
                   for k, v in (attributes or {}).items()})
    with OpenEXR.File(header, data) as f:
        f.write(path)


def read_exr(path: str) -> dict:
    """Read an EXR back as ``{channel: (H, W) float32}``."""
    import OpenEXR
    with OpenEXR.File(path, separate_channels=True) as f:
        return {k: np.array(v.pixels) for k, v in f.channels().items()}


def read_exr_header(path: str) -> dict:
    """The header attributes of an EXR (e.g. the small map layers of :func:`write_maps`)."""
    import OpenEXR
    with OpenEXR.File(path) as f:
        return dict(f.header())


def tonemap(img: np.ndarray) -> np.ndarray:
    """Linear RGB -> 8-bit preview (clip to [0, 1], gamma 2.2)."""
    return (np.clip(img, 0, 1) ** (1 / 2.2) * 255 + 0.5).astype(np.uint8)


def write_png(path: str, img: np.ndarray) -> None:
    import matplotlib.image
    arr = img if img.dtype == np.uint8 else tonemap(img)
    matplotlib.image.imsave(path, arr)


def _pyplot():
    import matplotlib
    if matplotlib.get_backend().lower() not in ("agg", "module://matplotlib_inline.backend_inline"):
        matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


# --------------------------------------------------------------------------- compare
def write_results(results, out_dir: str) -> dict:
    """Write every result's EXR/PNG, the contact sheet, the Pareto plot and tables.

    Returns the paths written, by kind (``exr``, ``png``, ``table``).
    """
    check_out_dir(out_dir)
    written = {"exr": [], "png": [], "table": []}
    for r in results:
        ref = r.reference_in(results)   # the one its metrics are against (its own spp's)
        base = os.path.join(out_dir, safe_name(r.name))
        ch = {}
        if r.image is not None:
            ch.update({"R": r.image[..., 0], "G": r.image[..., 1], "B": r.image[..., 2]})
            if ref.image is not None:
                err = r.image - ref.image
                ch.update({"img_err.R": err[..., 0], "img_err.G": err[..., 1],
                           "img_err.B": err[..., 2]})
        for label, v in r.visibility.items():
            ch[f"vis_{label}.Y"] = v
            ch[f"err_{label}.Y"] = v - ref.visibility[label]
        write_exr(base + ".exr", ch)
        written["exr"].append(base + ".exr")
        if r.image is not None:
            write_png(base + ".png", r.image)
            written["png"].append(base + ".png")
    sheet = os.path.join(out_dir, "contact_sheet.png")
    contact_sheet(results, sheet)
    written["png"].append(sheet)
    rows = [r.row() for r in results]
    pareto = os.path.join(out_dir, "pareto.png")
    pareto_plot(rows, pareto, time_key="time_warm", error_key="vis_rmse",
                title="compare: warm frame time vs visibility RMSE")
    written["png"].append(pareto)
    written["table"] += write_tables(rows, out_dir, "metrics")
    warn_stale(out_dir, [p for paths in written.values() for p in paths])
    return written


def warn_stale(out_dir: str, written, table: str | None = "metrics.csv") -> list:
    """Warn about EXR and PNG files in ``out_dir`` that this run did not write (an earlier
    run's methods, which ``table`` -- ``metrics.csv`` -- no longer lists; an earlier
    ``maps`` run's emitters); returns their names."""
    mine = {os.path.basename(p) for p in written}
    stale = sorted(f for f in os.listdir(out_dir)
                   if f.endswith((".exr", ".png")) and f not in mine)
    if stale:
        import warnings
        shown = ", ".join(stale[:6]) + (f" and {len(stale) - 6} more" if len(stale) > 6 else "")
        listed = f", not in its {table}" if table else ""
        warnings.warn(f"{out_dir} holds {len(stale)} image file(s) this run did not write "
                      f"(an earlier run's{listed}): {shown}", stacklevel=2)
    return stale


def largest_error(diff) -> np.ndarray:
    """Per pixel, the emitters' visibility error (``diff``: ``(n_emitters, H, W)``)
    largest in magnitude, with its sign: a mean over emitters let opposite errors of two
    lights cancel and halved a whole error of one of two."""
    diff = np.asarray(diff)
    k = np.abs(diff).argmax(axis=0)[None]
    return np.take_along_axis(diff, k, axis=0)[0]


def contact_sheet(results, path: str | None = None, max_cols: int = 6):
    """Images (top row) over visibility-error heat maps against the reference
    (bottom row; blue = too dark, red = too bright; per pixel the emitter whose error
    is largest); wraps after ``max_cols``.

    Saves to ``path`` if given; returns the figure (closed when saved).
    """
    plt = _pyplot()
    n = len(results)
    ncol = min(n, max_cols)
    nblk = math.ceil(n / ncol)
    fig, axes = plt.subplots(2 * nblk, ncol, figsize=(2.2 * ncol + 1.2, 4.6 * nblk), squeeze=False)
    im = None
    for a in axes.ravel():
        a.set_axis_off()
    for c, r in enumerate(results):
        top, bot = axes[2 * (c // ncol), c % ncol], axes[2 * (c // ncol) + 1, c % ncol]
        if r.image is not None:
            top.imshow(tonemap(r.image))
        top.set_title(_wrap(r.name), fontsize=7)
        err = largest_error(r.vis_stack() - r.reference_in(results).vis_stack())
        im = bot.imshow(err, cmap="RdBu_r", vmin=-1, vmax=1)
        rmse = r.metrics.get("vis_rmse")
        bot.set_title("vis error" + (f" (RMSE {rmse:.3f})" if rmse is not None else ""),
                      fontsize=7)
    fig.colorbar(im, ax=axes.ravel().tolist(), shrink=0.6,
                 label="method - reference visibility")
    if path is not None:
        fig.savefig(path, dpi=100)
        plt.close(fig)
    return fig


def _wrap(text: str, width: int = 28) -> str:
    words, lines, cur = text.split(" "), [], ""
    for w in words:
        if cur and len(cur) + 1 + len(w) > width:
            lines.append(cur)
            cur = w
        else:
            cur = f"{cur} {w}".strip()
    return "\n".join(lines + [cur])


# --------------------------------------------------------------------------- sweeps
def pareto_plot(rows: list[dict], path: str | None = None, time_key: str = "time",
                error_key: str = "error", title: str = "time vs error", ax=None,
                label_points: bool = True, xlabel: str | None = None,
                ylabel: str | None = None, highlight=None, budget: float | None = None):
    """Scatter of time (ms, log) vs error, one colour per method, the Pareto
    front joined by a line. ``rows`` are flat dicts (a SweepTable or
    ``[r.row() for r in results]``); reference rows are skipped.
    ``highlight``: ``{row name: label}`` (or a list of names) of points to mark
    with a star (e.g. the tuner's pick); ``budget``: an error drawn as a dashed line.

    Saves to ``path`` if given; returns the figure.
    """
    from . import metrics
    plt = _pyplot()
    pts = [r for r in rows if not r.get("reference")
           and r.get(error_key) is not None and math.isfinite(float(r[error_key]))]
    fig = None
    if ax is None:
        fig, ax = plt.subplots(figsize=(7, 4.5))
    else:
        fig = ax.figure
    if pts:
        t = np.array([float(r[time_key]) * 1e3 for r in pts])
        e = np.array([float(r[error_key]) for r in pts])
        front = metrics.pareto_front(t, e)
        methods = list(dict.fromkeys(r["method"] for r in pts))
        cmap = plt.get_cmap("tab10")
        for k, m in enumerate(methods):
            sel = np.array([r["method"] == m for r in pts])
            ax.scatter(t[sel], e[sel], color=cmap(k % 10), label=m, zorder=3,
                       marker="s" if m == "raytraced" else "o",
                       s=34 if m == "raytraced" else 28,
                       edgecolors="k" if m == "raytraced" else "none")
        order = np.argsort(t[front])
        ax.step(t[front][order], e[front][order], where="post", color="k", lw=1,
                alpha=0.6, label="Pareto front", zorder=2)
        if label_points:
            for r, x, y, f in zip(pts, t, e, front):
                if f:
                    ax.annotate(r["name"].replace(r["method"] + " ", "", 1)
                                if r["name"] != r["method"] else r["method"],
                                (x, y), fontsize=6, xytext=(3, 3), textcoords="offset points")
        marks = dict.fromkeys(highlight) if isinstance(highlight, (list, tuple)) else \
            dict(highlight or {})
        for r, x, y in zip(pts, t, e):
            if r["name"] in marks:
                ax.scatter([x], [y], marker="*", s=260, facecolors="none", edgecolors="r",
                           linewidths=1.5, zorder=4)
                ax.annotate(marks[r["name"]] or r["name"], (x, y), fontsize=7, color="r",
                            xytext=(6, -10), textcoords="offset points")
        ax.set_xscale("log")
        if (e > 0).all():
            ax.set_yscale("log")
    if budget is not None:
        ax.axhline(budget, color="r", ls="--", lw=1, alpha=0.7, label=f"limit {budget:.4g}")
    ax.set_xlabel(xlabel or f"{time_key} [ms]")
    ax.set_ylabel(ylabel or error_key)
    ax.set_title(title)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)
    if path is not None:
        fig.tight_layout()
        fig.savefig(path, dpi=110)
        plt.close(fig)
    return fig


def write_sweep(table, out_dir: str) -> dict:
    """``sweep.csv``, ``sweep.json`` and ``pareto.png`` for a SweepTable."""
    check_out_dir(out_dir)
    paths = write_tables(table.rows, out_dir, "sweep")
    png = os.path.join(out_dir, "pareto.png")
    ref = getattr(table, "reference", None)
    against = (f"\nagainst {ref.name}" + ("" if "spp=" in ref.name else f", {ref.spp} spp")
               if ref is not None and ref.name else "")
    pareto_plot(table.rows, png, time_key="time", error_key="error",
                title=f"sweep: {table.time_key} vs {table.error_key}{against}",
                xlabel=f"{table.time_key} [ms]", ylabel=table.error_key)
    return {"table": paths, "png": [png]}


# --------------------------------------------------------------------------- maps
def map_layer_image(smap, layer: str) -> np.ndarray | None:
    """Layer ``layer`` of ``smap`` as an ``(n_faces * res, res)`` image, faces stacked
    vertically: a layer of one value per texel as it is, a layer of one value per
    face (e.g. ``pcss_near``) filling its face. None for a layer of any other size
    (e.g. a few constants per map), which is no image."""
    data = np.asarray((smap.depth if layer == "depth" else smap.extra[layer]).numpy(),
                      dtype=np.float32).ravel()
    n_faces, res = smap.view.n_faces, smap.resolution
    if data.size == n_faces and data.size != n_faces * res * res:
        data = np.repeat(data, res * res)
    if data.size != n_faces * res * res:
        return None
    return data.reshape(-1, res)


def unique_file_stems(names) -> list[str]:
    """File-name-safe stems (:func:`~mi_shadowmap.tables.safe_name`) of ``names``, made
    unique: names that differ only in characters a file name cannot hold (``"lamp a"``
    and ``"lamp_a"``) or in case (one file on case-insensitive file systems) got one
    file, the later one overwriting the earlier. A name that is its own safe stem keeps
    it; the others take the first free ``<stem>_2``, ``<stem>_3``, ..."""
    names = list(names)
    stems = [safe_name(n) or "unnamed" for n in names]
    out, taken = [None] * len(names), set()
    for k, (name, stem) in enumerate(zip(names, stems)):   # names that are file names
        if name == stem and stem.casefold() not in taken:
            out[k] = stem
            taken.add(stem.casefold())
    for k, stem in enumerate(stems):                      # then the others, suffixed
        if out[k] is None:
            n = 1 if stem.casefold() not in taken else 2
            while n > 1 and f"{stem}_{n}".casefold() in taken:
                n += 1
            out[k] = stem if n == 1 else f"{stem}_{n}"
            taken.add(out[k].casefold())
    return out


def write_maps(maps, out_dir: str, names=None) -> list[str]:
    """One EXR per emitter: every layer of its :class:`ShadowMap` as a channel
    (``depth.Y``, ``second_depth.Y``, ``<extra>.Y``), faces stacked vertically
    (see :func:`map_layer_image`); a layer that is no image (a few values per map)
    as a float-vector attribute of the header named after it (:func:`read_exr_header`).
    A virtual map (:mod:`mi_shadowmap.virtual`) writes its built pages stacked vertically
    (``page_size`` wide) and their face, level and page coordinates as the attributes
    ``page_face``, ``page_level``, ``page_px``, ``page_py``.

    Files are named after the emitters' labels (``names``, one per map, if given),
    made unique by :func:`unique_file_stems`; the header attribute ``emitter`` holds
    the label. Returns the paths, one per map that is not None, in order. Image files
    in ``out_dir`` that this call did not write (an earlier run's maps) are warned about
    (:func:`warn_stale`)."""
    check_out_dir(out_dir)
    maps = list(maps)
    names = [m.view.label if m is not None else None for m in maps] if names is None \
        else list(names)
    kept = [(m, n) for m, n in zip(maps, names) if m is not None]
    stems = unique_file_stems(n for _, n in kept)
    paths = []
    for (smap, _), stem in zip(kept, stems):
        path = os.path.join(out_dir, f"{stem}.exr")
        if hasattr(smap, "page_records"):   # a virtual map: its pages, stacked
            rec = smap.page_records()
            ch = {f"{layer}.Y": smap.pages_numpy(layer).reshape(-1, smap.layout.page_size)
                  for layer in smap.layers()}
            attributes = {f"page_{k}": np.asarray(rec[k], np.float32)
                          for k in ("face", "level", "px", "py")}
            attributes["emitter"] = smap.view.label
            write_exr(path, ch, attributes)
            paths.append(path)
            continue
        ch, attributes = {}, {"emitter": smap.view.label}
        for layer in smap.layers():
            image = map_layer_image(smap, layer)
            if image is not None:
                ch[f"{layer}.Y"] = image
            else:
                attributes[layer] = np.asarray(smap.extra[layer].numpy(), np.float32)
        write_exr(path, ch, attributes)
        paths.append(path)
    warn_stale(out_dir, paths, table=None)   # an earlier run's maps (another scene's emitters) stay
    return paths


def tune_plot(result: dict, path: str | None = None, ax=None):
    """The search's time/error plot of a :func:`mi_shadowmap.tune.tune` result
    (:func:`pareto_plot`) with the pick and the raytraced configuration starred and
    the search threshold dashed."""
    marks = {result["name"]: "pick"} if result["name"] is not None else {}   # partial
    rt = result.get("raytraced")
    if rt is not None and rt["name"] != result["name"]:
        marks[rt["name"]] = "raytraced"
    se = result["search"]
    return pareto_plot(result["sweep"].rows, path, time_key="time", error_key="error",
                       title=f"tune: {result['metric']} <= {result['max_error']:g} "
                             f"(search at {se['size'][0]}x{se['size'][1]})",
                       ax=ax, highlight=marks, budget=se["threshold"],
                       xlabel=f"warm frame time at {se['size'][0]}x{se['size'][1]} [ms]",
                       ylabel=result["metric"])


def page_map_plot(vmap, path: str | None = None, faces=None, zoom_levels: int | None = 3):
    """Which pages of a virtual map (:class:`mi_shadowmap.virtual.VirtualShadowMap`) exist
    at which level: per face that has pages finer than the coarsest level, a panel of
    its pages -- each a rectangle of the face's ``uv``, coloured by its level (0:
    finest) -- and, with ``zoom_levels``, a second panel zoomed onto the pages of the
    ``zoom_levels`` finest levels present. Returns the figure."""
    plt = _pyplot()
    from matplotlib.collections import PatchCollection
    from matplotlib.patches import Rectangle
    rec = vmap.page_records()
    fine = rec["level"] < vmap.layout.coarsest
    if not fine.any():
        fine = np.ones_like(fine)
    if faces is None:
        faces = sorted(set(rec["face"][fine].tolist()))
    levels = rec["level"][fine]
    lo, hi = int(levels.min()), int(levels.max())
    panels = []
    for f in faces:
        sel = (rec["face"] == f) & fine
        panels.append((f, sel, "all pages"))
        if zoom_levels:
            near = sel & (rec["level"] < rec["level"][sel].min() + zoom_levels)
            panels.append((f, near, f"zoom: levels {rec['level'][sel].min()}-"
                                    f"{rec['level'][sel].min() + zoom_levels - 1}"))
    fig, axes = plt.subplots(1, len(panels), figsize=(5 * len(panels), 4.6), squeeze=False)
    cmap = plt.get_cmap("viridis")
    for ax, (f, sel, what) in zip(axes[0], panels):
        face_sel = (rec["face"] == f) & fine
        order = np.argsort(-rec["level"][face_sel])          # coarse first, fine on top
        patches, colours = [], []
        for k in np.flatnonzero(face_sel)[order]:
            patches.append(Rectangle((rec["u0"][k], rec["v0"][k]), rec["u1"][k] - rec["u0"][k],
                                     rec["v1"][k] - rec["v0"][k]))
            colours.append(rec["level"][k])
        pc = PatchCollection(patches, cmap=cmap, edgecolor="k", linewidth=0.2)
        pc.set_array(np.asarray(colours, float))
        pc.set_clim(lo, max(hi, lo + 1))
        ax.add_collection(pc)
        u0, v0 = rec["u0"][sel].min(), rec["v0"][sel].min()
        u1, v1 = rec["u1"][sel].max(), rec["v1"][sel].max()
        pad = 0.05 * max(u1 - u0, v1 - v0)
        ax.set_xlim(u0 - pad, u1 + pad)
        ax.set_ylim(v0 - pad, v1 + pad)
        ax.set_aspect("equal")
        ax.set_title(f"{vmap.view.label}, face {f}: {int(face_sel.sum())} pages ({what})",
                     fontsize=9)
        ax.set_xlabel("u (light)")
        ax.set_ylabel("v (light)")
        fig.colorbar(pc, ax=ax, label="level (0 = finest)")
    fig.tight_layout()
    if path is not None:
        fig.savefig(path, dpi=120)
    return fig
