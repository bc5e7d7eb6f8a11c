"""Training a run: one jitted program per run config (seeds vmapped, envs sharded) and the Trainer.

Role: what `train.py` runs (its CLI is hron_jax.cli); the run directory's files are written by
hron_jax.run_dir (config, checkpoints) and hron_jax.metrics_log (metrics, curves).

Program (`Programs`, built once per program-relevant config and cached in-process):
    init_params(keys u32[S, 2]) -> params [S, ...]     on the host CPU (see Programs.initialize)
    init(keys, params) -> RunnerState with a leading seed axis S on every leaf
    chunk(runner, n: static) -> (runner, metrics {name: f32[S, n]})
S = num_seeds seeds train in one program (jax.vmap of hron_jax.ppo over the RunnerState; with
S = 1 the unvmapped PPO runs and the axis is added outside, which keeps the branches of PPO's
truncation bootstrap (the rollout's 1-2 pass loop, the final-obs render under a cond) real).
Seed i uses jax.random.PRNGKey(seed + i), so seed i of a multi-seed run is the single-seed run
with --seed seed+i.
Env state leaves are [S, num_envs, ...] and sharded over a 1-D mesh of all devices, those of every
process in a multi-host job (hron_jax.multihost) (axis 'devices', NamedSharding P(None, 'devices'));
params, optimiser state and rng are replicated.
num_envs must be divisible by the device count.
metrics adds 'nonfinite' (1 where the update's loss or the chunk's final parameters hold a NaN /
Inf): the Trainer then stops without taking that state, so the last checkpoint stays finite.

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
"""

from __future__ import annotations

import dataclasses
import functools
import re
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from hron_jax.errors import NonFiniteError, UsageError
from hron_jax.metrics_log import MetricsLog, curve_rows, plot_learning_curves, recent_success, summarize_chunk
from hron_jax.multihost import is_main, sync
from hron_jax.run_config import RESUMABLE, TrainConfig, build_env, build_network, config_diff, run_label
from hron_jax.run_dir import (
    checkpoint_manager,
    load_config,
    record_process,
    restore_runner,
    save_config,
    storable,
)


class Programs(NamedTuple):
    env: Any
    network: Any
    ppo: Any
    mesh: Any
    init_params: Callable  # jitted for the host CPU: keys u32[S, 2] -> params [S, ...]
    init: Callable  # jitted: (keys u32[S, 2], params [S, ...]) -> RunnerState [S, ...]
    chunk: Callable  # jitted: (runner, n static) -> (runner, metrics f32[S, n])
    abstract: Any  # RunnerState of ShapeDtypeStruct with shardings
    shardings: Any  # RunnerState of NamedSharding
    compiler_options: dict  # XLA options of the chunks (FAST_COMPILE or none); init: FAST_COMPILE
    compiled: dict  # 'params' / 'init' / n -> AOT-compiled executable (shared by every Trainer)

    def initialize(self, keys):
        """The runners of seeds `keys`: init(keys, init_params(keys)), two programs that run once
        per run, so both compile without LLVM optimisation (most of them is the threefry code of
        ~100 parameter initialisers and the episode sampler; main exploratory config, 64 envs,
        2-core VM: compile 11.6 -> 6.0 s, run 0.28 -> 0.40 s; with the classic emitters of
        FAST_COMPILE 11.9 / 13.3 -> 9.8 / 8.7 s, run ~0.5 s either way; float rounding differs
        from LLVM's, initial params within 3e-6, the same on every run of a config).

        The parameters are computed on the host CPU, whatever the devices: their initialisers are
        14,612 of the 24,342 HLO instructions XLA:GPU made of one init program for an H100 at 1024
        envs (`bench compile --gpu-target h100`, 2-core EPYC VM: that program 23.0 s, its env
        reset alone 8.2 s, the parameters alone 11.4 s), and XLA:CPU compiles them in 2-3 s. In a
        multi-host job process 0's parameters are broadcast, so hosts with different CPUs cannot
        start from parameters that differ in rounding."""
        import jax

        if 'init' not in self.compiled:
            self.compiled['params'] = compile_lowered(self.init_params.lower(keys), FAST_COMPILE)
            lowered = self.init.lower(keys, self.abstract.params)  # replicated, as init takes them
            self.compiled['init'] = compile_lowered(lowered, FAST_COMPILE)
        params = jax.device_get(self.compiled['params'](keys))
        if jax.process_count() > 1:
            from jax.experimental import multihost_utils

            params = multihost_utils.broadcast_one_to_all(params)
        return self.compiled['init'](keys, params)

    def compiled_chunk(self, n: int):
        """(executable runner -> (runner, metrics), seconds spent compiling it now)."""
        if n in self.compiled:
            return self.compiled[n], 0.0
        t = time.perf_counter()
        self.compiled[n] = compile_lowered(self.chunk.lower(self.abstract, n), self.compiler_options)
        return self.compiled[n], time.perf_counter() - t


# XLA:CPU options of --fast-compile: no LLVM optimisation, and XLA's classic elemental emitters
# instead of its MLIR fusion emitters (which, once LLVM no longer optimises, are the largest part
# of the compile). Measured on the choice task, LLVM options alone: compiles ~3x faster (tiny model:
# 21 -> 5.5 s), runs ~2.7x slower at default model sizes. The emitters on top (2-core Xeon, tiny
# models, 1-update chunk / init compile s): choice 7.2 / 3.5 -> 3.8 / 2.4, directed 27.0 / 7.6 ->
# 15.7 / 5.7, exploratory 23.3 / 7.5 -> 18.1 / 6.3; default exploratory model at 16 x 16: 37.7 ->
# 21.5 s, but 34 -> 46 s per update. For tests and debugging; float rounding differs, so it is part
# of the config (resume checks it). XLA:GPU ignores those three; its counterpart is ptxas at -O0
# (XLA:CPU ignores it): the init's env reset at 1024 envs compiled for an H100 without one
# (bench compile --gpu-target, 2-core VM) in 11.9 / 11.1 -> 10.4 / 9.7 s, alternated.
FAST_COMPILE = {
    'xla_backend_optimization_level': 0,
    'xla_llvm_disable_expensive_passes': True,
    'xla_cpu_use_fusion_emitters': False,
    'xla_gpu_disable_gpuasm_optimizations': True,
}


# Compile options the installed XLA rejected as unknown (compile_lowered), e.g. jax >= 0.11's, and
# those supported_options has tried.
_UNKNOWN_OPTIONS: set[str] = set()
_CHECKED_OPTIONS: set[str] = set()


def compile_lowered(lowered, options: dict | None):
    """lowered.compile(options) without the options this XLA does not know: XLA drops flags
    between releases (xla_cpu_use_fusion_emitters is gone from jax 0.11's), and an unknown one
    fails the whole compile. Options are read before any compiling, so a retry costs nothing."""
    import jax

    options = {k: v for k, v in (options or {}).items() if k not in _UNKNOWN_OPTIONS}
    while True:
        try:
            return lowered.compile(options)
        except jax.errors.JaxRuntimeError as e:
            unknown = re.search(r"No such compile option: '(\w+)'", str(e))
            if unknown is None or unknown.group(1) not in options:
                raise
            _UNKNOWN_OPTIONS.add(unknown.group(1))
            del options[unknown.group(1)]


def supported_options(options: dict) -> dict:
    """`options` less those this XLA does not know, for `jax.jit(..., compiler_options=...)` (which,
    unlike compile_lowered, fails on them): a one-op program is compiled once to find out."""
    import jax
    import jax.numpy as jnp

    if not set(options) <= _CHECKED_OPTIONS:
        compile_lowered(jax.jit(lambda x: x + 1).lower(jnp.zeros(())), options)
        _CHECKED_OPTIONS.update(options)
    return {k: v for k, v in options.items() if k not in _UNKNOWN_OPTIONS}


def make_mesh(num_envs: int, devices=None):
    """1-D mesh over `devices` (default: all devices, of every process in a multi-host job); env
    batches are split over its 'devices' axis."""
    import jax

    devices = jax.devices() if devices is None else list(devices)
    if num_envs % len(devices):
        where = f'{jax.process_count()} processes' if jax.process_count() > 1 else 'this process'
        raise UsageError(
            f'--num-envs {num_envs} is not divisible by the {len(devices)} devices '
            f'({devices[0].platform}, {where}); use a multiple of {len(devices)}'
        )
    return jax.sharding.Mesh(np.asarray(devices), ('devices',))


def seed_keys(config: TrainConfig):
    import jax
    import jax.numpy as jnp

    # numpy: the same value on every process of a multi-host job (jit replicates it).
    return np.asarray(jnp.stack([jax.random.PRNGKey(config.seed + i) for i in range(config.num_seeds)]))


def _program_key(config: TrainConfig) -> TrainConfig:
    """The config with fields that do not change the compiled program normalised (cache key)."""
    ppo = config.ppo
    total = ppo.total_timesteps if ppo.anneal_lr else ppo.batch_size
    return dataclasses.replace(
        config,
        seed=0,
        checkpoint_every=1,
        keep_checkpoints=1,
        log_every=1,
        ppo=dataclasses.replace(ppo, total_timesteps=total),
    )


def programs(config: TrainConfig, devices=None) -> Programs:
    """The jitted programs of `config` on `devices` (default: all; compile-only devices of a
    GPU target give XLA:GPU's programs on a machine without one, hron_jax.bench.compile)."""
    import jax

    return _programs(_program_key(config), tuple(jax.devices() if devices is None else devices))


@functools.lru_cache(maxsize=4)
def _programs(config: TrainConfig, devices: tuple) -> Programs:
    import jax
    import jax.numpy as jnp
    from jax.sharding import NamedSharding, PartitionSpec

    from hron_jax.ppo import make_ppo

    mesh = make_mesh(config.ppo.num_envs, devices)
    try:
        env = build_env(config)
        network = build_network(config, env)
    except (ValueError, TypeError, OSError) as e:  # e.g. a scene file the loader rejects
        raise UsageError(f'cannot build the {config.task} env / {config.model} model: {e}') from None
    ppo = make_ppo(config.ppo, env, network)
    add = functools.partial(jax.tree.map, lambda x: x[None])
    drop = functools.partial(jax.tree.map, lambda x: x[0])

    if config.num_seeds == 1:

        def init_params(keys):
            return add(ppo.init_params(keys[0]))

        def init(keys, params):
            return add(ppo.init(keys[0], drop(params)))

        def updates(runner, n):
            return add(ppo.update_chunk(drop(runner), n))
    else:
        init_params = jax.vmap(ppo.init_params)
        init = jax.vmap(ppo.init)

        def updates(runner, n):
            return jax.vmap(lambda r: ppo.update_chunk(r, n))(runner)

    def chunk(runner, n):
        runner, metrics = updates(runner, n)
        # Checked once per chunk on the device (one reduction over the parameters), so a NaN
        # never reaches a checkpoint; non-finite parameters make the next update's loss NaN too.
        # One reduction over all leaves side by side: a reduction per leaf is a kernel per leaf.
        flat = jnp.concatenate([x.reshape(x.shape[0], -1) for x in jax.tree.leaves(runner.params)], 1)
        params_ok = jnp.isfinite(flat).all(1)
        bad = ~jnp.isfinite(metrics['loss'])
        metrics['nonfinite'] = bad.at[:, -1].set(bad[:, -1] | ~params_ok).astype(jnp.float32)
        return runner, metrics

    keys = jax.ShapeDtypeStruct((config.num_seeds, 2), np.uint32)
    abstract = jax.eval_shape(init, keys, jax.eval_shape(init_params, keys))
    replicated = NamedSharding(mesh, PartitionSpec())
    try:  # the host CPU computes the initial parameters (Programs.initialize)
        host = jax.sharding.SingleDeviceSharding(jax.local_devices(backend='cpu')[0])
    except RuntimeError:  # no CPU backend (JAX_PLATFORMS without cpu): a local device then
        host = jax.sharding.SingleDeviceSharding(jax.local_devices()[0])
    env_sharded = NamedSharding(mesh, PartitionSpec(None, 'devices'))
    # Env states are split over the devices; everything else (params, optimiser, rng, counters)
    # is replicated.
    shardings = jax.tree.map(lambda _: replicated, abstract).replace(
        env_state=jax.tree.map(lambda _: env_sharded, abstract.env_state)
    )
    abstract = jax.tree.map(
        lambda a, s: jax.ShapeDtypeStruct(a.shape, a.dtype, sharding=s), abstract, shardings
    )
    return Programs(
        env=env,
        network=network,
        ppo=ppo,
        mesh=mesh,
        init_params=jax.jit(init_params, in_shardings=host, out_shardings=host),
        init=jax.jit(init, in_shardings=replicated, out_shardings=shardings),
        chunk=jax.jit(chunk, static_argnums=1, out_shardings=(shardings, replicated)),
        abstract=abstract,
        shardings=shardings,
        compiler_options=dict(FAST_COMPILE) if config.fast_compile else {},
        compiled={},
    )


class Trainer:
    """One run: init or restore, then chunks of updates with logging and checkpoints.

    Trainer(config, run_dir, resume=False) creates run_dir (must not hold a run yet) and saves
    config.json and the initial state; resume=True restores the latest checkpoint of run_dir
    (config must equal its config.json up to RESUMABLE fields; `load_config` gives it).
    run(max_updates=None, should_stop=None) trains until config.num_updates (or max_updates more
    updates, or should_stop() is true after a chunk), then checkpoints; returns the RunnerState.
    A NaN / Inf in a chunk raises NonFiniteError; the state before that chunk is checkpointed.
    """

    def __init__(
        self,
        config: TrainConfig,
        run_dir,
        *,
        resume: bool = False,
        progress: bool = True,
        tensorboard: bool = True,
        log: Callable[[str], None] | None = None,
    ):
        import jax

        self.config = config
        self.run_dir = Path(run_dir)
        # In a multi-host job every process trains (and checkpoints its shards through orbax);
        # process 0 alone writes config, metrics, curves and progress.
        self.is_main = is_main()
        self.progress = progress and self.is_main
        self._log = (log or (lambda s: print(s, flush=True))) if self.is_main else (lambda s: None)
        if resume:
            saved = load_config(self.run_dir)
            diff = {k: v for k, v in config_diff(saved, config).items() if k not in RESUMABLE}
            if diff:
                raise UsageError(
                    f'{self.run_dir / "config.json"} differs from the requested config in '
                    + ', '.join(f'{k} (saved {a!r}, given {b!r})' for k, (a, b) in diff.items())
                )
            if config.ppo.anneal_lr and config.ppo.total_timesteps != saved.ppo.total_timesteps:
                raise UsageError(
                    'total steps cannot change on resume when the learning rate is '
                    'annealed over them (--anneal-lr)'
                )
        elif (self.run_dir / 'config.json').exists():
            raise UsageError(
                f'{self.run_dir} already holds a run; continue it with --resume '
                f'{self.run_dir} or choose another --out'
            )
        sync('hron_jax: run dir checked')  # by every process, before anyone writes to it
        self.programs = programs(config)
        t = time.perf_counter()
        if resume:
            self.runner, step = restore_runner(self.run_dir, self.programs.abstract, log=self._log)
            self._log(f'resumed {self.run_dir} at update {step} / {config.num_updates}')
            if self.is_main:
                save_config(self.run_dir, config)  # RESUMABLE fields may have changed
        else:
            self.run_dir.mkdir(parents=True, exist_ok=True)
            if self.is_main:
                save_config(self.run_dir, config)
            self.runner = self.programs.initialize(seed_keys(config))
            step = 0
        if self.is_main:
            record_process(self.run_dir, step)
        self.update = int(jax.device_get(self.runner.update[0]))
        assert self.update == step
        self.manager = checkpoint_manager(self.run_dir, keep=config.keep_checkpoints)
        if not resume:
            self._save()
        self.metrics = MetricsLog(self.run_dir, step if resume else None, tensorboard, write=self.is_main)
        sim = getattr(config.env, 'sim', None)
        self._log(
            f'init: {time.perf_counter() - t:.1f} s; {config.num_seeds} seed(s) x '
            f'{config.ppo.num_envs} envs on {len(self.programs.mesh.devices)} device(s)'
            + (f'; physics {sim.physics}' if sim is not None else '')
        )

    # -- checkpoints ----------------------------------------------------------------------------
    def _save(self) -> None:
        import orbax.checkpoint as ocp

        if self.update in self.manager.all_steps():
            return
        self.manager.save(self.update, args=ocp.args.StandardSave(storable(self.runner)))
        self.manager.wait_until_finished()

    def checkpoint(self) -> None:
        """Save the current state (if not saved yet) and redraw the learning curve."""
        self._save()
        self.metrics.flush()
        if self.metrics.rows and self.is_main:
            c = self.config
            title = (
                f'{c.task}{" + distractors" if c.distractors else ""}: {run_label(c)}, {c.num_seeds} seed(s)'
            )
            plot_learning_curves(
                {run_label(c): curve_rows([self.metrics.rows])}, self.run_dir / 'learning_curve.png', title
            )

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

        bar = tqdm(
            total=total * steps_per_update,
            initial=self.update * steps_per_update,
            unit='step',
            unit_scale=True,
            dynamic_ncols=True,
            disable=not self.progress,
            file=sys.stderr,
            mininterval=0.5,
            smoothing=0.1,
        )
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
                self._check_finite(metrics['nonfinite'])
                # Only now (chunk complete and finite) does the state advance, so a checkpoint
                # written on any exit is consistent.
                self.runner = runner
                self.update += n
                summary = summarize_chunk(metrics)
                row = self.metrics.append(
                    self.update, summary, wall0 + time.perf_counter() - t_run, n * steps_per_update / dt
                )
                bar.update(n * steps_per_update)
                bar.set_postfix_str(self._postfix(row), refresh=False)
                if self.update - last_ckpt >= c.checkpoint_every or self.update == total:
                    self.checkpoint()
                    last_ckpt = self.update
        except BaseException:
            bar.close()
            try:
                self.checkpoint()
            except Exception:  # keep the original error
                pass
            raise
        bar.close()
        self.checkpoint()
        return self.runner

    def _postfix(self, row: dict) -> str:
        """Progress-bar text. Its SR is over the episodes that ended in the last episode length's
        worth of updates, and only once every env has had time to end one: before that, only
        episodes that ended early (successes, wrong objects) can have finished, so the success
        rate among them says nothing about the policy (a random policy shows 1.0)."""
        c = self.config
        steps_per_env = self.update * c.ppo.num_steps
        window = -(-c.env.max_steps // c.ppo.num_steps)  # updates spanning one full episode
        sr, episodes = recent_success(self.metrics.rows, self.update - window)
        if steps_per_env < c.env.max_steps:
            sr_text = f'SR n/a until {c.env.max_steps} steps/env ({episodes:.0f} early eps)'
        else:
            sr_text = f'SR {sr:.3f} ({episodes:.0f} eps)' if episodes else 'SR - (0 eps)'
        ret = row.get('return')
        return f'upd {self.update}/{c.num_updates} {sr_text} ret {"-" if ret is None else format(ret, ".2f")}'

    def _check_finite(self, nonfinite) -> None:
        """NonFiniteError naming the first update (and seeds) whose loss or parameters are NaN /
        Inf; the state stays at the chunk's start, which the exit path checkpoints."""
        bad = np.asarray(nonfinite) > 0  # [S, n]
        if not bad.any():
            return
        i = int(bad.any(0).argmax())
        seeds = [self.config.seed + s for s in np.nonzero(bad[:, i])[0]]
        raise NonFiniteError(
            f'NaN or Inf in the loss or parameters at update {self.update + i + 1} (seed '
            f'{", ".join(map(str, seeds))}); stopped with the last finite state checkpointed at '
            f'update {self.update} in {self.run_dir / "checkpoints"}; start a new run with a lower '
            '--lr or --max-grad-norm'
        )

    def close(self) -> None:
        self.manager.wait_until_finished()
        self.manager.close()
        self.metrics.close()
