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

Prints: the Markdown table | stage | compile s | HLO text MB | as each stage is compiled (HLO text
size: the optimised module's text, a proxy for how much XLA had to work through).
"""

from __future__ import annotations

import argparse
import time

from .common import stream_table


def bench_compile(task: str, model: str, num_envs: int, extra: dict):
    import jax

    from ..cli import config_from_args
    from ..training import programs

    jax.config.update("jax_enable_compilation_cache", False)
    config = config_from_args(dict(task=task, model=model, num_envs=num_envs, **extra))
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
    for name, fn, args in stages:
        t = time.perf_counter()
        if fn is None:
            compiled = prog.chunk.lower(prog.abstract, 1).compile(options)
        else:
            compiled = fn.lower(*args).compile(options)
        seconds = time.perf_counter() - t
        yield dict(stage=name, compile_s=seconds, hlo_mb=len(compiled.as_text() or "") / 1e6)


HEADER = "| stage | compile s | HLO text MB |\n| --- | ---: | ---: |"


def format_row(r: dict) -> str:
    return f"| {r['stage']} | {r['compile_s']:.1f} | {r['hlo_mb']:.2f} |"


def add_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--task", default="exploratory", choices=("choice", "directed", "exploratory"))
    p.add_argument("--model", default="rgbd_sg_attn")
    p.add_argument("--num-envs", type=int, default=64)
    p.add_argument("--preset", default=None, help="a run_config preset, e.g. paper")
    p.add_argument("--fast-compile", action="store_true", help="XLA without LLVM optimisation")


def run(a: argparse.Namespace) -> None:
    extra = {"fast_compile": True} if a.fast_compile else {}
    if a.preset:
        extra["preset"] = a.preset
    print(
        f"task {a.task}, model {a.model}, {a.num_envs} envs, cold compiles (no persistent cache)", flush=True
    )
    stream_table(HEADER, bench_compile(a.task, a.model, a.num_envs, extra), format_row)
