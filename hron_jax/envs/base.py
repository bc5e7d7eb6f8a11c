"""Functional environment API shared by every hron-jax task (Brax / MuJoCo Playground style).

An environment is a pair of pure functions over a pytree state, one environment (no batch axis); the
learner vmaps them:

    env.reset(rng: PRNGKey) -> EnvState
    env.step(state: EnvState, action: i32[]) -> EnvState
    env.num_actions: int
    env.observation_example() -> obs pytree (one env, no batch axis)
    env.node_type_counts: tuple[int, ...], rows of obs['graph']'s node table by node type, a static
        layout (navigation: rooms, furniture, objects, then padding; choice: no rooms, the two
        rectangles, the objects); the HGT layers slice it (gnn.HGTConv)

``EnvState`` fields (all per env, scalars are shape ``[]``):

    obs      observation pytree after this step (after an auto-reset: the fresh episode's first obs)
    reward   f32, reward of the step that produced this state
    done     f32, 1 when that step ended the episode: terminated OR truncated
    metrics  dict of f32 describing the current episode so far; when ``metrics['episode_done']`` is 1
             they are the finished episode's final values, so a learner averages them over the steps
             where ``episode_done`` is 1 (keys: METRIC_KEYS)
    info     dict: 'steps' (f32 steps taken in the current episode), 'truncation' (f32, 1 when the
             step ended the episode by the time limit without a terminal event: GAE bootstraps there
             instead of cutting the return), 'episode_return' (running sum); wrappers add keys
             ('rng', 'final_obs')
    inner    the env-specific state (scene, agent pose, rng, ...)

Envs build their states with ``initial_state`` and ``next_state`` so the bookkeeping (step count,
truncation, return, metrics) is identical across tasks. ``AutoResetWrapper`` turns an episodic env into
an endless one for rollouts, and keeps the pre-reset observation in ``info['final_obs']`` so a learner
can bootstrap the value of a truncated episode from its real last state (learners ask for it with
``env.final_obs(state)``). An env may instead reset itself inside ``step`` (attribute
``auto_reset = True`` and a ``final_obs(state)`` method, e.g. the navigation envs, which so render
one frame per step and the pre-reset one only on demand); hron_jax.ppo then does not wrap it.
Rollouts of any env under a policy: hron_jax.rollout.
"""

from __future__ import annotations

from typing import Any, Protocol, runtime_checkable

import jax
import jax.numpy as jnp
from flax import struct

# What describes a finished episode (learners and evaluation read these at the steps where
# metrics['episode_done'] is 1). 'success' / 'spl' / 'path_length' come from the task,
# 'episode_length' / 'return' from the shared bookkeeping in next_state.
EPISODE_METRICS = ('success', 'spl', 'episode_length', 'path_length', 'return')
# Metrics every env reports; see EnvState.
METRIC_KEYS = EPISODE_METRICS + ('episode_done',)


@struct.dataclass
class EnvState:
    obs: Any
    reward: jax.Array
    done: jax.Array
    metrics: dict
    info: dict
    inner: Any = None


@runtime_checkable
class Env(Protocol):
    """What the learner relies on. Any object with these members plugs into hron_jax.ppo."""

    num_actions: int

    def reset(self, rng: jax.Array) -> EnvState: ...

    def step(self, state: EnvState, action: jax.Array) -> EnvState: ...

    def observation_example(self) -> Any: ...


def _f32(x) -> jax.Array:
    return jnp.asarray(x, jnp.float32)


def initial_state(obs, inner, info: dict | None = None) -> EnvState:
    """State right after a reset: zero reward/done/metrics, step counter at 0.

    ``info`` adds env-specific entries (they must keep their shape across steps).
    """
    zero = jnp.zeros((), jnp.float32)
    metrics = {k: zero for k in METRIC_KEYS}
    base_info = {'steps': zero, 'truncation': zero, 'episode_return': zero}
    if info:
        base_info.update(info)
    return EnvState(obs=obs, reward=zero, done=zero, metrics=metrics, info=base_info, inner=inner)


def next_state(
    prev: EnvState,
    obs,
    inner,
    reward,
    terminated,
    *,
    success=0.0,
    spl=None,
    path_length=0.0,
    max_steps: int | None = None,
    info: dict | None = None,
) -> EnvState:
    """State after one step, with the shared bookkeeping done here so every task agrees.

    terminated: a terminal event of the task (success, failure); the time limit is *not* one: pass
        ``max_steps`` and the step that reaches it without terminating is flagged as truncation.
    success/spl/path_length: the task's episode metrics so far (spl defaults to success, which is
        right for tasks without a path such as the choice bandit).
    Keys of ``prev.info`` that this function does not own (e.g. the wrapper's 'rng') are carried over.
    """
    terminated = _f32(terminated)
    steps = prev.info['steps'] + 1.0
    if max_steps is None:
        truncation = jnp.zeros((), jnp.float32)
    else:
        truncation = (steps >= max_steps).astype(jnp.float32) * (1.0 - terminated)
    done = jnp.maximum(terminated, truncation)
    reward = _f32(reward)
    episode_return = prev.info['episode_return'] + reward
    success = _f32(success)
    metrics = {
        'success': success,
        'spl': success if spl is None else _f32(spl),
        'path_length': _f32(path_length),
        'episode_length': steps,
        'return': episode_return,
        'episode_done': done,
    }
    new_info = dict(prev.info)
    new_info.update(steps=steps, truncation=truncation, episode_return=episode_return)
    if info:
        new_info.update(info)
    return EnvState(obs=obs, reward=reward, done=done, metrics=metrics, info=new_info, inner=inner)


class Wrapper:
    """Forwards everything it does not override to the wrapped env."""

    def __init__(self, env):
        self.env = env

    @property
    def num_actions(self) -> int:
        return self.env.num_actions

    def observation_example(self):
        return self.env.observation_example()

    def reset(self, rng):
        return self.env.reset(rng)

    def step(self, state, action):
        return self.env.step(state, action)

    @property
    def unwrapped(self):
        return getattr(self.env, 'unwrapped', self.env)

    def __getattr__(self, name):
        # Only reached for attributes not found on the wrapper itself.
        if name == 'env':
            raise AttributeError(name)
        return getattr(self.env, name)


def select_tree(pred, on_true, on_false):
    """Per-leaf where() of two pytrees of the same structure, for a scalar predicate (one env;
    vmapped outside): how a step picks between a continuing and a fresh episode without branching."""
    return jax.tree.map(lambda a, b: jnp.where(pred, a, b), on_true, on_false)


class AutoResetWrapper(Wrapper):
    """Starts a new episode in the same step that ends one.

    The returned state after a terminal/truncated step holds the *fresh* episode's obs, inner state,
    step counter and running return, while reward, done, metrics and info['truncation'] still describe
    the finished step (what the learner stores). info['final_obs'] is the pre-reset observation of the
    step (equal to obs when not done), for bootstrapping truncated episodes. info['rng'] is this env's
    own reset key, split at every step so resets are independent and reproducible.

    Cost: reset() is evaluated at every step and selected with where() (vmapped envs cannot branch
    per env); envs should keep reset cheap relative to step.
    """

    def reset(self, rng):
        rng, sub = jax.random.split(rng)
        state = self.env.reset(sub)
        info = dict(state.info)
        info['rng'] = rng
        info['final_obs'] = state.obs
        return state.replace(info=info)

    def step(self, state, action):
        rng, reset_key = jax.random.split(state.info['rng'])
        stepped = self.env.step(state, action)
        fresh = self.env.reset(reset_key)
        done = stepped.done > 0.5
        obs = select_tree(done, fresh.obs, stepped.obs)
        inner = select_tree(done, fresh.inner, stepped.inner)
        info = dict(stepped.info)
        # Per-episode accumulators restart with the new episode; everything else (truncation, and
        # any env-specific info) describes the step just taken.
        for k in ('steps', 'episode_return'):
            info[k] = jnp.where(done, fresh.info[k], stepped.info[k])
        info['rng'] = rng
        info['final_obs'] = stepped.obs
        return stepped.replace(obs=obs, inner=inner, info=info)

    def final_obs(self, state):
        """The pre-reset observation of the step that produced `state` (learners call this rather
        than reading info, so envs that reset themselves can render it only when needed)."""
        return state.info['final_obs']
