"""Differentiable shadows (issue 13): our gradients against Mitsuba's ``direct_projective``.

    python benchmarks/bench_gradients.py [--scene area,directional] [--image 128] [--spp 16]
                                         [--map 128] [--margin 8] [--seeds 8] [--mean-seeds 24]
                                         [--param sideways|along|light] [--methods vsm,pcf[,pcss]]
                                         [--sampler independent|stratified|multijitter|ldsampler]
                                         [--ref-spp 1024] [--ref-seeds 4] [--no-projective]
                                         [--projective-guiding octree|grid|none]
                                         [--time-rounds 0] [--time-seeds 4]
                                         [--no-fd] [--json out.json]

Default run: both scenes, parameter ``sideways``, about 4-6 minutes per scene on 2
cores (direct_projective's 25 gradients, 3-6 s each, are most of it).

Scenes: ``area`` -- a 0.6 x 0.6 rectangle area light 3 units up (its cube map seen from
its centre) over a ground plane, a flat box occluder 1 unit up: the same scene as
``mi_shadowmap.inverse.occluder_scene('area')``; ``directional`` --
tests/test_differentiable.py's scene (the ``box`` is the occluder). The occluder is a
welded 8-vertex box mesh (``--occluder welded``: ``mi_shadowmap.procedural.box`` placed
by ``mi_shadowmap.scenes.mesh``, the same vertices and faces as the benchmark's former
``welded_cube``); on Mitsuba's 24-vertex ``cube`` (``--occluder cube``)
direct_projective's gradients come out about 2x too large (each silhouette edge is a
boundary edge of two separate faces).

One scalar parameter ``t`` (``d loss / d t`` at ``t = 0``); the loss is the mean colour
of the *receiver* pixels: ground pixels at least ``--margin`` pixels away, on screen,
from anything that is not ground (so the occluder's own silhouette and shading never
enter the loss; only its shadow).

* ``--param sideways`` (default): the occluder translated horizontally (+z), across the
  light: its outline moves across the maps' texels. The maps are silhouette-
  antialiased whenever they are built for gradients (``mi_shadowmap.antialias``;
  property ``antialias``, default ``'gradients'``), which is what gives this motion its
  gradient (without it ours were ~100x too small); each worker reports whether its
  gradient renders' maps were antialiased.
* ``--param along``: every vertex moved along the light ray through it (away from the
  area light's centre, or along the directional light). The outline in the maps stays
  put; the maps change through their depths only. The true derivative is tiny (area
  scene: about -2.8e-5; directional: exactly 0, a hard shadow whose outline does not
  move). On the area scene its sign comes from *which* part of the light each receiver
  point loses (the shading's cosines and distances differ across the light): with the
  visibility made a factor of the unshadowed light (``raytraced``,
  ``light_sample='independent'``, printed as the "factored reference") the exact
  derivative is about +1.2e-5, the opposite sign. Every map method is such a factor,
  so none can get this motion's sign; ``pcss`` matches the factored reference,
  ``vsm`` has its sign but larger (its Chebyshev bound leaks light as the occluder
  nears the receiver), ``pcf``/``bilinear`` give 0 (a hard outline from the light's
  centre does not move).
* ``--param light``: the light moves -- the area light's ``to_world`` translated along
  +x (``mi_shadowmap.light_views.pose``), or the directional scene's sun turned about z
  (radians). The colour loss then also has Mitsuba's own shading terms of the light's
  pose (distance, cosines), in every integrator alike. direct_projective's default
  guiding (``octree``) fails to build for this motion at 128^2 x 16 spp (a warning:
  "Number of leaf nodes exceeds 'max_leaf_count'") and its gradient is then exactly 0
  at every seed; ``--projective-guiding none`` gives the right gradient (``grid``: about
  0.4x of it).

Integrators (all get the same scene, spp, parameter and loss):

* ``shadowmap`` methods (``--methods``), maps rebuilt in the AD graph at every gradient
  (``maps_need_gradients``), antialiased (``antialias`` left at its default). The short
  names are the settings for gradients (measured with this script, 2026-11-30):

  - ``vsm`` = ``vsm:filter_size=4,light_bleeding=0``. The default light-bleeding
    reduction (0.2) clamps the visibility, so its derivative jumps where the Chebyshev
    bound crosses 0.2: 2.5x the spread over seeds, and a mean 3 % off.
  - ``pcf`` = ``pcf:soft_compare=2,sampling=regular``. Compares on an
    antialiased map are blended by coverage, so a narrow smooth compare suffices for a
    moving outline's gradient; a wide one (the former 24 texels) leaks light under the
    occluder and gave moving it *along* the light the wrong sign. Regular taps
    (deterministic) over the pixel's footprint; with the pixel-centre gradients
    (``gradient_at``) this has spread 0.18x ``direct_projective``'s, a mean 0.1 % off
    the reference and 0.13 s a gradient (sixth session; the former ``min_size=4``,
    chosen for per-sample gradients: 0.12x, +2.2 %, 0.24 s).
  - ``pcss`` = ``pcss:soft_compare=2``: the penumbra follows the blocker's depth, so
    the along-the-light narrowing gets the factored reference's derivative.
  - ``bilinear`` = ``bilinear:soft_compare=2,kernel=4``: a fixed 4 x 4-texel box of
    bilinearly weighted compares, deterministic, and its derivative is continuous
    across texels.

  Any other entry is a method spec, e.g. ``"vsm:filter_size=6"``;
* ``direct_projective``: Mitsuba's projective-sampling direct integrator
  (``sppc = sppp = sppi = spp`` through ``mi.render(..., spp=)``; ``guiding`` Mitsuba's
  default, ``octree``, unless ``--projective-guiding``).

Each integrator runs in a fresh subprocess (``--worker``): one warm-up gradient
(compiles), then one gradient per seed, ``mi.render(scene, params, seed=s, spp=)`` +
``dr.backward(loss)``, timed with ``dr.sync_thread()``. Reported:

1. time per gradient: median over the ``--seeds`` runs (warm), and the speed-up
   direct_projective / ours; with ``--time-rounds N``, the median over N interleaved
   rounds of timing-only workers instead (ours, direct_projective, direct_projective,
   ours, ...: a shared machine's changing load then hits all alike);
2. spread: standard deviation of the scalar gradient over the first ``--seeds`` seeds,
   and its ratio to direct_projective's at equal spp; at equal time, the same ratio
   scaled by time, ``(std * sqrt(time / gradient))_ours / (...)_dp`` (averaging ``k``
   gradients divides the std by ``sqrt(k)``: what the std would be for the same
   seconds spent -- not a run at a different spp); the mean over ``--mean-seeds``
   seeds (sign check), with its standard error;
3. peak memory: ``ru_maxrss`` of the worker after the scene is loaded and at the end
   (the difference is what the gradients added);
4. our gradient against central finite differences of our own forward renders (same
   seed on both sides, ``--fd-h``, the maps antialiased in those renders too:
   ``antialias='always'``): the scalar ``t`` (relative error) and a small vector
   (cosine): one offset per corner of the box in the parameter's direction
   (``sideways``/``along``), or the light's translation x, y, z (``light``); plus a
   reference derivative: central differences of ray-traced renders (``shadowmap
   method=raytraced``, ``--ref-spp`` spp, the same seed on both sides, averaged over
   ``--ref-seeds`` seeds): the sign checks use it.

Times depend on the machine's load (direct_projective took 3.4 s per gradient on an
idle 2-core machine and 5.7 s with another job on one core).
"""
from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import time

import numpy as np

T = None   # mi.ScalarTransform4f, set after the import below (workers only import mitsuba)

#: The directional scene's light (as tests/test_differentiable.py).
DIR_LIGHT = np.array([1.0, -1.2, 0.3]) / np.linalg.norm([1.0, -1.2, 0.3])
#: The area scene's light: a 0.6 x 0.6 quad facing down, its centre here.
AREA_CENTRE = np.array([-1.2, 3.0, 0.0])

#: Short names of ``--methods``; any other entry is a method spec of the ``shadowmap``
#: plugin, ``"method:prop=value,..."`` (as ``mi-shadowmap --methods``).
METHODS = {
    "vsm": "vsm:filter_size=4,light_bleeding=0",
    "pcf": "pcf:soft_compare=2,sampling=regular",
    "pcss": "pcss:soft_compare=2",
    "bilinear": "bilinear:soft_compare=2,kernel=4",
}
#: The scene's sampler (``--sampler``), the same for every integrator.
SAMPLERS = ("independent", "stratified", "multijitter", "ldsampler")
PARAM_TEXT = {"sideways": ("occluder moved sideways (+z), across the light",) * 2,
              "along": ("occluder moved along the light",) * 2,
              "light": ("sun turned about z (radians)", "area light translated along +x")}


def method_dict(name: str) -> dict:
    """The integrator dict of a ``--methods`` entry (or ``direct_projective``)."""
    if name == "direct_projective":
        return {"type": "direct_projective"}
    from mi_shadowmap.specs import parse_method_string
    return {"type": "shadowmap", **parse_method_string(METHODS.get(name, name))}


def label(name: str) -> str:
    """``vsm (filter_size 4)`` for a ``--methods`` entry; ``direct_projective`` as is."""
    if name == "direct_projective":
        return name
    d = {k: v for k, v in method_dict(name).items() if k != "type"}
    props = ", ".join(f"{k} {v:g}" if isinstance(v, float) else f"{k} {v}"
                      for k, v in d.items() if k != "method")
    return d["method"] + (f" ({props})" if props else "")


def split_methods(items) -> list:
    """``--methods`` entries: space-separated specs; an entry without ``:`` may also be a
    comma-separated list of names (``vsm,pcf``, as before)."""
    out = []
    for item in items:
        out.extend([m for m in item.split(",") if m] if ":" not in item else [item])
    return out


# ------------------------------------------------------------------------ scenes
def _diffuse(v):
    return {"type": "diffuse", "reflectance": {"type": "rgb", "value": v}}


def welded_cube(to_world, bsdf):
    """The welded occluder: :func:`mi_shadowmap.procedural.box` (8 shared vertices, 12
    outward triangles) placed by ``to_world`` through :func:`mi_shadowmap.scenes.mesh`
    -- the same vertices and faces as a unit ``cube`` shape's corners under
    ``to_world``. (Mitsuba's ``cube`` has 24 vertices: every face a separate quad, so
    every edge is a boundary edge, and direct_projective counts each silhouette edge
    of it twice -- measured: its gradient is 2.0x the finite differences for a
    sideways translation, 1.0x with this mesh.)"""
    from mi_shadowmap.procedural import box
    from mi_shadowmap.scenes import mesh
    v, f, _ = box((1.0, 1.0, 1.0))
    return mesh("occluder", v, f, to_world, bsdf)


def scene_dict(kind, image, spp, occluder="welded", sampler="independent"):
    d = _scene_dict(kind, image, spp)
    d["sensor"]["sampler"] = {"type": sampler, "sample_count": spp}
    if occluder == "welded":
        d["occluder"] = welded_cube(d["occluder"]["to_world"], d["occluder"]["bsdf"])
    return d


def _scene_dict(kind, image, spp):
    import mitsuba as mi
    T = mi.ScalarTransform4f
    d = {
        "type": "scene",
        "ground": {"type": "rectangle", "to_world": T().rotate([1, 0, 0], -90).scale(4),
                   "bsdf": _diffuse(0.7)},
    }
    film = {"type": "hdrfilm", "width": image, "height": image, "rfilter": {"type": "box"}}
    sampler = {"type": "independent", "sample_count": spp}
    if kind == "area":
        d["sensor"] = {"type": "perspective", "fov": 45,
                       "to_world": T().look_at(origin=[0.0, 5.0, 4.5], target=[0.3, 0.0, 0.0],
                                               up=[0, 1, 0]),
                       "sampler": sampler, "film": film}
        # the occluder: a cube (a mesh: 24 vertices, 3 per corner) 1 unit above the ground
        d["occluder"] = {"type": "cube", "bsdf": _diffuse(0.5),
                         "to_world": T().translate([0.0, 1.0, 0.0]).rotate([0, 1, 0], 20)
                         .scale([0.35, 0.1, 0.35])}
        d["light"] = {"type": "rectangle",
                      "to_world": T().translate(AREA_CENTRE.tolist()).rotate([1, 0, 0], 90)
                      .scale(0.3),
                      "emitter": {"type": "area", "radiance": {"type": "rgb", "value": 25.0}}}
    else:   # tests/test_differentiable.py's scene (the box is the occluder)
        d["sensor"] = {"type": "perspective", "fov": 40,
                       "to_world": T().look_at(origin=[0.0, 5.5, 3.0], target=[0.0, 0.0, 0.0],
                                               up=[0, 1, 0]),
                       "sampler": sampler, "film": film}
        d["occluder"] = {"type": "cube", "bsdf": _diffuse(0.55),
                         "to_world": T().translate([0.3, 0.8, -0.6]).scale(0.25)}
        d["slab"] = {"type": "cube", "bsdf": _diffuse(0.5),
                     "to_world": T().translate([-1.0, 0.6, 0.3]).scale([0.35, 0.02, 0.35])}
        d["post"] = {"type": "cube", "bsdf": _diffuse(0.6),
                     "to_world": T().translate([3.8, 1.5, 3.8]).scale([0.05, 1.5, 0.05])}
        d["sun"] = {"type": "directional", "direction": DIR_LIGHT.tolist(),
                    "irradiance": {"type": "rgb", "value": 3.0}}
    return d


def receiver_mask(scene, spp, margin):
    """Ground pixels at least ``margin`` pixels from anything else on screen."""
    import mitsuba as mi
    integ = mi.load_dict({"type": "aov", "aovs": "p:position"})
    img = np.asarray(mi.render(scene, integrator=integ, spp=spp, seed=0))
    from mi_shadowmap.metrics import dilate
    return ~dilate(~(np.abs(img[..., 1]) < 1e-4), margin)


class Occluder:
    """The benchmark's parameter as a function of a scalar ``t`` (``set_scalar(t)``)
    and of a small vector ``theta`` (``set_vector(theta)``, for the finite-difference
    cosine).

    ``along`` / ``sideways``: the occluder's vertices (``occluder.vertex_positions``)
    move by ``t`` along the light ray through each vertex / along +z; ``theta`` holds
    one offset per distinct corner, in the same direction as ``t``'s.
    ``light``: the light moves -- the area light's ``to_world`` is translated by ``t``
    along +x (the directional scene's ``sun.to_world`` is turned by ``t`` radians
    about z); ``theta``: the area light's translation (x, y, z) / the sun's turn about
    (x, z)."""

    def __init__(self, scene, kind, param):
        import mitsuba as mi
        self.params = mi.traverse(scene)
        self.kind, self.param = kind, param
        if param == "light":
            self.key = "light.to_world" if kind == "area" else "sun.to_world"
            self.base_tf = mi.Transform4f(self.params[self.key])
            self.n_corners = 3 if kind == "area" else 2
            self.vector_label = ("light translation (x, y, z)" if kind == "area"
                                 else "sun rotation about (x, z)")
            return
        self.key = "occluder.vertex_positions"
        self.base = np.array(self.params[self.key]).reshape(-1, 3).astype(np.float64)
        _, inv = np.unique(np.round(self.base, 5), axis=0, return_inverse=True)
        self.group = inv.ravel().astype(np.uint32)
        self.n_corners = int(inv.max()) + 1
        if param == "along":        # along the light ray through each vertex
            if kind == "area":
                d = self.base - AREA_CENTRE[None, :]
                self.dirs = d / np.linalg.norm(d, axis=1, keepdims=True)
            else:
                self.dirs = np.tile(DIR_LIGHT, (len(self.base), 1))
        elif param == "sideways":   # horizontal, across the light
            self.dirs = np.tile(np.array([0.0, 0.0, 1.0]), (len(self.base), 1))
        else:
            raise ValueError(param)
        self.vector_label = f"per-corner offsets {param} ({self.n_corners} corners)"

    def _put(self, off, dirs):
        import drjit as dr
        import mitsuba as mi
        v = mi.Point3f(*[mi.Float(self.base[:, i].astype(np.float32))
                         + off * mi.Float(dirs[:, i].astype(np.float32)) for i in range(3)])
        self.params[self.key] = dr.ravel(v)
        self.params.update()

    def _light(self, x, y, z):
        """Area: translate by (x, y, z); directional: turn by x about x, then z about z."""
        import drjit as dr
        import mitsuba as mi
        if self.kind == "area":
            tf = mi.Transform4f().translate(mi.Vector3f(x, y, z)) @ self.base_tf
        else:
            cz, sz = dr.cos(z), dr.sin(z)
            cx, sx = dr.cos(x), dr.sin(x)
            rz = mi.Matrix4f(cz, -sz, 0, 0, sz, cz, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1)
            rx = mi.Matrix4f(1, 0, 0, 0, 0, cx, -sx, 0, 0, sx, cx, 0, 0, 0, 0, 1)
            tf = mi.Transform4f(rz) @ mi.Transform4f(rx) @ self.base_tf
        self.params[self.key] = tf
        self.params.update()

    def set_scalar(self, t):
        """``t``: a Python float or an attached ``mi.Float`` of size 1."""
        import mitsuba as mi
        t = mi.Float(t) if not isinstance(t, mi.Float) else t
        if self.param == "light":
            zero = mi.Float(0.0)
            if self.kind == "area":
                self._light(t, zero, zero)
            else:
                self._light(zero, zero, t)
            return
        self._put(t, self.dirs)

    def set_vector(self, theta):
        import drjit as dr
        import mitsuba as mi
        if not isinstance(theta, mi.Float):
            theta = mi.Float(np.asarray(theta, dtype=np.float32))
        if self.param == "light":
            c = [dr.gather(mi.Float, theta, mi.UInt32(k)) for k in range(self.n_corners)]
            if self.kind == "area":
                self._light(*c)
            else:
                self._light(c[0], mi.Float(0.0), c[1])
            return
        self._put(dr.gather(mi.Float, theta, mi.UInt32(self.group)), self.dirs)


def loss_of(img, weights):
    import drjit as dr
    return dr.sum(img.array * weights)


# ------------------------------------------------------------------------ workers
def _setup(args):
    import mi_shadowmap  # noqa: F401  (variant, registration)
    import drjit as dr  # noqa: F401
    import mitsuba as mi
    if mi.variant() != "llvm_ad_rgb":
        mi.set_variant("llvm_ad_rgb")
    scene = mi.load_dict(scene_dict(args.scene, args.image, args.spp, args.occluder,
                                    args.sampler))
    mask = receiver_mask(scene, args.spp, args.margin)
    occ = Occluder(scene, args.scene, args.param)
    n_ch = 3 + 1   # RGB + shadowmap's visibility AOV; direct_projective has 3 channels
    return scene, mask, occ, n_ch


def _weights(mask, channels):
    import mitsuba as mi
    w = np.zeros(mask.shape + (channels,), np.float32)
    w[..., :3] = mask[..., None] / (3.0 * mask.sum())   # mean colour over the receiver
    return mi.Float(w.ravel())


def _integrator(name, args, antialias=None):
    import mitsuba as mi
    d = method_dict(name)
    if d["type"] == "direct_projective" and args.projective_guiding:
        d["guiding"] = args.projective_guiding
    if d["type"] == "shadowmap":
        d["resolution"] = args.map
        if antialias is not None:
            d["antialias"] = antialias
    return mi.load_dict(d)


def _antialias_state(integ):
    """(the ``antialias`` property, whether the last render's maps were antialiased),
    or (None, None) for an integrator without maps."""
    opts = getattr(integ, "opts", None)
    if opts is None:
        return None, None
    maps = [m for m in (getattr(integ, "maps", None) or []) if m is not None]
    return getattr(opts, "antialias", None), any(m.coverage is not None for m in maps)


def worker_grad(args):
    """Warm-up + one gradient per seed; prints one JSON line."""
    import drjit as dr
    import mitsuba as mi
    scene, mask, occ, _ = _setup(args)
    integ = _integrator(args.worker, args)
    rss_loaded = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    weights = {}

    def gradient(seed):
        t = mi.Float(0.0)
        dr.enable_grad(t)
        occ.set_scalar(t)
        img = mi.render(scene, occ.params, integrator=integ, spp=args.spp, seed=seed)
        c = img.shape[-1]
        if c not in weights:
            weights[c] = _weights(mask, c)
        loss = loss_of(img, weights[c])
        dr.backward(loss)
        g = float(dr.grad(t)[0])
        lv = float(loss[0])
        occ.set_scalar(0.0)   # detached again
        return g, lv

    t0 = time.perf_counter()
    gradient(10_000)          # warm-up (compilation)
    dr.sync_thread()
    warm = time.perf_counter() - t0
    aa_prop, aa_on = _antialias_state(integ)
    grads, losses, times = [], [], []
    for s in range(args.n_seeds):
        t0 = time.perf_counter()
        g, lv = gradient(s)
        dr.sync_thread()
        times.append(time.perf_counter() - t0)
        grads.append(g)
        losses.append(lv)
    out = {"name": args.worker, "grads": grads, "losses": losses, "times": times,
           "first_seconds": warm, "antialias": aa_prop, "antialiased": aa_on,
           "rss_loaded_kb": rss_loaded,
           "rss_peak_kb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss,
           "mask_pixels": int(mask.sum())}
    print("RESULT " + json.dumps(out), flush=True)


def worker_fd(args):
    """AD vs central differences of the same method's forward renders (same seed)."""
    import drjit as dr
    import mitsuba as mi
    scene, mask, occ, _ = _setup(args)
    seed = 1
    if args.worker == "ref":   # ray-traced reference derivatives of the scalar parameter
        # 'shared': the ground truth; 'independent': visibility as a factor of the
        # unshadowed light (the shadow ray to an independent light sample), the ideal
        # of every shadow-map method (the same for delta lights)
        out = {"name": "ref"}
        for mode in ("shared", "independent"):
            integ = mi.load_dict({"type": "shadowmap", "method": "raytraced",
                                  "light_sample": mode})
            w = _weights(mask, 4)
            fds = []
            for s in range(args.ref_seeds):   # the same seed on both sides of each difference
                vals = []
                for sgn in (1.0, -1.0):
                    occ.set_scalar(sgn * args.ref_h)
                    img = mi.render(scene, integrator=integ, spp=args.ref_spp, seed=s + 1)
                    vals.append(float(loss_of(img, w)[0]))
                fds.append((vals[0] - vals[1]) / (2 * args.ref_h))
            occ.set_scalar(0.0)
            key = "" if mode == "shared" else "_factored"
            out["fd_t" + key], out["fds" + key] = float(np.mean(fds)), fds
        print("RESULT " + json.dumps(out), flush=True)
        return
    # 'always': the forward renders of the differences see the antialiased maps the
    # gradients see (with the default 'gradients' a primal render's maps are not
    # antialiased, a different -- piecewise-constant -- function of the outline)
    integ = _integrator(args.worker, args, antialias="always")
    w = _weights(mask, 4)
    h = args.fd_h

    def loss_scalar(t):
        occ.set_scalar(t)
        img = mi.render(scene, integrator=integ, spp=args.spp, seed=seed)
        return float(loss_of(img, w)[0])

    def loss_corners(theta):
        occ.set_vector(theta)
        img = mi.render(scene, integrator=integ, spp=args.spp, seed=seed)
        return float(loss_of(img, w)[0])

    # scalar parameter: AD and FD
    t = mi.Float(0.0)
    dr.enable_grad(t)
    occ.set_scalar(t)
    img = mi.render(scene, occ.params, integrator=integ, spp=args.spp, seed=seed)
    dr.backward(loss_of(img, w))
    g_t = float(dr.grad(t)[0])
    fd_t = (loss_scalar(h) - loss_scalar(-h)) / (2 * h)
    # per-corner offsets along the light
    n = occ.n_corners
    th = mi.Float(np.zeros(n, np.float32))
    dr.enable_grad(th)
    occ.set_vector(th)
    img = mi.render(scene, occ.params, integrator=integ, spp=args.spp, seed=seed)
    dr.backward(loss_of(img, w))
    g_v = dr.grad(th).numpy().astype(np.float64)
    fd_v = []
    for k in range(n):
        e = np.zeros(n)
        e[k] = h
        fd_v.append((loss_corners(e) - loss_corners(-e)) / (2 * h))
    fd_v = np.array(fd_v)
    occ.set_scalar(0.0)
    cos = float(g_v @ fd_v / (np.linalg.norm(g_v) * np.linalg.norm(fd_v) + 1e-30))
    print("RESULT " + json.dumps({"name": args.worker, "ad_t": g_t, "fd_t": fd_t,
                                  "cos": cos, "n": n, "vector": occ.vector_label, "ad_v": g_v.tolist(),
                                  "fd_v": fd_v.tolist()}), flush=True)


# ------------------------------------------------------------------------ driver
def run_worker(args, name, mode, n_seeds=None, timeout=3600):
    cmd = [sys.executable, os.path.abspath(__file__), "--worker", name, "--mode", mode,
           "--scene", args.scene, "--image", str(args.image), "--spp", str(args.spp),
           "--map", str(args.map), "--margin", str(args.margin), "--param", args.param,
           "--occluder", args.occluder, "--sampler", args.sampler,
           *(["--projective-guiding", args.projective_guiding] if args.projective_guiding else []),
           "--fd-h", str(args.fd_h), "--ref-h", str(args.ref_h), "--ref-spp", str(args.ref_spp),
           "--ref-seeds", str(args.ref_seeds),
           "--n-seeds", str(n_seeds or 0)]
    t0 = time.perf_counter()
    p = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
    dt = time.perf_counter() - t0
    # (a Mitsuba warning's colour reset can precede the line's start)
    lines = [l[l.index("RESULT "):] for l in p.stdout.splitlines() if "RESULT {" in l]
    if p.returncode != 0 or not lines:
        msg = (p.stderr or p.stdout).strip().splitlines()[-15:]
        print(f"  worker {name}/{mode} FAILED (exit {p.returncode}, {dt:.0f} s):\n    "
              + "\n    ".join(msg), flush=True)
        return {"name": name, "failed": True, "returncode": p.returncode, "stderr": msg}
    out = json.loads(lines[-1][len("RESULT "):])
    out["wall_seconds"] = dt
    print(f"  worker {name}/{mode}: {dt:.0f} s", flush=True)
    return out


def same_sign(a, b):
    """'yes' / 'NO' for the signs of ``a`` and ``b``; a value below 1e-4 of the other's
    magnitude is zero (e.g. ``pcf``'s +-2e-10 along the light: its kernel does not
    depend on depth), and has no sign."""
    if b is None:
        return "n/a"
    if b == 0:
        return "n/a (reference 0)"
    if abs(a) < 1e-4 * abs(b):
        return "n/a (zero)"
    return "yes" if np.sign(a) == np.sign(b) else "NO"


def fmt(x, digits=4):
    if x is None or (isinstance(x, float) and not np.isfinite(x)):
        return "n/a"
    return f"{x:.{digits}g}"


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scene", default="area,directional",
                    help="area, directional, or both comma-separated (run in turn)")
    ap.add_argument("--image", type=int, default=128, help="film width = height")
    ap.add_argument("--spp", type=int, default=16)
    ap.add_argument("--map", type=int, default=128, help="shadow-map resolution per face "
                    "(128 as tests/test_differentiable.py; at 512, soft_compare 24 is "
                    "narrower than the occluder's depth gap and pcf's gradient is exactly 0)")
    ap.add_argument("--margin", type=int, default=None, help="receiver pixels' distance "
                    "(px) from anything else on screen (default: image / 16, i.e. 8 at 128^2, "
                    "as tests/test_differentiable.py's 2 px at 32^2; at 3 px direct_projective's "
                    "mean was 1.8x the finite-difference reference on the area scene)")
    ap.add_argument("--param", choices=("sideways", "along", "light"), default="sideways",
                    help="the occluder moved across the light (default), along the light, "
                    "or the light moved (area: translation x; directional: turn about z)")
    ap.add_argument("--occluder", choices=("welded", "cube"), default="welded",
                    help="the occluder mesh: 8 shared vertices (default), or Mitsuba's "
                    "'cube' (24 vertices; direct_projective's gradient doubles on it)")
    ap.add_argument("--methods", nargs="+", default=["vsm,pcf"],
                    help="shadowmap methods: short names ("
                    + ", ".join(f"{k} = {v}" for k, v in METHODS.items())
                    + "), comma-separated, or method specs 'method:prop=value,...' "
                    "separated by spaces")
    ap.add_argument("--sampler", choices=SAMPLERS, default="independent",
                    help="the scene's sampler, for every integrator (our gradients are "
                    "integrals over the pixels, which a stratified sampler helps; "
                    "direct_projective's spread is its boundary samples')")
    ap.add_argument("--seeds", type=int, default=8, help="seeds for time and spread")
    ap.add_argument("--mean-seeds", type=int, default=24,
                    help="seeds for the mean (sign check); >= --seeds")
    ap.add_argument("--projective-mean-seeds", type=int, default=None,
                    help="direct_projective's --mean-seeds (default: the same)")
    ap.add_argument("--no-projective", action="store_true")
    ap.add_argument("--projective-guiding", choices=("octree", "grid", "none"), default=None,
                    help="direct_projective's 'guiding' of its indirect-discontinuity samples "
                    "(default: Mitsuba's, 'octree'). For the area light's translation at "
                    "128^2 x 16 spp its octree fails to build ('Number of leaf nodes exceeds "
                    "max_leaf_count', a warning) and its gradient is then exactly 0; 'none' "
                    "gives the right one (and is much faster)")
    ap.add_argument("--time-rounds", type=int, default=0,
                    help="after the main run, this many interleaved rounds of timing-only "
                    "workers (ours, direct_projective, ours, ...; --time-seeds gradients "
                    "each): the time per gradient and speed-up are then the median over "
                    "the rounds' warm gradients (robust to another job's load changing)")
    ap.add_argument("--time-seeds", type=int, default=4, help="gradients per timing worker")
    ap.add_argument("--no-fd", action="store_true")
    ap.add_argument("--fd-h", type=float, default=0.02, help="step of the self-consistency "
                    "finite differences (units; radians for the directional light's turn)")
    ap.add_argument("--ref-h", type=float, default=0.05)
    ap.add_argument("--ref-spp", type=int, default=1024)
    ap.add_argument("--ref-seeds", type=int, default=4, help="seeds averaged by the "
                    "ray-traced finite-difference reference")
    ap.add_argument("--json", default=None)
    # worker mode (internal)
    ap.add_argument("--worker", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--mode", default="grad", help=argparse.SUPPRESS)
    ap.add_argument("--n-seeds", type=int, default=0, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.margin is None:
        args.margin = max(1, args.image // 16)

    if args.worker:
        (worker_grad if args.mode == "grad" else worker_fd)(args)
        return
    allres = {}
    for kind in args.scene.split(","):
        a = argparse.Namespace(**vars(args))
        a.scene = kind
        allres[kind] = run_scene(a)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(allres, f, indent=1)


def run_scene(args):
    methods = split_methods(args.methods)
    mean_seeds = max(args.mean_seeds, args.seeds)
    dp_mean_seeds = max(args.projective_mean_seeds or mean_seeds, args.seeds)
    print(f"# bench_gradients: {args.scene} scene, {args.image}^2, {args.spp} spp, map "
          f"{args.map}, parameter '{args.param}', occluder '{args.occluder}', sampler "
          f"'{args.sampler}', "
          f"direct_projective guiding '{args.projective_guiding or 'octree (default)'}', {args.seeds} "
          f"seeds (spread), "
          f"{mean_seeds}/{dp_mean_seeds} seeds (mean: ours/direct_projective)", flush=True)
    res = {"args": vars(args), "grad": {}, "fd": {}}
    t_start = time.perf_counter()
    for m in methods:
        res["grad"][m] = run_worker(args, m, "grad", mean_seeds)
    if not args.no_projective:
        res["grad"]["direct_projective"] = run_worker(args, "direct_projective", "grad",
                                                      dp_mean_seeds)
    if not args.no_fd:
        for m in methods:
            res["fd"][m] = run_worker(args, m, "fd")
        res["fd"]["ref"] = run_worker(args, "ref", "fd")
    rounds = {}
    if args.time_rounds > 0:
        names = methods + ([] if args.no_projective else ["direct_projective"])
        for k in range(args.time_rounds):
            for m in (names if k % 2 == 0 else names[::-1]):   # interleaved
                r = run_worker(args, m, "grad", args.time_seeds)
                if not r.get("failed"):
                    rounds.setdefault(m, []).extend(r["times"])
    res["time_rounds"] = rounds
    res["total_seconds"] = time.perf_counter() - t_start

    # ---------------------------------------------------------------- tables
    G = res["grad"]
    dp = G.get("direct_projective")
    dp_ok = dp is not None and not dp.get("failed")
    n = args.seeds

    def stats(r):
        g = np.array(r["grads"])
        t = float(statistics.median(rounds.get(r["name"]) or r["times"][:n]))
        sd = float(np.std(g[:n], ddof=1))
        mean = float(g.mean())
        se = float(np.std(g, ddof=1) / np.sqrt(len(g)))
        return t, sd, mean, se, len(g)

    ref_t = res["fd"].get("ref", {}).get("fd_t")
    print()
    print(f"Scene: {args.scene} light, {args.image}x{args.image}, {args.spp} spp; parameter: "
          f"{PARAM_TEXT[args.param][args.scene == 'area']} (scalar t, d loss / d t at t = 0); loss: "
          f"mean colour over {next((r['mask_pixels'] for r in G.values() if 'mask_pixels' in r), '?')}"
          f" receiver pixels.")
    print()
    if rounds:
        print(f"Times: median of {args.time_rounds} interleaved rounds x {args.time_seeds} "
              "warm gradients (timing-only workers); the main run's own medians: "
              + ", ".join(f"{m} {statistics.median(r['times'][:n]):.3f} s"
                          for m, r in G.items() if not r.get("failed")) + ".")
    print("| integrator | time / gradient (median, s) | speed-up vs dp | "
          f"std over {n} seeds | std ratio (ours / dp), equal spp | std ratio, equal time "
          f"| mean ({mean_seeds} / {dp_mean_seeds} seeds) | std. error of mean | sign = dp mean? "
          "| sign = reference? | first gradient (compiles or reads the kernel cache), s |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    dp_stats = stats(dp) if dp_ok else None

    for m, r in G.items():
        if r.get("failed"):
            print(f"| {label(m)} | failed (exit {r['returncode']}) | | | | | | | | | |")
            continue
        t, sd, mean, se, k = stats(r)
        if m == "direct_projective" or dp_stats is None:
            sp, ratio, ratio_t, sign = ("1" if m == "direct_projective" else "n/a"), "-", "-", "-"
        else:
            sp = f"{dp_stats[0] / t:.1f}x"
            ok = dp_stats[1] > 0
            ratio = f"{sd / dp_stats[1]:.3f}" if ok else "n/a"
            # equal time: averaging k gradients divides the std by sqrt(k)
            ratio_t = (f"{sd * np.sqrt(t) / (dp_stats[1] * np.sqrt(dp_stats[0])):.3f}"
                       if ok else "n/a")
            sign = same_sign(mean, dp_stats[2])
        print(f"| {label(m)} | {t:.3f} | {sp} | {fmt(sd)} | {ratio} | {ratio_t} | {fmt(mean)} "
              f"| {fmt(se, 2)} | {sign} | {same_sign(mean, ref_t)} | {r['first_seconds']:.1f} |")
    for m, r in G.items():
        if not r.get("failed") and r.get("antialias") is not None:
            print(f"{label(m)}: property antialias = '{r['antialias']}'; the gradient "
                  f"renders' maps {'were' if r['antialiased'] else 'were NOT'} antialiased.")
    if ref_t is not None:
        fds = np.array(res["fd"]["ref"]["fds"])
        se = float(np.std(fds, ddof=1) / np.sqrt(len(fds))) if len(fds) > 1 else float("nan")
        print(f"\nReference derivative (central differences of ray-traced renders, "
              f"{args.ref_spp} spp, h = {args.ref_h}, the same seed on both sides, mean of "
              f"{len(fds)} seeds): {fmt(ref_t)} (std. error {fmt(se, 2)})")
        if "fds_factored" in res["fd"]["ref"]:
            f2 = np.array(res["fd"]["ref"]["fds_factored"])
            se2 = float(np.std(f2, ddof=1) / np.sqrt(len(f2))) if len(f2) > 1 else float("nan")
            print(f"Factored reference (the same, raytraced light_sample='independent': "
                  f"visibility a factor of the unshadowed light, the ideal of every map "
                  f"method): {fmt(float(f2.mean()))} (std. error {fmt(se2, 2)})")
            for m, r in G.items():
                if m != "direct_projective" and not r.get("failed"):
                    print(f"  {label(m)}: sign = factored reference? "
                          f"{same_sign(float(np.mean(r['grads'])), float(f2.mean()))}")

    print()
    print("| integrator | peak RSS after scene load (MiB) | peak RSS at end (MiB) | added by the gradients (MiB) |")
    print("|---|---|---|---|")
    for m, r in G.items():
        if r.get("failed"):
            continue
        a, b = r["rss_loaded_kb"] / 1024, r["rss_peak_kb"] / 1024
        print(f"| {label(m)} | {a:.0f} | {b:.0f} | {b - a:.0f} |")

    if res["fd"]:
        print()
        lab = next((r.get("vector") for r in res["fd"].values() if r.get("vector")), "vector")
        print(f"| method | AD d loss/dt (seed 1) | central FD (h = {args.fd_h}, seed 1, "
              f"antialias 'always') | rel. error | cosine, AD vs FD, {lab} "
              "| sign = reference? |")
        print("|---|---|---|---|---|---|")
        for m in methods:
            r = res["fd"].get(m)
            if r is None or r.get("failed"):
                print(f"| {label(m)} | failed | | | | |")
                continue
            rel = abs(r["ad_t"] - r["fd_t"]) / max(abs(r["fd_t"]), 1e-30)
            sgn = same_sign(r["ad_t"], ref_t)
            print(f"| {label(m)} | {fmt(r['ad_t'])} | {fmt(r['fd_t'])} | {rel:.3f} | "
                  f"{r['cos']:.4f} | {sgn} |")
    print(f"\nTotal {res['total_seconds']:.0f} s.\n")
    return res


if __name__ == "__main__":
    main()
