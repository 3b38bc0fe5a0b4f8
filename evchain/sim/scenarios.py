"""The scenarios of thesis section 4.2 (Fig. 4.5, Table 4.1) as procedural worlds.

* ``high-rise``: 280 m straight past high-rise buildings on both sides, sidewalks, lantern posts,
  a car across the ego lane at the end, a building closing the street far ahead (reference).
* ``high-rise-orange``: the same with an orange facade texture; ``extra_vertical_lines`` puts
  vertical lines on the building straight ahead (thesis Fig. 5.1).
* ``open-field``: 70 m straight through grass, delineator posts, a few distant buildings, a car
  blocking the road at the end.
* ``curves``: straights joined by left and right arcs, houses and lanterns beside the road, no
  obstacle.

The layout is random but fixed by ``layout_seed``.
"""

from __future__ import annotations

import numpy as np

from evchain.sim.config import CURVES_ROUTE, SceneConfig, route_length_m
from evchain.sim.route import path_points, segment_table
from evchain.sim.world import (
    MAT_CAR,
    MAT_ORANGE,
    MAT_ORANGE_LINES,
    MAT_PLAIN,
    MAT_WINDOWS,
    OBSTACLE_LABEL,
    World,
    make_ground,
    make_light,
)

ROAD_HALF_WIDTH = 5.0   # asphalt half width (two 3.5 m lanes plus shoulders)
EDGE_LINE = 3.5
SIDEWALK = 4.0


def build_world(cfg: SceneConfig) -> World:
    rng = np.random.default_rng([cfg.layout_seed, 4242])
    light = make_light(cfg.sun_azimuth_deg, cfg.sun_elevation_deg)
    route = route_length_m(cfg)
    centre = -cfg.lane_offset_m
    if cfg.scenario == "curves":
        segs = segment_table(0.0, cfg.lane_offset_m, 0.0, list(CURVES_ROUTE))
        ground = make_ground(centre, ROAD_HALF_WIDTH, EDGE_LINE, 3.0, 0, cfg.layout_seed)
        world = World(segs, ground, light, route)
        _curves(world, cfg, rng)
    else:
        segs = segment_table(0.0, cfg.lane_offset_m, 0.0, [(route, 0.0)])
        if cfg.scenario == "open-field":
            ground = make_ground(centre, 4.0, EDGE_LINE, 0.0, 0, cfg.layout_seed)
            world = World(segs, ground, light, route)
            _open_field(world, cfg, rng)
        else:
            ground = make_ground(centre, ROAD_HALF_WIDTH, EDGE_LINE, SIDEWALK, 1, cfg.layout_seed)
            world = World(segs, ground, light, route)
            _high_rise(world, cfg, rng)
    if cfg.has_obstacle:
        _obstacle(world, cfg)
    return world


def _facade(cfg: SceneConfig, rng) -> tuple[int, tuple[float, ...]]:
    if cfg.facade_kind == "orange":
        return MAT_ORANGE, (rng.uniform(0.45, 0.6), 3.0, rng.uniform(1.8, 2.4), 0.0)
    return MAT_WINDOWS, (rng.uniform(0.35, 0.55), 3.2, rng.uniform(2.2, 3.0), 0.0)


def _lantern(world: World, x: float, y: float, towards: float, arm: bool = True) -> None:
    """A post at (x, y) with an arm reaching ``towards`` (+1 / -1 along world y)."""
    world.add_box((x - 0.1, y - 0.1, 0.0), (x + 0.1, y + 0.1, 8.0), MAT_PLAIN, (0.22,), "lantern")
    if arm:
        y1 = y + towards * 1.8
        world.add_box((x - 0.06, min(y, y1), 7.8), (x + 0.06, max(y, y1), 7.95), MAT_PLAIN,
                      (0.22,), "lantern")
        world.add_box((x - 0.15, min(y1, y1 - towards * 0.6), 7.6),
                      (x + 0.15, max(y1, y1 - towards * 0.6), 7.8), MAT_PLAIN, (0.9,), "lantern")
    else:
        world.add_box((x - 0.2, y - 0.2, 8.0), (x + 0.2, y + 0.2, 8.4), MAT_PLAIN, (0.9,),
                      "lantern")


def _high_rise(world: World, cfg: SceneConfig, rng) -> None:
    route = world.route_m
    centre_y = 0.0   # the straight road's centre line is world y = 0
    for side in (1.0, -1.0):
        x = -60.0 + rng.uniform(0, 10)
        while x < route + 40.0:
            width = rng.uniform(15.0, 35.0)
            near = ROAD_HALF_WIDTH + SIDEWALK + rng.uniform(1.0, 4.0)
            depth = rng.uniform(15.0, 30.0)
            height = rng.uniform(25.0, 90.0)
            mat, par = _facade(cfg, rng)
            y0, y1 = sorted((centre_y + side * near, centre_y + side * (near + depth)))
            world.add_box((x, y0, 0.0), (x + width, y1, height), mat, par, "building")
            x += width + rng.uniform(4.0, 12.0)
    mat, par = _facade(cfg, rng)
    if cfg.extra_vertical_lines:
        mat = MAT_ORANGE_LINES
        if cfg.facade_kind != "orange":
            par = (0.5, 3.0, 2.0, 0.0)
    world.add_box((route + 50.0, centre_y - 45.0, 0.0), (route + 75.0, centre_y + 45.0, 60.0),
                  mat, par, "building-ahead")
    if cfg.lanterns:
        for i, x in enumerate(np.arange(10.0, route + 20.0, 35.0)):
            side = 1.0 if i % 2 == 0 else -1.0
            _lantern(world, x, centre_y + side * (ROAD_HALF_WIDTH + 0.6), -side)


def _open_field(world: World, cfg: SceneConfig, rng) -> None:
    route = world.route_m
    hw = world.ground[1]
    for x in np.arange(0.0, route + 200.0, 25.0):
        for side in (1.0, -1.0):
            y = side * (hw + 0.7)
            world.add_box((x - 0.06, y - 0.06, 0.0), (x + 0.06, y + 0.06, 1.0), MAT_PLAIN,
                          (0.75,), "post")
    for _ in range(8):
        side = rng.choice([-1.0, 1.0])
        x = rng.uniform(-50.0, route + 300.0)
        near = rng.uniform(60.0, 250.0)
        w, d, h = rng.uniform(10, 30), rng.uniform(8, 20), rng.uniform(5, 12)
        y0, y1 = sorted((side * near, side * (near + d)))
        world.add_box((x, y0, 0.0), (x + w, y1, h), MAT_PLAIN, (rng.uniform(0.3, 0.7),), "farm")
    if cfg.lanterns:
        for i, x in enumerate(np.arange(15.0, route + 20.0, 40.0)):
            side = 1.0 if i % 2 == 0 else -1.0
            _lantern(world, x, side * (hw + 1.0), -side)


def _curves(world: World, cfg: SceneConfig, rng) -> None:
    from evchain.kernels.scene_geometry import road_coords

    segs = world.segs
    centre = world.ground[0]
    clearance = ROAD_HALF_WIDTH + 3.0 + 1.0

    def clear(x0, y0, x1, y1) -> bool:
        for x in np.linspace(x0, x1, 6):
            for y in np.linspace(y0, y1, 6):
                _, d = road_coords(float(x), float(y), segs)
                if abs(d - centre) < clearance:
                    return False
        return True

    route = world.route_m
    pts, heads = path_points(segs, np.arange(5.0, route + 60.0, 9.0))
    for (px, py), h in zip(pts, heads, strict=True):
        for side in (1.0, -1.0):
            if rng.uniform() < 0.45:
                continue
            off = centre + side * rng.uniform(clearance + 2.0, clearance + 14.0)
            cx, cy = px - np.sin(h) * off, py + np.cos(h) * off
            w, d, hgt = rng.uniform(6, 14), rng.uniform(6, 14), rng.uniform(6, 25)
            box = (cx - w / 2, cy - d / 2, cx + w / 2, cy + d / 2)
            if not clear(*box):
                continue
            if any(_overlap(box, b) for b in world.boxes):
                continue
            mat, par = _facade(cfg, rng)
            world.add_box((box[0], box[1], 0.0), (box[2], box[3], hgt), mat, par, "house")
    if cfg.lanterns:
        pts, heads = path_points(segs, np.arange(10.0, route + 20.0, 30.0))
        for i, ((px, py), h) in enumerate(zip(pts, heads, strict=True)):
            side = 1.0 if i % 2 == 0 else -1.0
            off = centre + side * (ROAD_HALF_WIDTH + 0.6)
            _lantern(world, px - np.sin(h) * off, py + np.cos(h) * off, 0.0, arm=False)


def _overlap(a, b) -> bool:
    # a = (x0, y0, x1, y1); b = world box (x0, y0, z0, x1, y1, z1)
    return not (a[2] < b[0] or b[3] < a[0] or a[3] < b[1] or b[4] < a[1])


def _obstacle(world: World, cfg: SceneConfig) -> None:
    """A car standing across the ego lane, its near side ``obstacle_gap_m`` past the route end:
    body, cabin and two wheels, every box labelled ``OBSTACLE_LABEL``."""
    pts, hs = path_points(world.segs, np.array([world.route_m]))
    ex, ey, h = float(pts[0, 0]), float(pts[0, 1]), float(hs[0])
    if abs(np.sin(h)) > 1e-9:
        raise ValueError("the obstacle needs a route ending along world x")
    x0 = ex + cfg.obstacle_gap_m
    c = ey
    world.add_box((x0, c - 2.25, 0.3), (x0 + 1.8, c + 2.25, 1.0), MAT_CAR, (0.6, 9.0, 9.0, 0.4),
                  OBSTACLE_LABEL)
    world.add_box((x0 + 0.2, c - 1.2, 1.0), (x0 + 1.6, c + 1.1, 1.45), MAT_CAR,
                  (0.6, 1.05, 1.4, 0.0), OBSTACLE_LABEL)
    for wy in (c - 1.45, c + 1.45):
        world.add_box((x0 + 0.05, wy - 0.35, 0.0), (x0 + 0.35, wy + 0.35, 0.62), MAT_PLAIN,
                      (0.05,), OBSTACLE_LABEL)
    world.obstacle_rear = np.array([x0, c, 0.65])
