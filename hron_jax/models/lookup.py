"""Row lookups whose gradients avoid XLA:GPU's slow scatter-adds.

    take_rows(table, idx) == table[idx]       table [R, ...], idx int [...] in [0, R)
                                              -> [*idx.shape, ...], bitwise the same forward
    Embed                                     flax nn.Embed (same parameters) through take_rows

The gradient of `table[idx]` w.r.t. table is a scatter-add of the output's cotangent into R rows.
XLA:GPU emits it with atomic adds, which serialise when many indices share few rows. Measured on
one H100 (`python -m hron_jax.bench profile`, exploratory, 1024 envs x 16 steps, one PPO update):
41 ms per HGT layer scattering the per-edge relation priors into p_rel's 11 x 2 entries, 33-36 ms
each for the node featurizer's category and node-type embeddings, next to 1.7 s for the whole
update. Here, on a GPU (lax.platform_dependent), that gradient is one_hot(idx, R)^T @ cotangent,
a matmul at full float32 precision. On the CPU it stays the scatter-add, which XLA:CPU runs as
one sequential pass (the matmul costs ~3x there: rgbd_sg_attn fwd+grad at batch 64 on the 2-core
VM, `bench model`, 311 -> 403 ms), so CPU numbers are bitwise those of a plain gather.
Used wherever a parameter table is indexed per edge or node: the HGT's relation priors (gnn.py),
the category / node-type / map-class embeddings (encoders.py). Integer indices get no gradient (as
with a gather).

    gather_f32(table, *idxs) == (table[idx] in float32 for idx in idxs)
                                              table [R, ...] float32 or bfloat16

The per-edge gathers of the GNN's node tables (gnn.py) with ModelConfig.gnn_dtype='bfloat16': the
rows are read in bfloat16, but the gradient is summed in float32 and rounded to bfloat16 once per
row. Autodiff of a bfloat16 gather scatter-adds bfloat16 cotangents, and XLA:GPU's bfloat16
scatter-adds are slow: on one H100 (2026-12-05, `bench profile`, exploratory main model, 4096
envs x 16 steps, 32x32) the HGT layers' gather gradients took 1,203 ms per PPO update in bfloat16
(270-560 GB/s) against 205 ms in float32 (3.8-5.3 TB/s), so a bfloat16 update was slower than a
float32 one (3,403 vs 3,347 ms). A float32 table takes the plain gather (bitwise unchanged).
"""

from __future__ import annotations

import functools

import flax.linen as nn
import jax
import jax.numpy as jnp


@functools.partial(jax.custom_vjp, nondiff_argnums=(2,))
def _take_rows(table, idx, num_rows: int):
    return table[idx]


def _take_rows_fwd(table, idx, num_rows: int):
    return table[idx], idx


def _scatter_grad(num_rows: int, idx, g):
    """The gather's own transpose: XLA:CPU adds into the rows one index after the other."""
    return jnp.zeros((num_rows,) + g.shape[idx.ndim :], g.dtype).at[idx].add(g)


def _matmul_grad(num_rows: int, idx, g):
    onehot = jax.nn.one_hot(idx, num_rows, dtype=g.dtype)  # [*I, R]
    axes = tuple(range(idx.ndim))
    return jnp.tensordot(onehot, g, (axes, axes), precision=jax.lax.Precision.HIGHEST)


def _take_rows_bwd(num_rows: int, idx, g):
    grad = jax.lax.platform_dependent(
        idx,
        g,
        cpu=functools.partial(_scatter_grad, num_rows),
        default=functools.partial(_matmul_grad, num_rows),
    )
    return grad, None


_take_rows.defvjp(_take_rows_fwd, _take_rows_bwd)


@functools.partial(jax.custom_vjp, nondiff_argnums=(2,))
def _gather_f32(table, idxs, num_rows: int):
    return tuple(table[i].astype(jnp.float32) for i in idxs)


def _gather_f32_fwd(table, idxs, num_rows: int):
    # The table's dtype rides along as a zero-size array (residuals are arrays).
    return _gather_f32(table, idxs, num_rows), (idxs, jnp.zeros((0,), table.dtype))


def _gather_f32_bwd(num_rows: int, res, gs):
    # All gathers' cotangents into one float32 table, rounded once: a table per gather, each
    # rounded and then summed, would materialise them all (in XLA:GPU's program for an H100).
    idxs, like = res
    acc = jnp.zeros((num_rows,) + gs[0].shape[idxs[0].ndim :], jnp.float32)
    for i, g in zip(idxs, gs):
        acc = acc.at[i].add(g)
    return acc.astype(like.dtype), None


_gather_f32.defvjp(_gather_f32_fwd, _gather_f32_bwd)


def gather_f32(table: jax.Array, *idxs: jax.Array) -> tuple[jax.Array, ...]:
    """(table[idx] for idx in idxs) along the first axis, in float32, the gradient of all of them
    summed in one float32 table (see above)."""
    if table.dtype == jnp.float32:
        return tuple(table[i] for i in idxs)
    return _gather_f32(table, tuple(jnp.asarray(i) for i in idxs), table.shape[0])


def take_rows(table: jax.Array, idx: jax.Array) -> jax.Array:
    """table[idx] along the first axis (idx in [0, R)), with a one-hot-matmul gradient."""
    return _take_rows(table, jnp.asarray(idx), table.shape[0])


class Embed(nn.Embed):
    """nn.Embed (parameter 'embedding' [num_embeddings, features]) looked up with `take_rows`."""

    def __call__(self, inputs):
        if not jnp.issubdtype(inputs.dtype, jnp.integer):
            raise ValueError(f'Embed takes integer ids, got {inputs.dtype}')
        (embedding,) = self.promote_dtype(self.embedding, dtype=self.dtype, inexact=False)
        return take_rows(embedding, inputs)
