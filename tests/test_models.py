"""Tests of hron_jax.models: PyG agreement, masking, equivariance, pooling, every variant.

The PyG references (tests/data/*_reference.npz) are frozen outputs of torch_geometric 2.8 made by
tools/make_pyg_reference.py; torch is not needed here. HGTConv(softmax='per_relation'), the
paper-era PyG <= 2.2 attention, is checked against `_np_hgt_per_relation`, a NumPy loop version.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import pathlib
import re

import flax.linen as nn
import jax
import jax.numpy as jnp
import jraph
import numpy as np
import pytest

from hron_jax import graph_types as gt
from hron_jax.errors import ConfigError
from hron_jax.models import (
    VARIANTS,
    ActorCritic,
    GCNConv,
    HGTConv,
    ModelConfig,
    attention_readout,
    edge_relations,
    make_model,
    mean_pool,
    task_driven_pool,
)
from hron_jax.models.gnn import layout_mask, merge_types, split_types, spread_dead
from hron_jax.models.pyg_compat import gcn_params_from_pyg, hgt_params_from_pyg
from hron_jax.models.word_vectors import load_category_vectors
from hron_jax.scenes import vocabulary

DATA = pathlib.Path(__file__).resolve().parent / "data"
TOL = 1e-5


def _load(name):
    with np.load(DATA / name) as d:
        return {k: d[k] for k in d.files}


# --- layer runners (jitted once per module shape; reused across tests) -----------------------
_HGT = HGTConv(16, heads=2)
_GCN = GCNConv(16)


# Full f32 matmuls even on GPUs whose default is TF32, so the 1e-5 tolerance means something.
@jax.jit
@jax.default_matmul_precision("highest")
def _hgt_two_layers(p1, p2, x, node_type, mask, senders, receivers, edge_type, edge_mask):
    rel = edge_relations(node_type, senders, receivers, edge_type)
    args = (node_type, mask, senders, receivers, rel, edge_mask)
    h1 = _HGT.apply({"params": p1}, x, *args)
    h2 = _HGT.apply({"params": p2}, jax.nn.relu(h1), *args)
    return h1, h2


@jax.jit
@jax.default_matmul_precision("highest")
def _gcn_two_layers(p1, p2, x, node_type, mask, senders, receivers, edge_type, edge_mask):
    del node_type, edge_type
    h1 = _GCN.apply({"params": p1}, x, mask, senders, receivers, edge_mask)
    h2 = _GCN.apply({"params": p2}, jax.nn.relu(h1), mask, senders, receivers, edge_mask)
    return h1, h2


def _reference(kind):
    d = _load(f"{kind}_reference.npz")
    if kind == "hgt":
        heads = int(d["heads"])
        assert list(d["relation_names"]) == ["__".join(t) for t in gt.relation_names()]
        p1, p2 = (hgt_params_from_pyg(d, f"conv{i}.", heads) for i in (1, 2))
        run = _hgt_two_layers
    else:
        p1, p2 = (gcn_params_from_pyg(d, f"conv{i}.") for i in (1, 2))
        run = _gcn_two_layers
    graph = dict(
        x=d["x"],
        node_type=d["node_type"],
        mask=np.ones(len(d["x"]), bool),
        senders=d["senders"],
        receivers=d["receivers"],
        edge_type=d["edge_type"],
        edge_mask=np.ones(len(d["senders"]), bool),
    )
    return d, p1, p2, graph, run


def _call(run, p1, p2, g):
    return run(
        p1,
        p2,
        g["x"],
        g["node_type"],
        g["mask"],
        g["senders"],
        g["receivers"],
        g["edge_type"],
        g["edge_mask"],
    )


def _pad(g, extra_nodes, extra_edges, rng, garbage=1.0):
    """Append dead nodes (random features * garbage) and edges that must all be ignored:
    padded edges (0 -> 0, mask False), masked edges between live nodes, and edges with mask True
    that touch a dead node."""
    n, e = len(g["x"]), len(g["senders"])
    x = np.concatenate([g["x"], garbage * rng.standard_normal((extra_nodes, g["x"].shape[1]))])
    node_type = np.concatenate([g["node_type"], rng.integers(0, 3, extra_nodes)]).astype(np.int32)
    mask = np.concatenate([g["mask"], np.zeros(extra_nodes, bool)])
    k = extra_edges // 3
    pad_s = np.zeros(k, np.int32)
    live_pair_s, live_pair_r = rng.integers(0, n, k), rng.integers(0, n, k)
    dead_s = rng.integers(n, n + extra_nodes, extra_edges - 2 * k)
    dead_r = rng.integers(0, n, extra_edges - 2 * k)
    senders = np.concatenate([g["senders"], pad_s, live_pair_s, dead_s]).astype(np.int32)
    receivers = np.concatenate([g["receivers"], pad_s, live_pair_r, dead_r]).astype(np.int32)
    # Dead edges get the most tempting types (legal triples are likely).
    edge_type = np.concatenate([g["edge_type"], rng.integers(0, 9, extra_edges)]).astype(np.int32)
    edge_mask = np.concatenate([g["edge_mask"], np.zeros(2 * k, bool), np.ones(extra_edges - 2 * k, bool)])
    # Shuffle the table so dead rows are interleaved with live ones.
    perm_n = rng.permutation(n + extra_nodes)
    inv = np.argsort(perm_n)
    perm_e = rng.permutation(e + extra_edges)
    out = dict(
        x=x[perm_n].astype(np.float32),
        node_type=node_type[perm_n],
        mask=mask[perm_n],
        senders=inv[senders][perm_e].astype(np.int32),
        receivers=inv[receivers][perm_e].astype(np.int32),
        edge_type=edge_type[perm_e],
        edge_mask=edge_mask[perm_e],
    )
    return out, inv[:n]  # inv[:n]: new row of each original node


# --- PyG agreement ---------------------------------------------------------------------------
@pytest.mark.parametrize("kind", ["hgt", "gcn"])
def test_matches_pyg(kind):
    d, p1, p2, g, run = _reference(kind)
    h1, h2 = _call(run, p1, p2, g)
    err1 = np.abs(np.asarray(h1) - d["out1"]).max()
    err2 = np.abs(np.asarray(h2) - d["out2"]).max()
    print(
        f"{kind} vs torch_geometric {d['torch_geometric_version']}: "
        f"layer1 max err {err1:.2e}, layer2 max err {err2:.2e}"
    )
    assert err1 < TOL and err2 < TOL
    # The reference must be discriminating: outputs are not trivially small.
    assert np.abs(d["out2"]).max() > 0.1


def test_pyg_reference_is_sensitive_to_relation_layout():
    """Negative control: a head/relation transposition of k_rel is caught by the reference."""
    d, p1, p2, g, run = _reference("hgt")
    bad = dict(p1)
    bad["k_rel"] = np.asarray(d["conv1.k_rel.weight"]).reshape(p1["k_rel"].shape)
    h1, _ = _call(run, bad, p2, g)
    assert np.abs(np.asarray(h1) - d["out1"]).max() > 1e-2


@pytest.mark.parametrize("kind", ["hgt", "gcn"])
def test_padding_and_dead_nodes_do_not_change_live_outputs(kind):
    """Reference graph embedded in a larger padded table with dead nodes carrying garbage
    (finite, then NaN), padded/masked edges and live-masked edges touching dead nodes."""
    d, p1, p2, g, run = _reference(kind)
    rng = np.random.default_rng(1)
    for garbage in (100.0, np.nan):
        gp, rows = _pad(g, extra_nodes=7, extra_edges=30, rng=rng, garbage=garbage)
        h1, h2 = (np.asarray(h) for h in _call(run, p1, p2, gp))
        assert np.isfinite(h2).all()
        np.testing.assert_allclose(h1[rows], d["out1"], atol=TOL, rtol=0)
        np.testing.assert_allclose(h2[rows], d["out2"], atol=TOL, rtol=0)
        dead = ~gp["mask"]
        assert (h2[dead] == 0).all()


def test_spread_dead_keeps_live_indices_and_spreads_dead_ones_in_range():
    """Dead edges get rows in [0, rows) from their position, a bounded number per row (no shared
    row for the GPU's atomics to queue on); live edges keep theirs. Per-graph row counts broadcast."""
    rng = np.random.default_rng(0)
    b, e = 3, 50
    index = rng.integers(0, 7, (b, e)).astype(np.int32)
    live = rng.random((b, e)) < 0.3
    rows = np.array([7, 1, 4], np.int32)[:, None]
    out = np.asarray(spread_dead(jnp.asarray(index), jnp.asarray(live), jnp.asarray(rows)))
    np.testing.assert_array_equal(out[live], index[live])
    for g in range(b):
        dead = out[g][~live[g]]
        assert ((0 <= dead) & (dead < rows[g, 0])).all()
        assert np.bincount(dead).max() <= -(-e // rows[g, 0])
    assert len(np.unique(out[0][~live[0]])) == 7  # all rows used when there are enough dead edges


@pytest.mark.parametrize("kind", ["hgt", "gcn"])
def test_padding_is_exactly_invariant(kind):
    """Same padded graph, different garbage in the dead rows: live outputs identical."""
    d, p1, p2, g, run = _reference(kind)
    ga, rows = _pad(g, 5, 21, np.random.default_rng(2), garbage=1.0)
    gb = dict(ga)
    dead = ~ga["mask"]
    gb["x"] = ga["x"].copy()
    gb["x"][dead] = 1e3 * np.random.default_rng(3).standard_normal((dead.sum(), ga["x"].shape[1]))
    gb["edge_type"] = np.where(ga["edge_mask"], ga["edge_type"], (ga["edge_type"] + 4) % 9)
    ha, hb = (np.asarray(_call(run, p1, p2, gg)[1]) for gg in (ga, gb))
    np.testing.assert_allclose(ha[rows], hb[rows], atol=1e-6, rtol=0)


@pytest.mark.parametrize("kind", ["hgt", "gcn"])
def test_permutation_equivariance(kind):
    d, p1, p2, g, run = _reference(kind)
    rng = np.random.default_rng(4)
    gp, _ = _pad(g, 4, 12, rng)
    n, e = len(gp["x"]), len(gp["senders"])
    pn, pe = rng.permutation(n), rng.permutation(e)
    inv = np.argsort(pn)  # new index of old node i
    gq = dict(
        x=gp["x"][pn],
        node_type=gp["node_type"][pn],
        mask=gp["mask"][pn],
        senders=inv[gp["senders"]][pe].astype(np.int32),
        receivers=inv[gp["receivers"]][pe].astype(np.int32),
        edge_type=gp["edge_type"][pe],
        edge_mask=gp["edge_mask"][pe],
    )
    ha = np.asarray(_call(run, p1, p2, gp)[1])
    hb = np.asarray(_call(run, p1, p2, gq)[1])
    np.testing.assert_allclose(hb, ha[pn], atol=TOL, rtol=0)


def test_hgt_isolated_live_node_and_empty_graph_are_finite():
    d, p1, p2, g, run = _reference("hgt")
    g0 = dict(g, edge_mask=np.zeros_like(g["edge_mask"]))
    h1, h2 = (np.asarray(h) for h in _call(run, p1, p2, g0))
    assert np.isfinite(h2).all()
    # No live in-edges -> zero aggregate -> gelu(0) = 0 -> out_lin gives its bias (layer 1 changes
    # the width, so no residual): the PyG result for isolated nodes.
    np.testing.assert_allclose(h1, p1["out_bias"][g["node_type"]], atol=1e-6)
    g_dead = dict(g, mask=np.zeros_like(g["mask"]))
    assert (np.asarray(_call(run, p1, p2, g_dead)[1]) == 0).all()


def test_hgt_attention_is_a_softmax_over_live_in_edges():
    d, p1, p2, g, run = _reference("hgt")
    gp, _ = _pad(g, 4, 12, np.random.default_rng(5))
    rel = edge_relations(gp["node_type"], gp["senders"], gp["receivers"], gp["edge_type"])
    _, state = _HGT.apply(
        {"params": p1},
        gp["x"],
        gp["node_type"],
        gp["mask"],
        gp["senders"],
        gp["receivers"],
        rel,
        gp["edge_mask"],
        mutable=["attention"],
    )
    (alpha,) = state["attention"]["alpha"]
    alpha = np.asarray(alpha)
    live = gp["edge_mask"] & gp["mask"][gp["senders"]] & gp["mask"][gp["receivers"]]
    assert (alpha[~live] == 0).all()
    sums = np.zeros((len(gp["x"]), alpha.shape[1]))
    np.add.at(sums, gp["receivers"], alpha)
    has_in = np.zeros(len(gp["x"]), bool)
    has_in[gp["receivers"][live]] = True
    np.testing.assert_allclose(sums[has_in], 1.0, atol=1e-6)
    assert (sums[~has_in] == 0).all()


def _type_layout(g, rng, padding_rows=3):
    """g with its rows sorted by node type (rooms, furniture, objects; dead rows stay in their
    type's range) and then `padding_rows` dead rows of NaN with edges from them marked live: the
    static layout of the navigation envs' node tables. Returns (graph, node_type_counts, new row
    of each old row)."""
    order = np.argsort(g["node_type"], kind="stable")
    inv = np.argsort(order)
    n, k = len(order), padding_rows
    pad_s = np.arange(n, n + k).repeat(2).astype(np.int32)
    layout = dict(
        x=np.concatenate([g["x"][order], np.full((k, g["x"].shape[1]), np.nan, np.float32)]),
        node_type=np.concatenate([g["node_type"][order], rng.integers(0, 3, k)]).astype(np.int32),
        mask=np.concatenate([g["mask"][order], np.zeros(k, bool)]),
        senders=np.concatenate([inv[g["senders"]], pad_s]).astype(np.int32),
        receivers=np.concatenate([inv[g["receivers"]], rng.integers(0, n, 2 * k)]).astype(np.int32),
        edge_type=np.concatenate([g["edge_type"], rng.integers(0, 9, 2 * k)]).astype(np.int32),
        edge_mask=np.concatenate([g["edge_mask"], np.ones(2 * k, bool)]),
    )
    return layout, tuple(int(c) for c in np.bincount(g["node_type"], minlength=3)), inv


def _hgt_apply(module, p, x, node_type, mask, senders, receivers, edge_type, edge_mask):
    rel = edge_relations(node_type, senders, receivers, edge_type)
    out, state = module.apply(
        {"params": p}, x, node_type, mask, senders, receivers, rel, edge_mask, mutable=["attention"]
    )
    return out, state["attention"]["alpha"][0]


_GRAPH_KEYS = ("x", "node_type", "mask", "senders", "receivers", "edge_type", "edge_mask")


@pytest.mark.parametrize("softmax", ["joint", "per_relation"])
def test_hgt_static_type_layout_matches_single_graphs_and_pyg(softmax):
    """A batch with a static type layout (HGTConv(node_type_counts=...): each type's rows one table)
    gives, graph by graph, the outputs and attention of single-graph calls in any node order (the
    other code path: every type and relation on every node) and the sum of their parameter
    gradients, on graphs with dead rows of garbage (NaN included) inside the type ranges, NaN
    padding rows after them, live edges from the padding and nodes masked out at random; one graph
    runs as a batch of one; with joint softmax, PyG's outputs."""
    d, p1, p2, g, run = _reference("hgt")
    rng = np.random.default_rng(12)
    padded, padded_rows = _pad(g, 4, 12, rng)
    base, counts, rows = _type_layout(padded, rng)
    graphs = [base]
    for drop, garbage in ((0.2, 1e3), (0.5, np.nan)):
        gg = dict(base, x=base["x"].copy(), mask=base["mask"] & (rng.random(len(base["mask"])) > drop))
        gg["x"][~gg["mask"]] = garbage
        graphs.append(gg)
    batch = {k: np.stack([gg[k] for gg in graphs]) for k in _GRAPH_KEYS}
    params = jax.tree.map(jnp.asarray, p1)
    fns = {}
    for name, m in (
        ("single", _HGT),
        ("tables", HGTConv(16, heads=2, softmax=softmax, node_type_counts=counts)),
    ):
        m = m.clone(softmax=softmax)
        apply = jax.default_matmul_precision("highest")(functools.partial(_hgt_apply, m))
        loss = lambda p, *a, apply=apply: jnp.sum(jnp.sin(apply(p, *a)[0]))  # noqa: E731
        fns[name] = (jax.jit(apply), jax.jit(jax.grad(loss)))
    args = lambda gg: tuple(gg[k] for k in _GRAPH_KEYS)  # noqa: E731
    out_t, alpha_t = fns["tables"][0](params, *args(batch))
    grad_t = fns["tables"][1](params, *args(batch))
    assert np.isfinite(np.asarray(out_t)).all() and np.abs(np.asarray(out_t)).max() > 0.1
    grad_sum = None
    for i, gg in enumerate(graphs):
        out_1, alpha_1 = fns["single"][0](params, *args(gg))
        np.testing.assert_allclose(out_t[i], out_1, atol=TOL, rtol=0)
        np.testing.assert_allclose(alpha_t[i], alpha_1, atol=1e-6, rtol=0)
        g1 = fns["single"][1](params, *args(gg))
        grad_sum = g1 if grad_sum is None else jax.tree.map(jnp.add, grad_sum, g1)
    for a, b in zip(jax.tree.leaves(grad_t), jax.tree.leaves(grad_sum)):
        assert np.isfinite(np.asarray(a)).all()
        np.testing.assert_allclose(a, b, atol=1e-4, rtol=1e-4)
    out_1, alpha_1 = fns["tables"][0](params, *args(graphs[1]))  # one graph: a batch of one
    np.testing.assert_allclose(out_1, out_t[1], atol=TOL, rtol=0)
    np.testing.assert_allclose(alpha_1, alpha_t[1], atol=1e-6, rtol=0)
    # Without a layout a batch runs the single-graph form under vmap: the same values.
    out_v, alpha_v = fns["single"][0](params, *args(batch))
    np.testing.assert_allclose(out_v, out_t, atol=TOL, rtol=0)
    np.testing.assert_allclose(alpha_v, alpha_t, atol=1e-6, rtol=0)
    if softmax == "joint":
        np.testing.assert_allclose(np.asarray(out_t)[0][rows[padded_rows]], d["out1"], atol=TOL, rtol=0)


def test_hgt_static_type_layout_drops_nodes_off_their_rows():
    """A live node whose node_type is not its row's type, or a live padding row, is dropped (as if
    masked out), and counts that do not fit the table are an error."""
    _, p1, _, g, _ = _reference("hgt")
    lay, counts, _ = _type_layout(g, np.random.default_rng(13))
    bad = dict(lay, node_type=lay["node_type"].copy(), mask=lay["mask"].copy())
    wrong = counts[0]  # the first furniture row
    bad["node_type"][wrong] = gt.OBJECT
    bad["mask"][sum(counts)] = True  # a padding row
    expected = dict(lay, mask=lay["mask"].copy())
    expected["mask"][wrong] = False
    params = jax.tree.map(jnp.asarray, p1)
    sliced = HGTConv(16, heads=2, node_type_counts=counts)
    out, _ = jax.jit(functools.partial(_hgt_apply, sliced))(params, *(bad[k] for k in _GRAPH_KEYS))
    single = jax.jit(functools.partial(_hgt_apply, _HGT))
    ref, _ = single(params, *(expected[k] for k in _GRAPH_KEYS))
    np.testing.assert_allclose(out, ref, atol=TOL, rtol=0)
    assert not np.asarray(out)[[wrong, sum(counts)]].any()
    for counts_bad in ((counts[0], counts[1]), (counts[0], counts[1], len(lay["x"]))):
        with pytest.raises(ValueError, match="node_type_counts"):
            bad_layout = functools.partial(_hgt_apply, HGTConv(16, heads=2, node_type_counts=counts_bad))
            jax.eval_shape(bad_layout, params, *(lay[k] for k in _GRAPH_KEYS))


def test_hgt_stack_on_type_tables_matches_the_node_table():
    """Two HGT layers on per-type row tables (split once, merged once: what the scene-graph encoder
    runs) give the outputs, attention and gradients (parameters and input) of the same layers on
    the [B, N, F] node table, with dead rows of garbage, NaN padding rows and nodes off their
    rows' type; tables without node_type_counts are an error."""
    _, p1, p2, g, _ = _reference("hgt")
    rng = np.random.default_rng(14)
    lay, counts, _ = _type_layout(g, rng)
    graphs = []
    for drop in (0.0, 0.4):
        gg = dict(lay, x=lay["x"].copy(), mask=lay["mask"] & (rng.random(len(lay["mask"])) >= drop))
        gg["x"][~gg["mask"]] = np.nan  # dead rows: garbage must reach no value or gradient
        gg["node_type"] = gg["node_type"].copy()
        gg["node_type"][counts[0]] = gt.OBJECT  # a live furniture row labelled object: dropped
        graphs.append(gg)
    batch = {k: np.stack([gg[k] for gg in graphs]) for k in _GRAPH_KEYS}
    layers = [HGTConv(16, heads=2, node_type_counts=counts), HGTConv(16, heads=2, node_type_counts=counts)]
    params = [jax.tree.map(jnp.asarray, p) for p in (p1, p2)]
    node_type, mask, senders, receivers, edge_type, edge_mask = (
        jnp.asarray(batch[k]) for k in _GRAPH_KEYS[1:]
    )
    rel = edge_relations(node_type, senders, receivers, edge_type)
    graph = (node_type, mask, senders, receivers, rel, edge_mask)

    @jax.default_matmul_precision("highest")
    def stack(params, x, tables):
        alphas = []
        if tables:
            x = split_types(x, layout_mask(node_type, mask, counts), counts)
        for layer, p in zip(layers, params):
            x, state = layer.apply({"params": p}, x, *graph, mutable=["attention"])
            x = jax.tree.map(jax.nn.relu, x)
            alphas.append(state["attention"]["alpha"][0])
        if tables:
            x = merge_types(x, counts, *mask.shape)
        return x, alphas

    loss = lambda p, x, tables: jnp.sum(jnp.sin(stack(p, x, tables)[0]))  # noqa: E731
    x = jnp.asarray(batch["x"])
    (out_t, alpha_t), (out_n, alpha_n) = (
        jax.jit(stack, static_argnums=2)(params, x, t) for t in (True, False)
    )
    assert np.isfinite(np.asarray(out_t)).all() and np.abs(np.asarray(out_t)).max() > 0.1
    np.testing.assert_allclose(out_t, out_n, atol=TOL, rtol=0)
    for a, b in zip(alpha_t, alpha_n):
        np.testing.assert_allclose(a, b, atol=1e-6, rtol=0)
    grads = [jax.jit(jax.grad(loss, argnums=(0, 1)), static_argnums=2)(params, x, t) for t in (True, False)]
    for a, b in zip(*(jax.tree.leaves(gr) for gr in grads)):
        assert np.isfinite(np.asarray(a)).all()
        np.testing.assert_allclose(a, b, atol=1e-4, rtol=1e-4)
    assert not np.asarray(grads[0][1])[:, counts[0]].any()  # the dropped row gets no gradient
    with pytest.raises(ValueError, match="per-type row tables"):
        HGTConv(16, heads=2).apply({"params": params[0]}, split_types(x, mask, counts), *graph)


def test_illegal_relation_triple_is_dropped():
    node_type = jnp.array([gt.ROOM, gt.OBJECT])
    rel = edge_relations(
        node_type, jnp.array([0, 1, 1]), jnp.array([1, 0, 0]), jnp.array([gt.ON_TOP, gt.IN_ROOM, gt.ON_TOP])
    )
    assert rel.tolist() == [-1, gt.RELATION_INDEX[gt.IN_ROOM, gt.OBJECT, gt.ROOM], -1]
    assert gt.check_graph_types(
        np.asarray(node_type), [0, 1], [1, 0], [gt.ON_TOP, gt.IN_ROOM], [True, True]
    ).tolist() == [0]


# --- HGT softmax variants: paper-era per-relation softmax (PyG <= 2.2) vs joint (PyG >= 2.3) ----
def _np_hgt_per_relation(p, x, node_type, node_mask, senders, receivers, relation, edge_mask, heads):
    """Paper-era HGTConv (PyG <= 2.2; ../shared/DESIGN.md) from its formula, loops in float64.

    Independent of hron_jax.models.gnn: per live target node i and relation triple r, softmax of
    <q_i, k_j W_att[r]> p_rel[r] / sqrt(D) over i's live incoming edges of relation r only, their
    values v_j W_msg[r] weighted by it, summed over r; then gelu, A_t and the gated skip. An edge
    counts if it is masked in, both endpoints are live and r is a legal triple whose source type
    is the sender's. `p` holds the flax parameters (kqv blocks in PyG's k | q | v order).
    Cross-checked once (not frozen: torch_scatter, which PyG 2.2 needs, did not build here) against
    torch_geometric 2.2.0's own HGTConv, with a torch.scatter_reduce stand-in for torch_scatter, on
    the 'pyg' and 'random' graphs below: max abs difference 4.4e-16 in float64.
    """
    p = {k: np.asarray(v, np.float64) for k, v in p.items()}
    x = np.asarray(x, np.float64)
    n, f_in = x.shape
    f = p["out_kernel"].shape[-1]
    d = f // heads
    src_type = [s for s, _, _ in gt.RELATION_TRIPLES]
    kqv = {}
    for i in range(n):
        if node_mask[i]:
            t = node_type[i]
            y = x[i] @ p["kqv_kernel"][t] + p["kqv_bias"][t]
            kqv[i] = [y[j * f : (j + 1) * f].reshape(heads, d) for j in range(3)]  # k, q, v
    out = np.zeros((n, f))
    for i in range(n):
        if not node_mask[i]:
            continue
        agg = np.zeros((heads, d))
        for r in range(gt.NUM_RELATIONS):
            srcs = [
                senders[e]
                for e in range(len(senders))
                if receivers[e] == i
                and relation[e] == r
                and edge_mask[e]
                and node_mask[senders[e]]
                and node_type[senders[e]] == src_type[r]
            ]
            for h in range(heads):
                if not srcs:
                    continue
                keys = np.stack([kqv[j][0][h] @ p["k_rel"][r, h] for j in srcs])
                vals = np.stack([kqv[j][2][h] @ p["v_rel"][r, h] for j in srcs])
                score = keys @ kqv[i][1][h] * p["p_rel"][r, h] / np.sqrt(d)
                w = np.exp(score - score.max())
                agg[h] += (w / w.sum()) @ vals
        a = agg.reshape(f)
        gelu = 0.5 * a * (1.0 + np.vectorize(math.erf)(a / np.sqrt(2.0)))
        t = node_type[i]
        o = gelu @ p["out_kernel"][t] + p["out_bias"][t]
        if f_in == f:
            gate = 1.0 / (1.0 + np.exp(-p["skip"][t]))
            o = gate * o + (1.0 - gate) * x[i]
        out[i] = o
    return out


def _np_two_layers(p1, p2, g):
    """`_np_hgt_per_relation` twice, relu between (as `_hgt_two_layers_rel`), on a graph dict."""
    args = (g["node_type"], g["mask"], g["senders"], g["receivers"], g["rel"], g["edge_mask"], 2)
    ref1 = _np_hgt_per_relation(p1, g["x"], *args)
    return ref1, _np_hgt_per_relation(p2, np.maximum(ref1, 0.0), *args)


def _np_relations(g):
    """Relation triple of every edge straight from graph_types' table (-1 = illegal)."""
    return gt.RELATION_INDEX[g["edge_type"], g["node_type"][g["senders"]], g["node_type"][g["receivers"]]]


@functools.partial(jax.jit, static_argnames="softmax")
@jax.default_matmul_precision("highest")
def _hgt_two_layers_rel(p1, p2, x, node_type, mask, senders, receivers, rel, edge_mask, softmax):
    """Two stacked HGTConv (16 wide, 2 heads) with the given softmax; one graph or a batch."""
    layer = HGTConv(16, heads=2, softmax=softmax)
    args = (node_type, mask, senders, receivers, rel, edge_mask)
    h1, s1 = layer.apply({"params": p1}, x, *args, mutable=["attention"])
    h2 = layer.apply({"params": p2}, jax.nn.relu(h1), *args)
    return h1, h2, s1["attention"]["alpha"][0]


def _call_rel(p1, p2, g, softmax):
    keys = ("x", "node_type", "mask", "senders", "receivers", "rel", "edge_mask")
    return tuple(np.asarray(a) for a in _hgt_two_layers_rel(p1, p2, *(g[k] for k in keys), softmax=softmax))


def _random_hetero_graph(seed):
    """A small graph with random legal typed edges (several relations into most nodes, duplicates,
    one live node without in-edges) and random HGT weights 16 -> 16 (gated residual in both
    layers), attention sharpened and p_rel / skip randomised like the PyG reference."""
    rng = np.random.default_rng(seed)
    node_type = rng.permutation(np.repeat(np.arange(3), [3, 4, 6])).astype(np.int32)
    n = len(node_type)
    isolated = n - 1  # gets no in-edge
    senders, receivers, edge_type = [], [], []
    while len(senders) < 45:
        s, r = rng.integers(0, n, 2)
        ok = np.nonzero(gt.RELATION_INDEX[:, node_type[s], node_type[r]] >= 0)[0]
        if r != isolated and len(ok):
            senders.append(s), receivers.append(r), edge_type.append(rng.choice(ok))
    g = dict(
        x=rng.standard_normal((n, 16)).astype(np.float32),
        node_type=node_type,
        mask=np.ones(n, bool),
        senders=np.array(senders, np.int32),
        receivers=np.array(receivers, np.int32),
        edge_type=np.array(edge_type, np.int32),
        edge_mask=np.ones(len(senders), bool),
    )
    layer = HGTConv(16, heads=2)
    args = (g["node_type"], g["mask"], g["senders"], g["receivers"], _np_relations(g), g["edge_mask"])
    params = []
    for k in jax.random.split(jax.random.key(seed), 2):
        p = jax.tree.map(np.asarray, layer.init(k, g["x"], *args)["params"])
        p["kqv_kernel"] = 3.0 * p["kqv_kernel"]
        p["p_rel"] = rng.uniform(0.5, 1.5, p["p_rel"].shape).astype(np.float32)
        p["skip"] = rng.standard_normal(p["skip"].shape).astype(np.float32)
        params.append(p)
    return params[0], params[1], g


def _per_relation_case(name):
    """(p1, p2, padded graph with 'rel', rows of the original nodes) for 'pyg' (the frozen PyG
    graph and weights, 12 -> 16 -> 16) or 'random' (`_random_hetero_graph`), padded by `_pad` with
    NaN in the dead rows."""
    if name == "pyg":
        _, p1, p2, g, _ = _reference("hgt")
    else:
        p1, p2, g = _random_hetero_graph(11)
    gp, rows = _pad(g, 6, 24, np.random.default_rng(12), garbage=np.nan)
    gp["rel"] = _np_relations(gp).astype(np.int32)
    return p1, p2, gp, rows


def _live_relations_per_receiver(g):
    live = g["edge_mask"] & g["mask"][g["senders"]] & g["mask"][g["receivers"]] & (g["rel"] >= 0)
    kinds = [set() for _ in g["x"]]
    for r, rel in zip(g["receivers"][live], g["rel"][live]):
        kinds[r].add(int(rel))
    return live, kinds


@pytest.mark.parametrize("batched", [False, True], ids=["single", "batch"])
@pytest.mark.parametrize("case", ["pyg", "random"])
def test_hgt_per_relation_matches_numpy_reference(case, batched):
    """softmax='per_relation' equals the paper-era formula (`_np_hgt_per_relation`, float64) on a
    padded heterogeneous graph: several relations into one node, nodes lacking some relations,
    a live node without in-edges, masked / padded / dead-endpoint edges and NaN in dead rows.
    Tolerance 1e-5 absolute: the layer runs in float32 (highest matmul precision) against a float64
    reference; outputs are O(1), so float32 rounding through two layers stays near 1e-6."""
    p1, p2, g, rows = _per_relation_case(case)
    live, kinds = _live_relations_per_receiver(g)
    assert max(len(k) for k in kinds) >= 2  # some receiver gets several relation types
    assert any(m and not k for m, k in zip(g["mask"], kinds))  # a live node without in-edges
    assert (~g["edge_mask"]).any() and (g["edge_mask"] & ~live).any()
    ref1, ref2 = _np_two_layers(p1, p2, g)
    if batched:  # the same graph twice, as a batch [2, ...] (the disjoint-union fast path)
        gb = {k: np.stack([v, v]) for k, v in g.items()}
        outs = _call_rel(p1, p2, gb, "per_relation")
        np.testing.assert_array_equal(outs[1][0], outs[1][1])
        h1, h2, _ = (o[0] for o in outs)
    else:
        h1, h2, _ = _call_rel(p1, p2, g, "per_relation")
    err1, err2 = np.abs(h1 - ref1).max(), np.abs(h2 - ref2).max()
    print(
        f"per_relation vs numpy reference ({case}, {'batch' if batched else 'single'}): "
        f"layer1 max err {err1:.2e}, layer2 max err {err2:.2e}"
    )
    assert np.isfinite(h2).all()
    assert err1 < TOL and err2 < TOL
    assert (h2[~g["mask"]] == 0).all()
    assert np.abs(ref2).max() > 0.1  # not trivially small


@pytest.mark.parametrize("case", ["pyg", "random"])
def test_hgt_joint_differs_from_per_relation(case):
    """Negative control: on graphs where nodes receive 2+ relation types the joint softmax does
    not reproduce the per-relation reference (and the per-relation layer does not reproduce the
    frozen PyG 2.8 joint output)."""
    p1, p2, g, rows = _per_relation_case(case)
    ref1, _ = _np_two_layers(p1, p2, g)
    j1, j2, _ = _call_rel(p1, p2, g, "joint")
    diff = np.abs(j1 - ref1).max()
    print(f"joint vs per_relation reference ({case}): layer1 max diff {diff:.2e}")
    assert diff > 1e-2
    if case == "pyg":
        d = _load("hgt_reference.npz")
        pr1, _, _ = _call_rel(p1, p2, g, "per_relation")
        np.testing.assert_allclose(j1[rows], d["out1"], atol=TOL, rtol=0)  # joint is PyG 2.8's form
        assert np.abs(pr1[rows] - d["out1"]).max() > 1e-2


def test_hgt_per_relation_equals_joint_with_one_relation_per_receiver():
    """Sanity: when every node receives edges of at most one relation triple, both softmaxes
    normalise over the same sets, so outputs and attention agree."""
    p1, p2, g, _ = _per_relation_case("pyg")
    live, _ = _live_relations_per_receiver(g)
    first = {}
    for e in np.nonzero(live)[0]:
        first.setdefault(int(g["receivers"][e]), int(g["rel"][e]))
    keep = np.array([not live[e] or first[int(g["receivers"][e])] == g["rel"][e] for e in range(len(live))])
    g1 = {
        k: (v[keep] if k in ("senders", "receivers", "edge_type", "edge_mask", "rel") else v)
        for k, v in g.items()
    }
    _, kinds = _live_relations_per_receiver(g1)
    assert max(len(k) for k in kinds) == 1 and sum(map(len, kinds)) >= 10
    a = _call_rel(p1, p2, g1, "joint")
    b = _call_rel(p1, p2, g1, "per_relation")
    for x, y in zip(a, b):
        np.testing.assert_allclose(x, y, atol=1e-6, rtol=0)


def test_hgt_per_relation_attention_is_one_unit_per_relation():
    """Under per_relation each receiver hands out one unit of attention per incoming relation
    triple (not one in total): alpha sums to 1 over each (receiver, relation) group with a live
    edge, per head; dead edges get 0; the shape is [E, H] as for joint."""
    p1, p2, g, _ = _per_relation_case("pyg")
    live, kinds = _live_relations_per_receiver(g)
    _, _, alpha = _call_rel(p1, p2, g, "per_relation")
    assert alpha.shape == (len(g["senders"]), 2)
    assert (alpha[~live] == 0).all()
    sums = {}
    for e in np.nonzero(live)[0]:
        key = (int(g["receivers"][e]), int(g["rel"][e]))
        sums[key] = sums.get(key, 0.0) + alpha[e]
    np.testing.assert_allclose(np.stack(list(sums.values())), 1.0, atol=1e-6)
    per_node = np.zeros((len(g["x"]), 2))
    np.add.at(per_node, g["receivers"][live], alpha[live])
    np.testing.assert_allclose(per_node[:, 0], [len(k) for k in kinds], atol=1e-5)


@pytest.mark.parametrize("batched", [False, True], ids=["single", "batch"])
def test_hgt_per_relation_gradients_are_finite(batched):
    """Gradients w.r.t. parameters and inputs are finite with per_relation: empty (receiver,
    relation) groups, dead edges and NaN in dead rows leak nothing."""
    p1, p2, g, _ = _per_relation_case("random")
    if batched:
        g = {k: np.stack([v, v]) for k, v in g.items()}
    g = dict(g, x=np.where(g["mask"][..., None], g["x"], 0.0))  # the dead rows of x still get a gradient

    def loss(p1, p2, x):
        h1, h2, _ = _hgt_two_layers_rel(
            p1,
            p2,
            x,
            g["node_type"],
            g["mask"],
            g["senders"],
            g["receivers"],
            g["rel"],
            g["edge_mask"],
            "per_relation",
        )
        return jnp.sum(jnp.sin(h2))

    grads = jax.jit(jax.grad(loss, argnums=(0, 1, 2)))(p1, p2, g["x"])
    leaves = [np.asarray(a) for a in jax.tree.leaves(grads)]
    assert all(np.isfinite(a).all() for a in leaves)
    assert np.abs(grads[0]["k_rel"]).max() > 0 and np.abs(grads[1]["p_rel"]).max() > 0


def test_hgt_softmax_option_is_validated():
    assert ModelConfig().hgt_softmax == "joint"
    assert ModelConfig(hgt_softmax="per_relation").hgt_softmax == "per_relation"
    with pytest.raises(ConfigError) as err:
        ModelConfig(hgt_softmax="per_edge")
    assert err.value.field == "hgt_softmax"
    x = np.zeros((2, 16), np.float32)
    args = (np.zeros(2, np.int32), np.ones(2, bool), np.zeros(1, np.int32), np.ones(1, np.int32))
    with pytest.raises(ValueError, match="softmax"):
        HGTConv(16, softmax="per_edge").init(
            jax.random.key(0), x, *args, np.zeros(1, np.int32), np.ones(1, bool)
        )


def test_hgt_softmax_reaches_the_model():
    # House graphs: a room receives inRoom from furniture and roomConnected from rooms, so the two
    # softmaxes give different outputs from the same parameters once the option reaches HGTConv.
    from hron_jax.bench.model import model_inputs

    obs, _ = model_inputs(batch=2, image=8)
    cfg = ModelConfig(hidden=16, heads=1, gnn_layers=1, cnn_fc=(16, 16, 16), goal_fc=(16, 16, 16))
    joint = make_model("rgbd_sg_attn", 5, cfg)
    per = make_model("rgbd_sg_attn", 5, dataclasses.replace(cfg, hgt_softmax="per_relation"))
    params = jax.jit(joint.init)(jax.random.key(0), obs)
    (lj, vj), (lp, vp) = jax.jit(joint.apply)(params, obs), jax.jit(per.apply)(params, obs)
    assert float(jnp.abs(lj - lp).max() + jnp.abs(vj - vp).max()) > 1e-6


# --- pooling ---------------------------------------------------------------------------------
def test_task_driven_pool_mask_is_exact():
    rng = np.random.default_rng(6)
    n, f = 40, 8
    h = rng.standard_normal((n, f)).astype(np.float32)
    category = rng.integers(0, 12, n).astype(np.int32)
    mask = rng.random(n) < 0.6
    goal = np.array([3, 7, -1], np.int32)
    category[~mask & (np.arange(n) % 2 == 0)] = 3  # dead nodes of a goal class must not count
    pooled, w, sel = task_driven_pool(jnp.asarray(h), jnp.asarray(category), jnp.asarray(mask), goal)
    expect_w = (np.isin(category, [3, 7]) & mask).astype(np.float32)
    np.testing.assert_array_equal(np.asarray(w), expect_w)
    assert bool(sel) and expect_w.sum() > 0
    np.testing.assert_allclose(np.asarray(pooled), h[expect_w > 0].mean(0), atol=1e-6)
    # -1 (absent goal part) never matches, even for a node whose category is -1.
    category2 = category.copy()
    category2[0], mask2 = -1, mask.copy()
    mask2[0] = True
    _, w2, _ = task_driven_pool(h, category2, mask2, np.array([-1, -1, -1], np.int32))
    assert (np.asarray(w2) == 0).all()
    # No match: zeros and selected False (no NaN), also with NaN garbage on unselected rows.
    h_nan = h.copy()
    h_nan[~mask] = np.nan
    p0, w0, s0 = task_driven_pool(h_nan, category, mask, np.array([99, -1, -1], np.int32))
    assert not bool(s0) and (np.asarray(p0) == 0).all() and (np.asarray(w0) == 0).all()
    pm, wm, sm = mean_pool(h_nan, mask)
    np.testing.assert_allclose(np.asarray(pm), h[mask].mean(0), atol=1e-6)
    np.testing.assert_array_equal(np.asarray(wm), mask.astype(np.float32))
    pe, _, se = mean_pool(h, np.zeros(n, bool))
    assert not bool(se) and (np.asarray(pe) == 0).all()


# --- full models -----------------------------------------------------------------------------
N_NODES, N_EDGES, IMG, MAP, ACTIONS = 20, 40, 16, 12, 5
SMALL = ModelConfig(
    hidden=32,
    heads=2,
    conv_features=(8, 8, 8),
    conv_kernels=(4, 3, 3),
    conv_strides=(2, 2, 1),
    cnn_fc=(32, 32, 32),
    goal_fc=(32, 32, 32),
    fusion_fc=(32, 32, 32),
    head_fc=(32, 32),
    gnn_layers=2,
)
GOAL_DIM = (
    len(vocabulary.OBJECTS) + len(vocabulary.RELATIONS) + len(vocabulary.FURNITURE) + len(vocabulary.ROOMS)
)


def _obs(seed, with_image=True):
    """A random observation following the contract (legal edge triples, padded tails)."""
    r = np.random.default_rng(seed)
    n_live = 14
    node_type = r.integers(0, 3, N_NODES).astype(np.int32)
    category = r.integers(2, vocabulary.NUM_CLASSES, N_NODES).astype(np.int32)
    mask = np.arange(N_NODES) < n_live
    category[~mask], node_type[~mask] = 0, 0
    triples = np.array(gt.RELATION_TRIPLES)
    senders, receivers, etype = [], [], []
    while len(senders) < 30:
        s, d = r.integers(0, n_live, 2)
        ok = (triples[:, 0] == node_type[s]) & (triples[:, 2] == node_type[d])
        if ok.any() and s != d:
            senders.append(s), receivers.append(d), etype.append(r.choice(triples[ok, 1]))
    pad = N_EDGES - len(senders)
    edges = dict(
        edge_type=np.array(etype + [0] * pad, np.int32), mask=np.array([True] * len(etype) + [False] * pad)
    )
    nodes = dict(
        category=category,
        node_type=node_type,
        pos=(r.standard_normal((N_NODES, 3)) * mask[:, None]).astype(np.float32),
        size=(r.random((N_NODES, 3)) * mask[:, None]).astype(np.float32),
        mask=mask,
    )
    graph = jraph.GraphsTuple(
        nodes=nodes,
        edges=edges,
        senders=np.array(senders + [0] * pad, np.int32),
        receivers=np.array(receivers + [0] * pad, np.int32),
        n_node=np.array([N_NODES], np.int32),
        n_edge=np.array([N_EDGES], np.int32),
        globals=None,
    )
    goal = np.zeros(GOAL_DIM, np.float32)
    goal[r.choice(GOAL_DIM, 3, replace=False)] = 1
    obs = dict(
        graph=graph,
        goal=goal,
        goal_classes=np.array([category[0], category[1], -1], np.int32),
        map=r.random((MAP, MAP, 3)).astype(np.float32),
    )
    if with_image:
        obs["rgbd"] = r.random((IMG, IMG, 4)).astype(np.float32)
    return obs


def _stack(obs_list):
    return jax.tree.map(lambda *a: np.stack(a), *obs_list)


def _random_variables(model, obs, seed=0):
    """Variables with the model's structure, filled with scaled normals.

    Avoids compiling flax init (orthogonal init = one QR per weight shape, ~10 s of XLA compile on
    a 2-core CPU for the default sizes); init itself is exercised in test_real_init.
    """
    shapes = jax.eval_shape(model.init, jax.random.PRNGKey(0), obs)
    r = np.random.default_rng(seed)

    def fill(s):
        scale = 1.0 / np.sqrt(np.prod(s.shape[:-1]) if len(s.shape) >= 2 else 10.0)
        return jnp.asarray(r.standard_normal(s.shape) * scale, s.dtype)

    return jax.tree.map(fill, shapes)


def test_make_model_unknown_name_lists_valid_names():
    with pytest.raises(ValueError) as e:
        make_model("resnet", ACTIONS)
    for name in VARIANTS:
        assert name in str(e.value)


@pytest.mark.parametrize("name", list(VARIANTS))
def test_variant_jit_vmap_and_gradients(name):
    model = make_model(name, ACTIONS, SMALL)
    singles = [_obs(s) for s in range(3)]
    batch = _stack(singles)
    variables = _random_variables(model, singles[0])
    assert set(variables) == {"params"}  # nothing sown at init

    @jax.jit
    def run(v, one, b):
        l1, v1 = model.apply(v, one)
        lb, vb = model.apply(v, b)  # batch via the model's own nn.vmap
        if name == "rgbd_sg_attn":  # batch via external vmap (one variant: it is a compile)
            lv, vv = jax.vmap(model.apply, in_axes=(None, 0))(v, b)
        else:
            lv, vv = lb, vb

        def loss(p):
            lg, val = model.apply(p, b)
            return jnp.sum(jax.nn.log_softmax(lg)[:, 0]) + jnp.sum(val**2)

        return l1, v1, lb, vb, lv, vv, jax.grad(loss)(v)

    l1, v1, lb, vb, lv, vv, grads = run(variables, singles[0], batch)
    assert l1.shape == (ACTIONS,) and v1.shape == ()
    assert lb.shape == (3, ACTIONS) and vb.shape == (3,)
    np.testing.assert_allclose(lb[0], l1, atol=1e-5)
    np.testing.assert_allclose(lb, lv, atol=1e-5)
    np.testing.assert_allclose(vb, vv, atol=1e-5)
    leaves = jax.tree.leaves(grads)
    assert all(np.isfinite(np.asarray(x)).all() for x in leaves)
    p = variables["params"]["core"]
    expect = {
        "goal_encoder",
        "fusion",
        "policy_hidden",
        "policy_out",
        "value_hidden",
        "value_out",
        "rgbd_encoder",
    }
    expect |= {"map_encoder"} if VARIANTS[name].get("use_map") else set()
    expect |= {"graph_encoder"} if VARIANTS[name].get("use_graph") else set()
    assert set(p) == expect
    if "graph_encoder" in p:
        ge = grads["params"]["core"]["graph_encoder"]
        layer = "hgt_1" if VARIANTS[name]["gnn"] == "hgt" else "gcn_1"
        assert any(np.abs(np.asarray(x)).max() > 0 for x in jax.tree.leaves(ge[layer]))


def test_main_model_default_sizes_and_attention_readout():
    model = make_model("rgbd_sg_attn", ACTIONS)
    assert model.config.hidden == 128 and model.config.heads == 2 and model.config.gnn_layers == 3
    obs = _stack([_obs(10), _obs(11)])
    variables = _random_variables(model, jax.tree.map(lambda a: a[0], obs))
    logits, value, att = jax.jit(lambda v, o: attention_readout(model, v, o))(variables, obs)
    assert logits.shape == (2, ACTIONS) and value.shape == (2,)
    ge = att["core"]["graph_encoder"]
    for i in range(3):
        (alpha,) = ge[f"hgt_{i}"]["alpha"]
        assert alpha.shape == (2, N_EDGES, 2)
        assert (np.asarray(alpha)[~np.asarray(obs["graph"].edges["mask"])] == 0).all()
    (w,) = ge["pool_weights"]
    nodes = obs["graph"].nodes
    expect = np.stack(
        [
            np.isin(nodes["category"][b], obs["goal_classes"][b][obs["goal_classes"][b] >= 0])
            & nodes["mask"][b]
            for b in range(2)
        ]
    ).astype(np.float32)
    np.testing.assert_array_equal(np.asarray(w), expect)
    # The plain apply (training path) returns the same numbers and no extra state; extra leading
    # axes ([T, B] rollouts) are flattened and restored.
    obs_tb = jax.tree.map(lambda a: a[None], obs)
    l2, v2 = jax.jit(model.apply)(variables, obs_tb)
    assert l2.shape == (1, 2, ACTIONS) and v2.shape == (1, 2)
    np.testing.assert_allclose(l2[0], logits, atol=1e-5)
    np.testing.assert_allclose(v2[0], value, atol=1e-5)


def test_real_init():
    # Small graph-only model: init compile time grows with the number of weight shapes.
    model = make_model("rgbd_sg_attn", ACTIONS, dataclasses.replace(SMALL, use_rgbd=False, gnn_layers=1))
    obs = _obs(50, with_image=False)
    variables = jax.jit(model.init)(jax.random.PRNGKey(0), obs)
    assert set(variables) == {"params"}  # nothing sown at init: valid for single and batch
    assert all(np.isfinite(np.asarray(x)).all() for x in jax.tree.leaves(variables))
    hgt = variables["params"]["core"]["graph_encoder"]["hgt_0"]
    assert (np.asarray(hgt["p_rel"]) == 1).all() and (np.asarray(hgt["skip"]) == 1).all()
    logits, value = jax.jit(model.apply)(variables, _stack([obs, obs]))
    assert logits.shape == (2, ACTIONS) and np.isfinite(np.asarray(logits)).all()


def test_graph_only_model_without_rgbd():
    """Symbolic choice task: obs is scene graph + goal only."""
    model = make_model("rgbd_sg_attn", 2, dataclasses.replace(SMALL, use_rgbd=False))
    direct = ActorCritic(num_actions=2, num_classes=vocabulary.NUM_CLASSES, config=model.config)
    assert direct == model
    obs = _obs(20, with_image=False)
    variables = _random_variables(model, obs)
    logits, value = jax.jit(model.apply)(variables, obs)
    assert logits.shape == (2,) and np.isfinite(np.asarray(logits)).all()
    assert "rgbd_encoder" not in variables["params"]["core"]
    with pytest.raises(KeyError, match="use_rgbd=False"):
        jax.eval_shape(make_model("rgbd_sg_attn", 2, SMALL).init, jax.random.PRNGKey(0), obs)


def test_rgb_and_depth_are_accepted_instead_of_rgbd():
    model = make_model("rgbd", ACTIONS, SMALL)
    obs = _obs(21)
    split = dict(obs, rgb=obs["rgbd"][..., :3], depth=obs["rgbd"][..., 3:])
    del split["rgbd"]
    variables = _random_variables(model, obs)
    apply = jax.jit(model.apply)
    np.testing.assert_allclose(apply(variables, split)[0], apply(variables, obs)[0])


def test_dead_nodes_do_not_change_model_output():
    """Full main model: rewriting everything about dead nodes/edges leaves the output unchanged."""
    model = make_model("rgbd_sg_attn", ACTIONS, SMALL)
    obs = _obs(30)
    variables = _random_variables(model, obs)
    g = obs["graph"]
    dead, dead_e = ~g.nodes["mask"], ~g.edges["mask"]
    r = np.random.default_rng(0)
    nodes = {k: v.copy() for k, v in g.nodes.items()}
    nodes["category"][dead] = obs["goal_classes"][0]  # would be selected if the mask leaked
    nodes["node_type"][dead] = r.integers(0, 3, dead.sum())
    nodes["pos"][dead] = np.nan
    nodes["size"][dead] = 1e6
    edges = dict(g.edges, edge_type=np.where(dead_e, 0, g.edges["edge_type"]).astype(np.int32))
    senders = np.where(dead_e, r.integers(0, N_NODES, N_EDGES), g.senders).astype(np.int32)
    g2 = g._replace(nodes=nodes, edges=edges, senders=senders)
    apply = jax.jit(model.apply)
    a = apply(variables, obs)
    b = apply(variables, dict(obs, graph=g2))
    np.testing.assert_allclose(b[0], a[0], atol=1e-6)
    np.testing.assert_allclose(b[1], a[1], atol=1e-6)


def test_category_vectors_match_vocabulary():
    vec = load_category_vectors(vocabulary.NUM_CLASSES)
    assert vec.shape[0] == vocabulary.NUM_CLASSES and np.isfinite(vec).all()
    assert (vec[0] == 0).all()
    norms = np.linalg.norm(vec[2:], axis=1)
    np.testing.assert_allclose(norms, 1.0, atol=1e-4)
    # Different categories get different vectors.
    assert np.unique(np.round(vec[2:], 4), axis=0).shape[0] == vec.shape[0] - 2


def test_choice_env_observation_is_accepted():
    """Integration with the symbolic choice task (graph + goal, rgb/depth given apart)."""
    choice = pytest.importorskip("hron_jax.envs.choice")
    env = choice.ChoiceEnv(choice.ChoiceConfig(distractors=True, max_distractors=8, image_obs=True))
    obs = env.observation_example()
    model = make_model("rgbd_sg_attn", 2, SMALL)  # its rgb + depth feed the RGB-D branch
    variables = _random_variables(model, obs)
    logits, _ = jax.jit(model.apply)(variables, obs)
    assert logits.shape == (2,) and np.isfinite(np.asarray(logits)).all()


@pytest.mark.parametrize("impl", ["patches", "xla", "auto"])
@pytest.mark.parametrize(
    "size,kernel,stride", [((32, 32), 8, 4), ((8, 8), 4, 2), ((4, 4), 3, 1), ((7, 10), 5, 3), ((9, 9), 2, 2)]
)
def test_patch_conv_equals_xla_convolution(size, kernel, stride, impl):
    """PatchConv (slices + matmul, fast gradients inside lax.scan on XLA:CPU, or XLA's own
    convolution) is nn.Conv: same parameter shapes and init, same SAME-padded outputs and
    gradients as lax's convolution."""
    from hron_jax.models.encoders import RELU_INIT, PatchConv

    x = jax.random.normal(jax.random.PRNGKey(0), (3,) + size + (5,))
    ours = PatchConv(6, kernel, stride, impl=impl)
    ref = nn.Conv(6, (kernel, kernel), (stride, stride), padding="SAME", kernel_init=RELU_INIT)
    p_ours, p_ref = ours.init(jax.random.PRNGKey(1), x), ref.init(jax.random.PRNGKey(1), x)
    jax.tree.map(np.testing.assert_array_equal, p_ours, p_ref)
    params = jax.tree.map(lambda a: a + 0.1 * jax.random.normal(jax.random.PRNGKey(2), a.shape), p_ref)
    np.testing.assert_allclose(ours.apply(params, x), ref.apply(params, x), atol=1e-5)
    loss = lambda m: lambda p, x: jnp.sum(jnp.sin(m.apply(p, x)))  # noqa: E731
    g_ours = jax.grad(loss(ours), argnums=(0, 1))(params, x)
    g_ref = jax.grad(loss(ref), argnums=(0, 1))(params, x)
    jax.tree.map(lambda a, b: np.testing.assert_allclose(a, b, atol=1e-4), g_ours, g_ref)


@pytest.mark.parametrize(
    "size,kernel,stride",
    [((88, 88), 8, 4), ((11, 14), 4, 2), ((9, 9), 6, 3), ((7, 10), 5, 3), ((5, 6), 3, 1)],
)
def test_image_patches_are_the_same_padded_windows_as_a_loop(size, kernel, stride):
    # Bitwise, on both of image_patches' paths (space to depth where the stride divides the kernel,
    # strided slices otherwise), against windows cut one by one from a numpy copy padded as TF SAME.
    from hron_jax.models.encoders import image_patches

    x = np.asarray(jax.random.normal(jax.random.PRNGKey(0), (2,) + size + (3,)))
    ho, wo = -(-size[0] // stride), -(-size[1] // stride)
    ph = max((ho - 1) * stride + kernel - size[0], 0)
    pw = max((wo - 1) * stride + kernel - size[1], 0)
    xp = np.pad(x, ((0, 0), (ph // 2, ph - ph // 2), (pw // 2, pw - pw // 2), (0, 0)))
    want = np.stack(
        [
            np.stack(
                [
                    xp[:, r * stride : r * stride + kernel, q * stride : q * stride + kernel]
                    for q in range(wo)
                ],
                1,
            )
            for r in range(ho)
        ],
        1,
    ).reshape(2, ho, wo, -1)
    np.testing.assert_array_equal(image_patches(jnp.asarray(x), kernel, stride), want)


@pytest.mark.parametrize("side", [32, 33])
def test_conv_auto_is_patches_on_cpu_and_xla_convolution_on_gpu_above_32x32(side):
    # ModelConfig.conv='auto': the gradient program lowered for the CPU has no convolution op
    # (patches + matmul); lowered for a GPU it has convolutions and no patch concatenation, unless
    # the input has at most 32 x 32 pixels (patches there too).
    from hron_jax.models.encoders import AUTO_PATCHES_MAX_PIXELS, PatchConv

    assert AUTO_PATCHES_MAX_PIXELS == 32 * 32
    x = jnp.ones((2, side, side, 4))
    conv = PatchConv(8, 4, 2)
    params = conv.init(jax.random.PRNGKey(0), x)
    traced = jax.jit(jax.grad(lambda p: jnp.sum(conv.apply(p, x) ** 2))).trace(params)
    cpu, gpu = traced.lower().as_text(), traced.lower(lowering_platforms=("cuda",)).as_text()
    assert "convolution" not in cpu and "concatenate" in cpu
    if side <= 32:
        assert "convolution" not in gpu and "concatenate" in gpu
    else:
        assert "convolution" in gpu and "concatenate" not in gpu


def test_take_rows_is_a_gather_with_a_matmul_gradient_on_gpu():
    # hron_jax.models.lookup: same forward (bitwise) and gradient as table[idx]; lowered for a GPU
    # its backward has no scatter (the one-hot matmul that replaces XLA:GPU's atomic scatter-add),
    # on the CPU it keeps the gather's own scatter-add.
    from hron_jax.models.lookup import Embed, _matmul_grad, take_rows

    rng = np.random.default_rng(0)
    table = jnp.asarray(rng.normal(size=(11, 2, 3)), jnp.float32)
    idx = jnp.asarray(rng.integers(0, 11, size=(5, 40)), jnp.int32)
    cot = jnp.asarray(rng.normal(size=(5, 40, 2, 3)), jnp.float32)
    assert (take_rows(table, idx) == table[idx]).all()
    loss = lambda f: lambda t: jnp.sum(f(t) * cot)  # noqa: E731
    grad = jax.jit(jax.grad(loss(lambda t: take_rows(t, idx))))
    g_ref = jax.grad(loss(lambda t: t[idx]))(table)
    assert np.abs(g_ref).min() > 0  # every row was hit, so the comparisons cover all of them
    np.testing.assert_array_equal(grad(table), g_ref)  # CPU: the same scatter-add
    np.testing.assert_allclose(_matmul_grad(11, idx, cot), g_ref, rtol=1e-5, atol=1e-5)
    traced = grad.trace(table)
    cpu, gpu = traced.lower().as_text(), traced.lower(lowering_platforms=("cuda",)).as_text()
    assert "scatter" in cpu and "dot_general" not in cpu
    assert "scatter" not in gpu and "dot_general" in gpu
    # Embed keeps nn.Embed's parameters and outputs
    ids = idx[:2] % 7
    ref = nn.Embed(7, 4)
    params = ref.init(jax.random.PRNGKey(0), ids)
    assert jax.tree.structure(Embed(7, 4).init(jax.random.PRNGKey(0), ids)) == jax.tree.structure(params)
    assert (Embed(7, 4).apply(params, ids) == ref.apply(params, ids)).all()


def test_gather_f32_sums_a_bfloat16_gradient_in_float32():
    # lookup.gather_f32: bfloat16 rows read as float32; the gradient is the float64 sum of the
    # cotangents rounded once to bfloat16 (a bfloat16 scatter-add rounds after every add: with
    # 4000 cotangents on one row it drifts far from the sum); a float32 table is a plain gather.
    from hron_jax.models.lookup import gather_f32

    rng = np.random.default_rng(0)
    table = jnp.asarray(rng.normal(size=(3, 2)), jnp.bfloat16)
    idx = jnp.asarray(np.r_[np.zeros(4000, int), rng.integers(0, 3, size=50)], jnp.int32)
    cot = rng.uniform(0.5, 1.5, size=(idx.shape[0], 2)).astype(np.float32)
    (out,) = gather_f32(table, idx)
    assert out.dtype == jnp.float32 and (out == table[idx].astype(jnp.float32)).all()
    # two gathers (as the HGT's keys and values from one table) share one float32 sum
    half = idx.shape[0] // 2

    def loss(t):
        first, second = gather_f32(t, idx[:half], idx[half:])
        return jnp.sum(first * cot[:half]) + jnp.sum(second * cot[half:])

    grad = jax.jit(jax.grad(loss))(table)
    want = np.zeros((3, 2))
    np.add.at(want, np.asarray(idx), cot.astype(np.float64))
    assert grad.dtype == jnp.bfloat16
    np.testing.assert_allclose(np.asarray(grad, np.float64), want, rtol=2.0**-8)
    plain = jax.jit(jax.grad(lambda t: jnp.sum(t[idx].astype(jnp.float32) * cot)))(table)
    assert abs(float(plain[0, 0]) - want[0, 0]) > 0.05 * want[0, 0]  # what it avoids
    t32 = table.astype(jnp.float32)
    assert "custom_vjp" not in str(jax.make_jaxpr(gather_f32)(t32, idx))


@pytest.mark.parametrize("name", ["rgbd_sg_attn", "gcn"])
def test_gnn_bfloat16_tracks_float32(name):
    # ModelConfig.gnn_dtype: the same (float32) parameters; the GNN's k / q / v tables and their
    # per-edge gathers in bfloat16, while scores, softmax and message sums stay float32 (no
    # bfloat16 scatter-add), and the model's outputs and gradients are float32 and close to the
    # float32 model's (measured: logits within 4e-4 of a 0.5 scale, gradient cosine 0.9999).
    cfg = dataclasses.replace(SMALL, use_rgbd=False)  # graph-only: the GNN drives the outputs
    m32 = make_model(name, ACTIONS, cfg)
    m16 = make_model(name, ACTIONS, dataclasses.replace(cfg, gnn_dtype="bfloat16"))
    obs = _stack([_obs(s, with_image=False) for s in range(4)])
    variables = _random_variables(m32, jax.tree.map(lambda a: a[0], obs))
    assert jax.eval_shape(m16.init, jax.random.PRNGKey(0), obs) == jax.eval_shape(
        m32.init, jax.random.PRNGKey(0), obs
    )

    def run(model):
        def loss(p, o):
            logits, value = model.apply(p, o)
            return jnp.sum(jax.nn.log_softmax(logits)[:, 0]) + jnp.sum(value**2)

        return jax.jit(lambda p, o: (model.apply(p, o), jax.grad(loss)(p, o)))(variables, obs)

    (l32, v32), g32 = run(m32)
    (l16, v16), g16 = run(m16)
    assert l16.dtype == v16.dtype == jnp.float32
    assert {x.dtype for x in jax.tree.leaves(g16)} == {np.dtype(np.float32)}
    for a, b in ((l16, l32), (v16, v32)):
        err, scale = float(jnp.abs(a - b).max()), float(jnp.abs(b).max())
        assert 0 < err <= 0.01 * scale  # rounded (so bfloat16 ran), and only by bfloat16's 2^-8
    flat = lambda g: jnp.concatenate(
        [x.ravel() for x in jax.tree.leaves(g["params"]["core"]["graph_encoder"])]
    )  # noqa: E731
    a, b = flat(g16), flat(g32)
    assert float(a @ b / jnp.linalg.norm(a) / jnp.linalg.norm(b)) > 0.999
    text16, text32 = (
        str(jax.make_jaxpr(m16.apply)(variables, obs)),
        str(jax.make_jaxpr(m32.apply)(variables, obs)),
    )
    assert "bf16" not in text32
    assert re.search(r"bf16\[[0-9,]+\] = gather", text16)  # bfloat16 tables are gathered
    assert not re.search(r"bf16\[[0-9,]+\] = scatter-add", text16)  # sums are float32
    # ... and so are the gathers' gradients (lookup.gather_f32): XLA:GPU's bfloat16 scatter-adds
    # made a bfloat16 PPO update slower than a float32 one on an H100 (2026-12-05).
    grad16 = str(jax.make_jaxpr(jax.grad(lambda p: jnp.sum(m16.apply(p, obs)[0])))(variables))
    assert re.search(r"f32\[[0-9,]+\] = scatter-add", grad16)
    assert not re.search(r"bf16\[[0-9,]+\] = scatter-add", grad16)
    with pytest.raises(ConfigError, match="gnn_dtype"):
        dataclasses.replace(cfg, gnn_dtype="float16")
