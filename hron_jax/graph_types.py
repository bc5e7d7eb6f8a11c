"""Scene-graph type constants shared by the graph builder and the models.

One padded node table holds every node type, and one padded edge table holds every edge type, so
types are small integers stored per node (`node_type`) and per edge (`edge_type`).

Node types
    0 room, 1 furniture, 2 object.

Edge types (directed, sender -> receiver)
    0 inRoom         furniture/object -> room
    1 roomConnected  room -> room (stored in both directions, so it is its own reverse)
    2 onTop          object -> furniture
    3 inside         object -> furniture
    4 under          object -> furniture
    5 rev_inRoom     room -> furniture/object
    6 rev_onTop      furniture -> object
    7 rev_inside     furniture -> object
    8 rev_under      furniture -> object

Reverse types exist so that messages flow both ways along every relation while the GNN still
knows the direction (an object receiving "rev_onTop" from a table is different from a table
receiving "onTop" from an object).

HGT relation triples
    The heterogeneous graph transformer (and PyG's `HGTConv`) keys its per-relation weights by
    (source node type, edge type, destination node type). `inRoom` has two legal source types, so
    it yields two triples, as does `rev_inRoom`: 11 triples in all, listed in `RELATION_TRIPLES`
    in a fixed order (edge-type major). `RELATION_INDEX[edge_type, src_type, dst_type]` gives the
    triple's row, or -1 for a combination that is not a legal relation. The models treat an edge
    whose combination is illegal as absent (it carries no message), so the graph builder must only
    emit the combinations listed here; `check_graph_types` tells which live edges break that.
"""

from __future__ import annotations

import numpy as np

# --- node types -------------------------------------------------------------------------------
NODE_TYPES: tuple[str, ...] = ("room", "furniture", "object")
ROOM, FURNITURE, OBJECT = 0, 1, 2
NUM_NODE_TYPES = len(NODE_TYPES)

# --- edge types -------------------------------------------------------------------------------
EDGE_TYPES: tuple[str, ...] = (
    "inRoom",
    "roomConnected",
    "onTop",
    "inside",
    "under",
    "rev_inRoom",
    "rev_onTop",
    "rev_inside",
    "rev_under",
)
(IN_ROOM, ROOM_CONNECTED, ON_TOP, INSIDE, UNDER, REV_IN_ROOM, REV_ON_TOP, REV_INSIDE, REV_UNDER) = range(
    len(EDGE_TYPES)
)
NUM_EDGE_TYPES = len(EDGE_TYPES)

# Edge type -> the edge type of the opposite direction.
REVERSE_EDGE_TYPE: dict[int, int] = {
    IN_ROOM: REV_IN_ROOM,
    REV_IN_ROOM: IN_ROOM,
    ROOM_CONNECTED: ROOM_CONNECTED,
    ON_TOP: REV_ON_TOP,
    REV_ON_TOP: ON_TOP,
    INSIDE: REV_INSIDE,
    REV_INSIDE: INSIDE,
    UNDER: REV_UNDER,
    REV_UNDER: UNDER,
}

# Edge type -> the legal (source node type, destination node type) pairs.
EDGE_TYPE_ENDPOINTS: dict[int, tuple[tuple[int, int], ...]] = {
    IN_ROOM: ((FURNITURE, ROOM), (OBJECT, ROOM)),
    ROOM_CONNECTED: ((ROOM, ROOM),),
    ON_TOP: ((OBJECT, FURNITURE),),
    INSIDE: ((OBJECT, FURNITURE),),
    UNDER: ((OBJECT, FURNITURE),),
    REV_IN_ROOM: ((ROOM, FURNITURE), (ROOM, OBJECT)),
    REV_ON_TOP: ((FURNITURE, OBJECT),),
    REV_INSIDE: ((FURNITURE, OBJECT),),
    REV_UNDER: ((FURNITURE, OBJECT),),
}

# --- HGT relation triples ---------------------------------------------------------------------
RELATION_TRIPLES: tuple[tuple[int, int, int], ...] = tuple(
    (src, et, dst) for et in range(NUM_EDGE_TYPES) for (src, dst) in EDGE_TYPE_ENDPOINTS[et]
)
NUM_RELATIONS = len(RELATION_TRIPLES)

RELATION_INDEX = np.full((NUM_EDGE_TYPES, NUM_NODE_TYPES, NUM_NODE_TYPES), -1, dtype=np.int32)
for _i, (_src, _et, _dst) in enumerate(RELATION_TRIPLES):
    RELATION_INDEX[_et, _src, _dst] = _i
RELATION_INDEX.setflags(write=False)
del _i, _src, _et, _dst


def relation_names() -> list[tuple[str, str, str]]:
    """The relation triples as (src type, edge type, dst type) names, PyG metadata style."""
    return [(NODE_TYPES[s], EDGE_TYPES[e], NODE_TYPES[d]) for (s, e, d) in RELATION_TRIPLES]


def check_graph_types(node_type, senders, receivers, edge_type, edge_mask) -> np.ndarray:
    """Indices of live edges whose (edge type, sender type, receiver type) is not a legal triple.

    Host-side (numpy) helper for the graph builder's tests; an empty result means every live edge
    is seen by the HGT.
    """
    node_type = np.asarray(node_type)
    src_t = node_type[np.asarray(senders)]
    dst_t = node_type[np.asarray(receivers)]
    rel = RELATION_INDEX[np.asarray(edge_type), src_t, dst_t]
    return np.nonzero(np.asarray(edge_mask, bool) & (rel < 0))[0]
