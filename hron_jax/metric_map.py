"""Top-down semantic metric map for the RGB-D + MM ablation (paper, "Baselines and ablation studies").

Role: like SemExp, project the semantically segmented point cloud of each depth frame onto a 2D
grid of `cell` x `cell` metres (0.23 m in the paper) over the scene's bounds; when two points fall
into one cell the higher one wins, and the map accumulates over the episode (a cell never gets
lower). Pure JAX, jittable and vmappable:

    mm = MetricMap(scene, camera_config, MapConfig())   # the Camera's config: same rays
    key = mm.reset()                                     # i32[Hg, Wg]
    key = mm.update(key, pose, frame.depth, frame.semantic)
    obs = mm.observe(key, pose)                          # f32[M, M, 3] (egocentric) or f32[Hg, Wg, 5]

Grid: cell (i, j) covers world x in origin_x + [i, i + 1) * cell, y in origin_y + [j, j + 1) * cell,
origin = the scene's lower bounds corner; Hg x Wg = `shape` covers the bounds. Points outside fall
off the map.
State: `key` i32[Hg, Wg], -1 for never observed, else `height_mm * NUM_CLASSES + class` so that a
single scatter-max keeps the highest point and its class (deterministic on ties: higher class).
Heights are clipped to [0, max_height] and stored in millimetres.
Observation (`observe`), channels `OBSERVED_CHANNEL` 0 (observed 0/1), `HEIGHT_CHANNEL` 1
(height / max_height), `CLASS_CHANNEL` 2 (class id, an exact integer in a float, 0 where
unobserved):
    egocentric (default): f32[M, M, 3], M = `crop`, agent at the centre, heading up the rows: row 0
        is farthest ahead, column 0 farthest left (nearest-cell resampling of the global grid), so
        the map is in the agent's frame like the scene graph's node positions;
    global (`egocentric=False`): f32[Hg, Wg, 5], the whole grid in world axes (rows +x, columns
        +y) plus the agent's heading (cos yaw, sin yaw) in channels 3-4 at the agent's cell and 0
        elsewhere (a unit vector marks where the agent is and where it faces).
The class channel is the raw semantic class (vocabulary.class_id): a category, not a quantity, so
the model does not convolve it as a number. Its map branch (models.encoders.MapEncoder) replaces
it by a learned embedding of the class, concatenated with the other channels, before the RGB-D
branch's conv stack (the paper: "identical to the RGB and Depth branches"). The env keeps the
compact channel: one float per cell in the rollout buffers instead of NUM_CLASSES for a one-hot.
(The authors' release fed the class as one scalar channel, id / MAX_CLASS_COUNT, next to a
visited-path channel; a scalar makes the conv's response monotone in an arbitrary class order,
which handicaps the baseline, so we deviate.)

Crop (`crop` M: 88 cells x 0.23 m = 20.2 m by default, 128 = 29.4 m in the paper preset; the agent
at the centre). The paper states the cell (0.23 m) but not the map's size; the authors' public release
(github.com/mjlbach/ssg: ssg/obs/slam.py and ssg/envs/igibson_env.py, `metric_map_resolution`
128, `metric_map_voxel_size` 0.23, `use_egocentric_projection: true`) observes a 128 x 128
egocentric crop at 0.23 m, the pixel count of its 128 x 128 RGB-D images: the paper preset
(hron_jax.run_config.PRESETS) uses 128. The default is 88, the smallest crop that keeps what one
frame sees (below), as the default 32 x 32 camera keeps the paper's field of view and range at a
quarter of the resolution; smaller crops make a weaker baseline, not a cheaper copy of it:
    - the camera (sensors.CameraConfig: 120 deg square FoV, max_depth 10 m) puts points up to 10 m
      ahead into the map in one frame. The former crop of 32 cells (7.4 m, +-3.7 m) dropped
      everything seen more than 3.7 m ahead at once, so the map held less than the current frame;
      keeping one frame's reach takes >= 2 x 10 m / 0.23 m = 87 cells;
    - the scenes: house.xml's bounds are 17.1 m x 11.1 m (75 x 49 cells), the held-out houses'
      10.3-11.5 m x 13.45-15.15 m. Share of a house's bounds inside the crop over 300 random agent
      poses (position in the bounds, uniform heading), mean (worst): house.xml at M = 32: 0.21
      (0.09), 64: 0.60 (0.32), 88: 0.82 (0.55), 128: 0.98 (0.85); house_1..3 at 128: 1.00 (>= 0.92).
      All of house.xml from every pose would take M >= 178 (2 x its 20.4 m diagonal); at 128 only
      the far end is cut, and only from poses near a corner;
    - cost: the map branch's first conv reads M^2 x (2 + class embedding) inputs, so the branch's
      compute grows with M^2. Map encoder (default conv sizes, embedding 8), fwd + grad on a batch
      of 128 in lax.scan, 2 shared CPU cores at load 7-11, two runs: 0.13-0.20 s per SGD step at
      M = 32, 1.0-1.3 s at 88, 2.1-3.7 s at 128 (0.03-0.08 / 0.56-0.58 / 0.84-1.85 s with the old
      scalar class channel); of the order of the paper's 128 x 128 RGB-D branch. The observation
      is 128^2 x 3 floats = 192 KiB per env step (805 MB for a 4096-step rollout); at 88 the
      camera's reach and 0.82 of house.xml stay in view at a third to a half of that cost.
Pre-mapping (`premap=True`): the map starts as the static scene seen from above: for every cell,
the highest top of any static geom (rooms, walls, furniture; never a pool object, so never the
target) whose footprint overlaps the cell, with that geom's class. It is computed once on the
host from the geoms' world AABBs, which is exact for the axis-aligned boxes that make up the
shipped scenes (a rotated box, sphere or capsule is counted over its AABB footprint). Sampling one
ray per cell centre instead would miss the 0.1 m walls and every geom thinner than a cell, which
the camera's point cloud does put into the map.
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np

from .scenes import vocabulary as V
from .scenes.loader import Scene
from .sensors import CameraConfig, effective_rgba, world_rays


@dataclasses.dataclass(frozen=True)
class MapConfig:
    cell: float = 0.23  # m, the paper's resolution
    crop: int = 88  # M: egocentric crop side in cells (88 * 0.23 = 20.2 m; paper preset 128, docstring)
    max_height: float = 2.5  # m; heights are clipped to [0, max_height]
    egocentric: bool = True  # observe an egocentric crop; False: the global map + agent heading


# Channels of `observe` (egocentric and global; the global view adds cos / sin yaw as 3-4).
OBSERVED_CHANNEL, HEIGHT_CHANNEL, CLASS_CHANNEL = 0, 1, 2

_NC = V.NUM_CLASSES
_MM = 1000.0  # heights stored in millimetres


class MetricMap:
    """Static grid of one scene + pure functions `reset`, `update`, `observe`."""

    def __init__(
        self, scene: Scene, camera: CameraConfig, config: MapConfig = MapConfig(), premap: bool = False
    ):
        """premap: start from the static scene seen from above (the paper's pre-mapping)."""
        self.config, self.camera = config, camera
        lo, hi = scene.bounds[0, :2], scene.bounds[1, :2]
        self.origin = np.asarray(lo, np.float32)
        self.shape = tuple(int(math.ceil(v)) for v in (hi - lo) / config.cell)  # (nx, ny)
        self.premap_key = jnp.asarray(self._static_topdown(scene)) if premap else None

    def _static_topdown(self, scene: Scene) -> np.ndarray:
        """Key table of the highest static geom top over each cell (see the module docstring)."""
        inst = scene.geom_instance
        is_object = (inst >= 0) & (scene.node_type[np.maximum(inst, 0)] == V.OBJECT)
        visible = effective_rgba(scene.model)[:, 3] != 0  # as the camera: alpha 0 is never seen
        lo = scene.geom_aabb_center - scene.geom_aabb_half
        hi = scene.geom_aabb_center + scene.geom_aabb_half
        c = self.config.cell
        # Cells whose open interior overlaps the footprint; the 1e-6 m shrink keeps a face lying on
        # a cell boundary out of the neighbouring cell.
        i0 = np.floor((lo[:, :2] + 1e-6 - self.origin) / c).astype(int)
        i1 = np.ceil((hi[:, :2] - 1e-6 - self.origin) / c).astype(int)
        i0 = np.clip(i0, 0, self.shape)
        i1 = np.clip(i1, 0, self.shape)
        z = np.clip(hi[:, 2], 0.0, self.config.max_height)
        keys = np.round(z * _MM).astype(np.int64) * _NC + scene.geom_class
        key = np.full(self.shape, -1, np.int64)
        for g in np.nonzero(~is_object & visible & (hi[:, 2] >= -1e-6))[0]:
            sub = key[i0[g, 0] : i1[g, 0], i0[g, 1] : i1[g, 1]]
            np.maximum(sub, keys[g], out=sub)
        return key.astype(np.int32)

    def reset(self) -> jax.Array:
        if self.premap_key is not None:
            return self.premap_key
        return jnp.full(self.shape, -1, jnp.int32)

    def update(self, key: jax.Array, pose: jax.Array, depth: jax.Array, semantic: jax.Array) -> jax.Array:
        """Add one frame: depth f32[H,W] (z-depth, m), semantic i32[H,W] class ids."""
        o, dirs = world_rays(pose, self.camera)
        pts = o + depth[..., None] * dirs  # (H, W, 3)
        cell = jnp.floor((pts[..., :2] - self.origin) / self.config.cell).astype(jnp.int32)
        inside = jnp.all((cell >= 0) & (cell < jnp.array(self.shape)), -1)
        hit = (depth < self.camera.max_depth) & (semantic > V.NOTHING_CLASS) & inside
        z = jnp.clip(pts[..., 2], 0.0, self.config.max_height)
        k = jnp.round(z * _MM).astype(jnp.int32) * _NC + semantic
        k = jnp.where(hit, k, -1)
        cell = jnp.where(hit[..., None], cell, 0)
        return key.at[cell[..., 0].reshape(-1), cell[..., 1].reshape(-1)].max(k.reshape(-1))

    def observe(self, key: jax.Array, pose: jax.Array) -> jax.Array:
        """The policy's view of the map (see the module docstring for shapes and channels)."""
        if not self.config.egocentric:
            return self._observe_global(key, pose)
        m, c = self.config.crop, self.config.cell
        ahead = (m / 2 - 0.5 - jnp.arange(m)) * c  # rows: far ahead -> behind
        left = (m / 2 - 0.5 - jnp.arange(m)) * c  # cols: left -> right
        a, l = jnp.meshgrid(ahead, left, indexing="ij")
        cy, sy = jnp.cos(pose[2]), jnp.sin(pose[2])
        wx = pose[0] + a * cy - l * sy
        wy = pose[1] + a * sy + l * cy
        cell = jnp.floor((jnp.stack([wx, wy], -1) - self.origin) / c).astype(jnp.int32)
        inside = jnp.all((cell >= 0) & (cell < jnp.array(self.shape)), -1)
        k = jnp.where(
            inside,
            key[jnp.clip(cell[..., 0], 0, self.shape[0] - 1), jnp.clip(cell[..., 1], 0, self.shape[1] - 1)],
            -1,
        )
        return self._channels(k)

    def _channels(self, k: jax.Array) -> jax.Array:
        seen = k >= 0
        height = jnp.where(seen, (k // _NC) / _MM / self.config.max_height, 0.0)
        cls = jnp.where(seen, k % _NC, 0)
        channels = {OBSERVED_CHANNEL: seen, HEIGHT_CHANNEL: height, CLASS_CHANNEL: cls}
        return jnp.stack([channels[i].astype(jnp.float32) for i in range(3)], -1)

    def _observe_global(self, key: jax.Array, pose: jax.Array) -> jax.Array:
        cell = jnp.floor((pose[:2] - self.origin) / self.config.cell).astype(jnp.int32)
        at = (
            (jnp.arange(self.shape[0])[:, None] == cell[0]) & (jnp.arange(self.shape[1])[None, :] == cell[1])
        )[..., None]
        heading = jnp.where(at, jnp.stack([jnp.cos(pose[2]), jnp.sin(pose[2])]), 0.0).astype(jnp.float32)
        return jnp.concatenate([self._channels(key), heading], -1)
