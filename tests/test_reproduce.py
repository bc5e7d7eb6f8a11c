"""tools/reproduce.py: --plan, and the report aggregated from hand-made run dirs (no training)."""

import importlib.util
import json
import os
import re
from pathlib import Path

import pytest

from hron_jax.cli import config_from_args
from hron_jax.paths import REPO_ROOT
from hron_jax.reproduction import runner
from hron_jax.reproduction.grid import (
    ATTENTION_CELLS,
    GRID,
    HELD_OUT,
    TRAIN_HOUSE,
    ordering_disagreements,
    ordering_sentence,
    paper_diff,
    profile_config,
    profile_steps,
    train_argv,
)
from hron_jax.reproduction.report import (
    _ours,
    attention_section,
    config_text,
    estimate,
    generalisation_section,
    table_comparison,
)
from hron_jax.reproduction.runs import (
    ARCHIVED,
    collect_cell,
    default_runs,
    eval_json,
    held_out_dir,
    mean_std,
    reference_dir,
    repo_relative,
)
from hron_jax.run_config import run_label

ROOT = Path(REPO_ROOT)


@pytest.fixture(scope='module')
def cli():
    """tools/reproduce.py, the command line (a script, not a module): build_parser and main."""
    spec = importlib.util.spec_from_file_location('reproduce', ROOT / 'tools' / 'reproduce.py')
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def fake_eval(d: Path, sr: float, spl: float):
    d.mkdir()
    summary = {
        'success': {'mean': sr, 'per_seed': [sr]},
        'spl': {'mean': spl, 'per_seed': [spl]},
        'seeds': 1,
        'episodes': 50,
    }
    (d / 'eval.json').write_text(json.dumps({'summary': summary}))


def fake_run(
    d: Path, seed: int, sr: float, spl: float, distractors=True, task='choice', model='rgbd_sg_attn', **opts
):
    """A run dir as train.py + eval.py leave it (only the files the report reads); opts: more
    train.py options (config_from_args names), e.g. preset='paper' or lr=1e-3."""
    d.mkdir(parents=True)
    args = dict(
        task=task,
        model=model,
        distractors=distractors,
        seed=seed,
        total_steps=1024 if task == 'choice' else 4096,
        model_option=['hidden=32'],
    )
    cfg = config_from_args({**args, **opts})
    (d / 'config.json').write_text(json.dumps({'config': cfg.to_dict(), 'meta': {}}))
    write_rows(d, sr)
    fake_eval(d / 'eval_trained', sr, spl)
    (d / 'repro.json').write_text(json.dumps({'train_wall_s': 30.0, 'eval_wall_s': 10.0}))


def write_rows(d: Path, sr: float):
    rows = [
        dict(
            update=u,
            env_steps=256 * u,
            wall_time=2.0 * u,
            steps_per_s=128.0,
            success=s,
            success_std=0.0,
            **{'return': s},
        )
        for u, s in ((2, 0.5), (4, sr))
    ]
    (d / 'metrics.jsonl').write_text(''.join(json.dumps(r) + '\n' for r in rows))


CHOICE_CPU = (
    "preset default (not the paper's settings); HGT hidden 32, 2 heads, 3 layers, joint softmax; "
    'PPO 64 envs x 4 steps, 4 epochs, minibatch 64, lr 1e-4; 1,024 env steps / seed (the paper '
    'states no budget for this task)'
)


def test_report_from_runs(cli, tmp_path):
    runs = tmp_path / 'runs'
    for seed, sr in enumerate((1.0, 0.9, 0.8)):
        fake_run(runs / 'choice_rgbd_sg_attn_dist' / f's{seed}', seed, sr, sr)
    out = tmp_path / 'docs' / 'reproduction.md'
    assert cli.main(['--from-runs', '--runs', str(runs), '--out', str(out)]) == 0
    text = out.read_text()
    row = next(l for l in text.splitlines() if l.startswith('| yes | SG + TD ATTN |'))
    # Mean over seeds 0.9; sample std (ddof=1) of the per-seed means 0.1 (ddof=0 would be 0.082).
    assert '0.993 ± 0.007' in row and '0.900 ± 0.100 (n=3)' in row and '3 x 50' in row
    assert '1,024' in row and '| 8 s |' in row and '40 s' in row
    # The Config column says exactly what ran, from the runs' config.json.
    assert row.endswith(f'| {CHOICE_CPU} |')
    assert 'paper model' not in text and "= the paper's settings" not in row
    assert 'SG + TD ATTN + distractors: 0: 1.000, 1: 0.900, 2: 0.800' in text
    assert (out.parent / 'reproduction' / 'table1_curves.png').is_file()
    # Runs made by train.py alone record no load: the report names whose load it prints.
    assert '1-min load average when this report was written [' in text
    assert 'during the runs' not in text
    side = runs / 'choice_rgbd_sg_attn_dist' / 's1' / 'repro.json'
    side.write_text(json.dumps({**json.loads(side.read_text()), 'loadavg_training': [1.2, 3.4]}))
    assert cli.main(['--from-runs', '--runs', str(runs), '--out', str(tmp_path / 'again.md')]) == 0
    assert '1-min load average during the runs 1.2-3.4 (' in (tmp_path / 'again.md').read_text()
    # Runs whose processes (train.py's processes.jsonl) ran on two machines name both, and the
    # runs that named none are counted, not passed off as this machine.
    for seed, cpu in ((0, 'CPU A'), (2, 'CPU B')):
        proc = dict(update=0, machine=dict(cpu=cpu, cores=2, jax='0.10.2', devices=['cpu:0']))
        log = runs / 'choice_rgbd_sg_attn_dist' / f's{seed}' / 'processes.jsonl'
        log.write_text(json.dumps(proc) + '\n')
    assert cli.main(['--from-runs', '--runs', str(runs), '--out', str(tmp_path / 'machines.md')]) == 0
    assert (
        "- machine: the runs' processes ran on CPU A, 2 logical cores; CPU B, 2 logical cores "
        '(1 runs named no machine), JAX 0.10.2 on cpu:0; 1-min load average during the runs 1.2-3.4 ('
    ) in (tmp_path / 'machines.md').read_text()
    # The table's cells without runs are listed as not run, with the commands of the profile whose
    # settings its runs ran (here cpu, at the runs' budget), costed from those runs; nothing is
    # invented. A table without any run says so in one line and points to --plan (which lists its
    # commands).
    table1 = text.split('## Table I:')[1].split('## Table II:')[0]
    assert table1.count('| not yet run |') == 3
    assert "with the settings of this table's runs, the `cpu` profile at 1,024 env steps" in table1
    assert (
        'python train.py --task choice --model rgbd_sg --seed $SEED --distractors --total-steps 1024 '
        '--model-option hidden=32 --no-progress --out'
    ) in table1
    assert '128 env steps/s (proxy: runs of choice_rgbd_sg_attn_dist) -> 24 s' in table1
    assert 'a rough figure' not in table1
    for table in (2, 3):
        assert (
            f'No runs of this table under `{runs}`. `python tools/reproduce.py --plan --tables {table}`'
            in text
        )
    assert 'not yet run' not in text.split('## Table II:')[1]
    # The protocol names the paper's settings, and the cpu profile says it is not them.
    assert '`train.py --preset paper` (navigation: camera 128x128; HGT hidden 128, 2 heads, 3 layers' in text
    assert "Profile `cpu`, not the paper's settings" in text
    # Runs of settings no profile gives: the paper profile's commands, and the estimate from those
    # runs says it is rough.
    other = tmp_path / 'other'
    fake_run(other / 'choice_rgbd_sg_attn_dist' / 's0', 0, 1.0, 1.0, lr=1e-3)
    assert cli.main(['--from-runs', '--runs', str(other), '--out', str(tmp_path / 'other.md')]) == 0
    table1 = (tmp_path / 'other.md').read_text().split('## Table I:')[1].split('## Table II:')[0]
    assert 'commands per seed with the `paper` profile, i.e. `train.py --preset paper`, then' in table1
    assert 'python train.py --task choice --model rgbd_sg --seed $SEED --distractors --preset paper' in table1
    assert 'measured with preset default' in table1 and 'a rough figure' in table1


def test_one_seed_has_no_spread_and_old_config_files_are_read(tmp_path):
    """A pre-tree (flat) config.json, as the runs of 2026-11-23 wrote it, is read and described."""
    runs = tmp_path / 'runs'
    d = runs / 'directed_rgbd_sg_dist' / 's0'
    d.mkdir(parents=True)
    ppo = dict(
        num_envs=64,
        num_steps=64,
        total_timesteps=131072,
        update_epochs=4,
        num_minibatches=32,
        lr=2.5e-4,
        anneal_lr=False,
        gamma=0.99,
        gae_lambda=0.9,
        clip_eps=0.2,
        clip_value=True,
        ent_coef=0.01,
        vf_coef=0.5,
        max_grad_norm=0.5,
        normalize_advantages=True,
        seed=0,
    )
    old = dict(
        task='directed',
        model='rgbd_sg',
        scene='scenes/symmetric_room.xml',
        distractors=True,
        premap=False,
        env_options=[],
        model_options=[],
        ppo=ppo,
        seed=0,
        num_seeds=1,
        log_every=1,
        checkpoint_every=20,
        keep_checkpoints=3,
        fast_compile=False,
    )
    (d / 'config.json').write_text(json.dumps({'config': old, 'meta': {}}))
    write_rows(d, 0.55)
    fake_eval(d / 'eval_trained', 0.55, 0.174)
    cell = next(c for c in GRID if c.name == 'directed_rgbd_sg_dist')
    f = collect_cell(runs, cell)
    assert _ours(f['sr']) == '0.550 (n=1, no spread)'
    assert config_text(f) == (
        "preset default (not the paper's settings); camera 32x32; physics MJX (JAX); HGT hidden 128, 2 "
        'heads, 3 layers, joint softmax; PPO 64 envs x 64 steps, 4 epochs, minibatch 128, lr 2.5e-4; '
        "131,072 env steps / seed (9 % of the paper's 1.5 M)"
    )


def test_mean_std_is_the_sample_std_with_n():
    assert _ours(mean_std([0.5, 0.55])) == '0.525 ± 0.035 (n=2)'  # ddof=0 would print 0.025
    assert _ours(mean_std([1.0, 0.475, 1.0])) == '0.825 ± 0.303 (n=3)'  # ddof=0: 0.247
    assert mean_std([0.3]) == (0.3, None, 1)


def test_config_text_says_paper_settings_only_when_they_ran(tmp_path):
    runs = tmp_path / 'runs'
    base = dict(distractors=False, task='directed', model='rgbd_sg_attn', model_option=[])
    fake_run(runs / 'directed_rgbd_sg_attn' / 's0', 0, 0.9, 0.8, preset='paper', **base)
    fake_run(runs / 'directed_rgbd_sg_attn' / 's1', 1, 0.7, 0.6, preset='paper', lr=1e-3, **base)
    fake_run(runs / 'directed_rgbd' / 's0', 0, 0.5, 0.2, **{**base, 'model': 'rgbd'})
    f = collect_cell(runs, next(c for c in GRID if c.name == 'directed_rgbd_sg_attn'))
    text = config_text(f)
    # Seeds that ran different configs say so, each with its own description.
    assert (
        text.startswith('seeds ran different configs: seed 0: preset paper (= the paper')
        and (
            'camera 128x128; physics MJX (JAX); HGT hidden 128, 2 heads, 3 layers, per_relation softmax; '
            'PPO 8 envs x 512 '
            'steps, 30 epochs, minibatch 128, lr 1e-4, KL penalty 0.2; 4,096 env steps / seed (0.3 % of '
            "the paper's 1.5 M)"
        )
        in text
    )
    assert "seed 1: preset paper, changed: ppo.lr (not the paper's settings)" in text and 'lr 1e-3' in text
    # Rows of a table that ran different settings say so under the table.
    cells = [c for c in GRID if c.name in ('directed_rgbd', 'directed_rgbd_sg_attn')]
    done = [(c, collect_cell(runs, c)) for c in cells]
    lines = table_comparison(2, done)
    assert lines[0].startswith('The rows of this table did not all run the same settings: ')
    assert "preset default (not the paper's settings) (RGB-D only)" in lines[0]
    # GCN vs HGT is the model variant's choice, not a setting: rows of the same graph size and
    # PPO compare as the same settings; a GCN of another size, or HGT's heads, do not.
    t3 = dict(distractors=False, task='exploratory', model_option=['hidden=32'])
    fake_run(runs / 'exploratory_gcn' / 's0', 0, 0.4, 0.2, model='gcn', **t3)
    fake_run(runs / 'exploratory_rgbd_sg_attn' / 's0', 0, 0.8, 0.5, **t3)
    fake_run(
        runs / 'exploratory_rgbd_sg' / 's0',
        0,
        0.6,
        0.3,
        model='rgbd_sg',
        **{**t3, 'model_option': ['hidden=32', 'heads=4']},
    )
    fake_run(
        runs / 'exploratory_yang' / 's0', 0, 0.1, 0.0, model='yang', **{**t3, 'model_option': ['hidden=64']}
    )
    by_name = {c.name: c for c in GRID}

    def compare(*names):
        return table_comparison(3, [(by_name[n], collect_cell(runs, by_name[n])) for n in names])[0]

    assert compare('exploratory_gcn', 'exploratory_rgbd_sg_attn').startswith(
        'All rows of this table ran the same'
    )
    assert compare('exploratory_gcn', 'exploratory_yang') == (
        'The rows of this table did not all run the same settings: graph network hidden 32, 3 layers '
        '(Kipf et al. (GCN)) vs graph network hidden 64, 3 layers (Yang et al.).'
    )
    assert compare('exploratory_gcn', 'exploratory_rgbd_sg_attn', 'exploratory_rgbd_sg') == (
        'The rows of this table did not all run the same settings: HGT 2 heads, joint softmax (RGB-D + SG + '
        'TD ATTN) vs HGT 4 heads, joint softmax (RGB-D + SG).'
    )


def test_profiles(cli, capsys, tmp_path):
    for cell in GRID:
        paper = profile_config('paper', cell)
        assert '--preset paper' in ' '.join(train_argv(cell, 0, Path('x'), 'paper'))
        assert paper.preset == 'paper' and paper_diff(paper) == []
        assert paper_diff(profile_config('cpu', cell))  # the cheap profile is not the paper's
        assert cell.label == run_label(paper)  # the report's row = the run's own label
    assert profile_steps('paper', 'directed') == 1_500_000
    assert profile_steps('cpu', 'directed') == 131_072
    assert cli.main(['--plan', '--runs', str(tmp_path), '--tables', '2']) == 0
    out = capsys.readouterr().out
    assert "profile cpu: NOT the paper's settings" in out
    assert "settings (cpu): preset default (not the paper's settings); camera 32x32;" in out


def test_every_command_of_the_gpu_tables_script_parses(cli, tmp_path):
    from test_bench import gpu_script_commands  # the stand-in python3 that records commands

    runs = gpu_script_commands(
        tmp_path, 'tools/gpu_tables.sh', '2 3', '540', '8192', 'exploratory', RUNS=str(tmp_path / 'runs')
    )
    assert [a[0] for a in runs] == ['tools/reproduce.py'] * 2, runs
    train, report = (cli.build_parser().parse_args(a[1:]) for a in runs)  # SystemExit names a bad option
    assert (train.profile, train.tables, train.cells) == ('gpu', [2, 3], 'exploratory')
    assert train.total_steps == 8192
    assert 30 <= train.budget_s < 540 and not train.from_runs
    assert report.from_runs and report.runs == train.runs == str(tmp_path / 'runs')


def test_ordering_disagreements():
    paper = {'RGB-D only': 0.417, 'RGB-D + SG': 0.425, 'RGB-D + SG + TD ATTN': 0.900}
    ours = {'RGB-D only': 0.525, 'RGB-D + SG': 0.500, 'RGB-D + SG + TD ATTN': 0.900}
    # Table II with distractors: RGB-D only > RGB-D + SG here, < in the paper; the others agree.
    assert ordering_disagreements(ours, paper) == [('RGB-D only', 'RGB-D + SG', 0.525, 0.5, 0.417, 0.425)]
    sentence = ordering_sentence('SR', ours, paper)
    assert sentence.startswith('SR: 1 of 3 pairs of rows is NOT ordered as in the paper: ')
    assert 'RGB-D only 0.525 > RGB-D + SG 0.500 here, 0.417 < 0.425 in the paper' in sentence
    agree = {'RGB-D only': 0.4, 'RGB-D + SG': 0.5, 'RGB-D + SG + TD ATTN': 0.9}
    assert ordering_disagreements(agree, paper) == []
    assert ordering_sentence('SR', agree, paper) == 'SR: all 3 pairs of rows are ordered as in the paper.'
    # A tie on one side only is a different order; rows the paper lacks are left out.
    assert ordering_disagreements(
        {'SG': 0.825, 'SG + TD ATTN': 0.825, 'x': 1.0}, {'SG': 0.997, 'SG + TD ATTN': 0.991}
    ) == [('SG', 'SG + TD ATTN', 0.825, 0.825, 0.997, 0.991)]
    assert ordering_sentence('SR', {'SG': 0.5}, {'SG': 0.6}) is None


def test_a_cell_without_runs_is_costed_from_the_same_model_before_the_main_model(tmp_path):
    runs = tmp_path / 'runs'
    fake_run(runs / 'directed_rgbd' / 's0', 0, 0.5, 0.2, distractors=False, task='directed', model='rgbd')
    main = runs / 'directed_rgbd_sg_attn_dist' / 's0'
    fake_run(main, 0, 1.0, 0.8, task='directed')
    rows = [json.loads(l) for l in (main / 'metrics.jsonl').read_text().splitlines()]
    (main / 'metrics.jsonl').write_text(''.join(json.dumps({**r, 'steps_per_s': 40.0}) + '\n' for r in rows))
    by_name = {c.name: c for c in GRID}
    # RGB-D only with distractors: its own model's runs (128 env steps/s), not the main model's (40)
    text, sec = estimate(by_name['directed_rgbd_dist'], runs, 3, 'cpu')
    assert text.startswith('128 env steps/s (proxy: runs of directed_rgbd'), text
    assert sec == 3 * 131_072 / 128
    # SG with distractors has neither its own model's runs nor a probe: the main model's, same setting
    text, sec = estimate(by_name['directed_rgbd_sg_dist'], runs, 1, 'cpu')
    assert text.startswith('40 env steps/s (proxy: runs of directed_rgbd_sg_attn_dist'), text
    assert sec == 131_072 / 40


def test_plan_lists_every_cell(cli, tmp_path, capsys):
    report = tmp_path / 'report.md'  # its run archive is empty, unlike docs/reproduction's
    assert cli.main(['--plan', '--runs', str(tmp_path), '--out', str(report), '--tables', '1', '2', '3']) == 0
    text = capsys.readouterr().out
    for cell in GRID:
        assert cell.name in text
    assert '--total-steps 61440 --model-option hidden=32' in text  # choice: cpu profile
    assert (
        'python train.py --task directed --model rgbd --seed 2 --distractors --total-steps 131072 '
        '--no-progress'
    ) in text
    # no runs and no probes: nothing to cost, and the total says so instead of '0 s'
    assert text.splitlines()[-1] == (
        f'estimated training time: {len(GRID)} cell(s) left to train not measured '
        '(compilation and evaluation excluded)'
    )
    assert cli.plan_total([1800.0, None, 1800.0]) == (
        'estimated training time: 1.0 h for 2 cell(s) left to train; 1 cell(s) left to train not measured '
        '(compilation and evaluation excluded)'
    )
    assert cli.plan_total([]) == 'nothing left to train'


def test_generalisation_section_reads_held_out_evals(tmp_path):
    runs = tmp_path / 'runs'
    for seed, (sr, held) in enumerate(((0.6, 0.2), (0.4, 0.0))):
        d = runs / 'exploratory_rgbd_sg_attn' / f's{seed}'
        fake_run(d, seed, sr, sr / 2, distractors=False, task='exploratory')
        fake_eval(held_out_dir(d, HELD_OUT[0]), held, held / 2)
    # A baseline shows up only where its runs were evaluated in a held-out house.
    fake_run(runs / 'exploratory_gcn' / 's0', 0, 0.3, 0.1, distractors=False, task='exploratory', model='gcn')
    fake_run(
        runs / 'exploratory_rgbd' / 's0', 0, 0.2, 0.1, distractors=False, task='exploratory', model='rgbd'
    )
    fake_eval(held_out_dir(runs / 'exploratory_rgbd' / 's0', HELD_OUT[2]), 0.1, 0.02)
    lines = generalisation_section(runs)
    row = next(l for l in lines if l.startswith('| RGB-D + SG + TD ATTN |'))
    # Training house: mean SR of the seeds 0.5, SPL 0.25; house_1: 0.1 / 0.05; others not run.
    assert row.split(' | ')[2:5] == ['0.500 / 0.250 (2 x 50)', '0.100 / 0.050 (2 x 50)', 'not yet run']
    baseline = next(l for l in lines if l.startswith('| RGB-D only |'))
    cols = baseline.rstrip(' |').split(' | ')[2:]
    assert cols == ['0.200 / 0.100 (1 x 50)', 'not yet run', 'not yet run', '0.100 / 0.020 (1 x 50)']
    assert not any(l.startswith('| Kipf et al.') for l in lines)
    # The chance level of each house comes from the random-policy evaluations under _reference.
    (runs / '_reference').mkdir()
    fake_eval(reference_dir(runs, 'random', TRAIN_HOUSE), 0.05, 0.01)
    chance = next(l for l in generalisation_section(runs) if l.startswith('| random policy'))
    assert chance.split(' | ')[2:4] == ['0.050 / 0.010 (1 x 50)', 'not yet run']


def test_attention_section_reads_summaries_and_figures(tmp_path):
    runs, out_dir = tmp_path / 'runs', tmp_path / 'docs'
    name = ATTENTION_CELLS[0]
    (runs / name / 's0').mkdir(parents=True)
    summary = {
        'no distractors': {'episodes': 8, 'pool_goal_share_model': 1.0, 'pool_goal_share_mean': 0.5},
        'distractors': {'episodes': 8, 'pool_goal_share_model': 1.0, 'pool_goal_share_mean': 0.25},
    }
    (runs / name / 's0' / 'attention_summary.json').write_text(
        json.dumps(dict(step=8, episodes=8, max_steps=300, summary=summary))
    )
    figdir = out_dir / 'reproduction'
    figdir.mkdir(parents=True)
    (figdir / f'{name}_edge_types.png').write_bytes(b'png')
    text = '\n'.join(attention_section(runs, figdir, out_dir))
    assert f'### {name} (seed 0, checkpoint after 8 updates)' in text
    assert '| condition | episodes | pool goal share model | pool goal share mean |' in text
    assert '| distractors | 8 | 1 | 0.25 |' in text
    assert f'](reproduction/{name}_edge_types.png)' in text and 'graph_on_map' not in text
    # The other cell has no summary: no section invented for it.
    assert f'### {ATTENTION_CELLS[1]}' not in text


def test_a_shorter_run_is_resumed_to_the_profile_budget(tmp_path, monkeypatch):
    runs = tmp_path / 'runs'
    cell = next(c for c in GRID if c.name == 'exploratory_rgbd_sg_attn')
    d = runs / cell.name / 's0'
    # 1,024 env steps at the cpu profile's settings, evaluated
    fake_run(d, 0, 0.5, 0.25, distractors=False, task='exploratory', model_option=[])
    (d / 'checkpoints').mkdir()
    stale = held_out_dir(d, HELD_OUT[0])
    fake_eval(stale, 0.0, 0.0)
    calls = []
    monkeypatch.setattr(runner, 'run_logged', lambda argv, log: calls.append(argv) or 5.0)
    runner.run_cell_seed(cell, 0, runs, 'cpu', 20)
    budget = str(profile_steps('cpu', 'exploratory'))
    assert calls[0] == ['python', 'train.py', '--resume', str(d), '--total-steps', budget, '--no-progress']
    assert calls[1][:2] == ['python', 'eval.py'] and not stale.exists()  # re-evaluated, stale gone
    assert [c[c.index('--scene') + 1] for c in calls[2:]] == [str(runner.ROOT / s) for s in HELD_OUT]
    side = json.loads((d / 'repro.json').read_text())
    assert side['train_wall_s'] == 35.0  # 30 s of the first run + 5 s of the extension
    # A run at its budget is left alone.
    calls.clear()
    rows = [json.loads(l) for l in (d / 'metrics.jsonl').read_text().splitlines()]
    rows[-1]['env_steps'] = int(budget)
    (d / 'metrics.jsonl').write_text(''.join(json.dumps(r) + '\n' for r in rows))
    runner.run_cell_seed(cell, 0, runs, 'cpu', 20)
    assert calls == []


def test_a_second_report_has_its_own_runs_archive_and_figures(cli, tmp_path):
    """Runs of another budget (here the paper's 1.5 M env steps) make a report of their own: its
    archive and figures lie in the folder named as it, its runs default to runs/<its name>, and the
    first report's folder is left as it was; its notes say every row ran the paper's budget (Table I:
    the choice task's default, the paper states none)."""
    docs, cell = tmp_path / 'docs', 'directed_rgbd_sg_attn_dist'
    first, second = docs / 'reproduction.md', docs / 'full_budget.md'
    fake_run(tmp_path / 'runs_a' / cell / 's0', 0, 0.9, 0.7, task='directed')
    fake_run(tmp_path / 'runs_a' / 'choice_rgbd_sg_attn_dist' / 's0', 0, 1.0, 1.0)
    fake_run(tmp_path / 'runs_b' / 'choice_rgbd_sg_attn_dist' / 's0', 0, 1.0, 1.0, total_steps=200_000)
    full = tmp_path / 'runs_b' / cell / 's0'
    fake_run(full, 0, 1.0, 0.9, task='directed', total_steps=1_500_000, model_option=[])
    rows = [json.loads(l) for l in (full / 'metrics.jsonl').read_text().splitlines()]
    rows[-1]['env_steps'] = 1_500_000
    (full / 'metrics.jsonl').write_text(''.join(json.dumps(r) + '\n' for r in rows))

    assert cli.main(['--from-runs', '--runs', str(tmp_path / 'runs_a'), '--out', str(first)]) == 0
    folder = lambda: {p: p.read_bytes() for p in (docs / 'reproduction').rglob('*') if p.is_file()}
    before = folder()
    assert docs / 'reproduction' / 'table2_curves.png' in before
    assert cli.main(['--from-runs', '--runs', str(tmp_path / 'runs_b'), '--out', str(second)]) == 0
    assert folder() == before  # neither its figures nor its archive touched
    assert (docs / 'full_budget' / 'table2_curves.png').is_file()
    assert (docs / 'full_budget' / 'runs' / cell / 's0' / 'eval_trained' / 'eval.json').is_file()
    row = lambda p: next(
        l for l in p.read_text().splitlines() if l.startswith('| yes | RGB-D + SG + TD ATTN |')
    )
    assert '| 0.900 (n=1, no spread) |' in row(first) and '| 1,024 |' in row(first)
    assert '| 1.000 (n=1, no spread) |' in row(second) and '| 1,500,000 |' in row(second)
    text, table2 = second.read_text(), lambda t: t.split('## Table II:')[1].split('## Table III:')[0]
    assert (
        "Notes. (1) Budget and settings: every row with runs ran the paper's 1,500,000 env steps per seed"
        in text
    )
    assert 'early learning' not in table2(text) and 'early learning' in table2(first.read_text())
    table1 = lambda t: t.split('## Table I:')[1].split('## Table II:')[0]
    assert "(2) Budget and settings: every row with runs ran the task default's 200,000 env steps" in table1(
        text
    )
    assert '(2) Profile `cpu`' in table1(first.read_text()) and 'Budget and settings' not in table1(
        first.read_text()
    )
    assert f'python tools/reproduce.py --from-runs --out {repo_relative(second)} ' in text
    # The commands of its cells without runs write into its own run dirs, with its rows' settings
    # (the cpu profile) at its rows' budget.
    assert f'--out {repo_relative(tmp_path / "runs_b")}/directed_rgbd/s$SEED && python eval.py' in text
    assert (
        'python train.py --task directed --model rgbd --seed $SEED --distractors --total-steps 1500000 '
        '--no-progress'
    ) in table2(text)
    # A cell with fewer seeds than planned lists the seeds left, costed from its own runs.
    assert (
        f'- `{cell}` (RGB-D + SG + TD ATTN, distractors), seeds 1, 2: estimated 128 env steps/s (its runs)'
        in table2(text)
    )
    assert 'for SEED in 1 2; do python train.py --task directed --model rgbd_sg_attn --seed $SEED' in table2(
        text
    )
    assert 'for SEED in 0 1 2; do python train.py --task directed --model rgbd --seed $SEED' in table2(text)
    # Without --runs each report reads (and restores its archive into) run dirs of its own.
    assert default_runs(ROOT / 'docs' / 'reproduction.md') == ROOT.resolve() / 'runs' / 'repro'
    assert default_runs(second) == ROOT.resolve() / 'runs' / 'full_budget'


def test_a_report_inside_its_runs_does_not_archive_itself(cli, tmp_path):
    """tools/gpu_tables.sh writes its report into RUNS/_report: the report's folder (figures,
    archive) is then inside RUNS, and is neither a run nor archived again at the next call."""
    runs, cell = tmp_path / 'runs', 'choice_rgbd_sg_attn_dist'
    fake_run(runs / cell / 's0', 0, 1.0, 1.0)
    out = runs / '_report' / 'reproduction.md'
    for _ in range(3):  # the script's train call, its report call, a second lease's
        assert cli.main(['--from-runs', '--runs', str(runs), '--out', str(out)]) == 0
    archive = runs / '_report' / 'reproduction' / 'runs'
    assert sorted(p.relative_to(archive).parts[:2] for p in archive.rglob('*.json')) == [
        (cell, 's0'),
        (cell, 's0'),
        (cell, 's0'),
    ]  # config.json, repro.json, eval_trained/eval.json


def test_the_report_s_runs_are_archived_beside_it_and_restored_into_a_fresh_checkout(
    cli, tmp_path, monkeypatch, capsys
):
    runs, out = tmp_path / 'runs', tmp_path / 'docs' / 'reproduction.md'
    cell = next(c for c in GRID if c.name == 'choice_rgbd_sg_attn_dist')
    for seed, sr in enumerate((1.0, 0.9)):
        d = runs / cell.name / f's{seed}'
        fake_run(d, seed, sr, sr)
        (d / 'checkpoints' / '16').mkdir(parents=True)
        (d / 'checkpoints' / '16' / 'eval.json').write_text('{}')  # inside checkpoints: not archived
        (d / 'tb').mkdir()
        (d / 'processes.jsonl').write_text(json.dumps(dict(update=0, machine=dict(cpu='CPU A'))) + '\n')
    (runs / '_reference').mkdir()
    fake_eval(runs / '_reference' / 'random_house', 0.1, 0.05)
    assert cli.main(['--from-runs', '--runs', str(runs), '--out', str(out)]) == 0
    archive = tmp_path / 'docs' / 'reproduction' / 'runs'
    files = sorted(p.relative_to(archive).as_posix() for p in archive.rglob('*') if p.is_file())
    assert files == sorted(
        [
            '_reference/random_house/eval.json',
            *[
                f'choice_rgbd_sg_attn_dist/s{s}/{f}'
                for s in (0, 1)
                for f in ARCHIVED[:3] + ('processes.jsonl', 'eval_trained/eval.json')
            ],
        ]
    )
    table = [l for l in out.read_text().splitlines() if l.startswith('| yes | SG + TD ATTN |')]
    # A fresh checkout (no runs/) writes the same rows from the archive alone ...
    fresh = tmp_path / 'fresh_runs'
    assert cli.main(['--from-runs', '--runs', str(fresh), '--out', str(out)]) == 0
    assert [l for l in out.read_text().splitlines() if l.startswith('| yes | SG + TD ATTN |')] == table
    assert (fresh / 'choice_rgbd_sg_attn_dist' / 's1' / 'eval_trained' / 'eval.json').is_file()
    # --plan reads the archive without restoring it: 2 of 3 seeds done, the cost of the third from their rate.
    planned = tmp_path / 'planned_runs'
    assert cli.main(['--plan', '--runs', str(planned), '--out', str(out), '--tables', '1']) == 0
    line = next(l for l in capsys.readouterr().out.splitlines() if l.split()[2:3] == [cell.name])
    # the fake runs log 128 env steps/s; the cpu profile trains choice 61,440 steps per seed: 480 s
    assert line.endswith('2/3 seeds evaluated; 1 to train: 128 env steps/s (its runs) -> 8.0 min'), line
    assert not planned.exists()
    # ... and the runner counts the restored runs as done: nothing is retrained.
    calls = []
    monkeypatch.setattr(runner, 'run_logged', lambda argv, log: calls.append(argv) or 5.0)
    monkeypatch.setattr(runner, 'profile_steps', lambda profile, task: 1024)
    runner.run_cell_seed(cell, 1, fresh, 'cpu', 50)
    assert calls == []
    # A restored run short of the budget cannot be resumed (no checkpoints): the error says so.
    monkeypatch.setattr(runner, 'profile_steps', lambda profile, task: 4096)
    with pytest.raises(SystemExit, match='no checkpoints to resume'):
        runner.run_cell_seed(cell, 1, fresh, 'cpu', 50)
    # An eval archived after the run was restored reaches the restored copy, so the report's
    # save_runs keeps it in the archive; a run retrained in place (other metrics) takes none.
    late = Path('eval_200ep') / 'eval.json'
    for s in (0, 1):
        (archive / cell.name / f's{s}' / late).parent.mkdir()
        (archive / cell.name / f's{s}' / late).write_text('{"late": 1}')
    retrained = fresh / cell.name / 's0' / 'metrics.jsonl'
    retrained.write_text(retrained.read_text() * 2)
    assert cli.main(['--from-runs', '--runs', str(fresh), '--out', str(out)]) == 0
    assert (fresh / cell.name / 's1' / late).read_text() == '{"late": 1}'
    assert (archive / cell.name / 's1' / late).read_text() == '{"late": 1}'
    assert not (fresh / cell.name / 's0' / late).exists()
    assert not (archive / cell.name / 's0' / late).exists()  # the retrained s0 replaced it


def test_probe_runs_the_paper_profile(cli, tmp_path, monkeypatch):
    calls = []

    def fake(argv, log):
        calls.append(argv)
        Path(argv[argv.index('--out') + 1]).mkdir(parents=True)
        return 1.0

    monkeypatch.setattr(runner, 'run_logged', fake)
    cli.main(['--probe', 'directed_rgbd_sg_attn', '--runs', str(tmp_path)])
    argv = ' '.join(calls[0])
    assert '--preset paper' in argv and '--total-steps 4096' in argv  # one update of 8 envs x 512
    assert (tmp_path / '_probe' / 'directed_rgbd_sg_attn' / 'repro.json').is_file()


def test_a_run_of_other_settings_is_not_resumed_under_a_profile(tmp_path, monkeypatch):
    runs = tmp_path / 'runs'
    cell = next(c for c in GRID if c.name == 'directed_rgbd_sg_attn')
    fake_run(runs / cell.name / 's0', 0, 0.5, 0.25, distractors=False, task='directed', model_option=[])
    monkeypatch.setattr(runner, 'run_logged', lambda argv, log: pytest.fail(f'ran {argv}'))
    with pytest.raises(SystemExit, match=r"other settings than profile 'paper' \(.*preset"):
        runner.run_cell_seed(cell, 0, runs, 'paper', 20)


# ------------------------------------------------------------------------------------------------
# End to end at the tiny profile: train + eval in process (run_cells_in_process), then the report
# ------------------------------------------------------------------------------------------------

# One navigation cell per table (the cheapest to compile: no graph branch in the model). Measured on
# the 2 shared cores (load ~5): Table I ~30 s per cell (compile ~22 s + eval ~6 s), directed_rgbd
# ~85 s, exploratory_rgbd ~155 s (the house scene compiles slowest); about half that when idle.
NAV_CELLS = ('directed_rgbd', 'exploratory_rgbd')


def report_row(text: str, table: int, label: str, cond: str) -> list[str]:
    """The cells of a table's row in docs/reproduction.md (between its heading and the next)."""
    section = text.split(f'## {TABLE_HEADS[table]}')[1].split('\n## ')[0]
    row = next(l for l in section.splitlines() if l.startswith(f'| {cond} | {label} |'))
    return [x.strip() for x in row.strip('|').split('|')]


TABLE_HEADS = {1: 'Table I:', 2: 'Table II:', 3: 'Table III:'}


def check_row_from_runs(text: str, runs: Path, cell, seeds: int = 2) -> None:
    """The report row of `cell` holds the numbers of its run's eval.json (mean ± sample std over
    the vmapped seeds, n), its seeds x episodes and env steps, read from the run dir."""
    run = runs / cell.name / f's0x{seeds}'
    ev = json.loads((run / 'eval_trained' / 'eval.json').read_text())
    s = ev['summary']
    assert s['seeds'] == seeds and len(s['success']['per_seed']) == seeds
    cond = ('yes' if cell.distractors else 'no') if cell.table < 3 else ('yes' if cell.premap else 'no')
    row = report_row(text, cell.table, cell.label, cond)
    ours = row[3] if cell.table == 1 else row[4]
    assert ours == _ours(mean_std(s['success']['per_seed'])), (cell.name, row)
    assert f'(n={seeds})' in ours
    if cell.table > 1:
        assert row[5] == _ours(mean_std(s['spl']['per_seed'])), (cell.name, row)
    rest = row[4:] if cell.table == 1 else row[6:]
    steps = json.loads((run / 'metrics.jsonl').read_text().splitlines()[-1])['env_steps']
    assert rest[0] == f'{seeds} x {s["episodes"]}' and rest[1] == f'{steps:,}' == '32'
    assert all(re.fullmatch(r'[\d.]+ (s|min|h)', x) for x in rest[2:4]), rest  # train / process wall
    assert 'PPO 4 envs x 4 steps, 1 epochs, minibatch 16' in rest[4]  # the tiny profile's, from config.json


def test_tiny_profile_runs_table_1_and_a_navigation_cell_per_table_end_to_end(cli, tmp_path, capsys):
    """Table I completely and one cell each of Tables II and III, trained and evaluated in this
    process at the tiny profile, then the report from the run dirs. The first call trains one of
    the two updates of every Table I cell and stops (as a lease's time box does); the second
    resumes them with the programs compiled by the first (hron_jax.training's in-process cache: no
    program built, ~0 s compiling), finishes and evaluates them, and runs the navigation cells;
    a third call finds everything done."""
    runs, out = tmp_path / 'runs', tmp_path / 'docs' / 'reproduction.md'
    table1 = [c for c in GRID if c.table == 1]
    nav = [c for c in GRID if c.name in NAV_CELLS]
    run = lambda cells, **kw: runner.run_cells_in_process(cells, 'tiny', runs, compile_cache='none', **kw)

    first = run(table1, max_updates=1)
    assert [r['status'] for r in first] == ['stopped at 16 of 32; evaluated next time'] * 4
    assert [r['programs_built'] for r in first] == [1] * 4  # no two cells of the grid share one
    assert all(eval_json(runs / c.name / 's0x2') is None for c in table1)

    second = run(table1 + nav)
    assert [r['status'] for r in second] == ['evaluated'] * 6
    for a, b in zip(first, second[:4]):  # resumed with the compiled program: nothing to compile
        assert b['programs_built'] == 0 and b['compile_s'] < min(2.0, 0.1 * a['compile_s']), (a, b)
        assert (b['steps_from'], b['env_steps']) == (16, 32)
    assert [r['programs_built'] for r in second[4:]] == [1, 1]
    for r in second:  # eval.py's protocol and files, in process
        d = runs / r['cell'] / 's0x2'
        assert {'eval.json', 'eval.md', 'trajectories.png'} <= {
            p.name for p in (d / 'eval_trained').iterdir()
        }
        side = json.loads((d / 'repro.json').read_text())
        assert side['runner'] == 'in-process' and side['profile'] == 'tiny' and side['eval_wall_s'] > 0
    rows = capsys.readouterr().out
    with capsys.disabled():  # the rows, for the record (pytest -s)
        print('\n' + rows)

    # Everything done: the CLI skips every cell and writes the report from the runs.
    regex = '^(choice_.*|' + '|'.join(NAV_CELLS) + ')$'
    argv = ['--profile', 'tiny', '--cells', regex, '--compile-cache', 'none']
    assert cli.main(argv + ['--runs', str(runs), '--out', str(out)]) == 0
    printed = capsys.readouterr().out
    assert printed.count('done already') == 6 and 'built' not in printed
    assert cli.main(['--from-runs', '--runs', str(runs), '--out', str(out), '--seeds', '2']) == 0
    text = out.read_text()
    for cell in table1 + nav:
        check_row_from_runs(text, runs, cell)
    assert text.count('not yet run') >= 13  # the other cells, not invented


@pytest.mark.skipif(
    not os.environ.get('HRON_REPRO_TINY_ALL'),
    reason='all of Tables I-III at the tiny profile (~30-60 min on 2 cores): set HRON_REPRO_TINY_ALL=1',
)
def test_tiny_profile_runs_all_tables_end_to_end(cli, tmp_path):
    """Every cell of Tables I-III (and the held-out houses of the exploratory main model) through
    the CLI at the tiny profile, then the report: every row is filled from the runs."""
    runs, out = tmp_path / 'runs', tmp_path / 'docs' / 'reproduction.md'
    assert (
        cli.main(['--profile', 'tiny', '--compile-cache', 'none', '--runs', str(runs), '--out', str(out)])
        == 0
    )
    text = out.read_text()
    for cell in GRID:
        check_row_from_runs(text, runs, cell)
    assert 'not yet run' not in text.split('## Generalisation')[0]
    main = runs / 'exploratory_rgbd_sg_attn' / 's0x2'
    for scene in HELD_OUT:
        assert (held_out_dir(main, scene) / 'eval.json').is_file()


def test_summary_prints_training_windows_and_evaluations(cli, tmp_path, capsys):
    """--summary: SR / SPL / length per window of 32 rows weighted by the episodes each row
    finished (a row without episodes counts for none), entropy / KL / clip fraction plain means,
    and per evaluation its SR / SPL and the successes' own SPL and length (worked by hand)."""
    run = tmp_path / 'exploratory_rgbd' / 's0'
    run.mkdir(parents=True)
    rows = []
    for u in range(1, 35):  # windows 1-32 and 33-34
        ep = {1: 3.0, 2: 1.0}.get(u, 0.0) if u <= 32 else 2.0
        rows.append(
            dict(
                update=u,
                env_steps=4096 * u,
                wall_time=6.0 * u,
                steps_per_s=600.0 + u,
                seeds=1,
                episodes=ep,
                success={1: 1.0, 2: 0.0}.get(u) if u <= 32 else 0.5,
                spl={1: 0.6, 2: 0.0}.get(u) if u <= 32 else 0.2,
                episode_length={1: 100.0, 2: 500.0}.get(u) if u <= 32 else 300.0,
                entropy=1.5 if u % 2 else 1.3,
                approx_kl=0.02,
                clip_frac=0.3 if u <= 32 else 0.5,
            )
        )
    (run / 'metrics.jsonl').write_text(''.join(json.dumps(r) + '\n' for r in rows))
    (run / 'eval_200ep').mkdir()
    per = {
        'success': [[1.0, 0.0, 1.0, 0.0]],
        'spl': [[0.5, 0.0, 0.3, 0.0]],
        'episode_length': [[120, 500, 80, 500]],
    }
    summary = {'success': {'mean': 0.5}, 'spl': {'mean': 0.2}, 'seeds': 1, 'episodes': 4}
    (run / 'eval_200ep' / 'eval.json').write_text(
        json.dumps({'step': 34, 'summary': summary, 'per_episode': per})
    )
    assert cli.main(['--summary', str(run)]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[0] == (
        f'{run}: update 34, 139,264 env steps per seed x 1, train wall 3.4 min (compile excluded), '
        'median 618 env steps/s'
    )
    assert lines[1] == (
        '  updates 1-32 (to 131,072 env steps): train SR 0.750 SPL 0.450 over 4 episodes, length 200; '
        'entropy 1.40, approx KL 0.020, clip fraction 0.30'
    )
    assert lines[2].startswith(
        '  updates 33-34 (to 139,264 env steps): train SR 0.500 SPL 0.200 over 4 episodes'
    )
    assert lines[2].endswith('clip fraction 0.50')
    assert lines[3] == (
        '  eval_200ep: step 34, SR 0.500 SPL 0.200 over 1 x 4 episodes; its 2 successes: SPL 0.400, 100 steps'
    )
    assert len(lines) == 4
