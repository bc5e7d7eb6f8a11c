"""Running the grid's cells: train and evaluate them, leaving run dirs (runs.py's layout) behind.

Per seed in subprocesses (profiles cpu and paper): run_cell_seed(cell, seed, runs, profile,
episodes) trains one seed with train.py (a run short of its profile's budget is resumed; one
trained under other settings is refused: runs.config_mismatch), evaluates it with eval.py, records the
commands, wall times and machine in repro.json and evaluates the held-out houses (run_held_out).
probe: a short paper-profile run whose env steps/s the cost estimates read. run_references: the
random policy in every house of the generalisation table. Each process goes through run_logged
(argv, log) -> wall seconds. attention_figures: figures and attention_summary.json of seed 0 of
grid.ATTENTION_CELLS (hron_jax.analysis, in this process).

In process (profiles gpu and tiny): run_cells_in_process(cells, profile, runs, ...) trains each
cell as one run with the seeds vmapped and evaluates it with eval.py's code, resumable and
stoppable; returns one row (dict) per cell and prints it as it finishes. in_process_config /
in_process_argv: what it trains for a cell. JAX, the training and evaluation code are imported
inside the functions that use them.
"""

from __future__ import annotations

import json
import os
import shlex
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from hron_jax.bench import machine
from hron_jax.reproduction.grid import (
    ATTENTION_CELLS,
    EPISODES,
    GENERALISATION_MODELS,
    HELD_OUT,
    PROFILE_EPISODES,
    TRAIN_HOUSE,
    Cell,
    profile_config,
    profile_steps,
    train_argv,
)
from hron_jax.reproduction.runs import (
    EVAL_DIR,
    ROOT,
    config_mismatch,
    eval_argv,
    eval_json,
    held_out_dir,
    metric_rows,
    reference_dir,
    repo_relative,
    run_name,
    seed0_dir,
    steps_per_second,
)

# ------------------------------------------------------------------------------------------------
# Running train.py / eval.py processes (profiles cpu and paper; probes; reference policies)
# ------------------------------------------------------------------------------------------------


def run_logged(argv: list[str], log: Path) -> float:
    """Run argv (python -> this interpreter) in the repo root, output to `log`; wall seconds."""
    argv = [sys.executable if a == 'python' else a for a in argv[:1]] + argv[1:]
    env = dict(os.environ)
    env.setdefault('JAX_PLATFORMS', 'cpu')
    env['PYTHONPATH'] = str(ROOT) + (os.pathsep + env['PYTHONPATH'] if env.get('PYTHONPATH') else '')
    t = time.perf_counter()
    with open(log, 'w') as f:
        p = subprocess.run(argv, cwd=ROOT, stdout=f, stderr=subprocess.STDOUT, env=env)
    if p.returncode:
        raise SystemExit(f'{shlex.join(argv)} failed ({p.returncode}); see {log}')
    return time.perf_counter() - t


def run_cell_seed(cell: Cell, seed: int, runs: Path, profile: str, episodes: int) -> None:
    out = runs / cell.name / f's{seed}'
    budget = profile_steps(profile, cell.task)
    if (out / 'config.json').is_file():
        differ = config_mismatch(out, profile_config(profile, cell))
        if differ:
            raise SystemExit(
                f'{out} was trained with other settings than profile {profile!r} ({", ".join(differ)}); '
                'resuming it would mix them: use another --runs directory or the profile it ran'
            )
    trained = metric_rows(out)[-1]['env_steps'] if (out / 'config.json').is_file() and metric_rows(out) else 0
    if eval_json(out) is not None and trained >= budget:
        print(f'{cell.name} s{seed}: done already', flush=True)
        return
    if trained and not (out / 'checkpoints').is_dir():
        raise SystemExit(
            f'{out}: trained {trained:,} of {budget:,} env steps but has no checkpoints to resume '
            f'from (restored from the archive?); delete it (and its copy in the archive) to retrain it'
        )
    out.parent.mkdir(parents=True, exist_ok=True)
    mach = machine()
    targv = train_argv(cell, seed, out, profile)
    previous = json.loads((out / 'repro.json').read_text()) if (out / 'repro.json').is_file() else {}
    if (out / 'config.json').is_file():  # interrupted, or shorter than the budget: continue
        targv = ['python', 'train.py', '--resume', str(out), '--total-steps', str(budget), '--no-progress']
        for scene in HELD_OUT:  # evaluations of the shorter run are stale
            shutil.rmtree(held_out_dir(out, scene), ignore_errors=True)
    print(f'{cell.name} s{seed}: {shlex.join(targv)}', flush=True)
    t_train = run_logged(targv, out.parent / f's{seed}.train.log')
    load_end = os.getloadavg()[0]
    eargv = eval_argv(out, episodes)
    t_eval = run_logged(eargv, out.parent / f's{seed}.eval.log')
    write_json_file(
        out / 'repro.json',
        dict(
            train_argv=targv,
            eval_argv=eargv,
            train_wall_s=t_train + previous.get('train_wall_s', 0.0),
            eval_wall_s=t_eval,
            profile=profile,
            machine=mach,
            loadavg_training=[mach.get('loadavg', [load_end])[0], load_end],
            finished=time.strftime('%Y-%m-%d %H:%M:%S'),
        ),
    )
    print(f'{cell.name} s{seed}: train {t_train:.0f} s, eval {t_eval:.0f} s', flush=True)
    run_held_out(cell, out, episodes)


def run_held_out(cell: Cell, run_dir: Path, episodes: int) -> None:
    """Evaluate an exploratory main-model run on the houses it was not trained on."""
    if cell.task != 'exploratory' or cell.model not in GENERALISATION_MODELS:
        return
    for scene in HELD_OUT:
        out = held_out_dir(run_dir, scene)
        if (out / 'eval.json').is_file():
            continue
        argv = eval_argv(run_dir, episodes, out, extra=('--scene', str(ROOT / scene)))
        t = run_logged(argv, run_dir.parent / f'{run_dir.name}.eval_{Path(scene).stem}.log')
        print(f'{cell.name} {run_dir.name} on {scene}: eval {t:.0f} s', flush=True)


def probe(cell: Cell, runs: Path, updates: int = 1) -> None:
    """A short run of a cell with the paper profile (`--preset paper`, a few updates) to measure
    env steps/s."""
    out = runs / '_probe' / cell.name
    if (out / 'config.json').is_file():
        print(f'probe {cell.name}: exists ({out})')
        return
    steps = profile_config('paper', cell).ppo.batch_size * updates
    argv = train_argv(cell, 0, out, 'paper', extra=['--log-every', '1'], total_steps=steps)
    out.parent.mkdir(parents=True, exist_ok=True)
    mach = machine()
    wall = run_logged(argv, out.parent / f'{cell.name}.log')
    # The load average matters on a shared machine (measured: 17 vs 43 exploratory steps/s at load
    # ~7 vs ~1), so it is kept with the measurement.
    write_json_file(
        out / 'repro.json',
        dict(
            train_argv=argv,
            train_wall_s=wall,
            machine=mach,
            loadavg_end=[round(x, 2) for x in os.getloadavg()],
        ),
    )
    print(f'probe {cell.name}: {steps_per_second([out])} steps/s, process {wall:.0f} s', flush=True)


def run_references(runs: Path, episodes: int = 20) -> None:
    """Random-policy SR / SPL in every house of the generalisation table (its chance level: the
    houses differ in size and goal sets, so raw SRs across houses are not comparable alone)."""
    for scene in (TRAIN_HOUSE,) + HELD_OUT:
        out = reference_dir(runs, 'random', scene)
        if (out / 'eval.json').is_file():
            continue
        out.mkdir(parents=True, exist_ok=True)
        argv = [
            'python',
            'eval.py',
            '--policy',
            'random',
            '--task',
            'exploratory',
            '--scene',
            str(ROOT / scene),
            '--episodes',
            str(episodes),
            '--plots',
            '0',
            '--out',
            str(out),
        ]
        t = run_logged(argv, out.parent / f'random_{Path(scene).stem}.log')
        print(f'random policy on {scene}: eval {t:.0f} s', flush=True)


# ------------------------------------------------------------------------------------------------
# Attention figures of trained runs (--attention)
# ------------------------------------------------------------------------------------------------


def attention_figures(runs: Path, figdir: Path, episodes: int = 8, max_steps: int = 300) -> None:
    """Figures and attention_summary.json of seed 0 of each of ATTENTION_CELLS (hron_jax.analysis,
    as the notebook draws them): `episodes` sampled episodes without and with distractors."""
    import matplotlib

    matplotlib.use('Agg')
    from hron_jax import analysis as A

    for name in ATTENTION_CELLS:
        run_dir = seed0_dir(runs, name)
        if eval_json(run_dir) is None:
            print(f'attention: {name} has no evaluated seed 0; skipped', flush=True)
            continue
        if not (run_dir / 'checkpoints').is_dir():
            print(f'attention: {run_dir} has no checkpoints (an archived run); kept as is', flush=True)
            continue
        t = time.perf_counter()
        run = A.load_run(run_dir)
        recs = {
            label: A.collect(
                run, episodes=episodes, max_steps=max_steps, env=run.env_variant(distractors=dist)
            )
            for label, dist in (('no distractors', False), ('distractors', True))
        }
        rec = recs['distractors' if run.config.distractors else 'no distractors']
        ep = int(np.argmax(rec.success)) if rec.success.any() else 0
        figdir.mkdir(parents=True, exist_ok=True)
        for kind, fig in (
            ('graph_on_map', A.plot_graph_on_map(rec, episode=ep)),
            ('edge_types', A.plot_edge_type_attention(rec, title=f'{name}: attention mass per edge type')),
            (
                'goal_concentration',
                A.plot_goal_concentration(recs, title=f'{name}: goal-category nodes vs others'),
            ),
        ):
            fig.savefig(figdir / f'{name}_{kind}.png', dpi=90, bbox_inches='tight')
        summary = {label: A.summary(r) for label, r in recs.items()}
        write_json_file(
            run_dir / 'attention_summary.json',
            dict(
                run_dir=repo_relative(run_dir),
                step=run.step,
                episodes=episodes,
                max_steps=max_steps,
                summary=summary,
            ),
        )
        print(f'attention: {name} in {time.perf_counter() - t:.0f} s', flush=True)


# ------------------------------------------------------------------------------------------------
# In-process runner (profiles gpu and tiny): one process trains and evaluates the cells
# ------------------------------------------------------------------------------------------------

# JAX's compile-time events (tracing, lowering to MLIR, XLA compilation): their durations are
# summed by a listener, so the seconds a cell spent compiling are measured, not estimated.
_COMPILE_EVENTS = (
    '/jax/core/compile/jaxpr_trace_duration',
    '/jax/core/compile/jaxpr_to_mlir_module_duration',
    '/jax/core/compile/backend_compile_duration',
)
_compile_total = [0.0]
_listening = [False]


def compile_seconds() -> float:
    """Seconds this process has spent tracing, lowering and compiling JAX programs so far."""
    if not _listening[0]:
        from jax import monitoring

        def listen(name, secs, **_):
            if name in _COMPILE_EVENTS:
                _compile_total[0] += secs

        monitoring.register_event_duration_secs_listener(listen)
        _listening[0] = True
    return _compile_total[0]


def programs_built() -> int:
    """Training programs built in this process so far (misses of hron_jax.training's cache)."""
    from hron_jax import training

    return training._programs.cache_info().misses


def in_process_config(profile: str, cell: Cell, seeds: int | None = None, total_steps: int | None = None):
    """The TrainConfig of a cell under an in-process profile (`seeds` / `total_steps` override the
    profile's num_seeds / budget)."""
    from hron_jax.cli import build_parser, config_from_args

    args = build_parser().parse_args(in_process_argv(profile, cell, Path('run'), seeds, total_steps)[2:])
    return config_from_args(vars(args))


def in_process_argv(profile: str, cell: Cell, out: Path, seeds=None, total_steps=None) -> list[str]:
    """The train.py command that trains what run_cells_in_process trains for a cell."""
    base = profile_config(profile, cell)
    extra = ['--num-seeds', str(seeds)] if seeds and seeds != base.num_seeds else []
    extra += ['--total-steps', str(total_steps)] if total_steps else []
    return train_argv(cell, 0, out, profile, extra=extra)


def _log_to(path: Path):
    def log(text: str) -> None:
        with open(path, 'a') as f:
            f.write(text + '\n')

    return log


def evaluate_in_process(run_dir: Path, episodes: int, log: Path, out: Path | None = None, extra=()) -> float:
    """eval.py's main on a run in this process (the same protocol and files: eval.md, eval.json
    with the per-seed summary, trajectories.png), its output to `log`; wall seconds."""
    import contextlib

    from hron_jax import evaluation

    argv = eval_argv(run_dir, episodes, out, extra)[2:]
    t = time.perf_counter()
    with open(log, 'a') as f, contextlib.redirect_stdout(f), contextlib.redirect_stderr(f):
        rc = evaluation.main(argv)
    if rc:
        raise SystemExit(f'eval.py {shlex.join(argv)} failed ({rc}) in process; see {log}')
    return time.perf_counter() - t


def _row_text(r: dict) -> str:
    """One printed row of run_cells_in_process."""
    if r['status'] in ('done already', 'not started'):
        return f"{r['cell']:32s} {r['run']:6s} {r['status']}"
    steps = f"{r['steps_from']:,}->{r['env_steps']:,}"
    prog = 'reused' if not r['programs_built'] else 'built'
    return (
        f"{r['cell']:32s} {r['run']:6s} {steps:>20s} compile {r['compile_s']:7.1f} s ({prog}) "
        f"train {r['train_s']:7.1f} s  eval {r['eval_s']:6.1f} s (compile {r['eval_compile_s']:5.1f}) "
        f" {r['steps_per_s']:8.0f} env steps/s  {r['status']}"
    )


IN_PROCESS_HEAD = (
    f"{'cell':32s} {'run':6s} {'env steps / seed':>20s} compile s (program)   train s (loop)  "
    'eval s (incl. its compile)  steps/s (all seeds)  status'
)


def run_cells_in_process(
    cells: list[Cell],
    profile: str,
    runs: Path,
    *,
    seeds: int | None = None,
    episodes: int | None = None,
    total_steps: int | None = None,
    max_updates: int | None = None,
    should_stop=None,
    compile_cache: str | None = None,
    plots: int | None = None,
    print_row=lambda s: print(s, flush=True),
) -> list[dict]:
    """Train and evaluate `cells` in this process, one run per cell with the seeds vmapped
    (RUNS/<cell>/s0x<seeds>), printing one row per cell as soon as it is done: compile seconds
    (tracing + XLA of the training programs; ~0 when hron_jax.training's in-process cache had the
    program), training-loop seconds, evaluation seconds (eval.py's protocol and files, its compile
    included) and env steps/s. Returns the rows (dicts).

    Resumable: a cell whose run has its budget and an eval.json is skipped; an interrupted one
    (config.json and checkpoints) resumes from its last checkpoint; a run at a smaller budget is
    extended and evaluated again. `max_updates`: at most that many PPO updates per cell in this
    call; `should_stop()` (a signal, a deadline) is checked after every chunk of updates and between
    cells: training checkpoints and the remaining cells wait for the next call."""
    import absl.logging

    from hron_jax.cli import setup_compile_cache
    from hron_jax.run_config import RESUMABLE, config_diff
    from hron_jax.run_dir import load_config
    from hron_jax.training import Trainer

    setup_compile_cache(compile_cache)
    absl.logging.set_verbosity(absl.logging.ERROR)  # orbax's INFO lines
    stop = should_stop or (lambda: False)
    cache = ['--compile-cache', compile_cache] if compile_cache else []
    plots = (1 if profile == 'tiny' else 4) if plots is None else plots
    compile_seconds()  # start listening
    rows = []
    print_row(f'profile {profile}, runs {runs}')
    print_row(IN_PROCESS_HEAD)
    for cell in cells:
        cfg = in_process_config(profile, cell, seeds, total_steps)
        run_dir = runs / cell.name / run_name(cfg)
        n_eps = episodes or PROFILE_EPISODES.get(profile, EPISODES)[cell.task]
        row = dict(cell=cell.name, run=run_name(cfg), profile=profile, seeds=cfg.num_seeds)
        budget = cfg.ppo.total_timesteps
        exists = (run_dir / 'config.json').is_file()
        if exists:
            differ = [k for k in config_diff(load_config(run_dir), cfg) if k not in RESUMABLE]
            if differ:
                raise SystemExit(
                    f'{run_dir} was trained with other settings than profile {profile!r} '
                    f'({", ".join(differ)}); resuming it would mix them: use another --runs directory'
                )
        logged = metric_rows(run_dir) if exists else []
        trained = logged[-1]["env_steps"] if logged else 0
        if trained >= budget and eval_json(run_dir) is not None:
            rows.append(dict(row, status='done already', env_steps=trained))
            print_row(_row_text(rows[-1]))
            continue
        if stop():
            rows.append(dict(row, status='not started', env_steps=trained))
            print_row(_row_text(rows[-1]))
            continue
        run_dir.parent.mkdir(parents=True, exist_ok=True)
        side = run_dir / 'repro.json'
        previous = json.loads(side.read_text()) if side.is_file() else {}
        mach = machine()
        c0, p0, t0 = compile_seconds(), programs_built(), time.perf_counter()
        train_s = 0.0
        if trained < budget:
            resume = exists and (run_dir / 'checkpoints').is_dir()
            if resume:  # interrupted, or shorter than the budget: continue; its evals are stale
                for d in [run_dir / EVAL_DIR] + [held_out_dir(run_dir, s) for s in HELD_OUT]:
                    shutil.rmtree(d, ignore_errors=True)
            elif exists:  # config.json without a checkpoint: a run killed before its first save
                shutil.rmtree(run_dir)
            log = _log_to(run_dir.parent / f'{run_dir.name}.train.log')
            trainer = Trainer(cfg, run_dir, resume=resume, progress=False, log=log)
            wall0 = trainer.metrics.wall_time
            try:
                trainer.run(max_updates=max_updates, should_stop=stop)
            finally:
                trainer.close()
            train_s = trainer.metrics.wall_time - wall0
            trained = trainer.update * cfg.ppo.batch_size  # env steps per seed
            del trainer  # its RunnerState (device memory) before the next cell's
        compile_s = compile_seconds() - c0
        train_wall = time.perf_counter() - t0
        steps_from = logged[-1]["env_steps"] if logged else 0
        row.update(
            steps_from=steps_from,
            env_steps=trained,
            compile_s=compile_s,
            train_s=train_s,
            programs_built=programs_built() - p0,
            steps_per_s=(trained - steps_from) * cfg.num_seeds / train_s if train_s > 0 else float('nan'),
            eval_s=0.0,
            eval_compile_s=0.0,
        )
        record = dict(
            runner='in-process',
            profile=profile,
            machine=mach,
            train_wall_s=train_wall + previous.get('train_wall_s', 0.0),
            compile_s=compile_s + previous.get('compile_s', 0.0),
            train_s=train_s + previous.get('train_s', 0.0),
            loadavg_training=[mach.get('loadavg', [0.0])[0], os.getloadavg()[0]],
        )
        if trained < budget or stop():  # stopped (max_updates, a signal, the deadline)
            write_json_file(side, record)
            status = f'stopped at {trained:,} of {budget:,}' if trained < budget else 'trained'
            rows.append(dict(row, status=status + '; evaluated next time'))
            print_row(_row_text(rows[-1]))
            continue
        c1 = compile_seconds()
        elog = run_dir.parent / f'{run_dir.name}.eval.log'
        eval_s = evaluate_in_process(run_dir, n_eps, elog, extra=cache + ['--plots', str(plots)])
        held = 0.0
        if cell.task == 'exploratory' and cell.model in GENERALISATION_MODELS:
            for scene in HELD_OUT:
                held += evaluate_in_process(
                    run_dir,
                    n_eps,
                    elog,
                    held_out_dir(run_dir, scene),
                    extra=cache + ['--plots', '0', '--scene', str(ROOT / scene)],
                )
        row.update(eval_s=eval_s + held, eval_compile_s=compile_seconds() - c1, status='evaluated')
        record.update(
            eval_wall_s=eval_s,
            eval_compile_s=row['eval_compile_s'],
            held_out_eval_s=held,
            episodes=n_eps,
            finished=time.strftime('%Y-%m-%d %H:%M:%S'),
        )
        write_json_file(side, record)
        rows.append(row)
        print_row(_row_text(row))
    done = [r for r in rows if 'compile_s' in r]
    if done:
        print_row(
            f'total: compile {sum(r["compile_s"] for r in done):.1f} s, train '
            f'{sum(r["train_s"] for r in done):.1f} s, eval {sum(r["eval_s"] for r in done):.1f} s; '
            f'{sum(r["programs_built"] for r in done)} training program(s) built for {len(done)} cell(s)'
        )
    return rows


def write_json_file(path: Path, obj) -> None:
    """run_dir.write_json (atomic, indented), imported here: run_dir imports JAX, and --plan runs
    without it."""
    from hron_jax.run_dir import write_json

    write_json(path, obj)
