"""The ``mi-shadowmap`` command line.

``mi-shadowmap`` with no arguments runs ``compare`` on the built-in default
scene (the README's main command).
"""
from __future__ import annotations

import argparse
import os
import sys


def _parse_value(text: str):
    low = text.lower()
    if low in ("true", "false"):
        return low == "true"
    for conv in (int, float):
        try:
            return conv(text)
        except ValueError:
            pass
    return text


def _parse_sets(items) -> dict:
    out = {}
    for item in items or []:
        if "=" not in item:
            raise ValueError(f"--set expects name=value, got {item!r}")
        k, v = item.split("=", 1)
        out[k.strip()] = _parse_value(v.strip())
    return out


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="mi-shadowmap",
        description="Compare depth-map shadow methods against ray-traced ground truth "
                    "in Mitsuba 3. With no command, runs 'compare' on the built-in scene.")
    p.add_argument("--debug", action="store_true", help="show tracebacks on errors")
    sub = p.add_subparsers(dest="command")
    c = sub.add_parser("compare", help="render methods and the reference, write images + metrics")
    c.add_argument("scene", nargs="?", help="scene XML (default: built-in spot-light scene)")
    c.add_argument("--methods", nargs="+", default=None,
                   help="methods to compare (default: every shadow-map method)")
    c.add_argument("--set", action="append", metavar="NAME=VALUE",
                   help="integrator property for every method (repeatable)")
    c.add_argument("--spp", type=int, default=16, help="samples per pixel (default 16)")
    c.add_argument("--resolution", type=int, default=None, help="depth-map resolution")
    c.add_argument("--out", default="out", help="output folder (default ./out)")
    m = sub.add_parser("maps", help="export every depth map as EXR")
    m.add_argument("scene", nargs="?", help="scene XML (default: built-in scene)")
    m.add_argument("--set", action="append", metavar="NAME=VALUE")
    m.add_argument("--out", default="out/maps")
    return p


def _load(scene_arg):
    from . import harness, scenes
    if scene_arg is None:
        return harness.load_scene(scenes.default_scene())
    return harness.load_scene(scene_arg)


def cmd_compare(args) -> int:
    from . import harness, report
    from .options import MAP_METHODS, METHODS
    params = _parse_sets(args.set)
    if args.resolution is not None:
        params["resolution"] = args.resolution
    methods = args.methods or [m for m in METHODS if m in MAP_METHODS]
    scene = _load(args.scene)
    _check_out(args.out)
    results = harness.compare(scene, methods=methods, spp=args.spp, progress=True, **params)
    print(harness.format_table(results))
    written = report.write_results(results, args.out)
    print(f"\nwrote {len(written['exr'])} EXR, {len(written['png'])} PNG, metrics.csv and "
          f"metrics.json to {os.path.abspath(args.out)}")
    return 0


def cmd_maps(args) -> int:
    import mitsuba as mi
    from .depth_maps import write_exr
    params = _parse_sets(args.set)
    scene = _load(args.scene)
    _check_out(args.out)
    integrator = mi.load_dict({"type": "shadowmap", "method": params.pop("method", "hard"),
                               **params})
    maps = integrator.prepare_maps(scene)
    for smap in maps:
        if smap is None:
            continue
        for layer in smap.layers():
            path = os.path.join(args.out, f"{smap.view.label}_{layer}.exr")
            write_exr(smap, path, layer)
            print(f"{path}: {smap.view.describe()}, {smap.resolution}^2")
    return 0


def _check_out(out):
    try:
        os.makedirs(out, exist_ok=True)
    except OSError as e:
        raise PermissionError(f"cannot create output folder {out}: {e.strerror}") from None
    if not os.access(out, os.W_OK):
        raise PermissionError(f"output folder is not writable: {out}")


_COMMANDS = ("compare", "maps")


def main(argv=None) -> int:
    parser = build_parser()
    argv = list(sys.argv[1:] if argv is None else argv)
    flags = [a for a in argv if a == "--debug"]
    rest = [a for a in argv if a != "--debug"]
    if not rest or rest[0] not in _COMMANDS + ("-h", "--help"):
        rest = ["compare"] + rest      # no command: compare (default scene unless given)
    args = parser.parse_args(flags + rest)
    try:
        import mi_shadowmap  # noqa: F401  (LLVM set-up and registration)
        handler = {"compare": cmd_compare, "maps": cmd_maps}[args.command]
        return handler(args)
    except Exception as e:  # one line, no traceback, unless --debug
        if args.debug:
            raise
        msg = str(e).strip().splitlines()
        print(f"mi-shadowmap: error: {_innermost(msg)}", file=sys.stderr)
        return 2


def _innermost(lines) -> str:
    """The most informative line of a (possibly nested Mitsuba) error message."""
    for line in lines:
        if "shadowmap:" in line:
            return line[line.index("shadowmap:"):]
    return lines[-1] if lines else "unknown error"


if __name__ == "__main__":
    sys.exit(main())
