"""Directed and exploratory relational object navigation (paper, "Experimental setup") as pure JAX envs.

Role
----
`NavigationEnv(scene, NavConfig(task='directed' | 'exploratory'))` implements the functional API of
hron_jax.envs.base (reset / step over an EnvState pytree, one env, no batch axis; jit and vmap it)
on top of the MJX simulator, the ray-cast camera, the scene-graph builder and (optionally) the
metric map. Episodes are sampled by hron_jax.envs.placement (goals, stable object poses,
distractors, starts); geodesic distances come from fields precomputed there, so no step or reset
ever solves for a field.

Observation (one env):
    obs['rgbd']          f32[H, W, 4]  rgb in [0, 1], then depth / camera max_depth
    obs['goal']          f32[GOAL_DIM] one-hots (object, relation, furniture, room), hron_jax.goals;
                         the directed task has no room (zero block)
    obs['goal_classes']  i32[3]        class ids of (object, furniture, room), -1 absent
    obs['graph']         jraph.GraphsTuple from hron_jax.graph_builder (after this step's frame)
    obs['map']           f32[M, M, 3]  egocentric metric map, only with NavConfig.metric_map
Actions: hron_jax.sim (0 forward 0.2 m, 1 backward, 2 turn left 30 deg, 3 right, 4 stop); stop
does not end the episode.

Rewards and termination (per step; R = success_distance = 1 m, xy distances to object centres):
    + shaping_scale * (d_prev - d_now), d the geodesic distance (m) from the agent to the target's
      success region (potential-based shaping; unreachable lookups count as no change);
    + success_reward (10) and termination when within R of the target;
    directed only: - wrong_penalty (5) and termination when within R of the wrong object;
    max_steps (500) ends the episode as truncation (info['truncation'] = 1), never termination.
Metrics (EnvState.metrics, see base.METRIC_KEYS): success, spl = success * d0 / max(d0, p) with d0
the geodesic distance from the start to the success region at reset and p the path length, i.e.
the xy distance actually travelled (turning adds nothing), episode_length, return.

Auto-reset (NavConfig.auto_reset, default True): `step` starts the next episode itself when the
step ends one, with the bookkeeping of base.AutoResetWrapper (the returned state holds the new
episode's obs / inner / counters while reward, done, metrics and info['truncation'] describe the
finished step). Sampling an episode is cheap (table lookups, one `mjx.kinematics`), so it runs
every step and is selected per env, and the camera renders exactly once per step: physics first,
then success / failure / time limit from the new pose (no image needed), then the choice between
the continuing and the fresh episode, then one render for the obs of the returned state.
The pre-reset observation is not rendered; `info['final']` keeps what it takes to render it
(`FinalInputs`) and `env.final_obs(state)` renders it on demand. hron_jax.ppo calls it only in
rollout steps where some env truncated (to bootstrap GAE), and does not wrap an env whose
`auto_reset` attribute is True in AutoResetWrapper.

Shapes of the env state: `NavInner` (below); info adds 'final' (FinalInputs) and 'uncertain_rays'
(f32: the fraction of the observation's camera rays whose hit the culled ray caster could not
certify, hron_jax.sensors; PPO logs its mean as the metric of that name).
Determinism: everything is a function of the reset key (the env's own key in inner.rng is split
at every step), so a fixed seed reproduces rollouts exactly, batched or not.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import os
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from hron_jax import geodesic as G
from hron_jax import goals as goal_lib
from hron_jax import sim as S
from hron_jax.envs import NAV_TASKS
from hron_jax.envs import placement as P
from hron_jax.envs.base import EnvState, initial_state, next_state, select_tree
from hron_jax.envs.table_cache import episode_tables
from hron_jax.graph_builder import GraphBuilder, GraphConfig, Placement
from hron_jax.metric_map import MapConfig, MetricMap
from hron_jax.scenes.loader import Scene, load_scene
from hron_jax.sensors import Camera, CameraConfig


@dataclasses.dataclass(frozen=True)
class NavConfig:
    """Static settings of a navigation env (hashable)."""

    task: str = 'exploratory'
    max_steps: int = 500
    success_distance: float = 1.0
    success_reward: float = 10.0
    wrong_penalty: float = 5.0  # directed only
    shaping_scale: float = 1.0
    distractors: bool = False
    num_distractors: int = 6
    # Exploratory: other objects of the vocabulary on, inside and under furniture all over the
    # house (same-category ones never satisfy the goal), so a fully explored graph holds ~100
    # nodes as in the paper's scenes (placement.sample_exploratory). The directed task has none.
    num_clutter: int = P.DEFAULT_NUM_CLUTTER
    min_start_distance: float = 1.0  # exploratory: geodesic d0 of a start must exceed this (m)
    metric_map: bool = False
    premap: bool = False  # graph (and map) start with rooms + furniture discovered
    auto_reset: bool = True
    camera: CameraConfig = CameraConfig(width=32, height=32)
    sim: S.SimConfig = S.SimConfig()
    graph: GraphConfig = GraphConfig()
    map: MapConfig = MapConfig()
    placement: P.PlacementConfig = P.PlacementConfig()

    def __post_init__(self):
        if self.task not in NAV_TASKS:
            raise ValueError(f'unknown navigation task {self.task!r}; valid: {", ".join(NAV_TASKS)}')
        if self.max_steps < 1:
            raise ValueError('max_steps must be >= 1')


@struct.dataclass
class NavInner:
    data: Any  # sim.SimState: what of the mjx.Data persists between steps
    placement: Placement  # pool objects of this episode
    goal: jax.Array  # i32[4] vocabulary indices (room -1 in the directed task)
    target: jax.Array  # i32 pool entry
    target_xy: jax.Array  # f32[2]
    target_field: jax.Array  # i32 row of the precomputed fields
    wrong_xy: jax.Array  # f32[2] directed task's wrong object (inf: none)
    discovered: jax.Array  # bool[N_MAX] graph builder state
    map_key: Any  # i32[Hg, Wg] metric map state, or None
    dist: jax.Array  # f32 geodesic distance to the success region now (m)
    d0: jax.Array  # f32 the same at reset
    path_length: jax.Array  # f32 xy distance travelled this episode (m)
    rng: jax.Array  # this env's key for future resets


class FinalInputs(NamedTuple):
    """What rendering the pre-reset observation of a step needs (the static geoms do not move, so
    only the geom positions of that episode's objects differ from the returned state's data)."""

    geom_xpos: jax.Array  # f32[ngeom, 3]
    pose: jax.Array  # f32[3]
    discovered: jax.Array  # before the final frame
    map_key: Any
    placement: Placement
    goal: jax.Array


class _Start(NamedTuple):
    """An episode before its first frame (what reset and auto-reset share)."""

    data: Any
    episode: P.Episode
    discovered: jax.Array
    map_key: Any
    dist: jax.Array


class NavigationEnv:
    """Directed / exploratory object navigation; see the module docstring."""

    num_actions = S.NUM_ACTIONS

    def __init__(self, scene: Scene | str | os.PathLike, config: NavConfig = NavConfig()):
        if not isinstance(scene, Scene):
            scene = load_scene(scene)
        self.scene = scene
        self.config = config
        self.sim = S.Simulator.from_file(scene.path, config.sim)
        self.camera = Camera.for_simulator(self.sim, config.camera, scene=scene)
        self.graph_builder = GraphBuilder(scene, config.graph, premap=config.premap)
        self.metric_map = (
            MetricMap(scene, config.camera, config.map, premap=config.premap) if config.metric_map else None
        )
        self.tables = episode_tables(
            scene,
            self.sim.mj_model,
            config.placement,
            success_distance=config.success_distance,
            agent_radius=config.sim.radius,
            agent_height=config.sim.height,
        )
        if config.task == 'exploratory' and not self.tables.goal_ok.any():
            raise ValueError(f'{scene.path}: no satisfiable goal')
        if config.task == 'directed' and len(self.tables.pairs) == 0:
            raise ValueError(
                f'{scene.path}: no directed pair (same furniture category on both halves '
                'of x = centre with different relations); use a symmetric scene'
            )
        off = scene.num_rooms + scene.num_furniture
        self._pool_mocap = np.asarray(scene.mocap_id[off:], np.int32)
        self._parked = np.asarray(self.sim.default_mocap_pos, np.float32)
        quat = np.zeros((self.sim.nmocap, 4), np.float32)
        quat[:, 0] = 1.0
        self._mocap_quat = quat
        self._num_distractors = config.num_distractors if config.distractors else 0

    # ---- API of hron_jax.envs.base -------------------------------------------------------------
    @property
    def auto_reset(self) -> bool:
        return self.config.auto_reset

    @property
    def unwrapped(self):
        return self

    @property
    def node_type_counts(self) -> tuple[int, int, int]:
        """Rows of obs['graph']'s node table by type (rooms, furniture, objects), then padding."""
        return self.graph_builder.node_type_counts

    def sample_episode(self, key) -> P.Episode:
        """The episode a reset with this key draws (no physics, no rendering)."""
        t = self.tables
        if self.config.task == 'directed':
            return P.sample_directed(key, t, self._num_distractors)
        return P.sample_exploratory(
            key, t, self._num_distractors, self.config.min_start_distance, self.config.num_clutter
        )

    def reset(self, rng) -> EnvState:
        k_ep, k_env = jax.random.split(rng)
        return self.reset_to(self.sample_episode(k_ep), k_env)

    def reset_to(self, episode: P.Episode, rng) -> EnvState:
        """Start a given episode (hand-built situations: edit a sampled Episode, e.g. its pose)."""
        start = self._start(episode)
        obs, disc, mkey, uncertain = self._observe(
            start.data, episode.pose, start.discovered, start.map_key, episode.placement, episode.goal
        )
        inner = self._inner(start, disc, mkey, rng)
        final = FinalInputs(
            start.data.geom_xpos,
            episode.pose,
            start.discovered,
            start.map_key,
            episode.placement,
            episode.goal,
        )
        return initial_state(obs, inner, info={'final': final, 'uncertain_rays': uncertain})

    def step(self, state: EnvState, action) -> EnvState:
        cfg = self.config
        inner: NavInner = state.inner
        action = jnp.asarray(action, jnp.int32)
        old = self.sim.agent_pose(inner.data)
        data = self.sim.step(inner.data, action)
        pose = self.sim.agent_pose(data)
        path = inner.path_length + jnp.linalg.norm(pose[:2] - old[:2])

        dist = self._distance(inner.target_field, pose[:2])
        dist = jnp.where(jnp.isfinite(dist), dist, inner.dist)
        success = jnp.linalg.norm(pose[:2] - inner.target_xy) < cfg.success_distance
        wrong = (jnp.linalg.norm(pose[:2] - inner.wrong_xy) < cfg.success_distance) & ~success
        reward = (
            cfg.shaping_scale * (inner.dist - dist) + cfg.success_reward * success - cfg.wrong_penalty * wrong
        )
        terminated = success | wrong
        spl = success * inner.d0 / jnp.maximum(inner.d0, path)
        # The same truncation rule as base.next_state, needed here before rendering.
        steps = state.info['steps'] + 1.0
        done = terminated | (steps >= cfg.max_steps)

        cont = inner.replace(data=data, dist=dist, path_length=path)
        final = FinalInputs(
            data.geom_xpos, pose, inner.discovered, inner.map_key, inner.placement, inner.goal
        )
        rng = inner.rng
        if cfg.auto_reset:
            rng, k_ep = jax.random.split(rng)
            ep = self.sample_episode(k_ep)
            start = self._start(ep)
            fresh = self._inner(start, start.discovered, start.map_key, rng)
            nxt = select_tree(done, fresh, cont)
            view_pose = jnp.where(done, ep.pose, pose)
        else:
            nxt, view_pose = cont, pose
        obs, disc, mkey, uncertain = self._observe(
            nxt.data, view_pose, nxt.discovered, nxt.map_key, nxt.placement, nxt.goal
        )
        nxt = nxt.replace(discovered=disc, map_key=mkey, rng=rng)
        out = next_state(
            state,
            obs,
            nxt,
            reward,
            terminated,
            success=success,
            spl=spl,
            path_length=path,
            max_steps=cfg.max_steps,
            info={'final': final, 'uncertain_rays': uncertain},
        )
        if cfg.auto_reset:
            info = dict(out.info)
            for k in ('steps', 'episode_return'):
                info[k] = jnp.where(done, 0.0, info[k])
            out = out.replace(info=info)
        return out

    def final_obs(self, state: EnvState):
        """The observation the last step would have returned without auto-reset (renders once).

        Equal to state.obs when that step did not end an episode."""
        f: FinalInputs = state.info['final']
        data = state.inner.data.replace(geom_xpos=f.geom_xpos)
        return self._observe(data, f.pose, f.discovered, f.map_key, f.placement, f.goal)[0]

    def observation_example(self):
        return jax.jit(self.reset)(jax.random.PRNGKey(0)).obs

    # ---- helpers -------------------------------------------------------------------------------
    def field(self, index) -> jax.Array:
        """f32[H, W] precomputed geodesic field of a candidate target point."""
        return P.field(self.tables, index)

    @functools.cached_property
    def oracle_fields(self) -> np.ndarray:
        """Fields to the disks of radius success_distance - robust_margin (oracle_policy), built
        on first use (also from inside a trace) in the same dtype as the task's fields."""
        t = self.tables
        with jax.ensure_compile_time_eval():
            f = P.success_fields(
                t.grid,
                jnp.asarray(t.point_xy),
                self.config.success_distance - self.config.placement.robust_margin,
            )
            return np.asarray(f).astype(t.fields.dtype)

    def _distance(self, field_index, xy):
        return G.geodesic_distance(self.field(field_index), self.tables.grid, xy)

    def _mocap(self, placement: Placement):
        parked = jnp.asarray(self._parked)
        idx = jnp.asarray(self._pool_mocap)
        pos = jnp.where(placement.active[:, None], placement.pos, parked[idx])
        return parked.at[idx].set(pos.astype(parked.dtype))

    def _start(self, ep: P.Episode) -> _Start:
        data = self.sim.init(ep.pose, self._mocap(ep.placement), jnp.asarray(self._mocap_quat))
        disc = self.graph_builder.reset(ep.placement, ep.pose)
        mkey = self.metric_map.reset() if self.metric_map is not None else None
        dist = self._distance(ep.target_field, ep.pose[:2])
        return _Start(data=data, episode=ep, discovered=disc, map_key=mkey, dist=dist)

    def _inner(self, start: _Start, disc, mkey, rng) -> NavInner:
        ep = start.episode
        return NavInner(
            data=start.data,
            placement=ep.placement,
            goal=ep.goal,
            target=ep.target,
            target_xy=ep.target_xy,
            target_field=ep.target_field,
            wrong_xy=ep.wrong_xy,
            discovered=disc,
            map_key=mkey,
            dist=start.dist,
            d0=start.dist,
            path_length=jnp.zeros((), jnp.float32),
            rng=rng,
        )

    def _observe(self, data, pose, discovered, map_key, placement, goal):
        """Render one frame and fold it into the graph (and map): (obs, discovered, map_key,
        uncertain), the last the f32 fraction of the frame's rays the camera's culling could not
        certify (sensors: 0 = exact)."""
        frame = self.camera.render(data, pose)
        cam = self.config.camera
        uncertain = frame.uncertain.astype(jnp.float32) / (cam.width * cam.height)
        disc = self.graph_builder.update(discovered, placement, pose, frame.instance, frame.depth)
        rgbd = jnp.concatenate([frame.rgb, (frame.depth / cam.max_depth)[..., None]], -1)
        obs = {
            'rgbd': rgbd.astype(jnp.float32),
            'goal': goal_lib.encode_goal(goal[0], goal[1], goal[2], goal[3]),
            'goal_classes': goal_lib.goal_classes(goal[0], goal[2], goal[3]),
            'graph': self.graph_builder.graph(disc, placement, pose),
        }
        if self.metric_map is not None:
            map_key = self.metric_map.update(map_key, pose, frame.depth, frame.semantic)
            obs['map'] = self.metric_map.observe(map_key, pose)
        return obs, disc, map_key, uncertain

    def agent_pose(self, state: EnvState) -> jax.Array:
        return self.sim.agent_pose(state.inner.data)


# ------------------------------------------------------------------------------------------------
# Reference policies and rollouts
# ------------------------------------------------------------------------------------------------


def oracle_policy(env: NavigationEnv, state: EnvState, rng=None) -> jax.Array:
    """Shortest-path follower (geodesic.oracle_action): turn toward the descent direction of the
    target's geodesic field (a look-ahead point on the shortest path), move forward once within
    half a turn of it.

    It descends `env.oracle_fields` (the distance to the disk shrunk by placement's robust_margin)
    rather than the task's fields: the latter can bottom out where the disk only grazes free space
    (a dead end next to furniture or a wall), a few cm from success that 0.2 m steps at 30 deg
    headings cannot reliably cover; the shrunk disk lies inside the success disk, so the episode
    succeeds on the way in."""
    del rng
    env = getattr(env, 'unwrapped', env)
    inner: NavInner = state.inner
    pose = env.sim.agent_pose(inner.data)
    f = jnp.asarray(env.oracle_fields)[inner.target_field].astype(jnp.float32)
    code = G.oracle_action(f, env.tables.grid, pose[:2], pose[2], turn=math.radians(env.sim.config.turn_deg))
    table = jnp.array([S.FORWARD, S.TURN_LEFT, S.TURN_RIGHT, S.STOP], jnp.int32)
    return table[code]


def pose_record(env):
    """`record` hook of hron_jax.rollout.unroll for a navigation env: per step the agent pose
    before the step ('pose' f32[3]), after it but before any auto-reset ('final_pose'), and the
    episode's geodesic start distance ('d0', what SPL divides by)."""

    def record(state, action, extras, nxt):
        return dict(pose=env.agent_pose(state), final_pose=nxt.info['final'].pose, d0=state.inner.d0)

    return record
