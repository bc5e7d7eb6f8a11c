"""Actor-critic network of the paper and its baselines, selectable by name with `make_model`.

    obs -> [RGB-D CNN] [metric-map class embedding + CNN] [scene-graph GNN + pooling] [goal MLP] (per variant)
        -> concat -> fusion (3 FC) -> policy head (3 FC) -> logits f32[num_actions]
                                   -> value head  (3 FC) -> value  f32[]

Batching: `ActorCritic.__call__` accepts one observation or a batch. When obs['goal'] has
leading batch axes ([B, G], or [T, B, G], ...) they are flattened into one and the network runs on
the whole batch at once (every module takes a leading batch axis; the GNN layers then process the
batch as one disjoint-union graph, much cheaper than one graph at a time), giving logits
f32[B, A] and value f32[B] (or [T, B, A], [T, B]). Parameters are identical in both modes (both
live under 'core'), so init on one observation and apply on a batch, or vice versa.

Attention readout: HGT attention per layer/head/edge and the pooling weights are sown into the
'attention' collection. Training calls `apply(variables, obs)` and pays nothing for it; analysis
calls `apply(variables, obs, mutable=['attention'])` and gets them back
(see `attention_readout`).
"""

from __future__ import annotations

import dataclasses

import flax.linen as nn
import jax
import jax.numpy as jnp

from hron_jax.models.config import VARIANTS, ModelConfig
from hron_jax.models.encoders import MLP, ConvEncoder, MapEncoder, SceneGraphEncoder
from hron_jax.models.word_vectors import load_category_vectors


def _rgbd(obs):
    """obs['rgbd'], or rgb and depth concatenated when an env gives them apart (choice task)."""
    if "rgbd" in obs:
        return obs["rgbd"]
    if "rgb" in obs and "depth" in obs:
        return jnp.concatenate([obs["rgb"], obs["depth"]], axis=-1)
    raise KeyError(
        "the model uses the RGB-D branch (use_rgbd=True) but obs has no 'rgbd' "
        "(nor 'rgb' + 'depth'); build it with ModelConfig(use_rgbd=False) if the "
        "task has no image"
    )


class _ActorCriticCore(nn.Module):
    """The network on ONE observation or on a batch with ONE leading axis. See module docstring."""

    num_actions: int
    num_classes: int
    config: ModelConfig
    node_type_counts: tuple[int, ...] | None = None

    @nn.compact
    def __call__(self, obs):
        cfg = self.config
        feats = []
        img = None
        conv = dict(
            features=cfg.conv_features,
            kernels=cfg.conv_kernels,
            strides=cfg.conv_strides,
            fc=cfg.cnn_fc,
            impl=cfg.conv,
        )
        if cfg.use_rgbd:
            img = ConvEncoder(**conv, name="rgbd_encoder")(_rgbd(obs))
            feats.append(img)
        if cfg.use_map:
            # The RGB-D branch's conv stack on [map channels, embedding of the class channel].
            feats.append(
                MapEncoder(self.num_classes, cfg.map_class_features, **conv, name="map_encoder")(obs["map"])
            )

        word_vectors = None
        if cfg.node_features == "word_vectors" or cfg.goal_encoding == "word_vector":
            word_vectors = load_category_vectors(self.num_classes)
        if cfg.use_graph:
            feats.append(
                SceneGraphEncoder(cfg, self.num_classes, self.node_type_counts, name="graph_encoder")(
                    obs["graph"], obs.get("goal_classes"), img, word_vectors
                )
            )

        if cfg.goal_encoding == "one_hot":
            goal = obs["goal"]
        else:
            # Yang et al.: the goal is the word vector of the target object category (0 if absent).
            target = obs["goal_classes"][..., 0]
            table = jnp.asarray(word_vectors)
            goal = jnp.where(target[..., None] >= 0, table[jnp.clip(target, 0, table.shape[0] - 1)], 0.0)
        feats.append(MLP(cfg.goal_fc, name="goal_encoder")(goal.astype(jnp.float32)))

        z = MLP(cfg.fusion_fc, name="fusion")(jnp.concatenate(feats, axis=-1))
        logits = MLP(cfg.head_fc, name="policy_hidden")(z)
        logits = nn.Dense(self.num_actions, kernel_init=nn.initializers.orthogonal(0.01), name="policy_out")(
            logits
        )
        value = MLP(cfg.head_fc, name="value_hidden")(z)
        value = nn.Dense(1, kernel_init=nn.initializers.orthogonal(1.0), name="value_out")(value)
        return logits, value[..., 0]


class ActorCritic(nn.Module):
    """Policy and value network. `apply(variables, obs) -> (logits, value)`.

    Fields: num_actions, num_classes (semantic class vocabulary size, NUM_CLASSES), config,
    node_type_counts (the static type layout of the env's node table, `env.node_type_counts`, or
    None: the HGT layers then read every node's type from obs; same parameters either way).
    obs: one observation dict (logits f32[A], value f32[]) or a batch with the same leading axes
    on every leaf (logits f32[*lead, A], value f32[*lead]); the leading axes are those of
    obs['goal'] beyond its last (feature) axis.
    """

    num_actions: int
    num_classes: int
    config: ModelConfig = ModelConfig()
    node_type_counts: tuple[int, ...] | None = None

    @nn.compact
    def __call__(self, obs):
        lead = jnp.shape(obs["goal"])[:-1]
        if not lead:
            return _ActorCriticCore(
                self.num_actions, self.num_classes, self.config, self.node_type_counts, name="core"
            )(obs)
        # Any number of leading batch axes ([B], [T, B], ...): flatten them into one, run the
        # network on the whole batch, restore them on the outputs.
        flat = jax.tree.map(lambda a: jnp.reshape(a, (-1,) + jnp.shape(a)[len(lead) :]), obs)
        logits, value = _ActorCriticCore(
            self.num_actions, self.num_classes, self.config, self.node_type_counts, name="core"
        )(flat)
        return logits.reshape(lead + logits.shape[1:]), value.reshape(lead)


def make_model(
    name: str,
    num_actions: int,
    config: ModelConfig | None = None,
    num_classes: int | None = None,
    node_type_counts: tuple[int, ...] | None = None,
) -> ActorCritic:
    """The `ActorCritic` of a named variant (see config.VARIANTS).

    name: 'rgbd', 'rgbd_mm', 'rgbd_sg', 'rgbd_sg_attn' (main), 'gcn' (Kipf), 'yang' (Yang et al.).
    config: sizes and use_rgbd; the variant's own fields override it. num_classes defaults to
    hron_jax.scenes.vocabulary.NUM_CLASSES. node_type_counts: the env's (see ActorCritic).
    """
    if name not in VARIANTS:
        raise ValueError(f"unknown model {name!r}; valid names: {', '.join(VARIANTS)}")
    if num_classes is None:
        from hron_jax.scenes import vocabulary

        num_classes = vocabulary.NUM_CLASSES
    cfg = dataclasses.replace(config or ModelConfig(), **VARIANTS[name])
    counts = None if node_type_counts is None else tuple(int(c) for c in node_type_counts)
    return ActorCritic(
        num_actions=num_actions, num_classes=int(num_classes), config=cfg, node_type_counts=counts
    )


def attention_readout(model: ActorCritic, variables, obs):
    """Run the model once and return (logits, value, attention) for analysis (not for training).

    attention: nested dict mirroring the module tree, e.g.
        attention['core']['graph_encoder']['hgt_0']['alpha'] -> (f32[(B,) E, heads],)
        attention['core']['graph_encoder']['pool_weights']   -> (f32[(B,) N],)
    (flax `sow` stores a 1-tuple per call). Empty for variants without a graph.
    """
    (logits, value), state = model.apply(variables, obs, mutable=["attention"])
    return logits, value, state.get("attention", {})


__all__ = ["ActorCritic", "ModelConfig", "make_model", "attention_readout", "VARIANTS"]
