"""The ``mi-shadowmap`` command line.

``mi-shadowmap`` with no command runs ``compare`` (on the built-in default
scene unless a scene file is given): the README's main command.
"""
from __future__ import annotations

import argparse
import json
import os
import sys

EPILOG_MAIN = """\
commands:
  compare   render the reference and each method; print the metrics table and write
            EXR/PNG/contact sheet/Pareto plot/metrics.csv/metrics.json
  sweep     render a parameter grid; mark the Pareto front of time vs error and the
            equal-time / equal-error comparisons against raytraced
  maps      export every depth map (and second/extra layers) as float EXR

With no command, 'compare' runs. With no scene, the built-in scene (sphere and box under
a spot light; --light picks another light) is used. 'mi-shadowmap COMMAND --help' for
each command's options. Errors are one line on stderr with exit status 2; --debug shows
the traceback.

examples:
  mi-shadowmap --out out
  mi-shadowmap compare scenes_xml/room_two_points.xml --methods hard pcf:num_samples=16
  mi-shadowmap compare --set resolution=512 --spp 4 --width 256 --height 256
  mi-shadowmap --variant llvm_ad_spectral --out out/spectral
  mi-shadowmap sweep --grid 'method=hard resolution=256,512,1024' \\
                     --grid 'method=raytraced spp=1,4,16' --out out/sweep
  mi-shadowmap maps scenes_xml/spot_sphere_box.xml --out out/maps
"""

GRID_HELP = """\
a sub-grid (repeatable; the sweep runs the union of the sub-grids). Either a JSON file,
inline JSON ('{"method": ["hard"], "resolution": [256, 512]}' or a list of such dicts),
or 'name=v1,v2 name=v1,v2 ...' items separated by spaces or ';'. Every sub-grid needs
'method'; 'spp' may be swept too. A property is combined only with the methods that use
it. Default: every map method at resolution 256,512,1024 and raytraced at spp 1..16."""


#: Error columns a sweep can trade against time (all "lower is better").
ERROR_COLUMNS = ("vis_rmse", "vis_mae", "vis_misclassified", "vis_false_shadow",
                 "vis_false_lit", "vis_penumbra_rmse", "img_rmse", "img_mae",
                 "img_relative_mse", "img_flip")


class _Parser(argparse.ArgumentParser):
    """argparse with a one-line error (no usage dump) and exit status 2."""

    def error(self, message):
        self.exit(2, f"{self.prog}: error: {message} (see --help)\n")


def _add_scene_args(p, sizes=True, out="out"):
    p.add_argument("scene", nargs="?",
                   help="scene XML file (default: the built-in sphere-and-box scene)")
    p.add_argument("--light", default="spot", choices=("spot", "point", "directional", "area"),
                   help="light of the built-in scene (default: spot)")
    if sizes:
        p.add_argument("--width", type=int, default=None,
                       help="image width (built-in scene, or an XML file with $width)")
        p.add_argument("--height", type=int, default=None,
                       help="image height (built-in scene, or an XML file with $height)")
    p.add_argument("--set", action="append", metavar="NAME=VALUE", default=[],
                   help="integrator property for every method that uses it (repeatable), "
                        "e.g. --set resolution=512 --set bias=0.01")
    p.add_argument("--out", default=out, help=f"output folder (default: {out})")
    p.add_argument("--variant", default=None, metavar="NAME",
                   help="Mitsuba variant to render in: llvm_ad_rgb (default), llvm_ad_mono, "
                        "llvm_ad_spectral, or cuda_ad_* where a CUDA GPU exists")
    p.add_argument("--debug", action="store_true", help="show tracebacks on errors")


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(
        prog="mi-shadowmap",
        description="Compare depth-map shadow methods with ray-traced ground truth in "
                    "Mitsuba 3: images, visibility error metrics, timings, sweeps.",
        epilog=EPILOG_MAIN, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--debug", action="store_true", help="show tracebacks on errors")
    sub = p.add_subparsers(dest="command", parser_class=_Parser)

    c = sub.add_parser(
        "compare", help="render the reference and each method, write images and metrics",
        description="Render the reference (raytraced for delta lights; converged soft-shadow "
                    "reference for area lights) and each method with the same seed; print "
                    "the metrics table; write <out>/<method>.exr (RGB, vis_<emitter>, "
                    "err_<emitter>, img_err), PNG previews, contact_sheet.png, pareto.png, "
                    "metrics.csv and metrics.json.")
    _add_scene_args(c)
    c.add_argument("--methods", nargs="+", default=None, metavar="METHOD",
                   help="methods to compare, each 'name' or 'name:prop=value,prop=value' "
                        "(default: every implemented method except raytraced)")
    c.add_argument("--spp", type=int, default=16, help="samples per pixel (default 16)")
    c.add_argument("--seed", type=int, default=0, help="sampler seed (default 0)")
    c.add_argument("--repeats", type=int, default=3,
                   help="warm re-renders per method; the median is reported (default 3)")
    c.add_argument("--reference", default="auto",
                   help="'auto' (default), 'converged', or a method spec like 'raytraced'")
    c.add_argument("--ref-spp", type=int, default=64,
                   help="spp of the converged area-light reference (default 64)")
    c.add_argument("--ref-shadow-rays", type=int, default=64,
                   help="shadow rays of the converged area-light reference (default 64)")

    s = sub.add_parser(
        "sweep", help="render a parameter grid, Pareto front of time vs error",
        description="Render every configuration of the grid, score it against one reference "
                    "and write sweep.csv, sweep.json and pareto.png; print the table with "
                    "the Pareto front (*) and equal-time / equal-error ratios against "
                    "raytraced.", formatter_class=argparse.RawDescriptionHelpFormatter)
    _add_scene_args(s, out="out/sweep")
    s.add_argument("--grid", action="append", default=None, metavar="FILE|INLINE",
                   help=GRID_HELP)
    s.add_argument("--spp", type=int, default=16,
                   help="spp of configurations that do not sweep spp (default 16)")
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--repeats", type=int, default=3,
                   help="warm re-renders per configuration, median reported (default 3)")
    s.add_argument("--error", default="vis_rmse", choices=ERROR_COLUMNS, metavar="COLUMN",
                   help="error axis of the trade (lower is better): "
                        + ", ".join(ERROR_COLUMNS) + " (default vis_rmse)")

    m = sub.add_parser("maps", help="export every depth map as float EXR",
                       description="Build the depth maps of every emitter (with the "
                                   "second/extra layers the chosen methods use) and write "
                                   "one EXR per emitter: one channel per layer, cube faces "
                                   "stacked vertically.")
    _add_scene_args(m, sizes=False, out="out/maps")
    m.add_argument("--methods", nargs="+", default=None, metavar="METHOD",
                   help="build the layers these methods use (default: every map method)")
    return p


# --------------------------------------------------------------------------- helpers
def parse_sets(items) -> dict:
    """``["a=1", "b=x"]`` -> ``{"a": 1, "b": "x"}``."""
    from .harness import parse_value
    out = {}
    for item in items or []:
        if "=" not in item:
            raise ValueError(f"--set expects name=value, got {item!r}")
        k, v = item.split("=", 1)
        out[k.strip()] = parse_value(v.strip())
    return out


def parse_grid(text: str):
    """One ``--grid`` value: a JSON file, inline JSON, or ``name=v1,v2 ...`` items."""
    from .harness import parse_value
    t = text.strip()
    if os.path.isfile(t):
        with open(t) as f:
            try:
                return json.load(f)
            except json.JSONDecodeError as e:
                raise ValueError(f"grid file {t} is not valid JSON: {e}") from None
    if t.startswith(("{", "[")):
        try:
            return json.loads(t)
        except json.JSONDecodeError as e:
            raise ValueError(f"--grid is not valid JSON: {e}") from None
    if t.endswith(".json"):
        raise FileNotFoundError(f"grid file not found: {t}")
    sub = {}
    for item in t.replace(";", " ").split():
        if "=" not in item:
            raise ValueError(f"--grid expects name=v1,v2 items, got {item!r}")
        k, v = item.split("=", 1)
        sub[k.strip()] = [parse_value(x.strip()) for x in v.split(",") if x.strip()]
    if not sub:
        raise ValueError("--grid is empty")
    return sub


def load_scene_arg(args, sizes=True):
    """The scene of ``args``: the XML file, or the built-in scene."""
    from . import harness, scenes
    size = {}
    if sizes:
        for k in ("width", "height"):
            v = getattr(args, k, None)
            if v is not None:
                if v < 1:
                    raise ValueError(f"--{k} must be >= 1, got {v}")
                size[k] = v
    if args.scene is None:
        return harness.load_scene(scenes.default_scene(light=args.light, **size))
    return harness.load_scene(args.scene, **size)


# --------------------------------------------------------------------------- commands
def cmd_compare(args) -> int:
    from . import harness, report
    out = args.out
    params = parse_sets(args.set)
    methods = [harness.method_spec(m, params) for m in (args.methods or
                                                        harness.default_methods())]
    harness.check_shared_params(methods, params)
    reference = args.reference
    if reference not in ("auto", "converged"):
        reference = harness.method_spec(reference)
    scene = load_scene_arg(args)
    report.check_out_dir(out)
    results = harness.compare(scene, methods=methods, reference=reference, spp=args.spp,
                              seed=args.seed, repeats=args.repeats, progress=True,
                              ref_spp=args.ref_spp, ref_shadow_rays=args.ref_shadow_rays,
                              **params)
    print(harness.format_table(results))
    written = report.write_results(results, out)
    print(f"\nwrote {len(written['exr'])} EXR, {len(written['png'])} PNG, metrics.csv and "
          f"metrics.json to {os.path.abspath(out)}")
    return 0


def cmd_sweep(args) -> int:
    from . import harness, options, report
    out = args.out
    params = parse_sets(args.set)
    grid = None
    if args.grid:
        grid = []
        for g in args.grid:
            sub = parse_grid(g)
            grid += sub if isinstance(sub, list) else [sub]
    grid = grid if grid is not None else harness.default_grid()
    if params:   # --set values are fixed axes of every sub-grid with a method using them
        grid = [{**{k: v for k, v in params.items() if k not in g and _uses(g, k)}, **g}
                if isinstance(g, dict) else g for g in grid]
        harness.check_shared_params(
            [{"method": m, **{k: v for k, v in params.items()
                              if k in {p.name for p in options.properties_for(m)}}}
             for m in options.METHODS], params)
        unused = [k for k in params if not any(isinstance(g, dict) and k in g for g in grid)]
        if unused:
            raise options.OptionError(
                f"shadowmap: property '{unused[0]}' (--set) is not used by any method of "
                "the grid")
    harness.expand_grid(grid, default_spp=args.spp)   # reject bad entries before rendering
    scene = load_scene_arg(args)
    report.check_out_dir(out)
    table = harness.sweep(scene, grid, spp=args.spp, seed=args.seed, repeats=args.repeats,
                          error_key=args.error, progress=True)
    print(table.format())
    written = report.write_sweep(table, out)
    print(f"\nwrote sweep.csv, sweep.json and pareto.png to {os.path.abspath(out)}")
    return 0 if written else 1


def _uses(subgrid: dict, name: str) -> bool:
    """Does a method of ``subgrid`` use property ``name``?"""
    from . import harness, options
    methods = subgrid.get("method", [])
    methods = [methods] if isinstance(methods, str) else list(methods)
    return any(harness.uses_property(m, name) for m in methods if m in options.METHODS)


def cmd_maps(args) -> int:
    from . import harness, report
    from .depth_maps import build_depth_map
    from .filters import LAYERS
    from .light_views import emitter_kind, make_light_view
    from .options import MAP_METHODS
    out = args.out
    params = parse_sets(args.set)
    methods = args.methods or [m for m in harness.available_methods() if m in MAP_METHODS]
    layers = []
    for m in methods:
        opts = harness.validate_spec(harness.method_spec(m, params))
        for layer in LAYERS.get(opts.method, ()):
            if layer not in layers:
                layers.append(layer)
    opts = harness.validate_spec({"method": "hard", **{k: v for k, v in params.items()
                                                       if k in ("resolution", "memory_budget")}})
    scene = load_scene_arg(args, sizes=False)
    report.check_out_dir(out)
    views = [make_light_view(e, scene, i) for i, e in enumerate(scene.emitters())
             if emitter_kind(e) != "environment"]
    res = opts.resolution
    if res is None and hasattr(opts, "map_resolution"):   # automatic, within memory_budget
        film = scene.sensors()[0].film().crop_size() if scene.sensors() else (512, 512)
        res = opts.map_resolution(film, sum(v.n_faces for v in views) * (1 + len(layers)))
    maps = [build_depth_map(scene, v, res or 1024, tuple(layers)) for v in views]
    paths = report.write_maps(maps, out)
    for smap, path in zip(maps, paths):
        print(f"{path}: {smap.view.label} ({smap.view.projection}, {smap.view.n_faces} "
              f"face(s) of {smap.resolution}^2), layers {', '.join(smap.layers())}")
    return 0


_COMMANDS = {"compare": cmd_compare, "sweep": cmd_sweep, "maps": cmd_maps}


def main(argv=None) -> int:
    parser = build_parser()
    argv = list(sys.argv[1:] if argv is None else argv)
    rest = [a for a in argv if a != "--debug"]
    debug = len(rest) != len(argv)
    if not rest or rest[0] not in tuple(_COMMANDS) + ("-h", "--help"):
        rest = ["compare"] + rest      # no command: compare (default scene unless given)
    try:
        args = parser.parse_args(rest)
    except SystemExit as e:          # --help (0) or a usage error (2, one line printed)
        return e.code if isinstance(e.code, int) else 2
    debug = debug or getattr(args, "debug", False)
    try:
        import mi_shadowmap  # noqa: F401  (LLVM set-up and registration)
        if getattr(args, "variant", None) is not None:
            set_variant(args.variant)
        return _COMMANDS[args.command](args)
    except KeyboardInterrupt:
        print("mi-shadowmap: interrupted", file=sys.stderr)
        return 130
    except Exception as e:  # one line, no traceback, unless --debug
        if debug:
            raise
        print(f"mi-shadowmap: error: {one_line(e)}", file=sys.stderr)
        return 2


def set_variant(name: str) -> None:
    """Switch Mitsuba to the variant ``name``, or raise naming it and the supported ones."""
    import mitsuba as mi
    from .variants import UnsupportedVariantError, check_variant
    check_variant(name)
    try:
        mi.set_variant(name)
    except Exception as e:   # e.g. cuda_ad_* on a machine without a CUDA GPU
        raise UnsupportedVariantError(
            f"shadowmap: the Mitsuba variant '{name}' cannot be set on this machine "
            f"({one_line(e)})") from None


def one_line(exc: BaseException) -> str:
    """The most informative line of a (possibly wrapped Mitsuba) error."""
    while exc.__cause__ is not None:   # mi.render wraps errors of a Python integrator
        exc = exc.__cause__
    lines = [ln.strip() for ln in str(exc).strip().splitlines() if ln.strip()]
    for line in lines:
        if "shadowmap:" in line:
            return line[line.index("shadowmap:"):]
    if isinstance(exc, (FileNotFoundError, PermissionError)) and exc.filename and not lines:
        return f"{exc.strerror}: {exc.filename}"
    text = " ".join(lines) if len(lines) <= 3 else lines[-1]
    return text or type(exc).__name__


if __name__ == "__main__":
    sys.exit(main())
