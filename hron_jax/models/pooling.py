"""Graph readouts: task-driven attention pooling and mean pooling over live nodes.

Task-driven attention (paper, "Graph attention pooling"): weight 1 on every live node whose
semantic category is one of the goal's categories (object, furniture, room; -1 = absent), 0 on
every other node, then a weighted mean. The weights are a fixed indicator, not learned.

When no live node matches (e.g. nothing of the goal seen yet) the weighted mean is 0/0; we output
a zero vector and a `selected` flag False, which the graph encoder can append as a feature so
the policy can tell "nothing relevant in the graph" from a zero embedding. Mean pooling (the
"RGB-D + SG without attention" ablation) is the same with weight 1 on every live node.

Shapes (one graph; vmap for batches): h f32[N, F], category i32[N], node_mask bool[N],
goal_classes i32[K] -> pooled f32[F], weights f32[N] (exactly 0 or 1), selected bool[].
"""

from __future__ import annotations

import jax.numpy as jnp


def goal_match_weights(category, node_mask, goal_classes):
    """f32[N]: 1.0 where the node is live and its category is one of goal_classes (>= 0), else 0."""
    goal_classes = jnp.asarray(goal_classes)
    hit = (category[:, None] == goal_classes[None, :]) & (goal_classes[None, :] >= 0)
    return (jnp.any(hit, axis=-1) & node_mask).astype(jnp.float32)


def weighted_mean_pool(h, weights):
    """(pooled f32[F], selected bool[]): sum_i w_i h_i / sum_i w_i, or zeros when sum_i w_i = 0.

    Dividing by max(total, 1) is exact for 0/1 weights (total is then an integer >= 1 whenever
    any node is selected) and yields 0, not NaN, when none is.
    """
    w = weights.astype(h.dtype)
    total = jnp.sum(w)
    # where() so that a non-finite row with weight 0 cannot turn the sum into NaN.
    pooled = jnp.sum(jnp.where(w[:, None] > 0, w[:, None] * h, 0.0), axis=0) / jnp.maximum(total, 1.0)
    return pooled, total > 0


def task_driven_pool(h, category, node_mask, goal_classes):
    """Task-driven attention pooling. Returns (pooled f32[F], weights f32[N], selected bool[])."""
    w = goal_match_weights(category, node_mask, goal_classes)
    pooled, selected = weighted_mean_pool(h, w)
    return pooled, w, selected


def mean_pool(h, node_mask):
    """Mean over live nodes (0 for an empty graph). Returns (pooled, weights, selected)."""
    w = node_mask.astype(jnp.float32)
    pooled, selected = weighted_mean_pool(h, w)
    return pooled, w, selected
