"""Every scene kernel against the slow numpy references in tests/naive/scene_kernels.py."""

from __future__ import annotations

import math

import numpy as np
import pytest
from numba import njit

from evchain.kernels.scene_culling import frame_boxes
from evchain.kernels.scene_geometry import road_coords
from evchain.kernels.scene_render import (
    flow_terms,
    level_work,
    render_rows,
    row_vmax2,
    visible_columns,
)
from evchain.kernels.scene_shading import (
    box_albedo,
    box_pass,
    ground_levels,
    ground_pass,
    hash3,
)
from evchain.kernels.scene_truth import trace
from evchain.sim.drive import Scene
from tests.naive import scene_kernels as N

SCENES = {
    "high-rise": dict(scenario="high-rise", start_m=150.0),
    "orange-lines": dict(scenario="high-rise-orange", extra_vertical_lines=True, start_m=200.0),
    "open-field": dict(scenario="open-field", start_m=40.0),
    "curves": dict(scenario="curves", dynamics="curves", start_m=80.0),
    "pitch": dict(scenario="high-rise", dynamics="pitch", pitch_amplitude_deg=4.0),
    "rotation": dict(scenario="high-rise", dynamics="rotation", speed_mps=0.0, duration_s=4.0,
                     start_m=150.0, pan_dps=15.0, tilt_dps=5.0, rotation_start_s=0.2),
}


def tiny(name, **kw):
    return Scene.from_params(width=16, height=12, supersample=2, **{**SCENES[name], **kw})


def test_hash():
    rng = np.random.default_rng(1)
    i = rng.integers(-10**6, 10**6, 200)
    j = rng.integers(-10**6, 10**6, 200)
    for a, b in zip(i, j, strict=True):
        assert hash3(a, b, 7) == N.hash3(a, b, 7)


@njit(cache=True, error_model="numpy", inline="always")
def _tex_lookup(tex, x, y, inv, off, mask):
    """Nearest texel of a repeating texture level at world (x, y)."""
    i = np.int64(math.floor(x * inv)) & mask
    j = np.int64(math.floor(y * inv)) & mask
    return tex[off + j * (mask + 1) + i]


@njit(cache=True, error_model="numpy")
def ground_albedo_at(x, y, segs, ground, tex, lv_inv, lv_off, lv_mask):
    """The ground's albedo at one point, as the renderer's ``ground_pass`` computes it for a
    row of samples (the noise from the mip levels chosen by ``ground_levels``)."""
    s, d = road_coords(x, y, segs)
    w = abs(d - ground[0])
    seed = np.int64(ground[8])
    hw = ground[1]
    lw = ground[2] * 0.5
    if w < hw:
        if w < lw:
            per = ground[6]
            if s - per * math.floor(s / per) < ground[5]:
                return 0.75
        if abs(w - ground[3]) < lw:
            return 0.75
        return 0.16 + _tex_lookup(tex, x, y, lv_inv[0], lv_off[0], lv_mask[0])
    sw = ground[4]
    if w < hw + sw:
        if w < hw + 0.3:
            return 0.45
        sl = 1.2
        u = s - sl * math.floor(s / sl)
        v = (w - hw) - sl * math.floor((w - hw) / sl)
        if u < 0.05 or v < 0.05:
            return 0.2
        return 0.36 + 0.1 * (hash3(np.int64(math.floor(s / sl)),
                                     np.int64(math.floor((w - hw) / sl)), seed + 3) - 0.5)
    if ground[7] == 0.0:
        return 0.1 + _tex_lookup(tex, x, y, lv_inv[1], lv_off[1], lv_mask[1])
    return 0.3 + _tex_lookup(tex, x, y, lv_inv[2], lv_off[2], lv_mask[2])


@pytest.mark.parametrize("name", ["high-rise", "curves"])
def test_road_coords_and_ground(name):
    sc = tiny(name)
    rng = np.random.default_rng(2)
    x = rng.uniform(-50, 300, 400)
    y = rng.uniform(-80, 250, 400)
    got = np.array([road_coords(a, b, sc.segs) for a, b in zip(x, y, strict=True)])
    s, d = N.road_coords(x, y, sc.segs)
    np.testing.assert_allclose(got[:, 0], s, atol=1e-9)
    np.testing.assert_allclose(got[:, 1], d, atol=1e-9)
    lv_inv, lv_off, lv_mask = level_work(3)
    lit = sc.light[4] + sc.light[3] * max(sc.light[2], 0.0)
    for fp in (0.0, 0.05, 0.3, 2.0, 1e3):
        ground_levels(fp, sc.tex_inv, sc.tex_off, lv_inv, lv_off, lv_mask)
        want = N.ground_albedo(x, y, np.full(400, fp), sc.segs, sc.ground, sc.tex, sc.tex_inv,
                               sc.tex_off)
        got = [ground_albedo_at(a, b, sc.segs, sc.ground, sc.tex, lv_inv, lv_off, lv_mask)
               for a, b in zip(x, y, strict=True)]
        np.testing.assert_allclose(got, want, atol=1e-12)
        acc = np.zeros(400)
        ground_pass(np.ones(400, np.int32), x, y, 1.0, 0.0, 0.0, np.arange(400), sc.segs,
                    sc.ground, sc.light, sc.tex, lv_inv, lv_off, lv_mask, acc)
        np.testing.assert_allclose(acc / lit, want, atol=1e-12)


def test_ground_textures_are_mip_mapped_noise():
    """Level 0 is the sum of the value-noise octaves; every level is the 2x2 mean of the one
    below; coarse levels fade to the mean (a pre-filter instead of per-sample noise)."""
    from evchain.sim.world import GROUND_TEXTURES, TEX_LEVELS, TEX_N, ground_textures

    tex, inv, off = ground_textures(11)
    for k, (texel, octaves) in enumerate(GROUND_TEXTURES):
        assert inv[k] == 1.0 / texel
        jj, ii = np.mgrid[0:TEX_N, 0:TEX_N]
        want = sum(a * (N.hash3(ii // c, jj // c, 11 + s) - 0.5) for c, a, s in octaves)
        lv0 = tex[off[k, 0]:off[k, 0] + TEX_N * TEX_N].reshape(TEX_N, TEX_N)
        np.testing.assert_allclose(lv0, want, atol=1e-7)
        for lv in range(1, TEX_LEVELS):
            n = TEX_N >> lv
            img = tex[off[k, lv]:off[k, lv] + n * n].reshape(n, n)
            below = tex[off[k, lv - 1]:off[k, lv - 1] + 4 * n * n].reshape(2 * n, 2 * n)
            np.testing.assert_allclose(img, below.reshape(n, 2, n, 2).mean(axis=(1, 3)),
                                       atol=1e-6)
        top = tex[off[k, -1]]
        assert abs(top) < 0.02 and lv0.std() > 5 * abs(top)


def test_box_albedo_all_materials():
    rng = np.random.default_rng(3)
    for mat in range(5):
        par = np.array([0.5, 3.1, 2.3, 0.4])
        u = rng.uniform(-100, 100, 300)
        z = rng.uniform(0, 60, 300)
        # point values, footprints within a column, across a few and across many columns
        wu = np.concatenate([np.zeros(75), rng.uniform(0, 1, 75), rng.uniform(1, 10, 75),
                             rng.uniform(10, 300, 75)])
        got = [box_albedo(mat, *par, 5, a, b, w) for a, b, w in zip(u, z, wu, strict=True)]
        want = N.box_albedo(np.full(300, mat), np.tile(par, (300, 1)), 5, u, z, wu)
        np.testing.assert_allclose(got, want, atol=1e-12, err_msg=f"material {mat}")


def test_box_albedo_footprint_limits():
    """A vanishing footprint gives the value at u (away from edges); a footprint of whole
    window columns gives their exact mean; the average never leaves the albedos' range."""
    par = np.array([0.5, 3.1, 2.3, 0.4])
    z = 3.1 * 4 + 0.5 * 3.1                    # a window row of floor 4
    for u in (2.3 * 7 + 0.5 * 2.3, 2.3 * 7 + 0.05 * 2.3):   # a window's middle, the wall
        # lengths in the footprint round to eps |u|, relative to it eps |u| / wu ~ 1e-9
        assert box_albedo(1, *par, 5, u, z, 1e-6) == pytest.approx(
            box_albedo(1, *par, 5, u, z, 0.0), abs=1e-8)
    c0, c1 = 3, 11
    mean = box_albedo(1, *par, 5, (c0 + c1 + 1) * 2.3 / 2, z, (c1 + 1 - c0) * 2.3)
    wall = 0.5 + 0.06 * (hash3(4, 5, 77) - 0.5)
    wins = [0.06 + 0.2 * hash3(c, 4, 5) for c in range(c0, c1 + 1)]
    assert mean == pytest.approx(0.4 * wall + 0.6 * np.mean(wins), abs=1e-12)
    rng = np.random.default_rng(4)
    for mat in (1, 2, 3):
        v = [box_albedo(mat, *par, 5, u, z, w)
             for u, w in zip(rng.uniform(-50, 50, 200), rng.uniform(0, 100, 200), strict=True)]
        assert min(v) >= 0.06 - 1e-12 and max(v) <= 0.5 * 1.03 + 1e-12


def test_box_pass_vs_naive_albedo():
    """The box pass (window grid written out with cached hashes, footprint t gxs / t gys) equals
    the numpy box_albedo per sample: all faces and materials, runs of samples on one box and
    floor (the caches), footprints from zero to beyond the 64-column cap."""
    rng = np.random.default_rng(5)
    n = 4000
    box_mat = np.array([0, 1, 2, 3, 4, 1])
    box_par = np.array([[0.4, 3.0, 2.2, 0.3], [0.5, 3.1, 2.3, 0.4], [0.6, 3.3, 2.6, 0.4],
                        [0.55, 2.9, 2.1, 0.4], [0.3, 0.6, 1.1, 0.2], [0.45, 3.5, 3.0, 0.4]])
    hid = np.repeat(rng.integers(0, 6, n // 20), 20).astype(np.int32)     # runs on one box
    fc = np.repeat(rng.integers(0, 6, n // 10), 10).astype(np.int32)
    kd = np.where(rng.random(n) < 0.9, 2, 1).astype(np.int32)
    tb = np.repeat(rng.uniform(5, 300, n // 40), 40) + rng.uniform(0, 0.5, n)
    dxs, dys = rng.normal(0, 1, n), rng.normal(0, 1, n)
    scale = np.exp(rng.uniform(np.log(1e-12), np.log(5.0), n))
    scale[:200] = 0.0                                               # point samples
    gxs, gys = scale * rng.uniform(0.5, 2, n), scale * rng.uniform(0.5, 2, n)
    ox, oy, oz, dz = 3.0, -7.0, 1.2, 0.05
    lit = rng.uniform(0.3, 1.0, 6)
    acc = np.zeros(n)
    box_pass(kd, tb, hid, fc, dxs, dys, gxs, gys, ox, oy, oz, dz, np.arange(n), box_mat,
             box_par, lit, acc)
    side = fc < 4
    u = np.where(fc < 2, oy + tb * dys, ox + tb * dxs)
    z = oz + tb * dz
    wu = np.where(fc < 2, tb * gys, tb * gxs)
    want = N.box_albedo(box_mat[hid], box_par[hid], hid, u, z, wu)
    want = np.where(side, want, 0.8 * box_par[hid, 0]) * lit[fc] * (kd == 2)
    # lengths within the footprint round to eps |u|: relative to it eps |u| / wu
    tol = 1e-12 + 1e-15 * (np.abs(u) + 1.0) / np.maximum(wu, 1e-300)
    assert (np.abs(acc - want) <= tol).all()
    assert (np.abs(acc - want)[wu > 0.1] <= 1e-12).all()

def _trace_all(o, d, boxes):
    return np.array([trace(o[0], o[1], o[2], *r, boxes) for r in d])


def test_trace_random_and_axis_rays():
    sc = tiny("high-rise")
    rng = np.random.default_rng(4)
    o = np.array([150.0, -1.75, 1.2])
    d = rng.normal(size=(500, 3))
    d[:100, 1:] = 0.0          # along x only
    d[100:150, 0] = 0.0        # in the y-z plane
    d[150:200, 2] = 0.0        # horizontal
    d[200:220] = [[0.0, 0.0, -1.0]] * 20
    got = _trace_all(o, d, sc.boxes)
    t, kind, idx, face = N.trace(o, d, sc.boxes)
    np.testing.assert_allclose(got[:, 0], t, rtol=1e-12)
    np.testing.assert_array_equal(got[:, 1], kind)
    np.testing.assert_array_equal(got[:, 2], idx)
    np.testing.assert_array_equal(got[:, 3], face)


def test_trace_hits_known_box_faces():
    boxes = np.array([[10.0, -1.0, 0.0, 12.0, 1.0, 2.0]])
    o = np.array([0.0, 0.0, 1.0])
    got = _trace_all(o, np.array([[1.0, 0.0, 0.0], [1.0, 0.05, 0.0], [-1.0, 0.0, 0.0],
                                  [1.0, 0.0, 0.2], [1.0, 0.0, -0.05]]), boxes)
    assert tuple(got[0]) == (10.0, 2, 0, 0)          # near x face
    assert got[1, 0] == pytest.approx(10.0 / 1.0) and got[1, 3] == 0
    assert tuple(got[2, 1:]) == (0, -1, -1)          # backwards: sky
    assert got[3, 1] == 0                            # passes over the box
    assert got[4, 1] == 2 and got[4, 0] == pytest.approx(10.0)


@pytest.mark.parametrize("name", sorted(SCENES))
def test_camera_state_vs_naive_pose(name):
    sc = tiny(name)
    for t in (0.0, 0.37, 1.9, 3.3):
        pos, rot, vc, wc = sc.state(t)
        p, r = N.pose(t, sc.segs, sc.traj)
        np.testing.assert_allclose(pos, p, atol=1e-9)
        np.testing.assert_allclose(rot, r, atol=1e-12)
        # velocities against central differences of the naive pose
        h = 1e-6
        p1, r1 = N.pose(t + h, sc.segs, sc.traj)
        p0, r0 = N.pose(t - h, sc.segs, sc.traj)
        np.testing.assert_allclose(vc, r.T @ (p1 - p0) / (2 * h), atol=1e-5)
        omega = r.T @ ((r1 - r0) / (2 * h))        # skew matrix of the angular velocity
        np.testing.assert_allclose(wc, [omega[2, 1], omega[0, 2], omega[1, 0]], atol=1e-5)


@pytest.mark.parametrize("name", sorted(SCENES))
def test_render_tiny_vs_naive(name):
    sc = tiny(name)
    for t in (0.0, 1.3):
        frame, vmax = sc.render(t)
        want = N.render(sc, t)
        np.testing.assert_allclose(frame, want, rtol=2e-6, atol=2e-6)
        resting = t < SCENES[name].get("rotation_start_s", 0.0)   # standing still
        assert (vmax == 0) if resting else (vmax > 0)


def test_truth_depth_and_flow_vs_naive():
    sc = tiny("pitch")
    from evchain.sim.truth import SceneTruth

    truth = SceneTruth(sc)
    rng = np.random.default_rng(5)
    x = rng.uniform(-0.5, 15.5, 300)
    y = rng.uniform(-0.5, 11.5, 300)
    for t in (0.6, 2.2):
        depth, vx, vy = truth.depth_and_flow(x, y, t * 1e6)
        np.testing.assert_allclose(depth, N.depth(x, y, t, sc), rtol=1e-12)
        ok = np.isfinite(depth)
        fx, fy = N.flow_fd(x[ok], y[ok], t, sc)
        np.testing.assert_allclose(vx[ok], fx, atol=1e-3 * (1 + np.abs(fx).max()))
        np.testing.assert_allclose(vy[ok], fy, atol=1e-3 * (1 + np.abs(fy).max()))


OBJECT_SCENES = {**SCENES, "car-ahead": dict(scenario="high-rise", start_m=255.0)}


def _object_scene(name):
    return Scene.from_params(width=64, height=48, supersample=1, **OBJECT_SCENES[name])


@pytest.mark.parametrize("name", sorted(OBJECT_SCENES))
def test_truth_object_id_vs_naive_random(name):
    """The id of the surface seen (box index, -2 ground, -1 sky) at random pixel positions
    (also just outside the image) equals the naive trace's, every box against every ray."""
    from evchain.sim.truth import SceneTruth

    sc = _object_scene(name)
    truth = SceneTruth(sc)
    rng = np.random.default_rng(8)
    x = rng.uniform(-3, 66, 600)
    y = rng.uniform(-3, 50, 600)
    for t in (0.0, 0.9):
        got = truth.object_id(x, y, t * 1e6)
        assert got.dtype == np.int64
        np.testing.assert_array_equal(got, N.object_id(x, y, t, sc))
    if name == "car-ahead":
        assert np.isin(got, truth.obstacle_ids).any()


def _edge_points(box):
    """Corners, edge midpoints and face centres of a box [6] (world, [26, 3])."""
    lo, hi = np.asarray(box[:3]), np.asarray(box[3:])
    grid = np.stack(np.meshgrid(*[(a, (a + b) / 2, b) for a, b in zip(lo, hi, strict=True)],
                                indexing="ij"), -1).reshape(-1, 3)
    return np.delete(grid, 13, axis=0)           # all but the box's centre


@pytest.mark.parametrize("name", ["car-ahead", "pitch", "open-field"])
def test_truth_object_id_vs_naive_hard(name):
    """Rays grazing box edges and corners, through face centres (the car's too), along the
    horizon and into sky and ground: at 1e-6 px off a projected edge (never on it) kernel and
    naive agree exactly; exactly on it the kernel sees one of the surfaces around it."""
    from evchain.sim.truth import OBJECT_GROUND, OBJECT_SKY, SceneTruth

    sc = _object_scene(name)
    truth = SceneTruth(sc)
    cam = sc.camera
    e = 1e-6
    offsets = np.array([(e, 0.37 * e), (-e, -0.37 * e), (0.37 * e, -e), (-0.37 * e, e)])
    car_edge_crossed = False
    for t in (0.4, 1.1):
        pts = np.concatenate([_edge_points(b) for b in sc.boxes])
        pos, rot, _, _ = sc.state(t)
        depth = (pts - pos) @ rot[:, 2]
        uv = sc.project(pts[depth > 0.5], t)
        inside = ((uv[:, 0] > -0.5) & (uv[:, 0] < cam.width - 0.5) & (uv[:, 1] > -0.5)
                  & (uv[:, 1] < cam.height - 0.5))
        uv = uv[inside]
        # along the horizon row and just off it, top and bottom rows
        xs = np.linspace(-0.5, cam.width - 0.5, 9)
        for row in (cam.cy - 1e-6, cam.cy, cam.cy + 1e-6, -0.5, cam.height - 0.5):
            uv = np.concatenate([uv, np.stack([xs, np.full(9, row)], 1)])
        assert len(uv) > 50
        near = uv[:, None, :] + offsets[None]                      # [n, 4, 2]
        got_near = truth.object_id(near[..., 0], near[..., 1], t * 1e6)
        want_near = N.object_id(near[..., 0].ravel(), near[..., 1].ravel(), t, sc).reshape(-1, 4)
        np.testing.assert_array_equal(got_near, want_near)
        got = truth.object_id(uv[:, 0], uv[:, 1], t * 1e6)
        want = N.object_id(uv[:, 0], uv[:, 1], t, sc)
        seen = np.concatenate([want[:, None], want_near], 1)
        assert ((seen == got[:, None]).any(axis=1)).all()
        on_car = np.isin(want_near, truth.obstacle_ids)
        car_edge_crossed |= bool((on_car.any(axis=1) & ~on_car.all(axis=1)).any())
        if name == "open-field":       # level camera: the horizon ray runs parallel to the
            top, bottom = got[-18:-9], got[-9:]        # ground; top row sky, bottom row ground
            assert (top == OBJECT_SKY).all() and (bottom == OBJECT_GROUND).all()
    if name == "car-ahead":          # the car's outline was among the grazing rays
        assert car_edge_crossed
        body = int(truth.obstacle_ids[0])
        x0, y0, z0, x1, y1, z1 = sc.boxes[body]
        uv = sc.project(np.array([[x0, (y0 + y1) / 2, (z0 + z1) / 2]]), 1.1)[0]
        assert truth.object_id(uv[0], uv[1], 1.1e6) == body


def test_parallel_render_is_identical():
    serial = Scene.from_params(width=40, height=30, start_m=100.0)
    parallel = Scene.from_params(threads=2, width=40, height=30, start_m=100.0)
    a, va = serial.render(0.4)
    b, vb = parallel.render(0.4)
    np.testing.assert_array_equal(a, b)
    assert va == vb


@pytest.mark.parametrize("name", sorted(SCENES))
def test_render_larger_frames_vs_naive(name):
    """48x36 frames (2x2): the per-row spans and early exits of the renderer against testing
    every box for every sample, at the start (boxes close to the camera) and later."""
    sc = Scene.from_params(width=48, height=36, supersample=2, **SCENES[name])
    for t in (0.0, 0.9):
        frame, _ = sc.render(t)
        np.testing.assert_allclose(frame, N.render(sc, t), rtol=2e-6, atol=2e-6)


def test_visible_columns_vs_naive():
    """The column range of each visible box against the numpy reference: random rectangles,
    unbounded sides (a box reaching behind the camera), rectangles beyond either edge."""
    rng = np.random.default_rng(6)
    f, cx, k, w = 300.0, 31.5, 2, 64
    n = w * k
    bbox = np.sort(rng.uniform(-0.3, 0.3, (60, 2)), axis=1)
    bbox = np.concatenate([bbox, np.zeros((60, 2))], axis=1)
    bbox[:5, 0] = -np.inf
    bbox[5:10, 1] = np.inf
    bbox[10:12, :2] = [[-1e9, 1e9], [-np.inf, np.inf]]
    bbox[12:14, :2] = [[-0.5, -0.2], [0.2, 0.6]]          # left of, right of the image
    vis = rng.permutation(60)[:50]
    got = visible_columns(vis, bbox, f, cx, k, n)
    np.testing.assert_array_equal(got, N.visible_columns(vis, bbox, f, cx, k, n))


@pytest.mark.parametrize("name", ["high-rise", "rotation", "pitch"])
def test_visible_columns_cover_every_hit(name):
    """Every sample whose ray hits a box (the numpy trace against that box alone, nearest or
    not) lies in the box's column range, so the renderer's restriction to it loses no hit."""
    sc = Scene.from_params(width=40, height=30, supersample=2, **SCENES[name])
    cam = sc.camera
    k, n = 2, 80
    for t in (0.0, 0.6, 1.9):
        pos, rot, _, _ = sc.state(t)
        nb = len(sc.boxes)
        order, minz, bbox = np.zeros(nb, np.int64), np.zeros(nb), np.zeros((nb, 4))
        nvis = frame_boxes(sc.boxes, pos, rot, cam.f, cam.cx, cam.cy, cam.width, cam.height,
                           order, minz, bbox)
        vcol = visible_columns(order[:nvis], bbox, cam.f, cam.cx, k, n)
        col = dict(zip(order[:nvis].tolist(), vcol.tolist(), strict=True))
        xs, ys = np.meshgrid((np.arange(n) + 0.5) / k - 0.5, (np.arange(60) + 0.5) / k - 0.5)
        d = N.rays(xs.ravel(), ys.ravel(), cam.f, cam.cx, cam.cy, rot)
        c = np.tile(np.arange(n), 60)
        hits = 0
        for b, box in enumerate(sc.boxes):
            _, kind, _, _ = N.trace(pos, d, box[None])
            hit = c[kind == 2]
            if len(hit):
                assert b in col, (t, b)
                assert col[b][0] <= hit.min() and hit.max() <= col[b][1], (t, b, col[b])
                hits += 1
        assert hits > 3


def _with_boxes(sc, boxes, mats):
    """The scene with its boxes replaced (materials mats, default parameters of each)."""
    par = {0: (0.3, 0, 0, 0), 1: (0.35, 3.2, 2.5, 0), 2: (0.5, 3.2, 2.5, 0), 3: (0.5, 3.2, 2.5, 0),
           4: (0.4, 0.9, 1.3, 0.3)}
    sc.boxes = np.array(boxes, np.float64).reshape(-1, 6)
    sc.box_mat = np.array(mats, np.int64)
    sc.box_par = np.array([par[m] for m in mats], np.float64).reshape(-1, 4)
    sc._own = sc._scratch()
    return sc


@pytest.mark.parametrize("k", [1, 2])
def test_render_hard_geometry_vs_naive(k):
    """Frames whose boxes put the camera exactly on face planes, reach behind the camera, are
    seen along rays parallel to their faces (odd width, k = 1: the centre sample's ray runs
    along world x) or enclose the camera: renderer = every ray against every box, no NaN.
    (Not compared: a ray lying *in* a face plane, e.g. the level centre row at exactly a box's
    bottom height: its slab bound is 0 * inf = NaN, a grazing hit for the renderer and the
    truth, a miss for numpy's maximum.)"""
    for threads in (1, 2):
        sc = Scene.from_params(threads=threads, scenario="high-rise", width=33, height=25,
                               supersample=k, start_m=100.0)
        pos, _, _, _ = sc.state(0.0)
        x, y, z = pos
        boxes = [
            (x - 5, y, 0, x + 30, y + 4, 8),            # y-face through the camera, behind it too
            (x + 10, y - 6, z + 0.5, x + 14, y - 2, z + 3),   # centre row parallel to faces
            (x, y + 6, 0, x + 8, y + 9, 20),            # x-face through the camera centre
            (x - 20, y - 9, 0, x - 2, y - 7, 5),        # entirely behind
            (x + 40, y - 0.5, 0, x + 41, y + 0.5, z),   # top face at the camera height, ahead
            (x + 60, y - 30, 0, x + 70, y + 30, 40),    # wall closing the view
        ]
        _with_boxes(sc, boxes, [1, 4, 2, 0, 3, 1])
        frame, vmax = sc.render(0.0)
        assert np.isfinite(frame).all() and np.isfinite(vmax)
        np.testing.assert_allclose(frame, N.render(sc, 0.0), rtol=2e-6, atol=2e-6)
        # a camera inside a box: nothing but the box's inside (no NaN either way)
        _with_boxes(sc, [(x - 1, y - 1, 0, x + 1, y + 1, 3)] + boxes, [0, 1, 4, 2, 0, 3, 1])
        frame, vmax = sc.render(0.0)
        assert np.isfinite(frame).all() and np.isfinite(vmax)
        np.testing.assert_allclose(frame, N.render(sc, 0.0), rtol=2e-6, atol=2e-6)


def test_row_speed_maximum_vs_naive():
    """row_vmax2 (an integer maximum over the bit patterns) = the float maximum, exactly, on
    random rows and on rows with sky (inf depth), zero depths (NaN or inf speed), one sample,
    no rotation and only NaN."""
    rng = np.random.default_rng(3)
    for trial in range(60):
        n = int(rng.integers(1, 700))
        xbs = rng.uniform(-0.6, 0.6, n)
        yb = float(rng.uniform(-0.4, 0.4))
        tb = rng.uniform(0.5, 200.0, n)
        vc = rng.normal(0, 10, 3)
        wc = rng.normal(0, 0.5, 3) if trial % 2 else np.zeros(3)
        if trial % 3 == 0:
            tb[rng.random(n) < 0.3] = np.inf
        if trial % 5 == 0:
            tb[rng.random(n) < 0.1] = 0.0
        if trial % 7 == 0:        # forward motion at the FOE: 0 / 0 speed with zero depth
            xbs[:] = 0.0
            yb = 0.0
            vc[:2] = 0.0
            wc[:] = 0.0
            tb[:] = 0.0
        got = row_vmax2(flow_terms(xbs, vc, wc), yb, tb, 300.0, vc, wc, np.empty(n))
        want = N.row_speed2_max(xbs, yb, tb, 300.0, vc, wc)
        assert got == want, (trial, got, want)


@pytest.mark.parametrize("name", ["high-rise", "pitch", "curves"])
def test_frame_speed_bound_vs_naive(name):
    """The speed a frame returns (the time step's bound) is the largest motion-field speed over
    the first sample row of every pixel row, hits traced by testing every box."""
    sc = Scene.from_params(width=40, height=30, supersample=2, **SCENES[name])
    cam = sc.camera
    k = cam.supersample
    sub = (np.arange(k) + 0.5) / k - 0.5
    for t in (0.0, 0.9):
        o, rot, vc, wc = sc.state(t)
        xs = (np.arange(cam.width)[:, None] + sub[None, :]).ravel()
        best = 0.0
        for j in range(cam.height):
            ys = np.full(xs.shape, j + sub[0])
            tb = N.trace(o, N.rays(xs, ys, cam.f, cam.cx, cam.cy, rot), sc.boxes)[0]
            best = max(best, N.row_speed2_max((xs - cam.cx) / cam.f, (j + sub[0] - cam.cy) /
                                              cam.f, tb, cam.f, vc, wc))
        assert sc.render(t)[1] == pytest.approx(np.sqrt(best), rel=1e-9)


@pytest.mark.parametrize("name", ["high-rise", "pitch", "curves"])
def test_rows_reusing_directions_equal_rows_alone(name):
    """The renderer reuses the previous row's ray directions when r0, r1 are unchanged (no
    pitch): every row rendered alone (fresh scratch, directions computed) gives the same bits."""
    sc = Scene.from_params(width=40, height=30, supersample=2, **SCENES[name])
    for t in (0.0, 0.9):
        whole, _ = sc.render(t)
        alone = np.empty_like(whole)
        vmax = 0.0
        for j in range(whole.shape[0]):
            args = sc._frame_args(t, alone, sc._scratch())
            vmax = max(vmax, render_rows(*args, j, whole.shape[0]))
        np.testing.assert_array_equal(alone, whole)
        assert vmax == sc.render(t)[1]
