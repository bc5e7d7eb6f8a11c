"""Where the reproduction's runs lie and what they hold: the run-dir layout, the archive, reading.

Layout: RUNS/<cell>/<run> is a train.py run dir (run_name: s<seed>, or s<seed>x<n> for n vmapped
seeds) with eval.py's output in EVAL_DIR (eval_argv: the command; eval_json: its eval.json),
evaluations in held-out houses beside it (held_out_dir), the random policy's evaluations under
RUNS/_reference (reference_dir) and probe runs under RUNS/_probe/<cell>. ROOT is the repository
root, where train.py and eval.py run (repo_relative: a path relative to it, for the report and messages).

The archive: the ARCHIVED files of every run, in git beside the report (archive_of(out), in the
report's own folder report_dir(out), which also holds its figures); restore_runs copies the
archived runs RUNS lacks into it (and the archived files a restored run lacks), save_runs copies
RUNS's into the archive. default_runs(out): the run dirs a report reads unless told otherwise (each
report its own, so no two mix their cells).

Reading: cell_runs(runs, cell) -> its run dirs; num_seeds_of, steps_per_second (measured env
steps/s); collect_cell(runs, cell) -> a dict of its evaluated runs' per-seed SR / SPL (mean_std:
mean, sample std, n), env steps, wall times, machines and configs in words (grid.describe_config;
per aspect as rows are compared, grid.comparable_settings), or None; seed0_dir -> the run holding
seed 0; run_summary(run_dir) -> one run's training windows and evaluations in lines of text;
config_mismatch(run_dir, wanted) -> the fields where a run's settings are not `wanted`'s.
Writes nothing but the archive and restored runs.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np

from hron_jax.paths import REPO_ROOT
from hron_jax.reproduction.grid import GRID, Cell, comparable_settings, describe_config

# ------------------------------------------------------------------------------------------------
# The layout of RUNS
# ------------------------------------------------------------------------------------------------

ROOT = Path(REPO_ROOT).resolve()


def repo_relative(p: Path) -> str:
    try:
        return Path(p).resolve().relative_to(ROOT).as_posix()
    except ValueError:
        return str(p)


def run_name(cfg) -> str:
    """A run's dir name under RUNS/<cell>/: s<seed>, or s<seed>x<seeds> for vmapped seeds."""
    return f's{cfg.seed}' + (f'x{cfg.num_seeds}' if cfg.num_seeds > 1 else '')


def reference_dir(runs: Path, policy: str, scene: str) -> Path:
    return runs / '_reference' / f'{policy}_{Path(scene).stem}'


def held_out_dir(run_dir: Path, scene: str) -> Path:
    return Path(run_dir) / f'{EVAL_DIR}_{Path(scene).stem}'


# eval.py's output dir inside a run (named explicitly: eval.py's default name has changed before).
EVAL_DIR = 'eval_trained'


def eval_argv(run_dir: Path, episodes: int, out: Path | None = None, extra=()) -> list[str]:
    """eval.py on a run dir, output to `out` (default RUN/eval_trained); extra: more options."""
    run_dir = Path(run_dir).resolve()
    return [
        'python',
        'eval.py',
        str(run_dir),
        '--episodes',
        str(episodes),
        *extra,
        '--out',
        str(out or run_dir / EVAL_DIR),
    ]


def eval_json(run_dir: Path) -> Path | None:
    """The run's eval.json (ours, else eval.py's default sampled-policy dir), or None."""
    for name in (EVAL_DIR, 'eval_trained_sampled'):
        p = Path(run_dir) / name / 'eval.json'
        if p.is_file():
            return p
    return None


# ------------------------------------------------------------------------------------------------
# The archive beside the report
# ------------------------------------------------------------------------------------------------

# The files of a run that the report reads (no checkpoints, TensorBoard or figures): the report's
# runs keep them in git beside it, so a fresh checkout (no runs/) regenerates the report and adds
# seeds to it. Units are RUNS/<cell>/<run> (and _reference/<policy_house>, _probe/<cell>).
ARCHIVED = (
    'config.json',
    'metrics.jsonl',
    'repro.json',
    'attention_summary.json',
    'eval.json',
    'eval.md',
    'processes.jsonl',
)
NOT_ARCHIVED_DIRS = ('checkpoints', 'corrupt_checkpoints', 'tb')


DEFAULT_REPORT = ROOT / 'docs' / 'reproduction.md'


def report_dir(out: Path) -> Path:
    """The folder of the report at `out`, named as it (docs/reproduction.md: docs/reproduction):
    its figures and, in runs/, its archive. Each report has its own, so a second report (other
    runs, another budget) neither overwrites the first one's figures nor mixes with its runs."""
    return Path(out).with_suffix('')


def archive_of(out: Path) -> Path:
    """Where the runs of the report at `out` are archived: report_dir(out)/runs."""
    return report_dir(out) / 'runs'


def is_main_report(out: Path) -> bool:
    """Whether `out` is docs/reproduction.md (the one whose run dirs and command keep the defaults)."""
    return Path(out).resolve() == DEFAULT_REPORT


def default_runs(out: Path) -> Path:
    """The run dirs of the report at `out`: runs/repro for docs/reproduction.md, else runs/<its
    name>. Its archive is restored into them, so two reports sharing them would mix their cells."""
    return ROOT / 'runs' / ('repro' if is_main_report(out) else Path(out).stem)


# The folders of RUNS whose sub-folders are units; anything else there (a report written inside
# RUNS with its own archive, as tools/gpu_tables.sh does) is not a run, and archiving it would nest
# the archive in itself once more at every call.
UNIT_PARENTS = frozenset(c.name for c in GRID) | {'_reference', '_probe'}


def _units(root: Path) -> list[Path]:
    root = Path(root)
    return sorted(d for d in root.glob('*/*') if d.is_dir() and d.parent.name in UNIT_PARENTS)


def restore_runs(archive: Path, runs: Path) -> list[str]:
    """Copy every archived run that RUNS does not have into RUNS, and into each run RUNS has from
    the archive (the same run: config.json and metrics.jsonl equal) the archived files it lacks, such
    as an eval archived after the run was restored (save_runs would otherwise write the copy without
    it back over the archive); returns the names of the runs copied or completed. A restored run has
    no checkpoints: it is finished and evaluated, so the runner skips it."""
    restored = []
    for unit in _units(archive):
        rel = unit.relative_to(archive)
        here = runs / rel
        if not here.exists():
            shutil.copytree(unit, here)
            restored.append(rel.as_posix())
        elif _same_run(unit, here):
            missing = [f.relative_to(unit) for f in unit.rglob('*') if f.is_file()]
            missing = [f for f in missing if not (here / f).exists()]
            for f in missing:
                (here / f).parent.mkdir(parents=True, exist_ok=True)
                shutil.copy2(unit / f, here / f)
            if missing:
                restored.append(rel.as_posix())
    return restored


def _same_run(a: Path, b: Path) -> bool:
    """Whether run dirs a and b hold the same training: config.json and metrics.jsonl equal (a run
    retrained in its place logs other metrics, wall times at least, and must not take the old
    run's evals)."""
    files = [(a / n, b / n) for n in ('config.json', 'metrics.jsonl')]
    return all(x.is_file() and y.is_file() and x.read_bytes() == y.read_bytes() for x, y in files)


def save_runs(runs: Path, archive: Path) -> None:
    """Replace the archive's copy of every run in RUNS by the run's ARCHIVED files (archived runs
    that RUNS lacks stay: delete them there to drop them from the report)."""
    for unit in _units(runs):
        files = [
            f
            for f in unit.rglob('*')
            if f.name in ARCHIVED
            and f.is_file()
            and not set(f.relative_to(unit).parts[:-1]) & set(NOT_ARCHIVED_DIRS)
        ]
        if not files:
            continue
        dest = archive / unit.relative_to(runs)
        shutil.rmtree(dest, ignore_errors=True)
        for f in files:
            target = dest / f.relative_to(unit)
            target.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(f, target)


# ------------------------------------------------------------------------------------------------
# Reading run dirs
# ------------------------------------------------------------------------------------------------


def metric_rows(run_dir: Path) -> list[dict]:
    from hron_jax.run_dir import read_metrics

    return read_metrics(run_dir)


def cell_runs(runs: Path, cell: Cell) -> list[Path]:
    """Run dirs (with config.json) under RUNS/<cell>/, sorted."""
    base = runs / cell.name
    if not base.is_dir():
        return []
    return sorted(p for p in base.iterdir() if (p / 'config.json').is_file())


def num_seeds_of(run_dir: Path) -> int:
    """How many seeds a run dir trained (its config's num_seeds; vmapped in one run)."""
    return int(json.loads((Path(run_dir) / 'config.json').read_text())['config'].get('num_seeds', 1))


def steps_per_second(run_dirs: list[Path]) -> float | None:
    """Median env steps/s (all seeds of a run together) over the logged chunks; compile excluded."""
    rates = [r['steps_per_s'] for d in run_dirs for r in metric_rows(d) if r.get('steps_per_s')]
    return float(np.median(rates)) if rates else None


def config_mismatch(run_dir: Path, wanted) -> list[str]:
    """Dotted fields (preset, env, network, ppo; budget and seed aside) where a run dir's config
    differs from `wanted`; [] = resuming it continues the same settings."""
    from hron_jax.run_config import config_diff
    from hron_jax.run_dir import load_config

    return [
        k
        for k in config_diff(load_config(run_dir), wanted)
        if (k == 'preset' or k.split('.')[0] in ('env', 'network', 'ppo')) and k != 'ppo.total_timesteps'
    ]


def collect_cell(runs: Path, cell: Cell) -> dict | None:
    """Aggregate a cell's evaluated runs: per-seed SR / SPL means, steps, wall times, configs."""
    from hron_jax.run_dir import load_config, run_machines

    seeds, steps, train_wall, proc_wall, configs, episodes, machines, loads = (
        [],
        [],
        [],
        [],
        [],
        set(),
        [],
        [],
    )
    unrecorded = 0  # runs that name no machine (made before train.py kept processes.jsonl)
    for d in cell_runs(runs, cell):
        ev = eval_json(d)
        if ev is None:
            continue
        e = json.loads(ev.read_text())
        s = e['summary']
        cfg = load_config(d)
        rows = metric_rows(d)
        run_seeds = []
        for i, (sr, spl) in enumerate(zip(s['success']['per_seed'], s['spl']['per_seed'])):
            seeds.append((cfg.seed + i, sr, spl))
            run_seeds.append(cfg.seed + i)
        episodes.add(s['episodes'])
        # Wall times per seed: a run of n vmapped seeds counts n times with its wall / n.
        n = len(run_seeds)
        if rows:
            steps.append(rows[-1]['env_steps'])
            train_wall += [rows[-1]['wall_time'] / n] * n
        side = d / 'repro.json'
        r = json.loads(side.read_text()) if side.is_file() else {}
        if r:
            proc_wall += [(r.get('train_wall_s', np.nan) + r.get('eval_wall_s', 0.0)) / n] * n
            loads += r.get('loadavg_training') or (r.get('machine') or {}).get('loadavg', [])[:1]
        # The runner's record of the machine, else train.py's own (one per process).
        found = [r['machine']] if r.get('machine') else run_machines(d)
        machines += found
        unrecorded += not found
        configs.append((run_seeds, cfg))
    if not seeds:
        return None
    sr = np.array([x[1] for x in seeds])
    spl = np.array([x[2] for x in seeds])
    # The runs' configs in words, with the seeds of each (runs of one cell may differ).
    described: dict[str, list[int]] = {}
    for run_seeds, cfg in configs:
        described.setdefault(describe_config(cfg), []).extend(run_seeds)
    return {
        'seeds': [x[0] for x in seeds],
        'sr': mean_std(sr),
        'spl': mean_std(spl),
        'sr_per_seed': sr.tolist(),
        'spl_per_seed': spl.tolist(),
        'episodes': sorted(episodes),
        'env_steps': sorted(set(steps)),
        'budgets': sorted({cfg.ppo.total_timesteps for _, cfg in configs}),
        'train_wall_s': float(np.mean(train_wall)) if train_wall else None,
        'proc_wall_s': float(np.nanmean(proc_wall)) if proc_wall else None,
        'steps_per_s': steps_per_second(cell_runs(runs, cell)),
        'configs': described,
        'settings': [comparable_settings(cfg) for _, cfg in configs],
        'machines': machines,
        'unrecorded': unrecorded,
        'loads': loads,
    }


def run_summary(run_dir: Path, window: int = 32) -> list[str]:
    """A run in lines of text, for notes and the README's prose: its length, training time and
    median env steps/s; its training metrics per window of `window` logged rows
    (metrics_log.window_means: SR and SPL of the episodes finished in training, with actions
    sampled, entropy, approx KL, clip fraction); then each evaluation under it (eval*/eval.json:
    SR and SPL, and over the successful episodes alone their SPL and mean length in steps)."""
    from hron_jax.metrics_log import window_means

    run_dir = Path(run_dir)
    rows = metric_rows(run_dir)
    if not rows:
        return [f'{run_dir}: no metrics.jsonl rows']
    last = rows[-1]
    rate = steps_per_second([run_dir])
    lines = [
        f'{run_dir}: update {last["update"]}, {last["env_steps"]:,} env steps per seed x '
        f'{last.get("seeds", 1)}, train wall {last["wall_time"] / 60:.1f} min (compile excluded), '
        f'median {rate:.0f} env steps/s'
    ]
    for w in window_means(rows, window):
        lines.append(
            f'  updates {w["first_update"]}-{w["last_update"]} (to {w["env_steps"]:,} env steps): train SR '
            f'{w["success"]:.3f} SPL {w["spl"]:.3f} over {w["episodes"]:.0f} episodes, length '
            f'{w["episode_length"]:.0f}; entropy {w["entropy"]:.2f}, approx KL {w["approx_kl"]:.3f}, '
            f'clip fraction {w["clip_frac"]:.2f}'
        )
    for path in sorted(run_dir.glob('eval*/eval.json')):
        e = json.loads(path.read_text())
        s, per = e['summary'], e['per_episode']
        success = np.ravel(per['success']).astype(bool)
        line = (
            f'  {path.parent.name}: step {e["step"]:,}, SR {s["success"]["mean"]:.3f} SPL '
            f'{s["spl"]["mean"]:.3f} over {s["seeds"]} x {s["episodes"]} episodes'
        )
        if success.any():
            spl, length = np.ravel(per['spl'])[success], np.ravel(per['episode_length'])[success]
            line += f'; its {success.sum()} successes: SPL {spl.mean():.3f}, {length.mean():.0f} steps'
        lines.append(line)
    return lines


def mean_std(x) -> tuple[float, float | None, int]:
    """(mean, sample std with ddof=1 or None for one value, n) of per-seed values."""
    x = np.asarray(x, np.float64)
    return float(x.mean()), (float(x.std(ddof=1)) if len(x) > 1 else None), len(x)


def seed0_dir(runs: Path, name: str) -> Path:
    """The run dir holding seed 0 of a cell: s0, else an evaluated run of vmapped seeds s0x<n>
    (whose seed index 0 is seed 0); s0 when neither exists."""
    base = runs / name
    for d in [base / 's0'] + sorted(base.glob('s0x*')):
        if eval_json(d) is not None:
            return d
    return base / 's0'
