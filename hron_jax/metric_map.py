"""Top-down semantic metric map for the RGB-D + MM ablation (paper, "Baselines and ablation studies").

Role: like SemExp, project the semantically segmented point cloud of each depth frame onto a 2D
grid of `cell` x `cell` metres (0.23 m in the paper) over the scene's bounds; when two points fall
into one cell the higher one wins, and the map accumulates over the episode. The policy sees an
egocentric crop (agent at the centre, heading up the rows), so, like the scene graph's node
positions, the map is in the agent's frame.

State: `key` i32[Hg, Wg], -1 for never observed, else `height_mm * NUM_CLASSES + class` so that a
single scatter-max keeps the highest point and its class (deterministic on ties: higher class).
Observation: f32[M, M, 3] = (observed, height / max_height, class id) with M = `crop`; the model
embeds the class channel (hron_jax.models).
Pre-mapping: the map starts as the static scene seen from above (every cell's highest static
surface, cast once on the host with MuJoCo's `mj_ray`, the pool objects parked below the floor),
so it holds rooms, walls and furniture but never the target.
"""

from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from .scenes import vocabulary as V
from .scenes.loader import Scene
from .sensors import CameraConfig, world_rays


@dataclasses.dataclass(frozen=True)
class MapConfig:
    cell: float = 0.23        # m, the paper's resolution
    crop: int = 32            # M: egocentric crop side in cells (32 * 0.23 = 7.4 m)
    max_height: float = 2.5   # m; heights are clipped to [0, max_height]
    premap: bool = False


_NC = V.NUM_CLASSES
_MM = 1000.0  # heights stored in millimetres


class MetricMap:
    """Static grid of one scene + pure functions `reset`, `update`, `observe`."""

    def __init__(self, scene: Scene, camera: CameraConfig, config: MapConfig = MapConfig()):
        self.config, self.camera = config, camera
        lo, hi = scene.bounds[0, :2], scene.bounds[1, :2]
        self.origin = np.asarray(lo, np.float32)
        self.shape = tuple(int(math.ceil(v)) for v in (hi - lo) / config.cell)  # (nx, ny)
        self.premap_key = jnp.asarray(self._static_topdown(scene)) if config.premap else None

    def _static_topdown(self, scene: Scene) -> np.ndarray:
        """Highest static surface per cell as a key table, by casting rays down from above."""
        m = scene.model
        d = mujoco.MjData(m)
        mujoco.mj_forward(m, d)
        top = float(scene.bounds[1, 2]) + 1.0
        key = np.full(self.shape, -1, np.int64)
        geomid = np.zeros(1, np.int32)
        for i in range(self.shape[0]):
            for j in range(self.shape[1]):
                x, y = self.origin + (np.array([i, j]) + 0.5) * self.config.cell
                dist = mujoco.mj_ray(m, d, np.array([x, y, top]), np.array([0.0, 0.0, -1.0]), None, 1, -1, geomid)
                if dist >= 0:
                    cls = int(scene.geom_class[geomid[0]])
                    z = np.clip(top - dist, 0.0, self.config.max_height)
                    key[i, j] = int(round(z * _MM)) * _NC + cls
        return key.astype(np.int32)

    def reset(self) -> jax.Array:
        if self.premap_key is not None:
            return self.premap_key
        return jnp.full(self.shape, -1, jnp.int32)

    def update(self, key: jax.Array, pose: jax.Array, depth: jax.Array, semantic: jax.Array) -> jax.Array:
        """Add one frame: depth f32[H,W] (z-depth, m), semantic i32[H,W] class ids."""
        o, dirs = world_rays(pose, self.camera)
        pts = o + depth[..., None] * dirs                                   # (H, W, 3)
        cell = jnp.floor((pts[..., :2] - self.origin) / self.config.cell).astype(jnp.int32)
        inside = jnp.all((cell >= 0) & (cell < jnp.array(self.shape)), -1)
        hit = (depth < self.camera.max_depth) & (semantic > V.NOTHING_CLASS) & inside
        z = jnp.clip(pts[..., 2], 0.0, self.config.max_height)
        k = jnp.round(z * _MM).astype(jnp.int32) * _NC + semantic
        k = jnp.where(hit, k, -1)
        cell = jnp.where(hit[..., None], cell, 0)
        return key.at[cell[..., 0].reshape(-1), cell[..., 1].reshape(-1)].max(k.reshape(-1))

    def observe(self, key: jax.Array, pose: jax.Array) -> jax.Array:
        """Egocentric crop f32[M, M, 3]: row 0 is ahead of the agent, column 0 to its left."""
        m, c = self.config.crop, self.config.cell
        ahead = (m / 2 - 0.5 - jnp.arange(m)) * c                       # rows: far ahead -> behind
        left = (m / 2 - 0.5 - jnp.arange(m)) * c                        # cols: left -> right
        a, l = jnp.meshgrid(ahead, left, indexing="ij")
        cy, sy = jnp.cos(pose[2]), jnp.sin(pose[2])
        wx = pose[0] + a * cy - l * sy
        wy = pose[1] + a * sy + l * cy
        cell = jnp.floor((jnp.stack([wx, wy], -1) - self.origin) / c).astype(jnp.int32)
        inside = jnp.all((cell >= 0) & (cell < jnp.array(self.shape)), -1)
        k = jnp.where(inside, key[jnp.clip(cell[..., 0], 0, self.shape[0] - 1),
                                  jnp.clip(cell[..., 1], 0, self.shape[1] - 1)], -1)
        seen = k >= 0
        height = jnp.where(seen, (k // _NC) / _MM / self.config.max_height, 0.0)
        cls = jnp.where(seen, k % _NC, 0)
        return jnp.stack([seen.astype(jnp.float32), height.astype(jnp.float32), cls.astype(jnp.float32)], -1)
