"""notebooks/attention_analysis.ipynb runs top to bottom (nbclient) on the tiny CI configuration.

HRON_NB_TINY=1 makes the notebook train a tiny choice-task run itself (512 env steps, tiny model)
into a fresh HRON_RUN_DIR, roll it out without and with distractors and draw every figure; we check
that it produced its four figures and its attention summary. Budget: under 3 min on 2 CPU cores
(most of it is XLA compilation of the training program and of the two rollouts); measured 30 s
at load average ~1 and 173 s at ~7 on the shared 2-core development machine.
"""

import json
from pathlib import Path

import pytest

from hron_jax.paths import REPO_ROOT

nbformat = pytest.importorskip('nbformat')
nbclient = pytest.importorskip('nbclient')
pytest.importorskip('ipykernel')

ROOT = Path(REPO_ROOT)
NOTEBOOK = ROOT / 'notebooks' / 'attention_analysis.ipynb'


def test_attention_notebook_runs(tmp_path, monkeypatch):
    run_dir = tmp_path / 'run'
    # The kernel inherits this process's environment.
    monkeypatch.setenv('HRON_NB_TINY', '1')
    monkeypatch.setenv('HRON_RUN_DIR', str(run_dir))
    monkeypatch.setenv('JAX_PLATFORMS', 'cpu')
    monkeypatch.setenv('MPLBACKEND', 'module://matplotlib_inline.backend_inline')
    monkeypatch.setenv('JAX_COMPILATION_CACHE_DIR', str(tmp_path / 'xla'))
    nb = nbformat.read(NOTEBOOK, as_version=4)
    client = nbclient.NotebookClient(
        nb, timeout=240, kernel_name='python3', resources={'metadata': {'path': str(ROOT)}}
    )
    client.execute()

    errors = [
        o
        for c in nb.cells
        if c.cell_type == 'code'
        for o in c.get('outputs', [])
        if o.get('output_type') == 'error'
    ]
    assert not errors
    images = [
        o
        for c in nb.cells
        if c.cell_type == 'code'
        for o in c.get('outputs', [])
        if 'image/png' in o.get('data', {})
    ]
    assert len(images) >= 4, f'expected the 4 figures, got {len(images)} images'

    summary = json.loads((run_dir / 'attention_summary.json').read_text())
    assert summary['task'] == 'choice' and summary['model'] == 'rgbd_sg_attn'
    plain, dist = summary['summary']['no distractors'], summary['summary']['distractors']
    # Task-driven pooling takes every pooled feature from goal-category nodes in both conditions;
    # mean pooling is diluted by the distractor triangles.
    assert plain['pool_goal_share_model'] == pytest.approx(1.0)
    assert dist['pool_goal_share_model'] == pytest.approx(1.0)
    assert plain['pool_goal_share_mean'] == pytest.approx(1.0)
    assert dist['pool_goal_share_mean'] < 0.5
    assert dist['live_nodes'] > plain['live_nodes'] == 4
