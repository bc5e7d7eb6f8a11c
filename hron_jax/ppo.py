"""PPO for hron-jax environments, PureJaxRL style: the whole training loop is one pure function.

    ppo = make_ppo(config, env, network)
    runner = ppo.init(rng)                                   # params, optimiser, envs, rng
    params = ppo.init_params(rng)                            # init(rng)'s params alone
    runner, metrics = ppo.update_chunk(runner, n_updates)    # n_updates static; pure, jittable
    runner, metrics = ppo.train(rng)                         # = init + config.num_updates updates
    train = make_train(config, env, network)                 # same as ppo.train
    runner, metrics = jax.jit(jax.vmap(train))(rngs)         # several seeds in one program

env: any hron_jax.envs.base.Env (one env, no batch axis); it is wrapped in AutoResetWrapper unless it
    already is one or resets itself (an ``auto_reset`` attribute that is True, as the navigation envs,
    which render once per step that way), and vmapped over config.num_envs.
network: a flax module, ``network.apply(params, obs) -> (logits f32[B, A], value f32[B] or [B, 1])``
    on a batch of observations (every obs leaf with a leading [B] axis).

One update = a rollout of num_steps steps of num_envs envs (hron_jax.rollout.unroll of the vmapped
env step), GAE, then update_epochs passes over num_minibatches shuffled minibatches (lax.scan x
lax.scan) of the clipped PPO objective + clipped value loss - entropy bonus, with global-norm
gradient clipping and Adam.

The loss has two styles in one config (PPOConfig): PureJaxRL / CleanRL's (the defaults: PPO2
value clipping by clip_eps, advantages standardised per minibatch, gradient clipping, entropy
bonus) and RLlib's PPO of 2022, which the paper's release ran (hron_jax.run_config's `paper`
preset): the squared value error clamped at vf_loss_clip (RLlib's vf_clip_param), advantages
standardised once over the whole rollout, no gradient clipping, and an adaptive penalty
kl_coeff * KL(old || new) (exact categorical KL) whose coefficient grows x1.5 after an update whose
last epoch's mean KL exceeds 2 kl_target and halves below kl_target / 2 (RLlib's update_kl).

Termination vs truncation (as in Brax, but exact): an env step that truncates (time limit) is done,
so the value of the next obs (already the reset obs) is not used; instead the rollout evaluates the
value of the pre-reset final obs (``env.final_obs(state)``: AutoResetWrapper's info['final_obs'], or
what a self-resetting env renders on demand) and GAE bootstraps from it.
That extra forward pass is a second pass of the rollout's one model call site (`rollout`: a
while loop of 1 or 2 passes, in the iteration after the truncating step), so it costs nothing in
the steps where no env truncates (under vmap over seeds the render of the final obs turns into a
select and always runs), and the training program compiles the model once for acting, last value
and bootstrap (and once more for the update's forward + backward).

metrics (one entry per update, each f32[n_updates]): the episode metrics (envs.base.EPISODE_METRICS:
'success', 'spl', 'episode_length', 'path_length', 'return') are means over the episodes completed
during that update's rollout (NaN when none completed), 'episodes' their count, 'reward' the mean
per-step reward, 'env_steps' the cumulative number of env steps, 'kl_coeff' the penalty's
coefficient during the update, 'kl_last_epoch' the mean KL its adaptation used, the loss
terms ('kl' the exact KL(old || new)) averaged over epochs and minibatches, and, for envs whose
info has it (navigation), 'uncertain_rays': the mean fraction of each observed frame's rays that
the ray caster's culling could not certify (hron_jax.sensors; 0 = every frame exact).

Everything is deterministic given the rng: chunked updates give the same result as one-shot training.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.custom_batching
import jax.numpy as jnp
import optax
from flax import struct

from hron_jax.envs.base import EPISODE_METRICS, AutoResetWrapper
from hron_jax.errors import ConfigError
from hron_jax.rollout import unroll

ADVANTAGE_NORMS = ('minibatch', 'batch', 'none')


@dataclasses.dataclass(frozen=True)
class PPOConfig:
    num_envs: int = 8
    num_steps: int = 128  # rollout length per env per update
    total_timesteps: int = 1_500_000
    update_epochs: int = 4
    num_minibatches: int = 4
    lr: float = 2.5e-4
    anneal_lr: bool = False  # linear decay to 0 over all optimiser steps
    gamma: float = 0.99
    gae_lambda: float = 0.95
    clip_eps: float = 0.2
    clip_value: bool = True  # PPO2-style clipped value loss (same clip_eps)
    vf_loss_clip: float = 0.0  # > 0: each sample's squared value error is clamped here (RLlib)
    ent_coef: float = 0.01
    vf_coef: float = 0.5  # on 0.5 * squared error
    max_grad_norm: float = 0.5  # global-norm gradient clipping; 0: none
    advantage_norm: str = 'minibatch'  # standardise advantages per 'minibatch', per 'batch', or 'none'
    kl_coeff: float = 0.0  # initial coefficient of the adaptive KL(old || new) penalty; 0: none
    kl_target: float = 0.01  # the coefficient x1.5 after an update with KL > 2 target, x0.5 below target / 2
    adam_eps: float = 1e-5

    def __post_init__(self):
        if self.advantage_norm not in ADVANTAGE_NORMS:
            raise ConfigError(
                'advantage_norm', f'expected one of {ADVANTAGE_NORMS}, got {self.advantage_norm!r}'
            )
        if min(self.num_envs, self.num_steps, self.num_minibatches) < 1:
            raise ConfigError(
                'num_envs' if self.num_envs < 1 else 'num_steps' if self.num_steps < 1 else 'num_minibatches',
                'must be >= 1',
            )
        if self.batch_size % self.num_minibatches:
            raise ConfigError(
                'num_minibatches',
                f'must divide the rollout num_envs * num_steps = '
                f'{self.batch_size}, got {self.num_minibatches}',
            )
        if self.num_updates < 1:
            raise ConfigError(
                'total_timesteps',
                f'must be at least one rollout (num_envs * '
                f'num_steps = {self.batch_size} steps), got {self.total_timesteps}',
            )

    @property
    def batch_size(self) -> int:
        return self.num_envs * self.num_steps

    @property
    def minibatch_size(self) -> int:
        return self.batch_size // self.num_minibatches

    @property
    def num_updates(self) -> int:
        return self.total_timesteps // self.batch_size


@struct.dataclass
class RunnerState:
    """Everything training carries between updates (a checkpoint is exactly this pytree)."""

    params: Any
    opt_state: Any
    env_state: Any  # batched EnvState, leading axis num_envs
    rng: jax.Array
    update: jax.Array  # i32, number of updates done
    kl_coeff: jax.Array  # f32, the KL penalty's current coefficient (adapted after each update)


class Transition(NamedTuple):
    obs: Any
    action: jax.Array
    logits: jax.Array  # the acting policy's, for the exact KL(old || new) of the penalty
    log_prob: jax.Array
    value: jax.Array
    reward: jax.Array
    done: jax.Array
    truncation: jax.Array
    final_value: jax.Array  # value of the pre-reset obs where truncation, else 0
    metrics: dict
    uncertain_rays: Any = None  # the env's info['uncertain_rays'] per step, where it has one


class PPO(NamedTuple):
    init: Callable  # (rng, params=None) -> RunnerState (params None: init_params(rng))
    init_params: Callable  # rng -> the network parameters of init(rng)
    update_chunk: Callable  # (RunnerState, n_updates: static int) -> (RunnerState, metrics)
    train: Callable  # rng -> (RunnerState, metrics)
    evaluate: Callable  # (params, rng, num_steps: static int, greedy: static bool) -> metrics
    # (params, env_state, rng, num_steps: static, greedy: static) -> (env_state, rng, Transition,
    # last_value): the rollout of one update (obs has num_steps + 1 rows)
    rollout: Callable
    config: PPOConfig


def compute_gae(reward, value, done, truncation, final_value, last_value, gamma, gae_lambda):
    """Advantages and value targets over a [T, B] rollout.

    done = terminated or truncated. After a done step the next obs belongs to a new episode, so its
    value is dropped; on truncation the episode was cut, not ended, so the value of its real last obs
    (final_value) is bootstrapped instead.
    """

    def body(carry, t):
        adv_next, value_next = carry
        r, v, d, tr, fv = t
        next_value = (1.0 - d) * value_next + tr * fv
        delta = r + gamma * next_value - v
        adv = delta + gamma * gae_lambda * (1.0 - d) * adv_next
        return (adv, v), adv

    init = (jnp.zeros_like(last_value), last_value)
    _, adv = jax.lax.scan(body, init, (reward, value, done, truncation, final_value), reverse=True)
    return adv, adv + value


def _masked_episode_means(metrics: dict) -> dict:
    """Means of the episode metrics over steps where an episode ended (NaN if none did)."""
    mask = metrics['episode_done']
    count = mask.sum()
    out = {
        k: jnp.where(count > 0, (metrics[k] * mask).sum() / jnp.maximum(count, 1.0), jnp.nan)
        for k in EPISODE_METRICS
    }
    out['episodes'] = count
    return out


def make_ppo(config: PPOConfig, env, network) -> PPO:
    if not (isinstance(env, AutoResetWrapper) or getattr(env, 'auto_reset', False)):
        env = AutoResetWrapper(env)
    num_opt_steps = config.num_updates * config.update_epochs * config.num_minibatches
    lr = optax.linear_schedule(config.lr, 0.0, num_opt_steps) if config.anneal_lr else config.lr
    adam = optax.adam(lr, eps=config.adam_eps)
    tx = optax.chain(optax.clip_by_global_norm(config.max_grad_norm), adam) if config.max_grad_norm else adam
    # On one flat vector: the same per-element Adam, but one set of kernels instead of one per
    # parameter leaf (64 for the main model; 2,734 -> 2,425 fusions in the training chunk).
    tx = optax.flatten(tx)
    v_reset = jax.vmap(env.reset)
    v_step = jax.vmap(env.step)
    v_final_obs = jax.vmap(env.final_obs)

    def apply(params, obs):
        logits, value = network.apply(params, obs)
        return logits.astype(jnp.float32), jnp.reshape(value, logits.shape[:-1]).astype(jnp.float32)

    # Parameter init runs as a loop, not batched, when train is vmapped over seeds: orthogonal
    # initialisers call LAPACK QR, and jaxlib's batched CPU QR kernel can deadlock when several run
    # at once on a small thread pool (seen on 2 cores: jax.vmap(train) hung forever). Init is
    # cheap, so the loop costs nothing and gives bitwise the same params as a single-seed run.
    network_init = jax.custom_batching.sequential_vmap(network.init)

    def init_params(rng):
        """The network parameters of init(rng). Parameter initialisers read only the shapes of the
        observation, so one zero observation stands for the envs' (same values): this needs no
        env, and train.py runs it as its own program on the host CPU (training.Programs)."""
        _, k_params, k_env = jax.random.split(rng, 3)
        obs = jax.eval_shape(v_reset, jax.random.split(k_env, config.num_envs)).obs
        return network_init(k_params, jax.tree.map(lambda a: jnp.zeros((1,) + a.shape[1:], a.dtype), obs))

    def init(rng, params=None) -> RunnerState:
        """The runner of seed rng: fresh envs, init_params(rng) (or the given params), Adam at 0."""
        params = init_params(rng) if params is None else params
        rng, _, k_env = jax.random.split(rng, 3)
        env_state = v_reset(jax.random.split(k_env, config.num_envs))
        return RunnerState(
            params=params,
            opt_state=tx.init(params),
            env_state=env_state,
            rng=rng,
            update=jnp.zeros((), jnp.int32),
            kl_coeff=jnp.asarray(config.kl_coeff, jnp.float32),
        )

    def rollout(params, env_state, rng, num_steps, greedy=False):
        """num_steps env steps; returns (env_state, rng, Transition [T, B] with obs [T + 1, B],
        last_value [B]). The model runs at ONE call site (so the training program compiles it
        once outside the update): in every iteration of an unroll with policy_on_final, first on
        the real last observation of the episodes the previous step truncated (only when there
        are any; their bootstrap value), then on the current observation (the policy's action and
        value). Iteration T only evaluates: the last value, and the bootstrap of step T - 1."""
        num_actions = env.num_actions

        def policy(state, key):
            truncation = state.info['truncation']  # of the step that produced `state`

            def evaluate(carry):
                p, final_value, _, _ = carry
                obs = jax.lax.cond(p == 0, lambda: v_final_obs(state), lambda: state.obs)
                logits, value = apply(params, obs)
                return p + 1, jnp.where(p == 0, value * truncation, final_value), logits, value

            zeros = jnp.zeros_like(truncation)
            first = jnp.where(jnp.any(truncation > 0), 0, 1)
            init = (first, zeros, jnp.zeros(zeros.shape + (num_actions,), jnp.float32), zeros)
            _, final_value, logits, value = jax.lax.while_loop(lambda c: c[0] < 2, evaluate, init)
            action = jnp.argmax(logits, -1) if greedy else jax.random.categorical(key, logits)
            log_prob = jnp.take_along_axis(jax.nn.log_softmax(logits), action[:, None], -1)[:, 0]
            extras = {'logits': logits, 'log_prob': log_prob, 'value': value, 'prev_final_value': final_value}
            return action, extras

        env_state, rng, traj = unroll(
            v_step,
            env_state,
            policy,
            rng,
            num_steps,
            record=lambda s, *_: (
                {'obs': s.obs}
                | ({'uncertain_rays': s.info['uncertain_rays']} if 'uncertain_rays' in s.info else {})
            ),
            policy_on_final=True,
        )
        obs = traj.pop('obs')  # T + 1 rows; the learner samples only from the first T
        final_value = traj.pop('prev_final_value')[1:]  # step t's, evaluated on the state after it
        last_value = traj['value'][num_steps]
        traj = jax.tree.map(lambda x: x[:num_steps], traj)
        return env_state, rng, Transition(obs=obs, final_value=final_value, **traj), last_value

    def loss_fn(params, mb: Transition, adv, target, kl_coeff):
        logits, value = apply(params, mb.obs)
        logp_all = jax.nn.log_softmax(logits)
        logp = jnp.take_along_axis(logp_all, mb.action[:, None], -1)[:, 0]
        log_ratio = logp - mb.log_prob
        ratio = jnp.exp(log_ratio)
        if config.advantage_norm == 'minibatch':
            adv = (adv - adv.mean()) / (adv.std() + 1e-8)
        pg_loss = -jnp.minimum(
            ratio * adv, jnp.clip(ratio, 1.0 - config.clip_eps, 1.0 + config.clip_eps) * adv
        ).mean()
        v_err = jnp.square(value - target)
        if config.clip_value:
            v_clipped = mb.value + jnp.clip(value - mb.value, -config.clip_eps, config.clip_eps)
            v_err = jnp.maximum(v_err, jnp.square(v_clipped - target))
        if config.vf_loss_clip > 0:
            v_err = jnp.minimum(v_err, config.vf_loss_clip)
        value_loss = 0.5 * v_err.mean()
        entropy = -(jnp.exp(logp_all) * logp_all).sum(-1).mean()
        old_logp_all = jax.nn.log_softmax(mb.logits)
        kl = (jnp.exp(old_logp_all) * (old_logp_all - logp_all)).sum(-1).mean()
        loss = pg_loss + config.vf_coef * value_loss - config.ent_coef * entropy
        if config.kl_coeff > 0:
            loss = loss + kl_coeff * kl
        aux = {
            'loss': loss,
            'pg_loss': pg_loss,
            'value_loss': value_loss,
            'entropy': entropy,
            # k3 estimator of KL(old || new): non-negative, low variance.
            'approx_kl': ((ratio - 1.0) - log_ratio).mean(),
            'kl': kl,
            'clip_frac': (jnp.abs(ratio - 1.0) > config.clip_eps).mean(),
        }
        return loss, aux

    grad_fn = jax.grad(loss_fn, has_aux=True)

    def one_update(runner: RunnerState, _):
        env_state, rng, traj, last_value = rollout(
            runner.params, runner.env_state, runner.rng, config.num_steps
        )
        adv, target = compute_gae(
            traj.reward,
            traj.value,
            traj.done,
            traj.truncation,
            traj.final_value,
            last_value,
            config.gamma,
            config.gae_lambda,
        )

        if config.advantage_norm == 'batch':  # once over the whole rollout, as RLlib does
            adv = (adv - adv.mean()) / jnp.maximum(adv.std(), 1e-4)
        # Flatten [T, B] -> [T*B] (obs: [(T+1)*B], of which the permutation takes only the first
        # T*B rows, so the extra row is never copied out); the metrics are not needed by the loss.
        batch = (traj._replace(metrics={}, uncertain_rays=None), adv, target)
        batch = jax.tree.map(lambda x: x.reshape((-1,) + x.shape[2:]), batch)

        def epoch(carry, _):
            params, opt_state, rng = carry
            rng, k_perm = jax.random.split(rng)
            perm = jax.random.permutation(k_perm, config.batch_size)
            perm = perm.reshape(config.num_minibatches, config.minibatch_size)

            # Each minibatch is gathered where it is used: a shuffled copy of the whole batch
            # would double the rollout's memory (4096 envs x 16 steps of 128 x 128 RGB-D: 17 GB).
            # The indices are a permutation, always in bounds, so 'clip' takes the same rows as
            # the default 'fill' without the bounds-check code fill adds to every leaf's gather.
            def minibatch(carry, idx):
                params, opt_state = carry
                mb = jax.tree.map(lambda x: jnp.take(x, idx, axis=0, mode='clip'), batch)
                grads, aux = grad_fn(params, *mb, runner.kl_coeff)
                updates, opt_state = tx.update(grads, opt_state, params)
                return (optax.apply_updates(params, updates), opt_state), aux

            (params, opt_state), aux = jax.lax.scan(minibatch, (params, opt_state), perm)
            return (params, opt_state, rng), aux

        (params, opt_state, rng), aux = jax.lax.scan(
            epoch, (runner.params, runner.opt_state, rng), None, length=config.update_epochs
        )

        metrics = {k: v.mean() for k, v in aux.items()}
        metrics.update(_masked_episode_means(traj.metrics))
        metrics['reward'] = traj.reward.mean()
        if traj.uncertain_rays is not None:  # rays of the observed frames the camera could not certify
            metrics['uncertain_rays'] = traj.uncertain_rays.mean()
        update = runner.update + 1
        metrics['env_steps'] = (update * config.batch_size).astype(jnp.float32)
        # RLlib's adaptive KL coefficient, from the mean KL of the update's last epoch.
        kl = aux['kl'][-1].mean()
        factor = jnp.where(kl > 2.0 * config.kl_target, 1.5, jnp.where(kl < 0.5 * config.kl_target, 0.5, 1.0))
        metrics['kl_coeff'] = runner.kl_coeff
        metrics['kl_last_epoch'] = kl
        runner = RunnerState(
            params=params,
            opt_state=opt_state,
            env_state=env_state,
            rng=rng,
            update=update,
            kl_coeff=runner.kl_coeff * factor if config.kl_coeff > 0 else runner.kl_coeff,
        )
        return runner, metrics

    def update_chunk(runner: RunnerState, n_updates: int):
        return jax.lax.scan(one_update, runner, None, length=n_updates)

    def train(rng):
        return update_chunk(init(rng), config.num_updates)

    def evaluate(params, rng, num_steps: int, greedy: bool = True):
        """Runs the policy (no learning) on fresh envs; episode means as in the training metrics."""
        rng, k_env = jax.random.split(rng)
        env_state = v_reset(jax.random.split(k_env, config.num_envs))
        _, _, traj, _ = rollout(params, env_state, rng, num_steps, greedy=greedy)
        return _masked_episode_means(traj.metrics)

    return PPO(
        init=init,
        init_params=init_params,
        update_chunk=update_chunk,
        train=train,
        evaluate=evaluate,
        rollout=rollout,
        config=config,
    )


def make_train(config: PPOConfig, env, network) -> Callable:
    """PureJaxRL entry point: a pure ``train(rng) -> (RunnerState, metrics)``."""
    return make_ppo(config, env, network).train
