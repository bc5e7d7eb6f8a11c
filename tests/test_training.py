"""train.py / eval.py: exact resume, vmapped seeds, sharded envs, SIGTERM, CLI errors, eval table.

All on CPU with the choice task and a tiny model (PPO itself is tested in test_ppo.py). Compiles
dominate the time, so everything compiles with --fast-compile (no LLVM optimisation: ~3x faster
compiles) and there are three programs: in-process single-seed runs (hron_jax.training
caches the program per program-relevant config, so every such run shares it), train.py
subprocesses on 2 forced CPU devices with 2 vmapped seeds (they share a persistent XLA cache, so
only the first one compiles), and eval.py.
"""

import dataclasses
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import jax
import numpy as np
import pytest

from hron_jax import evaluation
from hron_jax.bench import machine
from hron_jax.cli import config_from_args, tune_malloc
from hron_jax.cli import main as train_main
from hron_jax.errors import NonFiniteError
from hron_jax.paths import REPO_ROOT
from hron_jax.run_config import TrainConfig, make_config
from hron_jax.run_dir import load_config, read_metrics, restore_runner, run_machines
from hron_jax.training import Trainer, programs

ROOT = Path(REPO_ROOT)
TINY_MODEL = [
    'hidden=16',
    'heads=1',
    'gnn_layers=1',
    'goal_fc=16,16,16',
    'fusion_fc=32,32,32',
    'head_fc=32,32',
]
BATCH = 8 * 2  # num_envs x num_steps
TINY = dict(
    task='choice',
    model='rgbd_sg_attn',
    num_envs=8,
    num_steps=2,
    epochs=2,
    minibatches=2,
    lr=1e-3,
    log_every=2,
    checkpoint_every=4,
    model_option=TINY_MODEL,
    fast_compile=True,
)


def tiny_config(updates: int, **kw):
    return config_from_args(dict(TINY, total_steps=BATCH * updates, **kw))


def tiny_argv(updates: int) -> list[str]:
    argv = [
        '--task',
        'choice',
        '--num-envs',
        '8',
        '--num-steps',
        '2',
        '--epochs',
        '2',
        '--minibatches',
        '2',
        '--lr',
        '1e-3',
        '--log-every',
        '2',
        '--checkpoint-every',
        '4',
        '--total-steps',
        str(BATCH * updates),
        '--no-progress',
        '--fast-compile',
    ]
    for opt in TINY_MODEL:
        argv += ['--model-option', opt]
    return argv


def train(config, run_dir, **kw):
    trainer = Trainer(config, run_dir, progress=False, log=lambda s: None, **kw)
    try:
        runner = trainer.run()
    finally:
        trainer.close()
    return runner


def leaves(tree):
    return [np.asarray(x) for x in jax.tree.leaves(tree)]


def assert_trees_equal(a, b):
    la, lb = leaves(a), leaves(b)
    assert len(la) == len(lb)
    for x, y in zip(la, lb):
        np.testing.assert_array_equal(x, y)


def max_diff(a, b):
    return max(
        float(np.max(np.abs(x.astype(np.float64) - y.astype(np.float64))))
        for x, y in zip(leaves(a), leaves(b))
        if x.dtype.kind == 'f'
    )


@pytest.fixture(scope='module')
def xla_cache(tmp_path_factory):
    return str(tmp_path_factory.mktemp('xla_cache'))


def cli_env(xla_cache, devices=1) -> dict:
    """Environment of an entry-point subprocess: CPU JAX with `devices` host devices, the module's
    XLA cache, this checkout on the path."""
    env = dict(os.environ, JAX_PLATFORMS='cpu', JAX_COMPILATION_CACHE_DIR=xla_cache, PYTHONPATH=str(ROOT))
    env.pop('XLA_FLAGS', None)
    if devices > 1:
        env['XLA_FLAGS'] = f'--xla_force_host_platform_device_count={devices}'
    return env


def run_cli(script, argv, xla_cache, devices=1, **kw):
    return subprocess.run(
        [sys.executable, str(ROOT / script)] + argv,
        env=cli_env(xla_cache, devices),
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=240,
        **kw,
    )


def start_train(argv, xla_cache, devices=1) -> subprocess.Popen:
    """train.py in a background subprocess (stdout / stderr piped as text)."""
    return subprocess.Popen(
        [sys.executable, str(ROOT / 'train.py')] + argv,
        env=cli_env(xla_cache, devices),
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


@pytest.fixture(scope='module')
def reference(tmp_path_factory):
    """An uninterrupted 8-update single-seed run: (config, run dir, final RunnerState)."""
    config = tiny_config(8)
    run_dir = tmp_path_factory.mktemp('runs') / 'reference'
    return config, run_dir, train(config, run_dir)


# --- resume ------------------------------------------------------------------------------------
def test_resume_after_interruption_is_exact(reference, tmp_path):
    config, ref_dir, ref = reference
    run_dir = tmp_path / 'run'
    # Train 6 of 8 updates (chunks of 2, checkpoints at 4 and at exit = 6), then "kill" the
    # process after update 6 but before its checkpoint landed: drop checkpoint 6.
    trainer = Trainer(config, run_dir, progress=False, log=lambda s: None)
    trainer.run(max_updates=6)
    trainer.close()
    assert sorted(int(p.name) for p in (run_dir / 'checkpoints').iterdir()) == [0, 4, 6]
    shutil.rmtree(run_dir / 'checkpoints' / '6')

    resumed = train(load_config(run_dir), run_dir, resume=True)
    assert int(resumed.update[0]) == 8
    assert_trees_equal(resumed.params, ref.params)  # bitwise
    assert_trees_equal(resumed.opt_state, ref.opt_state)
    assert_trees_equal(resumed.env_state, ref.env_state)
    np.testing.assert_array_equal(resumed.rng, ref.rng)
    # The log was rewound to update 4 and continued: same rows as the uninterrupted run.
    rows, ref_rows = read_metrics(run_dir), read_metrics(ref_dir)
    assert [r['update'] for r in rows] == [2, 4, 6, 8]
    assert [r['success'] for r in rows] == [r['success'] for r in ref_rows]
    csv_lines = (run_dir / 'metrics.csv').read_text().strip().splitlines()
    assert len(csv_lines) == 5 and csv_lines[0].startswith('update,env_steps')
    assert (run_dir / 'learning_curve.png').stat().st_size > 0
    assert list((run_dir / 'tb').glob('events.out.tfevents.*'))
    # Each process (the start and the resume) names its machine and where it took the run up.
    procs = [json.loads(line) for line in (run_dir / 'processes.jsonl').read_text().splitlines()]
    assert [p['update'] for p in procs] == [0, 4]
    assert [m['cpu'] for m in run_machines(run_dir)] == [machine()['cpu']] * 2
    assert procs[1]['machine']['cores'] == os.cpu_count() and procs[1]['machine']['jax'] == jax.__version__


def test_resume_config_mismatch(reference, tmp_path, capsys):
    _, ref_dir, _ = reference
    run_dir = tmp_path / 'copy'
    shutil.copytree(ref_dir, run_dir)
    rc = train_main(['--resume', str(run_dir), '--lr', '0.5', '--num-envs', '16', '--compile-cache', 'none'])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and 'ppo.lr' in err and 'ppo.num_envs' in err and 'Traceback' not in err
    # An existing run is not overwritten without --resume.
    assert train_main(tiny_argv(8) + ['--out', str(run_dir), '--compile-cache', 'none']) == 2
    assert 'already holds a run' in capsys.readouterr().err
    # A checkpoint that does not fit the config (another model size) names the path.
    cfg = json.loads((run_dir / 'config.json').read_text())
    cfg['config']['network']['hidden'] = 32
    (run_dir / 'config.json').write_text(json.dumps(cfg))
    rc = train_main(['--resume', str(run_dir), '--compile-cache', 'none'])
    err = capsys.readouterr().err.strip()
    assert rc == 1 and str(run_dir / 'checkpoints' / '8') in err and 'does not match' in err


def damage(step_dir: Path) -> None:
    for f in step_dir.rglob('*'):
        if f.is_file() and f.stat().st_size > 1000:
            f.write_bytes(f.read_bytes()[:100])


def test_damaged_newest_checkpoint_falls_back_to_an_intact_one(reference, tmp_path, capsys):
    config, ref_dir, ref = reference
    run_dir = tmp_path / 'damaged'
    shutil.copytree(ref_dir, run_dir)
    # Checkpoints 0, 4, 8: the newest is damaged; resuming falls back to 4, moves 8 aside (kept),
    # and recomputes updates 5-8 exactly.
    damage(run_dir / 'checkpoints' / '8')
    config = load_config(run_dir)
    messages = []
    trainer = Trainer(config, run_dir, resume=True, progress=False, log=messages.append)
    assert trainer.update == 4
    assert any('falling back to checkpoint 4' in m for m in messages), messages
    assert (run_dir / 'corrupt_checkpoints' / '8').is_dir()
    try:
        resumed = trainer.run()
    finally:
        trainer.close()
    assert_trees_equal(resumed.params, ref.params)
    assert [r['update'] for r in read_metrics(run_dir)] == [2, 4, 6, 8]
    # With every checkpoint damaged there is nothing to fall back to: one line, exit 1.
    for step in (0, 4, 8):
        damage(run_dir / 'checkpoints' / str(step))
    rc = train_main(['--resume', str(run_dir), '--compile-cache', 'none'])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 1 and 'Traceback' not in '\n'.join(err)
    assert err[-1].startswith('train.py: error:') and 'no older checkpoint' in err[-1]


def test_nan_stops_the_run_and_keeps_the_last_finite_checkpoint(reference, tmp_path):
    config, _, _ = reference
    run_dir = tmp_path / 'nan'
    trainer = Trainer(config, run_dir, progress=False, log=lambda s: None)
    try:
        trainer.run(max_updates=2)
        good = trainer.runner
        # Inject a NaN into one weight (as an overflowing update would leave it).
        ws, treedef = jax.tree.flatten(good.params)
        ws[0] = ws[0].at[(0,) * ws[0].ndim].set(np.nan)
        trainer.runner = good.replace(params=jax.tree.unflatten(treedef, ws))
        with pytest.raises(NonFiniteError, match='at update 3 '):
            trainer.run()
        assert trainer.update == 2
    finally:
        trainer.close()
    # The exit path checkpointed update 2 (the state the NaN entered into was never taken); it is
    # finite, and the metrics log ends at update 2.
    assert sorted(int(p.name) for p in (run_dir / 'checkpoints').iterdir()) == [0, 2]
    restored, step = restore_runner(run_dir, programs(config).abstract)
    assert step == 2
    assert all(np.isfinite(x).all() for x in leaves(restored.params))
    assert [r['update'] for r in read_metrics(run_dir)] == [2]


# --- seeds and devices: one sharded, multi-seed train.py run -------------------------------------
@pytest.fixture(scope='module')
def sharded_two_seeds(tmp_path_factory, xla_cache):
    """train.py on 2 forced CPU devices (envs sharded) with seeds 0 and 1 vmapped: its run dir.
    (One compile covers both checks below; their errors do not add up beyond 1e-6: measured
    3e-7 for vmapped vs single, 1.5e-7 for sharded vs unsharded.)"""
    run_dir = tmp_path_factory.mktemp('runs') / 'sharded_two_seeds'
    r = run_cli('train.py', tiny_argv(8) + ['--num-seeds', '2', '--out', str(run_dir)], xla_cache, devices=2)
    assert r.returncode == 0, r.stderr[-2000:]
    return run_dir


@pytest.fixture(scope='module')
def seed1(tmp_path_factory):
    """Single-seed run with --seed 1 (the `reference` program: no compile)."""
    return train(tiny_config(8, seed=1), tmp_path_factory.mktemp('runs') / 'seed1')


def test_vmapped_seeds_differ_and_match_single_runs(reference, seed1, sharded_two_seeds):
    _, _, ref = reference
    config = load_config(sharded_two_seeds)
    assert config.num_seeds == 2 and config.seed == 0
    two, _ = restore_runner(sharded_two_seeds, programs(config).abstract)
    for i, single in enumerate((ref, seed1)):
        assert max_diff(jax.tree.map(lambda x: x[i : i + 1], two.params), single.params) < 1e-6
    assert (
        max_diff(jax.tree.map(lambda x: x[:1], two.params), jax.tree.map(lambda x: x[1:], two.params)) > 1e-3
    )
    row = read_metrics(sharded_two_seeds)[-1]
    assert row['seeds'] == 2 and len(row['per_seed']['success']) == 2
    assert row['success'] == pytest.approx(np.mean(row['per_seed']['success']))


def test_sharded_run_matches_unsharded(reference, sharded_two_seeds):
    _, _, ref = reference
    meta = json.loads((sharded_two_seeds / 'config.json').read_text())['meta']
    assert len(meta['devices']) == 2
    config = load_config(sharded_two_seeds)
    runner, step = restore_runner(sharded_two_seeds, programs(config).abstract)
    assert step == 8
    assert max_diff(jax.tree.map(lambda x: x[:1], runner.params), ref.params) < 1e-6
    # The restore put the env state back onto this process's single device.
    assert len(jax.tree.leaves(runner.env_state)[0].sharding.device_set) == 1


def test_two_processes_train_like_one_with_two_devices(tmp_path, xla_cache, sharded_two_seeds):
    """Multi-host: two train.py processes of one CPU device each, joined by jax.distributed on
    localhost, train the program of `sharded_two_seeds` (2 devices, 2 seeds) to bitwise the same
    parameters and metrics; only process 0 writes the logs."""
    import socket

    with socket.socket() as s:
        s.bind(('localhost', 0))
        port = s.getsockname()[1]
    run_dir = tmp_path / 'two_hosts'
    argv = tiny_argv(8) + ['--num-seeds', '2', '--out', str(run_dir)]
    argv += ['--coordinator', f'localhost:{port}', '--num-processes', '2']
    procs = [start_train(argv + ['--process-id', str(i)], xla_cache) for i in range(2)]
    errs = [p.communicate(timeout=240)[1] for p in procs]
    for p, err in zip(procs, errs):
        assert p.returncode == 0, err[-2000:]
    assert 'done: 8 updates' in errs[0] and errs[1] == ''  # process 0 reports for the job
    config = load_config(run_dir)
    assert config == load_config(sharded_two_seeds)
    abstract = programs(config).abstract
    two_hosts, step = restore_runner(run_dir, abstract)
    one_host, _ = restore_runner(sharded_two_seeds, abstract)
    assert step == 8
    assert_trees_equal(two_hosts.params, one_host.params)
    assert_trees_equal(two_hosts.env_state, one_host.env_state)
    rows, ref_rows = read_metrics(run_dir), read_metrics(sharded_two_seeds)
    assert [r['update'] for r in rows] == [2, 4, 6, 8]  # written once, by process 0
    assert [r['per_seed']['return'] for r in rows] == [r['per_seed']['return'] for r in ref_rows]


# --- signals -----------------------------------------------------------------------------------
def test_sigterm_checkpoints_and_resume_continues(tmp_path, xla_cache, sharded_two_seeds):
    # The program of `sharded_two_seeds` (2 devices, 2 seeds) again: it comes from the XLA cache.
    updates = 150  # ~2 s of training on an idle machine: time to send the signal mid-run
    run_dir = tmp_path / 'sig'
    argv = tiny_argv(updates) + ['--num-seeds', '2', '--checkpoint-every', '1000']  # ckpt: init, exit
    popen = lambda out: start_train(argv + ['--out', str(out)], xla_cache, devices=2)
    proc = popen(run_dir)
    full = popen(tmp_path / 'uninterrupted')  # the reference, meanwhile
    deadline = time.time() + 200
    while time.time() < deadline and proc.poll() is None:
        if len(read_metrics(run_dir)) >= 1:  # training has started
            break
        time.sleep(0.02)
    assert proc.poll() is None, proc.communicate()[1][-2000:]
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 128 + signal.SIGTERM, err[-2000:]
    assert 'Traceback' not in err and '--resume' in err
    steps = sorted(int(p.name) for p in (run_dir / 'checkpoints').iterdir())
    stopped = steps[-1]
    assert steps[0] == 0 and 0 < stopped < updates and stopped % 2 == 0  # at a chunk boundary
    assert read_metrics(run_dir)[-1]['update'] == stopped

    r = run_cli('train.py', ['--resume', str(run_dir), '--no-progress'], xla_cache, devices=2)
    assert r.returncode == 0, r.stderr[-2000:]
    assert f'resumed {run_dir} at update {stopped}' in r.stderr
    rows = read_metrics(run_dir)
    assert [x['update'] for x in rows] == list(range(2, updates + 1, 2))
    # Bitwise the same final state as the uninterrupted run.
    assert full.wait(timeout=200) == 0, full.communicate()[1][-2000:]
    abstract = programs(load_config(run_dir)).abstract
    final, step = restore_runner(run_dir, abstract)
    ref, ref_step = restore_runner(tmp_path / 'uninterrupted', abstract)
    assert step == ref_step == updates
    assert_trees_equal(final, ref)


# --- CLI errors --------------------------------------------------------------------------------
BAD_CLI = [
    (['--task', 'navigate'], 1, "invalid choice: 'navigate'"),
    (['--task', 'choice', '--model', 'resnet'], 1, "invalid choice: 'resnet'"),
    (['--task', 'directed', '--scene', 'scenes/no_such_scene.xml'], 1, 'scene file not found'),
    (['--task', 'choice', '--num-envs', '7'], 2, 'not divisible by the 2 devices (cpu, this process)'),
    (
        ['--task', 'choice', '--num-envs', '6', '--num-steps', '1', '--minibatches', '4'],
        1,
        '--minibatches: must divide the rollout',
    ),
    (['--task', 'choice', '--coordinator', 'localhost:1'], 1, '--num-processes and --process-id go together'),
    (
        ['--task', 'choice', '--coordinator', 'localhost:1', '--num-processes', '2', '--process-id', '2'],
        1,
        '--process-id 2: must be in 0 .. 1',
    ),
]


def test_bad_cli_input_is_one_clear_line(tmp_path, xla_cache):
    procs = [  # all at once: each is mostly imports
        start_train(argv + ['--out', str(tmp_path / f'never{i}')], xla_cache, devices)
        for i, (argv, devices, _) in enumerate(BAD_CLI)
    ]
    for i, ((argv, _, needle), proc) in enumerate(zip(BAD_CLI, procs)):
        _, err = proc.communicate(timeout=120)
        err = err.strip()
        assert proc.returncode == 2, (argv, err)
        assert needle in err and err.startswith('train.py: error:'), (argv, err)
        assert len(err.splitlines()) == 1, (argv, err)
        assert not (tmp_path / f'never{i}').exists()


# Every option with values a user could get wrong: zero, negative, wrong type, out of range,
# cross-field (minibatches that do not divide the rollout, heads that do not divide hidden).
BAD_VALUES = {
    '--num-envs': ['0', '-5', 'abc', '2.5'],
    '--total-steps': ['0', '-1', '10', 'x'],
    '--seed': ['-1', 'abc'],
    '--num-seeds': ['0', '-2'],
    '--log-every': ['0'],
    '--checkpoint-every': ['0', '-1'],
    '--keep-checkpoints': ['0'],
    '--num-steps': ['0', '-3'],
    '--epochs': ['0'],
    '--minibatches': ['0', '-1', '3'],
    '--lr': ['0', '-1', 'nan', 'inf', 'abc'],
    '--gamma': ['-0.1', '1.5', 'nan'],
    '--gae-lambda': ['2'],
    '--clip-eps': ['0', '-0.2'],
    '--ent-coef': ['-0.01'],
    '--vf-coef': ['-1'],
    '--max-grad-norm': ['-1'],
    '--task': ['navigate'],
    '--model': ['resnet'],
    '--env-option': ['max_distractors=-1', 'image_size=0', 'nonsense=1', 'noequals', 'max_distractors=abc'],
    '--model-option': ['hidden=0', 'heads=3', 'cnn_fc=16,0,16', 'gnn=gcn', 'hidden=x'],
}
NAV_BAD_VALUES = {  # fields of the navigation env, dotted into its sub-configs
    '--env-option': [
        'max_steps=0',
        'camera.width=0',
        'success_distance=-1',
        'camera.vfov_deg=190',
        'camera.k_band=0',
        'sim.physics=mjx',
        'sim.collider=box',
        'sim.warp_contacts_per_env=0',
        'camera.nope=1',
        'num_distractors=-2',
    ],
}


def bad_cases():
    for task, table in (('choice', BAD_VALUES), ('directed', NAV_BAD_VALUES)):
        for option, values in table.items():
            for value in values:
                yield pytest.param(task, option, value, id=f'{task} {option} {value}')


@pytest.mark.parametrize('task,option,value', list(bad_cases()))
def test_every_option_rejects_bad_values_in_one_line(task, option, value, tmp_path, capsys):
    argv = ['--task', task] if option != '--task' else []
    rc = train_main(
        argv + [option, value, '--out', str(tmp_path / 'never'), '--compile-cache', 'none', '--no-progress']
    )
    err = capsys.readouterr().err.strip()
    assert rc == 2, (option, value, err)
    assert len(err.splitlines()) == 1 and err.startswith('train.py: error:'), err
    name = value.split('=')[0] if option.endswith('-option') and '=' in value else ''
    assert option in err and name in err, err  # it names what to fix
    assert not (tmp_path / 'never').exists()


def test_config_json_of_the_flat_format_is_upgraded():
    """config.json files written before the typed tree (flat env_options / model_options) load
    as the same config the new CLI builds."""
    old = {
        'task': 'exploratory',
        'model': 'rgbd_sg',
        'scene': 'scenes/house.xml',
        'distractors': True,
        'premap': True,
        'env_options': [['image_size', 8], ['max_steps', 40]],
        'model_options': [['hidden', 16], ['cnn_fc', [16, 16, 16]]],
        'ppo': dict(vars(make_config('exploratory').ppo), seed=3, num_envs=4),
        'seed': 3,
        'num_seeds': 1,
        'log_every': 1,
        'checkpoint_every': 20,
        'keep_checkpoints': 3,
        'fast_compile': False,
    }
    new = config_from_args(
        dict(
            task='exploratory',
            model='rgbd_sg',
            distractors=True,
            premap=True,
            num_envs=4,
            seed=3,
            # Those runs discovered an instance from 2 pixels of their own 8x8 frame.
            env_option=['image_size=8', 'max_steps=40', 'graph.pixel_reference=8'],
            model_option=['hidden=16', 'cnn_fc=16,16,16'],
        )
    )
    assert TrainConfig.from_dict(old) == new
    assert new.env.camera.width == new.env.camera.height == 8 and new.env.premap and new.distractors
    assert new.network.pooling == 'mean' and new.network.hidden == 16


def test_config_json_before_physics_fields_names_what_ran():
    """A typed config.json written before SimConfig had `physics` and `collider` loads as what
    those runs ran: MJX's JAX implementation, the agent colliding as its capsule."""
    d = make_config('exploratory').to_dict()
    del d['env']['sim']['physics'], d['env']['sim']['collider']
    old = TrainConfig.from_dict(d)
    assert (old.env.sim.physics, old.env.sim.collider) == ('jax', 'capsule')
    assert make_config('exploratory').env.sim.collider == 'sphere'


def test_paper_preset_sets_camera_hgt_and_ppo_and_flags_override_it():
    paper = config_from_args(dict(task='exploratory', preset='paper'))
    assert paper.preset == 'paper'
    assert (paper.env.camera.width, paper.env.camera.height) == (128, 128)
    assert paper.network.hgt_softmax == 'per_relation'
    p = paper.ppo
    assert (p.num_envs * p.num_steps, p.minibatch_size, p.update_epochs, p.lr) == (4096, 128, 30, 1e-4)
    assert (p.gamma, p.gae_lambda, p.kl_coeff, p.max_grad_norm, p.advantage_norm) == (
        0.99,
        0.9,
        0.2,
        0.0,
        'batch',
    )
    # Flags win over the preset; the rest of the preset stays; config.json keeps both.
    mine = config_from_args(
        dict(task='exploratory', preset='paper', num_envs=16, env_option=['image_size=64'])
    )
    assert mine.ppo.num_envs == 16 and mine.ppo.update_epochs == 30
    assert (mine.env.camera.width, mine.env.camera.height) == (64, 64)
    assert TrainConfig.from_dict(mine.to_dict()) == mine
    # The default preset is the per-task defaults; the choice task takes the PPO part only.
    assert config_from_args(dict(task='exploratory')).preset == 'default'
    choice = config_from_args(dict(task='choice', preset='paper'))
    assert choice.ppo == dataclasses.replace(paper.ppo, total_timesteps=200_000)  # its own budget
    assert choice.network.hgt_softmax == 'per_relation'


def test_progress_sr_waits_until_every_env_can_have_ended_an_episode():
    from types import SimpleNamespace

    config = config_from_args(dict(task='exploratory'))  # 500-step episodes, 64-step rollouts
    rows = [
        dict(update=u, success=s, episodes=n)
        for u, s, n in [(1, 1.0, 3), (2, 1.0, 5), (9, 0.5, 40), (10, 0.25, 40)]
    ]
    postfix = lambda update: Trainer._postfix(
        SimpleNamespace(config=config, update=update, metrics=SimpleNamespace(rows=rows[:update])), {}
    )
    # Update 2: 128 steps per env, only early (successful) episodes can have ended: no SR shown.
    assert 'SR n/a until 500 steps/env (8 early eps)' in postfix(2)
    # Update 10: 640 steps per env; the window is the last 8 updates (one episode length): 3..10.
    assert 'SR 0.375 (80 eps)' in Trainer._postfix(
        SimpleNamespace(config=config, update=10, metrics=SimpleNamespace(rows=rows)), {}
    )


# --- eval ----------------------------------------------------------------------------------------
def test_eval_summary_spread_is_the_sample_std_over_seeds():
    """eval.md's ± over seeds is the report's: sample std (ddof=1) of the per-seed means."""
    success = np.array([[1, 1, 0, 0], [1, 1, 1, 1], [0, 0, 0, 1]], np.float64)  # per seed 0.5, 1, 0.25
    s = evaluation.summarize(
        {'success': success, 'spl': success / 2, 'episode_length': success, 'finished': success >= 0}
    )
    assert s['success']['per_seed'] == [0.5, 1.0, 0.25]
    assert s['success']['std_seeds'] == pytest.approx(0.381881, abs=1e-6)  # ddof=0 would be 0.311805
    table = evaluation.markdown_table(
        [dict(task='choice', distractors=False, model='SG', policy='trained', mode='sampled', summary=s)]
    )
    assert '| 0.583 ± 0.382 | 0.292 ± 0.191 |' in table and 'ddof=1' in table
    one = evaluation.summarize(
        {
            k: v[:1]
            for k, v in dict(
                success=success, spl=success, episode_length=success, finished=success >= 0
            ).items()
        }
    )
    assert one['success']['std_seeds'] == 0.0


def test_eval_writes_table(reference, tmp_path, xla_cache):
    _, ref_dir, _ = reference
    out = tmp_path / 'eval'
    r = run_cli('eval.py', [str(ref_dir), '--episodes', '6', '--out', str(out)], xla_cache)
    assert r.returncode == 0, r.stderr[-2000:]
    table = (out / 'eval.md').read_text()
    assert (
        '| SR ↑ | SPL ↑ |' in table and '| choice | no | SG + TD ATTN | trained (sampled) | 1 x 6 |' in table
    )
    assert table.splitlines()[2] in r.stdout
    # compile and play timed apart: 1 seed x 6 one-step episodes
    assert re.search(r'compiled in \d+\.\d s; played 6 env steps in \d+\.\d s \(\d+ steps/s', r.stderr)
    res = json.loads((out / 'eval.json').read_text())
    assert res['step'] == 8 and res['summary']['episodes'] == 6
    sr = np.asarray(res['per_episode']['success'])
    assert sr.shape == (1, 6) and res['summary']['success']['mean'] == pytest.approx(sr.mean())
    assert (out / 'trajectories.png').stat().st_size > 0
    # A reference policy needs no run: the choice oracle is always right (in-process: no imports).
    rc = evaluation.main(
        [
            '--policy',
            'oracle',
            '--task',
            'choice',
            '--episodes',
            '5',
            '--plots',
            '0',
            '--out',
            str(tmp_path / 'oracle'),
            '--compile-cache',
            'none',
        ]
    )
    assert rc == 0
    assert '1.000 ± 0.000 | 1.000 ± 0.000 |' in (tmp_path / 'oracle' / 'eval.md').read_text()


# --- scenes in run dirs, held-out evaluation --------------------------------------------------------
def test_scene_paths_are_repo_relative_and_resolve_anywhere(tmp_path):
    inside = make_config('exploratory', overrides={'scene': str(ROOT / 'scenes' / 'house.xml')})
    assert inside.scene == 'scenes/house.xml'  # config.json survives moving the repository
    assert inside.scene_path == str(ROOT / 'scenes' / 'house.xml')
    assert TrainConfig.from_dict(inside.to_dict()) == inside
    outside = tmp_path / 'my_house.xml'
    cfg = make_config('exploratory', overrides={'scene': str(outside)})
    assert cfg.scene == str(outside) and cfg.scene_path == str(outside)


def test_eval_on_a_held_out_scene(tmp_path, monkeypatch):
    """eval.py RUN --scene OTHER evaluates the run's policy in a house it never saw: the env it
    builds is the held-out house, its episodes start where that house's episode sampler puts the
    eval keys' episodes (not where the training house's would), and eval.json reports exactly
    those episodes with consistent SR / SPL / lengths."""
    import jax.numpy as jnp

    from hron_jax.scenes.loader import load_scene
    from hron_jax.training import programs

    config = config_from_args(
        dict(
            task='exploratory',
            model='rgbd_sg_attn',
            num_envs=2,
            num_steps=2,
            epochs=1,
            minibatches=1,
            total_steps=4,
            log_every=1,
            checkpoint_every=1,
            fast_compile=True,
            env_option=['image_size=8'],
            model_option=TINY_MODEL + ['cnn_fc=16,16,16'],
            scene=str(ROOT / 'scenes' / 'house.xml'),
        )
    )
    run_dir = tmp_path / 'run'
    train(config, run_dir)
    # a navigation run logs the mean fraction of camera rays its renderer could not certify
    assert all(0.0 <= r['uncertain_rays'] <= 1.0 for r in read_metrics(run_dir))
    held_out = ROOT / 'scenes' / 'house_1.xml'
    seen = {}
    real_evaluate = evaluation.evaluate

    def spy(env, *args, **kw):
        seen['env'] = env
        seen['result'] = real_evaluate(env, *args, **kw)
        return seen['result']

    monkeypatch.setattr(evaluation, 'evaluate', spy)
    episodes = 2
    rc = evaluation.main(
        [
            str(run_dir),
            '--scene',
            str(held_out),
            '--episodes',
            str(episodes),
            '--plots',
            '0',
            '--compile-cache',
            'none',
        ]
    )
    assert rc == 0
    res = json.loads((run_dir / 'eval_trained_sampled_house_1' / 'eval.json').read_text())
    assert res['config']['scene'] == 'scenes/house_1.xml' and res['step'] == 1
    assert res['model'] == 'rgbd_sg_attn' and res['task'] == 'exploratory'
    assert res['summary']['episodes'] == episodes and res['summary']['seeds'] == 1

    # The env that played the episodes is the held-out house (not the training one).
    env, result = seen['env'], seen['result']
    env = getattr(env, 'unwrapped', env)
    house_1, house = load_scene(held_out), load_scene(ROOT / 'scenes' / 'house.xml')
    assert Path(env.scene.path).resolve() == held_out.resolve()
    np.testing.assert_array_equal(env.scene.bounds, house_1.bounds)
    assert not np.array_equal(house_1.bounds, house.bounds)
    assert not env.auto_reset  # episodic evaluation

    # Its episodes are the held-out house's episodes for the eval keys (reset(fold_in(key, i))
    # draws sample_episode(split(.)[0])): start pose and goal, and the training house would have
    # drawn other ones.
    keys = jax.vmap(lambda i: jax.random.split(jax.random.fold_in(jax.random.PRNGKey(0), i))[0])(
        jnp.arange(episodes)
    )
    want = jax.device_get(jax.vmap(env.sample_episode)(keys))
    train_env = programs(config).env  # the training house's env (cached by train above)
    train_env = getattr(train_env, 'unwrapped', train_env)
    other = jax.device_get(jax.vmap(train_env.sample_episode)(keys))
    start = result['poses'][0, :, 0]  # [E, 3] pose before the first step
    np.testing.assert_allclose(start, want.pose, atol=1e-5)
    np.testing.assert_array_equal(np.asarray(result['states'].inner.goal)[0], want.goal)
    assert np.abs(start - other.pose).max() > 0.1
    lo, hi = house_1.bounds[0, :2], house_1.bounds[1, :2]
    assert ((start[:, :2] > lo) & (start[:, :2] < hi)).all()
    goal_rows = {tuple(g) for g in env.tables.goals[env.tables.goal_ok]}
    assert all(tuple(g) in goal_rows for g in want.goal)

    # eval.json holds exactly these episodes, and their metrics are consistent.
    per = {k: np.asarray(v) for k, v in res['per_episode'].items()}
    for k in ('success', 'spl', 'episode_length', 'path_length', 'return'):
        assert per[k].shape == (1, episodes), k
        np.testing.assert_allclose(per[k], result[k], rtol=1e-6, err_msg=k)
    for k in ('success', 'spl'):
        assert 0.0 <= res['summary'][k]['mean'] <= 1.0
        assert res['summary'][k]['mean'] == pytest.approx(per[k].mean())
    sr, spl, length = per['success'], per['spl'], per['episode_length']
    assert set(np.unique(sr)) <= {0.0, 1.0}
    assert ((spl >= 0) & (spl <= sr + 1e-6)).all() and (spl[sr == 0] == 0).all()
    d0, path = result['d0'], per['path_length']
    np.testing.assert_allclose(spl, sr * d0 / np.maximum(d0, path), rtol=1e-5, atol=1e-6)
    max_steps = res['config']['env']['max_steps']
    np.testing.assert_array_equal(length, result['end'] + 1)
    assert (length <= max_steps).all() and (length[sr == 0] == max_steps).all()  # failure = time limit
    assert (path <= env.sim.config.forward_m * length + 1e-3).all()
    # The training scene is untouched in the run's own config.
    assert load_config(run_dir).scene == 'scenes/house.xml'
    assert evaluation.main([str(run_dir), '--scene', 'scenes/no_such_scene.xml']) == 2


@pytest.mark.parametrize(
    'argv,needle',
    [
        (['--scene', 'scenes/house_1.xml'], 'the choice task has no scene'),
        (['--distractors'], 'drop --task / --distractors'),
    ],
)
def test_eval_rejects_bad_env_options_with_a_run(reference, argv, needle, capsys):
    _, ref_dir, _ = reference
    assert evaluation.main([str(ref_dir)] + argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith('eval.py: error:') and needle in err and len(err.splitlines()) == 1


def test_tune_malloc_applies_on_glibc_cpu_only(monkeypatch):
    # Its speed effect is measured by `python -m hron_jax.bench model` (README); here: it applies
    # where JAX computes on the CPU, and not where a GPU would run the program.
    import platform

    if platform.libc_ver()[0] != 'glibc':
        pytest.skip('not a glibc system')
    monkeypatch.setenv('JAX_PLATFORMS', 'cuda')
    assert tune_malloc() is False
    monkeypatch.setenv('JAX_PLATFORMS', 'cpu')
    assert tune_malloc() is True


def test_learning_curve_points_pool_episodes_per_seed():
    """Each curve point is the episode-weighted mean over the fewest trailing chunks holding
    >= min_episodes of that seed's episodes (worked by hand); std is over seeds (ddof=1)."""
    from hron_jax.metrics_log import curve_rows, pooled_curve

    def row(step, episodes, success):
        return {'env_steps': step, 'per_seed': {'episodes': episodes, 'success': success, 'return': success}}

    rows = [
        row(100, [0, 3], [None, 1.0]),
        row(200, [2, 1], [0.5, 0.0]),
        row(300, [3, 4], [1.0, 0.25]),
        row(400, [0, 0], [None, None]),
    ]
    steps, pooled = pooled_curve(rows, ('success',), min_episodes=4)
    np.testing.assert_array_equal(steps, [100, 200, 300, 400])
    # seed 0: 2 episodes by 200; chunks 200-300 hold 5: (2 x 0.5 + 3 x 1.0) / 5; 400 adds none.
    # seed 1: chunks 100-200 hold 4: (3 x 1 + 1 x 0) / 4; from 300 on, chunk 300 alone holds 4.
    np.testing.assert_allclose(pooled['success'], [[np.nan, np.nan, 0.8, 0.8], [np.nan, 0.75, 0.25, 0.25]])
    curve = curve_rows([rows], ('success',), min_episodes=4)
    assert [r['success'] for r in curve[:2]] == [None, 0.75]
    assert curve[1]['success_std'] is None  # one seed has a point there
    assert curve[2]['success'] == pytest.approx(0.525)
    assert curve[2]['success_std'] == pytest.approx(0.55 / np.sqrt(2))
    # A second run (rows without per_seed count as one seed) joins the seeds at the steps it has.
    other = [{'env_steps': 300, 'episodes': 6, 'success': 0.5}]
    joined = {r['env_steps']: r for r in curve_rows([rows, other], ('success',), min_episodes=4)}
    assert joined[300]['success'] == pytest.approx((0.8 + 0.25 + 0.5) / 3)
    assert joined[400]['success'] == pytest.approx(0.525)


def test_compile_drops_only_the_options_this_xla_does_not_know():
    """XLA drops flags between releases (jax 0.11's has no xla_cpu_use_fusion_emitters): an unknown
    option is left out and the program still compiles and computes; any other bad option still
    fails, naming itself; supported_options gives jax.jit the options this XLA knows."""
    import jax.numpy as jnp

    from hron_jax.training import FAST_COMPILE, compile_lowered, supported_options

    lowered = jax.jit(lambda x: 2.0 * x + 1.0).lower(jnp.arange(3.0))
    options = dict(FAST_COMPILE, xla_option_no_release_has=True)
    out = compile_lowered(lowered, options)(jnp.arange(3.0))
    np.testing.assert_array_equal(np.asarray(out), [1.0, 3.0, 5.0])
    assert 'xla_option_no_release_has' in options  # the caller's dict is left as it was
    with pytest.raises(jax.errors.JaxRuntimeError, match='xla_backend_optimization_level'):
        compile_lowered(lowered, {'xla_backend_optimization_level': 'abc'})
    # jax.jit(..., compiler_options=...) call sites get the options this XLA knows.
    known = supported_options(dict(FAST_COMPILE, xla_option_no_release_has_either=False))
    assert 'xla_option_no_release_has_either' not in known
    assert known.get('xla_backend_optimization_level') == 0  # known to every release so far
    fn = jax.jit(lambda x: 2.0 * x + 1.0, compiler_options=known)
    np.testing.assert_array_equal(np.asarray(fn(jnp.arange(3.0))), [1.0, 3.0, 5.0])
