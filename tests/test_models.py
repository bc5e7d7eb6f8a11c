"""Tests of hron_jax.models: PyG agreement, masking, equivariance, pooling, every variant.

The PyG references (tests/data/*_reference.npz) are frozen outputs of torch_geometric 2.8 made by
tools/make_pyg_reference.py; torch is not needed here.
"""

from __future__ import annotations

import dataclasses
import pathlib

import jax
import jax.numpy as jnp
import jraph
import numpy as np
import pytest

from hron_jax import graph_types as gt
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


def test_hgt_batch_matches_single_graphs_and_differentiates():
    """A batch [B, ...] (run as one disjoint union, nodes grouped by type) equals B single-graph
    calls (a different code path): outputs, attention and parameter gradients; dead rows carry
    garbage, NaN included."""
    d, p1, p2, g, run = _reference("hgt")
    rng = np.random.default_rng(7)
    graphs = [_pad(g, 5, 20, rng, garbage=gb)[0] for gb in (1.0, np.nan, 100.0)]
    batch = {k: np.stack([gg[k] for gg in graphs]) for k in graphs[0]}
    params = jax.tree.map(jnp.asarray, p1)

    @jax.default_matmul_precision("highest")
    def apply(p, x, node_type, mask, senders, receivers, edge_type, edge_mask):
        rel = edge_relations(node_type, senders, receivers, edge_type)
        out, state = _HGT.apply(
            {"params": p}, x, node_type, mask, senders, receivers, rel, edge_mask, mutable=["attention"]
        )
        return out, state["attention"]["alpha"][0]

    def loss(p, *a):
        return jnp.sum(jnp.sin(apply(p, *a)[0]))

    def args(gg):
        return tuple(
            gg[k] for k in ("x", "node_type", "mask", "senders", "receivers", "edge_type", "edge_mask")
        )

    out_b, alpha_b = jax.jit(apply)(params, *args(batch))
    grad_b = jax.jit(jax.grad(loss))(params, *args(batch))
    one, grad_one = jax.jit(apply), jax.jit(jax.grad(loss))
    grad_sum = None
    for i, gg in enumerate(graphs):
        out_1, alpha_1 = one(params, *args(gg))
        np.testing.assert_allclose(out_b[i], out_1, atol=TOL, rtol=0)
        np.testing.assert_allclose(alpha_b[i], alpha_1, atol=1e-6, rtol=0)
        g1 = grad_one(params, *args(gg))
        grad_sum = g1 if grad_sum is None else jax.tree.map(jnp.add, grad_sum, g1)
    assert np.isfinite(np.asarray(out_b)).all()
    for a, b in zip(jax.tree.leaves(grad_b), jax.tree.leaves(grad_sum)):
        assert np.isfinite(np.asarray(a)).all()
        np.testing.assert_allclose(a, b, atol=1e-4, rtol=1e-4)


def test_illegal_relation_triple_is_dropped():
    node_type = jnp.array([gt.ROOM, gt.OBJECT])
    rel = edge_relations(
        node_type, jnp.array([0, 1, 1]), jnp.array([1, 0, 0]), jnp.array([gt.ON_TOP, gt.IN_ROOM, gt.ON_TOP])
    )
    assert rel.tolist() == [-1, gt.RELATION_INDEX[gt.IN_ROOM, gt.OBJECT, gt.ROOM], -1]
    assert gt.check_graph_types(
        np.asarray(node_type), [0, 1], [1, 0], [gt.ON_TOP, gt.IN_ROOM], [True, True]
    ).tolist() == [0]


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


@pytest.mark.parametrize(
    "size,kernel,stride", [((32, 32), 8, 4), ((8, 8), 4, 2), ((4, 4), 3, 1), ((7, 10), 5, 3), ((9, 9), 2, 2)]
)
def test_patch_conv_equals_xla_convolution(size, kernel, stride):
    """PatchConv (slices + matmul, fast gradients inside lax.scan on XLA:CPU) is nn.Conv: same
    parameter shapes and init, same SAME-padded outputs and gradients as lax's convolution."""
    import flax.linen as nn

    from hron_jax.models.encoders import RELU_INIT, PatchConv

    x = jax.random.normal(jax.random.PRNGKey(0), (3,) + size + (5,))
    ours = PatchConv(6, kernel, stride)
    ref = nn.Conv(6, (kernel, kernel), (stride, stride), padding="SAME", kernel_init=RELU_INIT)
    p_ours, p_ref = ours.init(jax.random.PRNGKey(1), x), ref.init(jax.random.PRNGKey(1), x)
    jax.tree.map(np.testing.assert_array_equal, p_ours, p_ref)
    params = jax.tree.map(lambda a: a + 0.1 * jax.random.normal(jax.random.PRNGKey(2), a.shape), p_ref)
    np.testing.assert_allclose(ours.apply(params, x), ref.apply(params, x), atol=1e-5)
    loss = lambda m: lambda p, x: jnp.sum(jnp.sin(m.apply(p, x)))  # noqa: E731
    g_ours = jax.grad(loss(ours), argnums=(0, 1))(params, x)
    g_ref = jax.grad(loss(ref), argnums=(0, 1))(params, x)
    jax.tree.map(lambda a, b: np.testing.assert_allclose(a, b, atol=1e-4), g_ours, g_ref)
