"""Directed and exploratory navigation envs: rewards, terminations, truncation, placement geometry,
goal satisfiability, distractors, oracle SR / SPL, determinism, vmap == single env, make_env.

Compiles are the cost here (MJX step on CPU), so every test shares a few jitted functions built in
module-scoped fixtures: for each env one `run(episode, rng, actions)` = reset_to + rollout.unroll
whose actions are scripted where >= 0 and the oracle's where -1, single and vmapped, compiled with
XLA's fast-compile options (measured, 16 envs: directed compile 25.5 -> 9.3 s, its 45 steps 0.3 ->
1.7 s; exploratory 36.8 -> 11.4 s, its 220 steps 5.6 -> 24.6 s).
"""

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from hron_jax import goals
from hron_jax.envs import TASKS, make_env
from hron_jax.envs import navigation as N
from hron_jax.envs.choice import ChoiceEnv
from hron_jax.rollout import episode_ends, unroll
from hron_jax.scenes import vocabulary as V
from hron_jax.sim import BACKWARD, FORWARD, STOP
from hron_jax.training import FAST_COMPILE, supported_options

ORACLE = -1
DIRECTED_T = 45  # = the directed env's max_steps; oracle episodes end (and auto-reset) sooner
EXPLORE_T = 220


def _make_run(env, num_steps):
    oracle = lambda state, k: (N.oracle_policy(env, state, k), {})

    def run(episode, rng, actions):
        k_env, k_pol = jax.random.split(rng)
        state0 = env.reset_to(episode, k_env)
        last, _, traj = unroll(
            env.step, state0, oracle, k_pol, num_steps, record=N.pose_record(env), actions=actions
        )
        return state0, last, traj

    return run


class Bundle:
    """An env with its shared jitted functions."""

    def __init__(self, env, num_steps):
        self.env = env
        self.T = num_steps
        self.sample = jax.jit(env.sample_episode)
        self.sample_batch = jax.jit(jax.vmap(env.sample_episode))
        run = _make_run(env, num_steps)
        self.run = jax.jit(run, compiler_options=supported_options(FAST_COMPILE))
        self.run_batch = jax.jit(jax.vmap(run), compiler_options=supported_options(FAST_COMPILE))

    def oracle_batch(self, seed, n):
        keys = jax.random.split(jax.random.PRNGKey(seed), n)
        eps = self.sample_batch(keys)
        actions = jnp.full((n, self.T), ORACLE, jnp.int32)
        return self.run_batch(eps, keys, actions)[2]


@pytest.fixture(scope='module')
def directed():
    env = make_env('directed', image_size=16, max_steps=DIRECTED_T, distractors=True, num_distractors=4)
    return Bundle(env, DIRECTED_T)


@pytest.fixture(scope='module')
def explore():
    env = make_env('exploratory', image_size=16, max_steps=300, distractors=True, num_distractors=8)
    return Bundle(env, EXPLORE_T)


@pytest.fixture(scope='module')
def directed_oracle(directed):
    return jax.tree.map(np.asarray, directed.oracle_batch(0, 16))


def _np(tree):
    return jax.tree.map(np.asarray, tree)


def _scripted(bundle, actions):
    a = np.full(bundle.T, ORACLE, np.int32)
    a[: len(actions)] = actions
    return jnp.asarray(a)


def _free_cell_near(env, xy, lo, hi, avoid=None):
    """A main free cell centre at xy distance in [lo, hi] from xy (and > 1.5 m from `avoid`)."""
    t = env.tables
    c = np.asarray(t.grid.centres()).reshape(-1, 2)
    d = np.linalg.norm(c - np.asarray(xy), axis=-1)
    ok = (t.room_cell >= 0) & (d >= lo) & (d <= hi)
    if avoid is not None and np.all(np.isfinite(avoid)):
        ok &= np.linalg.norm(c - np.asarray(avoid), axis=-1) > 1.5
    assert ok.any()
    return c[np.nonzero(ok)[0][0]]


# ---- factory -----------------------------------------------------------------------------------


def test_make_env_tasks_and_errors():
    assert TASKS == ('choice', 'directed', 'exploratory')
    assert isinstance(make_env('choice'), ChoiceEnv)
    with pytest.raises(ValueError, match='choice, directed, exploratory'):
        make_env('fetch')
    with pytest.raises(TypeError, match='valid'):
        make_env('choice', bogus=1)


def test_directed_env_defaults(directed):
    env = directed.env
    assert env.scene.path.endswith('symmetric_room.xml') and env.num_actions == 5
    assert env.auto_reset
    obs = env.observation_example()
    assert obs['rgbd'].shape == (16, 16, 4) and obs['rgbd'].dtype == jnp.float32
    assert 0.0 <= float(obs['rgbd'].min()) and float(obs['rgbd'].max()) <= 1.0
    assert obs['goal'].shape == (goals.GOAL_DIM,) and obs['goal_classes'].shape == (3,)
    assert 'map' not in obs
    n = env.scene.num_nodes
    assert obs['graph'].nodes['mask'].shape == (n,)
    # The directed goal has no room.
    assert goals.decode_goal(obs['goal'])[3] is None and int(obs['goal_classes'][2]) == -1


# ---- rewards, terminations, truncation (directed, hand-built situations) ----------------------


def test_success_when_placed_near_target(directed):
    env = directed.env
    key = jax.random.PRNGKey(11)
    ep = _np(directed.sample(key))
    xy = _free_cell_near(env, ep.target_xy, 0.4, 0.9, avoid=ep.wrong_xy)
    ep = ep._replace(pose=np.array([xy[0], xy[1], 0.0], np.float32))
    traj = _np(directed.run(ep, key, _scripted(directed, [STOP]))[2])
    # STOP leaves the pose unchanged, so shaping is exactly 0.
    assert traj['reward'][0] == pytest.approx(10.0, abs=1e-5)
    assert traj['done'][0] == 1.0 and traj['truncation'][0] == 0.0
    assert traj['metrics']['success'][0] == 1.0 and traj['metrics']['episode_done'][0] == 1.0
    assert traj['metrics']['episode_length'][0] == 1.0


def test_wrong_object_penalty_and_termination(directed):
    env = directed.env
    key = jax.random.PRNGKey(12)
    ep = _np(directed.sample(key))
    xy = _free_cell_near(env, ep.wrong_xy, 0.4, 0.9, avoid=ep.target_xy)
    ep = ep._replace(pose=np.array([xy[0], xy[1], 0.0], np.float32))
    traj = _np(directed.run(ep, key, _scripted(directed, [STOP]))[2])
    assert traj['reward'][0] == pytest.approx(-5.0, abs=1e-5)
    assert traj['done'][0] == 1.0 and traj['truncation'][0] == 0.0
    assert traj['metrics']['success'][0] == 0.0 and traj['metrics']['spl'][0] == 0.0


@pytest.mark.parametrize('action, sign', [(FORWARD, 1.0), (BACKWARD, -1.0)])
def test_shaping_sign(directed, action, sign):
    # From the fixed start (0, -2) facing +y, every target (tables at y = 0, shelves at y = 2.8) is
    # ahead, so forward shortens the geodesic distance and backward lengthens it.
    key = jax.random.PRNGKey(13)
    ep = directed.sample(key)
    traj = directed.run(ep, key, _scripted(directed, [action]))[2]
    r = float(traj['reward'][0])
    assert sign * r > 0.05 and abs(r) <= 0.2 + 1e-3
    assert float(traj['done'][0]) == 0.0
    assert float(traj['metrics']['path_length'][0]) == pytest.approx(0.2, abs=1e-3)


def test_truncation_is_not_termination_and_final_obs(directed):
    env = directed.env
    key = jax.random.PRNGKey(14)
    ep = directed.sample(key)
    state0, last, traj = directed.run(ep, key, _scripted(directed, [STOP] * directed.T))
    traj = _np(traj)
    m = env.config.max_steps
    assert m == directed.T
    assert not traj['done'][: m - 1].any()
    assert traj['done'][m - 1] == 1.0 and traj['truncation'][m - 1] == 1.0
    assert traj['reward'][m - 1] == 0.0 and traj['metrics']['success'][m - 1] == 0.0
    assert traj['metrics']['episode_length'][m - 1] == m
    assert traj['metrics']['episode_done'][m - 1] == 1.0
    # stop never ends an episode and never moves the agent
    assert np.all(traj['metrics']['path_length'] == 0.0)
    # Auto-reset: the returned state is the next episode's first...
    assert float(last.info['steps']) == 0.0 and float(last.info['episode_return']) == 0.0
    # ... and final_obs renders the truncated episode's last view, which (standing still all the
    # time) is its first one; GAE bootstraps from it.
    final = jax.jit(env.final_obs)(last)
    # (separately compiled renders may differ in the last bit)
    for k in ('rgbd', 'goal', 'goal_classes'):
        np.testing.assert_allclose(np.asarray(final[k]), np.asarray(state0.obs[k]), atol=1e-6)
    for k in ('mask', 'pos', 'category'):
        np.testing.assert_allclose(
            np.asarray(final['graph'].nodes[k]), np.asarray(state0.obs['graph'].nodes[k]), atol=1e-6
        )
    assert not np.array_equal(
        np.asarray(last.obs['graph'].nodes['pos']), np.asarray(final['graph'].nodes['pos'])
    )


def test_one_render_per_step(directed):
    """Auto-reset does not render twice: the traced step holds the simulator's step plus exactly
    one camera render (counted by primitives the renderer uses), and final_obs holds one."""
    env = directed.env
    state = jax.eval_shape(env.reset, jax.random.PRNGKey(0))
    action = jax.ShapeDtypeStruct((), jnp.int32)
    pose = jax.ShapeDtypeStruct((3,), jnp.float32)

    def count(fn, *args, prim):
        return str(jax.make_jaxpr(fn)(*args)).count(prim + '[')

    prims = [
        p
        for p in ('top_k', 'optimization_barrier', 'argmin', 'sort')
        if count(env.camera.render, state.inner.data, pose, prim=p) > 0
    ]
    assert prims
    for p in prims:
        per_render = count(env.camera.render, state.inner.data, pose, prim=p)
        physics = count(env.sim.step, state.inner.data, action, prim=p)
        assert count(env.step, state, action, prim=p) == physics + per_render, p
        assert count(env.final_obs, state, prim=p) == per_render, p


# ---- episode sampling: satisfiable goals, relation geometry, distractors ------------------------


def _slot_cats(env):
    t = env.tables
    return t.slot_relation, t.slot_furn_cat, t.slot_room_cat


def _check_placements(env, eps, directed_task):
    """Geometry of every active object against its slot, goal satisfaction, distractors."""
    scene = env.scene
    rel, fcat, rcat = _slot_cats(env)
    goal_rows = {tuple(g) for g in scene.goals.tolist()}
    off = scene.num_rooms + scene.num_furniture
    n = eps.goal.shape[0]
    for i in range(n):
        pl = jax.tree.map(lambda x: x[i], eps.placement)
        slots, goal, target = eps.slot[i], eps.goal[i], int(eps.target[i])
        active = np.nonzero(pl.active)[0]
        assert target in active
        assert np.all(slots[active] >= 0) and np.all(slots[~pl.active] == -1)
        assert len(set(slots[active].tolist())) == len(active)  # one object per slot
        for j in active:
            s = slots[j]
            half = V.OBJECT_HALF[scene.vocab_index[off + j]]
            c, h = scene.slot_center[s], scene.slot_half[s]
            assert np.all(np.abs(pl.pos[j, :2] - c[:2]) <= h[:2] - half[:2] + 1e-5)
            assert pl.pos[j, 2] == pytest.approx(c[2] - h[2] + half[2], abs=1e-5)
            assert 2 * half[2] <= 2 * h[2] + 1e-6
            assert pl.furniture[j] == scene.slot_furniture[s] and pl.relation[j] == scene.slot_relation[s]
        # target satisfies the goal tuple
        s = slots[target]
        assert scene.vocab_index[off + target] == goal[0]
        assert (rel[s], fcat[s]) == (goal[1], goal[2])
        np.testing.assert_allclose(eps.target_xy[i], pl.pos[target, :2], atol=1e-6)
        if directed_task:
            assert goal[3] == -1
            w = int(eps.wrong[i])
            sw = slots[w]
            assert scene.vocab_index[off + w] == goal[0] and fcat[sw] == goal[2] and rel[sw] != goal[1]
            mid = 0.5 * (scene.bounds[0, 0] + scene.bounds[1, 0])
            assert np.sign(pl.pos[w, 0] - mid) == -np.sign(pl.pos[target, 0] - mid)
            np.testing.assert_allclose(eps.wrong_xy[i], pl.pos[w, :2], atol=1e-6)
        else:
            assert tuple(goal.tolist()) in goal_rows and rcat[s] == goal[3]
            assert int(eps.wrong[i]) == -1
        # distractors of the goal's category never satisfy the goal tuple
        for j in active:
            if j == target or scene.vocab_index[off + j] != goal[0]:
                continue
            s = slots[j]
            room_ok = goal[3] < 0 or rcat[s] == goal[3]
            assert not (rel[s] == goal[1] and fcat[s] == goal[2] and room_ok)


def _ray_checks(scene, eps, count):
    """Independent check with mj_ray on the scene model: onTop rests on its furniture with open
    space above, inside has its furniture just below and above, under has the floor below and the
    furniture above."""
    m = scene.model
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    geomid = np.zeros(1, np.int32)
    off = scene.num_rooms + scene.num_furniture
    checked = 0
    for i in range(count):
        pl = jax.tree.map(lambda x: x[i], eps.placement)
        for j in np.nonzero(pl.active)[0]:
            half = V.OBJECT_HALF[scene.vocab_index[off + j]]
            p = pl.pos[j].astype(np.float64)
            furn, rel = int(pl.furniture[j]), int(pl.relation[j])
            eps_z = 1e-3
            down = mujoco.mj_ray(
                m, d, p - [0, 0, half[2] - eps_z], np.array([0, 0, -1.0]), None, 1, -1, geomid
            )
            g_down = int(geomid[0])
            up = mujoco.mj_ray(m, d, p + [0, 0, half[2] - eps_z], np.array([0, 0, 1.0]), None, 1, -1, geomid)
            g_up = int(geomid[0])
            assert 0 <= down < 2 * eps_z, (i, j, down)  # resting on a support
            owner_down = scene.geom_instance[g_down] if g_down >= 0 else -2
            owner_up = scene.geom_instance[g_up] if g_up >= 0 else -2
            if rel == V.ON_TOP:
                assert owner_down == furn
                assert up < 0 or up > 0.2 or owner_up != furn
            elif rel == V.INSIDE:
                assert owner_down == furn and owner_up == furn and up >= 0
            else:  # under
                assert scene.node_type[owner_down] == V.ROOM and owner_up == furn and up >= 0
            checked += 1
    return checked


def test_directed_episodes(directed):
    eps = _np(directed.sample_batch(jax.random.split(jax.random.PRNGKey(1), 128)))
    _check_placements(directed.env, eps, directed_task=True)
    assert _ray_checks(directed.env.scene, eps, 32) > 32
    # the fixed start
    np.testing.assert_allclose(eps.pose[:, :2], np.broadcast_to([0.0, -2.0], (128, 2)), atol=1e-5)
    # both relations and both sides occur
    assert len(set(eps.goal[:, 1].tolist())) == 3 and len(set(np.sign(eps.target_xy[:, 0]).tolist())) == 2


def test_exploratory_episodes(explore):
    env = explore.env
    eps = _np(explore.sample_batch(jax.random.split(jax.random.PRNGKey(2), 256)))
    _check_placements(env, eps, directed_task=False)
    assert _ray_checks(env.scene, eps, 48) > 48 * 5
    # Starts: random rooms, on main free cells, farther than min_start_distance from success.
    t = env.tables
    rc = np.asarray(t.grid.world_to_cell(eps.pose[:, :2]))
    w = t.grid.free.shape[1]
    assert np.all(t.room_cell[rc[:, 0] * w + rc[:, 1]] >= 0)
    rooms = env.scene.room_at(eps.pose[:, :2])
    assert len(set(rooms.tolist())) == env.scene.num_rooms
    d0 = jax.jit(jax.vmap(env._distance))(jnp.asarray(eps.target_field), jnp.asarray(eps.pose[:, :2]))
    assert np.all(np.asarray(d0) > env.config.min_start_distance)
    # goals vary, and include every relation
    assert len({tuple(g) for g in eps.goal.tolist()}) > 100
    assert set(eps.goal[:, 1].tolist()) == {0, 1, 2}
    # distractors: the goal category's other instances come first
    assert eps.placement.active.sum(1).min() >= 1 + min(8, 2)


# ---- oracle: SR / SPL (verifies metrics and physics) --------------------------------------------


def _report(name, m):
    print(
        f'{name}: oracle SR {m["success"].mean():.3f} SPL {m["spl"].mean():.3f} '
        f'({len(m["success"])} episodes, mean length {m["episode_length"].mean():.1f})'
    )


def _check_spl(traj):
    done = traj['metrics']['episode_done'] > 0.5
    succ = done & (traj['metrics']['success'] > 0.5)
    p = traj['metrics']['path_length'][succ]
    d0 = traj['d0'][succ]
    np.testing.assert_allclose(traj['metrics']['spl'][succ], d0 / np.maximum(d0, p), rtol=1e-5)


def first_episode_metrics(traj) -> dict:
    """Per env (leading batch axis [B, T]), the metrics of its first finished episode (of its last
    step where none finished), plus 'finished' (bool[B])."""
    finished, end = episode_ends(traj['metrics']['episode_done'])
    out = {k: np.take_along_axis(np.asarray(v), end[:, None], 1)[:, 0] for k, v in traj['metrics'].items()}
    out['finished'] = finished
    return out


def test_directed_oracle(directed_oracle):
    m = first_episode_metrics(directed_oracle)
    _report('directed', m)
    assert m['finished'].all()
    assert m['success'].mean() == 1.0
    assert m['spl'].mean() >= 0.85
    _check_spl(directed_oracle)


def test_exploratory_oracle(explore):
    traj = _np(explore.oracle_batch(0, 16))
    m = first_episode_metrics(traj)
    _report('exploratory', m)
    assert m['finished'].all()
    assert m['success'].mean() == 1.0
    assert m['spl'].mean() >= 0.85
    _check_spl(traj)
    # Return of a successful oracle episode: 10 + the shaping telescopes to d0 - d_final.
    done = traj['metrics']['episode_done'] > 0.5
    np.testing.assert_allclose(traj['metrics']['return'][done], 10.0 + traj['d0'][done], atol=0.35)


# ---- determinism and batching ---------------------------------------------------------------------


def test_deterministic(directed, directed_oracle):
    again = directed.oracle_batch(0, 16)
    for k in ('action', 'reward', 'done'):
        np.testing.assert_array_equal(np.asarray(again[k]), directed_oracle[k])
    other = directed.oracle_batch(1, 16)
    assert not np.array_equal(np.asarray(other['reward']), directed_oracle['reward'])


def test_vmap_matches_single_env(directed, directed_oracle):
    keys = jax.random.split(jax.random.PRNGKey(0), 16)
    actions = jnp.full(directed.T, ORACLE, jnp.int32)
    for i in range(16):
        ep = directed.sample(keys[i])
        traj = _np(directed.run(ep, keys[i], actions)[2])
        np.testing.assert_array_equal(traj['action'], directed_oracle['action'][i])
        np.testing.assert_array_equal(traj['done'], directed_oracle['done'][i])
        np.testing.assert_allclose(traj['reward'], directed_oracle['reward'][i], atol=1e-4)
        np.testing.assert_allclose(traj['metrics']['spl'], directed_oracle['metrics']['spl'][i], atol=1e-5)


def test_info_reports_the_observed_frames_uncertain_rays(directed):
    """info['uncertain_rays'] is the fraction of the observed frame's rays the camera could not
    certify: 0 <= it <= 1, equal to the camera's own count for that frame after reset and after
    steps; with culling sizes of 1 it is > 0 (and PPO logs its mean, see ppo.py)."""
    import dataclasses

    env = directed.env
    key = jax.random.PRNGKey(5)
    state0, last, _ = directed.run(directed.sample(key), key, _scripted(directed, [FORWARD, FORWARD]))
    pixels = env.config.camera.width * env.config.camera.height
    for s in (state0, last):
        data = s.inner.data
        frame = jax.jit(env.camera.render)(data, env.sim.agent_pose(data))
        assert float(s.info['uncertain_rays']) == float(frame.uncertain) / pixels
    tiny = dataclasses.replace(env.config.camera, k_box=1, k_sphere=1, k_capsule=1, k_band=1)
    coarse = make_env('directed', camera=tiny)
    frac = float(jax.jit(coarse.reset)(key).info['uncertain_rays'])
    assert 0.0 < frac <= 1.0
