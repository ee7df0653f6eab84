"""Method specs: the grammar of "which method, with which properties", and its validation.

A *method spec* is a dict ``{"method": name, <integrator properties>..., "spp": n}``.
:func:`method_spec` accepts the three ways of writing one: a name
(``"hard"``), a dict, or the string form ``"pcf:num_samples=4,res_factor=2"``
(the CLI's ``--methods`` and ``--set``). Every spec is validated with
:func:`~mi_shadowmap.options.parse_options` -- the only place that checks
properties -- before anything renders, so a typo'd comparison or sweep never
silently runs with defaults.

Which properties a method takes, and which methods exist, is read from the
method registry (:mod:`mi_shadowmap.methods`) and the scopes of
:mod:`mi_shadowmap.options`, so user methods registered with
:func:`mi_shadowmap.register_method` are specs like any built-in. Nothing
here renders.
"""
from __future__ import annotations

from . import methods as methods_mod
from . import options
from .options import OptionError

#: Keys of a method spec / sweep grid that are render settings, not integrator properties.
RENDER_KEYS = ("spp",)
#: The ground-truth method: the reference of delta lights and the baseline of sweeps.
REFERENCE_METHOD = "raytraced"


# --------------------------------------------------------------------------- registry
def available_methods() -> list[str]:
    """Every registered method (built-ins first, then user methods)."""
    return list(methods_mod.METHODS)


def default_methods() -> list[str]:
    """The methods a comparison runs by default: every registered one except the
    reference (:data:`REFERENCE_METHOD`)."""
    return [m for m in available_methods() if m != REFERENCE_METHOD]


def map_methods() -> list[str]:
    """Every registered method that reads a depth map."""
    return list(methods_mod.MAP_METHODS)


def uses_property(method: str, name: str) -> bool:
    """Whether a shared value of property ``name`` (``--set``, ``compare(**params)``,
    a sweep axis) is given to ``method``.

    The property must apply to the method (:func:`~mi_shadowmap.options.applies`),
    and a method that reads no map does not get the depth-map settings that it
    merely accepts (``resolution``, ``memory_budget``, ``cache_maps``: scope
    ``ACCEPTED``), so that e.g. ``resolution=[256, 512]`` in a sweep is not
    crossed with ``raytraced``. Unknown methods use nothing.
    """
    if name == "method" or name not in options.known_names():
        return False
    record = _record(method)
    if record is None or not options.applies(record, name):
        return False
    return record.uses_map or options.SCOPES.get(name) != options.ACCEPTED


def users_of(name: str) -> list[str]:
    """The methods that a shared value of ``name`` is given to (see :func:`uses_property`)."""
    return [m for m in available_methods() if uses_property(m, name)]


def _record(method: str):
    return next((m for m in methods_mod.records() if m.name == method), None)


def property_record(name: str):
    """The :class:`~mi_shadowmap.methods.Prop` of property ``name`` (shared, or a
    registered method's own), or None."""
    return next((p for p in options.all_properties() if p.name == name), None)


# --------------------------------------------------------------------------- grammar
def parse_value(text: str):
    """A command-line value: true/false, int, float, or the string itself."""
    low = text.lower()
    if low in ("true", "false"):
        return low == "true"
    for conv in (int, float):
        try:
            return conv(text)
        except ValueError:
            pass
    return text


def parse_method_string(text: str) -> dict:
    """``"pcf:num_samples=4,res_factor=2"`` -> ``{"method": "pcf", ...}``. A pair value
    is written with its comma (``"pcf:bias_range=0,0.01"``, as :func:`spec_name` prints
    it): an item without ``=`` continues the previous value. A name given twice is an
    error."""
    name, _, rest = text.partition(":")
    spec = {"method": name.strip()}
    items = []
    for item in filter(None, (s.strip() for s in rest.split(","))):
        if "=" not in item:
            if not items:
                raise OptionError(f"shadowmap: expected name=value in method spec "
                                  f"{text!r}, got {item!r}")
            items[-1] += "," + item
            continue
        items.append(item)
    for item in items:
        k, v = (x.strip() for x in item.split("=", 1))
        if k in spec:
            raise OptionError(f"shadowmap: {k!r} is given twice in method spec {text!r}")
        spec[k] = parse_value(v)
    return spec


def parse_assignments(items, what: str = "--set") -> dict:
    """``["a=1", "b=x"]`` -> ``{"a": 1, "b": "x"}`` (values by :func:`parse_value`); a
    name given twice is an error."""
    out = {}
    for item in items or []:
        if "=" not in item:
            raise ValueError(f"{what} expects name=value, got {item!r}")
        k, v = (x.strip() for x in item.split("=", 1))
        if k in out:
            raise ValueError(f"{what}: {k!r} is given twice")
        out[k] = parse_value(v)
    return out


def spec_name(spec: dict) -> str:
    """Display name: the method plus its given parameters (sorted)."""
    rest = {k: v for k, v in spec.items() if k != "method"}
    return spec["method"] + "".join(f" {k}={_fmt_value(v)}" for k, v in sorted(rest.items()))


def _fmt_value(v):
    if isinstance(v, (tuple, list)):
        return ",".join(str(x) for x in v)
    return str(v)


# --------------------------------------------------------------------------- validation
def method_spec(item, params: dict | None = None) -> dict:
    """Normalise a method item: ``"hard"``, ``{"method": "pcf", "num_samples": 4}`` or
    the string form ``"pcf:num_samples=4,res_factor=2"``.

    ``params`` (shared by every method) are added for the properties the method
    uses (:func:`uses_property`); the item's own values win. The result is
    validated.
    """
    if isinstance(item, str):
        spec = parse_method_string(item)
    elif isinstance(item, dict):
        spec = dict(item)
    else:
        raise OptionError(f"shadowmap: a method must be a name or a dict, got {item!r}")
    if "method" not in spec:
        raise OptionError(f"shadowmap: method spec {item!r} has no 'method'; valid methods: "
                          + ", ".join(available_methods()))
    for k, v in (params or {}).items():
        if (k in RENDER_KEYS or uses_property(spec["method"], k)) and k not in spec:
            spec[k] = v
    validate_spec(spec)
    return spec


def validate_spec(spec: dict) -> options.Options:
    """Validate one spec (integrator properties plus ``spp``); return its Options. A
    spec with ``visibility_aovs=false`` is refused (:func:`check_visibility_aovs`)."""
    props = {k: v for k, v in spec.items() if k not in RENDER_KEYS}
    if "spp" in spec:
        spp = spec["spp"]
        if isinstance(spp, bool) or not isinstance(spp, int) or spp < 1:
            raise OptionError(f"shadowmap: 'spp' must be an integer >= 1, got {spp!r}")
    opts = options.parse_options({"type": "shadowmap", **props})
    check_visibility_aovs(opts)
    return opts


def check_visibility_aovs(opts) -> None:
    """``visibility_aovs=false`` in a spec is an error naming the property: every user
    of specs (``compare``, ``sweep``, ``tune``, ``remeasure``, ``harness.render``,
    ``maps`` and the command line, the notebooks through them) reads the visibility
    AOVs or promises them in its result, and without them the metrics would be taken
    from channels the image does not have (a render's channels split into colour and
    AOVs by :func:`~mi_shadowmap.timing.split_channels`). The property is for a user's
    own ``mi.render``."""
    if not opts.visibility_aovs:
        raise OptionError(
            "shadowmap: property 'visibility_aovs' = false leaves the visibility AOVs "
            "(vis_<emitter>) out of the image, and comparisons, sweeps, tune, maps and "
            "harness.render read them (vis_rmse, the error layers, ...): leave "
            "'visibility_aovs' out here; it is for your own mi.render(scene) whose image "
            "should hold the film's channels only")


def check_run_args(**args) -> None:
    """Validate a run's own arguments, named as given: ``spp``, ``repeats``, ``ref_spp``
    and ``ref_shadow_rays`` integers >= 1, ``seed`` an integer in [0, 2^32) (Mitsuba's
    sampler seed), ``methods`` not empty. ``None`` values are skipped."""
    lows = {"spp": 1, "repeats": 1, "ref_spp": 1, "ref_shadow_rays": 1, "seed": 0}
    for name, value in args.items():
        if value is None:
            continue
        if name == "methods":
            if len(list(value)) == 0:
                raise OptionError("shadowmap: 'methods' is empty; leave it out (None) for "
                                  "every registered method, or name some: "
                                  + ", ".join(default_methods()))
            continue
        lo = lows[name]
        hi = 2 ** 32 if name == "seed" else None
        if isinstance(value, bool) or not isinstance(value, int) or value < lo \
                or (hi is not None and value >= hi):
            rng = "in [0, 2^32)" if hi is not None else f">= {lo}"
            raise OptionError(f"shadowmap: '{name}' must be an integer {rng}, got {value!r}")


def derived_seed(seed: int, k: int) -> int:
    """The seed ``k`` after ``seed`` (another seed for a reference or a re-measurement),
    within Mitsuba's [0, 2^32): ``seed + 1`` of the largest seed ``check_run_args`` takes,
    2^32 - 1, failed in Dr.Jit's ``sample_tea_32`` with "incompatible function
    arguments" after the setup."""
    return (int(seed) + int(k)) % 2 ** 32


def check_unique(specs: list[dict], rounded: list | None = None) -> None:
    """Two specs with one name (:func:`spec_name`) are an error: their records and output
    files would share it. ``rounded``: for the message, the specs whose ``spp`` the
    scene's sampler rounds (``"'pcf spp=3' at spp=4"``; ``specs`` hold the spp rendered)."""
    names = [spec_name(s) for s in specs]
    twice = sorted({n for n in names if names.count(n) > 1})
    if twice:
        why = (f" (the scene's sampler renders {', '.join(rounded)}; list each spp it "
               "renders once)" if rounded else "")
        raise OptionError(f"shadowmap: method {', '.join(repr(n) for n in twice)} is listed "
                          "more than once" + why)


def validate_property(name: str, value) -> None:
    """Validate one property name and value, whichever method uses it.

    An unknown name is an error naming it (and the valid ones); a value is
    valid if one of the methods that accept the property takes it (its
    first error is raised otherwise).
    """
    users = [] if name == "method" else list(options.methods_using(name))
    if not users:
        options.parse_options({name: value})   # "method", or an unknown name: raises
        return
    first = None
    for m in users:
        try:
            options.parse_options({"method": m, name: value})
            return
        except OptionError as e:
            first = first or e
    raise first


def check_no_shared_method(params: dict) -> None:
    """``method`` among the shared properties is an error: every spec names its own
    method, so a shared one (``compare(scene, methods=["hard"], method="pcf")``, the
    CLI's ``--set method=pcf``) was dropped without a word and every listed method
    rendered."""
    if "method" in params:
        raise OptionError(
            f"shadowmap: 'method' = {params['method']!r} is not a shared property: name "
            "the methods with 'methods' (on the command line --methods; in a sweep grid "
            "its 'method' axis)")


def check_shared_params(specs: list[dict], params: dict) -> None:
    """A shared parameter that no chosen method uses is an error (typo guard), and so
    is a shared ``method`` (:func:`check_no_shared_method`)."""
    check_no_shared_method(params)
    for k in params:
        if k in RENDER_KEYS:
            continue
        validate_property(k, params[k])
        if not any(k in s for s in specs):
            raise OptionError(
                f"shadowmap: property '{k}' is not used by any of the methods "
                f"{', '.join(s['method'] for s in specs)} (it is used by: "
                f"{', '.join(users_of(k)) or 'no method'})")


def to_mitsuba(props: dict) -> dict:
    """Property values Mitsuba's dict loader accepts ('pair' values as "a, b" strings).

    A value of None (a Python caller's "automatic", see
    :func:`~mi_shadowmap.options.parse_options`) is left out: Mitsuba 3.9's
    ``load_dict`` crashes the interpreter on a None value (segmentation fault, its
    own ``direct`` integrator too)."""
    return {k: (", ".join(repr(float(x)) for x in v) if isinstance(v, (tuple, list)) else v)
            for k, v in props.items() if v is not None}
