"""Shadowed environment light: Debevec's median cut into ``K`` directional regions.

``environment='shadowed'`` (the default) splits an environment emitter
(``envmap`` or ``constant``) into ``env_lights`` (K) regions with Debevec's
median cut (*A Median Cut Algorithm for Light Probe Sampling*, 2005) and
shadows each region with one orthographic depth map along its centroid
direction; all K maps live in one :class:`EnvironmentView` (a
:class:`~mi_shadowmap.light_views.multi.MultiView` of K orthographic
sub-views).

**Virtual maps** (``virtual`` true or automatic, the default, for K <=
:data:`MAX_VIRTUAL_REGIONS`): region ``k`` is face ``k`` of one virtual map
(:mod:`mi_shadowmap.virtual`), with the float64 interface of a virtual map's view
(:meth:`EnvironmentView.ray_through_f64` for the page build, per texel's face;
:class:`RegionView`'s for the lookups, per lane's region: the shading loop's). The
mark pass projects every camera point into every region
(:meth:`EnvironmentView.mark_views`; all regions in one kernel,
:meth:`EnvironmentView.mark_lanes`) that can light it: whose directions reach
above the point's horizon (its normal facing the camera; the region's largest angle
from its centroid plus :data:`MARK_SLACK`; either side's horizon where the point's BSDF
transmits light), so a region behind a wall or below the ground builds no page there;
each marks the pages of the point's pixel footprint as for a directional light. A
region's lookup that finds its page missing (a shading normal beyond the slack) walks
to a coarser level as every virtual lookup does. On
sky_sun (16 regions, 64^2 film) the first frame casts 76 texels per film pixel
against the full maps' 484, with the same visibility against 256 shadow rays per
camera sample (``tests/test_environment.py``). More than 32 regions keep full maps
(a page key has 5 bits of face). Full maps (``virtual=false``) are planned, budgeted
and cached by the map manager like every map.

**The cut** (:func:`median_cut`, numpy, at set-up; cached per emitter parameters
and K). The emitter's radiance is evaluated (``emitter.eval``, so whatever the
variant -- rgb, mono, spectral at four fixed wavelengths -- and whatever the
emitter: a ``constant`` one is uniform) over the cells of an ``H x W``
latitude-longitude grid (cells of half an envmap texel, :data:`GRID_REFINE`, or of
one texel past :data:`MAX_REFINED_CELLS`; 32 x 64 for ``constant``, finer for an emitter
without texels whose energy that grid misses, e.g. ``sunsky``'s sun: :func:`cut_grid`), in
Mitsuba's envmap convention (``u = atan2(d.x, -d.z)
/ 2 pi``, ``v = acos(d.y) / pi`` in the emitter's frame, row 0 at the zenith): a
cell's luminance is the mean of its centre and four corners, its energy that
times its solid angle (``sin theta`` weighting). "Texel" below means a cell.
Starting from the whole map, the region of largest energy that can be split
(more than one texel) is cut across its longer angular side (width
``d_phi sin(theta_mid)`` against height ``d_theta``) at the texel boundary
closest to the median of its energy -- Debevec's rule, one region at a time, so
any K works (for K a power of two on an even map it is Debevec's
all-regions-per-round cut; an emitter with no energy at all is cut by solid angle, as
a uniform one is). Per region: the ``(u, v)`` rectangle, its solid
angle ``2 pi du (cos theta0 - cos theta1)`` (they sum to 4 pi), its energy,
its luminance-weighted centroid direction in world space (through the emitter's
``to_world``) and its *angular diameter*: the diameter of the uniform disc with
the same luminance-weighted second moment of the angle to the centroid,
``2 sqrt(2 E[delta^2])`` (a uniform disc of angular radius ``r`` has
``E[delta^2] = r^2 / 2``), so a region holding a piece of the sun reports the
sun piece's extent, not the dark sky around it.

**Shading** (:func:`shade`, every map method through its ordinary lookup).
One ``dr.while_loop`` over the K regions (one kernel for any K; compile time
does not grow with K). For region ``k``: one direction ``d`` importance-sampled
inside the region: a cell by a pmf (90 % proportional to the cell's largest
luminance among its centre and corners times its solid angle -- Mitsuba
interpolates the map bilinearly, so a dark cell beside the sun is bright at its
edge -- and :data:`UNIFORM_SHARE` = 10 % proportional to solid angle, so every
direction of the region has a positive density), then uniformly in the cell's
solid angle (``phi`` uniform, ``cos theta`` uniform), from one 2-D sample per
camera sample shifted per region by a fixed R2 offset (Cranley--Patterson:
every region's sample has the right density, the K samples of one camera
sample are decorrelated); radiance ``emitter.eval`` in ``d`` (exact in every
variant); contribution ``L(d) f(wo) / pdf(d)`` (the BSDF value includes the
cosine). (Uniform sampling in the region's solid angle was measured first:
regions holding a piece of the sun and some sky made K = 16 at 16 spp noisier
than ``direct`` at 16 spp, 0.15 against 0.13 relative RMSE on sky_sun at 64^2.) visibility: the method's lookup on sub-view
``k`` (the region's orthographic map), with a light-sample record pointing along
``d``. The sum over the K regions is an unbiased estimate of the *unshadowed*
environment lighting (stratified by region); the only bias is the shadow:
every direction of region ``k`` takes the visibility of the map along its
centroid. The region's angular extent enters through the view: a
region sub-view reports its angular diameter (capped at 30 degrees) as a
directional light's ``light_width``, so ``pcss`` gives each region a penumbra
of its extent (``hard``, ``pcf``, ... ignore light widths: hard shadows per
region direction). ``multiview`` looks each region up as one view.

**The visibility AOV** of an environment emitter is the mean of the regions'
visibilities, each region's sampled direction weighted by its luminance over its
pdf (an estimate of the region's energy; a direction below the receiver's horizon
counts as 0): the fraction of the emitter's light -- directions weighted by
luminance, as the emitter samples them -- that arrives above the horizon
unoccluded, which is the expectation of ``raytraced``'s AOV (one shadow ray
towards ``sample_direction``'s sample, 0 below the horizon), so both can be
compared. (Weighting each region by its energy share alone counted a sampled dark
direction -- a black texel beside the sun, drawn by the uniform share -- as
shadowed: an open ground under a black sky with a sun read 0.90, not 1; now 1.0000.
Where every region's direction is dark the shares weigh the regions' visibilities,
each 0 where the region's own direction is below the receiver's horizon: with
``env_lights=1`` that ground read 0.86 (the sampled direction's horizon, and a lookup
that ran only where it was bright), 1.0000 now.)

``raytraced`` does not use the cut: it traces real shadow rays towards the
emitter's own ``sample_direction`` samples, so it equals ``direct``.
"""
from __future__ import annotations

import dataclasses
import functools
import hashlib
import math
import re
import warnings
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

from .light_views.base import look_along_np, opaque_scalar, position_np
from .light_views.multi import MultiView, SubView, stratified_points
from .light_views.ortho import directional_view
from .methods import whole_light_values
from .variants import bsdf_eval_reaches, bsdf_to_world, unpolarized

#: Coarsest grid of a texel-less environment emitter's cut (rows x columns;
#: a ``constant`` one's).
CONSTANT_GRID = (32, 64)
#: Largest relative difference between the energy of a texel-less environment emitter's
#: grid and its own sampled estimate before the grid is refined (:func:`cut_grid`).
ENERGY_TOLERANCE = 0.1
#: Cells per envmap texel side in the cut's grid.
GRID_REFINE = 2
#: Most cells of a refined grid: a larger envmap's cut works on its texels (a 4096 x 2048
#: map refined is 33.5M cells, evaluated twice: about 50 s and 4.6 GB per cut).
MAX_REFINED_CELLS = 1 << 21
#: Largest angular diameter (degrees) a region reports as its light width (pcss's range).
MAX_ANGULAR_DIAMETER = 30.0
#: Share of a region's texel-sampling probability spread by solid angle (the rest
#: follows the texels' energy), so every texel, dark or not, can be sampled.
UNIFORM_SHARE = 0.1
#: Most regions a virtual map holds (its page keys' face field); more keep full maps.
MAX_VIRTUAL_REGIONS = 32
#: Angle (radians, about 6 degrees) beyond a region's extent that the mark pass still
#: counts as above a point's horizon (shading normals differ from geometric ones).
MARK_SLACK = 0.1
#: Wavelengths (nm) at which spectral variants evaluate the map for the cut.
_WAVELENGTHS = (470.0, 530.0, 590.0, 650.0)


# ------------------------------------------------------------------ the cut
@dataclass(frozen=True)
class Regions:
    """The median cut of one environment emitter: K regions, numpy arrays of length K
    (``rects`` is ``(K, 4)``: ``u0, u1, v0, v1``; ``directions`` ``(K, 3)`` unit vectors
    towards the sky, world space)."""
    rects: np.ndarray
    solid_angle: np.ndarray
    energy: np.ndarray
    directions: np.ndarray
    angular_diameter: np.ndarray     # degrees
    grid: tuple                      # (H, W) of the luminance grid
    # Sampling tables (:func:`shade`): the texels of every region, region after region:
    offset: np.ndarray = None        # (K,) first texel of each region in the tables
    tex_row: np.ndarray = None       # texel rows j
    tex_col: np.ndarray = None       # texel columns i
    pmf: np.ndarray = None           # probability of the texel within its region
    cdf: np.ndarray = None           # cumulative pmf within the region (ends at 1)

    @property
    def count(self) -> int:
        return len(self.solid_angle)


def _texel_directions(H: int, W: int) -> np.ndarray:
    """Local unit directions of the texel centres, ``(H, W, 3)`` (Mitsuba's envmap
    convention: ``d = (sin t sin p, cos t, -sin t cos p)``, ``t = v pi``, ``p = 2 pi u``)."""
    theta = (np.arange(H) + 0.5) / H * np.pi
    phi = (np.arange(W) + 0.5) / W * 2.0 * np.pi
    t, p = np.meshgrid(theta, phi, indexing="ij")
    return np.stack([np.sin(t) * np.sin(p), np.cos(t), -np.sin(t) * np.cos(p)], axis=-1)


def _to_world(emitter) -> np.ndarray:
    return np.array(emitter.world_transform().matrix, dtype=np.float64).reshape(4, 4)[:3, :3]


def _eval_luminance(emitter, d_local: np.ndarray) -> np.ndarray:
    """``emitter.eval`` towards local directions ``(..., 3)`` as one luminance-like
    value each (rgb: luminance; mono: the value; spectral: the mean over four fixed
    wavelengths)."""
    shape = d_local.shape[:-1]
    d = d_local.reshape(-1, 3) @ _to_world(emitter).T
    si = dr.zeros(mi.SurfaceInteraction3f, len(d))
    si.wi = mi.Vector3f(*[mi.Float(-d[:, a].astype(np.float32)) for a in range(3)])
    if mi.is_spectral:
        si.wavelengths = type(si.wavelengths)(*_WAVELENGTHS)
    lum = np.asarray(_luminance(emitter.eval(si)).numpy(), dtype=np.float64).reshape(-1)
    lum = np.broadcast_to(lum, (len(d),))   # a constant emitter answers with one value
    return np.maximum(lum, 0.0).reshape(shape)


def _luminance(value) -> mi.Float:
    """One luminance-like value of a radiance (rgb: luminance; mono: the value;
    spectral: the mean over its wavelengths)."""
    v = unpolarized(value)
    if mi.is_rgb:
        return 0.212671 * v[0] + 0.715160 * v[1] + 0.072169 * v[2]
    n = dr.size_v(mi.UnpolarizedSpectrum)
    return sum(v[c] for c in range(n)) * (1.0 / n)


def _directions(theta: np.ndarray, phi: np.ndarray) -> np.ndarray:
    t, p = np.meshgrid(theta, phi, indexing="ij")
    return np.stack([np.sin(t) * np.sin(p), np.cos(t), -np.sin(t) * np.cos(p)], axis=-1)


def luminance_grid(emitter, H: int, W: int) -> tuple:
    """``(mean, bound)`` of the emitter's luminance over every cell of an ``H x W``
    lat-long grid: ``mean`` the average of its centre and four corners (the cut's
    energy), ``bound`` their maximum (the texel-sampling pmf: Mitsuba interpolates
    the map bilinearly, so a dark texel beside the sun is bright at its edge)."""
    c = _eval_luminance(emitter, _directions((np.arange(H) + 0.5) / H * np.pi,
                                             (np.arange(W) + 0.5) / W * 2.0 * np.pi))
    k = _eval_luminance(emitter, _directions(np.arange(H + 1) / H * np.pi,
                                             np.arange(W + 1) / W * 2.0 * np.pi))
    corners = np.stack([k[:-1, :-1], k[1:, :-1], k[:-1, 1:], k[1:, 1:]])
    return ((c + corners.sum(axis=0)) / 5.0,
            np.maximum(c, corners.max(axis=0)))


def median_cut(lum: np.ndarray, K: int) -> list:
    """Debevec's median cut of a lat-long luminance grid into at most ``K`` texel
    rectangles ``(j0, j1, i0, i1)`` (rows ``j``, columns ``i``; see the module doc)."""
    H, W = lum.shape
    theta_edges = np.arange(H + 1) / H * np.pi
    # energy per texel: luminance x solid angle
    omega_row = (2.0 * np.pi / W) * (np.cos(theta_edges[:-1]) - np.cos(theta_edges[1:]))
    e = lum * omega_row[:, None]
    if not np.any(e > 0):
        # an emitter with no energy (radiance 0, or scale 0) is cut by solid angle, as a
        # uniform one is: its regions are those of any uniform value (the cut of the
        # texel-count middle differed, and the derivative image of a tracked 0, which the
        # regions shadow, was not that of radiance 1: hard 371 against 1004)
        e = np.broadcast_to(omega_row[:, None], lum.shape)
    S = np.zeros((H + 1, W + 1))
    S[1:, 1:] = e.cumsum(0).cumsum(1)

    def energy(r):
        j0, j1, i0, i1 = r
        return S[j1, i1] - S[j0, i1] - S[j1, i0] + S[j0, i0]

    def split(r):
        j0, j1, i0, i1 = r
        t_mid = 0.5 * (theta_edges[j0] + theta_edges[j1])
        width = (i1 - i0) / W * 2.0 * np.pi * math.sin(t_mid)
        height = (j1 - j0) / H * np.pi
        along_u = (width >= height and i1 - i0 > 1) or j1 - j0 == 1
        sub = e[j0:j1, i0:i1]
        prof = sub.sum(axis=0) if along_u else sub.sum(axis=1)
        c = np.cumsum(prof)
        n = len(prof)
        if c[-1] > 0:
            m = int(np.argmin(np.abs(c[:-1] - 0.5 * c[-1]))) + 1
        else:   # no energy: the geometric middle
            m = n // 2
        m = min(max(m, 1), n - 1)
        if along_u:
            return (j0, j1, i0, i0 + m), (j0, j1, i0 + m, i1)
        return (j0, j0 + m, i0, i1), (j0 + m, j1, i0, i1)

    regions = [(0, H, 0, W)]
    while len(regions) < K:
        cand = [(energy(r), -k, k) for k, r in enumerate(regions)
                if (r[1] - r[0]) * (r[3] - r[2]) > 1]
        if not cand:
            break
        _, _, k = max(cand)
        a, b = split(regions[k])
        regions[k:k + 1] = [a, b]
    return regions


def regions_of(lum: np.ndarray, K: int, to_world: np.ndarray, bound=None) -> Regions:
    """:func:`median_cut` plus each region's solid angle, energy, centroid, extent and
    texel-sampling tables (pmf by ``bound``, default ``lum``, see :func:`luminance_grid`)."""
    H, W = lum.shape
    bound = lum if bound is None else bound
    cut = median_cut(lum, K)
    theta_edges = np.arange(H + 1) / H * np.pi
    omega_row = (2.0 * np.pi / W) * (np.cos(theta_edges[:-1]) - np.cos(theta_edges[1:]))
    d_tex = _texel_directions(H, W) @ to_world.T
    rects, omega, energy, dirs, diam = [], [], [], [], []
    offset, rows, cols, pmfs = [], [], [], []
    for j0, j1, i0, i1 in cut:
        w = lum[j0:j1, i0:i1] * omega_row[j0:j1, None]
        geo = np.broadcast_to(omega_row[j0:j1, None], w.shape)
        pm = geo / geo.sum()
        wb = bound[j0:j1, i0:i1] * omega_row[j0:j1, None]
        if wb.sum() > 0:   # mostly by energy; every texel keeps a share
            pm = (1.0 - UNIFORM_SHARE) * wb / wb.sum() + UNIFORM_SHARE * pm
        jj, ii = np.meshgrid(np.arange(j0, j1), np.arange(i0, i1), indexing="ij")
        offset.append(sum(len(r) for r in rows))
        rows.append(jj.ravel())
        cols.append(ii.ravel())
        pmfs.append(pm.ravel())
        d = d_tex[j0:j1, i0:i1].reshape(-1, 3)
        wf = w.ravel()
        if wf.sum() <= 0:   # no energy: geometric weights
            wf = np.broadcast_to(omega_row[j0:j1, None], w.shape).ravel()
        c = (wf[:, None] * d).sum(axis=0)
        c = c / max(np.linalg.norm(c), 1e-30)
        ang = np.arccos(np.clip(d @ c, -1.0, 1.0))
        m2 = float((wf * ang ** 2).sum() / wf.sum())
        rects.append((i0 / W, i1 / W, j0 / H, j1 / H))
        omega.append(2.0 * np.pi * (i1 - i0) / W
                     * (math.cos(theta_edges[j0]) - math.cos(theta_edges[j1])))
        energy.append(float(w.sum()))
        dirs.append(c)
        diam.append(math.degrees(2.0 * math.sqrt(2.0 * m2)))
    cdf = np.concatenate([np.minimum(np.cumsum(p), 1.0) for p in pmfs])
    for k, p in enumerate(pmfs):   # the region's last texel ends at exactly 1
        cdf[offset[k] + len(p) - 1] = 1.0
    return Regions(np.array(rects), np.array(omega), np.array(energy), np.array(dirs),
                   np.array(diam), (H, W), np.array(offset), np.concatenate(rows),
                   np.concatenate(cols), np.concatenate(pmfs), cdf)


def grid_shape(emitter) -> tuple:
    """``(H, W)`` of the emitter's cut (:func:`cut_grid`)."""
    params = mi.traverse(emitter)
    if "data" in params.keys():
        shape = params["data"].shape
        # Mitsuba pads the stored map with copies of border columns (W + 2 of them);
        # the cut works on cells of half a texel (GRID_REFINE).
        W = shape[1] - 2 if shape[1] >= 2 * shape[0] + 2 else shape[1]
        r = GRID_REFINE if GRID_REFINE ** 2 * int(shape[0]) * int(W) <= MAX_REFINED_CELLS else 1
        return r * int(shape[0]), r * int(W)
    return cut_grid(emitter)[:2]


def cut_grid(emitter) -> tuple:
    """``(H, W, mean, bound)``: the grid of the emitter's cut and its
    :func:`luminance_grid`. An envmap: cells of half a texel (of a texel past
    :data:`MAX_REFINED_CELLS`). Any other environment emitter (``constant``, ``sunsky``,
    ...) has no texels: its grid starts at :data:`CONSTANT_GRID` and doubles while the
    grid's energy (cell luminance times solid angle, summed) differs from the emitter's
    own estimate of it (:func:`sampled_energy`, through its ``sample_direction``) by more
    than :data:`ENERGY_TOLERANCE`, up to :data:`MAX_REFINED_CELLS` cells. A ``constant``
    keeps 32 x 64; a ``sunsky``'s sun (0.54 degrees) falls between the coarse grids'
    points: on 32 x 64 its cells' sampling missed it or caught it on a corner (image
    mean +16 %, RMSE 48x ``direct``'s noise at 48^2, 16 spp); its grid is 512 x 1024."""
    if "data" in mi.traverse(emitter).keys():
        H, W = grid_shape(emitter)
        return (H, W) + luminance_grid(emitter, H, W)
    target = sampled_energy(emitter)
    H, W = CONSTANT_GRID
    while True:
        mean, bound = luminance_grid(emitter, H, W)
        theta = np.arange(H + 1) / H * np.pi
        omega_row = (2.0 * np.pi / W) * (np.cos(theta[:-1]) - np.cos(theta[1:]))
        energy = float((mean * omega_row[:, None]).sum())
        if (abs(energy - target) <= ENERGY_TOLERANCE * max(target, 1e-30)
                or 4 * H * W > MAX_REFINED_CELLS):
            return H, W, mean, bound
        H, W = 2 * H, 2 * W


def sampled_energy(emitter, n: int = 256) -> float:
    """The emitter's luminance integrated over the sphere (as :func:`_eval_luminance`
    gives it), estimated with ``n^2`` stratified samples of its own ``sample_direction``
    (radiance over pdf): importance-sampled, so it sees a sun that a grid's points miss."""
    with dr.suspend_grad():
        N = n * n
        it = dr.zeros(mi.Interaction3f, N)
        if mi.is_spectral:
            it.wavelengths = type(it.wavelengths)(*_WAVELENGTHS)
        i = dr.arange(mi.UInt32, N)
        u = mi.Point2f((mi.Float(i % n) + 0.5) / n, (mi.Float(i // n) + 0.5) / n)
        _, weight = emitter.sample_direction(it, u, True)
        lum = np.asarray(_luminance(weight).numpy(), dtype=np.float64).reshape(-1)
    lum = np.broadcast_to(lum, (N,))   # a constant emitter answers with one value
    lum = lum[np.isfinite(lum)]
    return float(np.maximum(lum, 0.0).sum() / N)


_CACHE: dict = {}


def positive_scale(value) -> bool:
    """Whether an envmap's ``scale`` parameter (a JIT or Python scalar) is > 0."""
    return float(np.max(np.asarray(value, dtype=np.float64))) > 0.0


def emitter_regions(emitter, K: int, with_key: bool = False):
    """The cut of ``emitter`` into ``K`` regions, cached per emitter parameters (a hash
    of every ``mi.traverse(emitter)`` value but ``to_world``), variant and K, in the
    emitter's own frame: a rotated emitter rotates the cached cut's directions (the cut
    and the texel tables are the same in its frame; a sky turned every frame re-cut it
    every frame). ``with_key``: also a key of the cut and the transform."""
    from .map_manager import is_transform    # (map_manager imports this module lazily)
    params = mi.traverse(emitter)
    h = hashlib.blake2b(digest_size=16)
    h.update(f"{mi.variant()}/{K}".encode())
    for k in params.keys():
        v = params[k]
        if k == "scale":   # scales every texel alike: the cut is the same (but for 0)
            h.update(b"scale>0" if positive_scale(v) else b"scale=0")
            continue
        if k == "to_world":   # the cut is made in the emitter's frame (rotated below)
            continue
        h.update(k.encode())
        if is_transform(v):   # transforms: by value
            v = v.matrix
        try:
            a = np.asarray(v.numpy() if hasattr(v, "numpy") else v)
            h.update(a.tobytes() if a.dtype != object else repr(v).encode())
        except Exception:
            h.update(repr(v).encode())
    T = _to_world(emitter)
    local_key = h.hexdigest()
    h.update(T.tobytes())
    key = h.hexdigest()
    reg = _CACHE.get(local_key)
    if reg is None:
        H, W, mean, bound = cut_grid(emitter)
        top = float(bound.max()) if bound.size else 0.0
        if top > 0.0:   # relative luminance: an emitter's scale changes no cut
            mean, bound = mean / top, bound / top
        reg = regions_of(mean, K, np.eye(3), bound)
        if reg.count < K:   # once per cut (the cut is cached below)
            warnings.warn(
                f"shadowmap: property 'env_lights' = {K} asks for more regions than the "
                f"environment emitter's {H} x {W} cells allow; it gets {reg.count} regions",
                stacklevel=2)
        while len(_CACHE) >= 64:   # oldest first
            _CACHE.pop(next(iter(_CACHE)))
        _CACHE[local_key] = reg
    world = _CACHE.get(key)
    if world is None:   # centroids to world space (the maps' views read it by key)
        d = reg.directions @ T.T
        world = dataclasses.replace(
            reg, directions=d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-30))
        while len(_CACHE) >= 64:
            _CACHE.pop(next(iter(_CACHE)))
        _CACHE[key] = world
    return (world, key) if with_key else world


# ------------------------------------------------------------------ the view
class _Direction:
    """A stand-in emitter for :func:`directional_view`: light travelling along ``d``."""

    def __init__(self, d):
        self._T = look_along_np((0.0, 0.0, 0.0), d).inverse()

    def world_transform(self):
        return mi.Transform4f(self._T.matrix)


@dataclass(frozen=True)
class RegionView(SubView):
    """Sub-view ``k`` of an :class:`EnvironmentView`: the region's orthographic map,
    reporting the region's angular diameter as a directional light's width (per lane).

    With ``rows64`` (the region's ``light_from_world`` rows in float64, gathered per
    lane, :meth:`EnvironmentView.region_view`) it also has the float64 interface of a
    virtual map's view (:mod:`mi_shadowmap.virtual`): face ``k`` of the environment's
    K-face virtual map, one orthographic face per region."""
    spread: object = 0.0
    rows64: tuple = ()
    axes32: tuple = ()     # the light axes x, y, z in world space: rows64's rotation rows
    #                        in float32 (made once per lookup)
    #: An environment region is a set of directions, not a light point, and the
    #: shading (:func:`shade`) tests the horizon itself, of the direction it draws and
    #: of the region: a lookup's own horizon test (``multiview``'s) is left out, as its
    #: region's axis can lie below a horizon most of the region is above.
    caller_tests_horizon = True

    def light_width(self, light_size=None, angular_diameter: float = 0.0):
        return self.spread, True

    # ---------------------------------------------- float64 (virtual maps)
    def _half(self, double: bool = False):
        """The face's half sizes as opaque JIT scalars (:meth:`OrthoView._half`): a
        rotated environment refits them and compiles no new kernel."""
        return self.inner._half(double)

    def _light64(self, p_world):
        M = self.rows64
        p = mi.Point3d(p_world)
        return [M[4 * r] * p.x + M[4 * r + 1] * p.y + M[4 * r + 2] * p.z + M[4 * r + 3]
                for r in range(3)]

    def project_f64(self, p_world):
        x, y, z = self._light64(p_world)
        hx, hy = self._half(True)
        uv = mi.Point2d(0.5 * (x / hx + 1.0), 0.5 * (y / hy + 1.0))
        inside = (uv.x >= 0) & (uv.x <= 1) & (uv.y >= 0) & (uv.y <= 1)
        return mi.UInt32(self.offset), uv, z, inside

    def uv_on_face_f64(self, face, p_world):
        return self.project_f64(p_world)[1]

    def ray_through_f64(self, face, uv_light):
        return _region_ray64(self.rows64, self._half(True), uv_light)

    def ray_frame_f64(self, face, uv_light):
        ax, ay, az = self.axes32
        hx, hy = self._half()
        return False, az, ax * (2.0 * hx), ay * (2.0 * hy)

    def uv_differential(self, face, p_world, dp_world):
        ax, ay, _ = self.axes32
        dp = mi.Vector3f(dp_world)
        hx, hy = self._half()
        return mi.Point2f(0.5 * dr.dot(ax, dp) / hx, 0.5 * dr.dot(ay, dp) / hy)

    def depth_differential(self, p_world, dp_world):
        return dr.dot(mi.Vector3f(dp_world), self.axes32[2])


@dataclass(frozen=True)
class EnvironmentView(MultiView):
    """K orthographic views, one per median-cut region, in one map. ``rects``,
    ``solid_angles`` and ``angular_diameters`` (degrees) describe the regions,
    ``to_world_env`` the emitter's rotation (9 numbers, row-major)."""
    rects: tuple = ()
    solid_angles: tuple = ()
    angular_diameters: tuple = ()
    to_world_env: tuple = ()
    regions_key: str = ""    # the cut's cache key (its sampling tables: :attr:`regions`)

    @property
    def regions(self) -> Regions:
        return _CACHE[self.regions_key]

    projection = "environment"

    @functools.cached_property
    def _region_tables(self) -> dict:
        diam = np.minimum(np.asarray(self.angular_diameters), MAX_ANGULAR_DIAMETER)
        reg = self.regions
        H, W = reg.grid
        te = np.arange(H + 1) / H * np.pi
        counts = np.diff(np.append(reg.offset, len(reg.cdf)))
        cdf = mi.Float(reg.cdf)
        guide, guide_offset, guide_scale = search_guide(cdf.numpy(), reg.offset, counts)
        return {"offset": mi.UInt32(reg.offset.astype(np.uint32)),
                "count": mi.UInt32(counts.astype(np.uint32)),
                "row": mi.UInt32(reg.tex_row.astype(np.uint32)),
                "col": mi.Float(reg.tex_col.astype(np.float64)),
                "pmf": mi.Float(reg.pmf), "cdf": cdf,
                "guide": mi.UInt64(guide), "guide_offset": mi.UInt32(guide_offset),
                "guide_scale": mi.Float(guide_scale),
                "c0": mi.Float(np.cos(te[:-1])), "dc": mi.Float(np.cos(te[1:]) - np.cos(te[:-1])),
                "omega_row": mi.Float((2.0 * np.pi / W) * (np.cos(te[:-1]) - np.cos(te[1:]))),
                "W": float(W),
                "spread": mi.Float(2.0 * np.tan(np.radians(diam) * 0.5)),
                # an emitter with no energy lights nothing: visibility AOV 0, as
                # raytraced's and a delta light's of zero intensity (solid-angle shares
                # gave the geometric visibility: 84 % of a zero sky's pixels "false lit")
                "share": mi.Float(reg.energy / max(reg.energy.sum(), 1e-300))}

    def region_view(self, k) -> RegionView:
        k = mi.UInt32(k)
        s = dr.gather(mi.Float, self._region_tables["spread"], k)
        rows = tuple(dr.gather(mi.Float64, c, k) for c in self._rows64)
        axes = tuple(mi.Vector3f(*(mi.Float(rows[4 * r + a]) for a in range(3)))
                     for r in range(3))
        return RegionView(self.kind, self.position, self.light_from_world, self.light_size,
                          self.ignore_shape, self.light_normal, self.label,
                          inner=self.lane(k), offset=k * self.sub.n_faces, spread=s,
                          rows64=rows, axes32=axes)

    # ---------------------------------------------------- virtual maps
    # With ``virtual`` (the default), the K regions are the K faces of one virtual map
    # (:mod:`mi_shadowmap.virtual`): face k is region k's orthographic face, pages are
    # built where the camera's points read region k, at the density their pixels need.
    # A lookup reads through :meth:`region_view` (``k`` per lane: the shading loop's
    # region), the page build through :meth:`ray_through_f64` (the face per texel).
    @property
    def supports_virtual(self) -> bool:
        """Up to :data:`MAX_VIRTUAL_REGIONS` regions (faces of a virtual map's page key);
        more keep full maps."""
        return self.n_views <= MAX_VIRTUAL_REGIONS

    @property
    def half_extent(self) -> tuple:
        """Half sizes of every region's face (shared: the largest over the regions)."""
        return self.sub.half_extent

    @functools.cached_property
    def _matrices64(self) -> np.ndarray:
        """``(K, 3, 4)`` float64 ``light_from_world`` of every region: ``[R | -R p]``,
        ``R`` the nearest rotation to the stored (float32-rounded) one, so that ``R^T``
        inverts it to float64 precision (the page build casts through ``R^T``, lookups
        project through ``R``)."""
        U, _, Vt = np.linalg.svd(np.asarray(self.rotations, np.float64).reshape(-1, 3, 3))
        R = U @ Vt
        p = np.asarray(self.positions, np.float64).reshape(-1, 3)
        return np.concatenate([R, -np.einsum("kij,kj->ki", R, p)[:, :, None]], axis=2)

    @functools.cached_property
    def _rows64(self) -> tuple:
        M = self._matrices64.reshape(-1, 12)
        return tuple(mi.Float64(M[:, c].tolist() + [0.0] * (len(M) < 2))
                     for c in range(12))

    def ray_through_f64(self, face, uv_light):
        """Texel rays of ``face`` (the region, per lane) in float64 (the page build)."""
        face = mi.UInt32(face)
        return _region_ray64(tuple(dr.gather(mi.Float64, c, face) for c in self._rows64),
                             self.sub._half(True), uv_light)

    def depth_range64(self, corners: np.ndarray) -> tuple:
        """``(lo, hi)`` of the depths of ``corners`` (``(n, 3)``) over every region."""
        M = self._matrices64
        d = np.einsum("kj,nj->kn", M[:, 2, :3], corners) + M[:, 2, 3:4]
        return float(d.min()), float(d.max())

    @functools.cached_property
    def region_radii(self) -> np.ndarray:
        """Per region, the largest angle (radians) between its centroid and a direction
        of its rectangle (its boundary and interior on a 17 x 17 grid)."""
        R = np.asarray(self.to_world_env, np.float64).reshape(3, 3)
        out = []
        for (u0, u1, v0, v1), c in zip(np.asarray(self.rects).reshape(-1, 4),
                                       self.centroids):
            s = np.linspace(0.0, 1.0, 17)
            theta = (v0 + s * (v1 - v0)) * np.pi
            phi = (u0 + s * (u1 - u0)) * 2.0 * np.pi
            d = _directions(theta, phi).reshape(-1, 3) @ R.T
            out.append(float(np.arccos(np.clip(d @ c, -1.0, 1.0)).max()))
        return np.array(out)

    @property
    def centroids(self) -> np.ndarray:
        """``(K, 3)`` world directions towards each region's centroid (against the light's
        travel: each face's ``-z``)."""
        return -self._matrices64[:, 2, :3]

    def mark_views(self) -> list:
        """``(view, active(p, n, through))`` per region for the mark pass: the region's
        view and which camera points it can light (``n`` their normal facing the camera,
        ``through`` whether their BSDF transmits): those whose horizon the region
        reaches, with :data:`MARK_SLACK` radians to spare (shading normals), or, for a
        transmitting surface, the horizon of either side, so that a lookup finds its
        pages."""
        out = []
        for k, (c, r) in enumerate(zip(self.centroids, self.region_radii)):
            # opaque: every region's mark kernel is the same code (one compile)
            lim = dr.opaque(mi.Float, -math.sin(min(r + MARK_SLACK, 0.5 * math.pi)))
            cv = dr.opaque(mi.Vector3f, c.tolist())

            def active(p, n, through, cv=cv, lim=lim):
                c = dr.dot(n, cv)
                return (c > lim) | (mi.Bool(through) & (-c > lim))

            out.append((self.region_view(dr.opaque(mi.UInt32, k)), active))
        return out

    def _mark_tables(self) -> tuple:
        """Per region, :meth:`mark_views`'s centroid (float32) and horizon limit, as
        opaque JIT arrays (padded to two entries: a one-entry array would be a literal)."""
        c = np.asarray(self.centroids, np.float64).reshape(-1, 3)
        lim = [-math.sin(min(r + MARK_SLACK, 0.5 * math.pi)) for r in self.region_radii]
        pad = [0] * (len(lim) < 2)
        cv = mi.Vector3f(*(mi.Float(c[:, a].tolist() + [0.0] * len(pad)) for a in range(3)))
        lim = mi.Float(lim + [0.0] * len(pad))
        dr.make_opaque(cv, lim)
        return cv, lim

    def mark_lanes(self, k) -> tuple:
        """:meth:`mark_views` for the regions ``k`` (``mi.UInt32``, per lane) in one
        kernel: ``(view, active(p, n, through))``, the same values per lane as region
        ``k``'s entry of :meth:`mark_views`."""
        k = mi.UInt32(k)
        cv_all, lim_all = self._mark_tables()
        cv = dr.gather(mi.Vector3f, cv_all, k)
        lim = dr.gather(mi.Float, lim_all, k)

        def active(p, n, through):
            c = dr.dot(n, cv)
            return (c > lim) | (mi.Bool(through) & (-c > lim))

        return self.region_view(k), active

    def describe(self) -> str:
        return (f"{self.label}: environment light, {self.n_views} median-cut regions x "
                f"orthographic map ({self.n_faces} face(s))")


def environment_view(emitter, scene, label: str, K: int) -> EnvironmentView:
    """The :class:`EnvironmentView` of an environment emitter: K median-cut regions,
    one orthographic map each (fitted to the scene's bounds like a directional light's)."""
    reg, key = emitter_regions(emitter, K, with_key=True)
    travel = -reg.directions          # light travels from the sky towards the scene
    subs = [directional_view(_Direction(d), scene, label) for d in travel]
    half = tuple(max(v.half_extent[a] for v in subs) for a in range(2))
    template = dataclasses.replace(subs[0], half_extent=half)
    n = reg.count
    return EnvironmentView(
        "environment", subs[0].position, subs[0].light_from_world, 0.0, None, None, label,
        sub=template,
        positions=tuple(tuple(position_np(v).tolist()) for v in subs),
        rotations=tuple(tuple(np.array(v.light_from_world.matrix, dtype=np.float64)
                              .reshape(4, 4)[:3, :3].ravel()) for v in subs),
        samples=tuple(tuple(float(c) for c in s) for s in stratified_points(n)),
        rects=tuple(tuple(float(c) for c in r) for r in reg.rects),
        solid_angles=tuple(float(x) for x in reg.solid_angle),
        angular_diameters=tuple(float(x) for x in reg.angular_diameter),
        to_world_env=tuple(float(x) for x in _to_world(emitter).ravel()), regions_key=key)


def light_view(emitter, scene, index: int, opts, label: str | None = None):
    """The view of an environment emitter for a render with ``opts``: an
    :class:`EnvironmentView` with ``environment='shadowed'`` and a map method, else None.
    ``label``: its name (default: from :func:`~mi_shadowmap.light_views.emitter_labels`)."""
    from .light_views import emitter_labels
    if opts.environment != "shadowed" or not opts.uses_map:
        return None
    if label is None:
        label = emitter_labels(scene.emitters())[index]
    R = _to_world(emitter)
    if not np.allclose(R.T @ R, np.eye(3), atol=1e-4):
        # Mitsuba maps a direction into the emitter's frame through the inverse
        # transform and reads the texel of the result as if it were a unit vector, so a
        # scaled frame reads another texel than the region's sampling put there (a
        # to_world scaled by 2: the map methods rendered the sky 97 % too dark)
        raise ValueError(
            f"shadowmap: emitter '{label}': its to_world is not a rotation (it scales or "
            f"shears: rows {np.round(R, 4).tolist()}); environment='shadowed' needs a "
            "rotation (a mirror is fine). Remove the scale from to_world, or use "
            "method='raytraced' or environment='unshadowed'")
    return environment_view(emitter, scene, label, opts.env_lights)


def _region_ray64(rows, half, uv_light):
    """The texel ray through ``uv_light`` of the orthographic face whose float64
    ``light_from_world`` rows are ``rows`` (12 values, rotation rows and translation)."""
    uv = mi.Point2d(uv_light)
    s = (uv.x * 2.0 - 1.0) * half[0]
    t = (uv.y * 2.0 - 1.0) * half[1]
    M = rows
    # world_from_light of [R | q]: o = R^T ((s, t, 0) - q)
    lx, ly, lz = s - M[3], t - M[7], -M[11]
    o = mi.Point3d(*[M[a] * lx + M[4 + a] * ly + M[8 + a] * lz for a in range(3)])
    d = mi.Vector3d(M[8], M[9], M[10])
    return o, dr.normalize(d)


# ------------------------------------------------------------------ shading
_R2 = (0.7548776662466927, 0.5698402909980532)


#: At most 2^GUIDE_BITS buckets per region in :func:`search_guide`.
GUIDE_BITS = 12


def search_guide(cdf: np.ndarray, offset: np.ndarray, count: np.ndarray) -> tuple:
    """``(guide, guide_offset, guide_scale)``: for each region (its float32 ``cdf`` values
    ``cdf[offset:offset + count]``, non-decreasing) and each of its ``G`` buckets of the
    uniform number ``x`` (``G = 2^ceil(log2 count)``, at most ``2^GUIDE_BITS``; bucket
    ``floor(x G)``, exact: G is a power of two), the texels ``[lo, lo + n)`` that the
    first texel whose cdf exceeds ``x`` lies in or ends (``lo | n << 32``): ``lo`` that
    texel for the bucket's smallest ``x`` (``b / G``), ``lo + n`` for its largest (the
    float32 below ``(b + 1) / G``); the lower bound is monotonic in ``x``, so a search of
    those texels (:func:`_search_body`) finds what a search of the whole region finds.
    ``guide_offset``: each region's first bucket; ``guide_scale``: its ``G``."""
    guide, starts, scales = [], [], []
    total = 0
    for o, n in zip(np.asarray(offset).tolist(), np.asarray(count).tolist()):
        c = np.asarray(cdf[o:o + n], np.float32)
        G = 1 << min(max(int(n) - 1, 0).bit_length(), GUIDE_BITS)
        b = np.arange(G, dtype=np.float64)
        x0 = (b / G).astype(np.float32)
        x1 = np.nextafter(((b + 1) / G).astype(np.float32), np.float32(0))
        lo = o + np.searchsorted(c, x0, side="right")
        hi = o + np.searchsorted(c, x1, side="right")
        guide.append(lo.astype(np.uint64) | ((hi - lo).astype(np.uint64) << np.uint64(32)))
        starts.append(total)
        scales.append(float(G))
        total += G
    return (np.concatenate(guide), np.array(starts, np.uint32),
            np.array(scales, np.float32))


def _search_cond(lo, n):
    return n > 0


def _search_body(cdf, x):
    """One step of the binary search for the first texel of ``[lo, lo + n)`` whose
    ``cdf`` exceeds ``x`` (:func:`shade`'s texel of a region, ``[lo, lo + n)`` the texels
    :func:`search_guide` gives ``x``'s bucket): a loop that runs until every lane's range
    is empty. It ran the largest region's steps in every region (14 on sky_sun, whose 16
    regions hold 2-7110 texels; a fixed count is also a new kernel for each largest
    region size); stopping when the ranges are empty, 125 steps over the regions instead
    of 224: the render kernel of a ``hard`` frame (128^2, 16 spp, maps cached) 92.0 ->
    80.8 ms, ``pcss`` 259.8 -> 251.3 ms (medians of 8, alternated in one process); the
    guide's buckets then 0.95 of that ``hard`` frame, 0.98-0.99 of ``pcss``'s (pairs of
    frames). The same texels: images bit-identical."""
    def body(lo, n):
        half = n >> 1
        mid = lo + half
        # (masked as the loop masks it: an evaluated loop, SymbolicLoops off, may run the
        # body on every lane, and an empty range's mid may be the table's end)
        go = dr.gather(mi.Float, cdf, mid, n > 0) <= x
        return dr.select(go, mid + 1, lo), dr.select(go, n - half - 1, half)
    return body


#: The sun warp's band (:func:`_sun_warp`), in sun radii from the sun's centre: the
#: directions within the inner radius turn with the sun, those past the outer stay.
SUN_WARP_BAND = (2.0, 4.0)


def _sun_warp(emitter):
    """Where ``emitter`` is a ``sunsky`` whose ``sun_direction`` tracks gradients: a
    function ``d -> (d', jacobian)`` that turns the region samples near the sun with it,
    else ``None``.

    The regions' directions are drawn from tables cut at the sun's current direction
    (numpy, no derivative), so the sun's disc, whose radiance jumps at its rim, moved
    over fixed samples and its motion was lost: a ground under the sky, no occluder,
    16^2, the image's derivative as the sun turns about the sky's zenith (+z) was 0.0095
    against 0.0977 by finite differences of ``direct``; now 0.0903
    (``tests/test_environment.py``). (In the other directions Mitsuba's own derivative
    of the sun's radiance wrt its direction, which ``direct``'s AD shares, differs from
    the finite differences: at 32^2 the whole gradient (-0.139, -0.016, 0.036),
    ``direct``'s AD (-0.117, 0.014, 0.040), before (-0.071, -0.081, 0.076).) The
    samples are reparameterized (Loubet et al.,
    SIGGRAPH Asia 2019): ``d' = d + w(d) (ds0 x ds) x d`` to first order, ``ds`` the
    attached sun direction minus its value (0, so ``d' = d`` and the image is
    unchanged), ``w`` 1 within :data:`SUN_WARP_BAND` [0] sun radii of the sun's centre,
    0 past [1] (smoothstep between), so the sun and the sky around it turn rigidly and
    the horizon, where the sky's radiance jumps too, stays put; the estimate is
    multiplied by the warp's Jacobian ``1 + div(w V)`` (value 1; ``V = (s0 x ds) x d``
    is divergence-free, so ``div = grad w . V``). Shadow lookups keep ``d``: the
    regions' maps do not move with the sun (its shadows pass no gradient to it)."""
    params = mi.traverse(emitter)
    if "sun_direction" not in params.keys():
        return None
    s = mi.Vector3f(params["sun_direction"])
    if not dr.grad_enabled(s):
        return None
    s = dr.normalize(s)
    s0 = dr.detach(s)
    omega = dr.cross(s0, s - s0)          # value 0: the sun's rotation rate
    m = re.search(r"Sun aperture\s*=\s*([0-9.eE+-]+)", str(emitter))
    radius = math.radians(0.5 * (float(m.group(1)) if m else 0.5358))
    a0, a1 = SUN_WARP_BAND[0] * radius, SUN_WARP_BAND[1] * radius

    def warp(d):
        t = dr.clip(dr.dot(s0, d), -1.0, 1.0)
        a = dr.acos(t)
        u = dr.clip((a - a0) / (a1 - a0), 0.0, 1.0)
        w = 1.0 - u * u * (3.0 - 2.0 * u)
        dw = dr.select((u > 0) & (u < 1), -6.0 * u * (1.0 - u) / (a1 - a0), 0.0)
        V = dr.cross(omega, d)
        grad_a = -(s0 - t * d) / dr.maximum(dr.safe_sqrt(1.0 - t * t), 1e-12)
        return dr.normalize(d + w * V), 1.0 + dw * dr.dot(grad_a, V)
    return warp


def shade(smap, emitter, si, bsdf, active, sampler, dp_dx, dp_dy, opts):
    """Shadowed environment lighting at ``si`` (see the module doc): returns
    ``(radiance, visibility AOV)``."""
    from .filters import Lookup
    from .virtual import VirtualShadowMap
    view = smap.view
    virtual = isinstance(smap, VirtualShadowMap)
    t = view._region_tables
    K = view.n_views
    record = opts.record
    vis_fn = record.lookup
    ctx = mi.BSDFContext()
    # opaque: a rotated environment compiles no new kernel
    R = [[opaque_scalar(v) for v in row]
         for row in np.asarray(view.to_world_env, dtype=np.float64).reshape(3, 3).tolist()]
    shift = sampler.next_2d(active)
    act = mi.Bool(active)
    bsphere = 1e3 * (dr.norm(si.p) + 1.0)
    sun = _sun_warp(emitter)

    def cond(k, result, wsum, vsum, ssum, svsum, sampler):
        return act & (k < K)

    def body(k, result, wsum, vsum, ssum, svsum, sampler):
        kf = mi.Float(k)
        xi = shift + mi.Point2f(kf * _R2[0], kf * _R2[1])
        xi = xi - dr.floor(xi)
        # a texel of the region by its pmf (lower bound in the region's cdf), then a
        # direction uniform in the texel's solid angle
        off = dr.gather(mi.UInt32, t["offset"], k)
        # the texels the lower bound lies in for xi.x's bucket (search_guide), then the
        # search among them
        scale = dr.gather(mi.Float, t["guide_scale"], k)
        bucket = mi.UInt32(dr.minimum(xi.x * scale, scale - 1.0))
        r = dr.gather(mi.UInt64, t["guide"], dr.gather(mi.UInt32, t["guide_offset"], k) + bucket)
        lo, _ = dr.while_loop((mi.UInt32(r), mi.UInt32(r >> 32)), _search_cond,
                              _search_body(t["cdf"], xi.x),
                              label="environment: a texel of the region")
        last = off + dr.gather(mi.UInt32, t["count"], k) - 1
        idx = dr.minimum(lo, last)
        prev = dr.select(idx > off, dr.gather(mi.Float, t["cdf"], idx - 1, idx > off), 0.0)
        pm = dr.gather(mi.Float, t["pmf"], idx)
        x = dr.clip((xi.x - prev) / dr.maximum(pm, 1e-30), 0.0, 1.0)
        row = dr.gather(mi.UInt32, t["row"], idx)
        col = dr.gather(mi.Float, t["col"], idx)
        c0 = dr.gather(mi.Float, t["c0"], row)
        dc = dr.gather(mi.Float, t["dc"], row)
        omega = dr.gather(mi.Float, t["omega_row"], row) / dr.maximum(pm, 1e-30)  # 1 / pdf
        phi = (col + x) * (2.0 * math.pi / t["W"])
        cos_t = dr.clip(c0 + xi.y * dc, -1.0, 1.0)
        sin_t = dr.safe_sqrt(1.0 - cos_t * cos_t)
        sp, cp = dr.sincos(phi)
        loc = (sin_t * sp, cos_t, -sin_t * cp)
        d = dr.normalize(mi.Vector3f(*[R[a][0] * loc[0] + R[a][1] * loc[1] + R[a][2] * loc[2]
                                       for a in range(3)]))
        d_shade, jac = (d, 1.0) if sun is None else sun(d)
        si_e = dr.zeros(mi.SurfaceInteraction3f)
        si_e.wi = -d_shade
        si_e.wavelengths = si.wavelengths
        L = emitter.eval(si_e, act)
        wo = si.to_local(d_shade)
        f, seen = bsdf_eval_reaches(bsdf, ctx, si, wo, act)
        f = bsdf_to_world(si, f, wo)
        contrib = f * L * (omega * jac)
        # where the radiance tracks gradients, the term is gated by geometry (the BSDF
        # reaches d), not by its value: a radiance of exactly 0 cut the derivative wrt it
        lit = act & (seen if dr.grad_enabled(L) else (dr.max(unpolarized(contrib)) > 0))
        # the lookup runs wherever the direction is above the horizon, dark or not (the
        # region's visibility, its map's, does not depend on the direction's radiance),
        # and wherever the region's own direction is on the viewer's side: the AOV's
        # fallback, where every region's direction was dark, reads the regions there
        # (a black receiver too: the BSDF's pdf, bsdf_eval_reaches)
        rv = view.region_view(k)
        region_up = act & (si.to_local(-rv.axes32[2]).z * si.wi.z > 0)
        ask = seen | region_up
        ds = dr.zeros(mi.DirectionSample3f)
        ds.p = si.p + d * bsphere
        ds.d = d
        ds.dist = bsphere
        ds.pdf = dr.rcp(dr.maximum(omega, 1e-30))
        ds.emitter = mi.EmitterPtr(emitter)
        lk = Lookup(si.p, si.n, dp_dx, dp_dy, si, ds, sampler, emitter=emitter)
        if virtual:
            # region k's face of the virtual map, bound walked (VirtualShadowMap.visibility's
            # unwalked first try needs a dr.if_stmt outside symbolic loops, and this is
            # one); a per-tap lookup (hard) still gathers each read's own slot
            sub = smap.with_view(rv)
            bound = sub.bind(lk, ask, per_tap=record.virtual_per_tap)
            vis = dr.select(ask, vis_fn(bound, lk, opts, ask), 0.0)
        elif record.whole_light:
            sub = dataclasses.replace(smap, view=rv)
            _, _, weight = whole_light_values(vis_fn(sub, lk, opts, ask))
            vis = dr.select(ask, weight, 0.0)
        else:
            sub = dataclasses.replace(smap, view=rv)
            vis = dr.select(ask, vis_fn(sub, lk, opts, ask), 0.0)
        vis_region = dr.select(region_up, vis, 0.0)     # the fallback's
        vis = dr.select(seen, vis, 0.0)
        # the AOV's weight: the sample's luminance over its pdf, an estimate of the
        # region's energy, so a dark direction (a black texel of the sun's region, or the
        # uniform share's) weighs nothing instead of counting as shadowed
        w = dr.select(act, dr.maximum(_luminance(L), 0.0) * omega, 0.0)
        share = dr.gather(mi.Float, t["share"], k)     # where every direction was dark
        return (k + 1, result + dr.select(lit, contrib * vis, 0.0), wsum + w,
                vsum + w * vis, ssum + share, svsum + share * vis_region, sampler)

    z = mi.Float(0.0)
    _, result, wsum, vsum, ssum, svsum, _ = dr.while_loop(
        (mi.UInt32(0), mi.Spectrum(0.0), z, z, z, z, sampler), cond, body)
    aov = dr.select(wsum > 0, vsum / dr.maximum(wsum, 1e-30),
                    svsum / dr.maximum(ssum, 1e-30))
    return result, dr.select(act, aov, 0.0)
