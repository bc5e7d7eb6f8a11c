"""Walkable-space grids for checking that rooms, doors and relation slots are reachable.

Role: a conservative 2D occupancy test used by the generator (while placing furniture) and by the
scene tests (on loaded scenes). Not the geodesic module: it only answers "connected or not".

- `free_grid(lo, hi, obstacles, radius, res)`: bool (ny, nx) grid of cell centres in the box
  lo..hi (2,) whose disc of `radius` (inflated as a square, so conservative) misses every obstacle
  rectangle (K, 2, 2) [[xmin, ymin], [xmax, ymax]]. Returns (free, xs, ys).
- `scene_reachability(scene, radius, res)`: reachable mask (ny, nx) from the first start site (or
  the first door) over the union of room floors, with xs (nx,), ys (ny,).
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from . import vocabulary as V

ROBOT_RADIUS = 0.2
# Geoms higher than this above the floor cannot collide with the robot.
ROBOT_HEIGHT = 1.5


def free_grid(lo, hi, obstacles, radius, res=0.05):
    xs = np.arange(lo[0] + res / 2, hi[0], res)
    ys = np.arange(lo[1] + res / 2, hi[1], res)
    X, Y = np.meshgrid(xs, ys)
    free = np.ones(X.shape, bool)
    for o in np.asarray(obstacles, float).reshape(-1, 2, 2):
        free &= ~(
            (X > o[0, 0] - radius) & (X < o[1, 0] + radius) & (Y > o[0, 1] - radius) & (Y < o[1, 1] + radius)
        )
    return free, xs, ys


def component_at(free, xs, ys, points):
    """Connected-component label (0 = blocked) of the grid cell nearest each point (P, 2)."""
    labels, _ = ndimage.label(free)
    pts = np.asarray(points, float).reshape(-1, 2)
    ix = np.clip(np.round((pts[:, 0] - xs[0]) / (xs[1] - xs[0])).astype(int), 0, len(xs) - 1)
    iy = np.clip(np.round((pts[:, 1] - ys[0]) / (ys[1] - ys[0])).astype(int), 0, len(ys) - 1)
    return labels, labels[iy, ix]


def scene_obstacles(scene) -> np.ndarray:
    """(K, 2, 2) xy rectangles of static geoms the robot can bump into (walls, furniture)."""
    c, h = scene.geom_aabb_center, scene.geom_aabb_half
    gi = scene.geom_instance
    is_room = (gi >= 0) & (scene.node_type[np.maximum(gi, 0)] == V.ROOM)
    is_obj = (gi >= 0) & (scene.node_type[np.maximum(gi, 0)] == V.OBJECT)
    low = (c[:, 2] - h[:, 2] < ROBOT_HEIGHT) & (c[:, 2] + h[:, 2] > 0.01)
    keep = ~is_room & ~is_obj & low
    return np.stack([c[keep, :2] - h[keep, :2], c[keep, :2] + h[keep, :2]], 1)


def scene_reachability(scene, radius=ROBOT_RADIUS, res=0.05):
    lo, hi = scene.bounds[0, :2], scene.bounds[1, :2]
    free, xs, ys = free_grid(lo, hi, scene_obstacles(scene), radius, res)
    X, Y = np.meshgrid(xs, ys)
    free &= scene.room_at(np.stack([X, Y], -1)) >= 0
    seed = scene.start_pos[0, :2] if len(scene.start_pos) else scene.door_center[0, :2]
    labels, lab = component_at(free, xs, ys, seed)
    if lab[0] == 0:
        return np.zeros_like(free), xs, ys
    return labels == lab[0], xs, ys


def nearest_reachable_distance(reach, xs, ys, points) -> np.ndarray:
    """(P,) approximate xy distance (to within one cell) from points (P, 2) to the reachable set."""
    if not reach.any():
        return np.full(len(np.asarray(points).reshape(-1, 2)), np.inf)
    res = xs[1] - xs[0]
    dist = ndimage.distance_transform_edt(~reach) * res
    pts = np.asarray(points, float).reshape(-1, 2)
    ix = np.clip(np.round((pts[:, 0] - xs[0]) / res).astype(int), 0, len(xs) - 1)
    iy = np.clip(np.round((pts[:, 1] - ys[0]) / res).astype(int), 0, len(ys) - 1)
    return dist[iy, ix]
