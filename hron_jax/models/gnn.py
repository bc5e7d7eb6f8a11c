"""Graph layers on jraph-style padded graphs: HGT (heterogeneous graph transformer) and GCN.

Both layers work on ONE padded graph stored as flat tables, or on a batch of such graphs with a
leading [B] axis on every table. HGTConv's fast path is a batch whose node table has a static type
layout (`node_type_counts`, which every env's has): each type's rows of the batch form one table,
and a stack of HGT layers can pass them on as one row table per node type (`split_types` /
`merge_types`); a batch without a layout runs the single-graph form under `jax.vmap`:

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
`hron_jax.models.pyg_compat` converts PyG state dicts to these parameters. HGTConv's
softmax='per_relation' is the paper-era PyG <= 2.2 attention instead (see HGTConv), checked
against an independent NumPy implementation of that formula in the same tests.
"""

from __future__ import annotations

import functools
import math

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from hron_jax import graph_types as gt
from hron_jax.models.lookup import gather_f32, take_rows


# PyG's Linear/HeteroLinear default: kaiming_uniform(a=sqrt(5)) == U(+-1/sqrt(fan_in)), i.e.
# variance 1/(3 fan_in). The stacked per-type kernels have leading "batch" axes.
def _fan_in_uniform(batch_axis=()):
    return nn.initializers.variance_scaling(
        1.0 / 3.0, "fan_in", "uniform", in_axis=-2, out_axis=-1, batch_axis=batch_axis
    )


def _bias_uniform(fan_in: int):
    bound = 1.0 / math.sqrt(fan_in)
    return lambda key, shape, dtype=jnp.float32: jax.random.uniform(key, shape, dtype, -bound, bound)


def _f32(a):
    """float32 view of a (the identity on float32, so the default dtype's numbers are unchanged)."""
    return a.astype(jnp.float32)


def on_rows(f, x):
    """f, a row-wise linear map [M, K] -> [M, O], applied to x [..., K] as one [M, K] matrix:
    returns [..., O]. Over [B, N, K] the kernel's gradient contracts B and N, which XLA:CPU fed
    through a transposed copy of the [B, N, O] gradient (31 ms at B=128, N=119, O=128); on rows
    it is one 2-D dot. Same values."""
    y = f(x.reshape(-1, x.shape[-1]))
    return y.reshape(x.shape[:-1] + y.shape[-1:])


def live_edges(node_mask, senders, receivers, edge_mask):
    """bool[E]: edge is live and both endpoints are live."""
    return edge_mask & node_mask[senders] & node_mask[receivers]


def spread_dead(index, live, num_rows):
    """index [..., E] where live, else the edge's position mod num_rows (broadcastable, >= 1).

    A dead edge's values are masked, but it still takes part in every scatter (the message sum,
    the softmax's max and sum, the gathers' gradients) with a zero. With every dead edge on one
    row, those zero-adds are atomics on one address on a GPU, and early in an episode most edges
    are dead (the builder points them at node 0). Measured on one H200 (`bench profile`,
    exploratory main model, 4096 envs x 16 steps, 32x32): 9.58 -> 3.29 s per PPO update, the HGT
    layers 8.17 -> 1.92 s. Sums are unchanged (x + 0.0 == x).
    """
    return jnp.where(live, index, jnp.arange(index.shape[-1], dtype=index.dtype) % num_rows)


def edge_relations(node_type, senders, receivers, edge_type):
    """i32[(B,) E]: HGT relation-triple index of every edge (graph_types.RELATION_INDEX), -1 if illegal.

    Out-of-range types (garbage on padded rows) are clipped before the lookup; such edges are dead
    anyway, and the -1 of an illegal live combination makes the HGT drop that edge.
    """
    if jnp.ndim(node_type) == 2:  # a batch of graphs: node_type [B, N], the rest [B, E]
        return jax.vmap(edge_relations)(node_type, senders, receivers, edge_type)
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


SOFTMAX_MODES = ("joint", "per_relation")


def _softmax_groups(receivers, relation, num_nodes: int, num_relations: int, softmax: str):
    """Segment ids and count of the HGT attention softmax (static count).

    'joint': one group per receiver (all its incoming edges, across relations). 'per_relation':
    one group per (receiver, relation triple), id receiver * R + relation; `relation` must already
    be clipped to [0, R) (dead edges keep any such id and are excluded by the softmax's mask).
    """
    if softmax == "joint":
        return receivers, num_nodes
    if softmax == "per_relation":
        return receivers * num_relations + relation, num_nodes * num_relations
    raise ValueError(f"HGT softmax must be one of {SOFTMAX_MODES}, got {softmax!r}")


# ---------------------------------------------------------------------------------------------
# HGT internals: relation transforms per source-type slot; one graph, or per-type row tables


@functools.cache
def _relation_slots(num_node_types: int, num_relations: int):
    """Static tables mapping relations to per-source-type "slots".

    Returns (slot_rel i32[T, S], rel_slot i32[R], rel_src i32[R] or None): slot_rel[tau] lists the
    relations whose source type is tau (padded with -1), rel_slot[r] is the position of r in its
    source type's list, rel_src[r] the source type. A node of type tau is the source of at most S
    relations (graph_types: S = 4 of R = 11), so the relation transforms of its key and value cost
    S, not R, D x D products. With other sizes than graph_types' (a generic HGTConv) the source
    type of a relation is unknown: every relation is a slot of every type (S = R) and
    rel_src is None.
    """
    if (num_node_types, num_relations) != (gt.NUM_NODE_TYPES, gt.NUM_RELATIONS):
        return (
            np.tile(np.arange(num_relations, dtype=np.int32), (num_node_types, 1)),
            np.arange(num_relations, dtype=np.int32),
            None,
        )
    rel_src = np.array([src for src, _, _ in gt.RELATION_TRIPLES], np.int32)
    per_type = [np.nonzero(rel_src == tau)[0] for tau in range(num_node_types)]
    slot_rel = np.full((num_node_types, max(len(p) for p in per_type)), -1, np.int32)
    rel_slot = np.zeros(num_relations, np.int32)
    for tau, rels in enumerate(per_type):
        slot_rel[tau, : len(rels)] = rels
        rel_slot[rels] = np.arange(len(rels))
    return slot_rel, rel_slot, rel_src


def _slot_kernels(rel_kernel, slot_rel):
    """[R, H, D, D] relation kernels -> [T, H, D, S * D]: the slots of each source type side by side
    (zero blocks on padding slots)."""
    r, h, d, _ = rel_kernel.shape
    t, s = slot_rel.shape
    padded = jnp.concatenate([rel_kernel, jnp.zeros((1, h, d, d), rel_kernel.dtype)])
    w = padded[np.where(slot_rel >= 0, slot_rel, r)]  # [T, S, H, D, D]
    return w.transpose(0, 2, 3, 1, 4).reshape(t, h, d, s * d)


def _kvq_columns(a, f: int):
    """PyG's k | q | v columns of kqv_kernel / kqv_bias reordered k | v | q (k and v one slice)."""
    return jnp.concatenate([a[..., :f], a[..., 2 * f :], a[..., f : 2 * f]], -1)


def _relation_edges(live, relation, sender_type, num_relations: int, rel_src):
    """(live, rel): an edge of an illegal triple (relation -1), or whose sender is not of its
    relation's source type (rel_src None: unknown, nothing dropped), is dropped; rel is relation
    clipped to [0, R) (dead edges keep any such index)."""
    rel = jnp.clip(relation, 0, num_relations - 1)
    live = live & (relation >= 0)
    if rel_src is not None:  # a relation's edges leave nodes of its source type (edge_relations)
        live = live & (jnp.asarray(rel_src)[rel] == sender_type)
    return live, rel


def _attend(p_rel, q_e, k_e, v_e, rel, live, dst, rows: int, softmax: str):
    """The attention of every edge and the messages summed at the receivers.

    q_e / k_e / v_e f32[E, H, D] (the receiver's query, the sender's relation-transformed key and
    value: `gather_f32` rows, also of bfloat16 tables), rel i32[E] in [0, R), live bool[E], dst
    i32[E] the receiver's row of `rows`. Returns (gelu(aggregate) f32[rows, H D], alpha f32[E, H]).
    """
    h, d = q_e.shape[-2:]
    score = jnp.sum(q_e * k_e, -1) * take_rows(p_rel, rel) / math.sqrt(d)
    alpha = masked_segment_softmax(score, live, *_softmax_groups(dst, rel, rows, p_rel.shape[0], softmax))
    # where() rather than a product with alpha = 0: a non-finite value on a dead row must not leak.
    msg = jnp.where(live[:, None, None], v_e * alpha[..., None], 0.0)
    agg = jax.ops.segment_sum(msg, dst, rows).reshape(rows, h * d)
    return jax.nn.gelu(agg, approximate=False), alpha


def _hgt_single(
    params, x, node_type, node_mask, senders, receivers, relation, edge_mask, *, heads: int, softmax: str
):
    """HGTConv on ONE graph in any node order: (out f32[N, F], alpha f32[E, H]).

    Every per-type linear runs all T types on every node and selects (an input-side one-hot: one
    [N, T F_in] @ [T F_in, O] matmul), and keys / values get all R relation transforms: T x and
    R / S x the matmul work of `_hgt_tables`. For graphs without a static type layout (a batch
    vmaps it: the weights are shared, not copied per graph), and the form the tables are tested
    against.
    """
    n, f_in = x.shape
    t, _, f3 = params["kqv_kernel"].shape
    f = f3 // 3
    h, d = heads, f // heads
    r = params["k_rel"].shape[0]
    _, _, rel_src = _relation_slots(t, r)

    ntype = jnp.clip(node_type, 0, t - 1)
    live = live_edges(node_mask, senders, receivers, edge_mask)
    live, rel = _relation_edges(live, relation, ntype[senders], r, rel_src)
    onehot = jax.nn.one_hot(ntype, t, dtype=x.dtype)

    def typed(a, kernel, bias):  # [N, I] -> [N, O], kernel [T, I, O]
        mixed = (onehot[:, :, None] * a[:, None, :]).reshape(n, -1)
        return mixed @ kernel.reshape(-1, kernel.shape[-1]) + onehot @ bias

    x0 = jnp.where(node_mask[:, None], x, 0.0)
    kqv = typed(x0, params["kqv_kernel"], params["kqv_bias"])
    k, q, v = (kqv[:, i * f : (i + 1) * f].reshape(n, h, d) for i in range(3))
    k_all = jnp.einsum("nhd,rhde->nrhe", k, params["k_rel"]).reshape(n * r, h, d)
    v_all = jnp.einsum("nhd,rhde->nrhe", v, params["v_rel"]).reshape(n * r, h, d)
    senders, receivers = spread_dead(senders, live, n), spread_dead(receivers, live, n)
    row = senders * r + rel
    (q_e,), (k_e,), (v_e,) = gather_f32(q, receivers), gather_f32(k_all, row), gather_f32(v_all, row)
    a, alpha = _attend(params["p_rel"], q_e, k_e, v_e, rel, live, receivers, n, softmax)
    out = typed(a.astype(x.dtype), params["out_kernel"], params["out_bias"])
    if f_in == f:
        gate = jax.nn.sigmoid(onehot.astype(jnp.float32) @ params["skip"])[:, None]
        out = gate * out + (1.0 - gate) * x0
    return jnp.where(node_mask[:, None], out, 0.0).astype(x.dtype), alpha


def _row_types(counts: tuple[int, ...], num_nodes: int) -> np.ndarray:
    """i32[num_nodes]: the type of each row in the static type layout `counts` (the first counts[0]
    rows of a graph are of type 0, the next counts[1] of type 1, ...), -1 on the padding rows."""
    row_type = np.full(num_nodes, -1, np.int32)
    row_type[: sum(counts)] = np.repeat(np.arange(len(counts)), counts)
    return row_type


def layout_mask(node_type, node_mask, counts: tuple[int, ...]):
    """bool[B, N]: node_mask, less the live nodes whose node_type is not their row's type in the
    static type layout `counts` (`_row_types`), so that a table which breaks the layout cannot
    mislabel a node: such a node is dropped, as a dead one."""
    return node_mask & (node_type == _row_types(counts, node_type.shape[-1]))


def split_types(x, node_mask, counts: tuple[int, ...]):
    """[B, N, F] node table of a static type layout -> one row table per type, ([B * counts[0], F],
    [B * counts[1], F], ...), the batch's rows of that type in graph order; rows of dead nodes
    (node_mask [B, N] false, `layout_mask`) are zero, so garbage (even NaN) there reaches no value
    or gradient. The form `_hgt_tables` takes and returns, so a stack of HGT layers converts once."""
    b, _, f = x.shape
    x0 = jnp.where(node_mask[..., None], x, 0.0)
    ends = np.cumsum(counts)
    return tuple(x0[:, e - c : e].reshape(b * c, f) for c, e in zip(counts, ends))


def merge_types(xs, counts: tuple[int, ...], batch: int, num_nodes: int):
    """The inverse of `split_types`: per-type row tables -> [batch, num_nodes, F], padding rows zero."""
    b, f = batch, xs[0].shape[-1]
    parts = [a.reshape(b, c, f) for a, c in zip(xs, counts)]
    parts.append(jnp.zeros((b, num_nodes - sum(counts), f), xs[0].dtype))
    return jnp.concatenate(parts, 1)


def _hgt_tables(
    params,
    xs,
    node_mask,
    senders,
    receivers,
    relation,
    edge_mask,
    *,
    counts: tuple[int, ...],
    heads: int,
    softmax: str,
):
    """HGTConv on a batch of graphs whose node table has a static type layout (`layout_mask`), with
    the node features as one row table per type: xs = `split_types(x, node_mask, counts)`, rows of
    dead nodes zero. node_mask [B, N] already `layout_mask`ed, the edges [B, E]. Returns (outs, one
    [B * counts[tau], F] table per type with dead rows zero, the next layer's input; alpha f32[B,
    E, H]), the values of `_hgt_single` on each graph with the same parameters (to float rounding).

    A type's rows of the whole batch are one table, so each per-type linear is one plain matmul and
    each relation transform one matmul per (k | v, head): no type applied to a node of another
    type, no permutation, no per-graph weight copies. Between layers the tables stay tables (the scene
    graph encoder splits once and merges once): slicing them out of the [B, N, F] node table and
    concatenating them back in every layer, and the same in the gradient, was ~4 % of the HGT
    layers' bytes on a GPU (estimated for the 4096-env training chunk, docs/benchmarks.md, "GB
    moved"). Same values.
    """
    b, n = node_mask.shape
    f_in = xs[0].shape[-1]
    t, _, f3 = params["kqv_kernel"].shape
    f = f3 // 3
    h, d = heads, f // heads
    r = params["k_rel"].shape[0]
    slot_rel, rel_slot, rel_src = _relation_slots(t, r)
    s = slot_rel.shape[1]
    starts = np.cumsum(counts) - np.asarray(counts)
    rows = b * np.asarray(counts)  # rows of each type's tables
    q_off = np.concatenate([[0], np.cumsum(rows)[:-1]])  # a type's first row in the q / aggregate table
    kv_off = q_off * 2 * h * s  # ... and in the flat k | v table (rows of D)

    kernel, bias = _kvq_columns(params["kqv_kernel"], f), _kvq_columns(params["kqv_bias"], f)
    w = jnp.stack([_slot_kernels(params["k_rel"], slot_rel), _slot_kernels(params["v_rel"], slot_rel)], 1)
    qs, kvts = [], []
    for tau in range(t):
        kvq = xs[tau] @ kernel[tau] + bias[tau]
        qs.append(kvq[:, 2 * f :].reshape(rows[tau], h, d))
        # The S relation transforms of each row's key and value, in the matmul's own layout
        # [k | v, H, rows, S D]; each edge gathers its D columns (no transposed copy of the table).
        kv = kvq[:, : 2 * f].reshape(rows[tau], 2, h, d)
        kvts.append(jnp.einsum("njhd,jhde->jhne", kv, w[tau]).reshape(-1, d))
    q, table = jnp.concatenate(qs), jnp.concatenate(kvts)

    e = senders.shape[-1]
    graph = jnp.arange(b, dtype=senders.dtype)[:, None]
    row_t = jnp.asarray(_row_types(counts, n))
    flat = lambda a: (graph * n + a).reshape(-1)  # noqa: E731  (a node's row in the batch)
    live = live_edges(node_mask.reshape(-1), flat(senders), flat(receivers), edge_mask.reshape(-1))
    st, dt = jnp.clip(row_t[senders], 0, t - 1), jnp.clip(row_t[receivers], 0, t - 1)
    live, rel = _relation_edges(live, relation.reshape(-1), st.reshape(-1), r, rel_src)
    count, start = jnp.asarray(counts, senders.dtype), jnp.asarray(starts, senders.dtype)
    # A dead edge takes a row of its graph and type (spread_dead): in range, not one shared row.
    live_b = live.reshape(b, e)
    local_src = spread_dead(senders - start[st], live_b, jnp.maximum(count[st], 1))
    local_dst = spread_dead(receivers - start[dt], live_b, jnp.maximum(count[dt], 1))
    src = (graph * count[st] + local_src).reshape(-1)
    dst = (jnp.asarray(q_off, senders.dtype)[dt] + graph * count[dt] + local_dst).reshape(-1)
    st = st.reshape(-1)
    n_src = jnp.asarray(rows, senders.dtype)[st][:, None]
    slot = jnp.asarray(rel_slot)[rel][:, None]
    k_row = (
        jnp.asarray(kv_off, senders.dtype)[st][:, None] + (jnp.arange(h) * n_src + src[:, None]) * s + slot
    )
    v_row = k_row + h * n_src * s
    (q_e,), (k_e, v_e) = gather_f32(q, dst), gather_f32(table, k_row, v_row)
    a, alpha = _attend(params["p_rel"], q_e, k_e, v_e, rel, live, dst, int(rows.sum()), softmax)
    a = a.astype(xs[0].dtype)

    outs = []
    for tau in range(t):
        out = a[q_off[tau] : q_off[tau] + rows[tau]] @ params["out_kernel"][tau] + params["out_bias"][tau]
        if f_in == f:
            gate = jax.nn.sigmoid(params["skip"][tau])
            out = gate * out + (1.0 - gate) * xs[tau]
        live_rows = node_mask[:, starts[tau] : starts[tau] + counts[tau]].reshape(-1, 1)
        outs.append(jnp.where(live_rows, out, 0.0).astype(xs[0].dtype))
    return tuple(outs), alpha.reshape(b, e, h)


class HGTConv(nn.Module):
    """One heterogeneous graph transformer layer (Hu et al. 2020), as PyG 2.8 `HGTConv`.

    For node types tau, relation triples r = (src type, edge type, dst type), H heads of width
    D = features / H:
        k, q, v   = per-node-type linear of x (PyG `kqv_lin`, a HeteroDictLinear with bias)
        k_e, v_e  = k[src] @ k_rel[r, h],  v[src] @ v_rel[r, h]   (per relation and head, no bias)
        score_e,h = <q[dst]_h, k_e,h> * p_rel[r, h] / sqrt(D)
        alpha     = softmax of score over the live incoming edges of dst:
                    softmax='joint' (default): over ALL of them, across relations (PyG >= 2.3 and
                        the HGT paper's form);
                    softmax='per_relation': separately over those of each relation triple r
                        (PyG <= 2.2, before PR #6178; the form the HRON paper trained with)
        agg[i]    = sum_e alpha_e v_e                      (0 for a node without live in-edges;
                    per_relation: the sum over relations of each relation's softmax-weighted
                    messages, PyG 2.2's group='sum'; a relation with no live in-edge adds 0)
        a         = per-node-type linear of gelu(agg)      (exact erf gelu, as torch's default)
        out       = sigmoid(skip[tau]) a + (1 - sigmoid(skip[tau])) x   if F_in == features
                    else a                                  (PyG skips the residual then too)
    Dead nodes output 0.

    Inputs: one graph, x f32[N, F_in], node_type i32[N], node_mask bool[N], senders/receivers
        i32[E], relation i32[E] (`edge_relations`, -1 = no relation), edge_mask bool[E]; or a
        batch of graphs with a leading axis on every input (x f32[B, N, F_in], ..., senders
        i32[B, E]; the fast path with node_type_counts, see Cost).
    dtype: compute dtype ('float32' or 'bfloat16', ModelConfig.gnn_dtype): x, the kernels and biases
        and so the k / q / v tables and their per-edge gathers take it; scores, softmax, the
        message sum and the gathers' gradients (`lookup.gather_f32`) are float32, parameters
        float32.
    Output: [(B,) N, features] in dtype. Sows the attention alpha f32[(B,) E, H] (0 on dead edges) as
    ('attention', 'alpha'), collected only when the caller makes 'attention' mutable (and never
    during init, so `init` returns parameters only, valid for single and batched apply). The shape
    is the same for both softmax modes, but not the normalisation: under 'joint' the alphas of
    the live in-edges of a receiver sum to 1 per head; under 'per_relation' they sum to 1 per
    head AND incoming relation triple, so a receiver hands out one unit of attention per relation
    type it receives (e.g. a room with inRoom edges from furniture and from objects and a
    roomConnected edge sums to 3). Reductions that assume one unit per receiver must normalise
    per relation (or by the receiver's sum) first.

    softmax: 'joint' or 'per_relation' (ModelConfig.hgt_softmax). Parameters, shapes and cost are
    the same for both (per_relation's softmax has N x R segments instead of N).

    Parameters: kqv_kernel [T, F_in, 3F], kqv_bias [T, 3F] (k | q | v blocks), k_rel / v_rel
    [R, H, D, D], p_rel [R, H] (init 1), out_kernel [T, F, F], out_bias [T, F], skip [T] (init 1).

    Relation contract: an edge of relation r must leave a node of r's source type, as
    `edge_relations` guarantees (PyG's typed edge stores cannot express anything else); a live
    edge whose sender has another type is dropped like an illegal triple. (With non-default
    num_node_types / num_relations the source types are unknown and nothing is dropped.)

    Cost: with node_type_counts (below), each type's rows of the batch are one table
    (`_hgt_tables`), so each per-type linear is one plain matmul (no type is applied to a node of
    another type) and each node's key and value get only the S relation transforms of its type as
    a source (S = 4 of R = 11). For 64 house.xml graphs (119 nodes, 386 edges), hidden 128, 2
    heads that is 1.00 GMAC of matmul per layer forward, instead of 2.88 GMAC for every type and
    relation on every node (`_hgt_single`, which graphs without a layout take, vmapped over a
    batch; PyG, grouping by type, does about as much as the tables). Counted from the traced
    dot_generals; timings: `python -m hron_jax.bench model`.

    node_type_counts: the node table's static type layout (every env's `env.node_type_counts`;
    navigation: rooms, furniture, objects, then padding rows): the first counts[0] rows of every
    graph are of type 0, the next counts[1] of type 1, and so on. A live node off its row's type
    (or a live padding row) is dropped. None (the default: graphs in any node order): types are
    read from node_type, and each graph runs `_hgt_single`; same values and parameters. With
    node_type_counts, x may also be the batch's per-type row tables (`split_types`); the output is
    then such tables too, so a stack of layers splits the node table once and merges it once
    (`merge_types`), as the scene-graph encoder does.
    """

    features: int
    heads: int = 1
    num_node_types: int = gt.NUM_NODE_TYPES
    num_relations: int = gt.NUM_RELATIONS
    softmax: str = "joint"
    dtype: str = "float32"  # compute dtype (ModelConfig.gnn_dtype); parameters are float32
    node_type_counts: tuple[int, ...] | None = None  # static type layout of the node table, if any

    @nn.compact
    def __call__(self, x, node_type, node_mask, senders, receivers, relation, edge_mask):
        tables = isinstance(x, tuple)  # per-type row tables (split_types), returned as such
        if not tables and x.ndim not in (2, 3):
            raise ValueError(f"x must be [N, F] or [B, N, F], got shape {x.shape}")
        if self.softmax not in SOFTMAX_MODES:
            raise ValueError(f"HGTConv softmax must be one of {SOFTMAX_MODES}, got {self.softmax!r}")
        f_in = x[0].shape[-1] if tables else x.shape[-1]
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

        params = dict(
            kqv_kernel=kqv_kernel,
            kqv_bias=kqv_bias,
            k_rel=k_rel,
            v_rel=v_rel,
            p_rel=p_rel,
            out_kernel=out_kernel,
            out_bias=out_bias,
            skip=skip,
        )
        # Kernels, biases and the node features take the compute dtype; p_rel and skip scale
        # float32 scores and the output mix, so they stay float32.
        dt = jnp.dtype(self.dtype)
        params = {k: v if k in ("p_rel", "skip") else v.astype(dt) for k, v in params.items()}
        x = tuple(a.astype(dt) for a in x) if tables else x.astype(dt)
        graph = (node_type, node_mask, senders, receivers, relation, edge_mask)
        if tables and (self.node_type_counts is None or len(x) != t):
            raise ValueError(f"HGTConv takes {t} per-type row tables only with node_type_counts")
        if self.node_type_counts is not None:
            one = not tables and x.ndim == 2  # a single graph runs as a batch of one
            if one:
                x, graph = x[None], tuple(a[None] for a in graph)
            counts = self._counts(graph[0].shape[-1])
            mask = layout_mask(graph[0], graph[1], counts)
            xs = x if tables else split_types(x, mask, counts)
            out, alpha = _hgt_tables(
                params, xs, mask, *graph[2:], counts=counts, heads=h, softmax=self.softmax
            )
            if not tables:
                out = merge_types(out, counts, *x.shape[:2])
            if one:
                out, alpha = out[0], alpha[0]
        else:
            run = functools.partial(_hgt_single, heads=h, softmax=self.softmax)
            out, alpha = (jax.vmap(run, (None,) + (0,) * 7) if x.ndim == 3 else run)(params, x, *graph)
        if not self.is_initializing():  # keep init's variables free of sown values (batch-agnostic)
            self.sow("attention", "alpha", alpha)
        return out

    def _counts(self, num_rows: int) -> tuple[int, ...]:
        counts = tuple(self.node_type_counts)
        if len(counts) != self.num_node_types or min(counts) < 0 or sum(counts) > num_rows:
            raise ValueError(
                f"node_type_counts {counts} must give {self.num_node_types} non-negative row counts "
                f"that fit the {num_rows} rows of the node table"
            )
        return counts


class GCNConv(nn.Module):
    """Graph convolution of Kipf & Welling, as PyG 2.8 `GCNConv` (defaults), edge types ignored.

        out = D^-1/2 (A + I) D^-1/2 (x W) + b

    with A the live edges (sender -> receiver, each live edge counts once, duplicates add up),
    I one self loop per live node (PyG `add_remaining_self_loops`: an existing self-loop edge is
    replaced by it, so live self-loop edges are dropped from A), and D the in-degree of A + I
    (the receiver side, PyG's source_to_target flow). Dead nodes output 0.

    Inputs: x f32[N, F_in], node_mask bool[N], senders/receivers i32[E], edge_mask bool[E], or a
    batch with a leading axis on each. Output: [(B,) N, features] in dtype (x W in dtype, the
    normalised sums float32). Parameters: kernel [F_in, features] (glorot), bias [features] (0).
    """

    features: int
    dtype: str = "float32"  # compute dtype of x W (ModelConfig.gnn_dtype); sums stay float32

    @nn.compact
    def __call__(self, x, node_mask, senders, receivers, edge_mask):
        kernel = self.param("kernel", nn.initializers.glorot_uniform(), (x.shape[-1], self.features))
        bias = self.param("bias", nn.initializers.zeros, (self.features,))
        kernel, x = kernel.astype(self.dtype), x.astype(self.dtype)
        hx = on_rows(lambda rows: rows @ kernel, x)  # x W, not vmapped per graph (on_rows)
        if x.ndim == 3:  # a batch of graphs: [B, N, F_in], [B, N], [B, E] ...
            return jax.vmap(_gcn, in_axes=(0, None, 0, 0, 0, 0))(
                hx, bias, node_mask, senders, receivers, edge_mask
            )
        return _gcn(hx, bias, node_mask, senders, receivers, edge_mask)


def _gcn(hx, bias, node_mask, senders, receivers, edge_mask):
    """GCNConv on one graph (see the class), from its transformed features hx = x W [N, F]."""
    n = hx.shape[0]
    live = live_edges(node_mask, senders, receivers, edge_mask) & (senders != receivers)
    senders, receivers = spread_dead(senders, live, n), spread_dead(receivers, live, n)
    w = live.astype(jnp.float32)
    loop = node_mask.astype(jnp.float32)
    deg = jax.ops.segment_sum(w, receivers, n) + loop
    # deg is 0 only for dead nodes; guard the rsqrt so neither value nor gradient is inf.
    dis = jnp.where(deg > 0, jax.lax.rsqrt(jnp.where(deg > 0, deg, 1.0)), 0.0)
    norm = dis[senders] * w * dis[receivers]
    msg = jnp.where(live[:, None], norm[:, None] * gather_f32(hx, senders)[0], 0.0)  # no 0 * inf leaks
    out = jax.ops.segment_sum(msg, receivers, n)
    out = out + (dis * dis * loop)[:, None] * _f32(hx)
    out = out + bias
    return jnp.where(node_mask[:, None], out, 0.0).astype(hx.dtype)
