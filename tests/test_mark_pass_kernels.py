"""The mark pass of a camera move (virtual maps, issue 11): what it traces and how many
kernels it launches, with the marks, texels and images it gave before."""
from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from mi_shadowmap import virtual
from mi_shadowmap.control_flow import if_stmt
from mi_shadowmap.virtual import marks, planner

from conftest import SCENES

T = mi.ScalarTransform4f


def shadowmap(**kw):
    return mi.load_dict({"type": "shadowmap", **kw})


def _moved_scene(k: int = 1):
    """far_point at 64^2 (a point light, the biases capped and probed per pixel), its
    camera moved sideways and turned ``k`` times a small step."""
    scene = mi.load_file(str(SCENES / "far_point.xml"), width=64, height=64)
    params = mi.traverse(scene)
    key = next(k for k in params.keys() if k.endswith("to_world")
               and isinstance(params.properties[k][2], mi.Sensor))
    params[key] = type(params[key])(params[key]) @ T().translate([0.05 * k, 0, 0]) \
        @ T().rotate([0, 1, 0], 1.0 * k)
    params.update()
    return scene


def _probe_keeps_unrolled(scene, view, p, n, dp_dx, dp_dy, length, active, shape=None,
                          eye=None):
    """:func:`marks.probe_keeps` as it was, its four corners unrolled (the reference)."""
    own = None
    if shape is not None:
        own = dr.select(dr.dot(n, view.direction_to_light(p)) < 0, shape, mi.ShapePtr(None))
    hit0 = marks.probe_distance(scene, view, p, n, active, own)
    keep = mi.Bool(active) & (hit0 < mi.Float(length) * marks.PROBE_MARGIN)
    shadowed = dr.isfinite(hit0)
    for a in (-0.5, 0.5):
        for b in (-0.5, 0.5):
            c = p + dp_dx * a + dp_dy * b
            corner = marks.probe_distance(scene, view, c, n, active & ~keep, own)
            differs = mi.Bool(active) & ~keep & (dr.isfinite(corner) != shadowed)
            if eye is not None and shape is not None:
                differs = if_stmt(
                    (c, n, differs, shadowed, own, shape, eye), differs,
                    lambda c, n, d, s, o, sh, e: marks._surface_corner_differs(
                        scene, view, c, n, d, s, o, sh, e),
                    lambda c, n, d, s, o, sh, e: d)
            keep |= differs
    return keep


def test_the_corner_probes_are_traced_once_with_the_same_marks(monkeypatch):
    """The four corners of a pixel's footprint are probed in a loop, traced once: a
    moved frame traced ``probe_distance`` nine times (the centre, four corners, four
    corners again from the surface) and its mark kernel held 1616 operations on
    far_point at 256^2, 1059 with the corners looped. Marks, texels and image are those
    of the unrolled corners."""
    scene = _moved_scene()
    calls = []
    traced = marks.probe_distance

    def counting(*args, **kw):
        calls.append(1)
        return traced(*args, **kw)

    monkeypatch.setattr(marks, "probe_distance", counting)
    virtual.PAGE_CACHE.clear()
    looped = shadowmap(method="hard", cache_maps=False)
    img = np.asarray(mi.render(scene, integrator=looped, spp=2))
    n_traced = len(calls)
    monkeypatch.setattr(marks, "probe_keeps", _probe_keeps_unrolled)
    unrolled = shadowmap(method="hard", cache_maps=False)
    ref = np.asarray(mi.render(scene, integrator=unrolled, spp=2))
    print("probe_distance traced", n_traced, "times (unrolled:", len(calls) - n_traced, ")")
    assert 0 < n_traced <= 3
    assert np.array_equal(img, ref)
    for key in ("texels_built", "pages_marked", "pages_built"):
        assert looped.stats[key] == unrolled.stats[key], key


def _watch_before_marks(monkeypatch) -> tuple:
    """``(camera_hits, marked_points, before)``: the planner's own two functions, which
    ``monkeypatch`` replaces by watchers, and the list that receives, at the first call of
    ``marked_points``, the JIT kernels launched since ``camera_hits`` was called."""
    hits, points = planner.camera_hits, planner.marked_points
    before = []

    def hits_first(*args, **kw):
        dr.kernel_history()                 # (emptied: the mark pass's kernels from here)
        return hits(*args, **kw)

    def points_after(*args, **kw):
        if not before:
            before.append([k for k in dr.kernel_history()
                           if k["type"] == dr.KernelType.JIT])
        return points(*args, **kw)

    monkeypatch.setattr(planner, "camera_hits", hits_first)
    monkeypatch.setattr(planner, "marked_points", points_after)
    return hits, points, before


def test_a_moves_mark_pass_launches_the_hits_then_three_kernels_over_its_pixels(monkeypatch):
    """The camera hits are evaluated in a kernel of their own, launched before any light's
    marks are traced (the thread pool runs it while the host traces them); the marked
    points are evaluated in the kernel that scatters their keys into the dedupe's first
    tables, and the pixels' words (``planner._pixel_keeps``) in its second round: a moved
    frame's mark pass (camera hits to the dedupe's host reads) launches four kernels over
    its pixels, the first of them before ``marked_points`` is called, where it launched
    five (the points, the words, three dedupe rounds) and then three (the hits in the
    first round's). The kept points' rings, which read the words, ride in the second and
    third (``dedupe_many``'s ``late``). The image and texels are those of the hits traced
    into the first round and of the kernels apart."""
    scene = _moved_scene()
    tiles = planner.block_tiles
    hits, points, before_marks = _watch_before_marks(monkeypatch)
    seen = []

    def tiles_after(*args, **kw):
        if not seen:
            seen.append(before_marks[0] + [k for k in dr.kernel_history()
                                           if k["type"] == dr.KernelType.JIT])
        return tiles(*args, **kw)

    monkeypatch.setattr(planner, "block_tiles", tiles_after)
    virtual.PAGE_CACHE.clear()
    integ = shadowmap(method="hard", cache_maps=False)
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        img = np.asarray(mi.render(scene, integrator=integ, spp=2))
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    wide = [k for k in seen[0] if k["size"] >= 64 * 64]
    print("mark pass kernels (size, operations):",
          [(k["size"], k["operation_count"]) for k in seen[0]])
    assert sum(k["size"] >= 64 * 64 for k in before_marks[0]) == 1, \
        "the camera hits were not launched (alone) before the marks were traced"
    assert len(wide) == 4
    monkeypatch.setattr(planner, "marked_points", points)
    monkeypatch.setattr(planner, "block_tiles", tiles)

    # the references: the hits traced into the first round's kernel (as they were) ...
    def hits_fused(*args, **kw):
        return hits(*args, **{**kw, "evaluate": False})

    monkeypatch.setattr(planner, "camera_hits", hits_fused)
    fused = shadowmap(method="hard", cache_maps=False)
    assert np.array_equal(img, np.asarray(mi.render(scene, integrator=fused, spp=2)))
    # ... and the points, then the words, each evaluated alone before the dedupe
    dedupe = planner.dedupe_many

    def apart(groups, bits=14, parts=None, first=(), second=None, late=None):
        dr.eval(*first)
        if second is not None:
            dr.eval(*second())
        # the kept points' rings (planner._kept_read) as groups of the first round
        return dedupe(groups + (list(late()) if late is not None else []), bits, parts)

    monkeypatch.setattr(planner, "camera_hits", hits)
    monkeypatch.setattr(planner, "dedupe_many", apart)
    ref = shadowmap(method="hard", cache_maps=False)
    assert np.array_equal(img, np.asarray(mi.render(scene, integrator=ref, spp=2)))
    for key in ("texels_built", "pages_marked", "pages_built"):
        assert ref.stats[key] == integ.stats[key] == fused.stats[key], key


def test_the_dedupe_reads_its_stored_keys_with_the_same_marks(monkeypatch):
    """The dedupe's first kernel stores the candidates' keys (``STORED_KEY_BYTES``) and
    its second and third read them back, where they recomputed each key from the mark
    pass's stored points (29 bytes a candidate, and the key's operations: the third
    kernel of a room_two_points camera move 214 -> 46 operations). A first frame and a
    move of room_two_points (two point lights: two candidate lists) give the image,
    texels, pages and level histogram of the recomputed keys, and the later kernels hold
    fewer operations."""
    scene = mi.load_file(str(SCENES / "room_two_points.xml"), width=64, height=64)
    params = mi.traverse(scene)
    key = next(k for k in params.keys() if k.endswith("to_world")
               and isinstance(params.properties[k][2], mi.Sensor))
    start = type(params[key])(params[key])
    keys = ("texels_built", "pages_marked", "pages_built", "pages_reused")

    def frames(stored_bytes):
        monkeypatch.setattr(marks, "STORED_KEY_BYTES", stored_bytes)
        virtual.PAGE_CACHE.clear()
        integ = shadowmap(method="hard", cache_maps=False)
        out, ops = [], []
        for k in (0, 1):
            params[key] = start @ T().translate([0.05 * k, 0, 0]) @ T().rotate([0, 1, 0], k)
            params.update()
            dr.kernel_history()
            out.append((np.asarray(mi.render(scene, integrator=integ, spp=2)),
                        tuple(integ.stats[n] for n in keys),
                        str(integ.stats["level_histogram"])))
            ops.append([h["operation_count"] for h in dr.kernel_history()
                        if h["type"] == dr.KernelType.JIT and h["size"] == 64 * 64])
        return out, ops

    flag = dr.flag(dr.JitFlag.KernelHistory)
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        stored, ops = frames(1 << 23)
        recomputed, ops_ref = frames(0)
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, flag)
        params[key] = start
        params.update()
    for (img, stats, hist), (img_ref, stats_ref, hist_ref) in zip(stored, recomputed):
        assert np.array_equal(img, img_ref)
        assert stats == stats_ref
        assert hist == hist_ref
    print("mark pass kernels' operations, stored keys:", ops[1], "recomputed:", ops_ref[1])
    # (the camera hits, then the dedupe's three rounds)
    assert len(ops[1]) == len(ops_ref[1]) == 4
    assert ops[1][2] < ops_ref[1][2] and ops[1][3] < ops_ref[1][3]


def test_a_lens_cameras_hits_are_traced_into_the_mark_kernel(monkeypatch):
    """Through a lens the mark pass traces every pixel through 3 x 3 points of the lens
    (``marks.LENS_GRID``), so its camera hits are 9 lanes a pixel (their points, normals,
    footprints and validity, about 49 bytes a lane); evaluated in a kernel of their own
    they are stored and held through the mark pass (a 1024^2 thinlens frame of
    room_two_points: peak RSS 1.78 -> 2.22 GiB; a pinhole's 1024^2 509 -> 563 MiB,
    2048^2 1413 -> 1624 MiB). A lens camera's first frame is to trace them into the
    marks' kernel, as before: no kernel over its lanes before ``marked_points``."""
    scene = mi.load_file(str(SCENES / "far_point.xml"), width=32, height=32)
    sensor = mi.load_dict({
        "type": "thinlens", "fov": 40.0, "aperture_radius": 0.05, "focus_distance": 5.0,
        "to_world": T().look_at(origin=[0, 2, 6], target=[0, 0, 0], up=[0, 1, 0]),
        "film": {"type": "hdrfilm", "width": 32, "height": 32, "rfilter": {"type": "box"}}})
    _, _, before_marks = _watch_before_marks(monkeypatch)
    virtual.PAGE_CACHE.clear()
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        mi.render(scene, sensor=sensor, integrator=shadowmap(method="hard",
                                                             cache_maps=False), spp=1)
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    assert before_marks
    lanes = 32 * 32 * marks.LENS_GRID ** 2
    assert not [k for k in before_marks[0] if k["size"] >= lanes], \
        "the lens camera's hits were evaluated alone before the marks were traced"
