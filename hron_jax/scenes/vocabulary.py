"""Global, fixed category vocabularies shared by every scene, task and model.

Role: one place that fixes the meaning of category indices, so one-hot goal vectors and semantic
class ids are identical in every house (training and held-out) and in the symbolic choice task,
which reuses the vocabulary (circle = object, rectangle = furniture, triangle = distractor object).

Two integer spaces are used:
- vocabulary index: position within one kind's tuple (ROOMS, FURNITURE, OBJECTS, RELATIONS);
  this is what goal one-hots are built from (sizes len(ROOMS), len(FURNITURE), ...).
- semantic class id: one integer space over everything a ray can hit, used in segmentation images
  and node features: 0 nothing, 1 structure, then rooms, furniture, objects in vocabulary order.
  `class_id(kind, category)` maps to it, NUM_CLASSES is its size.

Object categories also carry their primitive shape (MJCF geom type and size) and axis-aligned half
extents, so the object pool bodies in every scene are generated from OBJECT_SHAPES alone and the
loader can check which objects fit which relation slot.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

ROOMS: tuple[str, ...] = (
    "kitchen",
    "living_room",
    "dining_room",
    "bedroom",
    "bathroom",
    "corridor",
    "office",
    "utility_room",
)

FURNITURE: tuple[str, ...] = (
    "table",
    "shelf",
    "cabinet",
    "fridge",
    "counter",
    "bed",
    "sofa",
    "desk",
    "nightstand",
    "wardrobe",
    "tv_stand",
    "coffee_table",
    "sink_cabinet",
    "dresser",
    "rectangle",  # symbolic choice task only
)

OBJECTS: tuple[str, ...] = (
    "apple",
    "bowl",
    "gym_shoe",
    "book",
    "mug",
    "bottle",
    "laptop",
    "towel",
    "circle",  # symbolic choice task: the goal object
    "triangle",  # symbolic choice task: distractor
)

# Categories that only exist in the 2D symbolic task; houses never contain them.
SYMBOLIC_FURNITURE: tuple[str, ...] = ("rectangle",)
SYMBOLIC_OBJECTS: tuple[str, ...] = ("circle", "triangle")
HOUSE_OBJECTS: tuple[str, ...] = tuple(o for o in OBJECTS if o not in SYMBOLIC_OBJECTS)

RELATIONS: tuple[str, ...] = ("onTop", "inside", "under")
ON_TOP, INSIDE, UNDER = 0, 1, 2

# Node types of the scene graph. FURNITURE is the category tuple, hence FURNITURE_NODE; the NODE_*
# names are the same constants spelled uniformly.
ROOM, FURNITURE_NODE, OBJECT = 0, 1, 2
NODE_ROOM, NODE_FURNITURE, NODE_OBJECT = ROOM, FURNITURE_NODE, OBJECT
NODE_TYPES: tuple[str, ...] = ("room", "furniture", "object")
KINDS: tuple[str, ...] = NODE_TYPES

NOTHING_CLASS = 0
STRUCTURE_CLASS = 1
_ROOM_BASE = 2
_FURNITURE_BASE = _ROOM_BASE + len(ROOMS)
_OBJECT_BASE = _FURNITURE_BASE + len(FURNITURE)
NUM_CLASSES = _OBJECT_BASE + len(OBJECTS)

_TABLES = {"room": ROOMS, "furniture": FURNITURE, "object": OBJECTS}
_BASES = {"room": _ROOM_BASE, "furniture": _FURNITURE_BASE, "object": _OBJECT_BASE}


def vocab(kind: str) -> tuple[str, ...]:
    """The category tuple of a kind ('room', 'furniture' or 'object')."""
    if kind not in _TABLES:
        raise KeyError(f"unknown kind {kind!r}; expected one of {NODE_TYPES}")
    return _TABLES[kind]


def index(kind: str, category: str) -> int:
    """Vocabulary index of `category` within its kind (for one-hot goals). KeyError if unknown."""
    table = vocab(kind)
    if category not in table:
        raise KeyError(f"unknown {kind} category {category!r}; known: {', '.join(table)}")
    return table.index(category)


def class_id(kind: str, category: str) -> int:
    """Semantic class id of a category (0 nothing and 1 structure are reserved)."""
    return _BASES[kind] + index(kind, category)


def class_name(cid: int) -> str:
    """Inverse of class_id for labels and plots: 'nothing', 'structure' or '<kind>:<category>'."""
    if cid == NOTHING_CLASS:
        return "nothing"
    if cid == STRUCTURE_CLASS:
        return "structure"
    for kind in ("object", "furniture", "room"):
        if cid >= _BASES[kind]:
            return f"{kind}:{_TABLES[kind][cid - _BASES[kind]]}"
    raise ValueError(f"class id {cid} out of range [0, {NUM_CLASSES})")


def relation_id(name: str) -> int:
    if name not in RELATIONS:
        raise KeyError(f"unknown relation {name!r}; known: {', '.join(RELATIONS)}")
    return RELATIONS.index(name)


# Class id -> node type (-1 for nothing/structure); handy as a JAX constant lookup table.
CLASS_NODE_TYPE = np.full(NUM_CLASSES, -1, np.int32)
CLASS_NODE_TYPE[_ROOM_BASE:_FURNITURE_BASE] = ROOM
CLASS_NODE_TYPE[_FURNITURE_BASE:_OBJECT_BASE] = FURNITURE_NODE
CLASS_NODE_TYPE[_OBJECT_BASE:] = OBJECT


class ObjectShape(NamedTuple):
    """Primitive of an object category.

    geom: MJCF geom type ('sphere', 'box' or 'capsule', capsule axis along z).
    size: MJCF size attribute (sphere (r,), box (hx, hy, hz), capsule (r, half_length)).
    half: axis-aligned half extents (3,) of the geom, used for slot fitting and placement.
    rgba: colour.
    """

    geom: str
    size: tuple[float, ...]
    half: tuple[float, float, float]
    rgba: tuple[float, float, float, float]


def _sphere(r, rgba):
    return ObjectShape("sphere", (r,), (r, r, r), rgba)


def _box(hx, hy, hz, rgba):
    return ObjectShape("box", (hx, hy, hz), (hx, hy, hz), rgba)


def _capsule(r, hl, rgba):
    return ObjectShape("capsule", (r, hl), (r, r, r + hl), rgba)


OBJECT_SHAPES: dict[str, ObjectShape] = {
    "apple": _sphere(0.045, (0.80, 0.08, 0.08, 1.0)),
    "bowl": _box(0.08, 0.08, 0.035, (0.95, 0.90, 0.75, 1.0)),
    "gym_shoe": _box(0.14, 0.05, 0.055, (0.15, 0.35, 0.85, 1.0)),
    "book": _box(0.10, 0.075, 0.02, (0.20, 0.55, 0.25, 1.0)),
    "mug": _capsule(0.04, 0.02, (0.95, 0.55, 0.10, 1.0)),
    "bottle": _capsule(0.035, 0.08, (0.30, 0.75, 0.70, 1.0)),
    "laptop": _box(0.16, 0.11, 0.012, (0.25, 0.25, 0.28, 1.0)),
    "towel": _box(0.12, 0.09, 0.03, (0.90, 0.45, 0.70, 1.0)),
    "circle": _sphere(0.10, (0.90, 0.20, 0.20, 1.0)),
    "triangle": _box(0.08, 0.08, 0.08, (0.20, 0.70, 0.20, 1.0)),
}
assert tuple(OBJECT_SHAPES) == OBJECTS

# (len(OBJECTS), 3) half extents in vocabulary order.
OBJECT_HALF = np.array([OBJECT_SHAPES[o].half for o in OBJECTS], np.float64)

# Display / render colours of rooms (floors) and furniture categories.
ROOM_RGBA: dict[str, tuple[float, float, float, float]] = {
    "kitchen": (0.93, 0.87, 0.62, 1.0),
    "living_room": (0.72, 0.84, 0.66, 1.0),
    "dining_room": (0.94, 0.74, 0.58, 1.0),
    "bedroom": (0.70, 0.76, 0.92, 1.0),
    "bathroom": (0.62, 0.88, 0.90, 1.0),
    "corridor": (0.82, 0.80, 0.78, 1.0),
    "office": (0.86, 0.74, 0.90, 1.0),
    "utility_room": (0.74, 0.74, 0.70, 1.0),
}
FURNITURE_RGBA: dict[str, tuple[float, float, float, float]] = {
    "table": (0.55, 0.35, 0.18, 1.0),
    "shelf": (0.62, 0.45, 0.25, 1.0),
    "cabinet": (0.78, 0.70, 0.55, 1.0),
    "fridge": (0.88, 0.90, 0.92, 1.0),
    "counter": (0.45, 0.45, 0.48, 1.0),
    "bed": (0.50, 0.30, 0.45, 1.0),
    "sofa": (0.35, 0.40, 0.60, 1.0),
    "desk": (0.40, 0.28, 0.16, 1.0),
    "nightstand": (0.70, 0.52, 0.32, 1.0),
    "wardrobe": (0.48, 0.33, 0.22, 1.0),
    "tv_stand": (0.20, 0.20, 0.22, 1.0),
    "coffee_table": (0.66, 0.50, 0.30, 1.0),
    "sink_cabinet": (0.85, 0.85, 0.80, 1.0),
    "dresser": (0.60, 0.42, 0.30, 1.0),
    "rectangle": (0.30, 0.30, 0.80, 1.0),
}
STRUCTURE_RGBA = (0.92, 0.91, 0.88, 1.0)
assert tuple(ROOM_RGBA) == ROOMS and tuple(FURNITURE_RGBA) == FURNITURE
