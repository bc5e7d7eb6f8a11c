"""hron_jax.rollout: unroll against a hand-written step loop (one env and a vmapped batch), record
hooks, scripted actions, the episode-end index, the uniform reference policy, the choice task
through the generic path."""

from types import SimpleNamespace

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hron_jax.envs.base import AutoResetWrapper, initial_state, next_state
from hron_jax.envs.choice import ChoiceConfig, ChoiceEnv
from hron_jax.rollout import episode_ends, random_policy, unroll


class Walk:
    """A 1-D walk: action 1 steps right, 0 left (floor 0); reaching 3 terminates with reward 1 and
    success; 5 steps truncate. obs = position as f32[1]."""

    num_actions = 2
    max_steps = 5

    def reset(self, rng):
        return initial_state(jnp.zeros(1, jnp.float32), jnp.zeros((), jnp.int32))

    def step(self, state, action):
        pos = jnp.maximum(state.inner + 2 * action - 1, 0)
        goal = pos >= 3
        return next_state(
            state, pos.astype(jnp.float32)[None], pos, goal, goal, success=goal, max_steps=self.max_steps
        )

    def observation_example(self):
        return jnp.zeros(1, jnp.float32)


def policy(state, key):
    """Right with probability 0.7 (one env or a batch); extras: the obs the policy saw."""
    action = jax.random.bernoulli(key, 0.7, state.reward.shape).astype(jnp.int32)
    return action, {'seen': state.obs[..., 0]}


def hand_loop(step, state, key, num_steps):
    rows = []
    for _ in range(num_steps):
        key, k = jax.random.split(key)
        action, extras = policy(state, k)
        nxt = step(state, action)
        rows.append(
            dict(
                action=action,
                reward=nxt.reward,
                done=nxt.done,
                truncation=nxt.info['truncation'],
                seen=extras['seen'],
                success=nxt.metrics['success'],
            )
        )
        state = nxt
    return state, key, {k: np.stack([np.asarray(r[k]) for r in rows]) for k in rows[0]}


def test_unroll_matches_a_step_loop_single_env():
    env = AutoResetWrapper(Walk())
    key = jax.random.PRNGKey(0)
    state0 = env.reset(jax.random.PRNGKey(1))
    run = jax.jit(lambda s, k: unroll(env.step, s, policy, k, 12))
    last, key_out, traj = run(state0, key)
    ref_last, ref_key, ref = hand_loop(env.step, state0, key, 12)
    for k in ('action', 'reward', 'done', 'truncation', 'seen'):
        np.testing.assert_array_equal(np.asarray(traj[k]), ref[k], err_msg=k)
    np.testing.assert_array_equal(np.asarray(traj['metrics']['success']), ref['success'])
    np.testing.assert_array_equal(np.asarray(key_out), np.asarray(ref_key))
    assert float(last.info['steps']) == float(ref_last.info['steps'])
    assert traj['action'].shape == (12,) and traj['metrics']['episode_done'].shape == (12,)
    # 12 steps of a 5-step-limited walk end at least two episodes.
    assert traj['done'].sum() >= 2


def test_unroll_vmapped_batch_and_truncation():
    env = AutoResetWrapper(Walk())
    states = jax.vmap(env.reset)(jax.random.split(jax.random.PRNGKey(2), 4))
    key = jax.random.PRNGKey(3)
    _, _, traj = jax.jit(lambda s, k: unroll(jax.vmap(env.step), s, policy, k, 10))(states, key)
    _, _, ref = hand_loop(jax.vmap(env.step), states, key, 10)
    assert traj['action'].shape == (10, 4) and traj['reward'].shape == (10, 4)
    for k in ('action', 'reward', 'done', 'truncation', 'seen'):
        np.testing.assert_array_equal(np.asarray(traj[k]), ref[k], err_msg=k)
    # Always left: the walk never reaches 3, so every 5th step truncates (done, not terminated).
    left = lambda s, k: (jnp.zeros(s.reward.shape, jnp.int32), {})
    _, _, traj = unroll(jax.vmap(env.step), states, left, key, 10)
    want = np.tile(np.array([0, 0, 0, 0, 1] * 2, np.float32)[:, None], (1, 4))
    np.testing.assert_array_equal(np.asarray(traj['done']), want)
    np.testing.assert_array_equal(np.asarray(traj['truncation']), want)


def test_policy_on_final_adds_one_policy_row_and_no_step():
    env = AutoResetWrapper(Walk())
    states = jax.vmap(env.reset)(jax.random.split(jax.random.PRNGKey(2), 4))
    key = jax.random.PRNGKey(3)
    record = lambda s, a, e, n: {'before': s.inner}  # noqa: E731
    last, _, traj = unroll(jax.vmap(env.step), states, policy, key, 10, record=record)
    last_f, key_f, traj_f = jax.jit(
        lambda s, k: unroll(jax.vmap(env.step), s, policy, k, 10, record=record, policy_on_final=True)
    )(states, key)
    assert traj_f['action'].shape == (11, 4) and traj_f['before'].shape == (11, 4)
    for k in ('action', 'reward', 'done', 'truncation', 'seen', 'before'):  # the 10 steps unchanged
        np.testing.assert_array_equal(np.asarray(traj_f[k][:10]), np.asarray(traj[k]), err_msg=k)
    jax.tree.map(np.testing.assert_array_equal, last_f, last)  # the env was not stepped again
    # row 10: the policy and record saw the final state
    np.testing.assert_array_equal(np.asarray(traj_f['seen'][10]), np.asarray(last.obs[:, 0]))
    np.testing.assert_array_equal(np.asarray(traj_f['before'][10]), np.asarray(last.inner))
    for _ in range(11):
        key, _ = jax.random.split(key)
    np.testing.assert_array_equal(np.asarray(key_f), np.asarray(key))


def test_record_hook_and_field_clash():
    env = Walk()
    record = lambda s, a, e, n: {'before': s.inner, 'after': n.inner, 'echo': e['seen']}
    _, _, traj = unroll(env.step, env.reset(None), policy, jax.random.PRNGKey(4), 4, record=record)
    np.testing.assert_array_equal(np.asarray(traj['before'][1:]), np.asarray(traj['after'][:-1]))
    np.testing.assert_array_equal(np.asarray(traj['echo']), np.asarray(traj['seen']))
    np.testing.assert_array_equal(np.asarray(traj['before']), np.asarray(traj['seen']).astype(int))
    with pytest.raises(ValueError, match='reward'):
        unroll(
            env.step,
            env.reset(None),
            policy,
            jax.random.PRNGKey(4),
            2,
            record=lambda s, a, e, n: {'reward': n.reward},
        )


def test_scripted_actions_override_the_policy():
    env = Walk()
    key = jax.random.PRNGKey(5)
    scripted = jnp.array([1, 1, -1, 0, -1, -1], jnp.int32)
    _, _, free = unroll(env.step, env.reset(None), policy, key, 6)
    _, _, traj = jax.jit(lambda a: unroll(env.step, env.reset(None), policy, key, 6, actions=a))(scripted)
    a, f = np.asarray(traj['action']), np.asarray(free['action'])
    np.testing.assert_array_equal(a[[0, 1, 3]], [1, 1, 0])
    # The policy ran with the same keys, so where not scripted it chose what it would have anyway.
    np.testing.assert_array_equal(a[[2, 4, 5]], f[[2, 4, 5]])
    assert traj['action'].dtype == jnp.int32
    # The scripted start moved the walker: 0 -> 1 -> 2.
    np.testing.assert_array_equal(np.asarray(traj['seen'][:3]), [0.0, 1.0, 2.0])


def test_episode_ends():
    done = np.array(
        [
            [0, 0, 1, 0, 1],  # first done at 2 (a later one does not count)
            [0, 0, 0, 0, 0],  # never done: the last step
            [1, 0, 0, 0, 0],
            [0, 0, 0, 0, 1],
        ],
        np.float32,
    )
    finished, end = episode_ends(done)
    np.testing.assert_array_equal(finished, [True, False, True, True])
    np.testing.assert_array_equal(end, [2, 4, 0, 4])
    # bool flags and extra leading axes ([S, E, T]) give the same per-row answer
    f2, e2 = episode_ends(np.stack([done, done[::-1]]) > 0.5)
    assert f2.shape == e2.shape == (2, 4)
    np.testing.assert_array_equal(e2[0], end)
    np.testing.assert_array_equal(e2[1], end[::-1])
    # one-step episodes (the choice task)
    f1, e1 = episode_ends(np.ones((3, 1)))
    assert f1.all() and (e1 == 0).all()


def test_random_policy_covers_every_action():
    env = SimpleNamespace(num_actions=5)
    a = jax.vmap(lambda k: random_policy(env, None, k))(jax.random.split(jax.random.PRNGKey(6), 200))
    assert a.dtype == jnp.int32 and set(np.asarray(a).tolist()) == set(range(5))


def test_choice_task_through_the_generic_path():
    """A choice episode is one step: config.max_steps = 1 and unroll gives the env's own step."""
    env = ChoiceEnv(ChoiceConfig())
    assert env.config.max_steps == 1
    state = env.reset(jax.random.PRNGKey(7))
    oracle = lambda s, k: (s.inner.correct_action, {})
    _, _, traj = unroll(env.step, state, oracle, jax.random.PRNGKey(8), env.config.max_steps)
    nxt = env.step(state, state.inner.correct_action)
    assert traj['done'].shape == (1,) and float(traj['done'][0]) == 1.0
    assert float(traj['reward'][0]) == float(nxt.reward) == 1.0
    finished, end = episode_ends(np.asarray(traj['done'])[None])
    assert finished[0] and end[0] == 0
