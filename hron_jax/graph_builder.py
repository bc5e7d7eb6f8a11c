"""Incremental scene graph with static shapes, built in pure JAX from segmentation every step.

Role: turn what the agent has seen so far into the padded `jraph.GraphsTuple` the models read
(paper, "Scene graph representation"; DESIGN.md step 4). Everything per step is jittable and
vmappable; the only state is one boolean per node:

    gb = GraphBuilder(scene, GraphConfig())
    disc = gb.reset(placement, pose)                                # bool[N_MAX]
    disc = gb.update(disc, placement, pose, frame.instance, frame.depth)
    g = gb.graph(disc, placement, pose)                             # jraph.GraphsTuple

Node table (N_MAX rows): every instance of the scene in the loader's order (rooms, furniture,
objects of the pool), then padding; `node_type_counts` (rooms, furniture, objects) is that static
layout, which lets the HGT layers slice the table by type instead of sorting it.
A node is *discovered* once its instance covers at least `GraphConfig.frame_min_pixels(W, H)`
pixels (`min_pixels` at the reference 128 x 128, scaled by the frame's pixel count, at least 1;
see GraphConfig) whose depth is below `detect_range` in one frame
(depth is the camera's z-depth along the optical axis, so the range is a slab in front of the
camera, not a sphere).
A room is discovered like any instance when enough of its floor is seen, or when the agent
stands in it (entered). Objects are nodes only while the episode uses them (`Placement.active`).

Edge table (E_MAX rows), directed and typed as `hron_jax.graph_types`:
    static:  furniture -inRoom-> room and the reverse; room -roomConnected-> room both ways;
    episode: for each pool object, object -onTop/inside/under-> furniture and the reverse (when it
             has a furniture), object -inRoom-> room and the reverse (the furniture's room, or the
             room containing the object when it has no furniture); masked when inactive.
An edge is live only when both ends are discovered. Dead and padded edges point at node 0 with
type 0 and mask False, so they can never leak into message passing (the models mask by
`edges['mask']`).

Node features (nodes dict of the GraphsTuple, shapes for one env):
    category  i32[N]    semantic class id (vocabulary.class_id)
    node_type i32[N]    0 room, 1 furniture, 2 object
    pos       f32[N,3]  AABB centre in the agent frame: x ahead, y left, z up from the floor (so the
                        agent knows where it is relative to each node)
    size      f32[N,3]  half extents of the world AABB (objects: their category's half extents);
                        a property of the instance, so it does not change when the agent turns
    mask      bool[N]   discovered and real
Rows that are not live (undiscovered, inactive objects, padding) have every feature zeroed: the
observation never carries the position of something the agent has not seen (the target included),
and outputs do not depend on N_MAX / E_MAX beyond the padded rows.
The scene has no articulated states (cavities are open, nothing toggles), so there is no state
feature beyond pose and size.
Pre-mapping (`premap=True`): rooms and furniture start discovered; objects never do.
"""

from __future__ import annotations

import dataclasses
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import jraph
import numpy as np

from . import graph_types as GT
from .scenes import vocabulary as V
from .scenes.loader import Scene, room_at


@dataclasses.dataclass(frozen=True)
class GraphConfig:
    """Static graph-builder settings (hashable).

    Discovery threshold: one frame of W x H pixels must show frame_min_pixels(W, H) = max(1,
    ceil(min_pixels * W * H / pixel_reference**2)) in-range pixels of an instance, i.e. the instance
    covers min_pixels / pixel_reference**2 of the frame, the same part of the field of view (same
    solid angle for one camera FoV) at every resolution. Default: 2 pixels of the paper's 128 x 128
    frame, so 2 at 128 x 128 (unchanged), 1 at 32 x 32 and 64 x 64 (was 2), 8 at 256 x 256.
    pixel_reference=None restores the earlier rule (min_pixels frame pixels at any size); in a run
    config (integers only) set env.graph.pixel_reference to the camera's side for the same effect.

    Why (`python -m hron_jax.bench discovery`: each house object on a table, approached head-on,
    median over 16 sub-pixel view offsets of the xy distance of first discovery): with 2 frame
    pixels a 32 x 32 agent first sees the apple / mug / book at 0.68 / 0.78 / 0.95 m, inside the 1 m
    success radius, and every category at 0.25-0.31 x its 128 x 128 distance (2.65-4.47 m): one
    32 x 32 pixel has the area of 16 at 128 x 128, so 2 of them ask 16x the reference's solid angle.
    With 1 pixel the 32 x 32 medians are 1.27-2.21 m (0.33-0.56 x), the 64 x 64 ones 2.53-4.05 m
    (0.66-0.99 x). A threshold cannot close the rest at 32 x 32: rays are point samples, and the
    reference's 2 pixels are 1/8 of a 32 x 32 pixel, below one sample, so an object that small shows
    up only where it happens to cover a pixel centre (which also lets one lucky ray discover a far
    object, up to the detect range). Matching 128 x 128 needs an instance image at that resolution;
    `update` takes any frame size and the threshold follows it.
    """

    max_nodes: int | None = None  # N_MAX; None = the scene's node count
    max_edges: int | None = None  # E_MAX; None = the scene's edge capacity
    min_pixels: int = 2  # pixels of one instance in one frame to discover it, counted at pixel_reference
    detect_range: float = 6.0  # m; farther pixels do not count (a detector's range)
    # Side of the square frame (pixel_reference**2 pixels) at which min_pixels is counted; a frame of
    # W x H pixels needs frame_min_pixels(W, H) of them. None: min_pixels counts the frame's own pixels.
    pixel_reference: int | None = 128

    def __post_init__(self):
        if self.min_pixels < 1:
            raise ValueError(f"min_pixels must be >= 1, got {self.min_pixels}")
        if self.pixel_reference is not None and self.pixel_reference < 1:
            raise ValueError(f"pixel_reference must be >= 1 or None, got {self.pixel_reference}")

    def frame_min_pixels(self, width: int, height: int) -> int:
        """Pixels of one instance a width x height frame needs: max(1, ceil(min_pixels * W * H /
        pixel_reference**2)), i.e. the instance covers at least min_pixels / pixel_reference**2 of
        the frame; min_pixels itself when pixel_reference is None."""
        if self.pixel_reference is None:
            return self.min_pixels
        return max(1, math.ceil(self.min_pixels * width * height / self.pixel_reference**2))


class Placement(NamedTuple):
    """Per-episode pose and relation of each pool object (O = scene.num_objects).

    active    bool[O]    used in this episode (target or distractor)
    pos       f32[O,3]   world centre
    furniture i32[O]     node index of the furniture it relates to (-1 if none)
    relation  i32[O]     vocabulary relation index (0 onTop, 1 inside, 2 under)
    """

    active: jax.Array
    pos: jax.Array
    furniture: jax.Array
    relation: jax.Array

    @staticmethod
    def empty(num_objects: int) -> Placement:
        return Placement(
            active=jnp.zeros((num_objects,), bool),
            pos=jnp.zeros((num_objects, 3)),
            furniture=jnp.full((num_objects,), -1, jnp.int32),
            relation=jnp.zeros((num_objects,), jnp.int32),
        )


# vocabulary relation index -> (forward edge type, reverse edge type)
_RELATION_EDGES = np.array(
    [[GT.ON_TOP, GT.REV_ON_TOP], [GT.INSIDE, GT.REV_INSIDE], [GT.UNDER, GT.REV_UNDER]], np.int32
)
assert V.RELATIONS == ("onTop", "inside", "under")


class GraphBuilder:
    """Static tables of one scene + pure functions `reset`, `update`, `graph`."""

    def __init__(self, scene: Scene, config: GraphConfig = GraphConfig(), premap: bool = False):
        """premap: rooms and furniture are discovered from the start (the paper's pre-mapping)."""
        self.config = config
        self.premap = premap
        n_real = scene.num_nodes
        self.num_objects = scene.num_objects
        self.object_offset = scene.num_rooms + scene.num_furniture
        # The node table's static type layout (rows by type, then padding), for the HGT layers.
        self.node_type_counts = (scene.num_rooms, scene.num_furniture, scene.num_objects)
        n_max = config.max_nodes or n_real
        if n_max < n_real:
            raise ValueError(
                f"GraphConfig.max_nodes={n_max} is smaller than the {n_real} instances of "
                f"{scene.path}; raise it or leave it None"
            )
        self.max_nodes = n_max

        def pad(a, fill=0):
            a = np.asarray(a)
            out = np.full((n_max,) + a.shape[1:], fill, a.dtype)
            out[:n_real] = a
            return out

        self.real = jnp.asarray(pad(np.ones(n_real, bool), False))
        self.node_type = jnp.asarray(pad(scene.node_type.astype(np.int32)))
        self.category = jnp.asarray(pad(scene.category.astype(np.int32)))
        self.static_center = jnp.asarray(pad(scene.aabb_center.astype(np.float32)))
        half = scene.aabb_half.astype(np.float32).copy()
        half[self.object_offset :] = V.OBJECT_HALF[scene.vocab_index[self.object_offset :]]
        self.static_half = jnp.asarray(pad(half))
        self.instance_room = jnp.asarray(pad(scene.instance_room.astype(np.int32), -1))
        self.is_room = self.real & (self.node_type == GT.ROOM)
        self.is_object = self.real & (self.node_type == GT.OBJECT)
        self.premap_mask = self.real & (self.node_type != GT.OBJECT)
        self.room_floors = jnp.asarray(scene.room_floors.astype(np.float32))

        # Static edges: furniture <-> its room, room <-> adjacent room.
        s, r, t = [], [], []
        for f in range(scene.num_rooms, self.object_offset):
            room = int(scene.instance_room[f])
            s += [f, room]
            r += [room, f]
            t += [GT.IN_ROOM, GT.REV_IN_ROOM]
        for a, b in zip(*np.nonzero(np.triu(scene.room_adjacency, 1))):
            s += [a, b]
            r += [b, a]
            t += [GT.ROOM_CONNECTED] * 2
        self.num_static_edges = len(s)
        e_cap = self.num_static_edges + 4 * self.num_objects
        e_max = config.max_edges or e_cap
        if e_max < e_cap:
            raise ValueError(
                f"GraphConfig.max_edges={e_max} is smaller than the {e_cap} possible edges of "
                f"{scene.path}; raise it or leave it None"
            )
        self.max_edges = e_max
        self.static_senders = jnp.asarray(np.array(s, np.int32))
        self.static_receivers = jnp.asarray(np.array(r, np.int32))
        self.static_types = jnp.asarray(np.array(t, np.int32))

    # ---- state ------------------------------------------------------------------------------
    def reset(self, placement: Placement, pose: jax.Array) -> jax.Array:
        """Discovered mask bool[N_MAX] at the start of an episode (before the first frame)."""
        del placement
        disc = self.premap_mask if self.premap else jnp.zeros_like(self.real)
        return disc | self._agent_room(pose)

    def update(
        self,
        discovered: jax.Array,
        placement: Placement,
        pose: jax.Array,
        instance: jax.Array,
        depth: jax.Array,
    ) -> jax.Array:
        """Add what one frame shows. instance i32[H,W] (-1 none), depth f32[H,W] (m)."""
        valid = (instance >= 0) & (depth < self.config.detect_range)
        idx = jnp.where(valid, instance, 0).reshape(-1)
        counts = jnp.zeros((self.max_nodes,), jnp.int32).at[idx].add(valid.reshape(-1).astype(jnp.int32))
        seen = counts >= self.config.frame_min_pixels(instance.shape[-1], instance.shape[-2])
        return (discovered | seen | self._agent_room(pose)) & self.real & self._node_active(placement)

    def _agent_room(self, pose):
        room = room_at(self.room_floors, pose[:2], jnp)
        return self.is_room & (jnp.arange(self.max_nodes) == room)

    def _node_active(self, placement: Placement):
        obj_active = (
            jnp.zeros((self.max_nodes,), bool)
            .at[self.object_offset + jnp.arange(self.num_objects)]
            .set(placement.active)
        )
        return ~self.is_object | obj_active

    # ---- output -----------------------------------------------------------------------------
    def graph(self, discovered: jax.Array, placement: Placement, pose: jax.Array) -> jraph.GraphsTuple:
        """The padded scene graph seen from `pose` (x, y, yaw)."""
        obj = self.object_offset + jnp.arange(self.num_objects)
        obj_pos = placement.pos.astype(jnp.float32)
        center = self.static_center.at[obj].set(obj_pos)
        c, s_ = jnp.cos(pose[2]), jnp.sin(pose[2])
        d = center[:, :2] - pose[:2]
        pos = jnp.stack([c * d[:, 0] + s_ * d[:, 1], -s_ * d[:, 0] + c * d[:, 1], center[:, 2]], -1)
        mask = discovered & self.real & self._node_active(placement)

        # Episode edges of the pool objects: 4 per object. The relation pair needs a furniture; the
        # inRoom pair uses the furniture's room, or the room under the object when it has none (a
        # placed object is always in some room, so it must not float unconnected).
        has_furn = placement.furniture >= 0
        furn = jnp.maximum(placement.furniture, 0)
        room = jnp.where(has_furn, self.instance_room[furn], room_at(self.room_floors, obj_pos[:, :2], jnp))
        rel = jnp.asarray(_RELATION_EDGES)[jnp.clip(placement.relation, 0, 2)]
        room_ok = placement.active & (room >= 0)
        room = jnp.maximum(room, 0)
        dyn_s = jnp.stack([obj, furn, obj, room], -1).reshape(-1)
        dyn_r = jnp.stack([furn, obj, room, obj], -1).reshape(-1)
        dyn_t = jnp.stack(
            [rel[:, 0], rel[:, 1], jnp.full_like(obj, GT.IN_ROOM), jnp.full_like(obj, GT.REV_IN_ROOM)], -1
        ).reshape(-1)
        rel_ok = placement.active & has_furn
        dyn_ok = jnp.stack([rel_ok, rel_ok, room_ok, room_ok], -1).reshape(-1)

        n_pad = self.max_edges - self.num_static_edges - 4 * self.num_objects
        zeros = jnp.zeros((n_pad,), jnp.int32)
        senders = jnp.concatenate([self.static_senders, dyn_s, zeros])
        receivers = jnp.concatenate([self.static_receivers, dyn_r, zeros])
        etype = jnp.concatenate([self.static_types, dyn_t, zeros])
        ok = jnp.concatenate([jnp.ones((self.num_static_edges,), bool), dyn_ok, jnp.zeros((n_pad,), bool)])
        live = ok & mask[senders] & mask[receivers]
        senders = jnp.where(live, senders, 0)
        receivers = jnp.where(live, receivers, 0)
        etype = jnp.where(live, etype, 0)
        # Zero every feature of rows that are not live (see the module docstring: no leaks).
        m3 = mask[:, None]
        return jraph.GraphsTuple(
            nodes={
                'category': jnp.where(mask, self.category, 0),
                'node_type': jnp.where(mask, self.node_type, 0),
                'pos': jnp.where(m3, pos, 0.0),
                'size': jnp.where(m3, self.static_half, 0.0),
                'mask': mask,
            },
            edges={'edge_type': etype, 'mask': live},
            senders=senders,
            receivers=receivers,
            n_node=jnp.array([self.max_nodes], jnp.int32),
            n_edge=jnp.array([self.max_edges], jnp.int32),
            globals=None,
        )
