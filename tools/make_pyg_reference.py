"""Write tests/data/{hgt,gcn}_reference.npz: PyTorch Geometric HGTConv / GCNConv on a small graph.

Role: frozen ground truth for tests/test_models.py, which loads the saved PyG weights into
hron_jax.models.gnn.HGTConv / GCNConv (via hron_jax.models.pyg_compat) and checks the outputs.
torch is not a project dependency: run this once in a side venv and commit the .npz files.

    python3 -m venv /tmp/torchenv
    /tmp/torchenv/bin/pip install torch==2.13.0 torch_geometric numpy   # pin torch: CPU build
    /tmp/torchenv/bin/python tools/make_pyg_reference.py

The graph: 4 rooms, 6 furniture, 8 objects with interleaved node types (so the per-type
bookkeeping is exercised), every one of the 11 HGT relation triples present, one isolated node of
each type, a roomConnected self loop and a duplicated edge. Two stacked layers are saved for each
operator: layer 1 changes the width (12 -> 16, so HGT has no residual), layer 2 keeps it (16 -> 16,
HGT gated residual) and is applied to relu(layer 1). Weights are drawn in float32 (PyG's own
initialisers, kqv weights scaled by 3 for peaked attention, p_rel and skip randomised since PyG
initialises them to 1, GCN bias randomised since PyG initialises it to 0), the forward pass is
run in float64, and weights/inputs are saved as float32, outputs as float64.
"""

from __future__ import annotations

import importlib.util
import pathlib
import sys

import numpy as np
import torch
import torch_geometric
from torch_geometric.nn import GCNConv, HGTConv

ROOT = pathlib.Path(__file__).resolve().parents[1]
OUT_DIR = ROOT / "tests" / "data"
IN_CH, OUT_CH, HEADS = 12, 16, 2


def load_graph_types():
    """Import hron_jax/graph_types.py by path (numpy only; the side venv has no jax)."""
    path = ROOT / "hron_jax" / "graph_types.py"
    spec = importlib.util.spec_from_file_location("hron_graph_types", path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod
    spec.loader.exec_module(mod)
    return mod


def build_graph(gt, rng):
    """Global node table (types interleaved) and a typed edge list over it."""
    counts = {gt.ROOM: 4, gt.FURNITURE: 6, gt.OBJECT: 8}
    node_type = np.concatenate([np.full(c, t, np.int32) for t, c in counts.items()])
    node_type = node_type[rng.permutation(len(node_type))]
    of = {t: list(np.nonzero(node_type == t)[0]) for t in counts}
    room, furn, obj = of[gt.ROOM], of[gt.FURNITURE], of[gt.OBJECT]
    # Isolated nodes: the last of each type gets no edge at all.
    room, furn, obj = room[:-1], furn[:-1], obj[:-1]

    edges = []  # (sender, receiver, edge_type)

    def both(a, b, et):
        edges.append((a, b, et))
        edges.append((b, a, gt.REVERSE_EDGE_TYPE[et]))

    both(room[0], room[1], gt.ROOM_CONNECTED)
    both(room[1], room[2], gt.ROOM_CONNECTED)
    edges.append((room[1], room[1], gt.ROOM_CONNECTED))  # self loop
    for i, f in enumerate(furn):
        both(f, room[i % len(room)], gt.IN_ROOM)
    rels = [gt.ON_TOP, gt.INSIDE, gt.UNDER]
    for i, o in enumerate(obj):
        f = furn[i % len(furn)]
        if i < 6:
            both(o, f, rels[i % 3])
        both(o, room[(i + 1) % len(room)], gt.IN_ROOM)
    edges.append(edges[-1])  # duplicated edge (object -> room inRoom)
    e = np.array(edges, np.int64)
    return node_type, e[:, 0], e[:, 1], e[:, 2].astype(np.int32)


def main() -> None:
    gt = load_graph_types()
    rng = np.random.default_rng(0)
    torch.manual_seed(0)
    node_type, senders, receivers, edge_type = build_graph(gt, rng)
    n = len(node_type)
    rel = gt.RELATION_INDEX[edge_type, node_type[senders], node_type[receivers]]
    assert (rel >= 0).all(), "reference graph uses an illegal relation triple"
    assert set(rel.tolist()) == set(range(gt.NUM_RELATIONS)), "every relation triple must appear"
    x = rng.standard_normal((n, IN_CH)).astype(np.float32)

    # --- HGT on PyG's dict-of-types representation -------------------------------------------
    names = gt.NODE_TYPES
    triples = gt.relation_names()
    local = np.zeros(n, np.int64)  # position of each global node within its type
    for t in range(gt.NUM_NODE_TYPES):
        idx = np.nonzero(node_type == t)[0]
        local[idx] = np.arange(len(idx))
    x_dict = {names[t]: torch.from_numpy(x[node_type == t]).double() for t in range(len(names))}
    ei_dict = {}
    for r, trip in enumerate(triples):  # metadata order == our relation index order
        sel = rel == r
        ei_dict[trip] = torch.from_numpy(np.stack([local[senders[sel]], local[receivers[sel]]]))

    def to_global(out_dict, width):
        out = np.zeros((n, width))
        for t in range(len(names)):
            out[node_type == t] = out_dict[names[t]].detach().numpy()
        return out

    metadata = (list(names), triples)
    conv1 = HGTConv(IN_CH, OUT_CH, metadata, heads=HEADS)
    conv2 = HGTConv(OUT_CH, OUT_CH, metadata, heads=HEADS)
    with torch.no_grad():
        for conv in (conv1, conv2):
            for p in conv.p_rel.values():
                p.copy_(torch.empty_like(p).uniform_(0.5, 1.5))
            for p in conv.skip.values():
                p.copy_(torch.randn_like(p))
            # PyG's init gives near-uniform attention on this graph; sharpen it so the test can
            # tell joint from per-relation softmax and catch errors in the max/normaliser.
            for lin in conv.kqv_lin.lins.values():
                lin.weight.mul_(3.0)
    weights = {}
    for pre, conv in (("conv1.", conv1), ("conv2.", conv2)):
        for k, v in conv.state_dict().items():
            weights[pre + k] = v.detach().numpy().astype(np.float32)
    conv1.double(), conv2.double()
    with torch.no_grad():
        h1 = conv1(x_dict, ei_dict)
        h2 = conv2({k: v.relu() for k, v in h1.items()}, ei_dict)
    hgt = dict(
        node_type=node_type,
        senders=senders.astype(np.int32),
        receivers=receivers.astype(np.int32),
        edge_type=edge_type,
        x=x,
        out1=to_global(h1, OUT_CH),
        out2=to_global(h2, OUT_CH),
        heads=np.int32(HEADS),
        node_type_names=np.array(names),
        relation_names=np.array(["__".join(t) for t in triples]),
        torch_geometric_version=np.array(torch_geometric.__version__),
        torch_version=np.array(torch.__version__),
        **weights,
    )

    # --- GCN on the same edges as one homogeneous graph ---------------------------------------
    g1, g2 = GCNConv(IN_CH, OUT_CH), GCNConv(OUT_CH, OUT_CH)
    with torch.no_grad():
        for g in (g1, g2):
            g.bias.copy_(torch.randn_like(g.bias) * 0.1)  # PyG initialises bias to 0
    gw = {}
    for pre, g in (("conv1.", g1), ("conv2.", g2)):
        for k, v in g.state_dict().items():
            gw[pre + k] = v.detach().numpy().astype(np.float32)
    g1.double(), g2.double()
    ei = torch.from_numpy(np.stack([senders, receivers]))
    xt = torch.from_numpy(x).double()
    with torch.no_grad():
        o1 = g1(xt, ei)
        o2 = g2(o1.relu(), ei)
    gcn = dict(
        node_type=node_type,
        senders=senders.astype(np.int32),
        receivers=receivers.astype(np.int32),
        edge_type=edge_type,
        x=x,
        out1=o1.numpy(),
        out2=o2.numpy(),
        torch_geometric_version=np.array(torch_geometric.__version__),
        torch_version=np.array(torch.__version__),
        **gw,
    )

    OUT_DIR.mkdir(parents=True, exist_ok=True)
    for name, data in (("hgt_reference.npz", hgt), ("gcn_reference.npz", gcn)):
        path = OUT_DIR / name
        np.savez_compressed(path, **data)
        print(f"wrote {path} ({path.stat().st_size} bytes, {n} nodes, {len(senders)} edges)")


if __name__ == "__main__":
    main()
