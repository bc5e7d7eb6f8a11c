"""The benchmarks: the profiling attribution of `python -m hron_jax.bench profile` / `compile
--by-source` (XLA ops of a trace are mapped to the hron_jax module whose code emitted them), and the
prepared GPU-lease script tools/gpu_bench.sh, whose every command the CLIs must accept (a bad
option there would waste a rare lease)."""

import inspect
import json
import os
import re
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hron_jax.bench.__main__ import build_parser as bench_parser
from hron_jax.bench.hlo import (
    deep_tracebacks,
    hlo_by_source,
    hlo_instructions,
    instruction_sources,
    kernel_traffic,
)
from hron_jax.bench.profile import op_times
from hron_jax.cli import build_parser as train_parser
from hron_jax.cli import config_from_args
from hron_jax.evaluation import build_parser as eval_parser
from hron_jax.paths import REPO_ROOT
from hron_jax.ppo import compute_gae


@pytest.fixture
def deep_stacks():
    limit = jax.config.jax_traceback_in_locations_limit
    deep_tracebacks()
    yield
    jax.config.update('jax_traceback_in_locations_limit', limit)  # other tests compile leaner


def test_profiled_ops_are_attributed_to_their_source_module(tmp_path, deep_stacks):
    T, B = 64, 256
    rng = np.random.default_rng(0)
    reward, value = (jnp.asarray(rng.normal(size=(T, B)), jnp.float32) for _ in range(2))
    done = jnp.asarray(rng.random((T, B)) < 0.1)
    final_value, last_value = jnp.zeros((T, B)), jnp.ones(B)

    def gae_then_loss(reward, value):  # ppo.py's GAE, then a reduction of this file's own
        adv, target = compute_gae(reward, value, done, done & False, final_value, last_value, 0.99, 0.95)
        return jnp.square(adv - target).sum()

    fn = jax.jit(gae_then_loss).lower(reward, value).compile()
    sources = instruction_sources(fn.as_text())
    assert 'ppo.py' in {s for _, s, _ in sources.values()}
    assert any(
        'scan' in name_stack or 'while' in name_stack
        for _, s, name_stack in sources.values()
        if s == 'ppo.py'
    )
    assert sum(hlo_by_source(fn.as_text()).values()) == len(sources)
    # with lines: the same ops at file:line, and ppo.py's are lines of compute_gae
    by_line = instruction_sources(fn.as_text(), lines=True)
    assert all(re.sub(r':\d+', '', by_line[k][1]) == v[1] for k, v in sources.items())
    body, first = inspect.getsourcelines(compute_gae)
    gae = {int(s.split(':')[1]) for _, s, _ in by_line.values() if s.startswith('ppo.py:')}
    assert len(gae) > 3 and all(first < n < first + len(body) for n in gae), (gae, first)
    # bench compile's count: the same instructions plus the parameters instruction_sources skips
    parameters = sum(' parameter(' in line for line in fn.as_text().splitlines())
    assert parameters >= 2 and hlo_instructions(fn.as_text()) == len(sources) + parameters
    jax.block_until_ready(fn(reward, value))
    with jax.profiler.trace(str(tmp_path)):
        jax.block_until_ready(fn(reward, value))
    (path,) = tmp_path.glob('**/*.xplane.pb')
    times = op_times(str(path))
    assert times and set(times) <= set(sources), set(times) - set(sources)
    assert all(t >= 0 for t in times.values())
    # GAE's reverse scan (a while loop) is ppo.py's; the only ops of no module are XLA's copies
    by_source = {sources[n][1] for n in times}
    assert 'ppo.py' in by_source
    assert all(
        s in ('ppo.py', "(XLA's own: no source)") or s.startswith('(no hron_jax frame)') for s in by_source
    )


def test_ops_without_our_frames_name_their_library(deep_stacks):
    # JAX drops its own frames from op stacks, so library code that is not JAX's (here optax, in
    # the chunk MJX) is what an op without a hron_jax frame can name
    import optax

    opt = optax.adam(1e-3)
    params = {'w': jnp.ones((4, 3))}
    fn = jax.jit(lambda g, s: opt.update(g, s, params)[0]).lower(params, opt.init(params)).compile()
    sources = {s for _, s, _ in instruction_sources(fn.as_text()).values()}
    assert '(no hron_jax frame) via optax' in sources, sources


# A module as XLA prints it: a table copied into a while loop of 7 known trips that gathers 10
# rows of it, scatter-adds them back and stores them at a row (both in place), then a loop whose
# trip count XLA does not know, a gather from the concatenation of two tables, a conditional, and
# a fusion that slices 100 rows of an elementwise product of two whole tables.
_TRAFFIC_MODULE = """HloModule traffic

%gather_rows (param_0: f32[1000,64], param_1: s32[10,1]) -> f32[10,64] {
  %param_0 = f32[1000,64]{1,0} parameter(0)
  %param_1 = s32[10,1]{1,0} parameter(1)
  %bitcast.1 = f32[1000,64]{1,0} bitcast(%param_0)
  ROOT %gather.1 = f32[10,64]{1,0} gather(%bitcast.1, %param_1), offset_dims={1}, slice_sizes={1,64}
}

%add (a: f32[], b: f32[]) -> f32[] {
  %a = f32[] parameter(0)
  %b = f32[] parameter(1)
  ROOT %sum = f32[] add(%a, %b)
}

%scatter_rows (param_0.1: f32[1000,64], param_1.1: s32[10,1], param_2: f32[10,64]) -> f32[1000,64] {
  %param_0.1 = f32[1000,64]{1,0} parameter(0)
  %param_1.1 = s32[10,1]{1,0} parameter(1)
  %param_2 = f32[10,64]{1,0} parameter(2)
  %negate.1 = f32[10,64]{1,0} negate(%param_2)
  ROOT %scatter.1 = f32[1000,64]{1,0} scatter(%param_0.1, %param_1.1, %negate.1), to_apply=%add
}

%store_rows (param_0.3: f32[1000,64], param_1.3: f32[10,64], param_2.3: s32[]) -> f32[1000,64] {
  %param_0.3 = f32[1000,64]{1,0} parameter(0)
  %param_1.3 = f32[10,64]{1,0} parameter(1)
  %param_2.3 = s32[] parameter(2)
  %zero.3 = s32[] constant(0)
  ROOT %dus = f32[1000,64]{1,0} dynamic-update-slice(%param_0.3, %param_1.3, %param_2.3, %zero.3)
}

%body (p: (s32[], f32[1000,64])) -> (s32[], f32[1000,64]) {
  %p = (s32[], f32[1000,64]{1,0}) parameter(0)
  %i = s32[] get-tuple-element(%p), index=0
  %table = f32[1000,64]{1,0} get-tuple-element(%p), index=1
  %rows = s32[10,1]{1,0} constant({...})
  %gathered = f32[10,64]{1,0} fusion(%table, %rows), kind=kLoop, calls=%gather_rows
  %scattered = f32[1000,64]{1,0} fusion(%table, %rows, %gathered), kind=kLoop, calls=%scatter_rows
  %stored = f32[1000,64]{1,0} fusion(%scattered, %gathered, %i), kind=kLoop, calls=%store_rows
  ROOT %next = (s32[], f32[1000,64]{1,0}) tuple(%i, %stored)
}

%cond (q: (s32[], f32[1000,64])) -> pred[] {
  %q = (s32[], f32[1000,64]{1,0}) parameter(0)
  ROOT %yes = pred[] constant(true)
}

%gather_concat (param_0.2: f32[1000,64], param_1.2: f32[3000,64], param_2.2: s32[10,1]) -> f32[10,64] {
  %param_0.2 = f32[1000,64]{1,0} parameter(0)
  %param_1.2 = f32[3000,64]{1,0} parameter(1)
  %param_2.2 = s32[10,1]{1,0} parameter(2)
  %both = f32[4000,64]{1,0} concatenate(%param_0.2, %param_1.2), dimensions={0}
  ROOT %gather.2 = f32[10,64]{1,0} gather(%both, %param_2.2), offset_dims={1}, slice_sizes={1,64}
}

%slice_of_product (param_0.4: f32[1000,64], param_1.4: bf16[1000,64]) -> f32[100,64] {
  %param_0.4 = f32[1000,64]{1,0} parameter(0)
  %param_1.4 = bf16[1000,64]{1,0} parameter(1)
  %wide = f32[1000,64]{1,0} convert(%param_1.4)
  %product = f32[1000,64]{1,0} multiply(%param_0.4, %wide)
  ROOT %rows = f32[100,64]{1,0} slice(%product), slice={[200:300], [0:64]}
}

%br_a (s: f32[10,64]) -> f32[10,64] {
  %s = f32[10,64]{1,0} parameter(0)
  ROOT %exp = f32[10,64]{1,0} exponential(%s)
}

%br_b (u: f32[10,64]) -> f32[10,64] {
  %u = f32[10,64]{1,0} parameter(0)
  ROOT %neg = f32[10,64]{1,0} negate(%u)
}

%body.2 (r: (s32[], f32[1000,64])) -> (s32[], f32[1000,64]) {
  %r = (s32[], f32[1000,64]{1,0}) parameter(0)
  %j = s32[] get-tuple-element(%r), index=0
  %t = f32[1000,64]{1,0} get-tuple-element(%r), index=1
  %half = f32[1000,64]{1,0} multiply(%t, %t)
  ROOT %next.2 = (s32[], f32[1000,64]{1,0}) tuple(%j, %half)
}

ENTRY %main (x: f32[1000,64], big: f32[3000,64], idx: s32[10,1], which: s32[]) -> RESULT {
  %x = f32[1000,64]{1,0} parameter(0)
  %copy.1 = f32[1000,64]{1,0} copy(%x)
  %zero = s32[] constant(0)
  %init = (s32[], f32[1000,64]{1,0}) tuple(%zero, %copy.1)
  %loop = (s32[], f32[1000,64]{1,0}) while(%init), condition=%cond, body=%body, TRIPS
  %loop.2 = (s32[], f32[1000,64]{1,0}) while(%loop), condition=%cond, body=%body.2
  %out = f32[1000,64]{1,0} get-tuple-element(%loop.2), index=1
  %big = f32[3000,64]{1,0} parameter(1)
  %idx = s32[10,1]{1,0} parameter(2)
  %which = s32[] parameter(3)
  %picked = f32[10,64]{1,0} fusion(%out, %big, %idx), kind=kLoop, calls=%gather_concat
  %branched = f32[10,64]{1,0} conditional(%which, %picked, %picked), branch_computations={%br_a, %br_b}
  %halves = bf16[1000,64]{1,0} convert(%x)
  %sliced = f32[100,64]{1,0} fusion(%x, %halves), kind=kLoop, calls=%slice_of_product
  ROOT %result = (f32[1000,64]{1,0}, f32[10,64]{1,0}, f32[100,64]{1,0}) tuple(%out, %branched, %sliced)
}
""".replace('TRIPS', 'backend_config={"known_trip_count":{"n":"7"}}').replace(
    'RESULT', '(f32[1000,64], f32[10,64], f32[100,64])'
)


def test_kernel_traffic_counts_bytes_per_run_of_every_kernel():
    moved, unknown = kernel_traffic(_TRAFFIC_MODULE)
    table, rows = 1000 * 64 * 4, 10 * 64 * 4
    assert unknown == 1
    assert moved == {
        'copy.1': 2 * table,  # read and written whole
        # 7 trips: the 10 gathered rows (not the table they are gathered from), the indices, the result
        'gathered': 7 * (rows + 10 * 4 + rows),
        # in place: the table is not streamed; indices and updates read, the touched rows read + written
        'scattered': 7 * (10 * 4 + rows + 2 * rows),
        'stored': 7 * (rows + 4 + rows),  # in place too: the 10 rows stored, not the table
        'half': 2 * table + table,  # the loop of unknown trip count: once
        'picked': rows + 10 * 4 + rows,  # 10 rows gathered from the two tables' concatenation
        'exp': 2 * rows,  # both branches of the conditional: an upper bound
        'neg': 2 * rows,
        'halves': table + table // 2,
        # an elementwise function of two whole tables, sliced: only the 100 rows' elements are read
        'sliced': 100 * 64 * (4 + 2) + 100 * 64 * 4,
    }


def test_kernel_traffic_of_a_compiled_program():
    # XLA:CPU's module of a scan of 5 trips, a gather of 64 rows and a scatter-add of 64 rows
    n, rows = 1024 * 256 * 4, 64 * 256 * 4

    def f(x, idx, upd):
        y, _ = jax.lax.scan(lambda c, _: (jnp.sin(c) * 2.0, None), x, None, length=5)
        return y[idx].sum(0), jnp.zeros_like(y).at[idx].add(upd)

    args = (jnp.ones((1024, 256)), jnp.arange(64) * 3, jnp.ones((64, 256)))
    text = jax.jit(f).lower(*args).compile().as_text()
    moved, unknown = kernel_traffic(text)
    sources = instruction_sources(text)
    assert unknown == 0
    ops = {op: stack for op, (_, _, stack) in sources.items() if op in moved}
    # each of the 5 trips reads and writes the carry once (beside it, the loop counter's add)
    step = sorted(moved[op] for op, stack in ops.items() if '/while/body/' in stack)
    assert step[-1] == 5 * 2 * n and sum(step[:-1]) < 1000
    (scatter,) = (op for op, stack in ops.items() if stack.endswith('scatter-add'))
    (gather,) = (op for op, stack in ops.items() if stack.endswith('/gather'))
    assert moved[scatter] == 64 * 4 + rows + 2 * rows  # not the 1 MB table it updates
    assert moved[gather] == rows + 64 * 4 + rows  # the rows, not the table


def gpu_script_commands(tmp_path, *script, **env) -> list[list[str]]:
    """The python3 commands a prepared GPU-lease script runs (less its setup's own and its inline
    helpers: -c and stdin scripts), recorded by a stand-in python3 first on PATH that writes its
    arguments and exits: every step "runs" at once."""
    bin_dir = tmp_path / 'bin'
    bin_dir.mkdir()
    stub = bin_dir / 'python3'
    stub.write_text(
        f'#!/bin/sh\nexec {sys.executable} -c "import json, os, sys; '
        "open(os.environ['CALLS'], 'a').write(json.dumps(sys.argv[1:]) + chr(10))\" \"$@\"\n"
    )
    stub.chmod(0o755)
    calls = tmp_path / 'calls.jsonl'
    path = f'{bin_dir}:{os.environ["PATH"]}'
    env = dict(os.environ, PATH=path, CALLS=str(calls), OUT=str(tmp_path / 'out'), **env)
    subprocess.run(['bash', *script], cwd=REPO_ROOT, env=env, check=True, capture_output=True)
    argvs = [json.loads(line) for line in calls.read_text().splitlines()]
    return [a for a in argvs if a[:1] not in (['-c'], ['-']) and a[:2] != ['-m', 'pip']]


def test_every_command_of_the_gpu_bench_script_parses(tmp_path):
    runs = gpu_script_commands(tmp_path, 'tools/gpu_bench.sh', '600')
    bench = [a[2:] for a in runs if a[:2] == ['-m', 'hron_jax.bench']]
    train = [a[1:] for a in runs if a[:1] == ['train.py']]
    evals = [a[1:] for a in runs if a[:1] == ['eval.py']]
    assert len(bench) + len(train) + len(evals) == len(runs), runs
    assert len(bench) == 13 and len(train) == 7 and len(evals) == 1  # the stages of the default list
    for argv in evals:
        args = eval_parser().parse_args(argv)
        assert args.run == '/tmp/gpu_bench_run' and args.episodes == 20, argv
    for argv in bench:
        args = bench_parser().parse_args(argv)  # SystemExit (exit 2) names a bad option
        # option values are checked where train.py checks them (UsageError names a bad one)
        options = {k: getattr(args, k, None) or [] for k in ('env_option', 'model_option')}
        config_from_args(dict(task='exploratory', **options))
    for argv in train:
        config = config_from_args(vars(train_parser().parse_args(argv)))
        assert config.task == 'exploratory' and config.ppo.num_envs == 1024, argv


def test_gpu_target_compiles_for_a_gpu_without_one():
    """`bench compile --gpu-target`: an unknown target is one line naming the valid ones; with the
    CUDA plugin (the cuda extra) XLA:GPU compiles for an H100 on this machine, without it the error
    says how to install it."""
    from hron_jax.bench.compile import gpu_target_devices

    with pytest.raises(SystemExit, match=r"--gpu-target 'b100x': expected one of \['h100'\]"):
        gpu_target_devices('b100x')
    import importlib.util

    def installed(module):
        try:
            return importlib.util.find_spec(module) is not None
        except ModuleNotFoundError:  # no jax_plugins package at all
            return False

    if not any(installed(f'jax_plugins.xla_cuda{v}') for v in (12, 13)):
        with pytest.raises(SystemExit, match=r"needs JAX's CUDA plugin \(pip install -e '\.\[cuda\]'\)"):
            gpu_target_devices('h100')
        return
    (device,) = gpu_target_devices('h100')
    assert device.device_kind == 'NVIDIA H100 80GB HBM3'
    # As a user runs it, without JAX_PLATFORMS (the plugin's device check fails without a GPU
    # unless the bench makes the local backend the CPU first).
    script = (
        "import argparse; from hron_jax.bench import compile as c; "
        "c.before_jax(argparse.Namespace(gpu_target='h100')); "
        "print(c.gpu_target_devices('h100')[0].device_kind)"
    )
    env = {k: v for k, v in os.environ.items() if k != 'JAX_PLATFORMS'}
    r = subprocess.run([sys.executable, '-c', script], env=env, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0 and r.stdout.strip() == 'NVIDIA H100 80GB HBM3', r.stderr[-2000:]
    on = jax.sharding.SingleDeviceSharding(device)
    x = jax.ShapeDtypeStruct((256, 256), jnp.float32, sharding=on)
    text = jax.jit(lambda a: jnp.tanh(a @ a).sum()).lower(x).compile().as_text()
    assert 'custom_call_target="__cublas' in text or '__triton' in text  # a GPU program, not XLA:CPU's
