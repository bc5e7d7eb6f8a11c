"""Model configuration (frozen dataclass) and the named variants of the paper.

`ModelConfig` holds every size of the network; the variant fields (`gnn`, `pooling`,
`node_features`, `goal_encoding`, `use_graph`, `use_map`) are set by `make_model(name, ...)` from
`VARIANTS`, so a caller normally changes only sizes and `use_rgbd`.
"""

from __future__ import annotations

import dataclasses
from typing import Literal

from hron_jax.errors import ConfigError


@dataclasses.dataclass(frozen=True)
class ModelConfig:
    """Sizes and switches of `ActorCritic`.

    Graph branch
        hidden: node embedding width of the featuriser and every GNN layer (paper release: 128).
        heads: HGT attention heads (release: 2); `hidden` must be divisible by it.
        gnn_layers: number of message-passing layers (release: 3), each followed by ReLU.
        gnn: 'hgt' (heterogeneous graph transformer) or 'gcn' (Kipf & Welling, edges homogeneous).
        hgt_softmax: how HGT normalises its attention (gnn.HGTConv): 'joint' (PyG >= 2.3, one softmax
            over all incoming edges of a node) or 'per_relation' (PyG <= 2.2, as the paper used it:
            one softmax per incoming relation triple, the relations' messages summed).
        pooling: 'task' (task-driven attention: indicator on goal categories) or 'mean' (live nodes).
        pool_flag: append a 0/1 feature "the pooling mask selected at least one node", so the policy
            can tell "nothing relevant seen yet" (pooled vector = 0) from a genuinely zero embedding.
        node_features: 'learned' (category + node-type embeddings + linear(pos, size)) or
            'word_vectors' (Yang et al.: frozen category word vectors + image code).
        yang_image_code: width of the softmax image code appended to every node (Yang et al. used a
            ResNet-50 softmax of the current frame; we use a learned softmax over the RGB-D embedding).
        gnn_dtype: compute dtype of the GNN layers (gnn.HGTConv / GCNConv): 'float32' (default, the
            paper's) or 'bfloat16', which halves the bytes of the per-node and per-edge tables
            (keys, values, queries: most of the HGT's memory traffic on a GPU). Parameters, the
            attention scores and softmax, the message sums, the gathers' gradients and the pooled
            output stay float32.
    Image / map / goal branches
        conv_features, conv_kernels, conv_strides: the 3 conv layers (SAME padding, ReLU).
        conv: how they are computed (same parameters and outputs, encoders.PatchConv): 'patches'
            (patch slices + one matmul: XLA:CPU runs a convolution's gradient ~30x slower inside
            the minibatch scan), 'xla' (XLA's convolution: cuDNN on a GPU, no patch tensor, whose
            size is k*k x the input's), or 'auto' (patches on a CPU and for inputs up to 32 x 32,
            where GPU profiles favoured them too, see PatchConv; XLA's for larger inputs elsewhere).
        cnn_fc: widths of the 3 FC layers after flattening (RGB-D and metric-map branches).
        map_class_features: width of the learned embedding of the metric map's class channel
            (encoders.MapEncoder: a class id is a category, not a magnitude).
        goal_fc: widths of the 3 FC layers of the goal MLP.
        goal_encoding: 'one_hot' (obs['goal']) or 'word_vector' (Yang et al.: word vector of
            obs['goal_classes'][0], the target object's class).
    Fusion and heads
        fusion_fc: widths of the 3 fusion FC layers; head_fc: widths of the 2 hidden layers of the
            policy and of the value head (the third layer is the output layer).
    Switches
        use_rgbd: image branch on/off; off lets an observation lack 'rgbd' (symbolic choice task).
        use_map: metric-map branch (obs['map']); use_graph: scene-graph branch (obs['graph']).
    """

    hidden: int = 128
    heads: int = 2
    gnn_layers: int = 3
    gnn: Literal["hgt", "gcn"] = "hgt"
    hgt_softmax: Literal["joint", "per_relation"] = "joint"
    pooling: Literal["task", "mean"] = "task"
    pool_flag: bool = True
    node_features: Literal["learned", "word_vectors"] = "learned"
    yang_image_code: int = 32
    gnn_dtype: Literal["float32", "bfloat16"] = "float32"

    conv_features: tuple[int, int, int] = (32, 64, 64)
    conv_kernels: tuple[int, int, int] = (8, 4, 3)
    conv_strides: tuple[int, int, int] = (4, 2, 1)
    conv: Literal["auto", "patches", "xla"] = "auto"
    cnn_fc: tuple[int, int, int] = (256, 128, 128)
    map_class_features: int = 8
    goal_fc: tuple[int, int, int] = (128, 128, 128)
    goal_encoding: Literal["one_hot", "word_vector"] = "one_hot"

    fusion_fc: tuple[int, int, int] = (256, 256, 256)
    head_fc: tuple[int, int] = (128, 128)

    use_rgbd: bool = True
    use_map: bool = False
    use_graph: bool = True

    def __post_init__(self):
        if self.heads < 1 or self.hidden % self.heads:
            raise ConfigError("heads", f"must divide hidden = {self.hidden}, got {self.heads}")
        for field, allowed in (
            ("gnn", ("hgt", "gcn")),
            ("hgt_softmax", ("joint", "per_relation")),
            ("pooling", ("task", "mean")),
            ("node_features", ("learned", "word_vectors")),
            ("goal_encoding", ("one_hot", "word_vector")),
            ("conv", ("auto", "patches", "xla")),
            ("gnn_dtype", ("float32", "bfloat16")),
        ):
            if getattr(self, field) not in allowed:
                raise ConfigError(field, f"expected one of {allowed}, got {getattr(self, field)!r}")


# Variant name -> the ModelConfig fields it fixes (everything else comes from the caller's config).
VARIANTS: dict[str, dict] = {
    # RGB-D only: image + goal, no scene representation.
    "rgbd": dict(use_graph=False, use_map=False, goal_encoding="one_hot"),
    # RGB-D + metric map: the map branch is a copy of the RGB-D branch's architecture.
    "rgbd_mm": dict(use_graph=False, use_map=True, goal_encoding="one_hot"),
    # RGB-D + scene graph, HGT, mean pooling (the "no attention" ablation).
    "rgbd_sg": dict(
        use_graph=True,
        use_map=False,
        gnn="hgt",
        pooling="mean",
        node_features="learned",
        goal_encoding="one_hot",
    ),
    # Main model: RGB-D + scene graph, HGT, task-driven attention pooling.
    "rgbd_sg_attn": dict(
        use_graph=True,
        use_map=False,
        gnn="hgt",
        pooling="task",
        node_features="learned",
        goal_encoding="one_hot",
    ),
    # Kipf et al.: GCN instead of HGT, everything else as the main model (incl. task pooling).
    "gcn": dict(
        use_graph=True,
        use_map=False,
        gnn="gcn",
        pooling="task",
        node_features="learned",
        goal_encoding="one_hot",
    ),
    # Yang et al.: GCN over word-vector node features (+ image code), goal = target word vector,
    # no task-driven attention (their model has none): mean pooling.
    "yang": dict(
        use_graph=True,
        use_map=False,
        gnn="gcn",
        pooling="mean",
        node_features="word_vectors",
        goal_encoding="word_vector",
    ),
}
