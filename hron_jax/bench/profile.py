"""Device time of one PPO update per source module (`python -m hron_jax.bench profile`).

Profiles the program train.py runs (hron_jax.training, one seed, the options of `bench train`):
compiles the 1-update chunk, runs it once to warm up and --repeats times untraced (wall time, best
of), then once under jax.profiler.trace, and attributes the time of every XLA op in the trace to
the innermost hron_jax source file on the op's stack (`hlo.instruction_sources`,
e.g. 'sim.py via mujoco' for MJX physics, 'models/gnn.py via flax', 'ppo.py'). Control-flow ops
(while, conditional, call) are left out, since their time is that of the ops inside them. Ops are
read from the GPU's stream lines (kernels and copies), or from the host threads that run XLA's
thunks on a CPU (whose ops overlap on several threads, so shares are of op time, not of wall
time). On a GPU the process runs without CUDA graphs (XLA command buffers), whose kernels a trace
names only by their graph: what is profiled launches every kernel on its own, and its wall time is
that of this setting.

Prints: the task and sizes, the wall ms per update, then the Markdown table | source | ms per
update | share of op time | ops | GB moved | GB/s |, most expensive first (on a GPU the gap between
the op time and the wall time is time the device waited: launches, host work, syncs; GB moved:
`hlo.kernel_traffic`'s estimate of the bytes those ops read and write, so GB/s near the device's
memory bandwidth marks memory-bound code and checks the estimate that `bench compile --gpu-target`
gives without a GPU), then the --top (default 15) most expensive ops with the end of their JAX
name stacks, with the same two columns, and with --lines MODULE (e.g. models/gnn.py) the same per
source line of that module (the op's innermost hron_jax frame there), with the line's code: which
part of the HGT layers takes the time (docs/benchmarks.md, "GB moved", estimates it without a GPU).
The raw trace stays in --trace-dir when given (TensorBoard / Perfetto).
"""

from __future__ import annotations

import argparse
import glob
import linecache
import re
import tempfile
import time
from pathlib import Path

from .common import progress
from .hlo import deep_tracebacks, instruction_sources, kernel_traffic
from .train import add_args as add_train_args
from .train import train_config

CONTROL_FLOW = ("while", "conditional", "call", "async-start", "async-done")


def before_jax(a: argparse.Namespace) -> None:
    """Run before JAX starts its backends: XLA:GPU without command buffers (see the docstring)."""
    import os

    os.environ["XLA_FLAGS"] = os.environ.get("XLA_FLAGS", "") + " --xla_gpu_enable_command_buffer="


def op_times(xplane_path: str) -> dict[str, float]:
    """{HLO instruction name: seconds} summed over a trace's XLA op events (the events that carry
    an hlo_op: on a GPU its streams' kernels and copies, on a CPU the thunks on host threads)."""
    from jax.profiler import ProfileData

    data = ProfileData.from_file(xplane_path)
    planes = [p for p in data.planes if p.name.startswith("/device:")]
    if not planes:  # CPU
        planes = [p for p in data.planes if p.name.startswith("/host:")]
    out: dict[str, float] = {}
    for plane in planes:
        for line in plane.lines:
            for e in line.events:
                name = dict(e.stats).get("hlo_op")
                if name is not None:
                    out[name] = out.get(name, 0.0) + e.duration_ns * 1e-9
    return out


def profile_update(
    config, repeats: int = 2, trace_dir: str | None = None, log=progress, lines: str | None = None
) -> dict:
    """{wall_s (best untraced update), rows: [(source, seconds of the traced update, ops, bytes
    moved)], ops: [(instruction, seconds, source, op_name, bytes moved)] most expensive first,
    lines: the rows of the source lines of module `lines` ('models/gnn.py:459', ...; [] without
    it), trace (path)}; bytes moved: `kernel_traffic`'s estimate per update."""
    import jax

    from ..training import programs, seed_keys

    deep_tracebacks()
    prog = programs(config)
    runner = jax.block_until_ready(prog.initialize(seed_keys(config)))
    fn, t_compile = prog.compiled_chunk(1)
    log(f"compiled the chunk in {t_compile:.1f} s")
    text = fn.as_text() or ""
    sources = instruction_sources(text, lines=True)
    try:
        moved, _ = kernel_traffic(text)
    except Exception as e:  # an estimate beside the measurement: never lose a profile to it
        log(f"GB moved not estimated: kernel_traffic failed on this XLA's module text ({e!r})")
        moved = {}
    runner, _ = jax.block_until_ready(fn(runner))  # warm-up
    wall = float("inf")
    for _ in range(repeats):
        t = time.perf_counter()
        runner, _ = jax.block_until_ready(fn(runner))
        wall = min(wall, time.perf_counter() - t)
    trace_dir = trace_dir or tempfile.mkdtemp(prefix="hron_profile_")
    with jax.profiler.trace(trace_dir):
        runner, _ = jax.block_until_ready(fn(runner))
    path = sorted(glob.glob(f"{trace_dir}/**/*.xplane.pb", recursive=True))[-1]
    per_source: dict[str, list] = {}
    per_line: dict[str, list] = {}
    ops = []

    def tally(table: dict, key: str, seconds: float, moved_bytes: int) -> None:  # one more op of key
        row = table.setdefault(key, [0.0, 0, 0])
        row[0] += seconds
        row[1] += 1
        row[2] += moved_bytes

    for name, seconds in op_times(path).items():
        opcode, at_line, op_name = sources.get(name, ("?", "(not in the chunk)", ""))
        if opcode in CONTROL_FLOW:
            continue
        source = re.sub(r":[\d?]+(?= via |$)", "", at_line)  # 'sim.py:564 via mujoco' -> 'sim.py via mujoco'
        tally(per_source, source, seconds, moved.get(name, 0))
        ops.append((name, seconds, source, op_name, moved.get(name, 0)))
        line = at_line.split(" via ")[0]  # a library's ops count at our line
        if lines and line.startswith(f"{lines}:"):
            tally(per_line, line, seconds, moved.get(name, 0))

    def ranked(table: dict) -> list:  # (key, seconds, ops, bytes), most seconds first
        return sorted(((k, t, n, b) for k, (t, n, b) in table.items()), key=lambda r: -r[1])

    ops.sort(key=lambda r: -r[1])
    return dict(wall_s=wall, rows=ranked(per_source), ops=ops, lines=ranked(per_line), trace=path)


def add_args(p: argparse.ArgumentParser) -> None:
    add_train_args(p, single_num_envs=True)
    p.add_argument("--trace-dir", help="keep the raw trace here (default: a temporary directory)")
    p.add_argument("--top", type=int, default=15, help="how many of the most expensive ops to list")
    p.add_argument(
        "--lines",
        metavar="MODULE",
        help="then ms and GB moved per source line of this module, e.g. models/gnn.py",
    )


def run(a: argparse.Namespace) -> None:
    config = train_config(a, a.num_envs[0])
    batch = config.ppo.num_envs * config.ppo.num_steps
    print(
        f"task {a.task}, model {a.model}, {config.ppo.num_envs} envs x {config.ppo.num_steps} steps, "
        f"{config.ppo.num_minibatches} minibatches x {config.ppo.update_epochs} epochs, camera "
        f"{config.env.camera.width}x{config.env.camera.height}"
        + (f", physics {config.env.sim.physics}" if a.task != "choice" else ""),
        flush=True,
    )
    r = profile_update(config, a.repeats, a.trace_dir, lines=a.lines)
    print(f"wall {1e3 * r['wall_s']:.1f} ms per update ({batch / r['wall_s']:.0f} env steps/s)\n")
    rows = r["rows"]
    total, total_bytes = sum(row[1] for row in rows), sum(row[3] for row in rows)

    def moved(b: float, t: float) -> str:  # the GB moved and GB/s columns
        return f"{b / 1e9:.1f} | {b / 1e9 / t:.0f}" if t > 0 else f"{b / 1e9:.1f} | -"

    print("| source (innermost hron_jax module) | ms per update | share of op time | ops | GB moved | GB/s |")
    print("| --- | ---: | ---: | ---: | ---: | ---: |")
    for source, t, n, b in rows[:20]:
        print(f"| {source} | {1e3 * t:.2f} | {100 * t / total:.1f} % | {n} | {moved(b, t)} |")
    ops = sum(row[2] for row in rows)
    print(f"| all ops | {1e3 * total:.2f} | 100 % | {ops} | {moved(total_bytes, total)} |")
    print("\n| op (most expensive) | ms per update | source | GB moved | GB/s | JAX name stack (its end) |")
    print("| --- | ---: | --- | ---: | ---: | --- |")
    for name, t, source, op_name, b in r["ops"][: a.top]:
        print(f"| {name} | {1e3 * t:.2f} | {source} | {moved(b, t)} | {op_name[-90:]} |")
    if a.lines:
        module_time = sum(row[1] for row in r["lines"])
        print(
            f"\n| line of {a.lines} | ms per update | share of its op time | ops | GB moved | GB/s | code |"
        )
        print("| --- | ---: | ---: | ---: | ---: | ---: | --- |")
        package = Path(__file__).resolve().parents[1]
        for line, t, n, b in r["lines"][:30]:
            code = linecache.getline(str(package / a.lines), int(line.rsplit(":", 1)[1])).strip()
            share = 100 * t / module_time if module_time else 0.0
            print(f"| {line} | {1e3 * t:.2f} | {share:.1f} % | {n} | {moved(b, t)} | `{code[:80]}` |")
    print(f"\ntrace: {r['trace']}")
