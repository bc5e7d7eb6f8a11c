"""A run directory on disk: its config, checkpoints and metrics (reading and writing, no training).

    RUN_DIR/config.json        {'config': TrainConfig.to_dict(), 'meta': jax version, devices, argv}
    RUN_DIR/checkpoints/<U>/   orbax checkpoint of the full RunnerState after U updates
    RUN_DIR/corrupt_checkpoints/<U>/  a checkpoint found damaged on restore, moved aside (kept)
    RUN_DIR/metrics.jsonl      one row per update chunk (hron_jax.metrics_log)
    RUN_DIR/processes.jsonl    one row per train.py start or resume (multi-host: process 0's): time,
                               argv, the update it started from, machine (CPU, cores, load, JAX, devices)

    load_config(run_dir) -> TrainConfig          save_config(run_dir, config)
    record_process(run_dir, update)               run_machines(run_dir) -> [machine dict]
    restore_runner(run_dir, abstract, log=...) -> (RunnerState [S, ...], update)
    restore_params(run_dir, config, env, network, step) -> (params [S, ...] numpy, update)
    read_metrics(run_dir) -> [row dict]           write_json(path, obj) (atomic)

Checkpoints hold zero-size leaves (mjx.Data has some) as 1-element placeholders, as orbax refuses
empty arrays. A checkpoint whose arrays do not match the config (another model size or code
version) is a CheckpointError; a damaged newest checkpoint is moved aside and the newest intact
one is restored instead (resuming recomputes the updates after it exactly), and the caller is told.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from hron_jax.errors import CheckpointError, UsageError
from hron_jax.multihost import is_main, sync
from hron_jax.run_config import TrainConfig


def write_json(path: Path, obj) -> None:
    """Write atomically: a reader never sees half a file."""
    path = Path(path)
    tmp = path.with_suffix(path.suffix + '.tmp')
    with open(tmp, 'w') as f:
        json.dump(obj, f, indent=2)
        f.write('\n')
    os.replace(tmp, path)


def load_config(run_dir) -> TrainConfig:
    path = Path(run_dir) / 'config.json'
    if not path.is_file():
        raise UsageError(f'{run_dir}: not a run directory (no config.json)')
    try:
        with open(path) as f:
            d = json.load(f)
    except (OSError, json.JSONDecodeError) as e:
        raise UsageError(f'{path}: unreadable ({e})') from None
    try:
        return TrainConfig.from_dict(d['config'] if 'config' in d else d)
    except UsageError as e:
        raise UsageError(f'{path}: {e}') from None


def save_config(run_dir, config: TrainConfig) -> None:
    import jax

    meta = dict(
        jax=jax.__version__,
        devices=[str(d) for d in jax.local_devices()],
        argv=sys.argv,
        time=time.strftime('%Y-%m-%d %H:%M:%S'),
    )
    write_json(Path(run_dir) / 'config.json', dict(config=config.to_dict(), meta=meta))


def record_process(run_dir, update: int) -> None:
    """Append this process to RUN_DIR/processes.jsonl. config.json's meta is rewritten by every
    resume, so this log is what says on which machines a run that was resumed elsewhere trained."""
    from hron_jax.bench import machine

    row = dict(time=time.strftime('%Y-%m-%d %H:%M:%S'), update=update, argv=sys.argv, machine=machine())
    with open(Path(run_dir) / 'processes.jsonl', 'a') as f:
        f.write(json.dumps(row) + '\n')


def run_machines(run_dir) -> list[dict]:
    """The machines of a run's processes, oldest first ([] for runs made before the log)."""
    path = Path(run_dir) / 'processes.jsonl'
    if not path.is_file():
        return []
    return [json.loads(line)['machine'] for line in path.read_text().splitlines() if line.strip()]


def read_metrics(run_dir) -> list[dict]:
    rows = []
    path = Path(run_dir) / 'metrics.jsonl'
    if path.exists():
        with open(path) as f:
            for line in f:
                try:
                    rows.append(json.loads(line))
                except json.JSONDecodeError:  # a line cut by a hard kill
                    pass
    return rows


# ------------------------------------------------------------------------------------------------
# Checkpoints
# ------------------------------------------------------------------------------------------------


def checkpoint_manager(run_dir, keep: int = 3, create: bool = True):
    import orbax.checkpoint as ocp

    return ocp.CheckpointManager(
        (Path(run_dir) / 'checkpoints').resolve(),
        item_handlers=ocp.StandardCheckpointHandler(),
        options=ocp.CheckpointManagerOptions(max_to_keep=keep, create=create),
    )


def _is_empty(x) -> bool:
    return int(np.prod(x.shape)) == 0


def storable(tree):
    """The tree as saved: zero-size leaves replaced by a 1-element placeholder."""
    import jax
    import jax.numpy as jnp

    return jax.tree.map(lambda x: jnp.zeros((1,), x.dtype) if _is_empty(x) else x, tree)


def _storable_abstract(abstract):
    import jax
    from jax.sharding import NamedSharding, PartitionSpec

    def f(a):
        if not _is_empty(a):
            return a
        sharding = a.sharding
        if isinstance(sharding, NamedSharding):
            sharding = NamedSharding(sharding.mesh, PartitionSpec())
        return jax.ShapeDtypeStruct((1,), a.dtype, sharding=sharding)

    return jax.tree.map(f, abstract)


def _from_storable(abstract, restored):
    import jax
    import jax.numpy as jnp

    return jax.tree.map(
        lambda a, r: jnp.zeros(a.shape, a.dtype, device=a.sharding) if _is_empty(a) else r, abstract, restored
    )


def _leaf_name(path) -> str:
    """A key path as orbax names checkpoint entries ('env_state.info.steps')."""
    parts = []
    for k in path:
        for attr in ('key', 'name', 'idx'):
            if hasattr(k, attr):
                parts.append(str(getattr(k, attr)))
                break
    return '.'.join(parts)


class _Damaged(CheckpointError):
    """The checkpoint's files are unreadable (as opposed to readable but for another config)."""


def _check_metadata(manager, step: int, abstract, path: Path, partial: bool = False) -> None:
    """Compare the stored arrays (names, shapes, dtypes) with what this config builds (with
    `partial`, only those in `abstract`, e.g. {'params': ...})."""
    import jax

    try:
        stored = {m.name: m for m in jax.tree.leaves(manager.item_metadata(step))}
        if not stored:
            raise ValueError('no arrays listed')
    except Exception as e:
        raise _Damaged(
            f'{path}: unreadable checkpoint metadata ({type(e).__name__}: {str(e)[:200]})'
        ) from None
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
                problems.append(
                    f'{name} stored {tuple(b.shape)} {b.dtype}, expected {tuple(a.shape)} {a.dtype}'
                )
    if problems:
        more = f' (+{len(problems) - 3} more)' if len(problems) > 3 else ''
        raise CheckpointError(
            f'{path}: checkpoint does not match this run\'s config: {"; ".join(problems[:3])}{more}. '
            'It was written by a different config or code version: restore config.json / the code, '
            'or start a new run with another --out'
        )


def _steps(run_dir: Path):
    """(manager, sorted checkpoint steps); CheckpointError if there are none."""
    manager = checkpoint_manager(run_dir, create=False) if (run_dir / 'checkpoints').is_dir() else None
    steps = sorted(manager.all_steps()) if manager is not None else []
    if not steps:
        if manager is not None:
            manager.close()
        raise CheckpointError(
            f'{run_dir / "checkpoints"}: no checkpoint found; start a new run (train.py without --resume)'
        )
    return manager, steps


@contextlib.contextmanager
def _restoring(path: Path):
    """Any failure inside other than a CheckpointError is a damaged checkpoint."""
    try:
        yield
    except CheckpointError:
        raise
    except Exception as e:
        raise _Damaged(
            f'{path}: cannot restore the checkpoint ({type(e).__name__}: {str(e)[:300]})'
        ) from None


def _set_aside(run_dir: Path, step: int) -> Path:
    """Move a damaged checkpoint out of checkpoints/ (kept for inspection, never overwritten)."""
    dest = run_dir / 'corrupt_checkpoints' / str(step)
    if dest.exists():
        dest = dest.with_name(f'{step}_{time.strftime("%Y%m%d-%H%M%S")}')
    dest.parent.mkdir(exist_ok=True)
    shutil.move(str(run_dir / 'checkpoints' / str(step)), str(dest))
    return dest


def restore_runner(run_dir, abstract, log: Callable[[str], None] = print):
    """(RunnerState restored onto `abstract`'s shardings, its update) from the newest intact
    checkpoint: damaged newer ones are moved to RUN_DIR/corrupt_checkpoints/ and reported with
    `log`. Raises CheckpointError when none is intact or they do not fit the config."""
    import orbax.checkpoint as ocp

    run_dir = Path(run_dir).resolve()
    stored = _storable_abstract(abstract)
    while True:
        manager, steps = _steps(run_dir)
        step = steps[-1]
        path = run_dir / 'checkpoints' / str(step)
        try:
            with _restoring(path):
                _check_metadata(manager, step, stored, path)
                runner = manager.restore(step, args=ocp.args.StandardRestore(stored))
            return _from_storable(abstract, runner), step
        except _Damaged as e:
            damaged = e
        finally:
            manager.close()
        if len(steps) == 1:
            raise CheckpointError(
                f'{damaged}; no older checkpoint to fall back to: start a new run with another --out'
            )
        if is_main():  # one process moves it; the others list the checkpoints after the barrier
            dest = _set_aside(run_dir, step)
            log(f'{damaged}: moved it to {dest}; falling back to checkpoint {steps[-2]}')
        sync(f'hron_jax: checkpoint {step} set aside')


def restore_params(run_dir, config: TrainConfig, env, network, step: int | None = None):
    """(params with a leading seed axis [S, ...] as numpy, step) of a run's checkpoint (the
    newest unless `step`): only the parameters are read, so `env` may be built differently from
    training (e.g. no auto-reset)."""
    import jax
    import orbax.checkpoint as ocp

    run_dir = Path(run_dir).resolve()  # orbax restores from absolute paths only
    manager, steps = _steps(run_dir)
    step = steps[-1] if step is None else step
    path = run_dir / 'checkpoints' / str(step)
    try:
        if step not in steps:
            raise CheckpointError(
                f'{run_dir / "checkpoints"}: no checkpoint for step {step}; available: {steps}'
            )
        obs = jax.eval_shape(env.reset, jax.random.PRNGKey(0)).obs
        one = jax.eval_shape(network.init, jax.random.PRNGKey(0), obs)
        item = {
            'params': jax.tree.map(
                lambda a: jax.ShapeDtypeStruct((config.num_seeds,) + a.shape, a.dtype), one
            )
        }
        with _restoring(path):
            _check_metadata(manager, step, item, path, partial=True)
            out = ocp.PyTreeCheckpointer().restore(
                path / 'default',
                args=ocp.args.PyTreeRestore(
                    item=item,
                    restore_args=ocp.checkpoint_utils.construct_restore_args(item),
                    partial_restore=True,
                ),
            )
    except _Damaged as e:
        raise CheckpointError(
            f'{e}; evaluate an older checkpoint (RUN_DIR/checkpoints/<update>, available: {steps})'
        ) from None
    finally:
        manager.close()
    return out['params'], step
