"""Models: flax actor-critic networks of the paper (HGT + task-driven attention) and baselines.

API
    make_model(name, num_actions, config=None, num_classes=None, node_type_counts=None) -> ActorCritic
        names: rgbd, rgbd_mm, rgbd_sg, rgbd_sg_attn (main), gcn (Kipf), yang (Yang et al.)
    ActorCritic.apply(variables, obs) -> (logits f32[(B,) A], value f32[(B,)])
    attention_readout(model, variables, obs) -> (logits, value, attention dict)
    ModelConfig (frozen dataclass of sizes and switches), VARIANTS
    Layers: HGTConv, GCNConv (gnn.py); task_driven_pool, mean_pool (pooling.py)

Observation contract (one env; a batch adds a leading axis to every leaf):
    obs['graph']  jraph.GraphsTuple of ONE padded graph:
        nodes {'category' i32[N] semantic class id, 'node_type' i32[N] (0 room, 1 furniture,
               2 object), 'pos' f32[N,3] agent frame, 'size' f32[N,3], 'mask' bool[N]}
        edges {'edge_type' i32[E] (graph_types.EDGE_TYPES), 'mask' bool[E]},
        senders/receivers i32[E]; n_node, n_edge, globals unused.
        An edge carries messages only if its mask and both endpoint masks are True, and (HGT) its
        (edge type, sender type, receiver type) is a triple of graph_types.RELATION_TRIPLES.
    obs['rgbd']   f32[H,W,4] (or obs['rgb'] f32[H,W,3] + obs['depth'] f32[H,W,1]); not needed
                  when ModelConfig.use_rgbd is False.
    obs['goal']   f32[G] concatenated one-hots (always present; batch detection uses its rank).
    obs['goal_classes'] i32[3] class ids of goal object, furniture, room (-1 = absent); used by
                  task pooling and by the Yang goal encoding.
    obs['map']    f32[M,M,C] metric map (rgbd_mm only).
"""

from hron_jax.models.actor_critic import ActorCritic, attention_readout, make_model
from hron_jax.models.config import VARIANTS, ModelConfig
from hron_jax.models.gnn import GCNConv, HGTConv, edge_relations, masked_segment_softmax
from hron_jax.models.pooling import mean_pool, task_driven_pool

__all__ = [
    "ActorCritic",
    "ModelConfig",
    "VARIANTS",
    "make_model",
    "attention_readout",
    "HGTConv",
    "GCNConv",
    "edge_relations",
    "masked_segment_softmax",
    "task_driven_pool",
    "mean_pool",
]
