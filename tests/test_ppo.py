"""PPO: GAE with truncation, the gymnax adapter, learning, vmapped seeds, chunked == one-shot."""

from typing import Any, NamedTuple

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import struct

from hron_jax import graph_types as GT
from hron_jax.envs.base import AutoResetWrapper, initial_state, next_state
from hron_jax.envs.choice import ChoiceConfig, ChoiceEnv
from hron_jax.ppo import PPOConfig, compute_gae, make_ppo, make_train
from hron_jax.scenes import vocabulary as V
from hron_jax.training import FAST_COMPILE, supported_options


# --- a small graph policy for the choice task (the project models are tested elsewhere) ---------
class TinyGraphNet(nn.Module):
    """One round of typed message passing, masked mean pooling, goal concat, 2-layer heads."""

    num_actions: int
    hidden: int = 32

    @nn.compact
    def __call__(self, obs):
        def embed(obs):
            g, n = obs['graph'], obs['graph'].nodes
            x = jnp.concatenate(
                [jax.nn.one_hot(n['category'], V.NUM_CLASSES), n['pos'][:, :2], n['size'][:, :2]], -1
            )
            h = nn.relu(nn.Dense(self.hidden)(x))
            e = jax.nn.one_hot(g.edges['edge_type'], GT.NUM_EDGE_TYPES)
            m = nn.relu(nn.Dense(self.hidden)(jnp.concatenate([h[g.senders], e], -1)))
            m = m * g.edges['mask'][:, None]
            h = nn.relu(
                nn.Dense(self.hidden)(
                    jnp.concatenate([h, jax.ops.segment_sum(m, g.receivers, num_segments=h.shape[0])], -1)
                )
            )
            mask = n['mask'][:, None]
            return jnp.concatenate([(h * mask).sum(0) / jnp.maximum(mask.sum(), 1), obs['goal']])

        # Orthogonal init (LAPACK QR) on purpose: vmapped over seeds it once deadlocked jaxlib.
        orth = nn.initializers.orthogonal(np.sqrt(2.0))
        z = nn.relu(nn.Dense(64, kernel_init=orth)(jax.vmap(embed)(obs)))
        logits = nn.Dense(self.num_actions)(nn.relu(nn.Dense(64, kernel_init=orth)(z)))
        value = nn.Dense(1)(nn.relu(nn.Dense(64, kernel_init=orth)(z)))
        return logits, value


class MLP(nn.Module):
    num_actions: int

    @nn.compact
    def __call__(self, obs):
        z = nn.tanh(nn.Dense(32)(obs))
        return nn.Dense(self.num_actions)(z), nn.Dense(1)(z)[..., 0]


# --- a tiny gymnax-style env (no gymnax dependency) -----------------------------------------------
class CorridorParams(NamedTuple):
    length: int = 4


class CorridorState(NamedTuple):
    pos: jax.Array
    time: jax.Array


class Corridor:
    """Walk right along a corridor; reward 1 and done at the end. Gymnax signatures.

    ``auto_reset=True`` mimics gymnax's Environment: step() resets internally and the raw versions
    are step_env / reset_env, which the wrapper must prefer.
    """

    num_actions = 2

    def __init__(self, auto_reset=False):
        if auto_reset:
            self.step_env, self.reset_env = self._step, self._reset
            self.step, self.reset = self._gymnax_step, self._reset
        else:
            self.step, self.reset = self._step, self._reset

    def _obs(self, s, params):
        return jax.nn.one_hot(s.pos, params.length + 1)

    def _reset(self, key, params):
        s = CorridorState(pos=jnp.int32(0), time=jnp.int32(0))
        return self._obs(s, params), s

    def _step(self, key, s, action, params):
        pos = jnp.clip(s.pos + 2 * action - 1, 0, params.length)
        s = CorridorState(pos=pos, time=s.time + 1)
        done = pos == params.length
        return self._obs(s, params), s, done.astype(jnp.float32), done, {'success': done}

    def _gymnax_step(self, key, s, action, params):
        obs, s2, r, d, info = self._step(key, s, action, params)
        obs0, s0 = self._reset(key, params)
        s2 = jax.tree.map(lambda a, b: jnp.where(d, a, b), s0, s2)
        return jnp.where(d, obs0, obs), s2, r, d, info


# --- an adapter from gymnax-style envs to hron_jax.envs.base (only these tests use one) -----------
def _f32(x):
    return jnp.asarray(x, jnp.float32)


@struct.dataclass
class GymnaxInner:
    env_state: Any
    rng: jax.Array


class GymnaxWrapper:
    """Adapts a gymnax-style env to the hron_jax.envs.base API.

    The wrapped env provides ``reset(key, params) -> (obs, env_state)`` and
    ``step(key, env_state, action, params) -> (obs, env_state, reward, done, info)``. If it also has
    ``reset_env`` / ``step_env`` (a real gymnax Environment, whose ``step`` auto-resets and so loses
    the final observation), those non-resetting versions are used instead; wrap the result in
    AutoResetWrapper (hron_jax.ppo does that for you).

    Termination vs truncation: gymnax folds its time limit into ``done``. The step is counted as a
    truncation when ``info['truncation']`` is set, or when ``max_steps`` is given here and reached
    without ``done`` (give the gymnax env a larger internal limit in that case). ``info['success']``,
    ``info['spl']`` and ``info['path_length']`` are passed through to metrics when present.
    """

    def __init__(self, env, params=None, max_steps: int | None = None, num_actions: int | None = None):
        self.env = env
        self.params = params
        self.max_steps = max_steps
        if num_actions is None:
            num_actions = getattr(env, 'num_actions', None)
        if num_actions is None:
            num_actions = int(env.action_space(params).n)
        self.num_actions = int(num_actions)
        self._reset = getattr(env, 'reset_env', env.reset)
        self._step = getattr(env, 'step_env', env.step)

    def reset(self, rng):
        rng, sub = jax.random.split(rng)
        obs, env_state = self._reset(sub, self.params)
        return initial_state(obs, GymnaxInner(env_state=env_state, rng=rng))

    def step(self, state, action):
        rng, sub = jax.random.split(state.inner.rng)
        obs, env_state, reward, done, info = self._step(sub, state.inner.env_state, action, self.params)
        info = info or {}
        done = _f32(done)
        trunc_flag = _f32(info['truncation']) if 'truncation' in info else jnp.zeros((), jnp.float32)
        terminated = done * (1.0 - trunc_flag)
        new = next_state(
            state,
            obs,
            GymnaxInner(env_state=env_state, rng=rng),
            reward,
            terminated,
            success=info.get('success', 0.0),
            spl=info.get('spl'),
            path_length=info.get('path_length', 0.0),
            max_steps=self.max_steps,
        )
        # An env-reported truncation ends the episode too (next_state only knows max_steps).
        truncation = jnp.maximum(new.info['truncation'], trunc_flag * done)
        done = jnp.maximum(new.done, truncation)
        info_out = dict(new.info, truncation=truncation)
        metrics = dict(new.metrics, episode_done=done)
        return new.replace(done=done, info=info_out, metrics=metrics)

    def observation_example(self):
        return self.reset(jax.random.PRNGKey(0)).obs


def test_gae_keeps_truncation_apart():
    gamma, lam = 0.9, 0.8
    # One env, 4 steps: step 1 truncates (bootstrap from final_value 5), step 3 terminates.
    r = jnp.array([[1.0], [2.0], [0.5], [3.0]])
    v = jnp.array([[0.1], [0.2], [0.3], [0.4]])
    done = jnp.array([[0.0], [1.0], [0.0], [1.0]])
    trunc = jnp.array([[0.0], [1.0], [0.0], [0.0]])
    fv = jnp.array([[0.0], [5.0], [0.0], [0.0]])
    last = jnp.array([7.0])  # after a terminal step: must be ignored
    adv, target = compute_gae(r, v, done, trunc, fv, last, gamma, lam)
    d3 = 3.0 - 0.4
    d2 = 0.5 + gamma * 0.4 - 0.3
    d1 = 2.0 + gamma * 5.0 - 0.2
    d0 = 1.0 + gamma * 0.2 - 0.1
    expected = np.array([d0 + gamma * lam * d1, d1, d2 + gamma * lam * d3, d3])
    np.testing.assert_allclose(np.asarray(adv)[:, 0], expected, rtol=1e-6)
    np.testing.assert_allclose(np.asarray(target), np.asarray(adv + v), rtol=1e-6)
    # No done at all: bootstraps from last_value.
    adv, _ = compute_gae(r[:1], v[:1], 0 * done[:1], 0 * trunc[:1], fv[:1], last, gamma, lam)
    np.testing.assert_allclose(float(adv[0, 0]), 1.0 + gamma * 7.0 - 0.1, rtol=1e-6)


@pytest.mark.parametrize('auto_reset', [False, True])
def test_gymnax_wrapper(auto_reset):
    env = AutoResetWrapper(GymnaxWrapper(Corridor(auto_reset), CorridorParams(4), max_steps=6))
    assert env.num_actions == 2 and env.observation_example().shape == (5,)
    step = jax.jit(env.step)
    s = env.reset(jax.random.PRNGKey(0))
    # Walking right reaches the end in 4 steps: terminated with success, the final obs is the end.
    for _ in range(4):
        s = step(s, jnp.int32(1))
    assert float(s.done) == 1 and float(s.info['truncation']) == 0 and float(s.reward) == 1
    assert float(s.metrics['success']) == 1 and float(s.metrics['episode_length']) == 4
    assert int(jnp.argmax(s.info['final_obs'])) == 4 and int(jnp.argmax(s.obs)) == 0
    assert float(s.info['steps']) == 0
    # Walking left hits the wrapper's 6-step limit: truncated, not terminated.
    for t in range(6):
        assert float(s.done) == (1.0 if t == 0 else 0.0)
        s = step(s, jnp.int32(0))
    assert float(s.done) == 1 and float(s.info['truncation']) == 1
    assert float(s.metrics['success']) == 0 and float(s.metrics['episode_length']) == 6


# --- learning ----------------------------------------------------------------------------------
def test_ppo_learns_choice():
    cfg = PPOConfig(
        num_envs=64,
        num_steps=2,
        total_timesteps=64 * 2 * 60,
        update_epochs=4,
        num_minibatches=2,
        lr=1e-3,
        ent_coef=0.01,
    )
    ppo = make_ppo(cfg, ChoiceEnv(ChoiceConfig()), TinyGraphNet(2))
    runner, metrics = jax.jit(ppo.train)(jax.random.PRNGKey(0))
    sr = np.asarray(metrics['success'])
    assert sr[:3].mean() < 0.7  # starts near chance
    assert sr[-5:].mean() >= 0.95  # stochastic policy at the end of training
    ev = jax.jit(ppo.evaluate, static_argnums=(2, 3))(runner.params, jax.random.PRNGKey(1), 8)
    assert float(ev['success']) >= 0.95 and float(ev['episodes']) == 64 * 8
    assert int(runner.update) == cfg.num_updates


def test_ppo_learns_gymnax_corridor_with_truncation():
    # 8-cell corridor, 12-step limit: a random walk mostly truncates; PPO must learn to walk right.
    env = GymnaxWrapper(Corridor(), CorridorParams(8), max_steps=12)
    cfg = PPOConfig(
        num_envs=16,
        num_steps=16,
        total_timesteps=16 * 16 * 40,
        update_epochs=4,
        num_minibatches=4,
        lr=3e-3,
        gamma=0.95,
        ent_coef=0.01,
    )
    _, metrics = jax.jit(make_train(cfg, env, MLP(2)))(jax.random.PRNGKey(0))
    sr = np.asarray(metrics['success'])
    assert sr[:2].mean() < 0.5 and np.nanmean(sr[-5:]) >= 0.95
    length = np.asarray(metrics['episode_length'])
    assert np.nanmean(length[-5:]) < 9.0


def test_rollout_values_bootstraps_and_last_value_match_a_step_loop():
    # PPO's rollout runs the model at one call site (a 1-2 pass loop per step, one more pass after
    # the last step); here every value it reports is recomputed from a plain loop over the same
    # actions: V(obs_t), V(real last obs) on truncating steps (0 elsewhere), V(obs_T).
    env = GymnaxWrapper(Corridor(), CorridorParams(8), max_steps=6)
    cfg = PPOConfig(num_envs=4, num_steps=14, total_timesteps=4 * 14, num_minibatches=2)
    ppo = make_ppo(cfg, env, MLP(2))
    runner = ppo.init(jax.random.PRNGKey(0))
    start = runner.env_state
    end, _, traj, last_value = jax.jit(ppo.rollout, static_argnums=(3, 4))(
        runner.params, start, jax.random.PRNGKey(1), 14, False
    )
    ppo_env = AutoResetWrapper(env)
    v_step, v_final_obs = jax.jit(jax.vmap(ppo_env.step)), jax.jit(jax.vmap(ppo_env.final_obs))
    value = lambda obs: np.asarray(MLP(2).apply(runner.params, obs)[1])  # noqa: E731
    state = start
    assert traj.obs.shape[0] == 15 and traj.value.shape == (14, 4)
    for t in range(14):
        np.testing.assert_array_equal(np.asarray(traj.obs[t]), np.asarray(state.obs))
        np.testing.assert_allclose(traj.value[t], value(state.obs), rtol=1e-5, atol=1e-6)
        state = v_step(state, traj.action[t])
        trunc = np.asarray(state.info['truncation'])
        np.testing.assert_array_equal(traj.truncation[t], trunc)
        np.testing.assert_allclose(
            traj.final_value[t], trunc * value(v_final_obs(state)), rtol=1e-5, atol=1e-6
        )
    assert np.asarray(traj.truncation).sum() >= 4  # the bootstrap branch ran (6-step limit, 14 steps)
    np.testing.assert_array_equal(np.asarray(traj.obs[14]), np.asarray(state.obs))
    np.testing.assert_allclose(last_value, value(state.obs), rtol=1e-5, atol=1e-6)
    jax.tree.map(np.testing.assert_array_equal, end.obs, state.obs)


# --- determinism: vmapped seeds, chunks ---------------------------------------------------------
SMALL = PPOConfig(
    num_envs=8, num_steps=2, total_timesteps=8 * 2 * 4, update_epochs=2, num_minibatches=2, lr=1e-3
)


@pytest.fixture(scope='module')
def small_ppo():
    return make_ppo(
        SMALL, ChoiceEnv(ChoiceConfig(distractors=True, max_distractors=6)), TinyGraphNet(2, hidden=16)
    )


@pytest.fixture(scope='module')
def single_train(small_ppo):
    return jax.jit(small_ppo.train)


def _max_diff(a, b):
    return max(float(jnp.max(jnp.abs(x - y))) for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)))


def test_vmapped_seeds_match_single_runs(small_ppo, single_train):
    keys = jax.random.split(jax.random.PRNGKey(42), 2)
    runners, metrics = jax.jit(jax.vmap(small_ppo.train))(keys)
    single = single_train
    for i in range(2):
        r, m = single(keys[i])
        assert _max_diff(jax.tree.map(lambda x: x[i], runners.params), r.params) < 1e-5
        np.testing.assert_allclose(np.asarray(metrics['success'][i]), np.asarray(m['success']))
    assert (
        _max_diff(jax.tree.map(lambda x: x[0], runners.params), jax.tree.map(lambda x: x[1], runners.params))
        > 1e-3
    )
    # Same key twice: bitwise identical.
    again = single(keys[0])[0]
    assert _max_diff(again.params, single(keys[0])[0].params) == 0.0


def test_chunked_updates_equal_one_shot(small_ppo, single_train):
    key = jax.random.PRNGKey(7)
    full, full_m = single_train(key)
    chunk = jax.jit(small_ppo.update_chunk, static_argnums=1)
    runner = jax.jit(small_ppo.init)(key)
    ms = []
    for _ in range(SMALL.num_updates // 2):
        runner, m = chunk(runner, 2)
        ms.append(m)
    assert int(runner.update) == SMALL.num_updates
    assert _max_diff(runner.params, full.params) < 1e-6
    assert _max_diff(runner.opt_state, full.opt_state) < 1e-6
    np.testing.assert_array_equal(np.asarray(runner.rng), np.asarray(full.rng))
    np.testing.assert_allclose(
        np.concatenate([np.asarray(m['success']) for m in ms]), np.asarray(full_m['success'])
    )


# --- the project model (issue target) -------------------------------------------------------------
# Small sizes of the main model (HGT + task-driven attention, no image branch) so CPU CI stays fast.
SG_ATTN_SIZES = dict(
    use_rgbd=False, hidden=32, fusion_fc=(64, 64, 64), head_fc=(64, 64), goal_fc=(32, 32, 32)
)


def test_rgbd_sg_attn_learns_choice_with_distractors():
    """Issue target: SR >= 0.95 on the choice task with up to 75 distractors, rgbd_sg_attn, CPU.

    Measured on a 2-core Xeon VM, seeds 0-7: 100 updates (12,800 env steps) took 107-151 s per seed
    with two such runs sharing the cores, after ~1 min of compile; SR first holds >= 0.95 over 5
    updates after 34-78 updates and ends at 1.00 for every seed. At ent_coef 0.01 the policy can
    turn deterministic on one of the 4 (goal side, relation) cases and stay there at SR ~0.73 (its
    entropy near 0, so no gradient reaches the other choice): seed 0 on that machine reached 1.00 at
    update 30, fell to 0.72 by update 70 (one update of approx KL 0.23) and ended at 0.74, choosing
    right never when the goal (circle above) is on the right and always rightly otherwise; one of
    seeds 100-107 (trained vmapped) never left ~0.72 in 100 updates (the freeze
    docs/reproduction.md's Table I note 3 saw at lr 3e-4, which made the task defaults' lr 1e-4: too
    slow for this test). 0.05 keeps both choices explored; it still allows an SR of 1.
    """
    from hron_jax.models import ModelConfig, make_model

    model = make_model('rgbd_sg_attn', 2, ModelConfig(**SG_ATTN_SIZES))
    cfg = PPOConfig(
        num_envs=64,
        num_steps=2,
        total_timesteps=64 * 2 * 100,
        update_epochs=4,
        num_minibatches=2,
        lr=5e-4,
        ent_coef=0.05,
    )
    ppo = make_ppo(cfg, ChoiceEnv(ChoiceConfig(distractors=True)), model)
    runner, metrics = jax.jit(ppo.train)(jax.random.PRNGKey(0))
    sr = np.asarray(metrics['success'])
    assert sr[:5].mean() < 0.7
    assert sr[-5:].mean() >= 0.95
    ev = jax.jit(ppo.evaluate, static_argnums=(2, 3))(runner.params, jax.random.PRNGKey(1), 8)
    assert float(ev['success']) >= 0.95


def test_init_params_are_those_of_the_envs_observations():
    # init_params stands one zero observation for the envs' batch (initialisers read shapes only),
    # so train.py computes the parameters on the host CPU without an env: the same values as
    # network.init on the real observations, and init(rng, params) is init(rng).
    from hron_jax.models import ModelConfig, make_model

    model = make_model('rgbd_sg_attn', 2, ModelConfig(**SG_ATTN_SIZES))
    ppo = make_ppo(SMALL, ChoiceEnv(ChoiceConfig(distractors=True, max_distractors=6)), model)
    key = jax.random.PRNGKey(3)
    runner = jax.jit(ppo.init, compiler_options=supported_options(FAST_COMPILE))(key)
    _, k_params, _ = jax.random.split(key, 3)
    direct = jax.jit(model.init, compiler_options=supported_options(FAST_COMPILE))(
        k_params, runner.env_state.obs
    )
    params = jax.jit(ppo.init_params, compiler_options=supported_options(FAST_COMPILE))(key)
    assert _max_diff(params, direct) == 0.0 and _max_diff(runner.params, direct) == 0.0
    given = jax.jit(ppo.init, compiler_options=supported_options(FAST_COMPILE))(
        key, jax.tree.map(lambda x: x + 1.0, params)
    )
    assert _max_diff(given.params, jax.tree.map(lambda x: x + 1.0, params)) == 0.0
    same = jax.tree.map(
        lambda x, y: bool(jnp.array_equal(x, y)), (given.env_state, given.rng), (runner.env_state, runner.rng)
    )
    assert all(jax.tree.leaves(same))


def test_vmapped_init_with_orthogonal_model_does_not_hang():
    # The project model uses orthogonal init (LAPACK QR); batched QR deadlocked jaxlib on 2 cores.
    from hron_jax.models import ModelConfig, make_model

    model = make_model('rgbd_sg_attn', 2, ModelConfig(**SG_ATTN_SIZES))
    ppo = make_ppo(SMALL, ChoiceEnv(ChoiceConfig(distractors=True, max_distractors=6)), model)
    keys = jax.random.split(jax.random.PRNGKey(3), 2)
    # compiled as train.py compiles init (Programs.initialize)
    runners = jax.jit(jax.vmap(ppo.init), compiler_options=supported_options(FAST_COMPILE))(keys)
    single = jax.jit(ppo.init, compiler_options=supported_options(FAST_COMPILE))(keys[1])
    assert _max_diff(jax.tree.map(lambda x: x[1], runners.params), single.params) == 0.0


# --- RLlib-style loss terms (the paper preset) ----------------------------------------------------
CORRIDOR = GymnaxWrapper(Corridor(), CorridorParams(8), max_steps=12)


def corridor_train(**kw):
    cfg = PPOConfig(
        **dict(
            dict(num_envs=16, num_steps=16, update_epochs=3, num_minibatches=4, lr=3e-3, gamma=0.95),
            total_timesteps=16 * 16 * kw.pop('updates', 8),
            **kw,
        )
    )
    return jax.jit(make_train(cfg, CORRIDOR, MLP(2)))(jax.random.PRNGKey(3))


def test_adaptive_kl_coefficient_follows_rllibs_rule():
    runner, m = corridor_train(kl_coeff=0.2, kl_target=0.01, updates=10)
    coeff, kl = np.asarray(m['kl_coeff']), np.asarray(m['kl_last_epoch'])
    assert coeff[0] == np.float32(0.2)
    expected = coeff[:-1] * np.where(kl[:-1] > 0.02, 1.5, np.where(kl[:-1] < 0.005, 0.5, 1.0))
    np.testing.assert_allclose(coeff[1:], expected, rtol=1e-6)
    # The run saw both directions or a plateau, i.e. the rule was exercised, not skipped.
    assert len(set(np.round(coeff / 0.2, 4))) > 1
    last = kl[-1]
    factor = 1.5 if last > 0.02 else 0.5 if last < 0.005 else 1.0
    np.testing.assert_allclose(float(runner.kl_coeff), coeff[-1] * factor, rtol=1e-6)
    # Without the penalty the coefficient stays put (and is not part of the loss).
    _, m0 = corridor_train(updates=3)
    assert np.all(np.asarray(m0['kl_coeff']) == 0.0)


def test_value_error_clamp_bounds_the_value_loss():
    _, clamped = corridor_train(vf_loss_clip=0.01, clip_value=False, updates=3)
    _, free = corridor_train(clip_value=False, updates=3)
    assert np.all(np.asarray(clamped['value_loss']) <= 0.5 * 0.01 + 1e-7)
    assert np.asarray(free['value_loss']).max() > 0.5 * 0.01  # the clamp had something to cut


def test_batch_advantage_norm_equals_minibatch_norm_with_one_minibatch():
    # One minibatch: standardising the batch once or the (same) minibatch is the same up to the
    # std floor (1e-4 vs + 1e-8); with 4 minibatches the two differ.
    one = dict(num_minibatches=1, updates=3, max_grad_norm=0.0)
    a, _ = corridor_train(advantage_norm='batch', **one)
    b, _ = corridor_train(advantage_norm='minibatch', **one)
    assert _max_diff(a.params, b.params) < 1e-4
    c, _ = corridor_train(advantage_norm='batch', updates=3)
    d, _ = corridor_train(advantage_norm='minibatch', updates=3)
    assert _max_diff(c.params, d.params) > 1e-3
