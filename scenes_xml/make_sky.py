"""Make ``textures/sky_sun.exr``: a procedural 64 x 128 sky with a 6-degree sun.

Run ``python scenes_xml/make_sky.py`` (from anywhere) to regenerate it; the
EXR is shipped so ``sky_sun.xml`` loads as is. Lat-long in Mitsuba's envmap
convention (row 0 at the zenith, +Y up, ``u = atan2(d.x, -d.z) / 2 pi``):

* sky: a gradient from a blue zenith (0.25, 0.45, 0.9) to a pale horizon
  (0.9, 0.95, 1.0), times 1;
* ground (below the horizon): a dim grey-brown (0.08, 0.07, 0.06);
* sun: a disc of angular diameter ``SUN_DIAMETER`` (6 degrees), radiance
  ``SUN_RADIANCE`` (1000 x the sky, warm white), at elevation 45 degrees,
  azimuth ``SUN_AZIMUTH``; every texel is supersampled 16 x 16, so the disc's
  energy is right at this resolution.
"""
from __future__ import annotations

import math
import os

import numpy as np

H, W = 64, 128
SUN_DIAMETER = 6.0           # degrees
SUN_ELEVATION = 45.0         # degrees above the horizon
SUN_AZIMUTH = 125.0          # degrees, u = azimuth / 360
SUN_RADIANCE = (1000.0, 960.0, 900.0)
SUPER = 16


def sky_image(h: int = H, w: int = W) -> np.ndarray:
    """The ``(h, w, 3)`` float32 radiance of the sky map (see the module doc)."""
    js = (np.arange(h * SUPER) + 0.5) / (h * SUPER)
    iu = (np.arange(w * SUPER) + 0.5) / (w * SUPER)
    theta = js * math.pi
    phi = iu * 2.0 * math.pi
    t, p = np.meshgrid(theta, phi, indexing="ij")
    d = np.stack([np.sin(t) * np.sin(p), np.cos(t), -np.sin(t) * np.cos(p)], axis=-1)
    up = np.clip(d[..., 1], 0.0, 1.0)[..., None]
    zen = np.array([0.25, 0.45, 0.9])
    hor = np.array([0.9, 0.95, 1.0])
    sky = hor + (zen - hor) * np.sqrt(up)
    ground = np.array([0.08, 0.07, 0.06])
    img = np.where(d[..., 1:2] >= 0.0, sky, ground)
    el, az = math.radians(SUN_ELEVATION), math.radians(SUN_AZIMUTH)
    s = np.array([math.cos(el) * math.sin(az), math.sin(el), -math.cos(el) * math.cos(az)])
    in_sun = (d @ s) >= math.cos(math.radians(SUN_DIAMETER) * 0.5)
    img = np.where(in_sun[..., None], np.array(SUN_RADIANCE), img)
    img = img.reshape(h, SUPER, w, SUPER, 3).mean(axis=(1, 3))
    return img.astype(np.float32)


def main(path: str | None = None) -> str:
    import mi_shadowmap  # noqa: F401  (chooses the libLLVM before mitsuba)
    import mitsuba as mi
    if mi.variant() is None:
        mi.set_variant("scalar_rgb")
    path = path or os.path.join(os.path.dirname(os.path.abspath(__file__)), "textures",
                                "sky_sun.exr")
    os.makedirs(os.path.dirname(path), exist_ok=True)
    mi.Bitmap(sky_image()).write(path)
    return path


if __name__ == "__main__":
    print(main())
