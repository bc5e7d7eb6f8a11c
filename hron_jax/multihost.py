"""Multi-host training (jax.distributed): process setup and the few places processes must agree.

One train.py per host, the same options on each (plus --coordinator / --num-processes /
--process-id, or --distributed to detect them): every process runs the same jitted programs on a
mesh over the devices of all hosts (hron_jax.training.make_mesh), the env states are sharded over
it and everything else is replicated, orbax writes each process's shards of a checkpoint into the
one (shared) run directory, and process 0 alone writes config, metrics, curves and progress.

    init_distributed(args) -> process index   jax.distributed.initialize from the parsed CLI
    is_main() -> bool                          process 0 (also True without jax.distributed)
    sync(name)                                 barrier of all processes (no-op with one)

Tested on one machine with CPU processes (tests/test_training.py: two processes of one device
each train bitwise like one process with two devices).
"""

from __future__ import annotations

from hron_jax.errors import UsageError


def init_distributed(args: dict) -> int:
    """jax.distributed.initialize from --coordinator / --num-processes / --process-id (all three)
    or --distributed (detected); before any JAX computation. Returns this process's index (0 when
    there is one process)."""
    given = {k: args[k] for k in ('coordinator', 'num_processes', 'process_id') if k in args}
    if not given and not args.get('distributed'):
        return 0
    if given and len(given) < 3 and not args.get('distributed'):
        raise UsageError(
            '--coordinator, --num-processes and --process-id go together (or give --distributed '
            'to detect them from the cluster environment)'
        )
    n, i = given.get('num_processes'), given.get('process_id')
    if n is not None and n < 1:
        raise UsageError(f'--num-processes {n}: must be >= 1')
    if i is not None and n is not None and not 0 <= i < n:
        raise UsageError(f'--process-id {i}: must be in 0 .. {n - 1} (--num-processes {n})')
    import jax

    try:
        jax.distributed.initialize(
            coordinator_address=given.get('coordinator'), num_processes=n, process_id=i
        )
    except (RuntimeError, ValueError) as e:
        raise UsageError(f'jax.distributed.initialize failed: {e}') from None
    return jax.process_index()


def is_main() -> bool:
    import jax

    return jax.process_index() == 0


def sync(name: str) -> None:
    """Wait until every process of the job has reached this point (a no-op with one)."""
    import jax

    if jax.process_count() > 1:
        from jax.experimental import multihost_utils

        multihost_utils.sync_global_devices(name)
