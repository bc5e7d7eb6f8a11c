"""tools/reproduce.py: --plan, and the report aggregated from hand-made run dirs (no training)."""

import importlib.util
import json
import sys
from pathlib import Path

import pytest

from hron_jax.cli import config_from_args
from hron_jax.paths import REPO_ROOT

ROOT = Path(REPO_ROOT)


@pytest.fixture(scope='module')
def R():
    spec = importlib.util.spec_from_file_location('reproduce', ROOT / 'tools' / 'reproduce.py')
    mod = importlib.util.module_from_spec(spec)
    sys.modules['reproduce'] = mod  # dataclasses resolve annotations through sys.modules
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


def fake_run(d: Path, seed: int, sr: float, spl: float, distractors=True, task='choice'):
    """A run dir as train.py + eval.py leave it (only the files the report reads)."""
    d.mkdir(parents=True)
    cfg = config_from_args(
        dict(
            task=task,
            model='rgbd_sg_attn',
            distractors=distractors,
            seed=seed,
            total_steps=1024 if task == 'choice' else 4096,
            model_option=['hidden=32'],
        )
    )
    (d / 'config.json').write_text(json.dumps({'config': cfg.to_dict(), 'meta': {}}))
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
    fake_eval(d / 'eval_trained', sr, spl)
    (d / 'repro.json').write_text(json.dumps({'train_wall_s': 30.0, 'eval_wall_s': 10.0}))


def test_report_from_runs(R, tmp_path):
    runs = tmp_path / 'runs'
    for seed, sr in enumerate((1.0, 0.9, 0.8)):
        fake_run(runs / 'choice_rgbd_sg_attn_dist' / f's{seed}', seed, sr, sr)
    out = tmp_path / 'docs' / 'reproduction.md'
    assert R.main(['--from-runs', '--runs', str(runs), '--out', str(out)]) == 0
    text = out.read_text()
    row = next(l for l in text.splitlines() if l.startswith('| yes | SG + TD ATTN |'))
    # Mean over seeds 0.9, std over seeds of per-seed means sqrt(2/3) * 0.1.
    assert '0.993 ± 0.007' in row and '0.900 ± 0.082' in row and '3 x 50' in row
    assert '1,024' in row and '| 8 s |' in row and '40 s' in row and 'hidden=32' in row
    assert 'SG + TD ATTN + distractors: 0: 1.000, 1: 0.900, 2: 0.800' in text
    assert (out.parent / 'reproduction' / 'table1_curves.png').is_file()
    # Cells without runs are listed as not run, with their commands; nothing is invented.
    assert text.count('not yet run') >= 2 * 15
    assert 'python train.py --task exploratory --model rgbd_sg_attn --seed $SEED' in text


def test_plan_lists_every_cell(R, tmp_path, capsys):
    assert R.main(['--plan', '--runs', str(tmp_path), '--tables', '1', '2', '3']) == 0
    text = capsys.readouterr().out
    for cell in R.GRID:
        assert cell.name in text
    assert '--total-steps 20480 --model-option hidden=32' in text  # choice: cpu profile
    assert (
        'python train.py --task directed --model rgbd --seed 2 --distractors --total-steps 131072 '
        '--no-progress'
    ) in text


def test_generalisation_section_reads_held_out_evals(R, tmp_path):
    runs = tmp_path / 'runs'
    for seed, (sr, held) in enumerate(((0.6, 0.2), (0.4, 0.0))):
        d = runs / 'exploratory_rgbd_sg_attn' / f's{seed}'
        fake_run(d, seed, sr, sr / 2, distractors=False, task='exploratory')
        fake_eval(R.held_out_dir(d, R.HELD_OUT[0]), held, held / 2)
    row = next(l for l in R.generalisation_section(runs) if l.startswith('| RGB-D + SG + TD ATTN |'))
    # Training house: mean SR of the seeds 0.5, SPL 0.25; house_1: 0.1 / 0.05; others not run.
    assert row.split(' | ')[2:5] == ['0.500 / 0.250 (2 x 50)', '0.100 / 0.050 (2 x 50)', 'not yet run']
    # The chance level of each house comes from the random-policy evaluations under _reference.
    (runs / '_reference').mkdir()
    fake_eval(R.reference_dir(runs, 'random', R.TRAIN_HOUSE), 0.05, 0.01)
    chance = next(l for l in R.generalisation_section(runs) if l.startswith('| random policy'))
    assert chance.split(' | ')[2:4] == ['0.050 / 0.010 (1 x 50)', 'not yet run']


def test_attention_section_reads_summaries_and_figures(R, tmp_path):
    runs, out_dir = tmp_path / 'runs', tmp_path / 'docs'
    name = R.ATTENTION_CELLS[0]
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
    text = '\n'.join(R.attention_section(runs, figdir, out_dir))
    assert f'### {name} (seed 0, checkpoint after 8 updates)' in text
    assert '| condition | episodes | pool goal share model | pool goal share mean |' in text
    assert '| distractors | 8 | 1 | 0.25 |' in text
    assert f'](reproduction/{name}_edge_types.png)' in text and 'graph_on_map' not in text
    # The other cell has no summary: no section invented for it.
    assert f'### {R.ATTENTION_CELLS[1]}' not in text


def test_a_shorter_run_is_resumed_to_the_profile_budget(R, tmp_path, monkeypatch):
    runs = tmp_path / 'runs'
    cell = next(c for c in R.GRID if c.name == 'exploratory_rgbd_sg_attn')
    d = runs / cell.name / 's0'
    fake_run(d, 0, 0.5, 0.25, distractors=False, task='exploratory')  # 1,024 env steps, evaluated
    stale = R.held_out_dir(d, R.HELD_OUT[0])
    fake_eval(stale, 0.0, 0.0)
    calls = []
    monkeypatch.setattr(R, 'run_logged', lambda argv, log: calls.append(argv) or 5.0)
    R.run_cell_seed(cell, 0, runs, 'cpu', 20)
    budget = str(R.profile_steps('cpu', 'exploratory'))
    assert calls[0] == ['python', 'train.py', '--resume', str(d), '--total-steps', budget, '--no-progress']
    assert calls[1][:2] == ['python', 'eval.py'] and not stale.exists()  # re-evaluated, stale gone
    assert [c[c.index('--scene') + 1] for c in calls[2:]] == [str(R.ROOT / s) for s in R.HELD_OUT]
    side = json.loads((d / 'repro.json').read_text())
    assert side['train_wall_s'] == 35.0  # 30 s of the first run + 5 s of the extension
    # A run at its budget is left alone.
    calls.clear()
    rows = [json.loads(l) for l in (d / 'metrics.jsonl').read_text().splitlines()]
    rows[-1]['env_steps'] = int(budget)
    (d / 'metrics.jsonl').write_text(''.join(json.dumps(r) + '\n' for r in rows))
    R.run_cell_seed(cell, 0, runs, 'cpu', 20)
    assert calls == []
