"""Behaviour of the main model and of each baseline on real navigation observations.

One module-scoped rollout of the exploratory task in house.xml (4 episodes x ROLLOUT_STEPS steps
of the shortest-path oracle, metric map on, no auto-reset) records every observation, the goal
sampled at reset, the fully discovered graph at the same pose and how many pixels of the target
each frame shows. On these observations:

- the chain goal tuple -> obs['goal'] / obs['goal_classes'] -> the task-pooling weights the main
  model sows is checked exactly at every step, with the target node live only once it was seen;
- obs['map'] (metric_map=True) has the documented shape and follows the agent;
- each variant of the paper is checked for its defining property by perturbing one input at a
  time (graph, map, which nodes are goal-category, the goal's relation / furniture / room, the
  goal object): what it must ignore leaves (logits, value) bitwise equal, what it must read
  changes them; and its sown pooling weights are the goal-category indicator (task-driven
  attention) or the live-node mask (mean pooling).

Models are tiny (hidden 16, one GNN layer); the rollout program dominates the time and is
compiled once with XLA's fast-compile options.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hron_jax import goals
from hron_jax.envs import make_env
from hron_jax.envs import navigation as N
from hron_jax.metric_map import MapConfig
from hron_jax.models import ModelConfig, attention_readout, make_model
from hron_jax.rollout import unroll
from hron_jax.scenes import vocabulary as V
from hron_jax.sim import TURN_LEFT, TURN_RIGHT
from hron_jax.training import FAST_COMPILE, compile_lowered, supported_options

MODELS = ('rgbd', 'rgbd_mm', 'rgbd_sg', 'rgbd_sg_attn', 'gcn', 'yang')
EPISODES = 4
ROLLOUT_STEPS = 100
MAP_CROP = 32  # a small egocentric map keeps the recorded observations small
TINY = ModelConfig(
    hidden=16,
    heads=1,
    gnn_layers=1,
    conv_features=(8, 8, 8),
    cnn_fc=(16, 16, 16),
    goal_fc=(16, 16, 16),
    fusion_fc=(16, 16, 16),
    head_fc=(16, 16),
)


def _np(tree):
    return jax.tree.map(np.asarray, jax.device_get(tree))


@pytest.fixture(scope='module')
def nav():
    """The recorded rollout: env, keys, and numpy traj with leading [EPISODES, ROLLOUT_STEPS]."""
    env = make_env(
        'exploratory', image_size=16, metric_map=True, map=MapConfig(crop=MAP_CROP), auto_reset=False
    )
    gb = env.graph_builder

    def episode(key):
        sampled = env.sample_episode(jax.random.split(key)[0])  # what reset(key) draws
        state = env.reset(key)

        def record(state, action, extras, nxt):
            pose = env.agent_pose(state)
            # The frame state.obs was built from (same data, same pose): target pixels in range.
            frame = env.camera.render(state.inner.data, pose)
            node = gb.object_offset + state.inner.target
            seen = jnp.sum((frame.instance == node) & (frame.depth < gb.config.detect_range))
            return dict(
                obs=state.obs,
                full_graph=gb.graph(gb.real, state.inner.placement, pose),
                target_pixels=seen,
                target_node=node,
                goal=state.inner.goal,
                pose=pose,
            )

        oracle = lambda s, k: (N.oracle_policy(env, s, k), {})
        traj = unroll(env.step, state, oracle, jax.random.fold_in(key, 1), ROLLOUT_STEPS, record=record)[2]
        return sampled.goal, traj

    keys = jax.random.split(jax.random.PRNGKey(0), EPISODES)
    run = compile_lowered(jax.jit(jax.vmap(episode)).lower(keys), FAST_COMPILE)
    sampled_goal, traj = _np(run(keys))
    return dict(env=env, sampled_goal=sampled_goal, traj=traj)


def _expected_goal_classes(goal):
    """i32[..., 3] class ids of (object, furniture, room) of goal tuples [..., 4], from the
    vocabulary directly (not through hron_jax.goals)."""
    g = np.asarray(goal)
    out = np.full(g.shape[:-1] + (3,), -1, np.int64)
    for j, (col, kind, names) in enumerate(
        ((0, 'object', V.OBJECTS), (2, 'furniture', V.FURNITURE), (3, 'room', V.ROOMS))
    ):
        ids = np.array([V.class_id(kind, n) for n in names])
        out[..., j] = np.where(g[..., col] >= 0, ids[np.maximum(g[..., col], 0)], -1)
    return out


def _indicator(graph, goal_classes):
    """bool[..., N]: live node whose category is one of goal_classes (>= 0)."""
    cat = np.asarray(graph.nodes['category'])[..., :, None]
    g = np.asarray(goal_classes)[..., None, :]
    return ((cat == g) & (g >= 0)).any(-1) & np.asarray(graph.nodes['mask']).astype(bool)


_RUNNERS: dict = {}


def _runner(name):
    """(model, jitted (params, obs) -> (logits, value, pool_weights or None)) of a tiny `name`."""
    if name not in _RUNNERS:
        model = make_model(name, N.NavigationEnv.num_actions, TINY)

        def apply(params, obs):
            logits, value, att = attention_readout(model, params, obs)
            enc = att.get('core', {}).get('graph_encoder', {})
            return logits, value, enc['pool_weights'][0] if 'pool_weights' in enc else None

        _RUNNERS[name] = (model, jax.jit(apply, compiler_options=supported_options(FAST_COMPILE)))
    return _RUNNERS[name]


@pytest.fixture(scope='module')
def params(nav):
    """Initialised parameters of every variant (on the first observation)."""
    obs0 = jax.tree.map(lambda x: x[0, 0], nav['traj']['obs'])
    out = {}
    for i, name in enumerate(MODELS):
        model, _ = _runner(name)
        out[name] = jax.jit(model.init, compiler_options=supported_options(FAST_COMPILE))(
            jax.random.PRNGKey(i), obs0
        )
    return out


def _run(name, params, obs):
    """numpy (logits [B, T, A], value [B, T], pool_weights [B, T, N] or None) on obs [B, T, ...]."""
    logits, value, pw = _np(_runner(name)[1](params[name], obs))
    return logits, value, None if pw is None else pw.reshape(value.shape + pw.shape[-1:])


# ------------------------------------------------------------------------------------------------
# 1. goal -> goal_classes -> task-pooling weights, at every step of real episodes
# ------------------------------------------------------------------------------------------------


def test_goal_classes_select_the_pooled_nodes_in_navigation_episodes(nav, params):
    env, traj = nav['env'], nav['traj']
    obs, goal = traj['obs'], traj['goal']  # goal i32[B, T, 4] (the env's inner goal)
    B, T = goal.shape[:2]

    # The goal sampled at reset is the episode's goal at every step, a satisfiable row of the
    # scene's goal table, with a room (exploratory task).
    np.testing.assert_array_equal(goal, np.broadcast_to(nav['sampled_goal'][:, None], goal.shape))
    table = {tuple(r) for r in env.tables.goals[env.tables.goal_ok]}
    assert all(tuple(g) in table for g in nav['sampled_goal'])
    assert (nav['sampled_goal'][:, 3] >= 0).all()
    assert len({tuple(g) for g in nav['sampled_goal']}) > 1  # several different goals

    # obs['goal'] encodes it (decoded names) and obs['goal_classes'] are its class ids.
    for b in range(B):
        o, r, f, room = nav['sampled_goal'][b]
        want = (V.OBJECTS[o], V.RELATIONS[r], V.FURNITURE[f], V.ROOMS[room])
        for t in (0, T // 2, T - 1):
            assert goals.decode_goal(obs['goal'][b, t]) == want
    np.testing.assert_array_equal(obs['goal_classes'], _expected_goal_classes(goal))

    # The main model's sown pooling weights: exactly 1 on live nodes of those categories, else 0.
    _, _, pw = _run('rgbd_sg_attn', params, obs)
    graph = obs['graph']
    want = _indicator(graph, obs['goal_classes'])
    np.testing.assert_array_equal(pw, want.astype(np.float32))
    live = graph.nodes['mask'].astype(bool)
    assert want.any() and (live & ~want).any()  # pooling selects some live nodes, not all

    # The target's node is live exactly from the first frame that shows it (never before).
    rows = np.arange(B)[:, None], np.arange(T)[None], traj['target_node']
    target_live = live[rows]
    seen = np.cumsum(traj['target_pixels'] > 0, axis=1) > 0
    np.testing.assert_array_equal(target_live, seen)
    np.testing.assert_array_equal(pw[rows], target_live.astype(np.float32))
    # Some episode starts with the target unseen and discovers it during the rollout, and before
    # that the pooling already selects the goal's furniture / room nodes (weight 1, not the target).
    late = [b for b in range(B) if not seen[b, 0] and seen[b, -1]]
    assert late, 'no episode discovers its target mid-rollout; change the keys or ROLLOUT_STEPS'
    before = ~seen
    assert (pw.sum(-1)[before] > 0).any()
    assert (pw[rows][before] == 0).all()


# ------------------------------------------------------------------------------------------------
# 2. metric_map=True through NavigationEnv
# ------------------------------------------------------------------------------------------------


def test_metric_map_observation_follows_the_agent(nav):
    traj = nav['traj']
    m = traj['obs']['map']
    assert m.shape == (EPISODES, ROLLOUT_STEPS, MAP_CROP, MAP_CROP, 3) and m.dtype == np.float32
    observed, height = m[..., 0], m[..., 1]
    assert set(np.unique(observed)) <= {0.0, 1.0}
    assert (height >= 0).all() and (height <= 1).all()
    assert (height[observed == 0] == 0).all()
    assert (observed[:, 0].sum((-1, -2)) > 0).all()  # the first frame is already in the map
    # Whenever the agent moves (> 1 cm) or turns, the egocentric map changes; where the pose
    # stays exactly the same (stop, or blocked), so does the map.
    step = np.abs(np.diff(traj['pose'], axis=1))  # [B, T-1, 3]
    moved = (step[..., :2].max(-1) > 0.01) | (step[..., 2] > 0.01)
    turned = np.isin(traj['action'][:, :-1], (TURN_LEFT, TURN_RIGHT)) & moved
    still = step.max(-1) == 0
    changed = np.abs(np.diff(m, axis=1)).max((-1, -2, -3)) > 0
    assert moved.sum() > 100 and turned.sum() > 10 and still.sum() > 10
    np.testing.assert_array_equal(changed[moved], True)
    np.testing.assert_array_equal(changed[still], False)


# ------------------------------------------------------------------------------------------------
# 3. each variant's defining property, by perturbation
# ------------------------------------------------------------------------------------------------

# What each variant of the paper reads (True: the perturbation must change its output, False: it
# must leave it bitwise equal), and its pooling ('task': goal-category indicator, 'mean': live
# nodes, None: no graph branch).
#   graph: the fully discovered graph at the same pose instead of the observed one
#   node_geometry: every live node's position shifted by 0.5 m (node features of learned
#       variants include it; Yang et al.'s are word vectors + image code only)
#   map: the metric map of another episode
#   goal_nodes: goal_classes' furniture and room dropped (-1), obs['goal'] unchanged, i.e. only
#       which nodes count as goal-category changes
#   goal_context: the goal's relation, furniture and room replaced (obs['goal'] and goal_classes)
#   goal_object: the goal's object replaced (obs['goal'] and goal_classes)
READS = {
    # graph, node_geometry, map, goal_nodes, goal_context, goal_object, pooling
    'rgbd': (False, False, False, False, True, True, None),
    'rgbd_mm': (False, False, True, False, True, True, None),
    'rgbd_sg': (True, True, False, False, True, True, 'mean'),
    'rgbd_sg_attn': (True, True, False, True, True, True, 'task'),
    'gcn': (True, True, False, True, True, True, 'task'),
    'yang': (True, False, False, False, False, True, 'mean'),
}
PERTURBATIONS = ('graph', 'node_geometry', 'map', 'goal_nodes', 'goal_context', 'goal_object')


def _with_goal(obs, goal):
    """obs with obs['goal'] and obs['goal_classes'] rebuilt from goal tuples i32[B, T, 4]."""
    enc = jax.vmap(jax.vmap(lambda g: goals.encode_goal(g[0], g[1], g[2], g[3])))(jnp.asarray(goal))
    return dict(obs, goal=np.asarray(enc), goal_classes=_expected_goal_classes(goal).astype(np.int32))


def _perturbed(nav, which):
    traj = nav['traj']
    obs, goal = traj['obs'], traj['goal']
    if which == 'graph':
        return dict(obs, graph=traj['full_graph'])
    if which == 'node_geometry':
        g = obs['graph']
        pos = g.nodes['pos'] + np.where(g.nodes['mask'][..., None], np.float32([0.5, 0.0, 0.0]), 0.0)
        return dict(obs, graph=g._replace(nodes=dict(g.nodes, pos=pos.astype(np.float32))))
    if which == 'map':
        return dict(obs, map=np.roll(obs['map'], 1, axis=0))
    if which == 'goal_nodes':
        gc = obs['goal_classes'].copy()
        gc[..., 1:] = -1
        return dict(obs, goal_classes=gc)
    new = goal.copy()
    if which == 'goal_context':
        for col, size in ((1, len(V.RELATIONS)), (2, len(V.FURNITURE) - 1), (3, len(V.ROOMS))):
            new[..., col] = (new[..., col] + 1) % size  # 'rectangle' (choice task only) left out
    else:
        new[..., 0] = (new[..., 0] + 1) % len(V.OBJECTS)
    return _with_goal(obs, new)


def _input_changed(nav, which, pooling=None):
    """bool[B, T]: observations whose perturbed input differs in what `which` is about: for
    'goal_nodes' the goal-category indicator over the live nodes; for 'node_geometry' under task
    pooling, the graph has a live goal-category node (else nothing is pooled, whatever the
    geometry)."""
    obs = nav['traj']['obs']
    p = _perturbed(nav, which)
    if which == 'graph':
        return (p['graph'].nodes['mask'] != obs['graph'].nodes['mask']).any(-1)
    if which == 'node_geometry':
        if pooling == 'task':
            return _indicator(obs['graph'], obs['goal_classes']).any(-1)
        return (p['graph'].nodes['pos'] != obs['graph'].nodes['pos']).any((-1, -2))
    if which == 'map':
        return (p['map'] != obs['map']).any((-1, -2, -3))
    if which == 'goal_nodes':
        return (
            _indicator(obs['graph'], p['goal_classes']) != _indicator(obs['graph'], obs['goal_classes'])
        ).any(-1)
    return (p['goal'] != obs['goal']).any(-1)


def test_perturbations_change_the_inputs(nav):
    """Each perturbation really changes what it claims to (else the invariances are vacuous)."""
    obs = nav['traj']['obs']
    for which in ('graph', 'node_geometry', 'map', 'goal_context', 'goal_object'):
        assert _input_changed(nav, which).all(), which
    assert 0.5 < _input_changed(nav, 'node_geometry', 'task').mean() < 1.0
    assert 0.5 < _input_changed(nav, 'goal_nodes').mean() < 1.0  # some steps have no such node
    p = _perturbed(nav, 'goal_context')
    np.testing.assert_array_equal(p['goal_classes'][..., 0], obs['goal_classes'][..., 0])
    assert (p['goal_classes'][..., 1:] != obs['goal_classes'][..., 1:]).all()
    p = _perturbed(nav, 'goal_object')
    assert (p['goal_classes'][..., 0] != obs['goal_classes'][..., 0]).all()
    np.testing.assert_array_equal(p['goal_classes'][..., 1:], obs['goal_classes'][..., 1:])
    assert (_indicator(obs['graph'], obs['goal_classes']) != obs['graph'].nodes['mask']).any()


@pytest.mark.parametrize('name', MODELS)
def test_variant_reads_exactly_its_inputs(name, nav, params):
    """Perturbing an input the variant must read changes (logits, value) on every observation
    where that input changed and on no other; perturbing one it must ignore leaves them bitwise
    equal. Its sown pooling weights are the goal-category indicator (task-driven attention) or
    the live-node mask (mean pooling)."""
    obs = nav['traj']['obs']
    base_logits, base_value, pw = _run(name, params, obs)
    *reads, pooling = READS[name]
    for which, must_read in zip(PERTURBATIONS, reads):
        logits, value, _ = _run(name, params, _perturbed(nav, which))
        diff = np.maximum(np.abs(logits - base_logits).max(-1), np.abs(value - base_value))
        if must_read:
            changed = _input_changed(nav, which, pooling)
            assert (diff[changed] > 0).all(), f'{name} ignores the {which} perturbation somewhere'
            assert (diff[~changed] == 0).all(), f'{name}: {which} changed outputs where it changed no input'
        else:
            np.testing.assert_array_equal(logits, base_logits, err_msg=f'{name} reads {which}')
            np.testing.assert_array_equal(value, base_value, err_msg=f'{name} reads {which}')

    graph = obs['graph']
    if pooling is None:
        assert pw is None
        # Never reads the graph: the observation may lack it altogether.
        no_graph = {k: v for k, v in obs.items() if k != 'graph'}
        logits, value, _ = _run(name, params, no_graph)
        np.testing.assert_array_equal(logits, base_logits)
        np.testing.assert_array_equal(value, base_value)
    elif pooling == 'task':
        np.testing.assert_array_equal(pw, _indicator(graph, obs['goal_classes']).astype(np.float32))
    else:
        np.testing.assert_array_equal(pw, graph.nodes['mask'].astype(np.float32))
