"""Compile seconds and program size per stage of the training program (`python -m hron_jax.bench compile`).

Measures what makes train.py's program slow to compile: each stage is jitted and compiled on its
own, cold (the persistent XLA cache is off for this process), for the config train.py builds from
the same options (--task, --model, --num-envs, --preset, --fast-compile):
    reset        vmap(env.reset) over num_envs
    step         vmap(env.step): physics, render, graph update and the in-step auto-reset
    final_obs    vmap(env.final_obs): the pre-reset render PPO bootstraps truncated episodes from
    forward      the model on a batch of num_envs observations
    fwd+grad     its gradient (what every PPO minibatch runs)
    chunk        the whole 1-update training chunk (hron_jax.training.programs: rollout scan, GAE,
                 epochs x minibatches scans), which contains all of the above
    init         the init program (env reset + parameter init) as train.py compiles it (without
                 LLVM optimisation, Programs.initialize); a run waits for init + chunk
Prints: the Markdown table | stage | compile s | HLO text MB | HLO instructions | as each stage is
compiled (the optimised module's text size and its instruction count, fused computations included:
proxies for how much XLA had to work through; unlike seconds, which vary by tens of percent on a
shared machine, they are the same in every run of the same code). Compile seconds include tracing
and lowering. With --by-source, then a second table: the chunk's HLO instructions
per source module (`hlo_by_source`), i.e. which part of the code makes the program big.
"""

from __future__ import annotations

import argparse
import re
import time

from .common import stream_table

# An instruction line of an HLO module's text: its name and opcode.
_INSTRUCTION = re.compile(r"\s*(?:ROOT )?%(\S+) = .*? ([a-z][\w-]*)\(")


def bench_compile(config):
    """Yields {stage, compile_s, hlo_mb, instructions} per stage of the training program of `config`."""
    import jax

    from ..training import FAST_COMPILE, programs

    jax.config.update("jax_enable_compilation_cache", False)
    num_envs = config.ppo.num_envs
    prog = programs(config)
    options = prog.compiler_options
    env, network = prog.env, prog.network
    keys = jax.random.split(jax.random.PRNGKey(0), num_envs)
    states = jax.eval_shape(jax.vmap(env.reset), keys)
    params = jax.eval_shape(network.init, jax.random.PRNGKey(0), states.obs)
    actions = jax.ShapeDtypeStruct((num_envs,), "int32")

    def loss(p, obs):
        logits, value = network.apply(p, obs)
        return logits.sum() + value.sum()

    stages = [
        ("reset", jax.jit(jax.vmap(env.reset)), (keys,)),
        ("step", jax.jit(jax.vmap(env.step)), (states, actions)),
    ]
    if hasattr(env, "final_obs"):
        stages.append(("final_obs", jax.jit(jax.vmap(env.final_obs)), (states,)))
    stages += [
        ("forward", jax.jit(network.apply), (params, states.obs)),
        ("fwd+grad", jax.jit(jax.grad(loss)), (params, states.obs)),
        ("chunk (1 update)", None, None),
    ]
    init_keys = jax.ShapeDtypeStruct((config.num_seeds, 2), "uint32")
    stages.append(("init", prog.init, (init_keys,)))
    for name, fn, args in stages:
        t = time.perf_counter()
        if fn is None:
            compiled = prog.chunk.lower(prog.abstract, 1).compile(options)
        else:  # init as the Trainer compiles it (Programs.initialize)
            compiled = fn.lower(*args).compile(dict(FAST_COMPILE) if name == "init" else options)
        seconds = time.perf_counter() - t
        text = compiled.as_text() or ""
        yield dict(stage=name, compile_s=seconds, hlo_mb=len(text) / 1e6, instructions=hlo_instructions(text))


def hlo_instructions(text: str) -> int:
    """Instructions of an optimised HLO module's text, those of fused computations included."""
    return sum(1 for line in text.splitlines() if _INSTRUCTION.match(line))


def instruction_sources(text: str) -> dict[str, tuple[str, str, str]]:
    """{instruction name: (opcode, source, op_name)} of an optimised HLO module's text (op_name:
    the JAX name stack of its metadata, e.g. '.../transpose(jvp(ActorCritic))/.../scatter-add').
    The source is the innermost hron_jax file on the instruction's stack (metadata stack frames),
    'via' the library whose code emitted it when that is not ours (e.g. 'sim.py via mujoco'),
    '(no hron_jax frame) via LIB' when the stack does not reach our code (e.g. MJX kinematics
    traced inside MJX's own scans, optax; JAX drops its own frames), or "XLA's own" for what
    XLA inserted (copies, layout changes; no metadata). Parameters are left out. Needs stacks
    deep enough to reach our frames: compile with jax_traceback_in_locations_limit raised
    (`deep_tracebacks`)."""
    sections, current = {}, None
    for line in text.splitlines():
        if line in ("FileNames", "FunctionNames", "FileLocations", "StackFrames"):
            current = sections.setdefault(line, {})
            continue
        m = re.match(r"(\d+) (.*)", line) if current is not None else None
        if m:
            current[int(m.group(1))] = m.group(2)
        else:
            current = None
    files = {k: v.strip('"') for k, v in sections.get("FileNames", {}).items()}
    loc_file = {
        k: files[int(re.search(r"file_name_id=(\d+)", v).group(1))]
        for k, v in sections.get("FileLocations", {}).items()
    }
    frames = {}
    for k, v in sections.get("StackFrames", {}).items():
        loc, parent = (int(x) for x in re.findall(r"=(\d+)", v)[:2])
        frames[k] = (loc, parent)

    def key(frame: int) -> str:
        inner, seen = None, set()
        while frame in frames and frame not in seen:
            seen.add(frame)
            loc, parent = frames[frame]
            path = loc_file[loc]
            if inner is None:
                inner = path
            if "/hron_jax/" in path:
                name = path.split("/hron_jax/", 1)[1]
                if "/hron_jax/" not in inner:
                    lib = inner.split("site-packages/", 1)[-1].split("/", 1)[0]
                    name += f" via {lib}"
                return name
            frame = parent
        if inner is None:
            return "(no hron_jax frame)"
        # e.g. MJX internals traced where the stack no longer reaches our code, optax: name the
        # library whose code emitted it (JAX drops its own frames, so jax.random is never here)
        lib = inner.split("site-packages/", 1)[-1].split("/", 1)[0] if "site-packages/" in inner else inner
        return f"(no hron_jax frame) via {lib.rsplit('/', 1)[-1]}"

    out = {}
    for line in text.splitlines():
        m = _INSTRUCTION.match(line)
        if m and m.group(2) != "parameter":
            frame = re.search(r"stack_frame_id=(\d+)", line)
            op_name = re.search(r'op_name="([^"]*)"', line)
            out[m.group(1)] = (
                m.group(2),
                key(int(frame.group(1))) if frame else "(XLA's own: no source)",
                op_name.group(1) if op_name else "",
            )
    return out


def hlo_by_source(text: str) -> dict[str, int]:
    """Instructions of an optimised HLO module's text per source (`instruction_sources`), most first."""
    counts: dict[str, int] = {}
    for _, source, _ in instruction_sources(text).values():
        counts[source] = counts.get(source, 0) + 1
    return dict(sorted(counts.items(), key=lambda kv: -kv[1]))


def deep_tracebacks() -> None:
    """Stacks deep enough to reach hron_jax frames under MJX / flax / optax code (for
    `instruction_sources`). They make bigger modules that compile slower, so only the source
    tables use them, on programs traced afresh."""
    import jax

    jax.config.update("jax_traceback_in_locations_limit", 64)
    jax.clear_caches()


HEADER = "| stage | compile s | HLO text MB | HLO instructions |\n| --- | ---: | ---: | ---: |"


def format_row(r: dict) -> str:
    return f"| {r['stage']} | {r['compile_s']:.1f} | {r['hlo_mb']:.2f} | {r['instructions']:,} |"


def add_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--task", default="exploratory", choices=("choice", "directed", "exploratory"))
    p.add_argument("--model", default="rgbd_sg_attn")
    p.add_argument("--num-envs", type=int, default=64)
    p.add_argument("--preset", default=None, help="a run_config preset, e.g. paper")
    p.add_argument("--fast-compile", action="store_true", help="XLA without LLVM optimisation")
    p.add_argument(
        "--by-source", action="store_true", help="then the chunk's HLO instructions per source module"
    )
    p.add_argument(
        "--env-option", action="append", default=[], help="NAME=VALUE as in train.py, e.g. sim.physics=warp"
    )


def run(a: argparse.Namespace) -> None:
    from ..cli import config_from_args

    extra = {"fast_compile": True} if a.fast_compile else {}
    if a.preset:
        extra["preset"] = a.preset
    config = config_from_args(
        dict(task=a.task, model=a.model, num_envs=a.num_envs, env_option=a.env_option, **extra)
    )
    physics = f", physics {config.env.sim.physics}" if a.task != "choice" else ""
    print(
        f"task {a.task}, model {a.model}, {a.num_envs} envs{physics}, cold compiles (no persistent cache)",
        flush=True,
    )
    stream_table(HEADER, bench_compile(config), format_row)
    if a.by_source:
        from ..training import programs

        deep_tracebacks()
        prog = programs(config)
        text = prog.chunk.lower(prog.abstract, 1).compile(prog.compiler_options).as_text() or ""
        counts = hlo_by_source(text)
        total = sum(counts.values())
        print("\n| source (innermost hron_jax module) | HLO instructions of the chunk | share |")
        print("| --- | ---: | ---: |")
        for name, n in list(counts.items())[:15]:
            print(f"| {name} | {n} | {100 * n / total:.1f} % |")
        print(f"| all | {total} | 100 % |")
