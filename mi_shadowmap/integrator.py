"""The ``shadowmap`` integrator: direct illumination with depth-map shadows.

``render()`` builds one :class:`~mi_shadowmap.depth_maps.ShadowMap` per
emitter (first pass), guarded against Mitsuba's re-entrant call of a Python
``render()`` override; ``sample()`` shades camera hits (second pass).
Shading is identical for every method -- only the visibility factor differs.

Maps are cached across renders (:class:`MapCache`, shared by every
integrator instance): a render whose scene geometry and emitters are
unchanged reuses them, whatever the camera or the method's filter
parameters.
"""
from __future__ import annotations

import contextlib
import math
import operator
import warnings
import weakref

import drjit as dr
import numpy as np
import mitsuba as mi

from . import environment as env_mod
from . import options as opt_mod
from .control_flow import if_stmt
from .depth_maps import (ShadowMap, _grouped_shapes, directed_edges, lights_outside,
                         solid_face_tables)
from .filters import Lookup, RayTracedLight, shifted_grid_point
from .sigint import outside_mitsuba, set_sigint_action, sigint_action
from .light_views import (aims_by_film, check_emitter_values, emitted_value_keys,
                          emitted_value_owners, emitter_class, emitter_kind,
                          emitter_labels, is_pinhole, UnsupportedEmitterError,
                          make_light_view, pinhole_footprint, pixel_steps,
                          unique_labels)  # noqa: F401  (re-exported)
from .light_views.base import scene_bounds
from .methods import MethodError, whole_light_values
from .packets import in_lit_packets, runs_in_lit_packets
from .rays import occlusion, surface_point
from .variants import (SUPPORTED_VARIANTS, bsdf_eval_reaches, bsdf_to_world, check_variant,
                       tilts_shading_frame, unpolarized, variant_class)
from .virtual import VirtualShadowMap, camera_frame, camera_state
from .map_manager import (MAP_CACHE, MapCache, MapStats, ParamWatch,  # noqa: F401  (re-exported)
                          differentiated, prepare_maps, scene_lease, scene_token)


class ShadowMapIntegratorMixin:
    """The variant-independent implementation of ``shadowmap``; see
    :func:`integrator_class` for the per-variant ``mi.SamplingIntegrator`` subclass."""

    __doc__ = r"""
Shadow-map direct illumination (``shadowmap``)
----------------------------------------------

Direct illumination from every emitter of the scene (emitter sampling:
one light sample per emitter per camera sample, or ``shadow_rays`` for
``raytraced``), where visibility comes from a depth map built with Dr.Jit
ray queries from each light (first pass) and looked up with the chosen
``method`` (second pass). ``method='raytraced'`` traces real shadow rays and
is the ground truth; it matches Mitsuba's ``direct`` integrator (for scenes
without delta BSDF lobes sample for sample with ``emitter_samples=1,
bsdf_samples=0``; but see ``blendbsdf`` below; an area light or environment with
``sampling_weight`` 0 is lit as by ``direct``'s defaults, whose BSDF samples reach it,
while ``direct`` with ``bsdf_samples=0`` never lights it).

Light seen through a delta lobe -- an area light or the environment in a
mirror (``conductor``), through glass (``dielectric``, ``thindielectric``), in
a smooth ``plastic``'s coating, or through a ``mask`` -- cannot be reached by
light sampling; as in ``direct`` (whose BSDF samples give it, with weight 1), one
BSDF sample restricted to the delta lobes and one traced ray add it, for every
method alike (that ray's visibility is its own, not a shadow map's). Scenes
without such a BSDF pay nothing for it. (Mitsuba's ``blendbsdf`` mixing a delta
lobe with a non-delta one weights its delta samples by the mixture's density in
``direct`` and ``path``: 0.77x of the blend's share on a diffuse/conductor blend;
this term uses the delta lobes alone and gives the share.)

One visibility AOV per emitter, ``vis_<id>`` (an area emitter without an id of
its own, or sharing it, takes its shape's id where unique; the rest ``vis_<index>``:
:func:`~mi_shadowmap.light_views.emitter_labels`), carries the visibility used for it (0 where it
contributes nothing; a method whose record has ``whole_light``, e.g.
``multiview``, reports its visibility of the whole light, horizon included).

Nested in Mitsuba's ``aov`` integrator (``{'type': 'aov', 'aovs': 'dd:depth',
'inner': {'type': 'shadowmap', ...}}``) it renders the same image, visibility AOVs
included, beside ``aov``'s channels (see :meth:`_prepare_nested`).

Maps: spot -- perspective covering the cutoff cone (cube faces from a
``cutoff_angle`` of 80 degrees); point, projector and area -- cube
maps (area lights as their centre); directional -- orthographic, fitted to
the scene bounds seen along the light. See :mod:`mi_shadowmap.light_views`.
By default (``virtual`` left out) the methods that read virtual maps (``hard``,
``pcf``, ``bilinear``, ``pcss``, ``second_depth``, ``mdsm``, ``vsm``, ``evsm``,
``msm``) build only the pages that
camera-visible points read, at the density their pixel footprint needs
(:mod:`mi_shadowmap.virtual`); ``resolution``, ``cascades``, ``fit_frusta``,
``cull_faces``, ``antialias='always'`` or ``virtual=false`` select full maps, and so
does a scene whose shape or emitter parameters have gradients enabled
(``virtual=true`` with ``cascades``: one virtual face per cascade).

Gradients (``mi.render(scene, params)`` with a shape's or an emitter's parameter
enabled): the maps are built in the AD graph, antialiased at silhouettes, and with
``gradient_at='pixel_centre'`` (default) each light's term (environment regions
excepted) keeps its value while its visibility derivative is taken at the surface point
under the pixel's centre (a perspective camera; other sensors at the sample), times
the unshadowed light averaged over ``gradient_light_samples`` stratified light
samples (:meth:`_gradient_light_term`). Shadows only: an object's own outline on
screen is Mitsuba's projective integrators' job.

""" + opt_mod.docs_table()

    def __init__(self, props=None):
        props = mi.Properties() if props is None else props
        self._mi_base.__init__(self, props)
        self.opts = opt_mod.parse_options(props)
        self.maps: list[ShadowMap] = []
        self.views = []
        self.build_seconds = 0.0
        self.resolution = None      # the resolution of the last render's maps
        self.stats = MapStats()     # see map_manager.prepare_maps()
        self._in_render = False
        self._sigint_before = None  # the SIGINT action before the render (sigint.py)
        self._sigint_after = None   # and the one the binding's scopes restore (render())
        self._nested = False        # sample() is called by another integrator (aov)
        # the render's lookups know their film pixel (Lookup.pixel: _first_pass sets it)
        self._pixels = False
        self._pixel_lane = None     # that pixel, while sample() is traced
        # while sample() is traced: the lookups run only in packets with a lit lane
        # (mi_shadowmap.packets: a built-in or lit_packets method, no gradients tracked)
        self._lit_packets = False
        self._names_given: list[str] = []   # aov_names() given outside a render
        # whether the image gets the visibility AOVs: never with visibility_aovs=false,
        # nor while rendering to a special film (specfilm, see _film_takes_aovs)
        self._writes_aovs = self.opts.visibility_aovs
        # a user method's render: a one-element counter of lookups outside [0, 1] or NaN
        self._out_of_range = None
        # scene_token() of the scene of the render in progress or just done (the memos
        # below keep tokens too: a scene holds its own integrator, see scene_token)
        self._last_render = None
        self._emitter_labels: list[str] = []
        self._unshadowed: list[bool] = []   # per emitter: environment='unshadowed' applies
        self._views_memo = None     # (scene_token, scene state, views, labels, unshadowed)
        self._centre_memo = {}      # _warn_if_centre_hidden's checks done
        # {scene_lease: [watches, token checked, values held]}, one scene's: weak, so
        # the getters (whose nodes may be an emitter: an envmap's data) go with the
        # scene (see _check_emitter_values)
        self._value_watch = weakref.WeakKeyDictionary()
        # An opaque JIT scalar, not a Python float: a new spp must not recompile sample().
        self._diff_scale, self._diff_spp = dr.opaque(mi.Float, 1.0), 1
        self._sensor = None
        self._pixel_step = None       # a sensor without ray differentials (render() sets it)
        self._pixel_step_memo = None
        # a perspective camera's light_views.pinhole_frame (opaque; render() sets it)
        self._pinhole = None
        self._delta_term = False
        self._delta_memo = None    # the scene has delta BSDF lobes (render() sets it)
        # (scene_token, tilted_frame_table(scene)); render() sets it
        self._tilted_memo = None
        self._tilted_table = None
        # second_depth: depth_maps.solid_face_tables of the scene (render() sets it)
        self._solid_faces = None
        # and per map (by id) the parts of transmitting solids its light is outside of
        self._light_outside = {}

    # ---------------------------------------------------------------- passes
    def render(self, scene, sensor=0, seed=0, spp=0, develop=True, evaluate=True):
        if self._in_render:   # Mitsuba re-enters a Python render() override
            # Its binding installs a Ctrl-C handler for the render and keeps the one it
            # replaces in a single static: this nested scope recorded the outer scope's
            # handler as the one to restore, so Mitsuba's stayed installed after every
            # render, bound to this integrator: a later Ctrl-C called cancel() on a freed
            # integrator ("free(): invalid pointer", a segfault) or was swallowed, and
            # no KeyboardInterrupt ever reached the caller. The nested scope gets the
            # handler from before the render instead (Python's, where that was Mitsuba's
            # own: see sigint.outside_mitsuba).
            set_sigint_action(self._sigint_after)
            return self._mi_base.render(self, scene, sensor, seed, spp, develop, evaluate)
        self._sigint_before = sigint_action()
        # what the binding's scopes are to restore: its static holds the action current
        # when a scope begins (see sigint.outside_mitsuba)
        self._sigint_after = outside_mitsuba(self._sigint_before)
        self._in_render = True
        self._nested = False
        self._last_render = None
        try:
            sensor_obj = _sensor_object(scene, sensor)
            # (visibility_aovs=false: no specfilm warning about AOVs nobody asked for)
            self._writes_aovs = (self.opts.visibility_aovs
                                 and _film_takes_aovs(sensor_obj.film()))
            self._check_hit_precision(scene, sensor_obj)
            self._first_pass(scene, sensor_obj,
                             spp if spp > 0 else sensor_obj.sampler().sample_count())
            self._last_render = scene_token(scene)
            record = self.opts.record
            self._out_of_range = None if record.builtin else dr.zeros(mi.UInt32, 1)
            set_sigint_action(self._sigint_after)    # the binding's scope keeps it
            image = self._mi_base.render(self, scene, sensor, seed, spp, develop, evaluate)
            if self._out_of_range is not None:
                bad = int(self._out_of_range.numpy()[0])     # evaluates the render
                if bad:
                    raise MethodError(
                        f"shadowmap: method '{record.name}' returned {bad} visibility "
                        "value(s) outside [0, 1] or NaN in this render; a lookup must "
                        "return the lit fraction, in [0, 1]")
            return image
        finally:
            self._in_render = False
            self._out_of_range = None
            set_sigint_action(self._sigint_before)   # as it was, whatever happened
            self._sigint_before = self._sigint_after = None

    @staticmethod
    def _check_hit_precision(scene, sensor) -> None:
        """:func:`warn_if_hits_imprecise` once per scene and sensor, whatever the
        integrator (its probe is a kernel launch of its own: a camera path, or a fresh
        integrator a frame, launches no more kernels than before after the first
        frame). A camera moved later is not probed again. The last
        :data:`PRECISION_SENSORS` sensors of a scene are remembered (held, so that an
        ``is`` test names them: a render loop that makes a sensor a frame would
        otherwise keep every sensor and its film alive); an older one is probed again."""
        seen = _PRECISION_CHECKED.setdefault(scene_lease(scene), [])
        if any(s is sensor for s in seen):
            return
        seen.append(sensor)      # held: Mitsuba then hands out this same object
        del seen[:-PRECISION_SENSORS]
        warn_if_hits_imprecise(scene, sensor)

    #: Methods whose lookups keep no differentiable state in a ``dr.while_loop`` but sums
    #: (``pcf``'s, ``bilinear``'s and ``pcss``'s taps, ``max_iterations=-1``; ``pcss``
    #: with ``soft_compare``, 128^2, 16 spp: 0.25 s a gradient against 0.75 s through
    #: Mitsuba's default, gradients unchanged): their gradient renders
    #: run with symbolic loops (:meth:`render_backward`). Others use Mitsuba's default,
    #: whose evaluated loops store every iteration.
    SYMBOLIC_BACKWARD = frozenset({"hard", "pcf", "bilinear", "pcss", "vsm", "evsm", "msm",
                                   "unshadowed"})

    def _symbolic_backward(self, scene) -> bool:
        return (self.opts.record.name in self.SYMBOLIC_BACKWARD
                and not any(e.is_environment() for e in scene.emitters()))

    def render_backward(self, scene, params, grad_in, sensor=0, seed=0, spp=0):
        """Reverse mode (``dr.backward`` after ``mi.render(scene, params, ...)``): the
        render again with gradients tracked (maps in the AD graph when a shape or
        emitter needs them), then ``grad_in`` propagated back. For the methods of
        :data:`SYMBOLIC_BACKWARD` in one pass of symbolic loops (measured: ``pcf`` with
        ``soft_compare``, 128^2, 16 spp, 0.36 s a gradient against 1.3 s through
        Mitsuba's default); the others go through Mitsuba's default."""
        self._check_gradient_channels(scene, sensor, grad_in)
        self._warn_if_no_shadow_gradient(scene)
        if not self._symbolic_backward(scene):
            return self._mi_base.render_backward(self, scene, params, grad_in, sensor, seed,
                                                 spp)
        with dr.resume_grad():
            image = self.render(scene, sensor, seed, spp, develop=True, evaluate=False)
            dr.set_grad(image, grad_in)
            dr.enqueue(dr.ADMode.Backward, image)
            dr.traverse(dr.ADMode.Backward)
        dr.eval()

    #: Methods whose visibility is a step of the map's depths at the nearest texels
    #: (README, "Differentiable shadows"): no shadow gradient at all (``multiview`` with
    #: ``filter='hard'``); ``pcf`` and ``pcss`` only with ``soft_compare`` > 0.
    #: (``bilinear`` without ``soft_compare`` still passes its weights' derivative in
    #: the receiver's and the light's position, so it is not warned about.)
    STEP_METHODS = frozenset({"hard", "second_depth", "mdsm", "multiview"})
    SOFT_COMPARE_METHODS = frozenset({"pcf", "pcss"})

    def _warn_if_no_shadow_gradient(self, scene) -> None:
        """Warn (once per integrator) when a gradient render differentiates a shape's or
        an emitter's parameter (its maps are built in the AD graph) with a method whose
        visibility passes no gradient: the shadows' part of the gradient is silently 0
        (measured: an occluder moved sideways under a spot, ``hard`` and ``pcf`` without
        ``soft_compare`` gave exactly the ``raytraced`` integrator's image gradient,
        none of the shadow's motion, without a word)."""
        if getattr(self, "_no_gradient_warned", False):
            return
        name = self.opts.record.name
        step = (name in self.STEP_METHODS
                and not (name == "multiview" and self.opts.filter != "hard")) or (
            name in self.SOFT_COMPARE_METHODS and not self.opts.soft_compare > 0)
        if not step or not differentiated(scene):
            return
        self._no_gradient_warned = True
        fix = ("set soft_compare > 0 (e.g. 2)" if name in self.SOFT_COMPARE_METHODS
               else "use vsm, evsm, msm, or pcf, pcss or bilinear with soft_compare > 0")
        warnings.warn(
            f"shadowmap: method '{name}'"
            + (" with soft_compare=0" if name in self.SOFT_COMPARE_METHODS else "")
            + " passes no shadow gradient: a shape's or an emitter's parameter has "
            "gradients enabled, but the shadows' part of its gradient is 0 (only the "
            f"shading's derivative remains); {fix}", RuntimeWarning, stacklevel=3)

    def _check_gradient_channels(self, scene, sensor, grad_in) -> None:
        """Refuse, with a message, an image gradient whose channels are not our image's.
        Mitsuba's ``aov`` splits the gradient of its image among its children by the
        channel count their ``aov_names()`` give then; built before this integrator had
        rendered the scene it was given none, so it cut our image's gradient short (RGB
        without the visibility AOVs) and shifted its own channels' gradients by as many;
        Dr.Jit then failed with "attempted to store a gradient of size 3072 into AD
        variable ..., which has size 4096" (or "incompatible tensor shapes")."""
        shape = tuple(getattr(grad_in, "shape", ()))
        if len(shape) != 3:
            return
        sensor_obj = _sensor_object(scene, sensor)
        film = sensor_obj.film()
        aovs = (len(scene.emitters())
                if self.opts.visibility_aovs and _film_takes_aovs(film) else 0)
        expected = film.base_channels_count() + aovs
        if shape[2] != expected:
            raise ValueError(
                f"shadowmap: the image gradient given to render_backward() has {shape[2]} "
                f"channels, this integrator's image {expected} ({aovs} visibility AOV(s)). "
                "Nested in Mitsuba's 'aov' integrator, that integrator splits the gradient "
                "by the AOV names this one gave when it was built (none before it had "
                "rendered a scene): render the scene once with the shadowmap integrator, "
                "then build the 'aov' integrator around it (in Python), give this one "
                "visibility_aovs=false (no AOV channels to split), or differentiate "
                "the shadowmap integrator alone")

    def render_forward(self, scene, params, sensor=0, seed=0, spp=0):
        """Forward mode (``dr.forward``): the derivative image, as :meth:`render_backward`
        (the methods outside :data:`SYMBOLIC_BACKWARD` with evaluated loops, as Mitsuba's
        default ``render_forward``).

        The maps built in the AD graph are targets of the traversal too: a method whose
        visibility reads them only through steps (``hard``, ``pcf`` without
        ``soft_compare``, ``second_depth``, ...) leaves them outside the image's graph,
        and Dr.Jit refuses to push derivatives from a scene parameter into variables of
        ``mi.render``'s ``dr.isolate_grad()`` scope that the image does not read (it
        raised "tried to forward-propagate derivatives across edge ... outside of the
        current dr.isolate_grad() scope"). Their derivatives are computed and dropped:
        about one more map build's work."""
        self._warn_if_no_shadow_gradient(scene)
        loops = (contextlib.nullcontext() if self._symbolic_backward(scene)
                 else dr.scoped_set_flag(dr.JitFlag.SymbolicLoops, False))
        with dr.resume_grad(), loops:
            image = self.render(scene, sensor, seed, spp, develop=True, evaluate=False)
            extra = _attached_arrays((self.maps, self.views)) if dr.grad_enabled(image) else []
            if extra:
                dr.forward_to(image, *extra, flags=dr.ADFlag.Default | dr.ADFlag.AllowNoGrad)
            else:
                dr.forward_to(image)
            return dr.grad(image)

    def prepare_maps(self, scene: mi.Scene, sensor=None, camera=None) -> list[ShadowMap]:
        """First pass: one depth map per emitter (None for ``raytraced``).

        Delegates to :func:`mi_shadowmap.map_manager.prepare_maps` (resolution,
        memory budget, cascades, fitting, culling, cache); sets ``views``,
        ``maps``, ``resolution``, ``stats`` and ``build_seconds``. ``camera``:
        ``sensor``'s :func:`~mi_shadowmap.virtual.camera_state` read in this render
        (default: read where needed).
        """
        views = self._light_views(scene)   # the light views, built once per render
        self.maps = [None] * len(scene.emitters())   # no stale maps if preparing fails
        prepared = prepare_maps(scene, sensor, self.opts, views, pixels=self._pixels,
                                camera=camera)
        self.views, self.maps = prepared.views, prepared.maps
        self.resolution, self.stats = prepared.resolution, prepared.stats
        self.build_seconds = prepared.stats.build_seconds
        return self.maps

    def _light_views(self, scene) -> list:
        """:meth:`check_scene`'s views, kept while the scene's state (the map cache's
        key: every shape and emitter parameter, which is all a light view reads) is
        unchanged, so a re-render builds none (about 0.2 ms a frame). Without map caching
        they are built every render."""
        opts = self.opts
        state = MAP_CACHE.scene_state(scene) if opts.uses_map and opts.cache_maps else None
        memo = self._views_memo
        if (state is not None and memo is not None and memo[0] is scene_token(scene)
                and memo[1] == state):
            self._check_emitter_values(scene)
            self._emitter_labels, self._unshadowed = list(memo[3]), list(memo[4])
            return list(memo[2])
        views = self.check_scene(scene)
        self._views_memo = (None if state is None else
                            (scene_token(scene), state, list(views), list(self._emitter_labels),
                             list(self._unshadowed)))
        return views

    def check_scene(self, scene):
        """Raise ValueError naming any emitter this integrator cannot handle.

        Called by ``render()``; call it yourself before ``mi.render`` to get the
        error unwrapped (``mi.render`` re-raises errors of a Python
        integrator as a RuntimeError whose ``__cause__`` holds the message).

        Returns the emitters' :class:`~mi_shadowmap.light_views.LightView`
        (None for environment emitters), which ``prepare_maps`` reuses, so
        views are built once per render.
        """
        views, unshadowed = [], []
        self._check_emitter_values(scene)
        labels = emitter_labels(scene.emitters())
        for i, e in enumerate(scene.emitters()):
            is_env = emitter_kind(e) == "environment"
            if is_env and self.opts.environment == "error":
                raise ValueError(
                    f"shadowmap: emitter '{labels[i]}' is an environment/constant "
                    "emitter and environment='error'; set the property "
                    "environment='shadowed' (median-cut maps) or 'unshadowed' (no shadows), "
                    "or remove it")
            # raises for unsupported emitters; environment='shadowed' with a map method:
            # K median-cut regions in one map (mi_shadowmap.environment)
            views.append(env_mod.light_view(e, scene, i, self.opts, labels[i]) if is_env
                         else make_light_view(e, scene, i, labels[i]))
            # environment='unshadowed': visibility 1, every method
            unshadowed.append(is_env and self.opts.environment == "unshadowed")
        if self.opts.uses_map and not self.opts.record.whole_light:
            for view in views:
                _warn_if_enclosing(scene, view, self.opts.method)
                _warn_if_centre_hidden(scene, view, self.opts.method, self._centre_memo)
        self._emitter_labels = labels
        self._unshadowed = unshadowed
        return views

    def _check_emitter_values(self, scene) -> None:
        """:func:`~mi_shadowmap.light_views.check_emitter_values` of every emitter, when
        a value changed since the last check: each render reads the values' JIT variable
        indices (:class:`~mi_shadowmap.map_manager.ParamWatch`, its values held), and
        checks them on the host when they differ.
        Emitted values are not part of the map cache's scene state (maps do not depend
        on them), so a ``params.update()`` of an intensity alone reaches only this.

        The memo holds no emitter, no ``mi.traverse`` of one (but an envmap's getters,
        whose node is the emitter), and lives while the scene does in the package's table
        of scenes (``map_manager.scene_lease``; ``clear_caches()`` empties it): it held
        the last scene's emitters past ``clear_caches()`` and ``del scene``, and an area
        emitter outliving its shape crashed Mitsuba's later kernels, which dispatch over
        every live emitter (``direct`` on the next scene: a segmentation fault)."""
        for i, e in enumerate(scene.emitters()):
            # Mitsuba refuses a NaN or negative weight at load, not an infinite one: its
            # `direct` then rendered the whole image black (every light), this one lit it
            w = float(e.sampling_weight())
            if not (math.isfinite(w) and w >= 0.0):
                raise UnsupportedEmitterError(
                    f"shadowmap: emitter '{emitter_labels(scene.emitters())[i]}' "
                    f"({emitter_class(e)}): parameter 'sampling_weight' is {w:g}; it "
                    "must be finite and >= 0")
        key = scene_lease(scene)
        memo = self._value_watch.get(key)
        if memo is None:
            watches = []
            labels = emitter_labels(scene.emitters())
            for i, e in enumerate(scene.emitters()):
                params = mi.traverse(e)
                watch = ParamWatch(params, emitted_value_keys(params))
                watch.params = None          # the getters only: not the emitter
                watches.append((emitter_class(e), labels[i], watch,
                                emitted_value_owners(params)))
            memo = [watches, None, None]
            self._value_watch.clear()        # the scene being rendered's only
            self._value_watch[key] = memo
        reads = [watch.read() for _, _, watch, _ in memo[0]]
        token = tuple(r[0] for r in reads)
        if token == memo[1]:
            return
        for (cls, label, watch, owners), (_, values) in zip(memo[0], reads):
            check_emitter_values(cls, label, dict(zip(watch.names, values)), owners)
        memo[1] = token
        memo[2] = [watch.held(values) for (_, _, watch, _), (_, values) in zip(memo[0], reads)]

    def aov_names(self):
        """``vis_<emitter>`` per emitter of the last scene rendered (none before one;
        none with ``visibility_aovs=false``, nor in a render to a film that cannot take
        them, see :func:`_film_takes_aovs`).
        Outside a render the list given is remembered: an integrator nesting this one
        (Mitsuba's ``aov``) sizes its channels by it when it is built, so while nested
        ``sample()`` returns values for exactly those names (:meth:`sample`)."""
        if self._nested:
            return list(self._names_given)
        # none with visibility_aovs=false, or for a render (or after one) to a film that
        # cannot take them; remembered like any list given, so that an integrator nesting
        # this one sizes its channels by what sample() will return
        names = self._names() if self._writes_aovs else []
        if not self._in_render:
            self._names_given = list(names)
        return names

    def _names(self):
        return [f"vis_{lab}" for lab in self._emitter_labels]

    def _prepare_nested(self, scene, sampler, ray=None):
        """``sample()`` called by another integrator's render: Mitsuba's ``aov`` (or
        ``moment``) integrator nesting this one. Mitsuba 3.9's ``aov`` renders its child
        with the child's ``render()`` (our image, visibility AOVs included) and then
        calls the child's ``sample()`` again in its own render, for its own channels;
        other integrators may call ``sample()`` alone. The first pass runs here: for
        the sensor of our render of this scene that just ran (its maps come from the
        cache), else for the sensor being rendered (:func:`_nested_sensor`: the one whose
        film's pixel count fits the render's wavefront, and if several do, whose ray
        through its first pixel is nearest the render's first ray); footprints take the
        spp from the render's sampler. Its lookups know their film pixel as a plain
        render's do (the pinhole projection of their hit, :meth:`_film_pixel`) where the
        sensor is known: the one our render just used, or one whose film fits the
        wavefront; the maps then carry the same per-pixel words, and a nested render
        reads the levels a plain one reads (``aov``'s colour is the plain image's)."""
        rendered = self._last_render is scene_token(scene)     # aov: our render() just ran
        if rendered and self._sensor is not None:
            sensor, known = self._sensor, True
        else:
            sensor = _nested_sensor(scene, sampler, ray)
            known = sensor is not None and _film_fits(sensor, sampler)
        self._first_pass(scene, sensor, max(sampler.sample_count(), 1), known)
        # (visibility_aovs=false: none are asked for, none missing)
        missing = ([n for n in self._names() if n not in self._names_given]
                   if self.opts.visibility_aovs else [])
        # after our own render() of this scene (Mitsuba's aov merges that image, whose
        # visibility AOVs are all there) nothing is missing; stokes only calls sample()
        if missing and not rendered:
            warnings.warn(
                f"shadowmap: nested in another integrator (Mitsuba's aov, stokes, ...), "
                f"whose channels were sized when it was built, with this integrator's AOV "
                f"names then "
                f"({', '.join(self._names_given) or 'none: it had not rendered a scene'}): "
                f"{', '.join(missing)} are left out of its image. Render the scene once "
                "with this integrator before building the nesting one to get them (not "
                "needed under Mitsuba's aov, which adds this integrator's own render)",
                RuntimeWarning, stacklevel=2)

    def _first_pass(self, scene, sensor, spp: int, nested_pixels: bool = False):
        """What ``sample()`` reads of a render, set before it is traced: the maps for
        ``sensor``, whether the delta-lobe term applies, the footprints' scale (Mitsuba
        scales ray differentials by 1/sqrt(spp); footprints use whole pixels; an opaque
        value, so a new spp compiles nothing) and a sensor's pixel step without ray
        differentials; a perspective camera's pinhole and pixel steps, from which its
        footprints are taken (:func:`~mi_shadowmap.light_views.pinhole_footprint`).
        Whether its lookups know their film pixel (``Lookup.pixel``: this integrator's own
        render through a ``perspective`` camera, or a nested ``sample()`` whose sensor is
        known, ``nested_pixels``, see :meth:`_prepare_nested`) is set first: virtual maps'
        marks decide the receiver biases' level per pixel then
        (:meth:`~mi_shadowmap.virtual.VirtualShadowMap.keeps`)."""
        own = self._in_render and not self._nested
        self._pixels = ((own or (self._nested and nested_pixels)) and sensor is not None
                        and is_pinhole(sensor))
        # the camera's state, read once a render: the page planner's (are its marks
        # stale?) and the pinhole frame's below (each read of every camera parameter is
        # about 0.1 ms of a moved frame)
        cam = camera_state(sensor) if sensor is not None else None
        self.prepare_maps(scene, sensor, camera=cam)
        self._sensor = sensor
        self._delta_term = self._scene_has_delta(scene)
        memo = self._tilted_memo
        if memo is None or memo[0] is not scene_token(scene):
            memo = self._tilted_memo = (scene_token(scene), tilted_frame_table(scene))
        self._tilted_table = memo[1]
        # every map method (_into_solid): a pass over the faces of every mesh with vertex
        # normals or a BSDF that transmits, on the first render of its geometry (0.55 s
        # for a 330k-triangle sphere, 1.3 s for 2M triangles; again after every edit of
        # its vertices); None, and no per-hit test, where every such face is flat-shaded
        # (cubes, rectangles); second_depth's builds have it already
        reads_second = (self.opts.uses_map
                        and "second_depth" in self.opts.record.layer_names(self.opts))
        # (second_depth: the faces of closed twosided meshes too, a room seen from inside)
        self._solid_faces = (solid_face_tables(scene, two_sided=reads_second)
                             if self.opts.uses_map else None)
        # per map (by id): which closed parts of the solid meshes its light is outside of
        # (every render: lights move); only where the scene has such parts
        self._light_outside = {}
        if self._solid_faces is not None and self._solid_faces[2] is not None:
            for k, emitter in enumerate(scene.emitters()):
                smap = self.maps[k] if k < len(self.maps) else None
                if smap is not None:
                    # the view's position is a delta light's (not a posed map's: its view
                    # is the pose's reference)
                    view = None if getattr(smap, "pose", None) is not None else smap.view
                    out = lights_outside(self._solid_faces[3], emitter, scene, view)
                    # padded: a one-entry array would be a literal compiled into the kernel
                    self._light_outside[id(self.maps[k])] = mi.Bool(np.append(out, False))
        if reads_second:    # the lookup's neighbouring faces (second_depth's virtual samples)
            directed_edges(scene)
        self._diff_scale, self._diff_spp = dr.opaque(mi.Float, math.sqrt(spp)), spp
        self._pixel_step = self._sensor_pixel_step(sensor)
        self._pinhole = camera_frame(sensor, cam)   # shared with the mark pass

    def _scene_has_delta(self, scene) -> bool:
        """:func:`has_delta_bsdf`, kept per scene (a scene's shapes and their BSDFs'
        types are fixed once it is loaded; 3,000 shapes take 8 ms to scan)."""
        memo = self._delta_memo
        if memo is None or memo[0] is not scene_token(scene):
            memo = self._delta_memo = (scene_token(scene), has_delta_bsdf(scene))
        return memo[1]

    def _sensor_pixel_step(self, sensor):
        """None for a sensor whose rays carry ray differentials or that does not aim its
        pixels' rays by film position (:func:`~mi_shadowmap.light_views.aims_by_film`:
        its pixel has no footprint, read as zero); else :class:`_PixelSteps`, the
        per-pixel ``(angle, offset)`` of :func:`~mi_shadowmap.light_views.pixel_steps`
        (a ``batch`` sensor: :meth:`_footprint` then takes a cone of its pixel's angle
        around each ray)."""
        if sensor is None or not (self.opts.record.needs_footprint or self.opts.uses_map):
            return None
        if not aims_by_film(sensor):     # irradiancemeter, distant: no pixel footprint
            return None
        memo = self._pixel_step_memo     # (sensor, its rays have differentials)
        if memo is None or memo[0] is not sensor:
            ray, _ = sensor.sample_ray_differential(0.0, 0.5, mi.Point2f(0.5), mi.Point2f(0.5))
            memo = self._pixel_step_memo = (sensor, bool(ray.has_differentials))
        if memo[1]:
            return None
        return _PixelSteps(sensor)       # every render: its cameras may have moved

    def sample(self, scene, sampler, ray, medium=None, active=True):
        if not self._in_render:
            # Nested: the parent reserved one channel per name aov_names() gave it when
            # it was built (before any scene: none) and advances by aov_names() now.
            self._nested = True
            self._prepare_nested(scene, sampler, ray)
            result, valid, aovs = self._sample(scene, sampler, ray, medium, active)
            mine = dict(zip(self._names(), aovs))
            return result, valid, [mine.get(n, mi.Float(0.0)) for n in self._names_given]
        # Mitsuba scales ray differentials by 1/sqrt of the count its sampler renders,
        # which the sampler may have rounded: a stratified sampler renders spp=3 as 4 (the
        # requested 3 made the footprints of non-pinhole cameras 0.87 of a pixel)
        spp = max(sampler.sample_count(), 1)
        if spp != self._diff_spp:
            self._diff_scale, self._diff_spp = dr.opaque(mi.Float, math.sqrt(spp)), spp
        return self._sample(scene, sampler, ray, medium, active)

    def _sample(self, scene, sampler, ray, medium=None, active=True):
        opts = self.opts
        if not isinstance(ray, mi.RayDifferential3f):   # copying drops the differentials
            ray = mi.RayDifferential3f(ray)
        flags = mi.RayFlags.All
        if opts.record.needs_curvature:
            flags = flags | mi.RayFlags.dNSdUV
        si = scene.ray_intersect(ray, flags, False, active)
        valid = active & si.is_valid()
        result = mi.Spectrum(0.0)
        if not opts.hide_emitters:
            result += si.emitter(scene, active).eval(si, active)
        bsdf = si.bsdf(ray)
        ctx = mi.BSDFContext()
        shade = valid & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth)
        record = opts.record
        gradient = self._gradient_render()   # gradient_at='pixel_centre' applies
        if record.needs_footprint or (opts.uses_map and opts.virtual) or gradient:
            dp_dx, dp_dy = self._footprint(ray, si, sampler)
        else:
            dp_dx = dp_dy = mi.Vector3f(0.0)
        p_centre = self._pixel_centre(si, dp_dx, dp_dy, valid) if gradient else None
        # the film pixel of each sample, for virtual maps' per-pixel level choice
        # (VirtualShadowMap.keeps): a perspective camera's, from the sample's point
        self._pixel_lane = (self._film_pixel(si, valid)
                            if self._pixels and opts.uses_map and opts.virtual
                            and any(isinstance(m, VirtualShadowMap)
                                    and m.keep is not None for m in self.maps)
                            else None)
        self._lit_packets = runs_in_lit_packets(record) and not _tracks_gradients(scene)
        aovs = []
        n_light = getattr(opts, record.shadow_rays) if record.shadow_rays else 1
        # A camera hit on a cylinder (or a non-mesh hit through an instance) found again
        # from near it (rays.surface_point, one ray_intersect where the scene has such
        # shapes): Mitsuba's float32 cylinder test puts a hit from afar ~u t^2 / r off
        # the surface. raytraced's shadow rays leave from it (computed once for every
        # emitter and light sample); the maps look it up (second_depth, with no slope
        # bias on a non-solid, shadowed the sunlit side of a post 1.7 wide 225 units
        # away: 24 % of the image off direct).
        p_surface = surface_point(si, scene)
        if opts.uses_map:
            si.p = p_surface
        # raytraced: the scene's shadow-ray query (rays.occlusion: its spheres, the maps'
        # copy for cylinders), prepared once for every emitter
        query = None if opts.uses_map else occlusion(scene)
        for k, emitter in enumerate(scene.emitters()):
            # a delta light with sampling_weight 0 is never sampled by Mitsuba's direct (nor
            # path), and no BSDF sample can hit it: it lights nothing; its visibility AOV is
            # still reported. An area light or an environment with weight 0 does light:
            # direct's and path's BSDF samples reach it (MIS then gives them the whole
            # weight), so it is shaded as any other (it rendered black: a rectangle light
            # 0 against direct's 0.0173)
            sampled = (emitter.sampling_weight() > 0
                       or not mi.has_flag(emitter.flags(), mi.EmitterFlags.Delta))
            if (opts.uses_map and k < len(self.maps)
                    and isinstance(getattr(self.maps[k], "view", None), env_mod.EnvironmentView)):
                # environment='shadowed': K median-cut regions, one while loop
                c, vis = env_mod.shade(self.maps[k], emitter, si, bsdf, shade, sampler,
                                       dp_dx, dp_dy, opts)
                result += c if sampled else 0.0
                aovs.append(dr.select(shade, vis, 0.0))
                continue
            if k < len(self._unshadowed) and self._unshadowed[k]:
                smap = None   # environment='unshadowed': no shadows for any method
            else:
                smap = (self.maps[k] if opts.uses_map
                        else RayTracedLight(scene, emitter, query, p_surface))
            vis_sum = mi.Float(0.0)
            contributes = mi.Bool(False)
            shift = None
            whole = None   # record.whole_light: the lookup's visibility of the whole light
            if p_centre is not None and smap is not None and n_light == 1:
                c, vis, whole = self._gradient_light_term(
                    smap, emitter, si, bsdf, ctx, shade, sampler, dp_dx, dp_dy, p_centre, k)
                result += c if sampled else 0.0
                aovs.append(vis if whole is None else dr.select(shade, whole, 0.0))
                continue
            if n_light > 1 and not record.whole_light:
                c, vis_sum, contributes = self._light_samples(
                    scene, smap, emitter, si, bsdf, ctx, shade, sampler, dp_dx, dp_dy,
                    n_light)
                result += c if sampled else 0.0
                aovs.append(dr.select(contributes, vis_sum / n_light, 0.0))
                continue
            for s in range(n_light):
                if n_light == 1:
                    u = sampler.next_2d(shade)
                else:
                    if s == 0:
                        shift = sampler.next_2d(shade)
                    u = shifted_grid_point(s, n_light, shift)
                ds, unshadowed, lit, counts = _light_sample(emitter, si, bsdf, ctx, u, shade)
                vis, whole = self._sample_visibility(smap, si, dp_dx, dp_dy, ds, sampler, lit,
                                                     shade, emitter, u)
                if sampled:
                    result += dr.select(lit, unshadowed * vis, 0.0) / n_light
                vis_sum += vis if counts is lit else dr.select(counts, vis, 0.0)
                contributes |= counts
            aovs.append(dr.select(contributes, vis_sum / n_light, 0.0) if whole is None
                        else dr.select(shade, whole, 0.0))
        if self._delta_term:
            result += _delta_lobe_term(scene, si, bsdf, sampler, valid)
        return result, valid, aovs if (self._writes_aovs or self._nested) else []

    def _sample_visibility(self, smap, si, dp_dx, dp_dy, ds, sampler, lit, shade, emitter,
                           u_light=None):
        """``(visibility, whole)`` of one light sample of ``emitter`` (see
        :meth:`_visibility`), drawn from the 2D sample ``u_light`` (``Lookup.u_light``);
        1 and None without a map (``smap`` None: an environment emitter lit without
        shadows)."""
        if smap is None:
            return mi.Float(1.0), None
        lk = self._lookup(smap, si, dp_dx, dp_dy, ds, sampler, emitter=emitter)
        lk.u_light = u_light
        return self._visibility(smap, lk, lit, shade)

    def _light_samples(self, scene, smap, emitter, si, bsdf, ctx, shade, sampler, dp_dx,
                       dp_dy, n: int):
        """``n`` > 1 stratified light samples of one emitter (``shadow_rays``, e.g.
        ``raytraced``'s): ``(contribution, sum of the visibilities, any sample lit)``.

        One ``dr.while_loop`` over the samples: an unrolled Python loop made a kernel ``n``
        times the size of one sample's, whose tracing and compilation dominated a
        reference render (``sky_sun`` at 64^2, 4 spp, 256 shadow rays: 48 s, about 11 us
        a shadow ray). The loop is symbolic (one small kernel for any ``n``) unless this
        render tracks gradients, where it runs evaluated (Dr.Jit differentiates evaluated
        loops in reverse mode). Same samples, same order of sums as the unrolled loop."""
        shift = sampler.next_2d(shade)

        def cond(k, result, vis_sum, contributes, sampler):
            return k < n

        def body(k, result, vis_sum, contributes, sampler):
            u = shifted_grid_point(k, n, shift)
            ds, unshadowed, lit, counts = _light_sample(emitter, si, bsdf, ctx, u, shade)
            vis, _ = self._sample_visibility(smap, si, dp_dx, dp_dy, ds, sampler, lit, shade,
                                             emitter, u)
            return (k + 1, result + dr.select(lit, unshadowed * vis, 0.0) / n,
                    vis_sum + (vis if counts is lit else dr.select(counts, vis, 0.0)),
                    contributes | counts, sampler)

        _, result, vis_sum, contributes, _ = dr.while_loop(
            (mi.UInt32(0), mi.Spectrum(0.0), mi.Float(0.0), mi.Bool(False), sampler), cond,
            body, labels=("k", "result", "vis_sum", "contributes", "sampler"),
            label="shadowmap light samples",
            mode="evaluated" if _tracks_gradients(scene) else None)
        return result, vis_sum, contributes

    def _gradient_light_term(self, smap, emitter, si, bsdf, ctx, shade, sampler, dp_dx, dp_dy,
                             centre, k):
        """One emitter's term in a gradient render with ``gradient_at='pixel_centre'``:
        ``(contribution, visibility AOV, whole-light visibility or None)``.

        The value is the usual one (one light sample ``L``, the visibility ``V`` at the
        sample's point). Its derivative is ``dL V + L_avg dV(p_centre)``: the shading's
        own derivative from the sample, and the visibility's derivative at the pixel
        centre's surface point (``centre = (p_centre, pixel)``, :meth:`_pixel_centre`;
        the lookup run again there, its random numbers :class:`_PixelSampler`'s: the
        same for every sample and seed of a pixel, independent between pixels and
        emitters ``k``) times the unshadowed contribution averaged over
        ``gradient_light_samples`` stratified light samples (the maps' visibility does
        not depend on the light sample). Both are unbiased to first order in the
        pixel's size; what they remove is the pixel position's and the light sample's
        noise in the visibility's derivative."""
        u = sampler.next_2d(shade)
        ds, unshadowed, lit, counts = _light_sample(emitter, si, bsdf, ctx, u, shade)
        p_centre, pixel = centre
        rec = _Recorder(sampler) if pixel is None else sampler
        with dr.suspend_grad():
            v_value, whole = self._visibility(
                smap, self._lookup(smap, si, dp_dx, dp_dy, ds, rec, emitter=emitter), lit,
                shade)
        centre_sampler = rec.replay() if pixel is None else _PixelSampler(sampler, pixel, k)
        v_centre, whole_centre = self._visibility(
            smap, self._lookup(smap, si, dp_dx, dp_dy, ds, centre_sampler, p_centre,
                               pixel is not None, emitter), shade,
            shade)
        delta = mi.has_flag(emitter.flags(), mi.EmitterFlags.Delta)
        n = 1 if delta else self.opts.gradient_light_samples
        with dr.suspend_grad():   # a weight: the shading's own derivative is the sample's
            average = dr.select(lit, unshadowed, 0.0)
            if n > 1:
                # the grid shifted by the sample's own u: no extra random number, so the
                # values of later emitters match the primal render's; one symbolic loop
                # (no derivatives here), whose kernel does not grow with n
                def body(k, average):
                    _, unshadowed_k, lit_k, _ = _light_sample(
                        emitter, si, bsdf, ctx, shifted_grid_point(k, n, u), shade)
                    return k + 1, average + dr.select(lit_k, unshadowed_k, 0.0)

                _, average = dr.while_loop((mi.UInt32(0), mi.Spectrum(0.0)),
                                           lambda k, average: k < n, body,
                                           labels=("k", "average"),
                                           label="shadowmap gradient light samples")
                average /= n
        value = dr.select(lit, unshadowed * v_value, 0.0)
        # d value = d(L) V + L_avg dV(p_centre)
        grad = dr.select(lit, unshadowed * dr.detach(v_value), 0.0) + average * v_centre
        aov = dr.replace_grad(v_value, v_centre)
        if counts is not lit:   # the AOV counts only samples the light's weight lights
            aov = dr.select(counts, aov, 0.0)
        if whole is not None:   # the whole-light AOV: its derivative at the centre too
            whole = dr.replace_grad(whole, whole_centre)
        return dr.replace_grad(value, grad), aov, whole

    def _visibility(self, smap, lk, lit, shade):
        """``(visibility, whole-light visibility or None)`` of one light sample at
        ``lk`` (0 where not ``lit``); a ``whole_light`` record's lookup sees the whole
        light, horizon included."""
        vis_fn, opts = self.opts.record.lookup, self.opts
        if self._tilted_table is not None and lk.tilted is None:
            lk.tilted = tilted_frame(self._tilted_table, lk.si)
        if lk.solid_back is None and self._solid_faces is not None:
            outside = self._light_outside.get(id(smap))
            if self.opts.record.whole_light or lk.si is None or lk.ds is None:
                lk.solid_back = self._solid_back(lk.si, outside)
            else:
                # read by _into_solid alone, where the light sample is behind the
                # geometric face: computed there only (its tables' gathers, the BSDF's
                # flags), in a conditional that packets of front-lit samples skip. The
                # same values wherever they are read; the 1M-triangle mesh's render
                # -31 ms of CPU a frame, paired (benchmarks/RESULTS.md, forty-ninth
                # session, helper E)
                si = lk.si
                behind = dr.dot(dr.detach(si.n), dr.detach(lk.ds.d)) < 0
                lk.solid_back = if_stmt((), behind,
                                        lambda: mi.Bool(self._solid_back(si, outside)),
                                        lambda: mi.Bool(False), label="solid back")
        if lk.pixel is None:
            lk.pixel = self._pixel_lane
        if self.opts.record.whole_light:
            # its fraction counts the light points behind a solid's face as occluded
            # (Lookup.solid_back), and weights the light sample, wherever it lies
            # (every packet: in a conditional on the shaded lanes, multiview's render on
            # cbox_area was 25 ms of 665 slower, 10 of 11 rounds; few packets are dark.
            # benchmarks/RESULTS.md, fifty-first session, helper D)
            whole, above, weight = whole_light_values(vis_fn(smap, lk, opts, shade))
            self._count_out_of_range((whole, above, weight), shade)
            return dr.select(lit, weight, 0.0), whole
        # a light sample that reaches the hit only through its solid (see _into_solid)
        lit = mi.Bool(lit) & ~self._into_solid(lk)
        per_tap = isinstance(smap, VirtualShadowMap) and self.opts.record.virtual_per_tap
        if isinstance(smap, VirtualShadowMap):
            def run(lk):
                return smap.visibility(vis_fn, lk, opts, lit, per_tap=per_tap)
        else:
            def run(lk):
                return vis_fn(smap, lk, opts, lit)
        # a built-in (or lit_packets) method's lookup runs only in packets with a lit lane
        # (mi_shadowmap.packets); a per-tap one draws nothing (VirtualShadowMap.visibility)
        if self._lit_packets and not (per_tap and not self.opts.record.builtin):
            vis = in_lit_packets(run, lk, lit, draws=not per_tap)
        else:   # a user's per-tap lookup: its reads' loop check cannot see through it
            vis = run(lk)
        self._count_out_of_range((vis,), lit)
        return dr.select(lit, vis, 0.0), None

    @staticmethod
    def _into_solid(lk):
        """Where the light sample ``lk.ds`` lies behind the geometric face of a camera hit
        seen from outside a solid that occludes it (``lk.solid_back``, see
        :meth:`_solid_back`): visibility 0.

        A smooth-shaded mesh's BSDF reflects light from below its geometric face near the
        terminator (its shading frame leans over), and Mitsuba's ``direct`` (and
        ``raytraced``) send the shadow ray from the light's side of the face, inside the
        solid, which then occludes it. A map's biases (and ``second_depth``'s second
        surface: such a face is one) let that light through: on a 20-face icosahedron
        with vertex normals under a point light 2.2 % of its pixels in a 128^2 view were
        lit by ``second_depth`` where ``raytraced`` is dark, at any map resolution. The
        other methods' biases let it through in a band along the terminator: an 80-face
        icosphere under a point light, 64^2, ``hard`` 17 pixels lit where ``raytraced`` is
        dark against 2 with ``face_normals`` (0.56 % against 0.20 % misclassified), the
        same for ``pcf``, ``bilinear``, ``pcss``, ``vsm``, ``evsm``, ``msm``; now 2-3.
        Applied for every map method (``multiview`` tests each of its views,
        ``Lookup.solid_back``). False where the scene has no such mesh (faces without
        interpolated normals reflect nothing from behind).
        Only for a part its light is outside of: a light inside a closed frosted-glass
        shade lights its outside through it, its shadow rays never leaving the solid
        (second_depth, which stores the shade as its second surface, is right there),
        while a glass ball's far side lit from outside is shaded through it by Mitsuba's
        ``direct``, whose shadow ray crosses the near side: ``second_depth`` lit it (its
        image 1.18x ``raytraced``'s for a glass icosphere beside a point light, 1.38x for
        a glass cube). So too a reflecting solid's outside lit from a light inside it,
        in the band where its shading frame leans towards the light: ``direct`` lights
        it, its shadow ray reaching the light inside (a point light just inside a smooth
        icosahedron: 27 of 48^2 pixels, which every map method rendered black when this
        applied to all methods with the light inside taken as occluded; a shapegroup's
        reflecting mesh is still taken so)."""
        if lk.solid_back is None or lk.si is None or lk.ds is None:
            return mi.Bool(False)
        n = dr.detach(lk.si.n)
        return mi.Bool(lk.solid_back) & (dr.dot(n, dr.detach(lk.ds.d)) < 0)

    def _solid_back(self, si, light_outside=None):
        """Where the camera hit ``si`` is on the outside of a solid (a closed,
        outward-oriented mesh part with vertex normals, or any such part of a mesh whose
        BSDF transmits or reflects on both sides, :func:`~mi_shadowmap.depth_maps.
        solid_face_tables`) that occludes light arriving from behind the hit's geometric
        face (``Lookup.solid_back``): its light is outside its part (``light_outside``,
        per part, :func:`~mi_shadowmap.depth_maps.lights_outside`; see
        :meth:`_into_solid`), or, where that is not known (no such table, a part of a
        shapegroup's mesh), its BSDF does not transmit. Also where the hit is seen from
        inside a part its light is outside of (a camera in a closed twosided room under a
        sun): light from behind the face, the camera's side, must leave the part to get
        there (``second_depth``, whose layer stores such a face as its own second
        surface, lit the room's floor and walls: 80.8 % of a view misclassified)."""
        tables = self._solid_faces
        if tables is None or si is None:
            return None
        offset, solid, part, _ = tables
        raw = dr.reinterpret_array(mi.UInt32, si.shape)
        known = raw < dr.width(offset)
        off = dr.gather(mi.Int32, offset, dr.select(known, raw, 0), known)
        known &= off >= 0
        row = mi.UInt32(dr.maximum(off, 0)) + mi.UInt32(si.prim_index)
        known &= row < dr.width(solid)
        inside = known & dr.gather(mi.Bool, solid, dr.select(known, row, 0), known)
        n = dr.detach(si.n)
        outside = dr.dot(n, dr.detach(si.to_world(si.wi))) > 0   # seen from outside
        # only from a light outside the hit's part: a light inside a closed frosted-glass
        # shade lights its outside through it, its shadow rays never leaving the solid
        # (second_depth, which stores the shade as its second surface, is right there),
        # and a light just inside a smooth solid lights its outside where the shading
        # frame leans towards it. Rows of a shapegroup's meshes that do not transmit have
        # no part: occluded.
        transmits = mi.has_flag(si.bsdf().flags(), mi.BSDFFlags.Transmission)
        blocked = ~transmits
        has = mi.Bool(False)
        if part is not None and light_outside is not None:
            p = dr.gather(mi.Int32, part, dr.select(inside, row, 0), inside)
            has = inside & (p >= 0)
            blocked = dr.select(has, dr.gather(mi.Bool, light_outside,
                                               mi.UInt32(dr.maximum(p, 0)), has), blocked)
        # seen from inside a part its light is outside of (a camera in a closed twosided
        # room under a sun): a light sample behind the geometric face, on the camera's
        # side, reaches the hit only through the part (the ray must leave it again)
        return inside & (outside | has) & blocked

    def _count_out_of_range(self, values, active):
        """A user method's render (:meth:`render` raises after it): count the lanes where
        a lookup returned a value outside [0, 1] or NaN. Built-in methods skip it."""
        if self._out_of_range is None:
            return
        bad = mi.Bool(False)
        for v in values:
            v = mi.Float(v)
            bad |= ~((v >= 0.0) & (v <= 1.0))
        dr.scatter_reduce(dr.ReduceOp.Add, self._out_of_range, mi.UInt32(1), mi.UInt32(0),
                          mi.Bool(active) & bad)

    def _gradient_render(self) -> bool:
        """Whether this render's maps are in the AD graph (a gradient render) and
        ``gradient_at`` is ``'pixel_centre'``."""
        if not self.opts.uses_map or self.opts.gradient_at != "pixel_centre":
            return False
        return any(isinstance(m, ShadowMap) and (dr.grad_enabled(m.depth)
                                                   or (m.pose is not None and m.pose.attached))
                   for m in self.maps)

    def _pixel_centre(self, si, dp_dx, dp_dy, active):
        """The surface point under the centre of the camera sample's pixel, to first
        order: ``p + dp_dx (1/2 - fx) + dp_dy (1/2 - fy)``, ``(fx, fy)`` the sample's
        position in its pixel (the film position of ``p``, from the sensor's
        ``sample_direction``). A ``perspective`` camera only: other sensors
        (``orthographic`` has no ``sample_direction``; a thin lens's film position
        depends on the aperture sample) keep ``p``, the sample's own point.
        Returns ``(point, pixel)``: ``pixel`` an id of the film pixel (``x + 65536 y``;
        None with other sensors)."""
        sensor = self._sensor
        if not is_pinhole(sensor):
            return si.p, None
        off, pixel = self._film_position(si, active)
        return si.p + dp_dx * off.x + dp_dy * off.y, pixel

    def _film_position(self, si, active):
        """``(offset, pixel)`` of a ``perspective`` camera's hits ``si``: from the film
        position of ``si.p`` (the sensor's ``sample_direction``), the offset from it to
        its pixel's centre (pixels) and the pixel's id (``x + 65536 y`` in the crop)."""
        ds, _ = self._sensor.sample_direction(dr.detach(si), mi.Point2f(0.5), active)
        uv = dr.detach(ds.uv)
        cell = dr.floor(uv)
        off = 0.5 - (uv - cell)
        pixel = mi.UInt32(dr.maximum(cell.x, 0.0)) + mi.UInt32(dr.maximum(cell.y, 0.0)) * 65536
        return off, pixel

    def _film_pixel(self, si, active):
        """The film pixel (``x + 65536 y``) of each hit ``si`` of a ``perspective``
        camera (:meth:`_film_position`), for :attr:`~mi_shadowmap.filters.common.Lookup.pixel`."""
        return self._film_position(si, active)[1]

    @staticmethod
    def _lookup(smap, si, dp_dx, dp_dy, ds, sampler, p=None, centre=False,
                emitter=None) -> Lookup:
        """The lookup of ``si`` in ``smap``, at ``p`` (default ``si.p``); ``centre``:
        ``p`` is the pixel centre's point, in the derivative run of
        :meth:`_gradient_light_term` (``Lookup.centre``); ``emitter``: the light shaded
        (``Lookup.emitter``). When the light's pose has
        gradients (``smap.pose``, :mod:`mi_shadowmap.light_views.pose`) the point,
        normal and footprint carry them (values unchanged)."""
        pose = getattr(smap, "pose", None)
        p = si.p if p is None else p
        if pose is None:
            return Lookup(p, si.n, dp_dx, dp_dy, si, ds, sampler, centre, emitter)
        return Lookup(pose.to_view(p), pose.vector_to_view(si.n),
                      pose.vector_to_view(dp_dx), pose.vector_to_view(dp_dy), si, ds, sampler,
                      centre, emitter)

    def _footprint(self, ray: mi.RayDifferential3f, si, sampler=None):
        """World-space pixel footprint on the tangent plane: a perspective camera's from
        its pinhole and pixel steps (:func:`~mi_shadowmap.light_views.pinhole_footprint`,
        the points its ray differentials would give, at a fraction of their cost: a
        virtual ``hard`` lookup's footprint cost as much as a full map's whole lookup);
        other sensors' from their ray differentials; a sensor without them (``batch``)
        from the one-pixel steps of each sample's pixel (``sampler``: the render's, whose
        lanes are the film's pixels, see :class:`_PixelSteps`)."""
        if self._pinhole is not None:
            return pinhole_footprint(si.p, si.n, self._pinhole)
        n = si.n
        scale = self._diff_scale

        def hit(o, d):
            t = dr.dot(n, si.p - o) / dr.select(dr.abs(dr.dot(n, d)) > 1e-12,
                                                dr.dot(n, d), 1e-12)
            return o + d * t

        ok = ray.has_differentials
        if not ok and self._pixel_step is not None:
            # a sensor without ray differentials (batch): a cone of its pixel's angle
            angle, offset = self._pixel_step.at(sampler)
            frame = mi.Frame3f(dr.normalize(ray.d))
            o_x, o_y = ray.o + frame.s * offset, ray.o + frame.t * offset
            d_x, d_y = frame.n + frame.s * angle, frame.n + frame.t * angle
            dp_dx, dp_dy = hit(o_x, d_x) - si.p, hit(o_y, d_y) - si.p
            return mi.Vector3f(dp_dx), mi.Vector3f(dp_dy)
        o_x = ray.o + (ray.o_x - ray.o) * scale
        o_y = ray.o + (ray.o_y - ray.o) * scale
        d_x = ray.d + (ray.d_x - ray.d) * scale
        d_y = ray.d + (ray.d_y - ray.d) * scale
        dp_dx = dr.select(ok, hit(o_x, d_x) - si.p, 0.0)
        dp_dy = dr.select(ok, hit(o_y, d_y) - si.p, 0.0)
        return mi.Vector3f(dp_dx), mi.Vector3f(dp_dy)

    def to_string(self):
        res = self.opts.resolution if self.opts.resolution is not None else "auto"
        return f"ShadowMapIntegrator[method={self.opts.method}, resolution={res}]"


def _tracks_gradients(scene) -> bool:
    """Whether any ``mi.traverse(scene)`` parameter has gradients enabled in the current
    AD scope (False in ``mi.render``'s primal pass, under ``dr.suspend_grad()``)."""
    if not dr.is_diff_v(mi.Float):
        return False
    params = MAP_CACHE.traverse(scene)
    return any(dr.grad_enabled(params[k]) for k in params.keys())


def _sensor_object(scene, sensor):
    """The sensor a render's ``sensor`` argument names: a ``mi.Sensor``, or an index into
    ``scene.sensors()`` of any integer type Mitsuba's own ``render()`` takes (``int``,
    ``bool``, numpy's integers). A numpy index was taken for a sensor ("'numpy.int64'
    object has no attribute 'film'", where Mitsuba's ``direct`` renders that sensor), an
    index out of range failed as a bare "list index out of range", and -1 had the first
    pass plan the last sensor's maps before Mitsuba refused it as "incompatible function
    arguments". Raises an error naming ``sensor`` and the valid indices."""
    if isinstance(sensor, mi.Sensor):
        return sensor
    try:
        index = operator.index(sensor)
    except TypeError:
        raise TypeError(
            f"shadowmap: render(): 'sensor' is {type(sensor).__name__} {sensor!r}; give a "
            "mi.Sensor or an index into scene.sensors()") from None
    sensors = scene.sensors()
    if not 0 <= index < len(sensors):
        valid = (f"valid: 0..{len(sensors) - 1}" if sensors else
                 "it has none: give a mi.Sensor")
        raise IndexError(
            f"shadowmap: render(): sensor index {index} is out of range: the scene has "
            f"{len(sensors)} sensor(s) ({valid})")
    return sensors[index]


def _film_takes_aovs(film) -> bool:
    """Whether ``film`` can take an integrator's AOV channels. Mitsuba 3.9's sampling
    integrators write them after an RGB film's R, G, B, [A], W channels whatever the
    film, so a film with its own channel layout (``FilmFlags.Special``: ``specfilm``)
    gets them at the wrong offsets: its own channels are left unset ("operands have
    incompatible sizes") and writes run past its sample buffer (heap corruption;
    Mitsuba's own ``aov`` integrator fails the same way, mitsuba3 issue #1189). Such a
    render leaves the visibility AOVs out, with a warning: render to an ``hdrfilm`` to
    get them."""
    if not mi.has_flag(film.flags(), mi.FilmFlags.Special):
        return True
    warnings.warn(
        f"shadowmap: the sensor's film ({film.class_name()}) has its own channel layout, "
        "into which Mitsuba 3.9 cannot write integrator AOVs (mitsuba3 issue #1189): this render "
        "leaves out the visibility AOVs (vis_<emitter>); the image itself is complete. "
        "Render to an 'hdrfilm' to get them", RuntimeWarning, stacklevel=4)
    return False


#: The sensors each scene (its :func:`scene_lease`) was probed for by
#: :func:`warn_if_hits_imprecise`.
_PRECISION_CHECKED: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()
#: Camera rays per film side of :func:`warn_if_hits_imprecise`'s probe.
PRECISION_PROBE = 16
#: Sensors a scene's probe remembers (:meth:`ShadowMapIntegratorMixin._check_hit_precision`).
PRECISION_SENSORS = 4


def warn_if_hits_imprecise(scene, sensor, probe: int = PRECISION_PROBE) -> float:
    """Warn when Mitsuba's own surface interactions put the camera's hits off their
    rays by more than a pixel and 1e-5 of their distance (or give them no normal), and
    return that error in pixels (0 where no probe ray hits or none is off by more than
    1e-5 of its distance).

    Mitsuba computes a hit's position from the shape's local coordinates (a
    rectangle's, a disk's) or from barycentrics (a mesh's triangle) in float32, so a
    shape scaled ``s`` places its hits about ``7e-8 s`` from the ray: a ground rectangle
    1e10 wide under a scene 1 unit across, seen from 10 units, puts them 723 units off
    (median of a 48^2 view; 6.75 at 1e8, 0.07 at 1e6) and, at 1e10, with a zero normal,
    so their shadow rays hit the ground itself. Every method then shades other points
    than the pixels see -- the ``raytraced`` reference too -- and a virtual map marks
    its pages where those points fall (pages across a whole face at level 0, more than
    the page table holds). No shadow map can mend that; the warning names the shapes
    whose size explains it (split a huge ground into tiles, or shrink it).

    The probe traces ``probe^2`` rays through pixel centres and their neighbours one
    pixel to the right (a kernel once per scene and sensor:
    :meth:`ShadowMapIntegratorMixin._check_hit_precision`)."""
    film = sensor.film()
    w, h = (int(x) for x in film.crop_size())     # sample_ray's [0, 1]^2: the crop
    nx, ny = min(probe, w), min(probe, h)
    px, py = np.meshgrid((np.arange(nx) + 0.5) * w / nx, (np.arange(ny) + 0.5) * h / ny)
    px, py = px.ravel(), py.ravel()
    u, v = np.concatenate([px, px + 1.0]) / w, np.concatenate([py, py]) / h
    with dr.suspend_grad():
        try:
            ray, _ = sensor.sample_ray(0.0, 0.5, mi.Point2f(mi.Float(u), mi.Float(v)),
                                       mi.Point2f(0.5, 0.5))
        except RuntimeError:    # a sensor without it (irradiancemeter): nothing probed
            return 0.0
        si = scene.ray_intersect(mi.Ray3f(ray))
        dr.eval(ray.o, ray.d, si.p, si.n, si.t)      # one kernel
        k = len(px)         # (a pinhole's ray origin may be one lane: broadcast)
        o, d, p, n = (np.stack([np.broadcast_to(np.asarray(c, np.float64), (2 * k,))
                                for c in a], 1) for a in (ray.o, ray.d, si.p, si.n))
        t = np.broadcast_to(np.asarray(si.t, np.float64), (2 * k,))
    hit = np.flatnonzero(np.isfinite(t[:k]) & (t[:k] > 0))
    if not len(hit):
        return 0.0
    t = t[hit, None]
    on_ray = o[hit] + d[hit] * t
    pixel = np.linalg.norm(o[k + hit] + d[k + hit] * t - on_ray, axis=1)   # one pixel over
    err = np.linalg.norm(p[hit] - on_ray, axis=1)
    no_normal = int((np.linalg.norm(n[hit], axis=1) < 0.5).sum())
    # errors within 1e-5 of the hit's own size are float32 rounding of a sound hit (a
    # 1 x 1 film's distant or radiancemeter sensor has no pixel to compare with: 1.7e-7
    # units off read as 1.7e23 pixels)
    rounding = 1e-5 * np.maximum(t[:, 0], np.abs(on_ray).max(axis=1))
    worst = float(np.where(err > rounding, err / np.maximum(pixel, 1e-30), 0.0).max())
    if worst <= 1.0 and not no_normal:
        return worst
    # the shapes whose float32 step (their box's widest side 2^-24) is near that error
    big = []
    for shape in scene.shapes():
        b = shape.bbox()
        if b.valid():
            side = float(dr.max(b.max - b.min))
            if side * 2.0 ** -24 >= 0.1 * float(err.max()):
                big.append((side, shape.id() or shape.class_name()))
    names = ", ".join(f"'{name}' ({side:.3g} wide)"
                      for side, name in sorted(big, reverse=True)[:3])
    warnings.warn(
        f"shadowmap: Mitsuba places this view's hits up to {float(err.max()):.3g} "
        f"units ({worst:.3g} pixels) off the camera's rays"
        + (f", {no_normal} of {len(hit)} probed without a normal" if no_normal else "")
        + f" (float32 surface interactions of a shape far wider than the view: "
        f"{names or 'none found'}): every method shades other points than the pixels "
        "see, the 'raytraced' reference too. Split or shrink the shape",
        RuntimeWarning, stacklevel=5)
    return worst


def _warn_if_enclosing(scene, view, method: str) -> None:
    """Warn when an area light's shape encloses every other shape (a sky dome: a
    sphere light turned inwards; its bounding box holds the scene's, whose own box holds
    the light's centre): a map from its centre sees it as a point light there,
    inside the scene (a dome over a floor and a box: ``hard`` 24 % too dark, ``pcf``
    17 %), which only methods sampling the light itself model."""
    if view is None or getattr(view, "kind", None) != "area" or view.ignore_shape is None:
        return
    b = view.ignore_shape.bbox()
    bounds = scene_bounds(scene, exclude=view.ignore_shape)
    if bounds is None or not b.valid():
        return
    lo_l = np.array([float(c) for c in b.min])
    hi_l = np.array([float(c) for c in b.max])
    centre = np.array([float(c) for c in view.position])
    if (np.all(lo_l <= bounds[0]) and np.all(bounds[1] <= hi_l)
            and np.all(bounds[0] <= centre) and np.all(centre <= bounds[1])):
        warnings.warn(
            f"shadowmap: area light '{view.label}' encloses the scene (a dome or sky "
            f"sphere); method '{method}' sees it from its centre, as a light at one point "
            "inside the scene. Use method='multiview' (maps from points on the light) or "
            "'raytraced', or an environment emitter (envmap, constant) with "
            "environment='shadowed'", RuntimeWarning, stacklevel=3)


def _nested_sensor(scene, sampler, ray):
    """The sensor a render that calls our ``sample()`` alone (Mitsuba's ``moment``,
    ``stokes``) is rendering: Mitsuba does not pass it. Its sampler's wavefront holds
    ``spp`` samples per pixel of that sensor's film (its crop and a sampled border,
    :func:`_film_fits`), which rules out sensors of other sizes; among several (or none)
    of that size, the one whose ray through the centre of its first pixel is nearest to
    the wavefront's first ray (Mitsuba's lane 0: that pixel, one jittered sample).
    Before, the scene's first sensor was taken: a ``moment`` render of ``sensor=1``
    built its maps for sensor 0's view. A sensor that is not the scene's
    (``mi.render(scene, sensor=obj)``) cannot be found: where no film of the scene fits,
    a warning says so."""
    sensors = list(scene.sensors())
    wavefront, spp = sampler.wavefront_size(), max(sampler.sample_count(), 1)


    fits = [s for s in sensors if _film_fits(s, sampler)]
    if not fits:
        warnings.warn(
            "shadowmap: nested in another integrator that calls its sample() alone "
            "(Mitsuba's moment, stokes, ...), which does not say which sensor it renders, "
            f"and no sensor of the scene has a film of the render's {wavefront // spp} "
            "pixels (a sensor given to mi.render that is not the scene's?): the maps are "
            + (f"built for the scene's sensor {sensors[0].id() or 0!r}" if sensors else
               "built without a sensor (a 512x512 film assumed)")
            + ", so their pages and footprints may not fit the view rendered",
            RuntimeWarning, stacklevel=4)
    if len(fits) == 1 or len(sensors) <= 1:
        return (fits or sensors or [None])[0]
    fits = fits or sensors
    if ray is None:
        return fits[0]
    # several films of this size: compare the first ray with each one's first pixel's
    def lane0(v):     # lane 0 of a 3-vector, float64
        return np.array([dr.slice(v.x, 0), dr.slice(v.y, 0), dr.slice(v.z, 0)], np.float64)
    o, d = lane0(ray.o), lane0(ray.d)
    best, best_err = fits[0], math.inf
    for s in fits:
        film = s.film()
        # a film position is a fraction of the crop (Mitsuba's render passes it so; of
        # the whole film, an offset crop's ray missed its first pixel by pixels)
        crop, first = film.crop_size(), 0.5 - _film_border(film)
        uv = mi.Point2f(first / crop[0], first / crop[1])
        r, _ = s.sample_ray(0.0, 0.5, uv, mi.Point2f(0.5))
        o_s, d_s = lane0(r.o), lane0(r.d)
        scale = max(float(np.linalg.norm(o_s)), float(np.linalg.norm(o)), 1e-30)
        err = float(np.linalg.norm(o - o_s)) / scale + float(np.linalg.norm(d - d_s))
        if err < best_err:
            best, best_err = s, err
    return best


def _film_border(film) -> int:
    """The pixels a film samples beyond its crop on each side: its filter's border where
    it has ``sample_border``, else 0."""
    return film.rfilter().border_size() if film.sample_border() else 0


def _film_fits(sensor, sampler) -> bool:
    """Whether the render's wavefront holds a whole number of samples per pixel of
    ``sensor``'s film (its crop and a sampled border; :func:`_nested_sensor`'s test)."""
    film = sensor.film()
    b = _film_border(film)
    size = film.crop_size()
    pixels = (int(size[0]) + 2 * b) * (int(size[1]) + 2 * b)
    wavefront, spp = sampler.wavefront_size(), max(sampler.sample_count(), 1)
    return (pixels > 0 and wavefront % pixels == 0
            and spp % max(wavefront // pixels, 1) == 0)


class _PixelSteps:
    """The one-pixel steps of a sensor without ray differentials (a ``batch``), per
    pixel of its film's crop (:func:`~mi_shadowmap.light_views.pixel_steps`), and which
    pixel each lane of a render's wavefront samples: Mitsuba's JIT render gives lane
    ``i`` the film pixel ``i // spp`` (row by row over the crop, and the filter's border
    around it when the film has ``sample_border``), as ``_nested_sensor`` reads it too.
    :meth:`at` returns ``(angle, offset)`` per lane; where the wavefront is not the
    film's pixels times the samples (no sampler given, a sensor whose film is not the
    one rendered), the medians over the film."""

    def __init__(self, sensor):
        film = sensor.film()
        self.crop = tuple(int(x) for x in film.crop_size())
        self.border = film.rfilter().border_size() if film.sample_border() else 0
        angle, offset = pixel_steps(sensor)
        self.angle, self.offset = mi.Float(angle), mi.Float(offset)
        # opaque: a new view's medians must not compile a new kernel
        self.median = tuple(dr.opaque(mi.Float, float(np.median(v)) if len(v) else 0.0)
                            for v in (angle, offset))

    def at(self, sampler):
        w, h = self.crop
        b = self.border
        pixels = (w + 2 * b) * (h + 2 * b)
        lanes = sampler.wavefront_size() if sampler is not None else 0
        if pixels == 0 or lanes == 0 or lanes % pixels != 0 or dr.width(self.angle) != w * h:
            return self.median
        # opaque: a new spp or film size compiles nothing
        # lanes counted unsigned (a wavefront may pass 2^31 samples); pixels fit Int32
        pixel = mi.Int32(dr.arange(mi.UInt32, lanes) // dr.opaque(mi.UInt32, lanes // pixels))
        row = pixel // dr.opaque(mi.Int32, w + 2 * b)
        col = pixel - row * dr.opaque(mi.Int32, w + 2 * b)
        b_op = dr.opaque(mi.Int32, b)
        col = dr.clip(col - b_op, 0, dr.opaque(mi.Int32, w - 1))   # border: the edge pixel's
        row = dr.clip(row - b_op, 0, dr.opaque(mi.Int32, h - 1))
        index = mi.UInt32(row * dr.opaque(mi.Int32, w) + col)
        return dr.gather(mi.Float, self.angle, index), dr.gather(mi.Float, self.offset, index)


def _warn_if_centre_hidden(scene, view, method: str, memo: dict) -> None:
    """Warn when an area light's centre, from which the map methods see it, is hidden
    from most of the light by other shapes (the centre inside a solid: two tube lights
    in one mesh with a beam between them, a disk light through a ball): the map then
    finds every receiver shadowed, though the light shines past the shape. Measured:
    the two tubes rendered black (0 against direct's 0.0278) in ``hard``, ``pcf``,
    ``vsm``, ``second_depth`` and ``pcss`` (0.0004), silently. 64 stratified points on
    the light (uniform by area) are each tested for a shape between them and the centre
    (the light's own shape is not an occluder of its map); more than half hidden warns.
    Once per scene, light and centre (``memo``)."""
    if view is None or getattr(view, "kind", None) != "area" or view.ignore_shape is None:
        return
    shape = view.ignore_shape
    centre = tuple(float(c) for c in view.position)
    key = (id(scene), id(shape), centre)
    if key in memo:
        return
    memo[key] = True
    with dr.suspend_grad():
        k = dr.arange(mi.UInt32, 64)
        u = mi.Point2f((mi.Float(k % 8) + 0.5) / 8, (mi.Float(k // 8) + 0.5) / 8)
        ps = shape.sample_position(0.0, u)
        # opaque: literals would compile these kernels anew per light and centre (40
        # area lights: 120 compiles, 1.4 s on the first render)
        c = dr.opaque(mi.Point3f, centre)
        d = ps.p - c
        dist = dr.norm(d)
        ok = dist > 1e-6 * dr.maximum(dr.max(dr.abs(ps.p)), 1.0)
        ray = mi.Ray3f(c, d / dr.maximum(dist, 1e-30))
        ray.maxt = dist * (1.0 - 1e-3)
        si = scene.ray_intersect(ray, mi.RayFlags.Minimal, False, ok)
        own = dr.opaque(mi.UInt32, int(dr.reinterpret_array(mi.UInt32, mi.ShapePtr(shape))[0]))
        hidden = ok & si.is_valid() & (dr.reinterpret_array(mi.UInt32, si.shape) != own)
        frac = int(dr.count(hidden)[0]) / 64
    if frac > 0.5:
        warnings.warn(
            f"shadowmap: area light '{view.label}': its centre, from which method "
            f"'{method}' sees it, is hidden from {100 * frac:.0f} % of the light by other "
            "shapes (inside a solid?); the map then shadows receivers the light reaches. "
            "Use method='multiview' (maps from points on the light) or 'raytraced'",
            RuntimeWarning, stacklevel=3)


def has_delta_bsdf(scene) -> bool:
    """Whether a shape of ``scene`` may have a delta BSDF lobe (a mirror, glass, smooth
    plastic, a ``mask``'s pass-through): then :func:`_delta_lobe_term` is part of the
    shading. Instances count as yes (their shape group's BSDFs are not reachable from
    Python), so such scenes pay one masked ray per camera sample."""
    delta = int(mi.BSDFFlags.Delta)
    for shape in scene.shapes():
        if shape.class_name() == "Instance":
            return True
        bsdf = shape.bsdf()
        if bsdf is not None and int(bsdf.flags()) & delta:
            return True
    return False


def tilted_frame_table(scene):
    """``mi.Bool`` by BSDF registry id: whether that BSDF of ``scene`` (its shapes', a
    shape group's too) is or nests one of
    :data:`~mi_shadowmap.variants.TILTING_BSDFS`; None where none does.

    Such a BSDF reflects light only from above both its shading frame's horizon and the
    tilted frame's (Mitsuba's ``normalmap`` and ``bumpmap`` evaluate the nested BSDF in
    the tilted frame), so a lookup may not take one horizon test for a whole hemisphere
    of directions there (:attr:`~mi_shadowmap.filters.common.Lookup.tilted`)."""
    listed = list(scene.shapes())
    bsdfs, seen = [], set()
    for shape in listed + _grouped_shapes(scene, listed):
        bsdf = shape.bsdf()
        if bsdf is None:
            continue
        key = int(dr.reinterpret_array(mi.UInt32, mi.BSDFPtr(bsdf))[0])
        if key in seen:
            continue
        seen.add(key)
        if tilts_shading_frame(bsdf):
            bsdfs.append(key)
    if not bsdfs:
        return None
    table = np.zeros(max(bsdfs) + 2, bool)   # padded: never a one-entry literal
    table[bsdfs] = True
    return mi.Bool(table)


def tilted_frame(table, si) -> mi.Bool:
    """Where the BSDF of the hits ``si`` is one that :func:`tilted_frame_table`
    marks (``table``)."""
    raw = dr.reinterpret_array(mi.UInt32, si.bsdf())
    known = raw < dr.width(table)
    return dr.gather(mi.Bool, table, dr.select(known, raw, 0), known)


def _delta_lobe_term(scene, si, bsdf, sampler, valid):
    """Emitted light seen through the delta lobes of ``bsdf`` at ``si`` (a mirror's
    reflection of an area light or of the environment, light refracted by glass or
    seen through a ``mask``): one BSDF sample restricted to the delta lobes and one
    traced ray; its radiance if the ray reaches an emitter (the environment when it
    escapes).

    Light sampling cannot reach these lobes (their value is a Dirac delta), so
    Mitsuba's ``direct`` gets them from its BSDF samples, where the multiple-importance
    weight of a delta lobe is 1; this is that term, for every method alike. The ray is
    a real one: whether it reaches the light is the mirror image's own visibility,
    which a shadow map of the light does not hold. For every other lobe, light
    sampling alone is the estimator (the same expectation as ``direct``'s MIS)."""
    ctx = mi.BSDFContext()
    ctx.type_mask = mi.BSDFFlags.Delta
    active = valid & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Delta)
    bs, weight = bsdf.sample(ctx, si, sampler.next_1d(active), sampler.next_2d(active), active)
    weight = bsdf_to_world(si, weight, bs.wo)
    active &= (bs.pdf > 0) & mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)
    active &= dr.max(unpolarized(weight)) > 0
    si_e = scene.ray_intersect(si.spawn_ray(si.to_world(bs.wo)), active)
    emitter = si_e.emitter(scene, active)
    active &= emitter != None  # noqa: E711  (a Dr.Jit pointer array)
    return dr.select(active, weight * emitter.eval(si_e, active), 0.0)


def _light_sample(emitter, si, bsdf, ctx, u, shade):
    """One light sample at ``si``: ``(ds, unshadowed = bsdf * weight, lit, counts)``
    (Mueller matrices in a polarized variant: :func:`~mi_shadowmap.variants.bsdf_to_world`).
    ``counts``: where the sample counts for the visibility AOV (the light's weight is
    non-zero and the light is above the horizon); ``lit``: where its term is shaded
    (visibility looked up, ``unshadowed * vis`` added) -- ``counts``, but where the
    weight tracks gradients every sample above the horizon, whatever the weight's value:
    a light of intensity exactly 0 has weight 0 everywhere, and gating its term by the
    weight's value cut the derivative wrt the intensity to 0 (``raytraced``, ``hard``,
    ``pcf``: 0 against ``direct``'s 55.5 on a point light; the image is linear in it)."""
    ds, w = emitter.sample_direction(si, u, shade)
    lit = shade & (ds.pdf > 0)
    wo = si.to_local(ds.d)
    f, reaches = bsdf_eval_reaches(bsdf, ctx, si, wo, lit)
    unshadowed = bsdf_to_world(si, f, wo) * w
    # a dark receiver is still lit (its BSDF's pdf): only the light's weight and the
    # horizon decide whether the sample counts for the visibility AOV
    counts = reaches & (dr.max(unpolarized(w)) > 0)
    return ds, unshadowed, (reaches if dr.grad_enabled(w) else counts), counts


class _Recorder:
    """The sampler a lookup sees in the value pass of :meth:`_gradient_light_term`:
    the wrapped sampler, recording what ``next_1d``/``next_2d`` return so that the
    pixel-centre pass draws the same numbers (:meth:`replay`). Other attributes are the
    sampler's."""

    def __init__(self, sampler):
        self.sampler, self.drawn = sampler, []

    def next_1d(self, active=True):
        v = self.sampler.next_1d(active)
        self.drawn.append(v)
        return v

    def next_2d(self, active=True):
        v = self.sampler.next_2d(active)
        self.drawn.append(v)
        return v

    def replay(self):
        return _Replay(self.sampler, list(self.drawn))

    def __getattr__(self, name):
        return getattr(self.sampler, name)


class _PixelSampler:
    """The sampler of the pixel-centre pass (perspective cameras): ``next_1d`` /
    ``next_2d`` come from a PCG32 stream per lane seeded by the film pixel and the
    emitter's index, so every sample and seed of a pixel reads the same taps and
    jitter there (the derivative's spread over seeds is not the taps' noise), while
    pixels draw independently (so, over the pixels, the taps' quadrature error
    averages out as with fresh random numbers). Other attributes are the sampler's."""

    def __init__(self, sampler, pixel, stream: int):
        self.sampler = sampler
        self.rng = mi.PCG32(size=dr.width(pixel), initstate=mi.UInt64(pixel),
                            initseq=mi.UInt64(0x5851F42D + stream))

    def next_1d(self, active=True):
        return self.rng.next_float32()

    def next_2d(self, active=True):
        return mi.Point2f(self.rng.next_float32(), self.rng.next_float32())

    def __getattr__(self, name):
        return getattr(self.sampler, name)


class _Replay:
    """The sampler of the pixel-centre pass: ``next_1d``/``next_2d`` return the value
    pass's numbers in order (the same taps, jitter and seeds). A lookup must draw them
    outside symbolic loops and the same way in both passes (see ``Lookup``)."""

    def __init__(self, sampler, drawn):
        self.sampler, self.drawn = sampler, drawn

    def _next(self):
        if not self.drawn:
            raise RuntimeError(
                "shadowmap: with gradient_at='pixel_centre' a lookup runs twice in a "
                "gradient render (at the sample and at its pixel's centre) and must draw "
                "the same random numbers both times; this lookup drew more the second "
                "time. Draw them the same way in both (not depending on "
                "dr.grad_enabled), or set gradient_at='sample'.")
        return self.drawn.pop(0)

    def next_1d(self, active=True):
        return self._next()

    def next_2d(self, active=True):
        return self._next()

    def __getattr__(self, name):
        return getattr(self.sampler, name)


def integrator_class():
    """The ``shadowmap`` integrator class of the current variant (see
    :func:`mi_shadowmap.variants.variant_class`); raises
    :class:`~mi_shadowmap.variants.UnsupportedVariantError` for scalar variants."""
    return variant_class(ShadowMapIntegratorMixin, name="ShadowMapIntegrator")


class _Refusal:
    """Registered for unsupported variants: constructing it raises a clear error."""

    def __init__(self, variant):
        self.variant = variant

    def __call__(self, props):
        check_variant(self.variant)   # raises, naming the variant and the supported ones


def register(variant: str | None = None) -> None:
    """Register ``shadowmap`` for the current Mitsuba variant (a refusal for unsupported ones)."""
    variant = variant or mi.variant()
    if variant is None:
        return
    if variant in SUPPORTED_VARIANTS:
        cls = integrator_class()
        mi.register_integrator("shadowmap", lambda props: cls(props))
    else:
        mi.register_integrator("shadowmap", _Refusal(variant))


def __getattr__(name):
    # ``integrator.ShadowMapIntegrator``: the current variant's class.
    if name == "ShadowMapIntegrator":
        return integrator_class()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def _attached_arrays(obj, out=None, seen=None) -> list:
    """Every Dr.Jit array with gradients enabled held by ``obj`` (lists, tuples, dicts,
    dataclasses and plain objects' attributes, walked once each): the maps' depths and
    layers, their poses and views, for :meth:`ShadowMapIntegratorMixin.render_forward`."""
    out = [] if out is None else out
    seen = set() if seen is None else seen
    if obj is None or isinstance(obj, (str, bytes, int, float, bool)) or id(obj) in seen:
        return out
    seen.add(id(obj))
    if dr.is_array_v(obj):
        if dr.grad_enabled(obj):
            out.append(obj)
        return out
    if isinstance(obj, dict):
        items = obj.values()
    elif isinstance(obj, (list, tuple)):
        items = obj
    elif hasattr(obj, "__dict__") and type(obj).__module__.startswith("mi_shadowmap"):
        items = vars(obj).values()
    elif hasattr(obj, "__dataclass_fields__"):
        items = [getattr(obj, f) for f in obj.__dataclass_fields__]
    else:
        return out
    for item in items:
        _attached_arrays(item, out, seen)
    return out
