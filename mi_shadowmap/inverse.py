"""Inverse problems driven by shadows (issue 13): a scene, a loss, an Adam loop.

The pieces the tests, ``notebooks/08_differentiable_shadows.ipynb`` and
``benchmarks/bench_gradients.py`` share:

* :func:`occluder_scene` -- a ground, a welded box occluder (a mesh: its
  outline is antialiased in the maps, :mod:`mi_shadowmap.antialias`) and one
  light (``area``, ``point``, ``spot`` or ``directional``);
* :func:`receiver_mask` -- the pixels of the receiving ground at least
  ``margin`` pixels from anything else on screen, so that a loss on them
  sees shadows only, never the occluder's own silhouette or shading (which
  would give the answer away, and which is Mitsuba's projective
  integrators' job, not this plugin's);
* :class:`Parameter` -- a named value of the scene driven by a small vector
  (an occluder's translation, a light's position);
* :func:`optimize` -- ``mi.ad.Adam`` on a parameter against a target image,
  recording the parameter, the loss and the time of every step;
* :class:`Problem`, :func:`occluder_problem`, :func:`light_problem`,
  :func:`shadow_art_problem` and :func:`solve` -- a whole inverse problem (scene,
  mask, ray-traced target, parameter, start) solved by any integrator given as a
  dict, with :func:`integrator` and :func:`render`, so that the notebook needs
  neither ``mitsuba`` nor ``drjit``.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import drjit as dr
import mitsuba as mi
import numpy as np

from .procedural import box
from .scenes import camera, load_scene, mesh
from .specs import derived_seed

T = mi.ScalarTransform4f
#: Where :func:`occluder_scene` puts the light (the area light's centre).
LIGHT_POSITION = (-1.2, 3.0, 0.0)
#: The ground's side (the scene's size, for tolerances relative to it).
SCENE_SIZE = 8.0


def _diffuse(v):
    return {"type": "diffuse", "reflectance": {"type": "rgb", "value": v}}


def occluder_scene(light: str = "area", image: int = 64, spp: int = 8,
                   light_position=LIGHT_POSITION, occluder=None) -> mi.Scene:
    """A flat welded box 1 unit above an 8 x 8 ground, one light above, a camera
    looking down at the shadow (``image`` pixels square, ``spp`` samples).

    ``light``: 'area' (a 0.6 x 0.6 quad facing down), 'point', 'spot' (facing down,
    its cone over the whole ground in view) or 'directional' (along the
    light-to-occluder direction). ``occluder``: ``(vertices, faces)`` of another
    mesh, placed as given (default: the box, 1 unit up, turned 20 degrees).
    """
    v, f, _ = box((0.35, 0.1, 0.35))
    to_world = T().translate([0.0, 1.0, 0.0]).rotate([0, 1, 0], 20)
    if occluder is not None:
        (v, f), to_world = occluder, None
    d = {
        "type": "scene",
        "sensor": camera([0.0, 5.0, 4.5], [0.3, 0.0, 0.0], image, image, spp, fov=45.0),
        "ground": {"type": "rectangle", "to_world": T().rotate([1, 0, 0], -90).scale(4),
                   "bsdf": _diffuse(0.7)},
        "occluder": mesh("occluder", v, f, to_world, _diffuse(0.5)),
    }
    p = [float(x) for x in light_position]
    if light == "area":
        d["light"] = {"type": "rectangle",
                      "to_world": T().translate(p).rotate([1, 0, 0], 90).scale(0.3),
                      "emitter": {"type": "area", "radiance": {"type": "rgb", "value": 25.0}}}
    elif light == "point":
        d["light"] = {"type": "point", "position": p,
                      "intensity": {"type": "rgb", "value": 20.0}}
    elif light == "spot":
        # straight down, its cone (70 degrees) over the whole ground the camera sees
        d["light"] = {"type": "spot", "to_world": T().look_at(p, [p[0], 0.0, p[2]], [0, 0, 1]),
                      "cutoff_angle": 70.0, "beam_width": 60.0,
                      "intensity": {"type": "rgb", "value": 20.0}}
    elif light == "directional":
        d["light"] = {"type": "directional", "direction": [-p[0], 1.0 - p[1], -p[2]],
                      "irradiance": {"type": "rgb", "value": 3.0}}
    else:
        raise ValueError(f"occluder_scene: light={light!r}; valid: area, point, spot, "
                         "directional")
    return mi.load_dict(d)


def _current(scene):
    """``scene`` if it is the current variant's ``mi.Scene``; another variant's (loaded
    before ``mi.set_variant``) is an error naming both variants (``mi.render`` failed on
    it with a bare AssertionError)."""
    return scene if isinstance(scene, mi.Scene) else load_scene(scene)


def receiver_mask(scene: mi.Scene, margin: int = 4, spp: int = 4) -> np.ndarray:
    """Ground pixels (``y = 0``) at least ``margin`` pixels from anything else on
    screen: ``(height, width)`` bool."""
    from .metrics import dilate
    integ = mi.load_dict({"type": "aov", "aovs": "p:position"})
    img = np.asarray(mi.render(_current(scene), integrator=integ, spp=spp, seed=0))
    ground = np.abs(img[..., 1]) < 1e-4
    return ~dilate(~ground, margin)


def masked_mse(image, target, mask: np.ndarray, channels: int | None = None):
    """Mean squared error of the first ``channels`` channels of ``image`` against
    ``target`` (a ``mi.TensorXf`` or numpy array of the same size, or with more
    channels: only the image's first ones are read) over ``mask``. Default: the colour
    channels of the current variant's film (3; 1 in a monochromatic variant), never the
    AOVs behind them (in mono, 3 took the visibility AOV into the loss: ``vsm``'s
    gradient of :func:`occluder_problem` was 9x rgb's, driven by the AOV)."""
    if channels is None:
        channels = 1 if mi.is_monochromatic else 3
    n_ch = image.shape[-1]
    target = np.asarray(target, np.float32)[..., :n_ch]
    w = np.zeros(mask.shape + (n_ch,), np.float32)
    w[..., :channels] = mask[..., None]
    w /= max(float(mask.sum()) * channels, 1.0)
    target = mi.Float(np.asarray(target, np.float32).ravel())
    return dr.sum(dr.square(image.array - target) * mi.Float(w.ravel()))


@dataclass
class Parameter:
    """A scene value driven by a vector ``x`` (numpy or an attached ``mi.Float``):
    ``key`` in ``mi.traverse(scene)`` and ``apply(base, x) -> value``, ``base`` the
    parameter's value when this was made (a copy, of the parameter's type)."""
    scene: mi.Scene
    key: str
    apply: object
    size: int
    params: object = field(init=False)
    base: object = field(init=False)

    def __post_init__(self):
        self.params = mi.traverse(self.scene)
        value = self.params[self.key]
        self.base = type(value)(dr.detach(value))   # a copy, of the parameter's type

    def set(self, x) -> None:
        self.params[self.key] = self.apply(self.base, x)
        self.params.update()

    def reset(self) -> None:
        self.set(np.zeros(self.size))


def _vec(x, k: int):
    """Component ``k`` of ``x``: attached (``mi.Float``) or a Python float."""
    if isinstance(x, mi.Float):
        return dr.gather(mi.Float, x, mi.UInt32(k))
    return float(np.asarray(x, np.float64).ravel()[k])


def translate_shape(scene: mi.Scene, name: str = "occluder", axes: str = "xz") -> Parameter:
    """A translation of mesh ``name`` along ``axes`` (e.g. 'xz', 'x', 'xyz')."""
    idx = ["xyz".index(a) for a in axes]

    def apply(base, x):
        v = np.array(base).reshape(-1, 3)
        comps = []
        for c in range(3):
            col = mi.Float(v[:, c].astype(np.float32))
            if c in idx:
                col = col + _vec(x, idx.index(c))
            comps.append(col)
        return dr.ravel(mi.Point3f(*comps))
    return Parameter(scene, f"{name}.vertex_positions", apply, len(idx))


def light_position(scene: mi.Scene, name: str = "light") -> Parameter:
    """A point light's ``position`` offset by ``x`` (3 values)."""
    def apply(base, x):
        b = np.asarray(base, np.float64).ravel()
        return mi.Point3f(*[mi.Float(float(b[c])) + _vec(x, c) for c in range(3)])
    return Parameter(scene, f"{name}.position", apply, 3)


@dataclass
class History:
    """Per step: the parameter after the step, the loss before it, seconds since start."""
    x: list = field(default_factory=list)
    loss: list = field(default_factory=list)
    seconds: list = field(default_factory=list)

    def as_arrays(self):
        return np.array(self.x), np.array(self.loss), np.array(self.seconds)


def optimize(param: Parameter, integrator, target, mask: np.ndarray, x0, steps: int = 100,
             lr: float = 0.02, spp: int | None = None, seed: int = 0, callback=None,
             penalty=None) -> History:
    """Adam (``mi.ad.Adam``) on ``param`` from ``x0`` against ``target`` with
    :func:`masked_mse` over ``mask`` (plus ``penalty(x)``, a ``mi.Float``, if
    given); a new seed every step (``seed + step`` within [0, 2^32),
    :func:`~mi_shadowmap.specs.derived_seed`). ``callback(step, history)`` after each step
    (e.g. a progress bar). The scene is left at the final value."""
    _current(param.scene)
    opt = mi.ad.Adam(lr=lr)
    opt["x"] = mi.Float(np.asarray(x0, np.float32).ravel())
    hist = History()
    t0 = time.perf_counter()
    for step in range(steps):
        param.set(opt["x"])
        img = mi.render(param.scene, param.params, integrator=integrator, spp=spp or 0,
                        seed=derived_seed(seed, step))
        loss = masked_mse(img, target, mask)
        if penalty is not None:
            loss = loss + penalty(opt["x"])
        dr.backward(loss)
        opt.step()
        hist.loss.append(float(loss[0]))
        hist.x.append(np.array(opt["x"]).ravel().copy())
        hist.seconds.append(time.perf_counter() - t0)
        if callback is not None:
            callback(step, hist)
    param.set(hist.x[-1])
    return hist


# ------------------------------------------------------------------ whole problems, for notebooks
def integrator(spec: dict) -> mi.Integrator:
    """An integrator from its dict, e.g. ``{'type': 'shadowmap', 'method': 'vsm'}``
    or ``{'type': 'direct_projective'}`` (``mi.load_dict``)."""
    return mi.load_dict(dict(spec))


def render(scene: mi.Scene, spec: dict, spp: int = 16, seed: int = 0) -> np.ndarray:
    """``scene`` rendered by the integrator ``spec``: ``(height, width, channels)``
    numpy (``shadowmap`` adds a visibility channel to RGB)."""
    return np.array(mi.render(_current(scene), integrator=integrator(spec), spp=spp,
                              seed=seed))


#: The ground truth of every target: real shadow rays.
RAYTRACED = {"type": "shadowmap", "method": "raytraced"}


@dataclass
class Problem:
    """An inverse problem: ``param`` of ``scene`` is at its true value when ``x``
    is ``truth``; ``target`` is the scene rendered by :data:`RAYTRACED` there,
    ``mask`` the pixels the loss reads, ``x0`` the start, ``penalty`` an optional
    regulariser for :func:`optimize`. :meth:`errors` measures a run."""
    scene: mi.Scene
    mask: np.ndarray
    target: np.ndarray
    param: Parameter
    x0: np.ndarray
    truth: np.ndarray
    penalty: object = None

    def errors(self, history: History) -> np.ndarray:
        """``|x - truth|`` after every step of ``history`` (scene units)."""
        x, _, _ = history.as_arrays()
        return np.linalg.norm(x - self.truth, axis=1)


def _problem(scene, param, x0, truth=None, target_spp=256, margin=4, penalty=None):
    mask = receiver_mask(scene, margin)
    truth = np.zeros(param.size) if truth is None else np.asarray(truth, np.float64)
    param.set(truth)
    target = render(scene, RAYTRACED, target_spp, seed=7)
    param.set(x0)
    return Problem(scene, mask, target, param, np.asarray(x0, np.float64), truth, penalty)


def occluder_problem(light: str = "area", image: int = 64, spp: int = 8,
                     offset=(0.24, -0.18), target_spp: int = 256) -> Problem:
    """The box of :func:`occluder_scene` translated in ``x`` and ``z``, starting
    ``offset`` away (0.3 units by default) from where the target was rendered."""
    scene = occluder_scene(light, image, spp)
    return _problem(scene, translate_shape(scene, axes="xz"), offset, target_spp=target_spp)


def light_problem(image: int = 64, spp: int = 8, offset=(0.5, 0.3, -0.4),
                  target_spp: int = 256) -> Problem:
    """A point light's ``position`` (3 values), starting ``offset`` away (0.71
    units, 9 % of :data:`SCENE_SIZE`, by default)."""
    scene = occluder_scene("point", image, spp)
    return _problem(scene, light_position(scene), offset, target_spp=target_spp)


def solve(problem: Problem, spec: dict, steps: int = 100, lr: float = 0.02,
          spp: int | None = None, seed: int = 0, callback=None) -> History:
    """:func:`optimize` ``problem`` from its start with the integrator ``spec``."""
    return optimize(problem.param, integrator(spec), problem.target, problem.mask,
                    problem.x0, steps, lr, spp, seed, callback, problem.penalty)


# ------------------------------------------------------------------ shadow art, a mesh version
def grid_square(n: int = 7, half: float = 0.5, height: float = 1.0):
    """A flat ``n x n``-vertex grid over ``[-half, half]^2`` at ``y = height``:
    ``(vertices (n*n, 3), faces, edges)``, ``edges`` the ``(E, 2)`` grid lines
    (neighbouring vertices), for :func:`smoothness`."""
    u = np.linspace(-half, half, n)
    xx, zz = np.meshgrid(u, u, indexing="ij")
    v = np.stack([xx.ravel(), np.full(n * n, height), zz.ravel()], 1).astype(np.float32)
    k = np.arange(n * n).reshape(n, n)
    a, b, c, d = k[:-1, :-1].ravel(), k[1:, :-1].ravel(), k[1:, 1:].ravel(), k[:-1, 1:].ravel()
    faces = np.concatenate([np.stack([a, c, b], 1), np.stack([a, d, c], 1)]).astype(np.int32)
    edges = np.concatenate([np.stack([k[:-1].ravel(), k[1:].ravel()], 1),
                            np.stack([k[:, :-1].ravel(), k[:, 1:].ravel()], 1)])
    return v, faces, edges


def square_to_disk(xz: np.ndarray, half: float, radius: float) -> np.ndarray:
    """The elliptical grid mapping of the square ``[-half, half]^2`` onto the disk of
    ``radius``: ``(N, 2)`` in, ``(N, 2)`` out (the square's outline onto the circle)."""
    u, v = xz[:, 0] / half, xz[:, 1] / half
    return radius * np.stack([u * np.sqrt(1 - v * v / 2), v * np.sqrt(1 - u * u / 2)], 1)


def offset_vertices(scene: mi.Scene, name: str = "occluder") -> Parameter:
    """In-plane (``x``, ``z``) offsets of every vertex of mesh ``name``: ``x`` holds
    ``2 * vertex_count`` values, ``(dx, dz)`` per vertex."""
    n = scene_shape(scene, name).vertex_count()

    def apply(base, x):
        v = np.array(base).reshape(-1, 3)
        i = mi.UInt32(np.arange(n, dtype=np.uint32))
        if isinstance(x, mi.Float):
            dx, dz = dr.gather(mi.Float, x, 2 * i), dr.gather(mi.Float, x, 2 * i + 1)
        else:
            x = np.asarray(x, np.float32).reshape(n, 2)
            dx, dz = mi.Float(x[:, 0]), mi.Float(x[:, 1])
        return dr.ravel(mi.Point3f(mi.Float(v[:, 0]) + dx, mi.Float(v[:, 1]),
                                   mi.Float(v[:, 2]) + dz))
    return Parameter(scene, f"{name}.vertex_positions", apply, 2 * n)


def scene_shape(scene: mi.Scene, name: str) -> mi.Shape:
    """The shape of ``scene`` whose id is ``name``."""
    return next(s for s in scene.shapes() if s.id() == name)


def smoothness(edges: np.ndarray, weight: float = 1.0):
    """A regulariser for :func:`offset_vertices`: ``weight`` times the mean squared
    difference of the offsets of the vertices joined by ``edges`` (``x -> mi.Float``).
    It carries the outline's motion into the interior, so triangles do not fold."""
    a, b = (mi.UInt32(np.asarray(e, np.uint32)) for e in np.asarray(edges).T)

    def penalty(x):
        d = [dr.gather(mi.Float, x, 2 * a + c) - dr.gather(mi.Float, x, 2 * b + c)
             for c in (0, 1)]
        return weight * dr.sum(dr.square(d[0]) + dr.square(d[1])) / (2 * len(edges))
    return penalty


#: Where :func:`shadow_art_problem` puts its point light: low and to the side, so
#: that the shadow (1.8x the occluder) lies on the ground clear of the occluder.
ART_LIGHT = (-2.0, 2.2, 0.0)


def shadow_art_problem(image: int = 64, spp: int = 8, n: int = 7, radius: float = 0.6,
                       weight: float = 1.0, target_spp: int = 256) -> Problem:
    """Shadow art on a mesh: a flat ``n x n`` grid (a unit square, 1 unit up) under
    the point light :data:`ART_LIGHT`; its vertices' in-plane offsets
    (:func:`offset_vertices`) start at 0 and should make its shadow the shadow of a
    disk of ``radius`` (the target: the grid mapped onto the disk,
    :func:`square_to_disk`, which is ``truth``). ``penalty``: :func:`smoothness`.
    Only the outline decides the shadow: :meth:`Problem.errors` tells little; read
    :func:`outline_error`."""
    v, f, edges = grid_square(n)
    scene = occluder_scene("point", image, spp, ART_LIGHT, occluder=(v, f))
    truth = (square_to_disk(v[:, [0, 2]], 0.5, radius) - v[:, [0, 2]]).ravel()
    return _problem(scene, offset_vertices(scene), np.zeros(2 * n * n), truth,
                    target_spp, penalty=smoothness(edges, weight))


def outline_error(problem: Problem, history: History, radius: float = 0.6) -> np.ndarray:
    """After every step: the mean distance of the grid's outline vertices from the
    target circle of ``radius`` (scene units)."""
    x, _, _ = history.as_arrays()
    v = np.array(problem.param.base).reshape(-1, 3)[:, [0, 2]]
    n = int(round(np.sqrt(len(v))))
    k = np.arange(n * n).reshape(n, n)
    rim = np.unique(np.concatenate([k[0], k[-1], k[:, 0], k[:, -1]]))
    p = v[None, rim] + x.reshape(len(x), -1, 2)[:, rim]
    return np.abs(np.linalg.norm(p, axis=2) - radius).mean(axis=1)


def gradient(problem: Problem, spec: dict, x=None, spp: int = 16, seed: int = 0) -> np.ndarray:
    """The gradient of :func:`masked_mse` (plus ``problem.penalty``) with respect to
    ``x`` (default: the start), with the integrator ``spec``: numpy. Leaves the scene
    at the start."""
    _current(problem.scene)
    x = mi.Float(np.asarray(problem.x0 if x is None else x, np.float32).ravel())
    dr.enable_grad(x)
    problem.param.set(x)
    img = mi.render(problem.scene, problem.param.params, integrator=integrator(spec),
                    spp=spp, seed=seed)
    loss = masked_mse(img, problem.target, problem.mask)
    if problem.penalty is not None:
        loss = loss + problem.penalty(x)
    dr.backward(loss)
    g = dr.grad(x).numpy()
    problem.param.set(problem.x0)
    return g
