"""PPO train env steps/s (env + update) per num_envs (`python -m hron_jax.bench train`).

Measures env steps/s of one PPO update of the program train.py runs (hron_jax.training, one seed),
for each --num-envs: a rollout of --num-steps steps of num_envs envs plus --epochs epochs over
minibatches of ~--minibatch-size samples (the paper's 128); and of the rollout alone (PPO.evaluate
with the sampled policy: env + policy forward), so the update's share shows. Times: best of
--repeats calls after compilation (init / compile times go to stderr).

Prints: the task and sizes, then the Markdown table | num_envs | minibatches x epochs | compile s |
s / update | train env steps / s | rollout-only steps / s | update share |, a row as soon as that
num_envs is measured.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from .common import progress, stream_table, timed


def bench_train(
    task: str = "exploratory",
    model: str = "rgbd_sg_attn",
    num_envs=(16, 64, 256),
    num_steps: int = 8,
    minibatch_size: int = 128,
    epochs: int | None = None,
    repeats: int = 2,
    extra: dict | None = None,
    log=progress,
):
    """Yields a row per num_envs as soon as it is measured (see the module docstring).
    extra: more train.py options (dest names)."""
    import jax

    from ..cli import config_from_args
    from ..training import programs, seed_keys

    for B in num_envs:
        batch = B * num_steps
        args = dict(
            task=task,
            model=model,
            num_envs=B,
            num_steps=num_steps,
            total_steps=batch,
            minibatches=max(1, batch // minibatch_size),
            **(extra or {}),
        )
        if epochs is not None:
            args["epochs"] = epochs
        cfg = config_from_args(args)
        t = time.perf_counter()
        prog = programs(cfg)
        runner = jax.block_until_ready(prog.initialize(seed_keys(cfg)))
        t_init = time.perf_counter() - t
        fn, t_compile = prog.compiled_chunk(1)
        best = np.inf
        for _ in range(repeats):
            (runner, _), t = timed(lambda: fn(runner))
            best = min(best, t)
        params = jax.tree.map(lambda x: x[0], runner.params)
        ev = jax.jit(prog.ppo.evaluate, static_argnums=(2, 3))
        _, t_ev_compile = timed(lambda: ev(params, jax.random.PRNGKey(1), num_steps, False))
        best_ev = min(
            timed(lambda: ev(params, jax.random.PRNGKey(2 + i), num_steps, False))[1] for i in range(repeats)
        )
        log(f"B={B}: init {t_init:.1f} s, compile {t_compile:.1f} s, {batch / best:.0f} train steps/s")
        yield dict(
            num_envs=B,
            minibatches=cfg.ppo.num_minibatches,
            epochs=cfg.ppo.update_epochs,
            compile_s=t_init + t_compile + t_ev_compile,
            s_per_update=best,
            train_steps_per_s=batch / best,
            rollout_steps_per_s=batch / best_ev,
            update_share=max(0.0, 1.0 - best_ev / best),
        )


HEADER = (
    "| num_envs | minibatches x epochs | compile s | s / update | train env steps / s | "
    "rollout-only steps / s | update share |\n"
    "| ---: | ---: | ---: | ---: | ---: | ---: | ---: |"
)


def format_row(r: dict) -> str:
    return (
        f"| {r['num_envs']} | {r['minibatches']} x {r['epochs']} | {r['compile_s']:.0f} | "
        f"{r['s_per_update']:.3f} | {r['train_steps_per_s']:.0f} | "
        f"{r['rollout_steps_per_s']:.0f} | {100 * r['update_share']:.0f}% |"
    )


def add_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--task", default="exploratory", choices=("choice", "directed", "exploratory"))
    p.add_argument("--model", default="rgbd_sg_attn")
    p.add_argument("--num-envs", type=int, nargs="+", default=[16, 64, 256])
    p.add_argument("--num-steps", type=int, default=8, help="rollout length per update")
    p.add_argument("--minibatch-size", type=int, default=128)
    p.add_argument("--epochs", type=int, default=None, help="default: the task's PPO default")
    p.add_argument("--repeats", type=int, default=2)
    p.add_argument("--distractors", action="store_true")


def run(a: argparse.Namespace) -> None:
    extra = {"distractors": True} if a.distractors else {}
    print(
        f"task {a.task}, model {a.model}, num_steps {a.num_steps}, minibatch ~{a.minibatch_size}", flush=True
    )
    stream_table(
        HEADER,
        bench_train(
            a.task, a.model, tuple(a.num_envs), a.num_steps, a.minibatch_size, a.epochs, a.repeats, extra
        ),
        format_row,
    )
