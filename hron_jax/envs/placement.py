"""Episode sampling for the navigation tasks: goals, stable object poses, distractors, clutter, starts.

Role
----
Everything the directed and exploratory tasks draw at reset, split into a host-side precomputation
(`build_tables`, once per scene) and pure, jittable, vmappable samplers over the resulting
`EpisodeTables` (`sample_exploratory`, `sample_directed`). No geodesic field is ever computed after
construction: targets are only ever placed at a fixed set of candidate points whose fields are
precomputed here, so resets and steps only look fields up.

Candidate points and fields
---------------------------
A relation slot (docs/scene_format.md) is a box whose bottom face is the support surface and whose
xy extent bounds the object's centre. Each slot gets `slot_grid`^2 candidate xy points: the centres
of a slot_grid x slot_grid grid over the slot's xy extent shrunk by the largest half extent of any
object category that fits the slot, so *every* fitting object may use *every* point of its slot
(the object's footprint stays inside the slot's extent). An object of half extents h placed at a
point p rests at z = support + h_z, i.e. exactly on the support surface and, since 2 h_z <= slot
height for a fitting object, within the clearance of inside / under slots. Points are deduplicated
across slots (slots stacked on one piece of furniture often share xy), and for each unique point
`success_fields` (geodesic.target_fields, minus seeds that cannot reach the disk) gives the distance
field to its success region (free cells within `success_distance` of it), stored as `field_dtype`
(float16 by default: at most ~1 cm of rounding below 16 m, half the memory of float32).

Reachability: the "main" free space is what the agent can reach from the scene's `start:0` site
(or, without one, from the most central free cell of the largest room). A candidate point is usable
only when a main free cell lies `robust_margin` inside its success disk (so success never hinges
on a cm-precise move into a sliver of the disk), a slot only when it has a usable point for the
object, a goal only when one of its slots is usable (so only satisfiable goals are sampled), and
agents only start on main free cells.

Samplers (one episode; jit / vmap them)
---------------------------------------
`sample_exploratory(key, tables, num_distractors, min_start_distance, num_clutter)` -> Episode: a
uniformly random satisfiable goal (object, relation, furniture, room) of the scene's goal table, a
uniform slot realising it and a uniform usable point of that slot, a random pool instance of the
object; start in a uniformly random room on a uniformly random main free cell of it whose geodesic
distance to the success region exceeds `min_start_distance` (by rejection, see _start_cell),
uniform yaw.
`sample_directed(key, tables, num_distractors, num_clutter)` -> Episode: a random "pair" (object
category of DIRECTED_OBJECTS, one slot on each half of the mirror plane x = centre of the scene's
bounds, furniture of the same category, different relations); both halves get an instance of the
object, the goal (object, relation, furniture, no room) names one of them at random, the other is
the wrong object. Fixed start at `start:0`. The paper's directed task spawns a bowl, a gym shoe or
an apple, so pairs are built for DIRECTED_OBJECTS only (build_tables' `directed_objects`).
Distractors (num_distractors > 0): pool instances other than the target (and wrong object), the
target's own category first, then random other categories, each in a random free slot (one object
per slot, so objects never overlap) that fits it. Instances that find no slot stay parked
(inactive).
Clutter (num_clutter > 0; DEFAULT_NUM_CLUTTER = 64 for the exploratory task, 0 for the directed
one, whose symmetric room is the paper's uncluttered set-up): the house's other objects, so that a
fully explored graph has ~100 nodes with many objects like the paper's Wainscott_0_int graphs
(where task-driven attention matters), not rooms + furniture + one target. After the target, wrong
object and distractors, `num_clutter` more pool entries, a uniformly random subset of the free ones
(the shipped houses' pools hold 9 of each of the 8 house objects, so every category, the goal's
included, is drawn about equally often), go one per free usable slot that fits them, at a uniform
usable candidate point, in every room and relation. The assignment is parallel over entries and
slots: one round per pool category (the goal's first, then those with the fewest usable slots
first), in which the r-th chosen entry of the category takes the r-th eligible slot in the
episode's random slot order (prefix sums and scatters, no sort, no step per object: the sampler
runs at every env step for the auto-reset). Clutter of the goal's category (about 7 an episode in
the shipped houses) are the relational confounders: anywhere but in a slot satisfying the goal
tuple, so for "apple on a table in the kitchen" there are apples inside kitchen cabinets, on tables
of other rooms, under the kitchen table..., and the goal is resolved only by checking relation,
furniture and room. Their slots are uniform among the free ones like every other clutter object's
(preferring "near-miss" slots would make where the goal's category lies a cue to the goal).
Entries that find no slot stay parked. The clutter's randomness comes from fold_in(key, 1), so a
key's goal, target, distractors and start do not depend on num_clutter. A fully explored graph
(rooms + furniture + active objects) of house.xml has 47 + 1 + 64 = 112 nodes, of the generated
houses 98-104 (`python -m hron_jax.scenes --stats SCENE`).
Goal uniqueness (both tasks, distractors and clutter alike): an instance of the goal's category
never goes into a slot that satisfies the goal tuple (same relation, furniture category and, when
the goal has one, room category), so exactly one active object satisfies it: the target.

Episode fields (O = scene.num_objects pool entries in node order, pool entry j = node R + F + j):
    placement   graph_builder.Placement (active bool[O], pos f32[O,3], furniture i32[O] node,
                relation i32[O])
    slot        i32[O] slot of each pool object, -1 when inactive
    goal        i32[4] vocabulary indices (object, relation, furniture, room); room -1 (directed)
    target      i32 pool entry of the target; target_xy f32[2]; target_field i32 row of `fields`
    wrong       i32 pool entry of the directed task's wrong object (-1: none); wrong_xy f32[2]
    pose        f32[3] agent start (x, y, yaw)
"""

from __future__ import annotations

import dataclasses
from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from hron_jax import geodesic as G
from hron_jax.graph_builder import Placement
from hron_jax.scenes import vocabulary as V
from hron_jax.scenes.loader import Scene

_NUM_OBJ = len(V.OBJECTS)

# The paper's directed task spawns one of these (paper, "Experimental setup").
DIRECTED_OBJECTS: tuple[str, ...] = ('bowl', 'gym_shoe', 'apple')
# Clutter objects of an exploratory episode (see the module docstring): with the shipped houses'
# 26-38 pieces of furniture in 7-9 rooms this gives 98-112 nodes when fully explored.
DEFAULT_NUM_CLUTTER = 64
# fold_in stream of the clutter's key, so the other draws of a key do not depend on num_clutter.
_CLUTTER_STREAM = 1


@dataclasses.dataclass(frozen=True)
class PlacementConfig:
    """How candidate target points and their geodesic fields are laid out (hashable).

    The success radius and the agent's size are not here: they belong to the task and the
    simulator (NavConfig.success_distance, SimConfig.radius / height) and are passed to
    `build_tables` from there, so each lives in one place."""

    slot_grid: int = 2  # candidate points per slot = slot_grid ** 2
    robust_margin: float = 0.25  # m; a usable target has a main free cell this far inside its disk
    cell_size: float = 0.1  # occupancy grid (m)
    # The grid is inflated by the capsule radius + clearance: contacts (2 cm margin) keep the capsule
    # 0-3 cm off surfaces, and cells free on a grid inflated by the bare radius but not physically
    # reachable became false minima of the fields (measured: an oracle stuck 2.5 cm outside the
    # success disk in a dead end next to a wall whose other side held the target).
    clearance: float = 0.03
    field_dtype: str = 'float16'  # 'float16' | 'float32' (bfloat16 is too coarse: 12 cm at 16 m)
    stencil: int = 48  # geodesic stencil (see hron_jax.geodesic)


class Episode(NamedTuple):
    placement: Placement
    slot: jax.Array
    goal: jax.Array
    target: jax.Array
    target_xy: jax.Array
    target_field: jax.Array
    wrong: jax.Array
    wrong_xy: jax.Array
    pose: jax.Array


@jax.tree_util.register_static
@dataclasses.dataclass(frozen=True, eq=False)
class EpisodeTables:
    """Static per-scene tables (numpy; they become constants under jit). See build_tables."""

    grid: G.OccupancyGrid
    point_xy: np.ndarray  # f32[P, 2] unique candidate target points
    fields: np.ndarray  # f16/f32[P, H, W] geodesic distance to each point's success region
    slot_point: np.ndarray  # i32[S, K] point index of each slot's candidates (0 where unused)
    slot_point_ok: np.ndarray  # bool[S, K] candidate exists and its success region is reachable
    slot_usable: np.ndarray  # bool[S, NUM_OBJ] the object fits the slot and it has a usable point
    slot_support: np.ndarray  # f32[S] z of the support surface (slot bottom)
    slot_furniture: np.ndarray  # i32[S] furniture node
    slot_relation: np.ndarray  # i32[S]
    slot_furn_cat: np.ndarray  # i32[S] furniture vocabulary index
    slot_room_cat: np.ndarray  # i32[S] room vocabulary index of the furniture's room
    goals: np.ndarray  # i32[Q, 4] the scene's goal table
    goal_ok: np.ndarray  # bool[Q] satisfiable (some slot usable for the goal's object)
    goal_slots: np.ndarray  # bool[Q, S] usable slots realising each goal
    pairs: np.ndarray  # i32[P2, 3] directed pairs (object of directed_objects, left slot, right slot)
    clutter_cats: np.ndarray  # i32[C] object categories in the pool, fewest usable slots first
    obj_cat: np.ndarray  # i32[O] object vocabulary index of each pool entry
    obj_half: np.ndarray  # f32[O, 3] half extents of each pool entry
    room_cell: np.ndarray  # i32[H*W] room of each reachable free cell, -1 elsewhere
    room_cells: np.ndarray  # i32[R', C] flat cells of each room that has main free cells (padded)
    room_ncells: np.ndarray  # i32[R'] how many
    point_far_cell: np.ndarray  # i32[P] the main cell farthest (geodesically) from each point
    num_rooms: int
    start_pose: np.ndarray  # f32[3] start:0 (x, y, yaw), or the reference cell with yaw 0
    reach: np.ndarray  # f32[H, W] geodesic distance from the reference point (diagnostics)

    @property
    def num_points(self) -> int:
        return int(self.point_xy.shape[0])

    @property
    def fields_nbytes(self) -> int:
        return int(self.fields.nbytes)


def _reachable_init(grid: G.OccupancyGrid, target_xy, success_radius: float):
    """geodesic.success_init without band cells whose straight line to the success disk is blocked.

    success_init seeds free cells just outside the disk with their straight-line distance to it;
    near a wall or furniture that line can end inside an (inflated) obstacle, e.g. behind the wall
    of the room next to the target, which turns such cells into false minima of the field (an
    oracle descending it gets stuck there, and d0 is underestimated). The segment is at most
    1.5 cells long, so checking a few points on it against the fine grid is enough."""
    base = G.success_init(grid, target_xy, success_radius)
    c = grid.centres()
    t = jnp.asarray(target_xy, jnp.float32)
    d = jnp.linalg.norm(c - t, axis=-1, keepdims=True)
    step = (t - c) / jnp.maximum(d, 1e-6) * jnp.maximum(d - success_radius, 0.0)
    los = grid.los_grid()
    ok = jnp.ones(base.shape, bool)
    for s in (0.25, 0.5, 0.75, 1.0):
        ok = ok & los.is_free(c + s * step)
    return jnp.where((base > 0) & ~ok, jnp.inf, base)


@partial(jax.jit, static_argnames=('success_radius', 'stencil'))
def success_fields(grid: G.OccupancyGrid, targets_xy, success_radius: float = 1.0, *, stencil: int = 48):
    """f32[N, H, W] geodesic distance (m) to the success disk of each target xy f32[N, 2]; as
    geodesic.target_fields but with _reachable_init (the inits are built one target at a time to
    keep memory at one grid of segment samples)."""
    inits = jax.lax.map(lambda t: _reachable_init(grid, t, success_radius), jnp.asarray(targets_xy))
    return G.grid_distance_fields(grid, inits, stencil=stencil)


def _slot_points(scene: Scene, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Candidate xy (S, n*n, 2) per slot and whether any object fits the slot (S,)."""
    half = V.OBJECT_HALF
    frac = (2.0 * (np.arange(n) + 0.5) / n - 1.0) if n > 1 else np.zeros(1)
    fu, fv = np.meshgrid(frac, frac, indexing='ij')
    frac2 = np.stack([fu.ravel(), fv.ravel()], -1)  # (K, 2)
    pts, any_fit = [], []
    for k in range(scene.num_slots):
        fits = [o for o in range(_NUM_OBJ) if np.all(half[o] <= scene.slot_half[k] + 1e-9)]
        any_fit.append(bool(fits))
        hmax = half[fits, :2].max(0) if fits else np.zeros(2)
        rng = np.maximum(scene.slot_half[k, :2] - hmax, 0.0)
        pts.append(scene.slot_center[k, :2] + frac2 * rng)
    return np.array(pts, np.float64).reshape(scene.num_slots, len(frac2), 2), np.array(any_fit)


def _reference_cell(scene: Scene, grid: G.OccupancyGrid) -> tuple[np.ndarray, float]:
    """Reference xy for the main free space and its yaw: start:0, or the largest room's most central
    free cell."""
    if len(scene.start_pos):
        return np.asarray(scene.start_pos[0, :2], np.float64), float(scene.start_yaw[0])
    free = np.asarray(grid.free)
    centres = np.asarray(grid.centres())
    rooms = scene.room_at(centres)
    big = int(np.argmax(scene.room_area()))
    fl = scene.room_floors[big][scene.room_floor_valid[big]]
    mid = np.array([(fl[:, 0].min() + fl[:, 2].max()) / 2, (fl[:, 1].min() + fl[:, 3].max()) / 2])
    ok = free & (rooms == big)
    d = np.where(ok, np.linalg.norm(centres - mid, axis=-1), np.inf)
    i, j = np.unravel_index(np.argmin(d), d.shape)
    return centres[i, j].astype(np.float64), 0.0


def build_tables(
    scene: Scene,
    model,
    config: PlacementConfig = PlacementConfig(),
    *,
    success_distance: float = 1.0,
    agent_radius: float = 0.2,
    agent_height: float = 1.2,
    directed_objects: tuple[str, ...] = DIRECTED_OBJECTS,
) -> EpisodeTables:
    """Host-side precomputation for one scene (see the module docstring).

    model: the compiled MuJoCo model the agent moves in (hron_jax.sim.Simulator.mj_model), whose
    collision bits define the obstacles; its occupancy grid is built at `config.cell_size`,
    inflated by agent_radius + config.clearance. success_distance: xy radius of the success region.
    directed_objects: the object categories of the directed task's pairs (vocabulary names).
    """
    if config.field_dtype not in ('float16', 'float32'):
        raise ValueError(f"field_dtype must be 'float16' or 'float32', got {config.field_dtype!r}")
    grid = G.occupancy_grid(
        model,
        config=G.GridConfig(
            cell_size=config.cell_size,
            agent_radius=agent_radius + config.clearance,
            agent_height=agent_height,
        ),
    )
    free = np.asarray(grid.free)
    h, w = free.shape

    # Main free space: reachable from the reference point.
    ref_xy, ref_yaw = _reference_cell(scene, grid)
    ref_rc = np.asarray(grid.world_to_cell(ref_xy))
    if not (0 <= ref_rc[0] < h and 0 <= ref_rc[1] < w and free[ref_rc[0], ref_rc[1]]):
        raise ValueError(f'{scene.path}: the reference start {ref_xy} is not on a free cell')
    src = np.zeros((1, h, w), bool)
    src[0, ref_rc[0], ref_rc[1]] = True
    reach = np.asarray(G.grid_distance_fields(grid, src, stencil=config.stencil))[0]
    main = np.isfinite(reach)

    # Candidate points, deduplicated to the millimetre.
    pts, any_fit = _slot_points(scene, config.slot_grid)
    s, k = pts.shape[:2]
    keys = np.round(pts.reshape(-1, 2) * 1000).astype(np.int64)
    uniq, inv = np.unique(keys, axis=0, return_inverse=True)
    point_xy = (uniq / 1000.0).astype(np.float32)
    fields = np.asarray(success_fields(grid, jnp.asarray(point_xy), success_distance, stencil=config.stencil))
    # A point is usable when a main free cell lies robust_margin inside its success disk. Points
    # whose disk meets free space only in a sliver (an object deep under a bed, or behind a wall)
    # need cm-precise final moves that 0.2 m steps and 30 deg turns cannot reliably make.
    centres = np.asarray(grid.centres())[main]
    inner = success_distance - config.robust_margin
    point_ok = np.array(
        [(np.linalg.norm(centres - q, axis=-1) <= inner).any() for q in point_xy], bool
    ).reshape(-1)
    slot_point = inv.reshape(s, k).astype(np.int32)
    slot_point_ok = point_ok[slot_point] & any_fit[:, None]

    fits = np.all(V.OBJECT_HALF[None, :, :] <= scene.slot_half[:, None, :] + 1e-9, -1)  # (S, NO)
    slot_usable = fits & slot_point_ok.any(1)[:, None]
    furn = scene.slot_furniture.astype(np.int32)
    slot_furn_cat = scene.vocab_index[furn].astype(np.int32)
    slot_room_cat = scene.vocab_index[scene.instance_room[furn]].astype(np.int32)

    goals = scene.goals.astype(np.int32).reshape(-1, 4)
    goal_slots = (
        scene.goal_slots.astype(bool) & slot_usable[:, goals[:, 0]].T
        if len(goals)
        else np.zeros((0, s), bool)
    )
    goal_ok = goal_slots.any(1)

    off = scene.num_rooms + scene.num_furniture
    obj_cat = scene.vocab_index[off:].astype(np.int32)
    obj_half = V.OBJECT_HALF[obj_cat].astype(np.float32)
    pool_count = np.bincount(obj_cat, minlength=_NUM_OBJ)

    # Directed pairs: same furniture category on both halves of the mirror plane, different relations.
    mid_x = 0.5 * (scene.bounds[0, 0] + scene.bounds[1, 0])
    side = np.sign(scene.aabb_center[furn, 0] - mid_x)
    pairs = []
    for o in sorted(V.index('object', name) for name in directed_objects):
        if pool_count[o] < 2:
            continue
        for a in np.nonzero((side < 0) & slot_usable[:, o])[0]:
            for b in np.nonzero((side > 0) & slot_usable[:, o])[0]:
                if slot_furn_cat[a] == slot_furn_cat[b] and scene.slot_relation[a] != scene.slot_relation[b]:
                    pairs.append((o, a, b))
    pairs = np.array(pairs, np.int32).reshape(-1, 3)
    # Clutter rounds: the pool's categories, those with the fewest usable slots first.
    in_pool = np.nonzero(pool_count > 0)[0]
    clutter_cats = in_pool[np.argsort(slot_usable[:, in_pool].sum(0), kind='stable')].astype(np.int32)

    centres = np.asarray(grid.centres()).reshape(-1, 2)
    rooms = scene.room_at(centres)
    room_cell = np.where(main.reshape(-1) & free.reshape(-1), rooms, -1).astype(np.int32)
    per_room = [np.nonzero(room_cell == r)[0] for r in range(scene.num_rooms)]
    per_room = [c for c in per_room if len(c)]
    room_cells = np.zeros((len(per_room), max(len(c) for c in per_room)), np.int32)
    for r, c in enumerate(per_room):
        room_cells[r, : len(c)] = c
    room_ncells = np.array([len(c) for c in per_room], np.int32)
    flat = fields.reshape(len(fields), -1)
    point_far_cell = np.argmax(np.where(main.reshape(-1) & np.isfinite(flat), flat, -1.0), -1)

    dtype = np.float16 if config.field_dtype == 'float16' else np.float32
    # Keep inf as inf in float16 (finite distances here are < 65504 m).
    return EpisodeTables(
        grid=grid,
        point_xy=point_xy,
        fields=fields.astype(dtype),
        slot_point=slot_point,
        slot_point_ok=slot_point_ok,
        slot_usable=slot_usable,
        slot_support=(scene.slot_center[:, 2] - scene.slot_half[:, 2]).astype(np.float32),
        slot_furniture=furn,
        slot_relation=scene.slot_relation.astype(np.int32),
        slot_furn_cat=slot_furn_cat,
        slot_room_cat=slot_room_cat,
        goals=goals,
        goal_ok=goal_ok,
        goal_slots=goal_slots,
        pairs=pairs,
        clutter_cats=clutter_cats,
        obj_cat=obj_cat,
        obj_half=obj_half,
        room_cell=room_cell,
        room_cells=room_cells,
        room_ncells=room_ncells,
        point_far_cell=point_far_cell.astype(np.int32),
        num_rooms=scene.num_rooms,
        start_pose=np.array([ref_xy[0], ref_xy[1], ref_yaw], np.float32),
        reach=reach,
    )


# ------------------------------------------------------------------------------------------------
# Jittable samplers
# ------------------------------------------------------------------------------------------------


def _choice(key, mask):
    """Uniform index among True entries of a bool vector (index 0 if none)."""
    logits = jnp.where(mask, 0.0, -jnp.inf)
    g = jax.random.gumbel(key, mask.shape)
    return jnp.argmax(jnp.where(mask, logits + g, -jnp.inf)).astype(jnp.int32)


def field(tables: EpisodeTables, index) -> jax.Array:
    """f32[H, W] geodesic field of candidate point `index` (a lookup, never a solve)."""
    return jnp.asarray(tables.fields)[index].astype(jnp.float32)


def _point_in_slot(key, t: EpisodeTables, slot):
    """(xy f32[2], point index i32) uniform among the slot's usable candidate points."""
    kk = _choice(key, jnp.asarray(t.slot_point_ok)[slot])
    p = jnp.asarray(t.slot_point)[slot, kk]
    return jnp.asarray(t.point_xy)[p], p


def _object_pos(t: EpisodeTables, entry, slot, xy):
    z = jnp.asarray(t.slot_support)[slot] + jnp.asarray(t.obj_half)[entry, 2]
    return jnp.concatenate([xy, z[None]])


def _satisfies(t: EpisodeTables, goal):
    """bool[S]: slots where an object of the goal's category satisfies the goal tuple."""
    room_ok = (goal[3] < 0) | (jnp.asarray(t.slot_room_cat) == goal[3])
    return (jnp.asarray(t.slot_relation) == goal[1]) & (jnp.asarray(t.slot_furn_cat) == goal[2]) & room_ok


def _place(t: EpisodeTables, pl: Placement, slots, entry, slot, xy):
    pos = _object_pos(t, entry, slot, xy)
    pl = Placement(
        active=pl.active.at[entry].set(True),
        pos=pl.pos.at[entry].set(pos),
        furniture=pl.furniture.at[entry].set(jnp.asarray(t.slot_furniture)[slot]),
        relation=pl.relation.at[entry].set(jnp.asarray(t.slot_relation)[slot]),
    )
    return pl, slots.at[entry].set(slot)


def _distractors(key, t: EpisodeTables, pl: Placement, slots, used, goal, exclude, num: int):
    """Place up to `num` distractors (see the module docstring); exclude bool[O] entries in use,
    used bool[S] slots in use. Returns (placement, slots, used)."""
    if num <= 0:
        return pl, slots, used
    o_count = t.obj_cat.shape[0]
    num = min(num, o_count)
    k_order, k_place = jax.random.split(key)
    cat = jnp.asarray(t.obj_cat)
    # Same category as the goal object first (the relational confounders), then the rest, each
    # group in random order.
    prio = (cat != goal[0]).astype(jnp.float32) + 0.5 * jax.random.uniform(k_order, (o_count,))
    prio = jnp.where(exclude, jnp.inf, prio)
    order = jnp.argsort(prio)[:num]
    valid = jnp.isfinite(prio[order])
    bad_for_goal = _satisfies(t, goal)

    def body(carry, x):
        pl, slots, used = carry
        entry, ok, key = x
        k_slot, k_pt = jax.random.split(key)
        c = cat[entry]
        elig = jnp.asarray(t.slot_usable)[:, c] & ~used & ~((c == goal[0]) & bad_for_goal)
        place = ok & elig.any()
        slot = _choice(k_slot, elig)
        xy, _ = _point_in_slot(k_pt, t, slot)
        pl2, slots2 = _place(t, pl, slots, entry, slot, xy)
        pl = jax.tree.map(lambda a, b: jnp.where(place, a, b), pl2, pl)
        slots = jnp.where(place, slots2, slots)
        used = used | (place & (jnp.arange(used.shape[0]) == slot))
        return (pl, slots, used), None

    keys = jax.random.split(k_place, num)
    (pl, slots, used), _ = jax.lax.scan(body, (pl, slots, used), (order, valid, keys))
    return pl, slots, used


def _ranks(u):
    """i32[n]: the rank of each entry of u f32[n] in ascending order, ties broken by index (a
    permutation of 0..n-1); n^2 compares, much cheaper than a sort at these sizes on XLA:CPU."""
    i = jnp.arange(u.shape[0])
    less = (u[None, :] < u[:, None]) | ((u[None, :] == u[:, None]) & (i[None, :] < i[:, None]))
    return less.sum(1).astype(jnp.int32)


def _clutter(key, t: EpisodeTables, pl: Placement, slots, used, goal, num: int):
    """Place up to `num` clutter objects (see the module docstring) among the pool entries that are
    not active yet, one per free usable slot (used bool[S] marks the slots in use).

    Parallel over entries and slots, and without sorts (XLA:CPU sorts cost ~1.5-4 ms per batch of
    64 each, and this runs at every env step for the auto-reset): random orders are pairwise ranks
    (_ranks). One round per object category (a lax.scan over clutter_cats), in which the r-th chosen
    entry of the category takes the r-th eligible slot of the episode's random slot order (prefix
    sums as matmuls and two scatters)."""
    o_count, s_count = t.obj_cat.shape[0], t.slot_point.shape[0]
    num = min(num, o_count)
    if num <= 0:
        return pl, slots
    # One draw for everything (each threefry call adds compile time): entries, slot order, points.
    u = jax.random.uniform(key, (2 * o_count + s_count,))
    u_pick, u_order, u_pt = u[:o_count], u[o_count : o_count + s_count], u[o_count + s_count :]
    cat = jnp.asarray(t.obj_cat)
    # A uniformly random subset of `num` free entries (active ones rank last).
    chosen = (_ranks(jnp.where(pl.active, 2.0, u_pick)) < num) & ~pl.active
    # The episode's random slot order: slots are visited by rank, via ranked[j] = j-th slot.
    rank = _ranks(u_order)
    ranked = jnp.zeros((s_count,), jnp.int32).at[rank].set(jnp.arange(s_count, dtype=jnp.int32))
    usable = jnp.asarray(t.slot_usable)[ranked]  # (S, NUM_OBJ), in that order
    bad = _satisfies(t, goal)[ranked]
    cats = jnp.asarray(t.clutter_cats)
    # The goal's category first (the confounders never lack a slot), the others in the static order.
    first = jnp.argmax(cats == goal[0])
    i = jnp.arange(cats.shape[0])
    cats = jnp.where(i == 0, cats[first], jnp.where(i <= first, jnp.roll(cats, 1), cats))
    # Inclusive prefix sums as matmuls of 0/1 values (exact in f32, TF32 too; cheaper to compile
    # than cumsum).
    tri_o = jnp.asarray(np.tril(np.ones((o_count, o_count), np.float32)))
    tri_s = jnp.asarray(np.tril(np.ones((s_count, s_count), np.float32)))

    def round_(carry, c):
        at, taken = carry  # at: position (in the order) of each entry's slot, -1 none; taken: by position
        members = chosen & (cat == c)
        r = (tri_o @ members.astype(jnp.float32)).astype(jnp.int32) - 1  # rank within the category
        elig = usable[:, c] & ~taken & ~((c == goal[0]) & bad)
        pos = (tri_s @ elig.astype(jnp.float32)).astype(jnp.int32) - 1  # rank among eligible slots
        nth = (  # nth[k] = position of the k-th eligible slot
            jnp.zeros((s_count,), jnp.int32)
            .at[jnp.where(elig, pos, s_count)]
            .set(jnp.arange(s_count, dtype=jnp.int32), mode='drop')
        )
        ok = members & (r < pos[-1] + 1)
        at = jnp.where(ok, nth[jnp.clip(r, 0, s_count - 1)], at)
        hit = jnp.zeros((s_count,), bool).at[jnp.where(ok, at, s_count)].set(True, mode='drop')
        return (at, taken | hit), None

    init = (jnp.full((o_count,), -1, jnp.int32), used[ranked])
    (at, _), _ = jax.lax.scan(round_, init, cats)
    slot_of = jnp.where(at >= 0, ranked[jnp.maximum(at, 0)], -1)
    place = slot_of >= 0
    slot_c = jnp.maximum(slot_of, 0)
    # A uniform usable candidate point of each slot: the j-th True of slot_point_ok[slot].
    ok_pts = jnp.asarray(t.slot_point_ok)[slot_c]  # (O, K)
    n_ok = ok_pts.sum(-1)
    j = jnp.minimum((u_pt * n_ok).astype(jnp.int32), n_ok - 1)
    kk = jnp.argmax(ok_pts & (jnp.cumsum(ok_pts, -1) - 1 == j[:, None]), -1)
    xy = jnp.asarray(t.point_xy)[jnp.asarray(t.slot_point)[slot_c, kk]]
    z = jnp.asarray(t.slot_support)[slot_c] + jnp.asarray(t.obj_half)[:, 2]
    pos = jnp.concatenate([xy, z[:, None]], -1)
    pl = Placement(
        active=pl.active | place,
        pos=jnp.where(place[:, None], pos, pl.pos),
        furniture=jnp.where(place, jnp.asarray(t.slot_furniture)[slot_c], pl.furniture),
        relation=jnp.where(place, jnp.asarray(t.slot_relation)[slot_c], pl.relation),
    )
    return pl, jnp.where(place, slot_of, slots)


def _empty(t: EpisodeTables):
    o = t.obj_cat.shape[0]
    return Placement.empty(o), jnp.full((o,), -1, jnp.int32)


def _start_cell(key, t: EpisodeTables, point, min_distance: float, tries: int = 16):
    """Flat index of a start cell: a uniformly random room, then a uniformly random main free cell
    of it, kept if its geodesic distance to the point's success region exceeds min_distance; the
    first of `tries` such draws that is kept (else the point's farthest cell). Rejection keeps the
    cost at a few lookups: a categorical over all H*W cells would draw H*W random numbers per
    reset, which dominated the auto-reset's cost (resets are evaluated at every step)."""
    k_room, k_idx = jax.random.split(key)
    nrooms = t.room_ncells.shape[0]
    room = jax.random.randint(k_room, (tries,), 0, nrooms)
    n = jnp.asarray(t.room_ncells)[room]
    idx = jnp.minimum((jax.random.uniform(k_idx, (tries,)) * n).astype(jnp.int32), n - 1)
    cells = jnp.asarray(t.room_cells)[room, idx]
    w = t.grid.free.shape[1]
    d = jnp.asarray(t.fields)[point, cells // w, cells % w].astype(jnp.float32)
    ok = (d > min_distance) & jnp.isfinite(d)
    first = jnp.argmax(ok)
    return jnp.where(ok[first], cells[first], jnp.asarray(t.point_far_cell)[point])


def sample_exploratory(
    key,
    t: EpisodeTables,
    num_distractors: int = 0,
    min_start_distance: float = 1.0,
    num_clutter: int = DEFAULT_NUM_CLUTTER,
) -> Episode:
    """One exploratory-task episode (module docstring). num_distractors and num_clutter are static.
    The clutter draws from fold_in(key, _CLUTTER_STREAM): every other draw of a key (goal, target,
    distractors, start) is the same for any num_clutter."""
    k_goal, k_slot, k_pt, k_inst, k_dis, k_room, k_yaw = jax.random.split(key, 7)
    q = _choice(k_goal, jnp.asarray(t.goal_ok))
    goal = jnp.asarray(t.goals)[q]
    o = goal[0]
    slot = _choice(k_slot, jnp.asarray(t.goal_slots)[q])
    xy, p = _point_in_slot(k_pt, t, slot)
    target = _choice(k_inst, jnp.asarray(t.obj_cat) == o)
    pl, slots = _empty(t)
    pl, slots = _place(t, pl, slots, target, slot, xy)
    used = jnp.arange(t.slot_point.shape[0]) == slot
    exclude = jnp.arange(t.obj_cat.shape[0]) == target
    pl, slots, used = _distractors(k_dis, t, pl, slots, used, goal, exclude, num_distractors)
    pl, slots = _clutter(jax.random.fold_in(key, _CLUTTER_STREAM), t, pl, slots, used, goal, num_clutter)

    cell = _start_cell(k_room, t, p, min_start_distance)
    w = t.grid.free.shape[1]
    cxy = t.grid.cell_to_world(jnp.stack([cell // w, cell % w]))
    yaw = jax.random.uniform(k_yaw, (), jnp.float32, -jnp.pi, jnp.pi)
    pose = jnp.concatenate([cxy, yaw[None]]).astype(jnp.float32)
    return Episode(
        placement=pl,
        slot=slots,
        goal=goal.astype(jnp.int32),
        target=target,
        target_xy=xy,
        target_field=p,
        wrong=jnp.int32(-1),
        wrong_xy=jnp.full((2,), jnp.inf, jnp.float32),
        pose=pose,
    )


def sample_directed(key, t: EpisodeTables, num_distractors: int = 0, num_clutter: int = 0) -> Episode:
    """One directed-task episode (module docstring). num_distractors and num_clutter are static; the
    default is the paper's set-up (no clutter in the symmetric room)."""
    if t.pairs.shape[0] == 0:
        raise ValueError(
            'this scene has no directed pairs (same furniture category on both halves '
            'with different relations)'
        )
    k_pair, k_side, k_inst, k_pa, k_pb, k_dis = jax.random.split(key, 6)
    pairs = jnp.asarray(t.pairs)
    pr = pairs[jax.random.randint(k_pair, (), 0, pairs.shape[0])]
    o, slot_a, slot_b = pr[0], pr[1], pr[2]
    target_is_a = jax.random.bernoulli(k_side)
    cat = jnp.asarray(t.obj_cat)
    # Two distinct pool instances of the object, in random order.
    same = cat == o
    prio = jnp.where(same, jax.random.uniform(k_inst, same.shape), jnp.inf)
    first, second = jnp.argsort(prio)[:2]
    xy_a, p_a = _point_in_slot(k_pa, t, slot_a)
    xy_b, p_b = _point_in_slot(k_pb, t, slot_b)
    pl, slots = _empty(t)
    pl, slots = _place(t, pl, slots, first, slot_a, xy_a)
    pl, slots = _place(t, pl, slots, second, slot_b, xy_b)
    target = jnp.where(target_is_a, first, second)
    wrong = jnp.where(target_is_a, second, first)
    t_slot = jnp.where(target_is_a, slot_a, slot_b)
    goal = jnp.stack(
        [o, jnp.asarray(t.slot_relation)[t_slot], jnp.asarray(t.slot_furn_cat)[t_slot], jnp.int32(-1)]
    ).astype(jnp.int32)
    s_idx = jnp.arange(t.slot_point.shape[0])
    used = (s_idx == slot_a) | (s_idx == slot_b)
    exclude = (jnp.arange(cat.shape[0]) == first) | (jnp.arange(cat.shape[0]) == second)
    pl, slots, used = _distractors(k_dis, t, pl, slots, used, goal, exclude, num_distractors)
    pl, slots = _clutter(jax.random.fold_in(key, _CLUTTER_STREAM), t, pl, slots, used, goal, num_clutter)
    return Episode(
        placement=pl,
        slot=slots,
        goal=goal,
        target=target,
        target_xy=jnp.where(target_is_a, xy_a, xy_b),
        target_field=jnp.where(target_is_a, p_a, p_b),
        wrong=wrong,
        wrong_xy=jnp.where(target_is_a, xy_b, xy_a),
        pose=jnp.asarray(t.start_pose, jnp.float32),
    )
