"""The report (docs/reproduction.md): the paper's tables with our numbers, read from run dirs only.

write_report(runs, out, seeds) -> the Markdown it writes to `out`: the machine and protocol, per
table the rows (the paper's SR / SPL beside ours: _pm, _ours, config_text; a cell's numbers from
runs.collect_cell), the per-seed values, table_comparison (rows that ran different settings; the
models' order against the paper's), grid.notes, the learning curves (plot_curves: a PNG in the
report's folder, runs.report_dir) and, for cells and seeds without runs, their commands
(runs_profile: the settings of the table's runs) and estimated cost (a table without any run: one
line); then generalisation_section (when Table III has runs) and attention_section (what the
runner's held-out, reference and attention runs left in the run dirs). It archives the runs it read
(runs.save_runs). estimate(cell, ...) -> (text, seconds) of training a cell's seeds from measured
env steps/s (also printed by --plan).
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from hron_jax.bench import machine
from hron_jax.reproduction.grid import (
    ATTENTION_CELLS,
    EPISODES,
    GENERALISATION_MODELS,
    GRID,
    HELD_OUT,
    IN_PROCESS,
    PAPER_STEPS,
    PROFILES,
    TABLE_TITLES,
    TRAIN_HOUSE,
    Cell,
    main_cell,
    notes,
    ordering_sentence,
    profile_config,
    profile_steps,
    settings,
    settings_text,
    train_argv,
)
from hron_jax.reproduction.runs import (
    EVAL_DIR,
    archive_of,
    cell_runs,
    collect_cell,
    config_mismatch,
    eval_json,
    held_out_dir,
    is_main_report,
    metric_rows,
    num_seeds_of,
    reference_dir,
    repo_relative,
    report_dir,
    save_runs,
    seed0_dir,
    steps_per_second,
)

# ------------------------------------------------------------------------------------------------
# Numbers and settings as the tables print them
# ------------------------------------------------------------------------------------------------


def config_text(f: dict) -> str:
    """A row's Config cell: its runs' config in words; seeds that ran different configs say so."""
    if len(f['configs']) == 1:
        return next(iter(f['configs']))
    return 'seeds ran different configs: ' + ' / '.join(
        f"seed{'s' if len(sd) > 1 else ''} {', '.join(map(str, sorted(sd)))}: {text}"
        for text, sd in f['configs'].items()
    )


def _pm(x, digits=3):
    if x is None:
        return '-'
    if 0 < abs(x[0]) < 0.1:  # the paper's Yang et al. SPL 0.0302 ± 0.0013 keeps its digits
        digits += 1
    return f'{x[0]:.{digits}f} ± {x[1]:.{digits}f}'


def _ours(x, digits=3) -> str:
    """Our mean ± sample std (ddof=1) over seeds with n beside it, e.g. '0.900 ± 0.071 (n=2)';
    one seed: the mean and n=1, no spread (± 0 would claim one)."""
    mean, std, n = x
    if std is None:
        return f'{mean:.{digits}f} (n={n}, no spread)'
    return f'{mean:.{digits}f} ± {std:.{digits}f} (n={n})'


def fmt_duration(s):
    if s is None or not np.isfinite(s):
        return '-'
    return f'{s / 3600:.1f} h' if s >= 3600 else (f'{s / 60:.1f} min' if s >= 60 else f'{s:.0f} s')


# ------------------------------------------------------------------------------------------------
# Training cost of cells without runs, from measured env steps/s
# ------------------------------------------------------------------------------------------------


def estimate(
    cell: Cell, runs: Path, seeds: int, profile: str, archive: Path | None = None, steps: int | None = None
) -> tuple[str, float | None]:
    """(text, seconds): training cost of `seeds` seeds of a cell (`steps` env steps each, by default
    the profile's budget) from measured env steps/s, from the first source that has a measurement:
    its own runs (in RUNS, else in `archive`, which --plan reads without restoring it), its --probe,
    then (flagged as a proxy) the runs and the probe of the same model on the same task in another
    distractor / premap setting, then of the main model on the same task (closest setting first: the
    model sets the cost, graph-free RGB-D only trains ~3x faster), then the exploratory main model's
    probe."""
    proxies = sorted(
        (c for c in GRID if c.task == cell.task and c.model in (cell.model, 'rgbd_sg_attn') and c != cell),
        key=lambda c: (c.model != cell.model, c.distractors != cell.distractors, c.premap != cell.premap),
    )
    sources = [(cell, 'runs', 'its runs'), (cell, 'probe', '--probe')]
    sources += [(m, kind, f'proxy: {kind} of {m.name}') for m in proxies for kind in ('runs', 'probe')]
    sources.append(
        (
            next(c for c in GRID if c.name == 'exploratory_rgbd_sg_attn'),
            'probe',
            'proxy: probe of exploratory_rgbd_sg_attn',
        )
    )
    rate = src = None
    for c, kind, what in sources:
        probe = runs / '_probe' / c.name
        if kind == 'runs':
            dirs = cell_runs(runs, c) or (cell_runs(archive, c) if archive else [])
        else:
            dirs = [probe] * (probe / 'config.json').is_file()
        rate, src = steps_per_second(dirs), what
        if rate is not None:
            side = probe / 'repro.json'
            load = (
                json.loads(side.read_text()).get('machine', {}).get('loadavg')
                if kind == 'probe' and side.is_file()
                else None
            )
            if load:
                src += f', load average {load[0]:.1f}'
            src += _settings_mismatch(dirs[0], profile_config(profile, cell))
            break
    if rate is None:
        return 'not measured', None
    steps = steps or profile_steps(profile, cell.task)
    sec = seeds * steps / rate
    return f'{rate:.0f} env steps/s ({src}) -> {fmt_duration(sec)}', sec


def _settings_mismatch(run_dir: Path, target) -> str:
    """'' when a measured run trained with the preset / camera / physics / PPO of the config to be estimated,
    else a flag naming what differs (the cost per env step depends on them)."""
    from hron_jax.run_dir import load_config

    cfg = load_config(run_dir)
    got, want = settings(cfg), settings(target)
    diff = [k for k in ('preset', 'camera', 'physics', 'ppo') if k in got and got[k] != want.get(k, got[k])]
    if not diff:
        return ''
    names = {'preset': 'preset', 'camera': 'camera', 'physics': 'physics', 'ppo': 'PPO'}
    return (
        f'; measured with preset {cfg.preset}: its {" / ".join(names[k] for k in diff)} settings '
        f"differ from the estimate's, {ROUGH}"
    )


ROUGH = 'a rough figure'


def runs_profile(runs: Path, done: list[tuple[Cell, dict]]) -> tuple[str, int | None] | None:
    """(profile, budget) whose train.py commands give the settings (preset, env, network, PPO:
    runs.config_mismatch) that every run of a table's done cells ran, so that its missing cells are
    run as its rows were: a profile run per seed, and the runs' budget where they share one that is
    not the profile's (else None; the full-budget report: profile cpu at 1,500,000 env steps). None
    when no profile matches them all."""
    ran = [(c, d) for c, _ in done for d in cell_runs(runs, c)]
    for profile in (p for p in PROFILES if p not in IN_PROCESS):
        if ran and not any(config_mismatch(d, profile_config(profile, c)) for c, d in ran):
            budgets = {b for _, f in done for b in f['budgets']}
            budget = budgets.pop() if len(budgets) == 1 else None
            return profile, None if budget == profile_steps(profile, done[0][0].task) else budget
    return None


# ------------------------------------------------------------------------------------------------
# Sections of the report
# ------------------------------------------------------------------------------------------------


def plot_curves(runs: Path, cells: list[Cell], path: Path, title: str) -> bool:
    from hron_jax.metrics_log import curve_rows, plot_learning_curves

    curves = {}
    for c in cells:
        dirs = cell_runs(runs, c)
        if dirs and any(metric_rows(d) for d in dirs):
            lab = c.label + (' + distractors' if c.distractors else '')
            n = sum(map(num_seeds_of, dirs))
            curves[f'{lab} ({n} seed{"s" * (n > 1)})'] = curve_rows([metric_rows(d) for d in dirs])
    if not curves:
        return False
    path.parent.mkdir(parents=True, exist_ok=True)
    plot_learning_curves(curves, path, title)
    return True


def generalisation_section(runs: Path) -> list[str]:
    """SR / SPL of exploratory runs in their training house and in HELD_OUT: the main model's
    (GENERALISATION_MODELS, which the runner evaluates there) and any other cell's whose runs have
    held-out evaluations (e.g. made by hand with `eval.py RUN --scene HOUSE`)."""
    held_out_json = [lambda d, s=s: held_out_dir(d, s) / 'eval.json' for s in HELD_OUT]
    rows = []
    for c in GRID:
        if c.task != 'exploratory':
            continue
        dirs = [d for d in cell_runs(runs, c) if eval_json(d) is not None]
        held = any(path_of(d).is_file() for path_of in held_out_json for d in dirs)
        if not dirs or (c.model not in GENERALISATION_MODELS and not held):
            continue
        cols = []
        for path_of in [eval_json] + held_out_json:
            per_seed = [
                json.loads(p.read_text())['summary']
                for p in map(path_of, dirs)
                if p is not None and p.is_file()
            ]
            if not per_seed:
                cols.append('not yet run')
                continue
            sr = [x for s in per_seed for x in s['success']['per_seed']]
            spl = [x for s in per_seed for x in s['spl']['per_seed']]
            cols.append(f'{np.mean(sr):.3f} / {np.mean(spl):.3f} ({len(sr)} x {per_seed[0]["episodes"]})')
        steps = sorted({metric_rows(d)[-1]['env_steps'] for d in dirs if metric_rows(d)})
        rows.append([c.label, '/'.join(f'{s:,}' for s in steps)] + cols)
    ref = []
    for scene in (TRAIN_HOUSE,) + HELD_OUT:
        p = reference_dir(runs, 'random', scene) / 'eval.json'
        sm = json.loads(p.read_text())['summary'] if p.is_file() else None
        ref.append(
            f"{sm['success']['mean']:.3f} / {sm['spl']['mean']:.3f} (1 x {sm['episodes']})"
            if sm
            else 'not yet run'
        )
    if rows:
        rows.append(['random policy (chance level)', '-'] + ref)
    out = [
        '## Generalisation: exploratory navigation in houses not seen in training',
        '',
        'Beyond the paper (which trains and tests in one house): the exploratory main model (and '
        'any other model whose runs were evaluated there), trained in scenes/house.xml, evaluated '
        'unchanged (`eval.py RUN --scene HOUSE --episodes 20`) in the generated houses '
        + ', '.join(f'`{s}`' for s in HELD_OUT)
        + ' (other room layouts, furniture and goal sets; the graph models take any node count). '
        'Cells: SR / SPL (seeds x episodes per seed).',
        '',
    ]
    if not rows:
        return out + [
            'No exploratory main-model run yet: `python tools/reproduce.py --tables 3 '
            '--cells "exploratory_rgbd_sg_attn$"` trains one and evaluates it here.',
            '',
        ]
    out[-2] += (
        ' Last row: a uniformly random policy in each house (`eval.py --policy random '
        '--task exploratory --scene HOUSE`), the chance level: houses differ in size, start '
        'distances and goal sets, so an SR is only meaningful next to it.'
    )
    head = ['Model', 'Env steps / seed', 'house.xml (training)'] + [Path(s).name for s in HELD_OUT]
    out += ['| ' + ' | '.join(head) + ' |', '|' + '---|' * len(head)]
    out += ['| ' + ' | '.join(r) + ' |' for r in rows]
    return out + ['']


def attention_section(runs: Path, figdir: Path, out_dir: Path) -> list[str]:
    lines = [
        '## Attention analysis',
        '',
        '`notebooks/attention_analysis.ipynb` (helpers in `hron_jax/analysis.py`) reads any of '
        f'these run dirs (`HRON_RUN_DIR={repo_relative(runs)}/<cell>/s0`) and shows HGT attention per layer '
        'and edge type, the task-driven pooling weights, the scene graph over the house map '
        'and the concentration on goal-category nodes with and without distractors.',
        '',
    ]
    for name in ATTENTION_CELLS:
        side = seed0_dir(runs, name) / 'attention_summary.json'
        if not side.is_file():
            continue
        a = json.loads(side.read_text())
        lines += [
            f'### {name} (seed 0, checkpoint after {a["step"]} updates)',
            '',
            f'`python tools/reproduce.py --attention`: {a["episodes"]} sampled episodes of at most '
            f'{a["max_steps"]} steps, without and with distractors.',
            '',
            '| condition | '
            + ' | '.join(k.replace('_', ' ') for k in a['summary'][next(iter(a['summary']))])
            + ' |',
            '|---|' + '---|' * len(a['summary'][next(iter(a['summary']))]),
        ]
        for label, sm in a['summary'].items():
            lines.append(
                f'| {label} | '
                + ' | '.join(f'{v:.3g}' if isinstance(v, float) else str(v) for v in sm.values())
                + ' |'
            )
        lines.append('')
        for kind in ('graph_on_map', 'edge_types', 'goal_concentration'):
            png = figdir / f'{name}_{kind}.png'
            if png.is_file():
                lines += [f'![{name} {kind}]({png.relative_to(out_dir).as_posix()})', '']
    return lines


def table_comparison(table: int, done: list) -> list[str]:
    """Lines under a table: whether its rows ran different settings, and per setting (distractors
    / pre-map) and metric whether every pair of rows is ordered as in the paper."""
    lines = []
    varying = {}
    for key in ('preset', 'camera', 'graph', 'attention', 'ppo', 'budget'):
        vals: dict[str, list[str]] = {}
        for c, f in done:
            for st in f['settings']:
                if key in st and c.label not in vals.setdefault(st[key], []):
                    vals[st[key]].append(c.label + (' + distractors' if c.distractors else ''))
        if len(vals) > 1:
            varying[key] = vals
    if varying:
        lines += [
            'The rows of this table did not all run the same settings: '
            + '; '.join(
                ' vs '.join(f"{v} ({', '.join(rows)})" for v, rows in vals.items())
                for vals in varying.values()
            )
            + '.',
            '',
        ]
    elif len(done) > 1:
        lines += ['All rows of this table ran the same settings apart from the model (Config column).', '']
    sentences = []
    for cond in (False, True):
        rows = [(c, f) for c, f in done if (c.premap if table == 3 else c.distractors) == cond]
        where = (
            ('with pre-mapping' if cond else 'without pre-mapping')
            if table == 3
            else ('with distractors' if cond else 'without distractors')
        )
        for metric, key, pkey in (('SR', 'sr', 'paper_sr'), ('SPL', 'spl', 'paper_spl'))[: 1 + (table > 1)]:
            ours = {c.label: f[key][0] for c, f in rows}
            paper = {c.label: getattr(c, pkey)[0] for c, _ in rows}
            sentence = ordering_sentence(f'Order of the models, {metric} {where}', ours, paper)
            if sentence:
                sentences.append(sentence)
    if sentences:
        lines += [
            ' '.join(sentences) + ' (Means as printed; the spreads over seeds are not taken into account.)',
            '',
        ]
    return lines


# ------------------------------------------------------------------------------------------------
# The report
# ------------------------------------------------------------------------------------------------


def write_report(runs: Path, out: Path, seeds: int) -> str:
    """Write the report of the runs under RUNS to `out` and archive their files (save_runs)."""
    figdir = report_dir(out)
    regenerate = 'python tools/reproduce.py --from-runs' + (
        '' if is_main_report(out) else f' --out {repo_relative(out)}'
    )
    lines = [
        '# Reproduction of Tables I-III',
        '',
        f'Generated by `{regenerate}` from the run dirs under '
        f'`{repo_relative(runs)}` ({time.strftime("%Y-%m-%d %H:%M")}). '
        'Numbers below are read from those runs only; '
        'cells without runs say so and give the commands and the measured cost to produce them.',
        '',
    ]
    found = {c: collect_cell(runs, c) for c in GRID}
    paper_nav = profile_config('paper', main_cell('directed'))
    run_machines = [x for f in found.values() if f for x in f['machines']]
    unrecorded = sum(f['unrecorded'] for f in found.values() if f)
    m = run_machines[0] if run_machines else machine()
    loads = [x for f in found.values() if f for x in f['loads']]
    if loads:
        load_txt = f'during the runs {min(loads):.1f}-{max(loads):.1f}'
    elif run_machines:
        starts = [x['loadavg'][0] for x in run_machines if x.get('loadavg')]
        load_txt = f'at the runs\' starts {min(starts):.1f}-{max(starts):.1f}' if starts else 'not recorded'
    else:
        # Runs made by train.py before processes.jsonl name no machine: only this process's is known.
        load_txt = (
            f'when this report was written {m.get("loadavg", "?")}; the runs recorded neither '
            'machine nor load, so both are this process\'s'
        )
    kinds = list(dict.fromkeys(f'{x.get("cpu")}, {x.get("cores")} logical cores' for x in run_machines))
    if len(kinds) > 1 or (run_machines and unrecorded):
        # Runs resumed or made on other machines: name them all, as XLA:CPU rounds per machine.
        where = f'the runs\' processes ran on {"; ".join(kinds)}' + (
            f' ({unrecorded} runs named no machine)' if unrecorded else ''
        )
    else:
        where = kinds[0] if kinds else f'{m.get("cpu")}, {m.get("cores")} logical cores'
    lines += [
        '## Machine and protocol',
        '',
        f'- machine: {where}, JAX {m.get("jax", "?")} on '
        f'{", ".join(m.get("devices", [])) or "?"}; 1-min load average {load_txt} '
        '(the cores are shared with other jobs: at load ~7 the same program ran '
        '2.5x slower than at ~1, so wall times are upper bounds).',
        f'- per cell: {seeds} seeds planned (seeds 0..{seeds - 1}: separate `train.py` runs '
        'RUNS/<cell>/s<seed> with profiles cpu / paper, or one run RUNS/<cell>/s0x<seeds> with the '
        'seeds vmapped, trained in one process with profiles gpu / tiny; the "Seeds x episodes" '
        'column says how many ran); the final checkpoint of each seed is evaluated with `eval.py '
        'RUN --episodes N` (or the same code in process: same episode starts / goals for every '
        'seed and model; actions sampled from the policy).',
        '- SR / SPL: mean over all episodes of all seeds ± sample std (ddof=1) over seeds of the '
        'per-seed means, n = seeds beside it; one seed: no spread (the paper: "averaged over 20 '
        'episodes across three random seeds"; its ± are copied as printed).',
        '- env steps: per seed; wall: mean per seed of training (excluding compilation, from '
        'metrics.jsonl) and of the whole train + eval processes (compilation included).',
        '- settings: every row\'s Config column says what its runs ran, read from each run\'s '
        'config.json: preset, camera and physics (navigation), HGT softmax and sizes (graph models), PPO '
        '(envs x steps per update, epochs, minibatch size, lr), budget. The paper\'s settings are '
        f"`train.py --preset paper` (navigation: {settings_text(paper_nav)}); only a run that ran exactly "
        'those says "= the paper\'s settings".',
    ]
    for table in (1, 2, 3):
        done = [(c, found[c]) for c in GRID if c.table == table and found[c] is not None]
        texts = sorted({t for _, f in done for t in f['configs']})
        if texts:
            lines.append(f'- {TABLE_TITLES[table].split(":")[0]} runs ran:')
            lines += [f'  - {t}' for t in texts]
    lines.append('')
    for table in (1, 2, 3):
        cells = [c for c in GRID if c.table == table]
        lines += [f'## {TABLE_TITLES[table]}', '']
        if all(found[c] is None for c in cells):  # e.g. a report of one table's runs at another budget
            lines += [
                f'No runs of this table under `{repo_relative(runs)}`. `python tools/reproduce.py '
                f'--plan --tables {table}` prints the paper\'s numbers, each cell\'s command and its '
                'estimated cost.',
                '',
            ]
            continue
        spl = table > 1
        head = (
            ['Distractors' if table < 3 else 'Pre-map', 'Model', 'Paper SR']
            + (['Paper SPL'] if spl else [])
            + ['Ours SR']
            + (['Ours SPL'] if spl else [])
            + ['Seeds x episodes', 'Env steps / seed', 'Train wall / seed', 'Process wall / seed', 'Config']
        )
        lines += ['| ' + ' | '.join(head) + ' |', '|' + '---|' * len(head)]
        to_run = []  # (cell, its planned seeds without a run)
        for c in cells:
            f = found[c]
            cond = ('yes' if c.distractors else 'no') if table < 3 else ('yes' if c.premap else 'no')
            row = [cond, c.label, _pm(c.paper_sr)] + ([_pm(c.paper_spl)] if spl else [])
            if f is None:
                row += ['not yet run'] + (['not yet run'] if spl else []) + ['-'] * 5
            else:
                row += [_ours(f['sr'])] + ([_ours(f['spl'])] if spl else [])
                row += [
                    f"{len(f['seeds'])} x {'/'.join(map(str, f['episodes']))}",
                    '/'.join(f'{s:,}' for s in f['env_steps']),
                    fmt_duration(f['train_wall_s']),
                    fmt_duration(f['proc_wall_s']),
                    config_text(f),
                ]
            lines.append('| ' + ' | '.join(row) + ' |')
            left = [s for s in range(seeds) if f is None or s not in f['seeds']]
            to_run += [(c, left)] if left else []
        lines.append('')
        done = [(c, found[c]) for c in cells if found[c] is not None]
        if done:
            for metric, key in (('SR', 'sr_per_seed'), ('SPL', 'spl_per_seed'))[: 1 + spl]:
                lines += [
                    f'Per-seed {metric} (seed: {metric}): '
                    + '; '.join(
                        f"{c.label}{' + distractors' if c.distractors else ''}"
                        f"{' (PM)' if c.premap and 'PM' not in c.label else ''}: "
                        + ', '.join(f'{sd}: {v:.3f}' for sd, v in zip(f['seeds'], f[key]))
                        for c, f in done
                    ),
                    '',
                ]
            lines += table_comparison(table, done)
        # A run stops at the last whole update within its budget (1,499,136 env steps of 1.5 M).
        short = any(b < PAPER_STEPS[c.task] for c, f in done for b in f['budgets'])
        lines += notes(table, paper_budget=not short) + ['']
        fig = figdir / f'table{table}_curves.png'
        if plot_curves(runs, cells, fig, TABLE_TITLES[table] + ': training SR, mean ± sample std over seeds'):
            lines += [
                f'![learning curves]({fig.relative_to(out.parent).as_posix()})',
                '',
                'Training success rate (episodes completed in each logged chunk of updates, '
                'sampled actions) against env steps per seed; band: sample std (ddof=1) over seeds.',
                '',
            ]
        if to_run:
            # The table's rows ran one profile's settings: its other cells and seeds are to be run
            # the same way (the full-budget report: not the paper preset it would otherwise name).
            matched = runs_profile(runs, done)
            profile, steps = matched or ('paper', None)
            how = f'the `{profile}` profile' + (f' at {steps:,} env steps' if steps else '')
            how += ', i.e. `train.py --preset paper`' if profile == 'paper' else ''
            how = f"the settings of this table's runs, {how}" if matched else how
            lines += [
                f'Not yet run, of {seeds} seeds per cell (commands per seed with {how}, then the '
                f'report; estimated training cost of the seeds left at '
                f'{steps or profile_steps(profile, cells[0].task):,} env steps per seed, from '
                'measured steps/s, compilation and evaluation excluded):',
                '',
            ]
            total, rough = 0.0, False
            for c, left in to_run:
                est, sec = estimate(c, runs, len(left), profile, steps=steps)
                total += sec or 0.0
                rough |= ROUGH in est
                rel = f'{repo_relative(runs)}/{c.name}/s$SEED'
                argv = train_argv(c, 0, Path(rel), profile, total_steps=steps)
                cmd = ' '.join(argv).replace('--seed 0', '--seed $SEED')
                which = f'seed {left[0]}' if len(left) == 1 else f'seeds {", ".join(map(str, left))}'
                lines += [
                    f'- `{c.name}` ({c.label}{", distractors" if c.distractors else ""}), {which}: '
                    f'estimated {est}',
                    f'  `for SEED in {" ".join(map(str, left))}; do {cmd} && python eval.py '
                    f'{rel} --episodes {EPISODES[c.task]} --out {rel}/{EVAL_DIR}; done`',
                ]
            if total:
                lines += [
                    '',
                    f'Total estimated training of the seeds left on this machine: '
                    f'{fmt_duration(total)} ({total / 86400:.0f} days).',
                ]
            if rough:
                lines += [
                    '',
                    f'Estimates marked "{ROUGH}" come from runs under other settings than the '
                    + (
                        "paper profile's `--preset paper` (e.g. 4 PPO epochs per update and a 32x32 "
                        'camera instead of 30 epochs and 128x128): they are presumably lower bounds.'
                        if profile == 'paper'
                        else f"`{profile}` profile's (the cost of an env step depends on them)."
                    ),
                ]
            lines.append('')
    if any(found[c] is not None for c in GRID if c.table == 3):
        lines += generalisation_section(runs)
    lines += attention_section(runs, figdir, out.parent)
    lines += [
        '## Regenerating',
        '',
        '```bash',
        'python tools/reproduce.py --plan                 # grid, commands, cost estimates',
        "python tools/reproduce.py --tables 1 --profile cpu  # Table I as run here: not the paper's settings",
        'python tools/reproduce.py --tables 2 3 --profile paper   # train.py --preset paper (GPU advised)',
        'python tools/reproduce.py --tables 2 --profile gpu  # same settings, 3 seeds vmapped, one process',
        'bash tools/gpu_tables.sh 2 540 8192              # a time-boxed GPU lease (one prepared script)',
        'python tools/reproduce.py --attention            # attention figures of the trained main models',
        f'{regenerate:<48} # this report from existing runs',
        '```',
        '',
        f'The runs behind this report are archived in `{repo_relative(archive_of(out))}` (their config, '
        'metrics and evaluation files; no checkpoints). Every call of this tool first copies the '
        'archived runs RUNS lacks into RUNS, where the runner counts them as done, and after writing '
        'the report saves every run of RUNS there: a fresh checkout regenerates this report, and adds '
        'seeds to it, without retraining what is archived. A report of other runs goes to another '
        '`--out` (its archive is beside it).',
        '',
    ]
    text = '\n'.join(lines)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(text)
    save_runs(runs, archive_of(out))
    return text
