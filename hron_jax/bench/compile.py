"""Compile seconds and program size per stage of the training program (`python -m hron_jax.bench compile`).

Measures what makes train.py's program slow to compile: each stage is jitted and compiled on its
own, cold (the persistent XLA cache is off for this process), for the config train.py builds from
the same options (--task, --model, --num-envs, --num-steps, --minibatches, --preset, --fast-compile):
    reset        vmap(env.reset) over num_envs
    step         vmap(env.step): physics, render, graph update and the in-step auto-reset
    final_obs    vmap(env.final_obs): the pre-reset render PPO bootstraps truncated episodes from
    forward      the model on a batch of num_envs observations
    fwd+grad     its gradient (what every PPO minibatch runs)
    chunk        the whole 1-update training chunk (hron_jax.training.programs: rollout scan, GAE,
                 epochs x minibatches scans), which contains all of the above
    init         the two init programs as train.py compiles them (without LLVM optimisation,
                 Programs.initialize): the parameters, always on the host CPU, and the env reset
                 with the optimiser's state; a run waits for both inits + chunk
Prints: the Markdown table | stage | compile s | HLO text MB | HLO instructions | GB moved | as each
stage is compiled (the optimised module's text size and its instruction count, fused computations
included: proxies for how much XLA had to work through; unlike seconds, which vary by tens of
percent on a shared machine, they are the same in every run of the same code; GB moved: the bytes
its kernels read and write per run, `hlo.kernel_traffic`, an estimate of the device time of
memory-bound programs such as the HGT layers on a GPU). Compile seconds include tracing and
lowering. With --by-source, then a second table: the chunk's HLO instructions and GB moved per
source module (`hlo.instruction_sources`), i.e. which part of the code makes the program big and
which moves the bytes.

--gpu-target h100 (or a GpuTargetConfigProto text file): the same programs compiled by XLA:GPU for
that GPU on this machine, which needs no GPU (a compile-only device of
`jax.experimental.topologies`; install the CUDA plugin with `pip install -e ".[cuda]"`, and keep
JAX_PLATFORMS=cpu where there is no GPU). The seconds are this machine's CPU doing XLA:GPU's work
(HLO passes, LLVM to PTX, ptxas), without autotuning, which needs the device, and with GEMMs on
cuBLAS (`deviceless_options`): a proxy that ranks changes to the GPU program between GPU leases,
not the seconds a GPU host takes.
"""

from __future__ import annotations

import argparse
import time

from .common import stream_table
from .hlo import (
    deep_tracebacks,
    gb_moved,
    hlo_by_source,
    hlo_instructions,
    instruction_sources,
    kernel_traffic,
)

# An NVIDIA H100 SXM (80 GB) as XLA:GPU's compiler sees it (stream_executor's GpuDeviceInfoProto):
# compute capability 9.0, 132 SMs, 228 KB of shared memory per SM (227 KB opt-in per block), 50 MB
# of L2, 3.35 TB/s, CUDA 13 and cuDNN 9 as the jax[cuda13] wheels bring them.
H100_TARGET = """
gpu_device_info {
  threads_per_block_limit: 1024 threads_per_warp: 32 shared_memory_per_block: 49152
  shared_memory_per_core: 233472 shared_memory_per_block_optin: 232448 threads_per_core_limit: 2048
  core_count: 132 fpus_per_core: 128 block_dim_limit_x: 2147483647 block_dim_limit_y: 65535
  block_dim_limit_z: 65535 memory_bandwidth: 3352320000000 l2_cache_size: 52428800
  clock_rate_ghz: 1.98 device_memory_size: 84929347584 registers_per_core_limit: 65536
  registers_per_block_limit: 65536 cuda_compute_capability { major: 9 minor: 0 }
}
platform_name: "CUDA"
dnn_version_info { major: 9 minor: 10 }
runtime_version { major: 13 }
device_description_str: "NVIDIA H100 80GB HBM3"
"""
GPU_TARGETS = {"h100": H100_TARGET}


def gpu_target_devices(target: str) -> list:
    """Compile-only devices of one GPU (`--gpu-target`: a GPU_TARGETS name or a text file of an
    XLA GpuTargetConfigProto); programs lowered for them compile with XLA:GPU without a GPU."""
    import os

    from jax.experimental import topologies

    if target in GPU_TARGETS:
        text = GPU_TARGETS[target]
    elif os.path.isfile(target):
        with open(target) as f:
            text = f.read()
    else:
        raise SystemExit(
            f"bench compile: --gpu-target {target!r}: expected one of {sorted(GPU_TARGETS)} or a "
            "GpuTargetConfigProto text file"
        )
    try:
        topology = topologies.get_topology_desc(platform="cuda", target_config=text, topology="1x1x1")
    except Exception as e:  # no CUDA plugin, or one that cannot make topologies
        raise SystemExit(
            f"bench compile: --gpu-target needs JAX's CUDA plugin (pip install -e '.[cuda]'): {e}"
        ) from None
    return list(topology.devices)


def deviceless_options(devices) -> dict:
    """XLA options a compile for compile-only GPU devices needs: Triton GEMMs off. Without the
    device XLA:GPU cannot autotune, and its untuned Triton tiling fails on the HGT layers' type
    slices (jax 0.10.2, H100 target: "Couldn't find output tile sizes that satisfy hlo: dot
    f32[73728,384]", the 72 object rows of 1024 graphs), so GEMMs go to cuBLAS there. The real
    device autotunes and compiles them (one H200, 2026-12-04)."""
    if devices and devices[0].platform != "cpu":
        return {"xla_gpu_enable_triton_gemm": False}
    return {}


def bench_compile(config, devices=None):
    """Yields {stage, compile_s, hlo_mb, instructions, gb_moved} per stage of the training program
    of `config`, compiled for `devices` (default: this machine's; `gpu_target_devices`)."""
    import jax

    from ..training import FAST_COMPILE, compile_lowered, programs

    jax.config.update("jax_enable_compilation_cache", False)
    num_envs = config.ppo.num_envs
    prog = programs(config, devices)
    # the stages' inputs live where the programs run (compile-only devices cannot take arrays)
    on = jax.sharding.NamedSharding(prog.mesh, jax.sharding.PartitionSpec())
    placed = lambda tree: jax.tree.map(lambda a: jax.ShapeDtypeStruct(a.shape, a.dtype, sharding=on), tree)
    deviceless = deviceless_options(devices)
    options, init_options = dict(prog.compiler_options, **deviceless), dict(FAST_COMPILE, **deviceless)
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
    stages.append(("init: parameters (host CPU)", prog.init_params, (init_keys,)))
    stages.append(("init: env reset", prog.init, (init_keys, prog.abstract.params)))
    for name, fn, args in stages:
        t = time.perf_counter()
        if fn is None:
            compiled = compile_lowered(prog.chunk.lower(prog.abstract, 1), options)
        elif fn is prog.init_params:  # on its own (host CPU) shardings, as Programs.initialize does
            compiled = compile_lowered(fn.lower(*args), FAST_COMPILE)
        else:  # init with the options Programs.initialize compiles it with
            compiled = compile_lowered(fn.lower(*placed(args)), init_options if fn is prog.init else options)
        seconds = time.perf_counter() - t
        text = compiled.as_text() or ""
        yield dict(
            stage=name,
            compile_s=seconds,
            hlo_mb=len(text) / 1e6,
            instructions=hlo_instructions(text),
            gb_moved=gb_moved(text),
        )


HEADER = (
    "| stage | compile s | HLO text MB | HLO instructions | GB moved per run |\n"
    "| --- | ---: | ---: | ---: | ---: |"
)


def format_row(r: dict) -> str:
    return (
        f"| {r['stage']} | {r['compile_s']:.1f} | {r['hlo_mb']:.2f} | {r['instructions']:,} "
        f"| {r['gb_moved']:.1f} |"
    )


def add_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--task", default="exploratory", choices=("choice", "directed", "exploratory"))
    p.add_argument("--model", default="rgbd_sg_attn")
    p.add_argument("--num-envs", type=int, default=64)
    p.add_argument("--num-steps", type=int, default=None, help="rollout length (default: the task's)")
    p.add_argument("--minibatches", type=int, default=None, help="per epoch (default: the task's)")
    p.add_argument("--preset", default=None, help="a run_config preset, e.g. paper")
    p.add_argument("--fast-compile", action="store_true", help="XLA without LLVM optimisation")
    p.add_argument(
        "--by-source",
        action="store_true",
        help="then the chunk's HLO instructions and GB moved per source module",
    )
    p.add_argument(
        "--env-option", action="append", default=[], help="NAME=VALUE as in train.py, e.g. sim.physics=warp"
    )
    p.add_argument(
        "--model-option",
        action="append",
        default=[],
        help="NAME=VALUE as in train.py, e.g. gnn_dtype=bfloat16",
    )
    p.add_argument(
        "--gpu-target",
        default=None,
        help="compile XLA:GPU's programs for this GPU without one: h100, or a GpuTargetConfigProto "
        "text file (needs the CUDA plugin: the cuda extra)",
    )


def before_jax(a: argparse.Namespace) -> None:
    """--gpu-target needs no local GPU: unless JAX_PLATFORMS says otherwise the local backend is
    the CPU, so JAX's CUDA plugin registers without its device check (cuInit fails on a machine
    without a GPU, and the plugin then offers no topologies)."""
    import os

    if a.gpu_target and not os.environ.get("JAX_PLATFORMS"):
        import jax

        jax.config.update("jax_platforms", "cpu")


def run(a: argparse.Namespace) -> None:
    from ..cli import config_from_args

    extra = {"fast_compile": True} if a.fast_compile else {}
    extra.update({k: v for k, v in (("num_steps", a.num_steps), ("minibatches", a.minibatches)) if v})
    if a.preset:
        extra["preset"] = a.preset
    config = config_from_args(
        dict(
            task=a.task,
            model=a.model,
            num_envs=a.num_envs,
            env_option=a.env_option,
            model_option=a.model_option,
            **extra,
        )
    )
    physics = f", physics {config.env.sim.physics}" if a.task != "choice" else ""
    devices = gpu_target_devices(a.gpu_target) if a.gpu_target else None
    target = (
        f", XLA:GPU for {devices[0].device_kind} (no device: compile only, Triton GEMMs off)"
        if devices
        else ""
    )
    print(
        f"task {a.task}, model {a.model}, {a.num_envs} envs{physics}{target}, cold compiles (no "
        "persistent cache)",
        flush=True,
    )
    stream_table(HEADER, bench_compile(config, devices), format_row)
    if a.by_source:
        from ..training import compile_lowered, programs

        deep_tracebacks()
        prog = programs(config, devices)
        options = dict(prog.compiler_options, **deviceless_options(devices))  # as bench_compile's
        text = compile_lowered(prog.chunk.lower(prog.abstract, 1), options).as_text() or ""
        counts = hlo_by_source(text)
        sources = instruction_sources(text)
        moved, unknown = kernel_traffic(text)
        gb: dict[str, float] = {}
        for op, n in moved.items():
            gb[sources[op][1]] = gb.get(sources[op][1], 0.0) + n / 1e9
        total, total_gb = sum(counts.values()), sum(gb.values())
        loops = f" ({unknown} loops of unknown trip count counted once)" if unknown else ""
        print(
            "\n| source (innermost hron_jax module) | HLO instructions of the chunk | share "
            f"| GB moved{loops} | share |"
        )
        print("| --- | ---: | ---: | ---: | ---: |")
        for name, n in list(counts.items())[:15]:
            g = gb.get(name, 0.0)
            print(f"| {name} | {n} | {100 * n / total:.1f} % | {g:.1f} | {100 * g / total_gb:.1f} % |")
        print(f"| all | {total} | 100 % | {total_gb:.1f} | 100 % |")
