"""The one rollout loop of hron-jax, after Brax's ``acting.generate_unroll``, and the episode-end
index of its trajectories. Users: hron_jax.ppo (a vmapped batch of auto-resetting envs),
evaluation and analysis (one episodic env, vmapped over episodes), the navigation tests.

    state, key, traj = unroll(step, state, policy, key, num_steps, record=None, actions=None,
                              policy_on_final=False)
    finished, end = episode_ends(traj['done'])                  # numpy, after device_get
    action = random_policy(env, state, rng)                     # uniform reference policy

step: ``step(state, action) -> EnvState`` (hron_jax.envs.base); one env, or a batch when the caller
    passes ``jax.vmap(env.step)``: unroll never adds or assumes a batch axis, so every per-step leaf
    below has whatever leading axes the state's reward has ([] or [B]).
policy: ``policy(state, key) -> (action, extras)``, extras a dict of per-step arrays (e.g. PPO's
    log_prob and value); the key of step t comes from splitting the carried key once per step,
    ``key, k = split(key)``, so a rollout is a function of the key it starts from.
record: optional ``record(state, action, extras, next_state) -> dict`` of further per-step fields
    (e.g. the observation acted on, the agent pose, a bootstrap value).
actions: optional scripted actions i32[num_steps, ...] overriding the policy wherever >= 0 (the
    policy still runs, so its extras describe its own choice, not the scripted one).
policy_on_final: also run the policy (and record) on the final state, in the same loop: traj gets
    num_steps + 1 rows, and row num_steps holds the policy's extras on the state after the last
    step (e.g. PPO's bootstrap value), while its step fields describe no step (the env is not
    stepped there: they repeat the final state's own) and are to be dropped. One loop means one
    call site of the policy, so a program that needs that last pass compiles the policy once.

traj: a flat dict of arrays with a leading [num_steps] axis: 'action', 'reward', 'done',
'truncation' (next_state.info['truncation']), 'metrics' (next_state.metrics), then the policy's
extras and record's fields under their own names (a name used twice is an error).

Everything is pure and jittable (lax.scan over a static num_steps); vmap it over episodes or seeds.
"""

from __future__ import annotations

from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np


def unroll(
    step: Callable,
    state,
    policy: Callable,
    key: jax.Array,
    num_steps: int,
    *,
    record: Callable | None = None,
    actions=None,
    policy_on_final: bool = False,
):
    """Run `num_steps` steps; returns (final state, final key, traj). See the module docstring."""

    def body(carry, xs):
        state, key = carry
        i, scripted = xs
        key, k = jax.random.split(key)
        action, extras = policy(state, k)
        if scripted is not None:
            action = jnp.where(scripted >= 0, scripted, action).astype(jnp.int32)
        if policy_on_final:
            nxt = jax.lax.cond(i < num_steps, step, lambda s, _: s, state, action)
        else:
            nxt = step(state, action)
        out = dict(
            action=action,
            reward=nxt.reward,
            done=nxt.done,
            truncation=nxt.info['truncation'],
            metrics=nxt.metrics,
        )
        fields = [extras] + ([record(state, action, extras, nxt)] if record is not None else [])
        for more in fields:
            clash = set(out) & set(more)
            if clash:
                raise ValueError(f'unroll: per-step field(s) {sorted(clash)} recorded twice')
            out.update(more)
        return (nxt, key), out

    length = num_steps + 1 if policy_on_final else num_steps
    scripted = None if actions is None else jnp.asarray(actions, jnp.int32)
    if scripted is not None and policy_on_final:
        scripted = jnp.concatenate([scripted, jnp.full_like(scripted[:1], -1)])
    (state, key), traj = jax.lax.scan(body, (state, key), (jnp.arange(length), scripted), length=length)
    return state, key, traj


def episode_ends(done) -> tuple[np.ndarray, np.ndarray]:
    """(finished bool[...], end int[...]) of done flags [..., T] (numpy; float 0/1 or bool).

    end is the index of the first done step, or T - 1 where no step is done (the episode ran out
    of recorded steps); so ``end + 1`` steps belong to the episode either way."""
    done = np.asarray(done) > 0.5
    finished = done.any(-1)
    end = np.where(finished, np.argmax(done, -1), done.shape[-1] - 1)
    return finished, end


def random_policy(env, state, rng) -> jax.Array:
    """Uniform over env.num_actions (the chance-level reference of every task; evaluation's
    reference-policy signature, one env)."""
    del state
    return jax.random.randint(rng, (), 0, env.num_actions).astype(jnp.int32)
