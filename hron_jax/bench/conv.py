"""Conv encoder fwd+grad in lax.scan: nn.Conv vs PatchConv (`python -m hron_jax.bench conv`).

Measures ms per fwd+grad step of the RGB-D conv stack (3 layers of ModelConfig's defaults) on
f32[--batch, --size, --size, 4], with flax nn.Conv (XLA convolution) and with encoders.PatchConv,
each run as PPO runs minibatches (--steps SGD steps in one lax.scan) and unrolled (the same steps as
straight-line code); best of --repeats calls after compilation. XLA:CPU emits the convolution's
gradient inside a while loop ~30x slower than outside it; PatchConv's slices + matmul do not depend
on the loop: the measurement behind models.encoders.PatchConv.

Prints: the sizes, then the Markdown table | conv | ms / step in lax.scan | ms / step unrolled |, a
row as soon as that conv is measured.
"""

from __future__ import annotations

import argparse

from .common import stream_table, time_calls


def bench_conv(batch: int = 128, size: int = 32, steps: int = 8, repeats: int = 3):
    """Yields rows {conv, scan, unrolled} (ms per step), nn.Conv first, then PatchConv."""
    import flax.linen as nn
    import jax
    import jax.numpy as jnp

    from ..models.config import ModelConfig
    from ..models.encoders import RELU_INIT, PatchConv

    cfg = ModelConfig()
    layers = list(zip(cfg.conv_features, cfg.conv_kernels, cfg.conv_strides))

    class Stack(nn.Module):
        patch: bool

        @nn.compact
        def __call__(self, x):
            for f, k, s in layers:
                conv = (
                    PatchConv(f, k, s, impl="patches")
                    if self.patch
                    else nn.Conv(f, (k, k), (s, s), padding="SAME", kernel_init=RELU_INIT)
                )
                x = nn.relu(conv(x))
            return x

    x = jax.random.normal(jax.random.PRNGKey(0), (steps, batch, size, size, 4))
    for name, patch in (("nn.Conv (XLA convolution)", False), ("PatchConv (slices + matmul)", True)):
        model = Stack(patch)
        params = model.init(jax.random.PRNGKey(1), x[0])
        loss = lambda p, xb: jnp.sum(model.apply(p, xb) ** 2)  # noqa: E731

        def sgd(p, xs, unroll):
            def body(p, xb):
                g = jax.grad(loss)(p, xb)
                return jax.tree.map(lambda a, b: a - 1e-6 * b, p, g), None

            return jax.lax.scan(body, p, xs, unroll=unroll)[0]

        row = dict(conv=name)
        for label, unroll in (("scan", 1), ("unrolled", steps)):
            fn = jax.jit(lambda p, xs, u=unroll: sgd(p, xs, u))
            jax.block_until_ready(fn(params, x))
            row[label] = 1e3 * time_calls(fn, [(params, x)], repeats) / steps
        yield row


def add_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--batch", type=int, default=128, help="minibatch (PPO: 128)")
    p.add_argument("--size", type=int, default=32, help="image side")
    p.add_argument("--steps", type=int, default=8, help="SGD steps per call")
    p.add_argument("--repeats", type=int, default=3)


def run(a: argparse.Namespace) -> None:
    print(
        f"RGB-D conv stack fwd+grad, batch {a.batch}, {a.size}x{a.size}x4, {a.steps} steps per call",
        flush=True,
    )
    stream_table(
        "| conv | ms / step in lax.scan | ms / step unrolled |\n| --- | ---: | ---: |",
        bench_conv(a.batch, a.size, a.steps, a.repeats),
        lambda r: f"| {r['conv']} | {r['scan']:.1f} | {r['unrolled']:.1f} |",
    )
