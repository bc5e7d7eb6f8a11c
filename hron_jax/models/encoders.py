"""Encoders of the observation branches: MLP, conv image encoder, node featurisers, scene graph.

All modules take ONE observation or a batch of them (leading [B] axis on every input);
`ActorCritic` passes whole batches, so the GNN layers see the batch (see gnn.HGTConv).

- `MLP`: Dense + ReLU per width.                                f32[I] -> f32[widths[-1]]
- `ConvEncoder`: 3 conv (SAME padding, ReLU), flatten, 3 FC.     f32[H, W, C] -> f32[fc[-1]]
  (RGB-D branch, and the conv stack of the metric-map branch, which the paper makes identical.)
- `MapEncoder`: metric-map branch of `rgbd_mm`: learned embedding of the class channel,
  concatenated with the other channels, then a `ConvEncoder`.  f32[M, M, C] -> f32[fc[-1]]
- `NodeFeaturizer`: category embedding + node-type embedding + linear(pos, size).
                                                                 graph nodes -> f32[N, hidden]
- `WordVectorNodeFeaturizer` (Yang et al.): linear of [word vector of the category, image code].
                                                                 graph nodes -> f32[N, hidden]
- `SceneGraphEncoder`: featuriser, `gnn_layers` x (HGTConv | GCNConv, ReLU), task-driven or mean
  pooling.                                                       GraphsTuple -> f32[hidden (+1)]
"""

from __future__ import annotations

from collections.abc import Sequence

import flax.linen as nn
import jax
import jax.numpy as jnp
import numpy as np

from hron_jax import graph_types as gt
from hron_jax.models import pooling
from hron_jax.models.config import ModelConfig
from hron_jax.models.gnn import (
    GCNConv,
    HGTConv,
    edge_relations,
    layout_mask,
    merge_types,
    on_rows,
    split_types,
)
from hron_jax.models.lookup import Embed

# PPO-style orthogonal init (PureJaxRL): sqrt(2) gain for ReLU layers.
RELU_INIT = nn.initializers.orthogonal(np.sqrt(2.0))


class MLP(nn.Module):
    """Stack of Dense layers, each followed by ReLU. f32[..., I] -> f32[..., widths[-1]]."""

    widths: Sequence[int]

    @nn.compact
    def __call__(self, x):
        for w in self.widths:
            x = nn.relu(nn.Dense(w, kernel_init=RELU_INIT)(x))
        return x


def image_patches(x, k: int, s: int):
    """SAME-padded k x k patches at stride s, as TF / flax SAME padding places them.

    f32[B, H, W, C] -> f32[B, ceil(H/s), ceil(W/s), k*k*C], features ordered (row, column, channel),
    so `patches @ kernel.reshape(k*k*C, F)` is the convolution with an HWIO kernel.

    Where s > 1 divides k, the padded image is first cut into s x s blocks (space to depth) and a
    patch is (k/s)^2 whole blocks: (k/s)^2 contiguous slices instead of k^2 strided ones. Same
    patches, bitwise; what it changes is the gradient with respect to x, which sums one padded
    copy of the image per slice: 4 instead of 64 for an 8 x 8 / stride 4 layer. Measured on
    RGB-D + MM's CPU update, whose map branch needs that gradient (class embedding): its encoders'
    op time -27 %, the update ~9 % faster (docs/benchmarks.md). The forward transposes the patch
    tensor instead of concatenating slices, so a layer whose input takes no gradient (a camera
    encoder's first) gains nothing.
    """
    b, h, w, c = x.shape
    ho, wo = -(-h // s), -(-w // s)
    ph, pw = max((ho - 1) * s + k - h, 0), max((wo - 1) * s + k - w, 0)
    x = jnp.pad(x, ((0, 0), (ph // 2, ph - ph // 2), (pw // 2, pw - pw // 2), (0, 0)))
    if s == 1 or k % s:
        span_h, span_w = (ho - 1) * s + 1, (wo - 1) * s + 1
        return jnp.concatenate(
            [x[:, i : i + span_h : s, j : j + span_w : s, :] for i in range(k) for j in range(k)],
            axis=-1,
        )
    q = k // s
    blocks = x[:, : (ho + q - 1) * s, : (wo + q - 1) * s].reshape(b, ho + q - 1, s, wo + q - 1, s, c)
    # (q*q, B, ho, s, wo, s, C), block (i, j) first -> (B, ho, wo, i, row in block, j, col, C).
    y = jnp.stack([blocks[:, i : i + ho, :, j : j + wo] for i in range(q) for j in range(q)])
    y = y.reshape(q, q, b, ho, s, wo, s, c).transpose(2, 3, 5, 0, 4, 1, 6, 7)
    return y.reshape(b, ho, wo, k * k * c)


# Inputs up to this many pixels take patches on every platform under impl 'auto' (PatchConv).
AUTO_PATCHES_MAX_PIXELS = 32 * 32


class PatchConv(nn.Module):
    """2-D convolution (SAME padding, HWIO kernel, bias), computed as `impl` says.

    Same parameters and outputs as nn.Conv(features, (k, k), (s, s), padding="SAME") (tested to
    float rounding). impl 'patches': patch extraction + one matmul. Why: XLA:CPU runs the
    *gradient* of a convolution ~30x slower inside a while loop (measured: RGB-D encoder fwd+grad
    at batch 128, 444 ms per step in a lax.scan vs 13 ms unrolled), and every PPO minibatch step
    runs inside lax.scan; as slices + matmul the gradient costs 19 ms in the loop. impl 'xla':
    XLA's convolution (cuDNN on a GPU), which never builds the patch tensor (k*k times the input:
    8.6 GB for the first layer of an 8192-sample minibatch of 128 x 128 RGB-D). impl 'auto': patches
    on a CPU; elsewhere patches for inputs of at most AUTO_PATCHES_MAX_PIXELS (32 x 32), XLA's
    convolution above (lax.platform_dependent, decided when the program is lowered). Why 32 x 32:
    `bench profile` of one PPO update (exploratory, 4096 envs x 16 steps, 32 x 32, minibatches of
    8192) put the whole encoders.py at 137 ms with patches on one H100 (2026-11-27) and at 365 ms
    with cuDNN on one H200 (2026-12-04), 310 ms of it the gradient of the first convolution (4
    input channels, 8 x 8 kernel, stride 4); larger inputs are not measured yet (`tools/gpu_bench.sh`
    train128 / train128p). f32[B, H, W, C] -> f32[B, H/s, W/s, features].
    """

    features: int
    kernel: int
    stride: int
    kernel_init: nn.initializers.Initializer = RELU_INIT
    impl: str = "auto"

    @nn.compact
    def __call__(self, x):
        c = x.shape[-1]
        kernel = self.param("kernel", self.kernel_init, (self.kernel, self.kernel, c, self.features))
        bias = self.param("bias", nn.initializers.zeros_init(), (self.features,))

        def patches(x, kernel):
            return image_patches(x, self.kernel, self.stride) @ kernel.reshape(-1, self.features)

        def xla(x, kernel):
            s = (self.stride, self.stride)
            return jax.lax.conv_general_dilated(
                x, kernel, s, "SAME", dimension_numbers=("NHWC", "HWIO", "NHWC")
            )

        if self.impl == "auto" and x.shape[-3] * x.shape[-2] <= AUTO_PATCHES_MAX_PIXELS:
            y = patches(x, kernel)
        elif self.impl == "auto":
            y = jax.lax.platform_dependent(x, kernel, cpu=patches, default=xla)
        else:
            y = {"patches": patches, "xla": xla}[self.impl](x, kernel)
        return y + bias


class ConvEncoder(nn.Module):
    """3 conv layers (ReLU), flatten, 3 FC layers (ReLU). f32[(B,) H, W, C] -> f32[(B,) fc[-1]].

    SAME padding keeps the encoder valid for any image size (small CPU images included); the
    flatten size follows from the static image shape. Convolutions are `PatchConv` (named Conv_i,
    the parameter tree of nn.Conv layers), computed as `impl` says (ModelConfig.conv).
    """

    features: Sequence[int]
    kernels: Sequence[int]
    strides: Sequence[int]
    fc: Sequence[int]
    impl: str = "auto"

    @nn.compact
    def __call__(self, img):
        x = img if img.ndim == 4 else img[None]
        for i, (f, k, s) in enumerate(zip(self.features, self.kernels, self.strides)):
            x = nn.relu(PatchConv(f, k, s, impl=self.impl, name=f"Conv_{i}")(x))
        out = MLP(self.fc)(x.reshape(x.shape[0], -1))
        return out if img.ndim == 4 else out[0]


# Channels of obs['map']: observed 0/1 and the semantic class id (an exact integer in a float);
# = hron_jax.metric_map.OBSERVED_CHANNEL / CLASS_CHANNEL (tested; not imported here: metric_map
# pulls in MuJoCo).
MAP_OBSERVED_CHANNEL = 0
MAP_CLASS_CHANNEL = 2


class MapEncoder(nn.Module):
    """Metric-map branch: class embedding + the other channels -> `ConvEncoder`.

    Input: obs['map'] f32[(B,) M, M, C] as hron_jax.metric_map.MetricMap.observe writes it: channel 0
    (`MAP_OBSERVED_CHANNEL`) observed 0/1, 1 height / max_height, 2 (`MAP_CLASS_CHANNEL`) the class
    id (0 where unobserved), and in the global view 3-4 the agent's heading. Output: f32[(B,) fc[-1]].

    The class id is a category, not a quantity: fed as a scalar channel, the first conv's response
    is affine in the id (class 17 is "more" than class 3, and the network can only tell classes
    apart by thresholds on that arbitrary order). Here it picks a learned row of an `nn.Embed(num_classes,
    class_features)` table instead (the `rgbd_mm` counterpart of the scene graph's category
    embedding), concatenated with the remaining channels before the first conv:
        x = [map without the class channel, where(observed, embed(class), 0)]   f32[M, M, C-1+E]
    Unobserved cells get the zero vector (the fixed "unknown" entry) rather than a learned row:
    that is also what the conv's SAME padding feeds beyond the crop's border and what `observe`
    writes for cells off the grid, so "never seen", "off the map" and "outside the crop" read alike,
    and the observed channel still separates them from seen cells. The env keeps emitting the
    compact integer channel (1 float per cell in the rollout buffers instead of num_classes for a
    one-hot); embedding is the one-hot times a learned matrix, done where it is learned. Ids are
    rounded and clipped to [0, num_classes) (the rollout may carry the float channel in any dtype).
    """

    num_classes: int
    class_features: int
    features: Sequence[int]
    kernels: Sequence[int]
    strides: Sequence[int]
    fc: Sequence[int]
    class_channel: int = MAP_CLASS_CHANNEL
    impl: str = "auto"

    @nn.compact
    def __call__(self, m):
        c = self.class_channel
        cls = jnp.clip(jnp.round(m[..., c]).astype(jnp.int32), 0, self.num_classes - 1)
        observed = m[..., MAP_OBSERVED_CHANNEL, None] > 0.5
        emb = Embed(self.num_classes, self.class_features, name="class_embed")(cls)
        rest = jnp.concatenate([m[..., :c], m[..., c + 1 :]], axis=-1).astype(emb.dtype)
        x = jnp.concatenate([rest, jnp.where(observed, emb, 0.0)], axis=-1)
        return ConvEncoder(self.features, self.kernels, self.strides, self.fc, self.impl, name="conv")(x)


def _node_arrays(graph):
    """(category, node_type, pos, size, mask) of a padded jraph graph (see models/__init__)."""
    n = graph.nodes
    return n["category"], n["node_type"], n["pos"], n["size"], n["mask"].astype(bool)


class NodeFeaturizer(nn.Module):
    """Learned node features: Embed(category) + Embed(node_type) + Dense([pos, size]).

    Input: graph nodes (category i32[N], node_type i32[N], pos f32[N,3], size f32[N,3], mask), or
    a batch of them ([B, N], ...). Output: f32[(B,) N, features], zero on dead nodes. Out-of-range
    ids (padding garbage) are clipped.
    """

    num_classes: int
    features: int

    @nn.compact
    def __call__(self, category, node_type, pos, size, mask):
        cat = jnp.clip(category, 0, self.num_classes - 1)
        nt = jnp.clip(node_type, 0, gt.NUM_NODE_TYPES - 1)
        # Zero the geometry of dead rows before the Dense: garbage there (even NaN) would
        # otherwise poison the kernel's gradient (0 * NaN) although the output is masked.
        geom = jnp.where(mask[..., None], jnp.concatenate([pos, size], -1), 0.0)
        h = (
            Embed(self.num_classes, self.features, name="category_embed")(cat)
            + Embed(gt.NUM_NODE_TYPES, self.features, name="type_embed")(nt)
            + on_rows(nn.Dense(self.features, name="geometry"), geom)
        )
        return jnp.where(mask[..., None], h, 0.0)


class WordVectorNodeFeaturizer(nn.Module):
    """Yang et al. node features: Dense([word_vector(category), image_code]).

    word_vectors: f32[num_classes, W] constant table (not trained), see word_vectors.py.
    image_code: optional f32[(B,) K] (a softmax code of the current image), broadcast to every
    node, standing in for Yang et al.'s ResNet-50 softmax of the current frame.
    category, mask: [(B,) N]. Output: f32[(B,) N, features], zero on dead nodes.
    """

    features: int

    @nn.compact
    def __call__(self, word_vectors, category, mask, image_code=None):
        table = jnp.asarray(word_vectors)
        wv = table[jnp.clip(category, 0, table.shape[0] - 1)]
        if image_code is not None:
            code = jnp.broadcast_to(image_code[..., None, :], wv.shape[:-1] + image_code.shape[-1:])
            wv = jnp.concatenate([wv, code], -1)
        h = on_rows(nn.Dense(self.features), wv)
        return jnp.where(mask[..., None], h, 0.0)


class SceneGraphEncoder(nn.Module):
    """Scene-graph branch: node features -> GNN stack -> pooled graph vector.

    Inputs: graph (jraph.GraphsTuple of one padded graph, nodes/edges dicts as in the observation
    contract), goal_classes i32[K] (used by task pooling), image_embedding f32[I] or None (used by
    the word-vector featuriser only), word_vectors (the Yang table, only for that featuriser); or
    all of them with a leading batch axis [B] (the GNN layers then run the whole batch at once).
    Output: f32[(B,) hidden + pool_flag]. Sows ('attention', 'pool_weights') f32[(B,) N] and, per
    HGT layer, ('attention', 'alpha') f32[(B,) E, heads].
    node_type_counts: the static type layout of the env's node table, if it has one (HGTConv); a
    batch then runs the HGT stack on per-type row tables (gnn.split_types).
    """

    config: ModelConfig
    num_classes: int
    node_type_counts: tuple[int, ...] | None = None

    @nn.compact
    def __call__(self, graph, goal_classes=None, image_embedding=None, word_vectors=None):
        cfg = self.config
        category, node_type, pos, size, mask = _node_arrays(graph)
        senders, receivers = graph.senders, graph.receivers
        edge_type = graph.edges["edge_type"]
        edge_mask = graph.edges["mask"].astype(bool)

        if cfg.node_features == "learned":
            h = NodeFeaturizer(self.num_classes, cfg.hidden, name="featurizer")(
                category, node_type, pos, size, mask
            )
        else:
            code = None
            if image_embedding is not None:
                code = nn.softmax(nn.Dense(cfg.yang_image_code, name="image_code")(image_embedding))
            h = WordVectorNodeFeaturizer(cfg.hidden, name="featurizer")(word_vectors, category, mask, code)

        # A batch of graphs with a static type layout goes through the HGT stack as per-type row
        # tables, split from the node table once and merged back once (gnn.split_types).
        counts = self.node_type_counts if cfg.gnn == "hgt" and mask.ndim == 2 else None
        if cfg.gnn == "hgt":
            relation = edge_relations(node_type, senders, receivers, edge_type)
        if counts is not None:
            h = split_types(h, layout_mask(node_type, mask, counts), counts)
        for i in range(cfg.gnn_layers):
            if cfg.gnn == "hgt":
                conv = HGTConv(
                    cfg.hidden,
                    cfg.heads,
                    softmax=cfg.hgt_softmax,
                    dtype=cfg.gnn_dtype,
                    node_type_counts=self.node_type_counts,
                    name=f"hgt_{i}",
                )
                h = conv(h, node_type, mask, senders, receivers, relation, edge_mask)
            else:
                conv = GCNConv(cfg.hidden, dtype=cfg.gnn_dtype, name=f"gcn_{i}")
                h = conv(h, mask, senders, receivers, edge_mask)
            h = jax.tree.map(nn.relu, h)
        if counts is not None:
            h = merge_types(h, counts, *mask.shape)
        h = h.astype(jnp.float32)  # pooling and everything after it in float32 (gnn_dtype)

        pool = (lambda f: jax.vmap(f)) if mask.ndim == 2 else (lambda f: f)  # noqa: E731
        if cfg.pooling == "task":
            if goal_classes is None:
                raise ValueError("task-driven pooling needs obs['goal_classes']")
            pooled, w, selected = pool(pooling.task_driven_pool)(h, category, mask, goal_classes)
        else:
            pooled, w, selected = pool(pooling.mean_pool)(h, mask)
        if not self.is_initializing():  # init returns params only (see HGTConv)
            self.sow("attention", "pool_weights", w)
        if cfg.pool_flag:
            pooled = jnp.concatenate([pooled, selected.astype(pooled.dtype)[..., None]], -1)
        return pooled
