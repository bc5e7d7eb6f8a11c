"""Benchmark: scene-graph and metric-map update cost per env step (DESIGN.md step 4).

Role: on a batch of `num_envs` envs (jax.vmap inside one jit, timed after a warm-up call), time
    graph   GraphBuilder.update + GraphBuilder.graph   (discovery state carried from call to call)
    map     MetricMap.update + MetricMap.observe      (map state carried from call to call)
on real camera frames of the scene: poses are sampled on the walkable floor (seeded), every pool
object is placed at the centre of a random relation slot, and the frames are rendered once
beforehand with the ray-cast camera. The camera's own render cost for the same batch is printed as
a reference row, since both updates are meant to be small next to sensing.

    python -m hron_jax.bench_graph [--scene scenes/house.xml] [--num-envs 64] [--width 32]
                                   [--height 32] [--reps 30]

`bench_graph(...)` returns the rows (dicts) so hron_jax.bench can append them to its env table;
`format_rows(rows)` prints them as a Markdown table.
"""

from __future__ import annotations

import argparse
import os
import platform
import time

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from .graph_builder import GraphBuilder, GraphConfig, Placement
from .metric_map import MapConfig, MetricMap
from .scenes import load_scene
from .scenes import vocabulary as V
from .scenes.walkable import scene_reachability
from .sensors import Camera, CameraConfig

_DEFAULT_SCENE = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "scenes",
                              "house.xml")


def _episode_inputs(scene, num_envs: int, rng: np.random.Generator):
    """Per-env poses (B, 3), placements (batched Placement) and geom poses with objects placed."""
    reach, xs, ys = scene_reachability(scene)
    iy, ix = np.nonzero(reach)
    pick = rng.integers(len(ix), size=num_envs)
    poses = np.stack([xs[ix[pick]], ys[iy[pick]], rng.uniform(-np.pi, np.pi, num_envs)], -1)
    o0 = scene.num_rooms + scene.num_furniture
    half = V.OBJECT_HALF[scene.vocab_index[o0:]]
    slot = rng.integers(scene.num_slots, size=(num_envs, scene.num_objects))
    support = scene.slot_center[:, 2] - scene.slot_half[:, 2]
    pos = np.concatenate([scene.slot_center[slot, :2], (support[slot] + half[None, :, 2])[..., None]], -1)
    placement = Placement(active=jnp.ones((num_envs, scene.num_objects), bool),
                          pos=jnp.asarray(pos, jnp.float32),
                          furniture=jnp.asarray(scene.slot_furniture[slot], jnp.int32),
                          relation=jnp.asarray(scene.slot_relation[slot], jnp.int32))
    m = scene.model
    d = mujoco.MjData(m)
    xpos, xmat = [], []
    for b in range(num_envs):
        d.mocap_pos[scene.mocap_id[o0:]] = pos[b]
        mujoco.mj_forward(m, d)
        xpos.append(d.geom_xpos.copy())
        xmat.append(d.geom_xmat.copy())
    return (jnp.asarray(poses, jnp.float32), placement, jnp.asarray(np.stack(xpos), jnp.float32),
            jnp.asarray(np.stack(xmat), jnp.float32))


def _time(fn, state, args, reps: int) -> float:
    """Median seconds per call of state = fn(state, *args)[0], after one warm-up (compile) call."""
    out = fn(state, *args)
    jax.block_until_ready(out)
    state = out[0]
    times = []
    for _ in range(reps):
        t = time.perf_counter()
        out = fn(state, *args)
        jax.block_until_ready(out)
        times.append(time.perf_counter() - t)
        state = out[0]
    return float(np.median(times))


def bench_graph(scene_path: str = _DEFAULT_SCENE, num_envs: int = 64, width: int = 32, height: int = 32,
                reps: int = 30, seed: int = 0) -> list[dict]:
    """Rows {stage, num_envs, ms_per_batch, us_per_env_step, env_steps_per_s} for render / graph / map."""
    scene = load_scene(scene_path)
    cam_cfg = CameraConfig(width=width, height=height)
    cam = Camera(scene.model, cam_cfg, scene.geom_instance, scene.geom_class)
    gb = GraphBuilder(scene, GraphConfig())
    mm = MetricMap(scene, cam_cfg, MapConfig())
    poses, placement, xpos, xmat = _episode_inputs(scene, num_envs, np.random.default_rng(seed))

    render = jax.jit(jax.vmap(cam.render_geoms))
    frames = render(xpos, xmat, poses)
    jax.block_until_ready(frames)

    @jax.jit
    def graph_step(disc, placement, poses, instance, depth):
        def one(d, pl, p, i, z):
            d = gb.update(d, pl, p, i, z)
            return d, gb.graph(d, pl, p)
        return jax.vmap(one)(disc, placement, poses, instance, depth)

    @jax.jit
    def map_step(key, poses, depth, semantic):
        def one(k, p, z, s):
            k = mm.update(k, p, z, s)
            return k, mm.observe(k, p)
        return jax.vmap(one)(key, poses, depth, semantic)

    disc0 = jax.vmap(gb.reset)(placement, poses)
    key0 = jnp.broadcast_to(mm.reset(), (num_envs,) + mm.shape)
    t_render = _time(lambda s, *a: (s, render(*a)), None, (xpos, xmat, poses), reps)
    t_graph = _time(graph_step, disc0, (placement, poses, frames.instance, frames.depth), reps)
    t_map = _time(map_step, key0, (poses, frames.depth, frames.semantic), reps)

    rows = []
    for stage, t in ((f"render {width}x{height} (camera, reference)", t_render),
                     (f"graph update+graph (N={gb.max_nodes}, E={gb.max_edges})", t_graph),
                     (f"map update+observe (grid {mm.shape[0]}x{mm.shape[1]}, crop {mm.config.crop})",
                      t_map)):
        rows.append(dict(stage=stage, num_envs=num_envs, ms_per_batch=1e3 * t,
                         us_per_env_step=1e6 * t / num_envs, env_steps_per_s=num_envs / t))
    return rows


def format_rows(rows: list[dict]) -> str:
    lines = ["| stage | num_envs | ms / batch step | us / env step | env steps / s |",
             "| --- | --- | --- | --- | --- |"]
    for r in rows:
        lines.append(f"| {r['stage']} | {r['num_envs']} | {r['ms_per_batch']:.2f} | "
                     f"{r['us_per_env_step']:.1f} | {r['env_steps_per_s']:.0f} |")
    return "\n".join(lines)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--scene", default=_DEFAULT_SCENE)
    p.add_argument("--num-envs", type=int, default=64)
    p.add_argument("--width", type=int, default=32)
    p.add_argument("--height", type=int, default=32)
    p.add_argument("--reps", type=int, default=30)
    a = p.parse_args(argv)
    rows = bench_graph(a.scene, a.num_envs, a.width, a.height, a.reps)
    print(f"{os.path.basename(a.scene)}, jax {jax.__version__} on {jax.devices()[0].platform} "
          f"({platform.processor() or platform.machine()}, {os.cpu_count()} cpus)")
    print(format_rows(rows))


if __name__ == "__main__":
    main()
