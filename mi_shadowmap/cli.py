"""The ``mi-shadowmap`` command line: it parses arguments and calls the harness.

``mi-shadowmap`` with no command runs ``compare`` (on the built-in default
scene unless a scene file is given): the README's main command. Everything
is validated by the harness (:mod:`mi_shadowmap.specs`) and the options
module; errors are one line on stderr with exit status 2.

``--plugin FILE.py`` (any command, repeatable) runs a Python file first, by
path; it registers methods with :func:`mi_shadowmap.register_method`, which
``--methods`` and ``--grid`` then accept like the built-ins.
"""
from __future__ import annotations

import argparse
import contextlib
import importlib
import importlib.util
import json
import math
import os
import re
import sys
import warnings

EPILOG_MAIN = """\
commands:
  compare   render the reference and each method; print the metrics table and write
            EXR/PNG/contact sheet/Pareto plot/metrics.csv/metrics.json
  sweep     render a parameter grid; mark the Pareto front of time vs error and the
            equal-time / equal-error comparisons against raytraced
  maps      export every depth map (and second/extra layers) as float EXR
  tune      the fastest method and settings that meet an error budget (--max-error);
            writes tune_pareto.png, tune.json and a ready-to-paste integrator.xml

With no command, 'compare' runs. With no scene, the built-in scene (sphere and box under
a spot light; --light picks another light) is used. 'mi-shadowmap COMMAND --help' for
each command's options. Errors are one line on stderr with exit status 2; --debug shows
the traceback.

The scene file's own integrator: the properties of its <integrator type="shadowmap">
(e.g. resolution, bias; not 'method', which --methods chooses, nor 'cache_maps') are the
base of every method that uses them; --set overrides them, and 'method:prop=value' both
(compare, sweep, maps; a sweep axis too). tune keeps the ones it does not search fixed
and searches the others (resolution, its main parameters). A note on stderr names the
properties taken and those no method uses; another integrator (path, aov, ...) is not
used, with a note. --ignore-scene-integrator leaves them all out.

examples:
  mi-shadowmap --out out
  mi-shadowmap compare scenes_xml/room_two_points.xml --methods hard pcf:num_samples=16
  mi-shadowmap compare --set resolution=512 --spp 4 --width 256 --height 256
  mi-shadowmap --variant llvm_ad_spectral --out out/spectral
  mi-shadowmap sweep --grid 'method=hard resolution=256,512,1024' \\
                     --grid 'method=raytraced spp=1,4,16' --out out/sweep
  mi-shadowmap maps scenes_xml/spot_sphere_box.xml --out out/maps
  mi-shadowmap tune scenes_xml/spot_sphere_box.xml --max-error 0.02 --out out/tune
  mi-shadowmap compare --plugin my_filter.py --methods hard my_filter pcf

A plugin file (--plugin, repeatable, any command) is run first; it registers its methods
with mi_shadowmap.register_method(name, lookup, properties=...).
"""

GRID_HELP = """\
a sub-grid (repeatable; the sweep runs the union of the sub-grids). Either a JSON file,
inline JSON ('{"method": ["hard"], "resolution": [256, 512]}' or a list of such dicts),
or 'name=v1,v2 name=v1,v2 ...' items separated by spaces or ';'. Every sub-grid needs
'method'; 'spp' may be swept too. A property is combined only with the methods that use
it. Default: every map method at resolution 256,512,1024 and raytraced at spp 1..16."""


#: Error columns a sweep can trade against time (all "lower is better"): sweep.ERROR_KEYS,
#: spelled out so that the CLI's argument parser does not import Mitsuba
#: (tests/test_tune.py checks they agree).
ERROR_COLUMNS = ("vis_rmse", "vis_mae", "vis_misclassified", "vis_false_shadow",
                 "vis_false_lit", "vis_penumbra_rmse", "img_rmse", "img_mae",
                 "img_relative_mse", "img_flip")


PLUGIN_HELP = ("a Python file run before the command (repeatable) that registers shadow "
               "methods with mi_shadowmap.register_method(...); they are then valid in "
               "--methods and --grid")


def _ranged(kind: type, lo: float, hi: float | None = None, lo_open: bool = False,
            hi_open: bool = True, allow_inf: bool = False):
    """An argparse ``type``: an ``int``, or a ``float`` (finite unless ``allow_inf``),
    from ``lo`` (``lo_open``: above it) up to ``hi`` (``hi_open``: below it), so that a
    bad value is one line naming the option as typed (``argument --ref-spp: must be an
    integer >= 1, got '0'``) and its allowed values; the harness named its parameter
    (``'ref_spp'``), a name the command line does not have."""
    what = "an integer" if kind is int else "a number"
    if hi is None:
        rng = ("> " if lo_open else ">= ") + f"{lo:g}"
    else:
        top = "2^32" if hi == 2 ** 32 else f"{hi:g}"
        rng = ("in (" if lo_open else "in [") + f"{lo:g}, {top}" + (")" if hi_open else "]")

    def parse(text: str):
        try:
            value = kind(text)
        except ValueError:
            value = None
        bad = value is None or math.isnan(value) or (math.isinf(value) and not allow_inf)
        if not bad:
            bad = (value <= lo if lo_open else value < lo) or (
                hi is not None and (value >= hi if hi_open else value > hi))
        if bad:
            raise argparse.ArgumentTypeError(f"must be {what} {rng}, got {text!r}")
        return value
    parse.__name__ = kind.__name__
    return parse


_COUNT = _ranged(int, 1)                  # spp, repeats, reference spp and rays
_SEED = _ranged(int, 0, 2 ** 32)          # Mitsuba's sampler seed


class _Parser(argparse.ArgumentParser):
    """argparse with a one-line error (no usage dump) and exit status 2."""

    def error(self, message):
        self.exit(2, f"{self.prog}: error: {message} (see --help)\n")


def _add_scene_args(p, sizes=True, out="out"):
    p.add_argument("scene", nargs="?",
                   help="scene XML file (default: the built-in sphere-and-box scene)")
    p.add_argument("--light", default=None, choices=("spot", "point", "directional", "area"),
                   help="light of the built-in scene (default: spot); not with a scene file")
    if sizes:
        p.add_argument("--width", type=int, default=None,
                       help="image width (built-in scene, or an XML file with $width)")
        p.add_argument("--height", type=int, default=None,
                       help="image height (built-in scene, or an XML file with $height)")
    p.add_argument("--param", action="append", metavar="NAME=VALUE", default=[],
                   help="value of the scene file's $NAME parameter (repeatable), e.g. "
                        "--param light_distance=1e6; needed for one without a <default>")
    p.add_argument("--set", action="append", metavar="NAME=VALUE", default=[],
                   help="integrator property for every method that uses it (repeatable), "
                        "e.g. --set resolution=512 --set bias=0.01; overrides the scene "
                        "file's own <integrator type=\"shadowmap\"> properties")
    p.add_argument("--ignore-scene-integrator", action="store_true",
                   help="do not take the scene file's own <integrator type=\"shadowmap\"> "
                        "properties as the base of every method's (see 'mi-shadowmap "
                        "--help')")
    p.add_argument("--out", default=out, help=f"output folder (default: {out})")
    p.add_argument("--variant", default=None, metavar="NAME",
                   help="Mitsuba variant to render in: llvm_ad_rgb (default), llvm_ad_mono, "
                        "llvm_ad_spectral, their *_polarized twins, or cuda_ad_* where a "
                        "CUDA GPU exists")
    _add_common_args(p)


def _add_common_args(p):
    p.add_argument("--plugin", action="append", default=[], metavar="FILE.py",
                   help=PLUGIN_HELP)
    p.add_argument("--debug", action="store_true", help="show tracebacks on errors")


def _methods_help(what: str, maps: bool = False) -> str:
    """``what`` and the registered methods (``maps``: only those that read a depth map,
    the ones ``maps`` accepts)."""
    from .specs import available_methods, map_methods
    if maps:
        return f"{what}; with maps: {', '.join(map_methods())} (and --plugin ones)"
    return f"{what}; registered: {', '.join(available_methods())} (and --plugin ones)"


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(
        prog="mi-shadowmap",
        description="Compare depth-map shadow methods with ray-traced ground truth in "
                    "Mitsuba 3: images, visibility error metrics, timings, sweeps.",
        epilog=EPILOG_MAIN, formatter_class=argparse.RawDescriptionHelpFormatter)
    _add_common_args(p)
    sub = p.add_subparsers(dest="command", parser_class=_Parser)

    c = sub.add_parser(
        "compare", help="render the reference and each method, write images and metrics",
        description="Render the reference (raytraced for delta lights, with the size the "
                    "methods give them: light_size, angular_diameter; converged soft-shadow "
                    "reference for area lights and environments) and each method with one "
                    "seed (the reference too, unless --reference converged is given: that "
                    "one has a seed of its own); print "
                    "the metrics table; write <out>/<method>.exr (RGB, vis_<emitter>, "
                    "err_<emitter>, img_err), PNG previews, contact_sheet.png, pareto.png, "
                    "metrics.csv and metrics.json.")
    _add_scene_args(c)
    c.add_argument("--methods", nargs="+", default=None, metavar="METHOD",
                   help=_methods_help("methods to compare, each 'name' or "
                                      "'name:prop=value,prop=value' (default: every "
                                      "registered method except raytraced)"))
    c.add_argument("--spp", type=_COUNT, default=None,
                   help="samples per pixel (default: a scene file's sampler's "
                        "sample_count; 16 for the built-in scene)")
    c.add_argument("--seed", type=_SEED, default=0, help="sampler seed (default 0)")
    c.add_argument("--repeats", type=_COUNT, default=3,
                   help="warm re-renders per method; the median is reported (default 3)")
    c.add_argument("--reference", default="auto",
                   help="'auto' (default), 'converged', or a method spec like 'raytraced'")
    c.add_argument("--ref-spp", type=_COUNT, default=64,
                   help="spp of --reference converged, at least --spp (default 64); the "
                        "automatic reference renders at --spp, with the methods' camera "
                        "samples")
    c.add_argument("--ref-shadow-rays", type=_COUNT, default=64,
                   help="shadow rays per camera sample of the converged reference's image "
                        "(area lights and environments; default 64): they set its image "
                        "metrics (PSNR, FLIP, img_*); its visibility AOVs average 1024 light "
                        "samples whatever this is")

    s = sub.add_parser(
        "sweep", help="render a parameter grid, Pareto front of time vs error",
        description="Render every configuration of the grid, score it against one reference "
                    "and write sweep.csv, sweep.json and pareto.png; print the table with "
                    "the Pareto front (*) and equal-time / equal-error ratios against "
                    "raytraced.", formatter_class=argparse.RawDescriptionHelpFormatter)
    _add_scene_args(s, out="out/sweep")
    s.add_argument("--grid", action="append", default=None, metavar="FILE|INLINE",
                   help=GRID_HELP)
    s.add_argument("--spp", type=_COUNT, default=None,
                   help="spp of configurations that do not sweep spp (default: a scene "
                        "file's sampler's sample_count; 16 for the built-in scene)")
    s.add_argument("--seed", type=_SEED, default=0, help="sampler seed (default 0)")
    s.add_argument("--repeats", type=_COUNT, default=3,
                   help="warm re-renders per configuration, median reported (default 3)")
    s.add_argument("--error", default="vis_rmse", choices=ERROR_COLUMNS, metavar="COLUMN",
                   help="error axis of the trade (lower is better): "
                        + ", ".join(ERROR_COLUMNS) + " (default vis_rmse)")

    m = sub.add_parser("maps", help="export every depth map as float EXR",
                       description="Build the depth maps of every emitter (with the "
                                   "second/extra layers the chosen methods use) and write "
                                   "one EXR per emitter, <emitter>.exr: one channel per "
                                   "layer, cube faces stacked vertically (a layer of a few "
                                   "values, a prefiltered map's depth span *_span, is a "
                                   "header attribute of that name). Methods whose "
                                   "maps of an emitter differ (multiview's views of an area "
                                   "light beside a cube map; another resolution) get one "
                                   "file per map, <emitter>_<method>.exr. These are full "
                                   "maps, as virtual=false renders them (at the automatic "
                                   "resolution unless --set resolution=N), although renders "
                                   "default to virtual maps; --set virtual=true writes the "
                                   "virtual pages a render builds instead (pages stacked "
                                   "vertically; each page's face, level and position in the "
                                   "header attributes page_face, page_level, page_px, "
                                   "page_py).")
    _add_scene_args(m, sizes=False, out="out/maps")
    m.add_argument("--methods", nargs="+", default=None, metavar="METHOD",
                   help=_methods_help("build the layers these methods use (default: every "
                                      "method that reads a depth map)", maps=True))

    t = sub.add_parser(
        "tune", help="the fastest method and settings that meet an error budget",
        description="Search the methods and their main parameters on a reduced-size render "
                    "of the scene, verify the fastest configuration that meets --max-error "
                    "at full size against the reference (stepping up if it misses), and "
                    "find the raytraced configuration that meets the same budget. Prints "
                    "the choice and writes tune_pareto.png (the search's Pareto plot, pick "
                    "marked), tune.json and integrator.xml (a ready-to-paste <integrator>).")
    _add_scene_args(t, out="out/tune")
    t.add_argument("--max-error", type=_ranged(float, 0, lo_open=True), required=True,
                   metavar="E",
                   help="the error budget (> 0) on --metric at the full size")
    t.add_argument("--metric", default="vis_rmse",
                   help="error metric, lower is better: " + ", ".join(ERROR_COLUMNS)
                        + " (default vis_rmse)")
    t.add_argument("--methods", nargs="+", default=None, metavar="METHOD",
                   help=_methods_help("methods searched, 'name' or 'name:prop=value' (given "
                                      "properties stay fixed; default: every registered "
                                      "method)"))
    t.add_argument("--time-limit", type=_ranged(float, 0, lo_open=True, allow_inf=True),
                   default=None, metavar="SECONDS",
                   help="stop searching after 60%% of it and verifying at 100%% (default: none)")
    t.add_argument("--search-size", type=_ranged(int, 8), default=128, metavar="PIXELS",
                   help="long side of the reduced film searched on (default 128)")
    t.add_argument("--margin", type=_ranged(float, 0, 1), default=0.05,
                   help="the pick must meet --max-error x (1 - margin) at full size, "
                        "0 <= margin < 1 (default 0.05)")
    t.add_argument("--spp", type=_COUNT, default=None,
                   help="fix the spp (default: searched, up to --max-spp)")
    t.add_argument("--max-spp", type=_COUNT, default=1024, help="largest spp searched (1024)")
    t.add_argument("--seed", type=_SEED, default=0,
                   help="seed of the search's renders; the references and the verification "
                        "renders derive their own from it (default 0)")
    t.add_argument("--repeats", type=_COUNT, default=3,
                   help="warm re-renders per configuration, median reported (default 3)")
    return p


# --------------------------------------------------------------------------- helpers
def parse_sets(items) -> dict:
    """``["a=1", "b=x"]`` -> ``{"a": 1, "b": "x"}`` (the ``--set`` values)."""
    from .specs import parse_assignments
    return parse_assignments(items, "--set")


def parse_grid(text: str):
    """One ``--grid`` value: a JSON file, inline JSON, or ``name=v1,v2 ...`` items."""
    from .specs import parse_value
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
        if k.strip() in sub:    # ';' does not start another sub-grid: repeat --grid
            raise ValueError(f"--grid: {k.strip()!r} is given twice in {text!r} (one "
                             "sub-grid per --grid; repeat --grid for another)")
        sub[k.strip()] = [parse_value(x.strip()) for x in v.split(",") if x.strip()]
    if not sub:
        raise ValueError("--grid is empty")
    return sub


def check_scored_film(scene) -> None:
    """:func:`mi_shadowmap.timing.check_scored_film` and
    :func:`mi_shadowmap.ground_truth.check_emitters`, and that the scene has a sensor,
    before anything renders."""
    from .ground_truth import check_emitters
    from .timing import check_scored_film as check
    check_emitters(scene)
    if len(scene.sensors()) == 0:   # was Mitsuba's "No sensor specified!" mid-render
        raise ValueError("the scene has no sensor: comparing methods renders its first "
                         "sensor; add a <sensor> (with an hdrfilm)")
    note_sensors(scene)
    check(scene)


def note_sensors(scene, what: str = "renders") -> None:
    """A note naming the sensors left out when the scene has more than one: the
    commands render (``maps``: size virtual pages for) the first sensor only, and the
    others were dropped without a word."""
    sensors = scene.sensors()
    if len(sensors) < 2:
        return

    def name(k, s):
        return f"'{s.id()}'" if s.id() else f"#{k} ({s.class_name()})"
    rest = [name(k, s) for k, s in enumerate(sensors) if k > 0]
    note(f"the scene has {len(sensors)} sensors; this command {what} the first one, "
         f"{name(0, sensors[0])}, only (not {', '.join(rest)}): move the sensor to use "
         "to the top of the file")


def load_scene_arg(args, sizes=True):
    """The scene of ``args``: the XML file, or the built-in scene."""
    from . import scenes
    size = {}
    if sizes:
        for k in ("width", "height"):
            v = getattr(args, k, None)
            if v is not None:
                if v < 1:
                    raise ValueError(f"--{k} must be >= 1, got {v}")
                size[k] = v
    params = {}
    for item in getattr(args, "param", None) or []:
        name, eq, value = item.partition("=")
        name = name.strip().lstrip("$")
        if not eq or not re.fullmatch(r"[A-Za-z_]\w*", name):
            raise ValueError(f"--param expects NAME=VALUE (a scene file's $NAME), got {item!r}")
        if name in size:
            raise ValueError(f"--param {name}=... and --{name} both set ${name}; give one")
        params[name] = value
    if args.scene is None:
        if params:
            raise ValueError("--param fills a scene file's $ parameters; the built-in scene "
                             "has none (give a scene file, or use --width, --height, --light)")
        return scenes.load_scene(scenes.default_scene(light=args.light or "spot", **size))
    if args.light is not None:
        raise ValueError(f"--light {args.light} picks the built-in scene's light; the scene "
                         f"file {args.scene} brings its own (leave --light out, or the file)")
    try:
        return scenes.load_scene(args.scene, **size, **params)
    except RuntimeError as e:    # Mitsuba's parser: "... undefined parameter: $ypos"
        m = re.search(r"undefined parameter: \$(\w+)", str(e))
        if m is None:
            raise
        raise ValueError(f"scene file {args.scene} uses ${m.group(1)}, which has no "
                         f"<default>: give it with --param {m.group(1)}=VALUE") from None


#: compare's and sweep's spp for the built-in scene (a scene file without a <sampler>
#: gets Mitsuba's default one, of sample_count 4, and renders 4)
DEFAULT_SPP = 16


def run_spp(args, scene) -> int:
    """The spp compare and sweep render: ``--spp``; else the scene file's sampler's
    ``sample_count`` (its ``$spp`` too), named in a note where it is not 16 -- it was
    16 whatever the file or ``--param spp=N`` said; 16 for the built-in scene."""
    if args.spp is not None or args.scene is None:
        return args.spp if args.spp is not None else DEFAULT_SPP
    from .timing import sampler_spp
    n = sampler_spp(scene)      # read before any render: the file's own count
    if n < 1:
        return DEFAULT_SPP
    if n != DEFAULT_SPP:
        note(f"rendering {n} spp, the sample_count of the scene's sampler (Mitsuba's "
             "default, 4, where the file has no <sampler>; --spp overrides)")
    return n


def note(text: str) -> None:
    """One line on stderr: ``mi-shadowmap: note: <text>``."""
    print(f"mi-shadowmap: note: {text}", file=sys.stderr)


#: Properties of a scene's shadowmap integrator that the commands do not take: the
#: method (--methods chooses), cache_maps (frames are timed with maps rebuilt), and
#: visibility_aovs (the commands score and write the visibility AOVs: kept on; a scene
#: file may set it false for a plain mi.render of the file).
NOT_INHERITED = ("method", "cache_maps", "visibility_aovs")


def _fmt(props: dict) -> str:
    """``"bias=0.3, resolution=64"``."""
    from .specs import spec_name
    return ", ".join(spec_name({"method": "", k: v}).strip() for k, v in sorted(props.items()))


def scene_integrator_params(args, scene, sets: dict, used) -> dict:
    """``--set`` values over the properties of the scene file's own ``<integrator
    type="shadowmap">`` (:func:`mi_shadowmap.scenes.integrator_properties`) that a
    method of the command uses (``used(name)``); the shared properties of every method
    (method strings and sweep axes override both). Notes on stderr name the scene's
    properties taken and those left out; a scene integrator of another type is not
    used, with a note. ``--ignore-scene-integrator``: ``sets`` alone."""
    props = scene_integrator_base(args, scene)
    refused = {k: v for k, v in props.items() if k not in sets and used(k)
               and _refusing(used.methods, k, v)}
    for k, v in refused.items():
        who = _refusing(used.methods, k, v)
        note(f"the scene's shadowmap integrator sets {_fmt({k: v})}, which "
             f"{', '.join(who)} cannot take: not taken for any method (give it per method, "
             f"'<method>:{k}=...', or --set it)")
    taken = {k: v for k, v in props.items() if k not in sets and used(k) and k not in refused}
    unused = {k: v for k, v in props.items() if k not in sets and not used(k)}
    if taken:
        note(f"the scene's shadowmap integrator gives {_fmt(taken)} to every method that "
             "uses it (--set and 'method:prop=value' override; --ignore-scene-integrator "
             "drops them)" + (f"; {_fmt(unused)}: used by none of the methods, ignored"
                              if unused else ""))
    elif unused:
        note(f"the scene's shadowmap integrator sets {_fmt(unused)}, used by none of the "
             "methods: ignored")
    return {**taken, **sets}


def check_param_method(args, props: dict) -> None:
    """``--param method=X`` that filled the method of the scene's shadowmap integrator
    (every scene of ``scenes_xml/`` takes ``$method``), with no methods named: an error
    naming ``--methods`` (a sweep's ``--grid``). The commands do not take that method,
    so every method rendered without a word."""
    given = {}
    for item in getattr(args, "param", None) or []:
        name, _, value = item.partition("=")
        given[name.strip().lstrip("$")] = value.strip()
    named = args.grid if args.command == "sweep" else args.methods
    if "method" not in given or named or props.get("method") != given["method"]:
        return
    how = ("--grid 'method=" + given["method"] + " ...'" if args.command == "sweep"
           else f"--methods {given['method']}")
    raise ValueError(f"--param method={given['method']} fills the scene's $method, the "
                     "method of its <integrator type=\"shadowmap\">, which mi-shadowmap "
                     f"{args.command} does not take: name the methods with {how}")


def scene_integrator_base(args, scene) -> dict:
    """The scene's shadowmap integrator properties the commands take (none with
    ``--ignore-scene-integrator``); notes on the ones not taken."""
    from .scenes import integrator_properties
    if getattr(args, "ignore_scene_integrator", False) or args.scene is None:
        return {}
    props, other = integrator_properties(scene)
    if other is not None:
        note(f"the scene's integrator ({other}) is not 'shadowmap' and is not used: every "
             "method renders with the shadowmap integrator")
        return {}
    props = props or {}
    check_param_method(args, props)
    dropped = {k: props[k] for k in ("cache_maps",) if k in props}
    if dropped and args.command != "maps":
        note(f"the scene's shadowmap integrator sets {_fmt(dropped)}, not taken (frames "
             "are timed with the maps rebuilt; --set cache_maps=true caches them)")
    if props.get("visibility_aovs") is False and args.command != "maps":
        note("the scene's shadowmap integrator sets visibility_aovs=false, not taken: "
             f"mi-shadowmap {args.command} scores and writes the visibility AOVs")
    return {k: v for k, v in props.items() if k not in NOT_INHERITED}


def _used_by(specs_or_names):
    """``used(name)``: whether one of the methods uses the shared property ``name``
    (``used.methods``: their names)."""
    from .specs import uses_property
    names = [s["method"] if isinstance(s, dict) else s for s in specs_or_names]

    def used(k):
        return any(uses_property(m, k) for m in names)
    used.methods = names
    return used


def _accepts(method: str, name: str, value) -> bool:
    """Whether ``method`` takes property ``name`` = ``value`` (some methods use a
    property but refuse some values: ``virtual=true`` for ``multiview``)."""
    from .options import OptionError
    from .specs import validate_spec
    try:
        validate_spec({"method": method, name: value})
    except OptionError:
        return False
    return True


def _refusing(methods, name: str, value) -> list:
    """The ``methods`` that use property ``name`` but refuse ``value``."""
    from .specs import uses_property
    return [m for m in dict.fromkeys(methods)
            if uses_property(m, name) and not _accepts(m, name, value)]


# --------------------------------------------------------------------------- commands
def cmd_compare(args) -> int:
    from . import harness, report
    out = args.out
    params = parse_sets(args.set)
    methods = [harness.method_spec(m, params) for m in (args.methods or
                                                        harness.default_methods())]
    harness.check_shared_params(methods, params)
    harness.check_run_args(spp=args.spp, seed=args.seed, repeats=args.repeats,
                           ref_spp=args.ref_spp, ref_shadow_rays=args.ref_shadow_rays)
    harness.check_unique(methods)
    if "spp" in params:
        raise ValueError(f"--set spp={params['spp']}: compare's samples per pixel are "
                         "--spp (the reference shares them); give a method its own with "
                         "'<method>:spp=N'")
    reference = args.reference
    if reference not in ("auto", "converged"):
        reference = harness.method_spec(reference)
    scene = load_scene_arg(args)
    check_scored_film(scene)
    spp = run_spp(args, scene)
    params = scene_integrator_params(args, scene, params, _used_by(methods))
    methods = [harness.method_spec(m, params) for m in (args.methods or
                                                        harness.default_methods())]
    report.check_out_dir(out, create=False)   # made when written: no empty folder
    try:
        results = harness.compare(scene, methods=methods, reference=reference, spp=spp,
                                  seed=args.seed, repeats=args.repeats, progress=True,
                                  ref_spp=args.ref_spp, ref_shadow_rays=args.ref_shadow_rays,
                                  **params)
    except BaseException as exc:    # a method that failed, Ctrl-C: keep those rendered
        done = getattr(exc, "compare_results", None)
        if done is not None and len(done) > 1:
            _close_progress_bars()
            print(harness.format_table(done))
            report.write_results(done, out)
            print(f"mi-shadowmap: the comparison stopped after {len(done) - 1} of "
                  f"{len(methods)} methods; the reference and those are in "
                  f"{os.path.abspath(out)}", file=sys.stderr)
        raise
    print(harness.format_table(results))
    # a method scored against a reference of its own (its own spp, another light size)
    for r in results[1:]:
        if r.scored_against is not None:
            print(f"{r.name}: scored against {r.scored_against.name}")
    written = report.write_results(results, out)
    print(f"\nwrote {len(written['exr'])} EXR, {len(written['png'])} PNG, metrics.csv and "
          f"metrics.json to {os.path.abspath(out)}")
    return 0


def cmd_sweep(args) -> int:
    from . import harness, report
    out = args.out
    params = parse_sets(args.set)
    grid = None
    if args.grid:
        grid = []
        for g in args.grid:
            sub = parse_grid(g)
            grid += sub if isinstance(sub, list) else [sub]
    grid = grid if grid is not None else harness.default_grid()
    harness.expand_grid(harness.with_shared(grid, params) if params else grid,
                        default_spp=args.spp or DEFAULT_SPP)   # reject bad entries first
    harness.check_run_args(spp=args.spp, seed=args.seed, repeats=args.repeats)
    scene = load_scene_arg(args)
    check_scored_film(scene)
    spp = run_spp(args, scene)
    grid_methods = [m for g in ([grid] if isinstance(grid, dict) else grid)
                    for m in ([g.get("method", [])] if isinstance(g.get("method"), str)
                              else g.get("method", []))]
    params = scene_integrator_params(args, scene, params, _used_by(grid_methods))
    if params:   # fixed axes of every sub-grid with a method using them (its axes win)
        grid = harness.with_shared(grid, params)
    report.check_out_dir(out, create=False)   # made when written: no empty folder
    try:
        table = harness.sweep(scene, grid, spp=spp, seed=args.seed,
                              repeats=args.repeats, error_key=args.error, progress=True)
    except BaseException as exc:    # a bug, Ctrl-C: the rows rendered so far are kept
        done = getattr(exc, "sweep_table", None)
        if done is not None and len(done):
            report.write_sweep(done, out)
            print(f"mi-shadowmap: the sweep stopped; the {len(done)} rows rendered are in "
                  f"{os.path.abspath(out)}", file=sys.stderr)
        raise
    print(table.format())
    written = report.write_sweep(table, out)
    print(f"\nwrote sweep.csv, sweep.json and pareto.png to {os.path.abspath(out)}")
    return 0 if written else 1


def cmd_maps(args) -> int:
    from . import harness, report
    out = args.out
    params = parse_sets(args.set)
    harness.map_specs(args.methods, params)   # validated before anything loads
    scene = load_scene_arg(args, sizes=False)
    from .ground_truth import check_emitters
    check_emitters(scene, "depth map to write")
    note_sensors(scene, "builds the maps (virtual pages) for")
    params = scene_integrator_params(args, scene, params,
                                     _used_by(harness.map_specs(args.methods)))
    harness.map_specs(args.methods, params)
    report.check_out_dir(out, create=False)   # made when written: no empty folder
    maps = harness.emitter_maps(scene, args.methods, **params)
    if not maps:      # environment emitters only, and no method of --methods maps them
        raise ValueError("shadowmap: no emitter of the scene has a depth map (an "
                         "environment emitter has one only with environment='shadowed')")
    # an emitter with several maps (methods whose maps differ: multiview's K views
    # beside a cube map) has one file per map, <label>_<its first method>.exr
    count = {}
    for m in maps:
        count[m.index] = count.get(m.index, 0) + 1
    names = [m.label if count[m.index] == 1 else f"{m.label} {m.methods[0].split()[0]}"
             for m in maps]
    paths = report.write_maps([m.map for m in maps], out, names=names)
    for m, path in zip(maps, paths):
        smap = m.map
        print(f"{path}: {m.label} ({harness.describe_map(smap)}), layers "
              f"{', '.join(smap.layers())}; read by {', '.join(m.methods)}")
    return 0


def tune_methods(args, scene, sets: dict):
    """``--methods`` of tune with the scene file's own shadowmap integrator properties
    (:func:`scene_integrator_params`) fixed in each method that uses them and does not
    search them (tune searches ``resolution`` and :data:`mi_shadowmap.tune.MAIN_PARAMETERS`;
    those start from the package defaults), below ``--set`` and the method strings.
    ``args.methods`` as it is when the scene gives nothing to add."""
    from .specs import available_methods, method_spec, uses_property
    from .tune import MAIN_PARAMETERS
    props = {k: v for k, v in scene_integrator_base(args, scene).items() if k not in sets}
    if not props:
        return args.methods
    items = [method_spec(m) for m in (args.methods or available_methods())]
    fixed, searched, unused = {}, {}, dict(props)
    for spec in items:
        m = spec["method"]
        tuned = {"resolution", *MAIN_PARAMETERS.get(m, {})}
        for k, v in props.items():
            if not uses_property(m, k):
                continue
            unused.pop(k, None)
            if k in spec:      # the method string's value
                continue
            if not _accepts(m, k, v):
                note(f"the scene's shadowmap integrator sets {_fmt({k: v})}, which {m} "
                     "cannot take: not taken for it")
                continue
            if k in tuned:
                searched[k] = v
            else:
                spec[k] = fixed[k] = v
    if fixed:
        note(f"the scene's shadowmap integrator gives {_fmt(fixed)} to every method that "
             "uses it, fixed (--set and 'method:prop=value' override; "
             "--ignore-scene-integrator drops them)")
    if searched:
        note(f"the scene's shadowmap integrator sets {_fmt(searched)}, which tune searches "
             "(--set fixes a value)")
    if unused:
        note(f"the scene's shadowmap integrator sets {_fmt(unused)}, used by none of the "
             "methods: ignored")
    return items if fixed else args.methods


def cmd_tune(args) -> int:
    from . import report
    from .tune import check_inputs, format_result, integrator_xml, tune
    out = args.out
    params = parse_sets(args.set)
    kwargs = dict(metric=args.metric, methods=args.methods, time_limit=args.time_limit,
                  search_size=args.search_size, margin=args.margin, spp=args.spp,
                  max_spp=args.max_spp)
    check_inputs(args.max_error, params=params, **kwargs)   # before anything renders
    from .specs import check_run_args
    check_run_args(seed=args.seed, repeats=args.repeats)
    scene = load_scene_arg(args)
    check_scored_film(scene)
    kwargs["methods"] = tune_methods(args, scene, params)
    report.check_out_dir(out, create=False)   # made when written: no empty folder
    try:
        res = tune(scene, args.max_error, seed=args.seed, repeats=args.repeats,
                   progress=True, **kwargs, **params)
    except BaseException as exc:    # Ctrl-C, a bug, no pick: the search so far is kept
        done = getattr(exc, "tune_result", None)
        if done is not None and len(done["sweep"]):
            _close_progress_bars()
            print(format_result(done))
            written = _write_tune(done, out)
            what = "was interrupted" if done["interrupted"] else "stopped on an error"
            pick = (f" and the best pick verified so far ({done['name']}; a faster one may "
                    "exist)" if done["name"] is not None else "")
            print(f"mi-shadowmap: tune {what} after {done['search']['renders']} search "
                  f"renders; those{pick} are in {os.path.abspath(out)} "
                  f"({', '.join(written)}, marked \"partial\": true)", file=sys.stderr)
        raise
    print(format_result(res))
    _write_tune(res, out)
    print("\n" + integrator_xml(res))
    print(f"wrote tune_pareto.png, tune.json and integrator.xml to {os.path.abspath(out)}")
    return 0


def _write_tune(res: dict, out: str) -> list[str]:
    """``tune_pareto.png``, ``tune.json`` and (if there is a pick) ``integrator.xml`` of a
    :func:`~mi_shadowmap.tune` result, complete or partial; the names written."""
    from . import report
    from .report import tune_plot
    from .tune import integrator_xml, result_json
    report.check_out_dir(out)
    tune_plot(res, os.path.join(out, "tune_pareto.png"))
    with open(os.path.join(out, "tune.json"), "w") as f:
        json.dump(result_json(res), f, indent=2)
    written = ["tune_pareto.png", "tune.json"]
    xml = os.path.join(out, "integrator.xml")
    if res["name"] is not None:
        with open(xml, "w") as f:
            f.write(integrator_xml(res))
        written.append("integrator.xml")
    elif os.path.isfile(xml) and _is_tune_xml(xml):
        # an earlier tune's pick, beside this run's tune.json without one: it was
        # left there and read as this run's result
        os.remove(xml)
        import warnings
        warnings.warn(f"removed {xml}: an earlier tune run's pick (this run verified "
                      "none; its tune.json and tune_pareto.png replaced that run's)",
                      stacklevel=2)
    elif os.path.exists(xml):
        import warnings
        warnings.warn(f"{xml} is not this run's (it verified no pick): the file was "
                      "there before and is left as it was", stacklevel=2)
    return written


def _is_tune_xml(path: str) -> bool:
    """Whether the file ``path`` is an ``integrator.xml`` that tune wrote (its first
    line is tune's comment, partial or not); a file of the user's is left alone."""
    try:
        with open(path) as f:
            first = f.readline()
    except (OSError, UnicodeDecodeError):
        return False
    return first.startswith("<!-- ") and "mi-shadowmap tune:" in first


_COMMANDS = {"compare": cmd_compare, "sweep": cmd_sweep, "maps": cmd_maps, "tune": cmd_tune}


def _pre_parse(argv):
    """``(plugin files, debug, variant, the other arguments)``: ``--plugin``, ``--debug``
    and ``--variant`` are taken out wherever they stand (before or after the command:
    ``mi-shadowmap --variant llvm_ad_mono sweep scene.xml`` said "unrecognized arguments:
    scene.xml", and without a scene "scene file not found: sweep")."""
    pre = _Parser(prog="mi-shadowmap", add_help=False, allow_abbrev=False)
    pre.add_argument("--plugin", action="append", default=[])
    pre.add_argument("--debug", action="store_true")
    pre.add_argument("--variant", default=None)
    known, rest = pre.parse_known_args(argv)
    return known.plugin, known.debug, known.variant, rest


def _unknown_command(word: str) -> str | None:
    """The error for a first argument that is neither a command, an option nor a scene
    file (an existing file, or a name ending in .xml): a mistyped command
    ('compar scene.xml' said "unrecognized arguments: scene.xml"). None otherwise."""
    if (word in _COMMANDS or word.startswith("-") or os.path.exists(word)
            or word.lower().endswith(".xml")):
        return None
    import difflib
    close = difflib.get_close_matches(word, list(_COMMANDS), n=1)
    hint = f" (did you mean '{close[0]}'?)" if close else ""
    return (f"unknown command '{word}'{hint}; commands: {', '.join(_COMMANDS)}, or a scene "
            "file (.xml) to compare")


class PluginError(RuntimeError):
    """A ``--plugin`` file is missing or failed to run."""


def load_plugin(path: str):
    """Run the Python file ``path`` as a module (it registers its methods with
    :func:`mi_shadowmap.register_method`); return the module. A missing file or an
    error while running it raises :class:`PluginError` naming the file."""
    if not os.path.isfile(path):
        raise PluginError(f"shadowmap: plugin file not found: {path}")
    stem = re.sub(r"\W", "_", os.path.splitext(os.path.basename(path))[0])
    name = f"mi_shadowmap_plugin_{stem}"
    spec = importlib.util.spec_from_file_location(name, path)
    if spec is None or spec.loader is None:
        raise PluginError(f"shadowmap: plugin {path} is not a Python file")
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    try:
        spec.loader.exec_module(module)
    except Exception as e:   # one line naming the file; --debug shows the traceback
        del sys.modules[name]
        raise PluginError(f"shadowmap: plugin {path} failed: {type(e).__name__}: "
                          f"{' '.join(str(e).split())}")
    return module


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    try:
        plugins, debug, variant, rest = _pre_parse(argv)
    except SystemExit as e:          # e.g. --plugin without a file name
        return e.code if isinstance(e.code, int) else 2
    parser = build_parser()
    if rest and _unknown_command(rest[0]):
        print(f"mi-shadowmap: error: {_unknown_command(rest[0])} (see --help)",
              file=sys.stderr)
        return 2
    if not rest or rest[0] not in tuple(_COMMANDS) + ("-h", "--help"):
        rest = ["compare"] + rest      # no command: compare (default scene unless given)
    try:
        args = parser.parse_args(rest)
    except SystemExit as e:          # --help (0) or a usage error (2, one line printed)
        return e.code if isinstance(e.code, int) else 2
    # an abbreviation after the command ("--varia X") reaches the command's own parser
    # only (the pre-parse takes whole names): taken from there too, not dropped
    if variant is None:
        variant = getattr(args, "variant", None)
    plugins = list(plugins) + [p for p in getattr(args, "plugin", None) or []
                               if p not in plugins]
    debug = debug or bool(getattr(args, "debug", False))
    try:
        with one_line_warnings():
            # the package's import does the LLVM set-up and the registration
            importlib.import_module("mi_shadowmap")
            if variant is not None:
                set_variant(variant)
            for path in plugins:
                load_plugin(path)
            return _COMMANDS[args.command](args)
    except KeyboardInterrupt:
        print("mi-shadowmap: interrupted", file=sys.stderr)
        return 130
    except Exception as e:  # one line, no traceback, unless --debug
        from .timing import root_error
        if isinstance(root_error(e), KeyboardInterrupt):   # mi.render wraps a Ctrl-C
            _close_progress_bars()
            print("mi-shadowmap: interrupted", file=sys.stderr)
            return 130
        if debug:
            raise
        _close_progress_bars()
        print(f"mi-shadowmap: error: {one_line(e)}", file=sys.stderr)
        return 2


@contextlib.contextmanager
def one_line_warnings():
    """Warnings shown while the command runs are one line on stderr, ``mi-shadowmap:
    warning: <message>`` (Python's default format added the file and line that warned
    and that line's source). Warnings recorded by a caller (``pytest.warns``,
    ``warnings.catch_warnings(record=True)``) are recorded as before."""
    previous = warnings.formatwarning

    def formatwarning(message, category, filename, lineno, line=None):
        kind = "" if category is UserWarning else f"{category.__name__}: "
        return f"mi-shadowmap: warning: {kind}{' '.join(str(message).split())}\n"

    warnings.formatwarning = formatwarning
    try:
        yield
    finally:
        warnings.formatwarning = previous


def _close_progress_bars() -> None:
    """End the progress bars an error interrupted, so that the error's line starts a
    line of its own (it was appended to the unfinished bar)."""
    try:
        from tqdm import tqdm
    except ImportError:
        return
    for bar in list(getattr(tqdm, "_instances", ())):
        bar.close()


def set_variant(name: str) -> None:
    """Switch Mitsuba to the variant ``name``, or raise naming it and the supported ones."""
    import mitsuba as mi
    from .variants import UnsupportedVariantError, check_variant
    check_variant(name)
    try:
        mi.set_variant(name)
    except Exception as e:   # e.g. cuda_ad_* on a machine without a CUDA GPU
        import drjit as dr
        if name.startswith("cuda") and not dr.has_backend(dr.JitBackend.CUDA):
            # Dr.Jit's own text ("Make sure to call jit_init(JitBackend::CUDA)") is advice
            # for its C++ users
            why = ("Dr.Jit found no CUDA GPU or driver; use an llvm_ad_* variant, e.g. "
                   f"{name.replace('cuda', 'llvm', 1)}")
        else:
            why = one_line(e)
        raise UnsupportedVariantError(
            f"shadowmap: the Mitsuba variant '{name}' cannot be set on this machine "
            f"({why})") from None


def one_line(exc: BaseException) -> str:
    """The most informative line of a (possibly wrapped Mitsuba) error."""
    from .timing import root_error
    exc = root_error(exc)              # mi.render wraps errors of a Python integrator
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
