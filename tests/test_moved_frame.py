"""What a camera move's frame does on the host besides its kernels (virtual maps, issue
11's camera move: the moved frame <= 1.5x the unshadowed frame)."""
from __future__ import annotations

import mitsuba as mi
import numpy as np

from mi_shadowmap import virtual
from mi_shadowmap.virtual import camera

from conftest import SCENES

T = mi.ScalarTransform4f


def shadowmap(**kw):
    return mi.load_dict({"type": "shadowmap", **kw})


def test_a_moved_frame_reads_its_cameras_parameters_once():
    """The first pass reads the camera's state (every ``mi.traverse`` parameter of the
    sensor, :func:`~mi_shadowmap.virtual.camera_state`) once a render and hands it to
    the page planner (are its marks stale?) and to the pinhole frame: each read it
    again, twice a moved frame (about 0.1 ms each on far_point at 256^2). The moved
    frame's image is a fresh integrator's at the same pose."""
    scene = mi.load_file(str(SCENES / "far_point.xml"), width=64, height=64)
    integ = shadowmap(method="hard")
    mi.render(scene, integrator=integ, spp=2)
    params = mi.traverse(scene)
    key = next(k for k in params.keys() if k.endswith("to_world")
               and isinstance(params.properties[k][2], mi.Sensor))
    params[key] = type(params[key])(params[key]) @ T().translate([0.05, 0, 0]) \
        @ T().rotate([0, 1, 0], 1.0)
    params.update()
    sensor = scene.sensors()[0]
    watch = camera._CAMERAS[id(sensor)][1]    # the sensor's ParamWatch, kept per sensor
    reads = []
    read = watch.read
    watch.read = lambda: reads.append(1) or read()
    try:
        img = np.asarray(mi.render(scene, integrator=integ, spp=2))
    finally:
        del watch.read
    assert integ.stats["pages_built"] > 0        # a moved frame: marked and built anew
    assert len(reads) == 1
    virtual.PAGE_CACHE.clear()
    fresh = shadowmap(method="hard", cache_maps=False)
    assert np.array_equal(img, np.asarray(mi.render(scene, integrator=fresh, spp=2)))
