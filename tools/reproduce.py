"""Reproduce the paper's Tables I-III: train + evaluate the experiment grid, write docs/reproduction.md.

    python tools/reproduce.py --plan                       # print the grid, commands, estimated cost
    python tools/reproduce.py --tables 1                   # train + eval what is missing, then report
    python tools/reproduce.py --from-runs                  # report only, from existing run dirs
    python tools/reproduce.py --probe directed_rgbd_sg_attn  # short run to measure env steps/s
    python tools/reproduce.py --summary RUN [RUN ...]      # a run's training windows and evaluations

The command line only: build_parser() and main(argv) -> exit status. What each option does lives in
hron_jax.reproduction (its docstring: the grid, the runs and their archive, the profiles, the
report's statistics): grid (cells, profiles), runs (run dirs, archive), report (write_report,
estimate) and runner (run_cell_seed, probe, run_cells_in_process, attention_figures).
"""

from __future__ import annotations

import argparse
import re
import shlex
import sys
import time
from pathlib import Path

# Run as a script from any directory: the checkout this file is in provides hron_jax.
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from hron_jax.reproduction.grid import (  # noqa: E402
    EPISODES,
    GRID,
    IN_PROCESS,
    PROFILE_EPISODES,
    PROFILE_TEXT,
    PROFILES,
    describe_config,
    main_cell,
    profile_config,
    train_argv,
)
from hron_jax.reproduction.report import estimate, fmt_duration, write_report  # noqa: E402
from hron_jax.reproduction.runner import (  # noqa: E402
    attention_figures,
    in_process_argv,
    in_process_config,
    probe,
    run_cell_seed,
    run_cells_in_process,
    run_references,
)
from hron_jax.reproduction.runs import (  # noqa: E402
    DEFAULT_REPORT,
    archive_of,
    cell_runs,
    default_runs,
    eval_argv,
    eval_json,
    num_seeds_of,
    repo_relative,
    restore_runs,
    run_name,
    run_summary,
)


def plan_total(costs: list[float | None]) -> str:
    """The last line of `--plan`, from the training seconds of each cell left to train (None: no
    estimate): the total over the cells that have one, and how many have none."""
    if not costs:
        return 'nothing left to train'
    measured = [sec for sec in costs if sec is not None]
    unmeasured = len(costs) - len(measured)
    parts = [f'{fmt_duration(sum(measured))} for {len(measured)} cell(s) left to train'] if measured else []
    if unmeasured:
        parts.append(f'{unmeasured} cell(s) left to train not measured')
    return 'estimated training time: ' + '; '.join(parts) + ' (compilation and evaluation excluded)'


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        description=__doc__.splitlines()[0], formatter_class=argparse.ArgumentDefaultsHelpFormatter
    )
    p.add_argument('--plan', action='store_true', help='print the grid and commands, run nothing')
    p.add_argument('--from-runs', action='store_true', help='only write the report from existing runs')
    p.add_argument(
        '--attention',
        action='store_true',
        help='draw the attention figures of the trained main models and evaluate the random '
        'policy in each house of the generalisation table, then the report',
    )
    p.add_argument('--probe', nargs='+', metavar='CELL', help='measure steps/s of these cells (short runs)')
    p.add_argument(
        '--summary',
        nargs='+',
        metavar='RUN',
        help="print these run dirs' training (SR, SPL, entropy, KL per 32 updates) and evaluations; "
        'run nothing',
    )
    p.add_argument('--tables', type=int, nargs='+', default=[1, 2, 3], choices=[1, 2, 3])
    p.add_argument('--cells', help='regex on cell names (e.g. "choice_.*_dist")')
    p.add_argument(
        '--profile',
        choices=tuple(PROFILES),
        default='cpu',
        help='; '.join(f'{k}: {v}' for k, v in PROFILE_TEXT.items()),
    )
    p.add_argument(
        '--seeds',
        type=int,
        default=None,
        help='seeds per cell (default 3; in-process profiles: their num_seeds, gpu 3, tiny 2)',
    )
    p.add_argument(
        '--episodes',
        type=int,
        default=None,
        help='eval episodes per seed (default: 200 for choice, the paper\'s 20 for navigation)',
    )
    p.add_argument(
        '--runs',
        help='run dirs of the report (default: runs/repro for docs/reproduction.md, else runs/<name '
        "of --out>: another report's archive is restored into runs of its own, not mixed with these)",
    )
    p.add_argument(
        '--out',
        default=str(DEFAULT_REPORT),
        help='the report; its figures and run archive go in the folder of its name (docs/reproduction/)',
    )
    g = p.add_argument_group(f'in-process profiles ({", ".join(IN_PROCESS)})')
    g.add_argument(
        '--total-steps',
        type=int,
        help="env steps per seed instead of the profile's budget (e.g. a short GPU lease; a run "
        'at a smaller budget is extended later)',
    )
    g.add_argument(
        '--max-updates', type=int, help='at most this many PPO updates per cell in this call (then resume)'
    )
    g.add_argument(
        '--budget-s',
        type=float,
        help='stop training (checkpointed) and leave the remaining cells after this many seconds',
    )
    g.add_argument(
        '--compile-cache',
        metavar='DIR',
        help="persistent XLA cache (default as train.py; 'none' disables)",
    )
    return p


def main(argv=None) -> int:
    p = build_parser()
    a = p.parse_args(argv)
    if a.summary:
        for run in a.summary:
            print('\n'.join(run_summary(Path(run))))
        return 0
    out = Path(a.out)
    runs = Path(a.runs) if a.runs else default_runs(out)
    in_process = a.profile in IN_PROCESS
    if a.seeds is None:
        a.seeds = profile_config(a.profile, main_cell('choice')).num_seeds if in_process else 3
    cells = [c for c in GRID if c.table in a.tables and (not a.cells or re.search(a.cells, c.name))]
    if not (a.plan or a.probe):  # --plan reads the archive where it is; the probe writes its own short runs
        restored = restore_runs(archive_of(out), runs)
        if restored:
            print(
                f'restored {len(restored)} archived runs (or their files a copy lacked) into {runs} '
                f'(from {repo_relative(archive_of(out))})'
            )
    if a.probe:
        by_name = {c.name: c for c in GRID}
        for name in a.probe:
            if name not in by_name:
                p.error(f'unknown cell {name!r}; cells: {", ".join(by_name)}')
            probe(by_name[name], runs)
        return 0
    if a.plan:
        print(f'profile {a.profile}: {PROFILE_TEXT[a.profile]}')
        archive, costs = archive_of(out), []  # costs: training seconds (or None) of each cell left to train
        for c in cells:
            done = {d.name: d for root in (archive, runs) for d in cell_runs(root, c) if eval_json(d)}
            n_done = sum(map(num_seeds_of, done.values()))
            prof = a.profile if PROFILES[a.profile][c.task] is not None else 'paper'
            to_train = max(a.seeds - n_done, 0)
            todo = 'nothing to train'
            if to_train:
                est, sec = estimate(c, runs, to_train, prof, archive)
                costs.append(sec)
                todo = f'{to_train} to train: {est}'
            print(f'[Table {c.table}] {c.name:34s} {n_done}/{a.seeds} seeds evaluated; {todo}')
            if in_process:  # one run, the seeds vmapped; this process runs what these commands do
                cfg = in_process_config(prof, c, a.seeds, a.total_steps)
                print(f'    settings ({prof}): {describe_config(cfg)}')
                d = runs / c.name / run_name(cfg)
                print(
                    '    in process, as: '
                    + shlex.join(in_process_argv(prof, c, d, a.seeds, a.total_steps))
                    + ' && '
                    + shlex.join(eval_argv(d, a.episodes or PROFILE_EPISODES.get(prof, EPISODES)[c.task]))
                )
                continue
            print(f'    settings ({prof}): {describe_config(profile_config(prof, c))}')
            for s in range(a.seeds):
                d = runs / c.name / f's{s}'
                print(
                    '    '
                    + shlex.join(train_argv(c, s, d, prof))
                    + ' && '
                    + shlex.join(eval_argv(d, a.episodes or EPISODES[c.task]))
                )
        print(plan_total(costs))
        return 0
    if a.attention:
        attention_figures(runs, out.parent / 'reproduction')
        run_references(runs)
    elif in_process and not a.from_runs:
        from hron_jax.cli import GracefulStop, tune_malloc

        tune_malloc()
        deadline = time.monotonic() + a.budget_s if a.budget_s else None
        with GracefulStop(lambda s: print(s, flush=True)) as signal_stop:
            run_cells_in_process(
                cells,
                a.profile,
                runs,
                seeds=a.seeds,
                episodes=a.episodes,
                total_steps=a.total_steps,
                max_updates=a.max_updates,
                should_stop=lambda: signal_stop() or (deadline is not None and time.monotonic() > deadline),
                compile_cache=a.compile_cache,
            )
        write_report(runs, out, a.seeds)
        print(f'wrote {out}')
        return 128 + signal_stop.signum if signal_stop.signum else 0
    elif not a.from_runs:
        for s in range(a.seeds):  # seed-major: every cell gets a first seed early
            for c in cells:
                if PROFILES[a.profile][c.task] is None:
                    print(f'{c.name}: not in profile {a.profile!r}; skipped (use --profile paper)')
                    continue
                run_cell_seed(c, s, runs, a.profile, a.episodes or EPISODES[c.task])
    write_report(runs, out, a.seeds)
    print(f'wrote {out}')
    return 0


if __name__ == '__main__':
    sys.exit(main())
