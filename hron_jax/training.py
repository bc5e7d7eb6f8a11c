"""Training runs: config, one jitted program per run (seeds vmapped, envs sharded), checkpoints, logs.

Role: everything behind ``train.py`` (which only calls `main`). A run is a directory::

    RUN_DIR/config.json        TrainConfig (checked on --resume) + informational 'meta'
    RUN_DIR/checkpoints/<U>/   orbax checkpoint of the full RunnerState after U updates
    RUN_DIR/metrics.jsonl      one row per update chunk (mean / std over seeds, per-seed lists)
    RUN_DIR/metrics.csv        the same rows, mean and std columns only
    RUN_DIR/tb/                TensorBoard events (x axis: env steps per seed)
    RUN_DIR/learning_curve.png SR (and return) vs env steps, mean +- std over seeds

Program (`Programs`, built once per program-relevant config and cached in-process):
    init(keys u32[S, 2]) -> RunnerState with a leading seed axis S on every leaf
    chunk(runner, n: static) -> (runner, metrics {name: f32[S, n]})
S = num_seeds seeds train in one program (jax.vmap of hron_jax.ppo over the RunnerState; with
S = 1 the unvmapped PPO runs and the axis is added outside, which keeps PPO's lax.cond on
truncation a real branch). Seed i uses jax.random.PRNGKey(seed + i), so seed i of a
multi-seed run is the single-seed run with --seed seed+i.
Env state leaves are [S, num_envs, ...] and sharded over a 1-D mesh of all local devices
(axis 'devices', NamedSharding P(None, 'devices')); params, optimiser state and rng are replicated.
num_envs must be divisible by the device count.

Determinism and resuming: chunk boundaries are always multiples of `log_every` updates (counted
from 0) or the end of training, checkpoints are only written at chunk boundaries, and a restored
RunnerState holds everything the next update reads (params, optimiser, env states, rng, update
counter). So an interrupted run that resumes issues the same sequence of compiled calls on the same
state as an uninterrupted one and ends with bitwise the same parameters. Fields of TrainConfig that
change the computation must match on resume; `RESUMABLE` ones may change (e.g. total steps, to
extend a run, as long as the learning rate is not annealed over it). The device count may change
too (orbax reshards the env states), but then results agree only up to the order of float
reductions (measured: sharded vs unsharded params differ by ~1e-7 after 8 updates; chaotic
training amplifies that to ~5e-4 after 300).
Checkpoints hold zero-size leaves (mjx.Data has some) as 1-element placeholders, as orbax refuses
empty arrays. Persistent XLA cache: on by default (`setup_compile_cache`), so a resumed run skips
most compiling (the navigation programs currently miss it across processes: their MLIR bytecode
differs though the printed module is identical, so they compile again).
"""
from __future__ import annotations

import argparse
import contextlib
import csv
import dataclasses
import functools
import json
import math
import os
import signal
import sys
import time
from pathlib import Path
from typing import Any, Callable, NamedTuple

import numpy as np

from hron_jax.envs import DEFAULT_SCENES, TASKS
from hron_jax.models.config import VARIANTS, ModelConfig
from hron_jax.ppo import EPISODE_METRICS, PPOConfig

# ------------------------------------------------------------------------------------------------
# Defaults per task (the one place they live).
#
# The paper (RLlib PPO, 8 envs, ~1.5 M steps): rollout 4096 steps, minibatch 128, 30 epochs,
# lr 1e-4, gamma 0.99, GAE lambda 0.9. We keep its rollout size (num_envs x num_steps = 64 x 64 =
# 4096 at the default --num-envs 64), minibatch size (32 minibatches -> 128), gamma, lambda and the
# 1.5 M steps, but run 4 epochs with lr 2.5e-4. Why: the update dominates training on CPU. Measured
# with `python -m hron_jax.bench train` (exploratory, rgbd_sg_attn, 2 shared EPYC cores): with 4
# epochs the update is already ~90 % of the time (each epoch costs ~2.3x the rollout: env step +
# policy forward), so 30 epochs would cut train steps/s ~7x, while with 64 parallel envs fresh,
# less correlated data is cheap; 4 epochs with a larger step is the usual trade (PureJaxRL / Brax
# defaults) and keeps approx_kl moderate. num_steps = 64 with 500-step episodes: GAE bootstraps
# across rollout ends from the value, which lambda = 0.9 discounts anyway ((0.99*0.9)^64 ~ 6e-4).
# The choice task is a one-step bandit: rollouts of 4 steps are 4 independent episodes per env,
# gamma / lambda do not matter; with these defaults the main model reaches SR 1.0 (no distractors)
# within ~10 k steps (measured: 0.51 / 0.81 / 0.91 / 1.0 after 2.6 / 5.1 / 7.7 / 10.2 k steps).
_NAV_PPO = PPOConfig(num_envs=64, num_steps=64, total_timesteps=1_500_000, update_epochs=4,
                     num_minibatches=32, lr=2.5e-4, gamma=0.99, gae_lambda=0.9, clip_eps=0.2,
                     ent_coef=0.01, vf_coef=0.5, max_grad_norm=0.5)
TASK_DEFAULTS: dict[str, dict] = {
    # log_every: updates per jitted chunk (one progress / log row each); checkpoint_every: updates.
    'choice': dict(ppo=PPOConfig(num_envs=64, num_steps=4, total_timesteps=200_000, update_epochs=4,
                                 num_minibatches=4, lr=3e-4, gamma=0.99, gae_lambda=0.9,
                                 ent_coef=0.01),
                   log_every=10, checkpoint_every=200),
    'directed': dict(ppo=_NAV_PPO, log_every=1, checkpoint_every=20),
    'exploratory': dict(ppo=_NAV_PPO, log_every=1, checkpoint_every=20),
}
DEFAULT_TASK = 'exploratory'
DEFAULT_MODEL = 'rgbd_sg_attn'
MODELS = tuple(VARIANTS)
_GRAPH_FREE = ('rgbd', 'rgbd_mm')


REPO_ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _portable_path(path: str) -> str:
    """`path` relative to the repository root when it lies inside it, else absolute."""
    path = os.path.abspath(os.path.join(REPO_ROOT, path))
    rel = os.path.relpath(path, REPO_ROOT)
    return path if rel.startswith(os.pardir) else rel


class UsageError(Exception):
    """Bad user input (CLI, config): reported as one line, exit code 2."""


class CheckpointError(Exception):
    """A checkpoint that cannot be restored: reported as one line naming the path, exit code 1."""


@dataclasses.dataclass(frozen=True)
class TrainConfig:
    """Everything that defines a run (hashable; JSON via to_dict / from_dict).

    env_options / model_options: sorted (name, value) pairs of extra NavConfig / ChoiceConfig
    (plus `image_size`) and ModelConfig fields; distractors / premap have their own fields.
    """
    task: str = DEFAULT_TASK
    model: str = DEFAULT_MODEL
    scene: str | None = None          # repo-relative when inside the repo (see scene_path); None: choice
    distractors: bool = False
    premap: bool = False
    env_options: tuple = ()
    model_options: tuple = ()
    ppo: PPOConfig = TASK_DEFAULTS[DEFAULT_TASK]['ppo']
    seed: int = 0
    num_seeds: int = 1
    log_every: int = 1                # updates per jitted chunk
    checkpoint_every: int = 20        # updates
    keep_checkpoints: int = 3
    fast_compile: bool = False        # FAST_COMPILE XLA options (tests, debugging)

    def __post_init__(self):
        if self.scene is not None:  # run dirs stay valid when the repository moves
            object.__setattr__(self, 'scene', _portable_path(self.scene))
        if self.task not in TASKS:
            raise UsageError(f'unknown task {self.task!r}; valid: {", ".join(TASKS)}')
        if self.model not in MODELS:
            raise UsageError(f'unknown model {self.model!r}; valid: {", ".join(MODELS)}')
        if self.task == 'choice':
            if self.scene is not None:
                raise UsageError('the choice task has no scene (drop --scene)')
            if self.premap:
                raise UsageError('--premap applies to the navigation tasks only')
            if self.model == 'rgbd_mm':
                raise UsageError('the choice task has no metric map: use another --model')
        for name in ('num_seeds', 'log_every', 'checkpoint_every', 'keep_checkpoints'):
            if getattr(self, name) < 1:
                raise UsageError(f'{name} must be >= 1, got {getattr(self, name)}')

    @property
    def scene_path(self) -> str | None:
        """Absolute path of the scene file (relative ones are relative to the repository root)."""
        return None if self.scene is None else os.path.join(REPO_ROOT, self.scene)

    @property
    def num_updates(self) -> int:
        return self.ppo.num_updates

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d['env_options'] = [list(kv) for kv in self.env_options]
        d['model_options'] = [list(kv) for kv in self.model_options]
        return d

    @classmethod
    def from_dict(cls, d: dict) -> 'TrainConfig':
        d = dict(d)
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(d) - names)
        if unknown:
            raise UsageError(f'config has unknown field(s) {unknown}')
        ppo = dict(d.pop('ppo', {}))
        ppo_names = {f.name for f in dataclasses.fields(PPOConfig)}
        if set(ppo) - ppo_names:
            raise UsageError(f'config has unknown ppo field(s) {sorted(set(ppo) - ppo_names)}')
        for k in ('env_options', 'model_options'):
            d[k] = tuple((n, _freeze(v)) for n, v in d.get(k, ()))
        try:
            return cls(ppo=PPOConfig(**ppo), **d)
        except ValueError as e:
            raise UsageError(str(e)) from None


def _freeze(v):
    return tuple(_freeze(x) for x in v) if isinstance(v, list) else v


# Fields that may differ between a run and its resumption (they do not change the computation).
RESUMABLE = ('checkpoint_every', 'keep_checkpoints', 'ppo.total_timesteps')


def config_diff(a: TrainConfig, b: TrainConfig) -> dict[str, tuple]:
    """{dotted field: (a's value, b's value)} where they differ."""
    fa, fb = _flat(a.to_dict()), _flat(b.to_dict())
    return {k: (fa.get(k), fb.get(k)) for k in sorted(set(fa) | set(fb)) if fa.get(k) != fb.get(k)}


def _flat(d: dict, prefix='') -> dict:
    out = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(_flat(v, f'{prefix}{k}.'))
        else:
            out[prefix + k] = v
    return out


# ------------------------------------------------------------------------------------------------
# Env + model from a config
# ------------------------------------------------------------------------------------------------

def model_config(config: TrainConfig) -> ModelConfig:
    opts = dict(config.model_options)
    if config.task == 'choice' and config.model not in _GRAPH_FREE:
        # The choice task is symbolic (the paper's SG models see only the graph); images are
        # rendered only for a model that asks for them with use_rgbd=True.
        opts.setdefault('use_rgbd', False)
    return ModelConfig(**opts)


def env_kwargs(config: TrainConfig) -> dict:
    """make_env(task, scene, **env_kwargs(config)) as training builds it."""
    opts = dict(config.env_options)
    opts['distractors'] = config.distractors
    if config.task == 'choice':
        opts['image_obs'] = model_config(config).use_rgbd
    else:
        opts['premap'] = config.premap
        opts['metric_map'] = VARIANTS[config.model].get('use_map', False)
    return opts


def build_env(config: TrainConfig, **overrides):
    from hron_jax.envs import make_env
    return make_env(config.task, config.scene_path, **dict(env_kwargs(config), **overrides))


def build_network(config: TrainConfig, num_actions: int):
    from hron_jax.models import make_model
    return make_model(config.model, num_actions, model_config(config))


# ------------------------------------------------------------------------------------------------
# The jitted program
# ------------------------------------------------------------------------------------------------

class Programs(NamedTuple):
    env: Any
    network: Any
    ppo: Any
    mesh: Any
    init: Callable          # jitted: keys u32[S, 2] -> RunnerState [S, ...]
    chunk: Callable         # jitted: (runner, n static) -> (runner, metrics f32[S, n])
    abstract: Any           # RunnerState of ShapeDtypeStruct with shardings
    shardings: Any          # RunnerState of NamedSharding
    compiler_options: dict  # XLA options of every compile (FAST_COMPILE or none)
    compiled: dict          # 'init' / n -> AOT-compiled executable (shared by every Trainer)

    def initialize(self, keys):
        """init(keys), compiled with compiler_options."""
        if 'init' not in self.compiled:
            self.compiled['init'] = self.init.lower(keys).compile(self.compiler_options)
        return self.compiled['init'](keys)

    def compiled_chunk(self, n: int):
        """(executable runner -> (runner, metrics), seconds spent compiling it now)."""
        if n in self.compiled:
            return self.compiled[n], 0.0
        t = time.perf_counter()
        self.compiled[n] = self.chunk.lower(self.abstract, n).compile(self.compiler_options)
        return self.compiled[n], time.perf_counter() - t


# XLA:CPU options of --fast-compile: no LLVM optimisation. Measured on the choice task: compiles
# ~3x faster (tiny model: 21 -> 5.5 s), runs ~2.7x slower at default model sizes. For tests and
# debugging; float rounding differs, so it is part of the config (resume checks it).
FAST_COMPILE = {'xla_backend_optimization_level': 0, 'xla_llvm_disable_expensive_passes': True}


def make_mesh(num_envs: int):
    """1-D mesh over all local devices; env batches are split over its 'devices' axis."""
    import jax
    devices = jax.local_devices()
    if num_envs % len(devices):
        raise UsageError(f'--num-envs {num_envs} is not divisible by the {len(devices)} local devices '
                         f'({devices[0].platform}); use a multiple of {len(devices)}')
    return jax.sharding.Mesh(np.asarray(devices), ('devices',))


def seed_keys(config: TrainConfig):
    import jax
    import jax.numpy as jnp
    return jnp.stack([jax.random.PRNGKey(config.seed + i) for i in range(config.num_seeds)])


def _program_key(config: TrainConfig) -> TrainConfig:
    """The config with fields that do not change the compiled program normalised (cache key)."""
    ppo = config.ppo
    total = ppo.total_timesteps if ppo.anneal_lr else ppo.batch_size
    return dataclasses.replace(config, seed=0, checkpoint_every=1, keep_checkpoints=1,
                               log_every=1, ppo=dataclasses.replace(ppo, total_timesteps=total, seed=0))


def programs(config: TrainConfig) -> Programs:
    import jax
    return _programs(_program_key(config), tuple(jax.local_devices()))


@functools.lru_cache(maxsize=4)
def _programs(config: TrainConfig, devices: tuple) -> Programs:
    import jax
    from jax.sharding import NamedSharding, PartitionSpec as P
    from hron_jax.ppo import make_ppo

    del devices  # part of the cache key only
    mesh = make_mesh(config.ppo.num_envs)
    try:
        env = build_env(config)
        network = build_network(config, env.num_actions)
    except (ValueError, TypeError, OSError) as e:   # scene file, env or model option rejected
        raise UsageError(f'cannot build the {config.task} env / {config.model} model: {e}') from None
    ppo = make_ppo(config.ppo, env, network)
    add = functools.partial(jax.tree.map, lambda x: x[None])
    drop = functools.partial(jax.tree.map, lambda x: x[0])

    if config.num_seeds == 1:
        def init(keys):
            return add(ppo.init(keys[0]))

        def chunk(runner, n):
            return add(ppo.update_chunk(drop(runner), n))
    else:
        init = jax.vmap(ppo.init)

        def chunk(runner, n):
            return jax.vmap(lambda r: ppo.update_chunk(r, n))(runner)

    abstract = jax.eval_shape(init, jax.ShapeDtypeStruct((config.num_seeds, 2), np.uint32))
    replicated = NamedSharding(mesh, P())
    env_sharded = NamedSharding(mesh, P(None, 'devices'))
    shardings = abstract.replace(
        params=jax.tree.map(lambda _: replicated, abstract.params),
        opt_state=jax.tree.map(lambda _: replicated, abstract.opt_state),
        env_state=jax.tree.map(lambda _: env_sharded, abstract.env_state),
        rng=replicated, update=replicated)
    abstract = jax.tree.map(lambda a, s: jax.ShapeDtypeStruct(a.shape, a.dtype, sharding=s),
                            abstract, shardings)
    return Programs(env=env, network=network, ppo=ppo, mesh=mesh,
                    init=jax.jit(init, out_shardings=shardings),
                    chunk=jax.jit(chunk, static_argnums=1, out_shardings=(shardings, replicated)),
                    abstract=abstract, shardings=shardings,
                    compiler_options=dict(FAST_COMPILE) if config.fast_compile else {}, compiled={})


# ------------------------------------------------------------------------------------------------
# Checkpoints
# ------------------------------------------------------------------------------------------------

def _manager(run_dir: Path, keep: int = 3, create: bool = True):
    import orbax.checkpoint as ocp
    return ocp.CheckpointManager(
        (run_dir / 'checkpoints').resolve(), item_handlers=ocp.StandardCheckpointHandler(),
        options=ocp.CheckpointManagerOptions(max_to_keep=keep, create=create))


# orbax refuses zero-size arrays, and mjx.Data has some (e.g. `act` of a model without
# actuator activations): they are stored as a 1-element placeholder and rebuilt from the abstract.
def _is_empty(x) -> bool:
    return int(np.prod(x.shape)) == 0


def _storable(tree):
    """The tree as saved: zero-size leaves replaced by a 1-element placeholder."""
    import jax
    import jax.numpy as jnp
    return jax.tree.map(lambda x: jnp.zeros((1,), x.dtype) if _is_empty(x) else x, tree)


def _storable_abstract(abstract):
    import jax
    from jax.sharding import NamedSharding, PartitionSpec as P

    def f(a):
        if not _is_empty(a):
            return a
        sharding = a.sharding
        if isinstance(sharding, NamedSharding):
            sharding = NamedSharding(sharding.mesh, P())
        return jax.ShapeDtypeStruct((1,), a.dtype, sharding=sharding)
    return jax.tree.map(f, abstract)


def _from_storable(abstract, restored):
    import jax
    import jax.numpy as jnp
    return jax.tree.map(
        lambda a, r: jnp.zeros(a.shape, a.dtype, device=a.sharding) if _is_empty(a) else r,
        abstract, restored)


def _leaf_name(path) -> str:
    """A key path as orbax names checkpoint entries ('env_state.info.steps')."""
    parts = []
    for k in path:
        for attr in ('key', 'name', 'idx'):
            if hasattr(k, attr):
                parts.append(str(getattr(k, attr)))
                break
    return '.'.join(parts)


def _check_metadata(manager, step: int, abstract, path: Path, partial: bool = False) -> None:
    """Compare the stored arrays (names, shapes, dtypes) with what this config builds (with
    `partial`, only those in `abstract`, e.g. {'params': ...})."""
    import jax
    try:
        stored = {m.name: m for m in jax.tree.leaves(manager.item_metadata(step))}
        if not stored:
            raise ValueError('no arrays listed')
    except Exception as e:  # unreadable metadata: the checkpoint is damaged
        raise CheckpointError(
            f'{path}: unreadable checkpoint metadata ({type(e).__name__}: {str(e)[:200]}); delete '
            'this step directory to resume from the previous checkpoint, or start a new run') from None
    want = {_leaf_name(p): a for p, a in jax.tree_util.tree_flatten_with_path(abstract)[0]}
    if partial:
        roots = {n.split('.')[0] for n in want}
        stored = {n: m for n, m in stored.items() if n.split('.')[0] in roots}
    problems = []
    for name in sorted(set(want) | set(stored)):
        if name not in stored:
            problems.append(f'{name} missing')
        elif name not in want:
            problems.append(f'{name} unexpected')
        else:
            a, b = want[name], stored[name]
            if tuple(a.shape) != tuple(b.shape) or np.dtype(a.dtype) != np.dtype(b.dtype):
                problems.append(f'{name} stored {tuple(b.shape)} {b.dtype}, expected '
                                f'{tuple(a.shape)} {a.dtype}')
    if problems:
        more = f' (+{len(problems) - 3} more)' if len(problems) > 3 else ''
        raise CheckpointError(
            f'{path}: checkpoint does not match this run\'s config: {"; ".join(problems[:3])}{more}. '
            'It was written by a different config or code version: restore config.json / the code, '
            'or start a new run with another --out')


def _checkpoint_step(run_dir: Path, step: int | None):
    """(manager, step): the latest (or the given) checkpoint step of a run; CheckpointError if none."""
    manager = _manager(run_dir, create=False) if (run_dir / 'checkpoints').is_dir() else None
    steps = manager.all_steps() if manager is not None else []
    if not steps:
        raise CheckpointError(f'{run_dir / "checkpoints"}: no checkpoint found; start a new run '
                              '(train.py without --resume)')
    step = max(steps) if step is None else step
    if step not in steps:
        raise CheckpointError(f'{run_dir / "checkpoints"}: no checkpoint for step {step}; '
                              f'available: {sorted(steps)}')
    return manager, step


@contextlib.contextmanager
def _restoring(manager, path: Path):
    """Closes `manager`; any failure inside, other than a CheckpointError, becomes a
    CheckpointError that names `path` and what to do."""
    try:
        yield
    except CheckpointError:
        raise
    except Exception as e:
        raise CheckpointError(
            f'{path}: cannot restore the checkpoint ({type(e).__name__}: {str(e)[:300]}); delete '
            'this step directory to resume from the previous checkpoint, or start a new run') from None
    finally:
        manager.close()


def restore_runner(run_dir: Path, abstract, step: int | None = None):
    """(RunnerState restored onto `abstract`'s shardings, its step). Raises CheckpointError."""
    import orbax.checkpoint as ocp
    run_dir = Path(run_dir)
    manager, step = _checkpoint_step(run_dir, step)
    path = run_dir / 'checkpoints' / str(step)
    stored = _storable_abstract(abstract)
    with _restoring(manager, path):
        _check_metadata(manager, step, stored, path)
        runner = manager.restore(step, args=ocp.args.StandardRestore(stored))
    return _from_storable(abstract, runner), step


def restore_params(run_dir, config: TrainConfig, env, network, step: int | None = None):
    """(params with a leading seed axis [S, ...] as numpy, step) of a run's checkpoint: only the
    parameters are read, so `env` may be built differently from training (e.g. no auto-reset)."""
    import jax
    import orbax.checkpoint as ocp
    run_dir = Path(run_dir).resolve()     # orbax restores from absolute paths only
    manager, step = _checkpoint_step(run_dir, step)
    path = run_dir / 'checkpoints' / str(step)
    obs = jax.eval_shape(env.reset, jax.random.PRNGKey(0)).obs
    one = jax.eval_shape(network.init, jax.random.PRNGKey(0), obs)
    item = {'params': jax.tree.map(
        lambda a: jax.ShapeDtypeStruct((config.num_seeds,) + a.shape, a.dtype), one)}
    with _restoring(manager, path):
        _check_metadata(manager, step, item, path, partial=True)
        out = ocp.PyTreeCheckpointer().restore(path / 'default', args=ocp.args.PyTreeRestore(
            item=item, restore_args=ocp.checkpoint_utils.construct_restore_args(item),
            partial_restore=True))
    return out['params'], step


def load_config(run_dir: Path) -> TrainConfig:
    path = Path(run_dir) / 'config.json'
    if not path.is_file():
        raise UsageError(f'{run_dir}: not a run directory (no config.json)')
    try:
        with open(path) as f:
            d = json.load(f)
    except (OSError, json.JSONDecodeError) as e:
        raise UsageError(f'{path}: unreadable ({e})') from None
    return TrainConfig.from_dict(d['config'] if 'config' in d else d)


def _write_json(path: Path, obj) -> None:
    tmp = path.with_suffix(path.suffix + '.tmp')
    with open(tmp, 'w') as f:
        json.dump(obj, f, indent=2)
        f.write('\n')
    os.replace(tmp, path)


def save_config(run_dir: Path, config: TrainConfig) -> None:
    import jax
    meta = dict(jax=jax.__version__, devices=[str(d) for d in jax.local_devices()],
                argv=sys.argv, time=time.strftime('%Y-%m-%d %H:%M:%S'))
    _write_json(Path(run_dir) / 'config.json', dict(config=config.to_dict(), meta=meta))


# ------------------------------------------------------------------------------------------------
# Metrics: per-chunk summaries, jsonl / csv / TensorBoard, learning curve
# ------------------------------------------------------------------------------------------------

def summarize_chunk(metrics: dict) -> dict[str, np.ndarray]:
    """{name: f32[S]} from one chunk's PPO metrics {name: [S, n]}: episode metrics averaged over
    the episodes completed in the chunk (NaN if none), 'episodes' summed, 'env_steps' the last
    value, everything else (losses, reward) the mean over updates."""
    m = {k: np.asarray(v, np.float64) for k, v in metrics.items()}
    ep = m['episodes']
    count = ep.sum(-1)
    out = {}
    for k, v in m.items():
        if k in EPISODE_METRICS:
            s = np.where(ep > 0, v, 0.0) * ep
            out[k] = np.where(count > 0, s.sum(-1) / np.maximum(count, 1), np.nan)
        elif k == 'episodes':
            out[k] = count
        elif k == 'env_steps':
            out[k] = v[:, -1]
        else:
            out[k] = v.mean(-1)
    return out


def _num(x):
    x = float(x)
    return None if not math.isfinite(x) else x


def _nan_stats(v: np.ndarray):
    v = np.asarray(v, np.float64)
    ok = np.isfinite(v)
    if not ok.any():
        return None, None
    return float(v[ok].mean()), float(v[ok].std())


class MetricsLog:
    """metrics.jsonl (source of truth), metrics.csv and TensorBoard, resumable at an update."""

    def __init__(self, run_dir: Path, resume_update: int | None, tensorboard: bool = True):
        self.run_dir = Path(run_dir)
        self.jsonl = self.run_dir / 'metrics.jsonl'
        self.csv = self.run_dir / 'metrics.csv'
        self.rows: list[dict] = []
        if resume_update is not None and self.jsonl.exists():
            # Rows written after the checkpoint we resume from are replayed: drop them.
            with open(self.jsonl) as f:
                for line in f:
                    line = line.strip()
                    if line:
                        try:
                            row = json.loads(line)
                        except json.JSONDecodeError:   # a line cut by a hard kill
                            continue
                        if row['update'] <= resume_update:
                            self.rows.append(row)
        with open(self.jsonl, 'w') as f:
            for row in self.rows:
                f.write(json.dumps(row) + '\n')
        self._rewrite_csv()
        self.tb = None
        if tensorboard:
            from tensorboardX import SummaryWriter
            purge = None
            if resume_update is not None:
                purge = (self.rows[-1]['env_steps'] + 1) if self.rows else 0
            self.tb = SummaryWriter(str(self.run_dir / 'tb'), purge_step=purge)

    @property
    def wall_time(self) -> float:
        return self.rows[-1]['wall_time'] if self.rows else 0.0

    def _columns(self) -> list[str]:
        keys = []
        for row in self.rows:
            for k in row:
                if k != 'per_seed' and k not in keys:
                    keys.append(k)
        return keys

    def _rewrite_csv(self) -> None:
        cols = self._columns()
        with open(self.csv, 'w', newline='') as f:
            w = csv.writer(f)
            w.writerow(cols)
            for row in self.rows:
                w.writerow(['' if row.get(k) is None else row.get(k) for k in cols])

    def append(self, update: int, summary: dict[str, np.ndarray], wall_time: float,
               steps_per_s: float) -> dict:
        row = {'update': int(update), 'env_steps': int(summary['env_steps'][0]),
               'wall_time': round(wall_time, 3), 'steps_per_s': round(steps_per_s, 1),
               'seeds': int(len(summary['env_steps']))}
        for k in sorted(summary):
            if k == 'env_steps':
                continue
            mean, std = _nan_stats(summary[k])
            row[k], row[k + '_std'] = mean, std
        row['per_seed'] = {k: [_num(x) for x in v] for k, v in sorted(summary.items())
                           if k != 'env_steps'}
        new_cols = any(k not in self._columns() for k in row if k != 'per_seed')
        self.rows.append(row)
        with open(self.jsonl, 'a') as f:
            f.write(json.dumps(row) + '\n')
        if new_cols:
            self._rewrite_csv()
        else:
            with open(self.csv, 'a', newline='') as f:
                csv.writer(f).writerow(['' if row.get(k) is None else row.get(k)
                                        for k in self._columns()])
        if self.tb is not None:
            step = row['env_steps']
            for k, v in summary.items():
                if k == 'env_steps':
                    continue
                if row[k] is not None:
                    self.tb.add_scalar(f'train/{k}', row[k], step)
                if len(v) > 1:
                    for i, x in enumerate(v):
                        if math.isfinite(x):
                            self.tb.add_scalar(f'seed{i}/{k}', float(x), step)
            self.tb.add_scalar('perf/steps_per_s', steps_per_s, step)
        return row

    def flush(self) -> None:
        if self.tb is not None:
            self.tb.flush()

    def close(self) -> None:
        if self.tb is not None:
            self.tb.close()
            self.tb = None


def read_metrics(run_dir) -> list[dict]:
    rows = []
    path = Path(run_dir) / 'metrics.jsonl'
    if path.exists():
        with open(path) as f:
            for line in f:
                try:
                    rows.append(json.loads(line))
                except json.JSONDecodeError:
                    pass
    return rows


def run_label(config: TrainConfig) -> str:
    names = {'rgbd': 'RGB-D only', 'rgbd_mm': 'RGB-D + MM', 'rgbd_sg': 'RGB-D + SG',
             'rgbd_sg_attn': 'RGB-D + SG + TD ATTN', 'gcn': 'Kipf et al. (GCN)', 'yang': 'Yang et al.'}
    label = names.get(config.model, config.model)
    if config.task == 'choice' and config.model not in _GRAPH_FREE and not model_config(config).use_rgbd:
        label = label.replace('RGB-D + ', '')
    if config.premap:
        label = 'PM: ' + label
    return label


def plot_learning_curves(runs: dict[str, list[dict]], path, title: str = '') -> None:
    """SR and return vs env steps (per seed), mean +- std over seeds, one line per run label."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(9, 3.4))
    for label, rows in runs.items():
        x = np.asarray([r['env_steps'] for r in rows], np.float64)
        for ax, key in zip(axes, ('success', 'return')):
            mean = np.asarray([np.nan if r.get(key) is None else r[key] for r in rows])
            std = np.asarray([np.nan if r.get(key + '_std') is None else r[key + '_std'] for r in rows])
            ok = np.isfinite(mean)
            if not ok.any():
                continue
            line, = ax.plot(x[ok], mean[ok], lw=1.5, label=label)
            s = np.nan_to_num(std[ok])
            ax.fill_between(x[ok], mean[ok] - s, mean[ok] + s, color=line.get_color(), alpha=0.2, lw=0)
    axes[0].set_ylabel('success rate (SR)')
    axes[0].set_ylim(-0.02, 1.02)
    axes[1].set_ylabel('episode return')
    for ax in axes:
        ax.set_xlabel('environment steps')
        ax.grid(alpha=0.3)
        ax.ticklabel_format(axis='x', style='sci', scilimits=(0, 3))
    if axes[0].get_legend_handles_labels()[0]:
        axes[0].legend(fontsize=7, loc='lower right')
    if title:
        fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    tmp = Path(str(path) + '.tmp.png')
    fig.savefig(tmp, dpi=110)
    plt.close(fig)
    os.replace(tmp, path)


# ------------------------------------------------------------------------------------------------
# Trainer
# ------------------------------------------------------------------------------------------------

class Trainer:
    """One run: init or restore, then chunks of updates with logging and checkpoints.

    Trainer(config, run_dir, resume=False) creates run_dir (must not hold a run yet) and saves
    config.json and the initial state; resume=True restores the latest checkpoint of run_dir
    (config must equal its config.json up to RESUMABLE fields; `load_config` gives it).
    run(max_updates=None, should_stop=None) trains until config.num_updates (or max_updates more
    updates, or should_stop() is true after a chunk), then checkpoints; returns the RunnerState.
    """

    def __init__(self, config: TrainConfig, run_dir, *, resume: bool = False, progress: bool = True,
                 tensorboard: bool = True, log: Callable[[str], None] | None = None):
        import jax
        self.config = config
        self.run_dir = Path(run_dir)
        self.progress = progress
        self._log = log or (lambda s: print(s, flush=True))
        if resume:
            saved = load_config(self.run_dir)
            diff = {k: v for k, v in config_diff(saved, config).items() if k not in RESUMABLE}
            if diff:
                raise UsageError(f'{self.run_dir / "config.json"} differs from the requested config in '
                                 + ', '.join(f'{k} (saved {a!r}, given {b!r})' for k, (a, b) in diff.items()))
            if config.ppo.anneal_lr and config.ppo.total_timesteps != saved.ppo.total_timesteps:
                raise UsageError('total steps cannot change on resume when the learning rate is '
                                 'annealed over them (--anneal-lr)')
        elif (self.run_dir / 'config.json').exists():
            raise UsageError(f'{self.run_dir} already holds a run; continue it with --resume '
                             f'{self.run_dir} or choose another --out')
        self.programs = programs(config)
        t = time.perf_counter()
        if resume:
            self.runner, step = restore_runner(self.run_dir, self.programs.abstract)
            self._log(f'resumed {self.run_dir} at update {step} / {config.num_updates}')
            save_config(self.run_dir, config)   # RESUMABLE fields may have changed
        else:
            self.run_dir.mkdir(parents=True, exist_ok=True)
            save_config(self.run_dir, config)
            self.runner = self.programs.initialize(seed_keys(config))
            step = 0
        self.update = int(jax.device_get(self.runner.update[0]))
        assert self.update == step
        self.manager = _manager(self.run_dir, keep=config.keep_checkpoints)
        if not resume:
            self._save()
        self.metrics = MetricsLog(self.run_dir, step if resume else None, tensorboard)
        self._log(f'init: {time.perf_counter() - t:.1f} s; {config.num_seeds} seed(s) x '
                  f'{config.ppo.num_envs} envs on {len(self.programs.mesh.devices)} device(s)')

    # -- checkpoints ----------------------------------------------------------------------------
    def _save(self) -> None:
        import orbax.checkpoint as ocp
        if self.update in self.manager.all_steps():
            return
        self.manager.save(self.update, args=ocp.args.StandardSave(_storable(self.runner)))
        self.manager.wait_until_finished()

    def checkpoint(self) -> None:
        """Save the current state (if not saved yet) and redraw the learning curve."""
        self._save()
        self.metrics.flush()
        if self.metrics.rows:
            c = self.config
            title = (f'{c.task}{" + distractors" if c.distractors else ""}: {run_label(c)}, '
                     f'{c.num_seeds} seed(s)')
            plot_learning_curves({run_label(c): self.metrics.rows},
                                 self.run_dir / 'learning_curve.png', title)

    # -- training -------------------------------------------------------------------------------
    def run(self, max_updates: int | None = None, should_stop: Callable[[], bool] | None = None):
        import jax
        c = self.config
        total = c.num_updates
        stop_at = total if max_updates is None else min(total, self.update + max_updates)
        steps_per_update = c.ppo.batch_size * c.num_seeds
        # Compile every chunk length this call will use before the clock starts (at most three:
        # a partial first chunk after a resume, full chunks, a partial last one).
        u, sizes = self.update, set()
        while u < stop_at:
            n = min(c.log_every - u % c.log_every, stop_at - u)
            sizes.add(n)
            u += n
        for n in sorted(sizes):
            _, dt = self.programs.compiled_chunk(n)
            if dt > 1.0:
                self._log(f'compiled the {n}-update chunk in {dt:.1f} s')
        from tqdm import tqdm
        bar = tqdm(total=total * steps_per_update, initial=self.update * steps_per_update,
                   unit='step', unit_scale=True, dynamic_ncols=True, disable=not self.progress,
                   file=sys.stderr, mininterval=0.5, smoothing=0.1)
        last_ckpt = self.update
        wall0 = self.metrics.wall_time
        t_run = time.perf_counter()
        try:
            while self.update < stop_at and not (should_stop and should_stop()):
                n = min(c.log_every - self.update % c.log_every, stop_at - self.update)
                fn, _ = self.programs.compiled_chunk(n)
                t = time.perf_counter()
                runner, metrics = fn(self.runner)
                metrics = jax.device_get(metrics)
                dt = time.perf_counter() - t
                # Only now (chunk complete) does the state advance, so a checkpoint written on
                # any exit is consistent.
                self.runner = runner
                self.update += n
                summary = summarize_chunk(metrics)
                row = self.metrics.append(self.update, summary, wall0 + time.perf_counter() - t_run,
                                          n * steps_per_update / dt)
                bar.update(n * steps_per_update)
                bar.set_postfix_str(_postfix(row, self.update, total), refresh=False)
                if self.update - last_ckpt >= c.checkpoint_every or self.update == total:
                    self.checkpoint()
                    last_ckpt = self.update
        except BaseException:
            bar.close()
            try:
                self.checkpoint()
            except Exception:   # keep the original error
                pass
            raise
        bar.close()
        self.checkpoint()
        return self.runner

    def close(self) -> None:
        self.manager.wait_until_finished()
        self.manager.close()
        self.metrics.close()


def _postfix(row: dict, update: int, total: int) -> str:
    def f(k, fmt):
        v = row.get(k)
        return '-' if v is None else format(v, fmt)
    return f'upd {update}/{total} SR {f("success", ".3f")} ret {f("return", ".2f")}'


# ------------------------------------------------------------------------------------------------
# CLI
# ------------------------------------------------------------------------------------------------

class _Parser(argparse.ArgumentParser):
    """argparse that reports errors as one line (exit 2), without the usage block."""

    def error(self, message):
        self.exit(2, f'{self.prog}: error: {message} (see --help)\n')


# CLI option -> TrainConfig field (dotted for PPOConfig fields).
_FIELD = {
    'task': 'task', 'model': 'model', 'scene': 'scene', 'distractors': 'distractors',
    'premap': 'premap', 'seed': 'seed', 'num_seeds': 'num_seeds', 'log_every': 'log_every',
    'checkpoint_every': 'checkpoint_every', 'keep_checkpoints': 'keep_checkpoints',
    'env_option': 'env_options', 'model_option': 'model_options', 'fast_compile': 'fast_compile',
    'num_envs': 'ppo.num_envs', 'total_steps': 'ppo.total_timesteps', 'num_steps': 'ppo.num_steps',
    'epochs': 'ppo.update_epochs', 'minibatches': 'ppo.num_minibatches', 'lr': 'ppo.lr',
    'anneal_lr': 'ppo.anneal_lr', 'gamma': 'ppo.gamma', 'gae_lambda': 'ppo.gae_lambda',
    'clip_eps': 'ppo.clip_eps', 'ent_coef': 'ppo.ent_coef', 'vf_coef': 'ppo.vf_coef',
    'max_grad_norm': 'ppo.max_grad_norm',
}


def _defaults_epilog() -> str:
    lines = ['per-task defaults (hron_jax.training.TASK_DEFAULTS; the paper: rollout 4096, minibatch '
             '128, 30 epochs, lr 1e-4, gamma 0.99, lambda 0.9):']
    for task, d in TASK_DEFAULTS.items():
        p = d['ppo']
        lines.append(f'  {task:12s} num-envs {p.num_envs}, num-steps {p.num_steps}, epochs '
                     f'{p.update_epochs}, minibatches {p.num_minibatches}, lr {p.lr:g}, gamma '
                     f'{p.gamma:g}, gae-lambda {p.gae_lambda:g}, ent-coef {p.ent_coef:g}, total-steps '
                     f'{p.total_timesteps:,}, log-every {d["log_every"]}, checkpoint-every '
                     f'{d["checkpoint_every"]}')
    return '\n'.join(lines)


def build_parser(prog: str = 'train.py') -> argparse.ArgumentParser:
    S = argparse.SUPPRESS   # unset options stay absent: task defaults or the resumed config apply
    p = _Parser(prog=prog, argument_default=S, description=(
        'Train a HRON policy with PPO (all seeds in one jitted program). Options left out take '
        'the per-task defaults of hron_jax.training.TASK_DEFAULTS, or on --resume the run\'s '
        'config.json.'), epilog=_defaults_epilog(), formatter_class=argparse.RawDescriptionHelpFormatter)
    g = p.add_argument_group('run')
    g.add_argument('--task', choices=TASKS, help=f'task (default {DEFAULT_TASK})')
    g.add_argument('--model', choices=MODELS, help=f'model variant (default {DEFAULT_MODEL})')
    g.add_argument('--scene', help='scene MJCF (default: scenes/symmetric_room.xml for directed, '
                                   'scenes/house.xml for exploratory)')
    g.add_argument('--distractors', action=argparse.BooleanOptionalAction,
                   help='add distractor objects (default off)')
    g.add_argument('--premap', action=argparse.BooleanOptionalAction,
                   help='pre-mapping: graph/map start with rooms + furniture (default off)')
    g.add_argument('--num-envs', type=int, help='parallel envs per seed (default 64)')
    g.add_argument('--total-steps', type=int, help='env steps per seed (default per task)')
    g.add_argument('--seed', type=int, help='seed of the first run (default 0)')
    g.add_argument('--num-seeds', type=int, help='seeds seed..seed+N-1 trained together (default 1)')
    g.add_argument('--out', help='run directory (default runs/<task>_<model>_..._<timestamp>)')
    g.add_argument('--resume', metavar='RUN_DIR', help='continue this run exactly where its last '
                   'checkpoint left off (other options must match its config.json)')
    g.add_argument('--log-every', type=int, help='updates per jitted chunk = per log row')
    g.add_argument('--checkpoint-every', type=int, help='updates between checkpoints')
    g.add_argument('--keep-checkpoints', type=int, help='checkpoints kept (default 3)')
    g.add_argument('--env-option', action='append', metavar='NAME=VALUE',
                   help='extra env field (NavConfig / ChoiceConfig, or image_size), repeatable')
    g.add_argument('--model-option', action='append', metavar='NAME=VALUE',
                   help='ModelConfig field, e.g. hidden=64 or cnn_fc=128,64,64; repeatable')
    g.add_argument('--no-progress', action='store_true', help='no progress bar')
    g.add_argument('--fast-compile', action=argparse.BooleanOptionalAction,
                   help='XLA without LLVM optimisation: ~3x faster compiles, ~2.7x slower steps '
                        '(tests, debugging)')
    g.add_argument('--compile-cache', metavar='DIR', help='persistent XLA compilation cache '
                   "(default ~/.cache/hron_jax/xla or $JAX_COMPILATION_CACHE_DIR; 'none' disables)")
    h = p.add_argument_group('PPO (defaults per task)')
    h.add_argument('--num-steps', type=int, help='rollout length per env per update')
    h.add_argument('--epochs', type=int, help='PPO epochs per update')
    h.add_argument('--minibatches', type=int, help='minibatches per epoch')
    h.add_argument('--lr', type=float, help='Adam learning rate')
    h.add_argument('--anneal-lr', action=argparse.BooleanOptionalAction, help='linear decay to 0')
    h.add_argument('--gamma', type=float)
    h.add_argument('--gae-lambda', type=float)
    h.add_argument('--clip-eps', type=float)
    h.add_argument('--ent-coef', type=float)
    h.add_argument('--vf-coef', type=float)
    h.add_argument('--max-grad-norm', type=float)
    return p


def _parse_value(text: str, default, what: str):
    """Parse NAME=VALUE's value in the type of the field's default."""
    try:
        if isinstance(default, bool):
            if text.lower() in ('1', 'true', 'yes', 'on'):
                return True
            if text.lower() in ('0', 'false', 'no', 'off'):
                return False
            raise ValueError
        if isinstance(default, int):
            return int(text)
        if isinstance(default, float):
            return float(text)
        if isinstance(default, tuple):
            item = type(default[0]) if default else float
            return tuple(item(x) for x in text.split(',') if x)
        if default is None or isinstance(default, str):
            return text
    except ValueError:
        pass
    raise UsageError(f'{what}: cannot parse {text!r} as {type(default).__name__}')


def _options(items: list[str], fields: dict, what: str, reserved: dict) -> tuple:
    out = {}
    for item in items or []:
        if '=' not in item:
            raise UsageError(f'{what} {item!r}: expected NAME=VALUE')
        name, text = item.split('=', 1)
        if name in reserved:
            raise UsageError(f'{what} {name}: use {reserved[name]} instead')
        if name not in fields:
            raise UsageError(f'{what} {name!r} unknown; valid: {", ".join(sorted(fields))}')
        out[name] = _parse_value(text, fields[name], f'{what} {name}')
    return tuple(sorted(out.items()))


def _env_fields(task: str) -> dict:
    if task == 'choice':
        from hron_jax.envs.choice import ChoiceConfig
        return {f.name: f.default for f in dataclasses.fields(ChoiceConfig)}
    from hron_jax.envs.navigation import NavConfig
    fields = {f.name: f.default for f in dataclasses.fields(NavConfig)
              if not dataclasses.is_dataclass(f.default)}
    fields['image_size'] = 32
    return fields


_ENV_RESERVED = {'distractors': '--distractors', 'premap': '--premap', 'task': '--task',
                 'image_obs': "--model (an RGB-D model, or --model-option use_rgbd=true)",
                 'metric_map': '--model rgbd_mm', 'auto_reset': 'nothing (training needs it)'}


def config_from_args(args: dict, base: TrainConfig | None = None) -> TrainConfig:
    """TrainConfig from parsed CLI options (only those given are in `args`) over `base` (a resumed
    run's config) or the per-task defaults."""
    task = args.get('task', base.task if base else DEFAULT_TASK)
    if base is None:
        d = TASK_DEFAULTS[task]
        flat = _flat(TrainConfig(task=task, ppo=d['ppo'], log_every=d['log_every'],
                                 checkpoint_every=d['checkpoint_every'],
                                 scene=DEFAULT_SCENES.get(task)).to_dict())
    else:
        flat = _flat(base.to_dict())
    for k, v in args.items():
        if k not in _FIELD:
            continue
        if k == 'scene':
            v = os.path.abspath(v)
            if not os.path.isfile(v):
                raise UsageError(f'scene file not found: {v}')
        elif k == 'env_option':
            v = [list(kv) for kv in _options(v, _env_fields(task), '--env-option', _ENV_RESERVED)]
        elif k == 'model_option':
            fields = {f.name: f.default for f in dataclasses.fields(ModelConfig)}
            v = [list(kv) for kv in _options(v, fields, '--model-option', {})]
        flat[_FIELD[k]] = v
    if base is None and task == 'choice' and 'scene' not in args:
        flat['scene'] = None
    if flat['ppo.seed'] != flat['seed']:
        flat['ppo.seed'] = flat['seed']
    d = {k: v for k, v in flat.items() if not k.startswith('ppo.')}
    d['ppo'] = {k[4:]: v for k, v in flat.items() if k.startswith('ppo.')}
    if d['task'] != 'choice' and d['scene'] is None:
        d['scene'] = DEFAULT_SCENES[d['task']]
    return TrainConfig.from_dict(d)


def default_run_dir(config: TrainConfig) -> Path:
    parts = [config.task, config.model]
    if config.distractors:
        parts.append('dist')
    if config.premap:
        parts.append('pm')
    parts.append(f's{config.seed}' + (f'x{config.num_seeds}' if config.num_seeds > 1 else ''))
    parts.append(time.strftime('%Y%m%d-%H%M%S'))
    return Path('runs') / '_'.join(parts)


def tune_malloc() -> bool:
    """Keep freed memory in the process (glibc): one arena, no mmap'd chunks, trim above 2 GiB.

    XLA:CPU takes every call's temporaries from malloc and glibc hands large blocks back to the
    OS, so each call page-faults its working set again: measured 374 -> 270 ms per rgbd_sg_attn
    fwd+grad at batch 64 on the 2-core VM (`python -m hron_jax.bench model`), the same as setting
    MALLOC_ARENA_MAX=1 MALLOC_MMAP_MAX_=0 MALLOC_TRIM_THRESHOLD_ before start. Called by the
    train / eval / bench entry points; returns False where there is no glibc (nothing changes).
    """
    import ctypes
    try:
        libc = ctypes.CDLL('libc.so.6')
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    m_trim_threshold, m_mmap_max, m_arena_max = -1, -4, -8     # glibc malloc.h
    return bool(mallopt(m_arena_max, 1) and mallopt(m_mmap_max, 0)
                and mallopt(m_trim_threshold, 2 ** 31 - 1))


def setup_compile_cache(path: str | None) -> None:
    """Persistent XLA cache, so a resumed (or repeated) run does not pay the compile again."""
    import jax
    if path is None:
        path = os.environ.get('JAX_COMPILATION_CACHE_DIR') or os.path.join(
            os.path.expanduser('~'), '.cache', 'hron_jax', 'xla')
    if path.lower() == 'none':
        return
    jax.config.update('jax_compilation_cache_dir', path)
    jax.config.update('jax_persistent_cache_min_compile_time_secs', 1.0)


class GracefulStop:
    """SIGINT / SIGTERM set a flag (the current chunk finishes, then the run checkpoints and
    exits); a second signal gets the default behaviour (abort)."""

    def __init__(self, log):
        self.signum = None
        self._log = log
        self._old = {}

    def __enter__(self):
        for s in (signal.SIGINT, signal.SIGTERM):
            self._old[s] = signal.signal(s, self._handle)
        return self

    def _handle(self, signum, frame):
        self.signum = signum
        self._log(f'\n{signal.Signals(signum).name}: finishing the current chunk, then checkpointing '
                  '(send it again to abort)')
        for s, old in self._old.items():
            signal.signal(s, old)

    def __exit__(self, *exc):
        for s, old in self._old.items():
            signal.signal(s, old)

    def __call__(self) -> bool:
        return self.signum is not None


def main(argv=None, prog: str = 'train.py') -> int:
    tune_malloc()
    parser = build_parser(prog)
    args = vars(parser.parse_args(argv))
    log = lambda s: print(s, file=sys.stderr, flush=True)
    try:
        if 'resume' in args and 'out' in args and os.path.abspath(args['out']) != os.path.abspath(args['resume']):
            raise UsageError('give either --out or --resume, not both')
        base = load_config(Path(args['resume'])) if 'resume' in args else None
        config = config_from_args(args, base)
        setup_compile_cache(args.get('compile_cache'))
        import absl.logging
        absl.logging.set_verbosity(absl.logging.ERROR)   # orbax's INFO lines
        make_mesh(config.ppo.num_envs)                   # device-count check before any build
        run_dir = Path(args['resume']) if base is not None else Path(args.get('out') or default_run_dir(config))
        trainer = Trainer(config, run_dir, resume=base is not None,
                          progress=not args.get('no_progress', False), log=log)
    except UsageError as e:
        print(f'{prog}: error: {e}', file=sys.stderr)
        return 2
    except CheckpointError as e:
        print(f'{prog}: error: {e}', file=sys.stderr)
        return 1
    log(f'run dir: {run_dir}')
    with GracefulStop(log) as stop:
        try:
            trainer.run(should_stop=stop)
        finally:
            trainer.close()
    if stop.signum is not None:
        log(f'stopped at update {trainer.update} / {config.num_updates}; continue with: '
            f'python {prog} --resume {run_dir}')
        return 128 + stop.signum
    log(f'done: {trainer.update} updates; {run_dir}')
    return 0
