"""Goal encoding shared by every task (choice, directed, exploratory) and every model.

A goal is the tuple (object, relation, furniture, room) of *vocabulary indices* (positions in
vocabulary.OBJECTS, RELATIONS, FURNITURE, ROOMS; the same order as scenes.goal_table rows). -1 means
"not part of the goal" (the choice and directed tasks have no room) and encodes as an all-zero block.

Two views of a goal go into observations:
- obs['goal']: f32[GOAL_DIM], concatenated one-hots [object | relation | furniture | room] with block
  sizes (len(OBJECTS), len(RELATIONS), len(FURNITURE), len(ROOMS)) starting at GOAL_SLICES.
- obs['goal_classes']: i32[3], semantic class ids (vocabulary.class_id) of (object, furniture, room),
  -1 where absent. The task-driven attention pools nodes whose category is one of these.

All functions are jittable (integer inputs may be traced) and vmap over batches of goals.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from hron_jax.scenes import vocabulary as V

NUM_OBJECTS = len(V.OBJECTS)
NUM_RELATIONS = len(V.RELATIONS)
NUM_FURNITURE = len(V.FURNITURE)
NUM_ROOMS = len(V.ROOMS)
GOAL_SIZES = (NUM_OBJECTS, NUM_RELATIONS, NUM_FURNITURE, NUM_ROOMS)
GOAL_DIM = sum(GOAL_SIZES)
# Start offset of each block in the goal vector: object, relation, furniture, room.
GOAL_SLICES = {
    'object': slice(0, NUM_OBJECTS),
    'relation': slice(NUM_OBJECTS, NUM_OBJECTS + NUM_RELATIONS),
    'furniture': slice(NUM_OBJECTS + NUM_RELATIONS, NUM_OBJECTS + NUM_RELATIONS + NUM_FURNITURE),
    'room': slice(GOAL_DIM - NUM_ROOMS, GOAL_DIM),
}

# Vocabulary index -> semantic class id, as constant lookup tables.
OBJECT_CLASS = np.array([V.class_id('object', c) for c in V.OBJECTS], np.int32)
FURNITURE_CLASS = np.array([V.class_id('furniture', c) for c in V.FURNITURE], np.int32)
ROOM_CLASS = np.array([V.class_id('room', c) for c in V.ROOMS], np.int32)


def _one_hot_or_zero(idx, size):
    idx = jnp.asarray(idx, jnp.int32)
    # one_hot of a negative index is all zeros, which is exactly "absent".
    return (jnp.arange(size, dtype=jnp.int32) == idx).astype(jnp.float32)


def encode_goal(object_idx, relation_idx, furniture_idx, room_idx) -> jnp.ndarray:
    """f32[GOAL_DIM] concatenated one-hots; an index of -1 gives an all-zero block."""
    return jnp.concatenate(
        [
            _one_hot_or_zero(object_idx, NUM_OBJECTS),
            _one_hot_or_zero(relation_idx, NUM_RELATIONS),
            _one_hot_or_zero(furniture_idx, NUM_FURNITURE),
            _one_hot_or_zero(room_idx, NUM_ROOMS),
        ]
    )


def _lookup(table, idx):
    idx = jnp.asarray(idx, jnp.int32)
    return jnp.where(idx >= 0, jnp.asarray(table)[jnp.maximum(idx, 0)], -1)


def goal_classes(object_idx, furniture_idx, room_idx) -> jnp.ndarray:
    """i32[3] semantic class ids of the goal's object, furniture and room (-1 where absent)."""
    return jnp.stack(
        [
            _lookup(OBJECT_CLASS, object_idx),
            _lookup(FURNITURE_CLASS, furniture_idx),
            _lookup(ROOM_CLASS, room_idx),
        ]
    ).astype(jnp.int32)


def goal_indices(
    object: str | None, relation: str | None, furniture: str | None, room: str | None
) -> tuple[int, int, int, int]:
    """Names -> vocabulary indices (None -> -1), for building goals outside jit."""
    return (
        -1 if object is None else V.index('object', object),
        -1 if relation is None else V.relation_id(relation),
        -1 if furniture is None else V.index('furniture', furniture),
        -1 if room is None else V.index('room', room),
    )


def decode_goal(goal) -> tuple[str | None, str | None, str | None, str | None]:
    """Inverse of encode_goal for labels and debugging (numpy, not jittable)."""
    goal = np.asarray(goal)
    names = (V.OBJECTS, V.RELATIONS, V.FURNITURE, V.ROOMS)
    out = []
    for key, table in zip(('object', 'relation', 'furniture', 'room'), names):
        block = goal[GOAL_SLICES[key]]
        out.append(table[int(block.argmax())] if block.max() > 0 else None)
    return tuple(out)
