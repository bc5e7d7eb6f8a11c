"""Actor-critic forward / forward+grad ms per variant (`python -m hron_jax.bench model`).

Measures every model variant of hron_jax.models on a batch of house scene graphs: fwd =
jit(model.apply); grad = jit(value_and_grad) of a PPO-like scalar (log-prob of action 0 + squared
value) w.r.t. all parameters. Parameters are scaled normals (timing does not depend on them; flax
init would cost ~10 s of compile per variant). The variants are timed round robin, one call each
per round, and the median over --reps rounds is reported, so a load change on a shared machine hits
every variant alike; CPU-ms is the process CPU time per call (all threads), steadier than wall time
when other jobs share the cores.

Allocator: XLA:CPU takes each call's temporaries from malloc, and glibc returns large blocks to the
OS, so every call page-faults its whole working set again (measured ~0.45 ms per MB on the 2-core
VM: 30-50 % of rgbd_sg_attn's gradient time). The CLI (like train.py and eval.py) calls
hron_jax.cli.tune_malloc() first, which keeps that memory in the process.

HGT layers: with the scene's static node layout (`node_type_counts`, each type's rows one table, as
training runs them).

Prints: the batch's graph sizes, each variant's compile time (stderr) as it compiles, then (all rows
finish together, round robin) the Markdown table | variant | forward ms | fwd+grad ms | fwd / gcn |
grad / gcn | fwd CPU-ms | fwd+grad CPU-ms | compile s |.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from .common import DEFAULT_SCENE, progress, random_placement, timed

VARIANTS = ("rgbd", "rgbd_mm", "rgbd_sg", "rgbd_sg_attn", "gcn", "yang")


def model_inputs(batch: int = 64, scene_path: str = DEFAULT_SCENE, image: int = 32, seed: int = 0):
    """A batch of observations following hron_jax.models' contract: scene graphs of `scene_path`
    from GraphBuilder with every node discovered and every pool object placed in a random slot
    (house.xml: N=119, E=386, all live), random poses, random RGB-D / map images, random goals."""
    import jax
    import jax.numpy as jnp

    from .. import goals as GL
    from ..graph_builder import GraphBuilder, GraphConfig
    from ..scenes import load_scene

    rng = np.random.default_rng(seed)
    scene = load_scene(scene_path)
    gb = GraphBuilder(scene, GraphConfig())
    _, placement = random_placement(scene, batch, rng)
    lo, hi = scene.bounds[0, :2], scene.bounds[1, :2]
    poses = jnp.asarray(
        np.concatenate([rng.uniform(lo, hi, (batch, 2)), rng.uniform(-np.pi, np.pi, (batch, 1))], -1),
        jnp.float32,
    )
    disc = jnp.broadcast_to(gb.real, (batch, gb.max_nodes))
    graph = jax.jit(jax.vmap(gb.graph))(disc, placement, poses)
    cat = np.asarray(graph.nodes["category"])
    pick = rng.integers(0, gb.max_nodes, (batch, 3))
    goal = np.zeros((batch, GL.GOAL_DIM), np.float32)
    goal[np.arange(batch)[:, None], rng.integers(0, GL.GOAL_DIM, (batch, 3))] = 1.0
    obs = dict(
        graph=graph,
        goal=jnp.asarray(goal),
        goal_classes=jnp.asarray(np.take_along_axis(cat, pick, 1), jnp.int32),
        rgbd=jnp.asarray(rng.random((batch, image, image, 4)), jnp.float32),
        map=jnp.asarray(rng.random((batch, image, image, 3)), jnp.float32),
    )
    return obs, gb


def bench_model(
    variants=VARIANTS,
    batch: int = 64,
    reps: int = 20,
    scene_path: str = DEFAULT_SCENE,
    seed: int = 0,
    log=print,
) -> list[dict]:
    """Rows {variant, fwd_ms, grad_ms, fwd_cpu_ms, grad_cpu_ms, compile_s} at `batch` (see the
    module docstring)."""
    import jax
    import jax.numpy as jnp

    from ..models import make_model

    obs, gb = model_inputs(batch, scene_path, seed=seed)
    log(
        f"batch {batch}: N={gb.max_nodes} nodes, E={gb.max_edges} edges "
        f"(live {int(np.asarray(obs['graph'].edges['mask']).sum()) / batch:.0f}/graph)"
    )
    one = jax.tree.map(lambda a: a[0], obs)
    fns = {}
    for name in variants:
        model = make_model(name, 5, node_type_counts=gb.node_type_counts)
        shapes = jax.eval_shape(model.init, jax.random.PRNGKey(0), one)
        r = np.random.default_rng(seed)
        variables = jax.tree.map(
            lambda s: jnp.asarray(
                r.standard_normal(s.shape) / np.sqrt(max(int(np.prod(s.shape[:-1])), 1)), s.dtype
            ),
            shapes,
        )

        def loss(v, o, model=model):
            logits, value = model.apply(v, o)
            return jnp.sum(jax.nn.log_softmax(logits)[:, 0]) + jnp.sum(value**2)

        fwd, grad = jax.jit(model.apply), jax.jit(jax.value_and_grad(loss))
        _, t = timed(lambda: (fwd(variables, obs), grad(variables, obs)))
        progress(f"{name}: compile {t:.1f} s")
        fns[name] = (fwd, grad, variables, t)
    times = {name: ([], [], [], []) for name in fns}
    for _ in range(reps):
        for name, (fwd, grad, v, _) in fns.items():
            for i, f in enumerate((fwd, grad)):
                c = time.process_time()
                _, t = timed(lambda: f(v, obs))
                times[name][i].append(t)
                times[name][2 + i].append(time.process_time() - c)
    med = lambda name, i: 1e3 * float(np.median(times[name][i]))  # noqa: E731
    return [
        dict(
            variant=name,
            fwd_ms=med(name, 0),
            grad_ms=med(name, 1),
            fwd_cpu_ms=med(name, 2),
            grad_cpu_ms=med(name, 3),
            compile_s=fns[name][3],
        )
        for name in fns
    ]


def format_model_rows(rows: list[dict], batch: int) -> str:
    ref = {r["variant"]: r for r in rows}.get("gcn")
    lines = [
        f"| variant | forward ms (B={batch}) | fwd+grad ms (B={batch}) | fwd / gcn | grad / gcn "
        "| fwd CPU-ms | fwd+grad CPU-ms | compile s |",
        "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for r in rows:
        rel = f"{r['fwd_ms'] / ref['fwd_ms']:.2f} | {r['grad_ms'] / ref['grad_ms']:.2f}" if ref else "- | -"
        lines.append(
            f"| {r['variant']} | {r['fwd_ms']:.1f} | {r['grad_ms']:.1f} | {rel} | "
            f"{r['fwd_cpu_ms']:.0f} | {r['grad_cpu_ms']:.0f} | {r['compile_s']:.1f} |"
        )
    return "\n".join(lines)


def add_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--variants", nargs="+", default=list(VARIANTS))
    p.add_argument("--batch", type=int, default=64)
    p.add_argument("--reps", type=int, default=20, help="timed rounds (median reported)")
    p.add_argument("--scene", default=DEFAULT_SCENE)


def run(a: argparse.Namespace) -> None:
    rows = bench_model(tuple(a.variants), a.batch, a.reps, a.scene)
    print(format_model_rows(rows, a.batch), flush=True)
