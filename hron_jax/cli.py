"""Command line and process setup of the entry points: train.py's CLI, one-line errors, signals.

    main(argv) -> exit code           train.py (0 done, 2 bad input, 1 checkpoint / NaN, 128+sig)
    build_parser(prog)                its options; per-task defaults in the epilog
    config_from_args(args, base)      parsed options (only those given) -> TrainConfig
    option_name(field)                the CLI option of a dotted config field ('ppo.lr' -> '--lr')
    error_line(prog, error)           the one line a UsageError / CheckpointError prints
    ArgumentParser                    argparse that reports errors as one line (exit 2)
    tune_malloc(), setup_compile_cache(path), GracefulStop   process setup shared with eval.py

Every option maps to one dotted field of the run config (hron_jax.run_config), which checks all
values in one place; a bad value prints `train.py: error: --OPTION: what is wrong` and exits 2.
"""

from __future__ import annotations

import argparse
import os
import signal
import sys
from pathlib import Path

from hron_jax.envs import TASKS
from hron_jax.errors import CheckpointError, ConfigError, NonFiniteError, UsageError
from hron_jax.multihost import init_distributed
from hron_jax.paths import CACHE_ROOT
from hron_jax.run_config import (
    DEFAULT_MODEL,
    DEFAULT_TASK,
    MODELS,
    PRESETS,
    TASK_DEFAULTS,
    TrainConfig,
    default_run_dir,
    make_config,
    override,
)


class ArgumentParser(argparse.ArgumentParser):
    """argparse that reports errors as one line (exit 2), without the usage block."""

    def error(self, message):
        self.exit(2, f'{self.prog}: error: {message} (see --help)\n')


# CLI option (argparse dest) -> dotted run-config field. --env-option / --model-option /
# --ppo-option NAME=VALUE set 'env.NAME' / 'network.NAME' / 'ppo.NAME'.
FIELDS = {
    'task': 'task',
    'model': 'model',
    'scene': 'scene',
    'distractors': 'env.distractors',
    'premap': 'env.premap',
    'seed': 'seed',
    'num_seeds': 'num_seeds',
    'log_every': 'log_every',
    'checkpoint_every': 'checkpoint_every',
    'keep_checkpoints': 'keep_checkpoints',
    'fast_compile': 'fast_compile',
    'num_envs': 'ppo.num_envs',
    'total_steps': 'ppo.total_timesteps',
    'num_steps': 'ppo.num_steps',
    'epochs': 'ppo.update_epochs',
    'minibatches': 'ppo.num_minibatches',
    'lr': 'ppo.lr',
    'anneal_lr': 'ppo.anneal_lr',
    'gamma': 'ppo.gamma',
    'gae_lambda': 'ppo.gae_lambda',
    'clip_eps': 'ppo.clip_eps',
    'ent_coef': 'ppo.ent_coef',
    'vf_coef': 'ppo.vf_coef',
    'max_grad_norm': 'ppo.max_grad_norm',
    'preset': 'preset',
}
_OPTION_PREFIXES = {'env_option': 'env.', 'model_option': 'network.', 'ppo_option': 'ppo.'}


def option_name(field: str) -> str:
    """The CLI option that sets a dotted config field."""
    for dest, f in FIELDS.items():
        if f == field:
            return '--' + dest.replace('_', '-')
    for dest, prefix in _OPTION_PREFIXES.items():
        if field.startswith(prefix):
            return f'--{dest.replace("_", "-")} {field[len(prefix) :]}'
    return field


def error_line(prog: str, error: Exception) -> str:
    if isinstance(error, ConfigError):
        return f'{prog}: error: {option_name(error.field)}: {error.message}'
    return f'{prog}: error: {error}'


def config_from_args(args: dict, base: TrainConfig | None = None) -> TrainConfig:
    """TrainConfig from parsed CLI options (only those given are in `args`) over `base` (a resumed
    run's config) or the per-task defaults."""
    overrides = {}
    for dest, value in args.items():
        if dest in _OPTION_PREFIXES:
            for item in value or []:
                name, sep, text = item.partition('=')
                if not sep or not name:
                    raise UsageError(f'--{dest.replace("_", "-")} {item!r}: expected NAME=VALUE')
                overrides[_OPTION_PREFIXES[dest] + name] = text
        elif dest == 'scene':
            path = os.path.abspath(value)
            if not os.path.isfile(path):
                raise ConfigError('scene', f'scene file not found: {path}')
            overrides['scene'] = path
        elif dest in FIELDS and dest not in ('task', 'model'):
            overrides[FIELDS[dest]] = value
    if base is None:
        return make_config(args.get('task', DEFAULT_TASK), args.get('model', DEFAULT_MODEL), overrides)
    for dest in ('task', 'model'):
        if dest in args and args[dest] != getattr(base, dest):
            raise UsageError(
                f'--{dest} {args[dest]}: the run to resume is {dest} {getattr(base, dest)}; drop --{dest}'
            )
    return override(base, overrides)


def _defaults_epilog() -> str:
    lines = [
        'per-task defaults (hron_jax.run_config.TASK_DEFAULTS; the paper: rollout 4096, minibatch '
        '128, 30 epochs, lr 1e-4, gamma 0.99, lambda 0.9):'
    ]
    for task, d in TASK_DEFAULTS.items():
        p = d['ppo']
        lines.append(
            f'  {task:12s} num-envs {p.num_envs}, num-steps {p.num_steps}, epochs '
            f'{p.update_epochs}, minibatches {p.num_minibatches}, lr {p.lr:g}, gamma '
            f'{p.gamma:g}, gae-lambda {p.gae_lambda:g}, ent-coef {p.ent_coef:g}, total-steps '
            f'{p.total_timesteps:,}, log-every {d["log_every"]}, checkpoint-every '
            f'{d["checkpoint_every"]}'
        )
    return '\n'.join(lines)


def build_parser(prog: str = 'train.py') -> argparse.ArgumentParser:
    S = argparse.SUPPRESS  # unset options stay absent: task defaults or the resumed config apply
    p = ArgumentParser(
        prog=prog,
        argument_default=S,
        description=(
            'Train a HRON policy with PPO (all seeds in one jitted program). Options left out take '
            'the per-task defaults of hron_jax.run_config.TASK_DEFAULTS, or on --resume the run\'s '
            'config.json.'
        ),
        epilog=_defaults_epilog(),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    g = p.add_argument_group('run')
    g.add_argument('--task', choices=TASKS, help=f'task (default {DEFAULT_TASK})')
    g.add_argument(
        '--preset',
        choices=tuple(PRESETS),
        help="settings applied under the other options: 'paper' = the paper release's camera "
        '(128x128), HGT softmax (per relation) and PPO (RLlib: 8 envs x 512 steps, 30 epochs, '
        'minibatch 128, lr 1e-4, KL penalty); default: the faster per-task defaults below',
    )
    g.add_argument('--model', choices=MODELS, help=f'model variant (default {DEFAULT_MODEL})')
    g.add_argument(
        '--scene',
        help='scene MJCF (default: scenes/symmetric_room.xml for directed, scenes/house.xml for exploratory)',
    )
    g.add_argument(
        '--distractors', action=argparse.BooleanOptionalAction, help='add distractor objects (default off)'
    )
    g.add_argument(
        '--premap',
        action=argparse.BooleanOptionalAction,
        help='pre-mapping: graph/map start with rooms + furniture (default off)',
    )
    g.add_argument('--num-envs', type=int, help='parallel envs per seed (default 64)')
    g.add_argument('--total-steps', type=int, help='env steps per seed (default per task)')
    g.add_argument('--seed', type=int, help='seed of the first run (default 0)')
    g.add_argument('--num-seeds', type=int, help='seeds seed..seed+N-1 trained together (default 1)')
    g.add_argument('--out', help='run directory (default runs/<task>_<model>_..._<timestamp>)')
    g.add_argument(
        '--resume',
        metavar='RUN_DIR',
        help='continue this run exactly where its last '
        'checkpoint left off (other options must match its config.json)',
    )
    g.add_argument('--log-every', type=int, help='updates per jitted chunk = per log row')
    g.add_argument('--checkpoint-every', type=int, help='updates between checkpoints')
    g.add_argument('--keep-checkpoints', type=int, help='checkpoints kept (default 3)')
    g.add_argument(
        '--env-option',
        action='append',
        metavar='NAME=VALUE',
        help='env config field (NavConfig / ChoiceConfig; dotted into sub-configs, e.g. '
        'max_steps=300, camera.width=64, or image_size=64 for a square camera); '
        'repeatable',
    )
    g.add_argument(
        '--model-option',
        action='append',
        metavar='NAME=VALUE',
        help='ModelConfig field, e.g. hidden=64 or cnn_fc=128,64,64; repeatable',
    )
    g.add_argument('--no-progress', action='store_true', help='no progress bar')
    g.add_argument(
        '--fast-compile',
        action=argparse.BooleanOptionalAction,
        help='XLA without LLVM optimisation: ~3x faster compiles, ~2.7x slower steps (tests, debugging)',
    )
    g.add_argument(
        '--compile-cache',
        metavar='DIR',
        help='persistent XLA compilation cache '
        "(default ~/.cache/hron_jax/xla or $JAX_COMPILATION_CACHE_DIR; 'none' disables)",
    )
    d = p.add_argument_group(
        'multi-host (jax.distributed: one train.py per host, the same options on each; the envs '
        'shard over the devices of all hosts)'
    )
    d.add_argument('--coordinator', metavar='HOST:PORT', help="address of process 0's coordinator service")
    d.add_argument('--num-processes', type=int, help='processes (hosts) in the job')
    d.add_argument('--process-id', type=int, help='this process, 0 .. num-processes - 1')
    d.add_argument(
        '--distributed',
        action='store_true',
        help='detect the three options above from the cluster environment (SLURM, Open MPI, '
        'Cloud TPU; see jax.distributed.initialize)',
    )
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
    h.add_argument('--max-grad-norm', type=float, help='global-norm gradient clipping (0: none)')
    h.add_argument(
        '--ppo-option',
        action='append',
        metavar='NAME=VALUE',
        help='any other PPOConfig field, e.g. kl_coeff=0.2, advantage_norm=batch; repeatable',
    )
    return p


def computes_on_gpu() -> bool:
    """Whether JAX will compute on a GPU here, decided without starting its backends (a multi-host
    run must call jax.distributed.initialize first): the first of $JAX_PLATFORMS, else whether a
    CUDA / ROCm plugin of JAX is installed (what `pip install -e ".[cuda]"` adds)."""
    import importlib.metadata
    import os

    platforms = os.environ.get('JAX_PLATFORMS', '').strip()
    if platforms:
        return platforms.split(',')[0].strip() in ('cuda', 'gpu', 'rocm')
    plugins = importlib.metadata.entry_points(group='jax_plugins')
    return any(gpu in f'{ep.name} {ep.value}' for ep in plugins for gpu in ('cuda', 'rocm'))


def tune_malloc() -> bool:
    """Keep freed memory in the process (glibc): two arenas, no mmap'd chunks, trim above 2 GiB.

    XLA:CPU takes every call's temporaries from malloc and glibc hands large blocks back to the
    OS, so each call page-faults its working set again. Measured on the 2-core VM
    (rgbd_sg_attn fwd+grad at batch 64, `python -m hron_jax.bench model`): 490 ms untuned, 323 ms
    with 1 or 2 arenas (mmap off and trim alone: 490; 4 arenas: 367). The arena count also
    serialises XLA's parallel LLVM compile: cold compile of init + the main exploratory chunk
    52-54 s untuned, 59 s with 2 arenas, 76-79 s with 1 (what this function set before). Called
    by the train / eval / bench entry points; returns False where nothing changes: no glibc, or
    JAX computes on a GPU (`computes_on_gpu`), where XLA takes no per-call memory from malloc and
    the arena limit would only serialise the compiler's threads.
    """
    import ctypes

    if computes_on_gpu():
        return False
    try:
        libc = ctypes.CDLL('libc.so.6')
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    m_trim_threshold, m_mmap_max, m_arena_max = -1, -4, -8  # glibc malloc.h
    return bool(mallopt(m_arena_max, 2) and mallopt(m_mmap_max, 0) and mallopt(m_trim_threshold, 2**31 - 1))


def setup_compile_cache(path: str | None) -> None:
    """Persistent XLA cache, so a resumed (or repeated) run does not pay the compile again."""
    import jax

    if path is None:
        path = os.environ.get('JAX_COMPILATION_CACHE_DIR') or os.path.join(CACHE_ROOT, 'xla')
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
        self._log(
            f'\n{signal.Signals(signum).name}: finishing the current chunk, then checkpointing '
            '(send it again to abort)'
        )
        for s, old in self._old.items():
            signal.signal(s, old)

    def __exit__(self, *exc):
        for s, old in self._old.items():
            signal.signal(s, old)

    def __call__(self) -> bool:
        return self.signum is not None


def main(argv=None, prog: str = 'train.py') -> int:
    from hron_jax.training import Trainer, make_mesh

    tune_malloc()
    try:
        args = vars(build_parser(prog).parse_args(argv))
    except SystemExit as e:  # --help, or a bad option (argparse has printed its one line)
        return e.code
    log = lambda s: print(s, file=sys.stderr, flush=True)
    try:
        if init_distributed(args) != 0:
            log = lambda s: None  # process 0 reports for the job
        if (
            'resume' in args
            and 'out' in args
            and os.path.abspath(args['out']) != os.path.abspath(args['resume'])
        ):
            raise UsageError('give either --out or --resume, not both')
        from hron_jax.run_dir import load_config

        base = load_config(Path(args['resume'])) if 'resume' in args else None
        config = config_from_args(args, base)
        setup_compile_cache(args.get('compile_cache'))
        import absl.logging

        absl.logging.set_verbosity(absl.logging.ERROR)  # orbax's INFO lines
        make_mesh(config.ppo.num_envs)  # device-count check before any build
        import jax

        if jax.process_count() > 1 and 'out' not in args and base is None:
            raise UsageError('a multi-host run needs --out (the same shared directory on every host)')
        run_dir = (
            Path(args['resume']) if base is not None else Path(args.get('out') or default_run_dir(config))
        )
        trainer = Trainer(
            config, run_dir, resume=base is not None, progress=not args.get('no_progress', False), log=log
        )
    except (UsageError, CheckpointError) as e:
        print(error_line(prog, e), file=sys.stderr)
        return 2 if isinstance(e, UsageError) else 1
    log(f'run dir: {run_dir}')
    with GracefulStop(log) as stop:
        try:
            trainer.run(should_stop=stop)
        except NonFiniteError as e:
            print(error_line(prog, e), file=sys.stderr)
            return 1
        finally:
            trainer.close()
    if stop.signum is not None:
        log(
            f'stopped at update {trainer.update} / {config.num_updates}; continue with: '
            f'python {prog} --resume {run_dir}'
        )
        return 128 + stop.signum
    log(f'done: {trainer.update} updates; {run_dir}')
    return 0
