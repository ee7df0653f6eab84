"""Tables of results as text, CSV and JSON: one module for the harness and the report.

A table is a list of flat dicts (rows): :meth:`~mi_shadowmap.timing.MethodResult.row`
for a comparison, the rows of a :class:`~mi_shadowmap.sweep.SweepTable` for a
sweep. This module formats them -- :func:`format_table` (the comparison table
printed by the CLI), :func:`format_sweep`, :func:`text_table` for any columns
-- and writes them (:func:`write_csv`, :func:`write_json`,
:func:`write_tables`). It knows nothing about Mitsuba.
"""
from __future__ import annotations

import csv
import json
import math
import os
import re

import numpy as np

#: Columns of :func:`format_table`: (row key, header, format).
COMPARE_COLUMNS = (
    ("name", "method", "{}"), ("vis_rmse", "vis RMSE", "{:.4f}"),
    ("vis_penumbra_rmse", "penumbra RMSE", "{:.4f}"),
    ("vis_misclassified", "miscl. %", "{:.2%}"),
    ("vis_false_shadow", "false shd %", "{:.2%}"),
    ("vis_false_lit", "false lit %", "{:.2%}"), ("img_psnr", "PSNR dB", "{:.1f}"),
    ("img_flip", "FLIP", "{:.4f}"),
    ("time_build", "build ms", "{:.1f}"), ("time_shading", "shade ms", "{:.1f}"),
    ("time_warm", "frame ms", "{:.1f}"), ("time_cold", "cold ms", "{:.1f}"),
    ("time_cached", "cached ms", "{:.1f}"),
    ("map_kib", "maps KiB", "{:.0f}"))


def jsonable(v):
    """A JSON-safe version of a table value (numpy scalars, inf/nan as strings)."""
    if isinstance(v, (np.floating, np.integer, np.bool_)):
        v = v.item()
    if isinstance(v, tuple):
        return [jsonable(x) for x in v]
    if isinstance(v, float) and not math.isfinite(v):
        return str(v)
    return v


def safe_name(name: str) -> str:
    """A file-name-safe version of a display name."""
    return re.sub(r"[^A-Za-z0-9_.=,-]+", "_", name).strip("_")


def columns(rows: list[dict]) -> list[str]:
    """Every key of ``rows``, in first-seen order."""
    return list(dict.fromkeys(k for r in rows for k in r))


def text_table(rows: list[dict], cols) -> str:
    """A plain-text table; ``cols`` are ``(key, header, format)``; missing or NaN
    values print as ``-``."""
    body = []
    for row in rows:
        cells = []
        for key, _, fmt in cols:
            v = row.get(key)
            if v is None or (isinstance(v, float) and math.isnan(v)):
                cells.append("-")
            else:
                try:
                    cells.append(fmt.format(v))
                except (ValueError, TypeError):
                    cells.append(str(v))
        body.append(cells)
    head = [c[1] for c in cols]
    widths = [max([len(h)] + [len(r[i]) for r in body]) for i, h in enumerate(head)]

    def line(cells):
        return "  ".join(c.ljust(w) for c, w in zip(cells, widths)).rstrip()

    return "\n".join([line(head), line(["-" * w for w in widths])] + [line(r) for r in body])


def format_table(results) -> str:
    """The metrics table of a comparison (times in ms; rates in %): one line per
    :class:`~mi_shadowmap.timing.MethodResult`."""
    rows = []
    for r in results:
        row = r.row()
        for k in list(row):
            if k.startswith("time_") and row[k] is not None:
                row[k] = row[k] * 1e3
        row["map_kib"] = r.map_bytes / 1024
        rows.append(row)
    return text_table(rows, COMPARE_COLUMNS)


def format_sweep(rows: list[dict], error_key: str = "vis_rmse") -> str:
    """The table of an analysed sweep (see :func:`mi_shadowmap.sweep.analyse`):
    configuration, error, time, Pareto front (``*``) and the ratios against
    ray tracing."""
    cols = [("name", "configuration", "{}"), ("error", error_key, "{:.4f}"),
            ("time", "time ms", "{:.1f}"), ("pareto", "pareto", "{}"),
            ("error_ratio_equal_time", "err ratio @= time", "{:.2f}"),
            ("speedup_equal_error", "speedup @= error", "{:.2f}")]
    return text_table([{**r, "time": r["time"] * 1e3, "pareto": "*" if r["pareto"] else ""}
                       for r in rows], cols)


def write_csv(rows: list[dict], path) -> str:
    """``rows`` as CSV (a column per key of any row)."""
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=columns(rows))
        w.writeheader()
        w.writerows(rows)
    return os.fspath(path)


def write_json(rows: list[dict], path) -> str:
    """``rows`` as a JSON list (values made JSON-safe by :func:`jsonable`)."""
    with open(path, "w") as f:
        json.dump([{k: jsonable(v) for k, v in r.items()} for r in rows], f, indent=2)
    return os.fspath(path)


def write_tables(rows: list[dict], out_dir: str, stem: str) -> list[str]:
    """``<stem>.csv`` and ``<stem>.json`` in ``out_dir``."""
    return [write_csv(rows, os.path.join(out_dir, stem + ".csv")),
            write_json(rows, os.path.join(out_dir, stem + ".json"))]
