"""Scene-graph / metric-map update cost per env step (`python -m hron_jax.bench graph`).

Measures, on a batch of --num-envs envs (jax.vmap inside one jit, timed after a warm-up call,
median of --reps calls):
    graph   GraphBuilder.update + GraphBuilder.graph   (discovery state carried from call to call)
    map     MetricMap.update + MetricMap.observe      (map state carried from call to call)
on real camera frames of the scene: poses are sampled on the walkable floor (seeded), every pool
object is placed at the centre of a random relation slot, and the frames are rendered once
beforehand with the ray-cast camera. The camera's own render cost for the same batch is the first
row, for scale, since both updates are meant to be small next to sensing (DESIGN.md step 4).

Prints: the scene, then the Markdown table | stage | num_envs | ms / batch step | us / env step |
env steps / s |, a row as soon as it is measured (render, graph, map).
"""

from __future__ import annotations

import argparse

import jax
import jax.numpy as jnp
import mujoco
import numpy as np

from ..graph_builder import GraphBuilder, GraphConfig
from ..metric_map import MapConfig, MetricMap
from ..scenes import load_scene
from ..scenes.walkable import scene_reachability
from ..sensors import Camera, CameraConfig
from .common import DEFAULT_SCENE, random_placement, stream_table, timed


def _episode_inputs(scene, num_envs: int, rng: np.random.Generator):
    """Per-env poses (B, 3), placements (batched Placement) and geom poses with objects placed."""
    reach, xs, ys = scene_reachability(scene)
    iy, ix = np.nonzero(reach)
    pick = rng.integers(len(ix), size=num_envs)
    poses = np.stack([xs[ix[pick]], ys[iy[pick]], rng.uniform(-np.pi, np.pi, num_envs)], -1)
    pos, placement = random_placement(scene, num_envs, rng)
    m = scene.model
    d = mujoco.MjData(m)
    xpos, xmat = [], []
    for b in range(num_envs):
        d.mocap_pos[scene.mocap_id[scene.num_rooms + scene.num_furniture :]] = pos[b]
        mujoco.mj_forward(m, d)
        xpos.append(d.geom_xpos.copy())
        xmat.append(d.geom_xmat.copy())
    return (
        jnp.asarray(poses, jnp.float32),
        placement,
        jnp.asarray(np.stack(xpos), jnp.float32),
        jnp.asarray(np.stack(xmat), jnp.float32),
    )


def _time(fn, state, args, reps: int) -> float:
    """Median seconds per call of state = fn(state, *args)[0], after one warm-up (compile) call."""
    state = jax.block_until_ready(fn(state, *args))[0]
    times = []
    for _ in range(reps):
        out, t = timed(lambda: fn(state, *args))
        times.append(t)
        state = out[0]
    return float(np.median(times))


def bench_graph(
    scene_path: str = DEFAULT_SCENE,
    num_envs: int = 64,
    width: int = 32,
    height: int = 32,
    reps: int = 30,
    seed: int = 0,
):
    """Yields rows {stage, num_envs, ms_per_batch, us_per_env_step, env_steps_per_s} for render /
    graph / map, each as soon as it is measured."""
    scene = load_scene(scene_path)
    cam_cfg = CameraConfig(width=width, height=height)
    cam = Camera(scene.model, cam_cfg, scene.geom_instance, scene.geom_class)
    gb = GraphBuilder(scene, GraphConfig())
    mm = MetricMap(scene, cam_cfg, MapConfig())
    poses, placement, xpos, xmat = _episode_inputs(scene, num_envs, np.random.default_rng(seed))

    render = jax.jit(jax.vmap(cam.render_geoms))
    frames = jax.block_until_ready(render(xpos, xmat, poses))

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
    stages = (
        (
            f"render {width}x{height} (camera, reference)",
            lambda: _time(lambda s, *a: (s, render(*a)), None, (xpos, xmat, poses), reps),
        ),
        (
            f"graph update+graph (N={gb.max_nodes}, E={gb.max_edges})",
            lambda: _time(graph_step, disc0, (placement, poses, frames.instance, frames.depth), reps),
        ),
        (
            f"map update+observe (grid {mm.shape[0]}x{mm.shape[1]}, crop {mm.config.crop})",
            lambda: _time(map_step, key0, (poses, frames.depth, frames.semantic), reps),
        ),
    )
    for stage, measure in stages:
        t = measure()
        yield dict(
            stage=stage,
            num_envs=num_envs,
            ms_per_batch=1e3 * t,
            us_per_env_step=1e6 * t / num_envs,
            env_steps_per_s=num_envs / t,
        )


HEADER = (
    "| stage | num_envs | ms / batch step | us / env step | env steps / s |\n| --- | --- | --- | --- | --- |"
)


def format_row(r: dict) -> str:
    return (
        f"| {r['stage']} | {r['num_envs']} | {r['ms_per_batch']:.2f} | "
        f"{r['us_per_env_step']:.1f} | {r['env_steps_per_s']:.0f} |"
    )


def add_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--scene", default=DEFAULT_SCENE)
    p.add_argument("--num-envs", type=int, default=64)
    p.add_argument("--width", type=int, default=32)
    p.add_argument("--height", type=int, default=32)
    p.add_argument("--reps", type=int, default=30)


def run(a: argparse.Namespace) -> None:
    print(f"scene: {a.scene}", flush=True)
    stream_table(HEADER, bench_graph(a.scene, a.num_envs, a.width, a.height, a.reps), format_row)
