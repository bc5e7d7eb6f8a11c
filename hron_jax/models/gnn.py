"""Graph layers on jraph-style padded graphs: HGT (heterogeneous graph transformer) and GCN.

Both layers work on ONE padded graph stored as flat tables (batch them with `jax.vmap`):

    x          f32[N, F_in]   node features (one table for every node type)
    node_type  i32[N]         0 room, 1 furniture, 2 object (see hron_jax.graph_types)
    node_mask  bool[N]        live nodes (discovered and real)
    senders    i32[E]         edge sources
    receivers  i32[E]         edge destinations
    edge_mask  bool[E]        live edges; padded edges (pointing at node 0) have False

An edge carries a message only if it is live AND both its endpoints are live (the graph builder
should already guarantee that; we enforce it so a bad builder cannot leak dead nodes). Dead
edges never contribute to any sum, max or normaliser, a node without live incoming edges gets a
zero aggregate (no NaN), and the outputs of dead nodes are zeroed so that they are inert
downstream. Everything has static shapes and is jittable and vmappable.

Semantics follow PyTorch Geometric 2.8 (`torch_geometric.nn.HGTConv` and `GCNConv`), checked
numerically in tests/test_models.py against outputs saved by tools/make_pyg_reference.py;
`hron_jax.models.pyg_compat` converts PyG state dicts to these parameters.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import flax.linen as nn

from hron_jax import graph_types as gt

# PyG's Linear/HeteroLinear default: kaiming_uniform(a=sqrt(5)) == U(+-1/sqrt(fan_in)), i.e.
# variance 1/(3 fan_in). The stacked per-type kernels have leading "batch" axes.
def _fan_in_uniform(batch_axis=()):
    return nn.initializers.variance_scaling(1.0 / 3.0, "fan_in", "uniform",
                                            in_axis=-2, out_axis=-1, batch_axis=batch_axis)


def _bias_uniform(fan_in: int):
    bound = 1.0 / math.sqrt(fan_in)
    return lambda key, shape, dtype=jnp.float32: jax.random.uniform(key, shape, dtype, -bound, bound)


def live_edges(node_mask, senders, receivers, edge_mask):
    """bool[E]: edge is live and both endpoints are live."""
    return edge_mask & node_mask[senders] & node_mask[receivers]


def edge_relations(node_type, senders, receivers, edge_type):
    """i32[E]: HGT relation-triple index of every edge (graph_types.RELATION_INDEX), -1 if illegal.

    Out-of-range types (garbage on padded rows) are clipped before the lookup; such edges are dead
    anyway, and the -1 of an illegal live combination makes the HGT drop that edge.
    """
    table = jnp.asarray(gt.RELATION_INDEX)
    et = jnp.clip(edge_type, 0, gt.NUM_EDGE_TYPES - 1)
    st = jnp.clip(node_type[senders], 0, gt.NUM_NODE_TYPES - 1)
    dt = jnp.clip(node_type[receivers], 0, gt.NUM_NODE_TYPES - 1)
    return table[et, st, dt]


def masked_segment_softmax(logits, live, segment_ids, num_segments):
    """Softmax of logits[E, ...] over the live entries of each segment (PyG `utils.softmax`).

    Dead entries get weight exactly 0 and do not enter the max or the normaliser; a segment with
    no live entry yields all zeros. Like PyG, the max is not differentiated through and 1e-16 is
    added to the denominator.
    """
    live_b = live.reshape(live.shape + (1,) * (logits.ndim - 1))
    neg = jnp.where(live_b, logits, -jnp.inf)
    seg_max = jax.ops.segment_max(neg, segment_ids, num_segments)
    # Empty segments give -inf; replace so no inf - inf appears.
    seg_max = jax.lax.stop_gradient(jnp.where(jnp.isfinite(seg_max), seg_max, 0.0))
    # exp of 0 on dead entries (then zeroed) keeps both the value and its gradient finite.
    z = jnp.where(live_b, logits - seg_max[segment_ids], 0.0)
    e = jnp.where(live_b, jnp.exp(z), 0.0)
    denom = jax.ops.segment_sum(e, segment_ids, num_segments) + 1e-16
    return e / denom[segment_ids]


def _typed_dense(x, types, kernel, bias):
    """Per-node-type affine map: out[n] = x[n] @ kernel[types[n]] + bias[types[n]].

    All types are applied to all nodes and the right one selected: with 3 types this costs 3x a
    plain Dense but avoids gathering an [N, in, out] weight tensor.
    """
    every = jnp.einsum("ni,tio->nto", x, kernel) + bias[None]
    return jnp.take_along_axis(every, types[:, None, None], axis=1)[:, 0]


class HGTConv(nn.Module):
    """One heterogeneous graph transformer layer (Hu et al. 2020), as PyG 2.8 `HGTConv`.

    For node types tau, relation triples r = (src type, edge type, dst type), H heads of width
    D = features / H:
        k, q, v   = per-node-type linear of x (PyG `kqv_lin`, a HeteroDictLinear with bias)
        k_e, v_e  = k[src] @ k_rel[r, h],  v[src] @ v_rel[r, h]   (per relation and head, no bias)
        score_e,h = <q[dst]_h, k_e,h> * p_rel[r, h] / sqrt(D)
        alpha     = softmax of score over ALL live incoming edges of dst, across relations
                    (the current PyG / HGT-paper form; PyG < 2.3 normalised per relation)
        agg[i]    = sum_e alpha_e v_e                      (0 for a node without live in-edges)
        a         = per-node-type linear of gelu(agg)      (exact erf gelu, as torch's default)
        out       = sigmoid(skip[tau]) a + (1 - sigmoid(skip[tau])) x   if F_in == features
                    else a                                  (PyG skips the residual then too)
    Dead nodes output 0.

    Inputs: x f32[N, F_in], node_type i32[N], node_mask bool[N], senders/receivers i32[E],
        relation i32[E] (`edge_relations`, -1 = no relation), edge_mask bool[E].
    Output: f32[N, features]. Sows the attention alpha f32[E, H] (0 on dead edges) as
    ('attention', 'alpha'), collected only when the caller makes 'attention' mutable (and never
    during init, so `init` returns parameters only, valid for single and batched apply).

    Parameters: kqv_kernel [T, F_in, 3F], kqv_bias [T, 3F] (k | q | v blocks), k_rel / v_rel
    [R, H, D, D], p_rel [R, H] (init 1), out_kernel [T, F, F], out_bias [T, F], skip [T] (init 1).

    Cost: node types are not grouped (the table is one padded array with types in any order), so
    the per-type linears run every type on every node (T x) and the relation transforms every
    relation on every node (R x; PyG, with nodes grouped by type, pays ~3.7 x here). Measured on
    the 2-core CPU, 64 graphs of 72 nodes / 196 edges, hidden 128, 2 heads: ~65 ms CPU forward per
    layer, ~4 x that for a gradient. A per-observation one-hot (matmul) formulation of the gathers
    and segment sums was tried and was 2 x slower.
    """

    features: int
    heads: int = 1
    num_node_types: int = gt.NUM_NODE_TYPES
    num_relations: int = gt.NUM_RELATIONS

    @nn.compact
    def __call__(self, x, node_type, node_mask, senders, receivers, relation, edge_mask):
        n, f_in = x.shape
        f, h = self.features, self.heads
        if f % h:
            raise ValueError(f"features ({f}) must be divisible by heads ({h})")
        d = f // h
        t, r = self.num_node_types, self.num_relations

        kqv_kernel = self.param("kqv_kernel", _fan_in_uniform((0,)), (t, f_in, 3 * f))
        kqv_bias = self.param("kqv_bias", _bias_uniform(f_in), (t, 3 * f))
        k_rel = self.param("k_rel", _fan_in_uniform((0, 1)), (r, h, d, d))
        v_rel = self.param("v_rel", _fan_in_uniform((0, 1)), (r, h, d, d))
        p_rel = self.param("p_rel", nn.initializers.ones, (r, h))
        out_kernel = self.param("out_kernel", _fan_in_uniform((0,)), (t, f, f))
        out_bias = self.param("out_bias", _bias_uniform(f), (t, f))
        skip = self.param("skip", nn.initializers.ones, (t,))

        ntype = jnp.clip(node_type, 0, t - 1)
        kqv = _typed_dense(x, ntype, kqv_kernel, kqv_bias)
        k, q, v = (a.reshape(n, h, d) for a in jnp.split(kqv, 3, axis=-1))

        live = live_edges(node_mask, senders, receivers, edge_mask) & (relation >= 0)
        rel = jnp.clip(relation, 0, r - 1)
        # Relation transforms per (node, relation) then gathered per edge: [N, R, H, D] is far
        # smaller than gathering a [E, H, D, D] weight per edge.
        k_all = jnp.einsum("nhd,rhde->nrhe", k, k_rel)
        v_all = jnp.einsum("nhd,rhde->nrhe", v, v_rel)
        k_e = k_all[senders, rel]
        v_e = v_all[senders, rel]
        score = jnp.sum(q[receivers] * k_e, axis=-1) * p_rel[rel] / math.sqrt(d)
        alpha = masked_segment_softmax(score, live, receivers, n)
        if not self.is_initializing():  # keep init's variables free of sown values (batch-agnostic)
            self.sow("attention", "alpha", alpha)

        # where() rather than a product with alpha = 0: a non-finite value on a dead node
        # (0 * inf = NaN) must not reach a live one.
        msg = jnp.where(live[:, None, None], v_e * alpha[..., None], 0.0)
        agg = jax.ops.segment_sum(msg, receivers, n).reshape(n, f)
        out = _typed_dense(jax.nn.gelu(agg, approximate=False), ntype, out_kernel, out_bias)
        if f_in == f:
            gate = jax.nn.sigmoid(skip[ntype])[:, None]
            out = gate * out + (1.0 - gate) * x
        return jnp.where(node_mask[:, None], out, 0.0)


class GCNConv(nn.Module):
    """Graph convolution of Kipf & Welling, as PyG 2.8 `GCNConv` (defaults), edge types ignored.

        out = D^-1/2 (A + I) D^-1/2 (x W) + b

    with A the live edges (sender -> receiver, each live edge counts once, duplicates add up),
    I one self loop per live node (PyG `add_remaining_self_loops`: an existing self-loop edge is
    replaced by it, so live self-loop edges are dropped from A), and D the in-degree of A + I
    (the receiver side, PyG's source_to_target flow). Dead nodes output 0.

    Inputs: x f32[N, F_in], node_mask bool[N], senders/receivers i32[E], edge_mask bool[E].
    Output: f32[N, features]. Parameters: kernel [F_in, features] (glorot), bias [features] (0).
    """

    features: int

    @nn.compact
    def __call__(self, x, node_mask, senders, receivers, edge_mask):
        n = x.shape[0]
        kernel = self.param("kernel", nn.initializers.glorot_uniform(), (x.shape[-1], self.features))
        bias = self.param("bias", nn.initializers.zeros, (self.features,))
        hx = x @ kernel

        live = live_edges(node_mask, senders, receivers, edge_mask) & (senders != receivers)
        w = live.astype(hx.dtype)
        loop = node_mask.astype(hx.dtype)
        deg = jax.ops.segment_sum(w, receivers, n) + loop
        # deg is 0 only for dead nodes; guard the rsqrt so neither value nor gradient is inf.
        dis = jnp.where(deg > 0, jax.lax.rsqrt(jnp.where(deg > 0, deg, 1.0)), 0.0)
        norm = dis[senders] * w * dis[receivers]
        msg = jnp.where(live[:, None], norm[:, None] * hx[senders], 0.0)  # no 0 * inf leaks
        out = jax.ops.segment_sum(msg, receivers, n)
        out = out + (dis * dis * loop)[:, None] * hx
        out = out + bias
        return jnp.where(node_mask[:, None], out, 0.0)
