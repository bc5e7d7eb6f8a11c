"""Convert PyTorch Geometric state dicts (as numpy arrays) into our flax layer parameters.

Role: lets tests (and anyone porting a PyG checkpoint) load `torch_geometric.nn.HGTConv` and
`GCNConv` weights into `hron_jax.models.gnn.HGTConv` / `GCNConv`. numpy only: torch is not needed.

PyG 2.8 HGTConv layout (per layer prefix):
    kqv_lin.lins.<node type>.weight [3F, F_in], .bias [3F]     -> kqv_kernel[t] = weight.T
    out_lin.lins.<node type>.weight [F, F], .bias [F]          -> out_kernel[t] = weight.T
    k_rel.weight / v_rel.weight [H * R, D, D], row h * R + r,
        applied as x @ W (HeteroLinear stores [in, out])       -> k_rel[r, h] = weight[h * R + r]
    p_rel.<src>__<edge>__<dst> [1, H]                          -> p_rel[r]
    skip.<node type> [1]                                       -> skip[t]
Relation r is the position of the triple in the metadata PyG was built with; pass those names
(in our RELATION_TRIPLES order when built by tools/make_pyg_reference.py).
GCNConv: lin.weight [F, F_in] -> kernel = weight.T; bias [F] -> bias.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from hron_jax import graph_types as gt


def hgt_params_from_pyg(
    state: Mapping[str, np.ndarray],
    prefix: str = "",
    heads: int = 1,
    node_types: Sequence[str] = gt.NODE_TYPES,
    relations: Sequence[str] | None = None,
) -> dict[str, np.ndarray]:
    """Flax params of one HGTConv from a PyG HGTConv state dict (keys `prefix + name`).

    `relations`: 'src__edge__dst' names in the PyG metadata order, which must equal our relation
    index order; defaults to graph_types.relation_names().
    """
    if relations is None:
        relations = ["__".join(t) for t in gt.relation_names()]
    g = lambda name: np.asarray(state[prefix + name], np.float32)  # noqa: E731
    r = len(relations)
    kqv_kernel = np.stack([g(f"kqv_lin.lins.{t}.weight").T for t in node_types])
    kqv_bias = np.stack([g(f"kqv_lin.lins.{t}.bias") for t in node_types])
    out_kernel = np.stack([g(f"out_lin.lins.{t}.weight").T for t in node_types])
    out_bias = np.stack([g(f"out_lin.lins.{t}.bias") for t in node_types])

    def rel_stack(name):
        w = g(name)  # [H * R, D, D], head-major
        hr, d, _ = w.shape
        if hr != heads * r:
            raise ValueError(f"{prefix + name}: {hr} rows, expected heads*relations = {heads * r}")
        return w.reshape(heads, r, d, d).transpose(1, 0, 2, 3)

    p_rel = np.stack([g(f"p_rel.{name}").reshape(heads) for name in relations])
    skip = np.stack([g(f"skip.{t}").reshape(()) for t in node_types])
    return dict(
        kqv_kernel=kqv_kernel,
        kqv_bias=kqv_bias,
        k_rel=rel_stack("k_rel.weight"),
        v_rel=rel_stack("v_rel.weight"),
        p_rel=p_rel,
        out_kernel=out_kernel,
        out_bias=out_bias,
        skip=skip,
    )


def gcn_params_from_pyg(state: Mapping[str, np.ndarray], prefix: str = "") -> dict[str, np.ndarray]:
    """Flax params of one GCNConv from a PyG GCNConv state dict (keys `prefix + name`)."""
    return dict(
        kernel=np.asarray(state[prefix + "lin.weight"], np.float32).T,
        bias=np.asarray(state[prefix + "bias"], np.float32),
    )
