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
  recording the parameter, the loss and the time of every step.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import drjit as dr
import mitsuba as mi
import numpy as np

from .procedural import box
from .scenes import mesh

T = mi.ScalarTransform4f
#: Where :func:`occluder_scene` puts the light (the area light's centre).
LIGHT_POSITION = (-1.2, 3.0, 0.0)
#: The ground's side (the scene's size, for tolerances relative to it).
SCENE_SIZE = 8.0


def _diffuse(v):
    return {"type": "diffuse", "reflectance": {"type": "rgb", "value": v}}


def occluder_scene(light: str = "area", image: int = 64, spp: int = 8,
                   light_position=LIGHT_POSITION) -> mi.Scene:
    """A flat welded box 1 unit above an 8 x 8 ground, one light above, a camera
    looking down at the shadow (``image`` pixels square, ``spp`` samples).

    ``light``: 'area' (a 0.6 x 0.6 quad facing down), 'point', 'spot' (facing down,
    its cone over the whole ground in view) or 'directional' (along the
    light-to-occluder direction).
    """
    v, f, _ = box((0.35, 0.1, 0.35))
    d = {
        "type": "scene",
        "sensor": {"type": "perspective", "fov": 45,
                   "to_world": T().look_at(origin=[0.0, 5.0, 4.5], target=[0.3, 0.0, 0.0],
                                           up=[0, 1, 0]),
                   "sampler": {"type": "independent", "sample_count": spp},
                   "film": {"type": "hdrfilm", "width": image, "height": image,
                            "rfilter": {"type": "box"}}},
        "ground": {"type": "rectangle", "to_world": T().rotate([1, 0, 0], -90).scale(4),
                   "bsdf": _diffuse(0.7)},
        "occluder": mesh("occluder", v, f,
                         T().translate([0.0, 1.0, 0.0]).rotate([0, 1, 0], 20), _diffuse(0.5)),
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


def receiver_mask(scene: mi.Scene, margin: int = 4, spp: int = 4) -> np.ndarray:
    """Ground pixels (``y = 0``) at least ``margin`` pixels from anything else on
    screen: ``(height, width)`` bool."""
    from .metrics import dilate
    integ = mi.load_dict({"type": "aov", "aovs": "p:position"})
    img = np.asarray(mi.render(scene, integrator=integ, spp=spp, seed=0))
    ground = np.abs(img[..., 1]) < 1e-4
    return ~dilate(~ground, margin)


def masked_mse(image, target, mask: np.ndarray, channels: int = 3):
    """Mean squared error of the first ``channels`` channels of ``image`` against
    ``target`` (same shape; a ``mi.TensorXf`` or numpy array) over ``mask``."""
    n_ch = image.shape[-1]
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
             lr: float = 0.02, spp: int | None = None, seed: int = 0, callback=None) -> History:
    """Adam (``mi.ad.Adam``) on ``param`` from ``x0`` against ``target`` with
    :func:`masked_mse` over ``mask``; a new seed every step. ``callback(step,
    history)`` after each step (e.g. a progress bar). The scene is left at the
    final value."""
    opt = mi.ad.Adam(lr=lr)
    opt["x"] = mi.Float(np.asarray(x0, np.float32).ravel())
    hist = History()
    t0 = time.perf_counter()
    for step in range(steps):
        param.set(opt["x"])
        img = mi.render(param.scene, param.params, integrator=integrator, spp=spp or 0,
                        seed=seed + step)
        loss = masked_mse(img, target, mask)
        dr.backward(loss)
        opt.step()
        hist.loss.append(float(loss[0]))
        hist.x.append(np.array(opt["x"]).ravel().copy())
        hist.seconds.append(time.perf_counter() - t0)
        if callback is not None:
            callback(step, hist)
    param.set(hist.x[-1])
    return hist
