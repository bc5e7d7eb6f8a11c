"""PPO train env steps/s (env + update) per num_envs (`python -m hron_jax.bench train`).

Measures env steps/s of one PPO update of the program train.py runs (hron_jax.training, one seed),
for each --num-envs: a rollout of --num-steps steps of num_envs envs plus --epochs epochs over
minibatches of ~--minibatch-size samples (the paper's 128); and of the rollout alone (PPO.evaluate
with the sampled policy: env + policy forward), so the update's share shows. Times: best of
--repeats calls after compilation (init / compile times go to stderr).

Prints: the task and sizes, then the Markdown table | num_envs | minibatches x epochs | init +
chunk compile s | s / update | train env steps / s | rollout-only steps / s | update share |, a
row as soon as that num_envs is measured.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from .common import progress, stream_table, timed


def train_config(a: argparse.Namespace, num_envs: int):
    """The TrainConfig train.py builds for these benchmark options at num_envs (one update)."""
    from ..cli import config_from_args

    batch = num_envs * a.num_steps
    args = dict(
        task=a.task,
        model=a.model,
        num_envs=num_envs,
        num_steps=a.num_steps,
        total_steps=batch,
        minibatches=max(1, batch // a.minibatch_size),
    )
    if a.epochs is not None:
        args["epochs"] = a.epochs
    if a.distractors:
        args["distractors"] = True
    args["env_option"] = list(a.env_option or [])
    if a.image_size is not None:
        args["env_option"].append(f"image_size={a.image_size}")
    if a.model_option:
        args["model_option"] = list(a.model_option)
    return config_from_args(args)


def bench_train(a: argparse.Namespace, log=progress):
    """Yields a row per --num-envs as soon as it is measured (see the module docstring)."""
    import jax

    from ..training import programs, seed_keys

    for B in a.num_envs:
        cfg = train_config(a, B)
        num_steps = cfg.ppo.num_steps
        batch = B * num_steps
        t = time.perf_counter()
        prog = programs(cfg)
        runner = jax.block_until_ready(prog.initialize(seed_keys(cfg)))
        t_init = time.perf_counter() - t
        fn, t_compile = prog.compiled_chunk(1)
        best = np.inf
        for _ in range(a.repeats):
            (runner, _), t = timed(lambda: fn(runner))
            best = min(best, t)
        params = jax.tree.map(lambda x: x[0], runner.params)
        ev = jax.jit(prog.ppo.evaluate, static_argnums=(2, 3))
        _, t_ev_compile = timed(lambda: ev(params, jax.random.PRNGKey(1), num_steps, False))
        key = jax.random.PRNGKey
        best_ev = min(timed(lambda: ev(params, key(2 + i), num_steps, False))[1] for i in range(a.repeats))
        log(
            f"B={B}: init {t_init:.1f} s, chunk compile {t_compile:.1f} s, rollout-only compile "
            f"{t_ev_compile:.1f} s, {batch / best:.0f} train steps/s"
        )
        yield dict(
            num_envs=B,
            minibatches=cfg.ppo.num_minibatches,
            epochs=cfg.ppo.update_epochs,
            compile_s=t_init + t_compile,
            s_per_update=best,
            train_steps_per_s=batch / best,
            rollout_steps_per_s=batch / best_ev,
            update_share=max(0.0, 1.0 - best_ev / best),
        )


HEADER = (
    "| num_envs | minibatches x epochs | init + chunk compile s | s / update | train env steps / s | "
    "rollout-only steps / s | update share |\n"
    "| ---: | ---: | ---: | ---: | ---: | ---: | ---: |"
)


def format_row(r: dict) -> str:
    return (
        f"| {r['num_envs']} | {r['minibatches']} x {r['epochs']} | {r['compile_s']:.0f} | "
        f"{r['s_per_update']:.3f} | {r['train_steps_per_s']:.0f} | "
        f"{r['rollout_steps_per_s']:.0f} | {100 * r['update_share']:.0f}% |"
    )


def add_args(p: argparse.ArgumentParser, single_num_envs: bool = False) -> None:
    p.add_argument("--task", default="exploratory", choices=("choice", "directed", "exploratory"))
    p.add_argument("--model", default="rgbd_sg_attn")
    if single_num_envs:
        p.add_argument("--num-envs", type=int, nargs=1, default=[64])
    else:
        p.add_argument("--num-envs", type=int, nargs="+", default=[16, 64, 256])
    p.add_argument("--num-steps", type=int, default=8, help="rollout length per update")
    p.add_argument("--minibatch-size", type=int, default=128)
    p.add_argument("--epochs", type=int, default=None, help="default: the task's PPO default")
    p.add_argument("--image-size", type=int, default=None, help="square camera (default: the task's, 32)")
    p.add_argument(
        "--model-option", action="append", metavar="NAME=VALUE", help="as train.py's, e.g. conv=xla"
    )
    p.add_argument(
        "--env-option", action="append", metavar="NAME=VALUE", help="as train.py's, e.g. sim.physics=warp"
    )
    p.add_argument("--repeats", type=int, default=2)
    p.add_argument("--distractors", action="store_true")


def run(a: argparse.Namespace) -> None:
    env = train_config(a, a.num_envs[0]).env
    physics = f", physics {env.sim.physics}" if a.task != "choice" else ""
    print(
        f"task {a.task}, model {a.model}, num_steps {a.num_steps}, minibatch ~{a.minibatch_size}, "
        f"camera {a.image_size or 'default'}, env options {a.env_option or 'none'}{physics}",
        flush=True,
    )
    stream_table(HEADER, bench_train(a), format_row)
