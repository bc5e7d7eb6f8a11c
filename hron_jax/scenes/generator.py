"""Procedural houses: floor plan by splitting a footprint around a corridor, doors, furniture.

Role: `generate_house(seed) -> str` (MJCF text) gives a distinct, plausible multi-room house per
seed, deterministically (numpy Generator seeded with `seed`, no other randomness). `build_house`
turns an explicit plan (rooms, doors, per-room furniture wish lists) into MJCF with the same
furniture placer, which is how the hand-designed default house is made (houses.py).

Plan: the footprint W x H is cut by a horizontal corridor into a day band (living room, dining room,
kitchen, kitchen next to dining room) and a night band (bedrooms, bathroom, office, utility room);
each band is split into rooms along x, and sometimes the living room takes a full-height end
instead. Every room has a door to the corridor or to a neighbour, so the door graph is connected.

Furniture: each room type has a wish list; each piece goes back-to-wall (or free-standing for
dining tables, in front of the sofa for coffee tables, beside the bed for nightstands) at the first
position that overlaps nothing, keeps door zones clear, and keeps every door and every placed piece
reachable for a disc of radius 0.3 m (so walkways are at least 0.6 m wide). Pieces that do not fit
are dropped.

Objects: every house gets the same pool, POOL_PER_CATEGORY mocap bodies of each house object
category, parked below the floor; episodes place the target and the clutter of the other objects
(on, inside and under furniture) from it (hron_jax.envs.placement), so static shapes never change.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from . import mjcf
from . import vocabulary as V
from .walkable import component_at, free_grid

WALK_RADIUS = 0.3
GAP = 0.02  # between furniture and walls / other furniture
HALF_WALL = mjcf.WALL_THICKNESS / 2
DOOR_CLEAR_DEPTH = 1.0
ROUND = 0.01
# Mocap bodies per house object category: the target, distractors and the exploratory task's
# clutter (hron_jax.envs.placement.DEFAULT_NUM_CLUTTER = 64 per episode) come from this pool, so
# 8 categories x 9 = 72 >= 1 + 64 + a few distractors, and every category can appear up to 9 times.
POOL_PER_CATEGORY = 9

# Pieces placed as near the middle of their wall as possible (others start in the corners).
CENTRED = ("bed", "sofa", "tv_stand", "desk")
# Side of the room a piece's back is against -> yaw that turns local +y (back) to that side.
SIDE_YAW = {"N": 0.0, "S": 180.0, "E": -90.0, "W": 90.0}


@dataclasses.dataclass
class RoomSpec:
    category: str
    rect: tuple[float, float, float, float]  # xmin, ymin, xmax, ymax


@dataclasses.dataclass
class DoorSpec:
    a: int
    b: int
    centre: tuple[float, float]
    along: str  # 'x': the wall runs along x
    width: float


@dataclasses.dataclass
class Item:
    """A furniture wish: category, placement mode, optional dims override.

    mode: 'wall' (back to a wall), 'centre' (free-standing near the room centre),
    'front' (in front of the last placed `ref` category), 'beside' (next to `ref`, same wall),
    'opposite' (against the wall facing `ref`).
    """

    category: str
    mode: str = "wall"
    ref: str | None = None
    dims: dict | None = None
    sides: str | None = None  # preferred walls, e.g. "NS"


@dataclasses.dataclass
class Placed:
    category: str
    x: float
    y: float
    yaw: float
    parts: list
    fp: np.ndarray  # (2, 2) world footprint
    side: str | None  # wall side or None if free-standing
    approach: np.ndarray  # (2, 2) region where the robot can stand to reach it


# ----------------------------------------------------------------------------------------------
# furniture placement in one room
# ----------------------------------------------------------------------------------------------


def _overlap(a, b, gap=0.0):
    return (
        a[0, 0] < b[1, 0] + gap
        and b[0, 0] < a[1, 0] + gap
        and a[0, 1] < b[1, 1] + gap
        and b[0, 1] < a[1, 1] + gap
    )


def _front_dir(side):
    return {"N": (0, -1), "S": (0, 1), "E": (-1, 0), "W": (1, 0), None: (0, 0)}[side]


def _approach_region(fp, side, r=WALK_RADIUS, reach=0.4):
    """(2, 2) rectangle where the robot centre may stand to reach a piece: a strip in front of it
    (wall pieces, slightly wider than the piece) or a band all around it (free-standing)."""
    (x0, y0), (x1, y1) = fp
    m = r + reach
    if side is None:
        return np.array([[x0 - m, y0 - m], [x1 + m, y1 + m]])
    return {
        "N": np.array([[x0 - 0.3, y0 - m], [x1 + 0.3, y0]]),
        "S": np.array([[x0 - 0.3, y1], [x1 + 0.3, y1 + m]]),
        "E": np.array([[x0 - m, y0 - 0.3], [x0, y1 + 0.3]]),
        "W": np.array([[x1, y0 - 0.3], [x1 + m, y1 + 0.3]]),
    }[side]


class RoomFurnisher:
    """Places furniture in one rectangular room; `placed` holds the result in order."""

    def __init__(self, rect, door_zones, door_points, rng):
        self.rect = np.array(rect, float)
        self.inner = self.rect + np.array([HALF_WALL, HALF_WALL, -HALF_WALL, -HALF_WALL])
        self.door_zones = door_zones  # list of (2, 2) keep-out rectangles
        self.door_points = np.array(door_points, float).reshape(-1, 2)
        self.rng = rng
        self.placed: list[Placed] = []

    # -- feasibility ----------------------------------------------------------------------------
    def _fits(self, fp):
        # poses are rounded to the ROUND grid after being computed flush with a wall or neighbour,
        # so allow half a grid step of slack
        m = GAP - ROUND / 2 - 1e-9
        x0, y0, x1, y1 = self.inner
        if fp[0, 0] < x0 + m or fp[0, 1] < y0 + m or fp[1, 0] > x1 - m or fp[1, 1] > y1 - m:
            return False
        if any(_overlap(fp, z) for z in self.door_zones):
            return False
        return not any(_overlap(fp, p.fp, m) for p in self.placed)

    def _walkable(self, extra):
        pieces = self.placed + [extra]
        lo, hi = self.inner[:2], self.inner[2:]
        free, xs, ys = free_grid(lo, hi, [p.fp for p in pieces], WALK_RADIUS)
        # the walls themselves: a robot centre must stay WALK_RADIUS from the inner faces
        X, Y = np.meshgrid(xs, ys)
        free &= (
            (X > lo[0] + WALK_RADIUS)
            & (X < hi[0] - WALK_RADIUS)
            & (Y > lo[1] + WALK_RADIUS)
            & (Y < hi[1] - WALK_RADIUS)
        )
        labels, door_lab = component_at(free, xs, ys, self.door_points)
        if len(self.door_points) == 0 or door_lab[0] == 0 or np.any(door_lab != door_lab[0]):
            return False
        reach = labels == door_lab[0]
        for p in pieces:
            a = p.approach
            region = (X >= a[0, 0]) & (X <= a[1, 0]) & (Y >= a[0, 1]) & (Y <= a[1, 1])
            if not np.any(reach & region):
                return False
        return True

    def _try(self, cat, parts, x, y, yaw, side):
        x, y = round(x / ROUND) * ROUND, round(y / ROUND) * ROUND
        fp = mjcf.world_footprint(parts, x, y, yaw)
        if not self._fits(fp):
            return None
        p = Placed(cat, x, y, yaw, parts, fp, side, _approach_region(fp, side))
        if not self._walkable(p):
            return None
        self.placed.append(p)
        return p

    # -- modes ----------------------------------------------------------------------------------
    def _wall_pose(self, parts, side, t):
        """(x, y, yaw) putting the piece's back on `side`, at fraction t in [0, 1] along the wall."""
        yaw = SIDE_YAW[side]
        fp0 = mjcf.world_footprint(parts, 0.0, 0.0, yaw)
        x0, y0, x1, y1 = self.inner
        if side in "NS":
            lo, hi = x0 + GAP - fp0[0, 0], x1 - GAP - fp0[1, 0]
            y = (y1 - GAP - fp0[1, 1]) if side == "N" else (y0 + GAP - fp0[0, 1])
            return lo + t * (hi - lo), y, yaw
        lo, hi = y0 + GAP - fp0[0, 1], y1 - GAP - fp0[1, 1]
        x = (x1 - GAP - fp0[1, 0]) if side == "E" else (x0 + GAP - fp0[0, 0])
        return x, lo + t * (hi - lo), yaw

    def place_wall(self, cat, parts, sides="NSEW", ts=None):
        sides = list(sides)
        self.rng.shuffle(sides)
        if ts is None and cat in CENTRED:
            ts = 0.5 + np.array([0.0, 1, -1, 2, -2, 3, -3, 4, -4, 6, -6, 8, -8, 10, -10]) * 0.05
        elif ts is None:
            ts = np.concatenate([[0.0, 1.0], self.rng.permutation(np.linspace(0, 1, 21))])
        for side in sides:
            for t in ts:
                p = self._try(cat, parts, *self._wall_pose(parts, side, t), side)
                if p is not None:
                    return p
        return None

    def place_centre(self, cat, parts):
        x0, y0, x1, y1 = self.rect
        yaw = 0.0 if (x1 - x0) >= (y1 - y0) else 90.0
        cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
        offsets = [(0.0, 0.0)] + [tuple(self.rng.uniform(-0.6, 0.6, 2)) for _ in range(20)]
        for dx, dy in offsets:
            p = self._try(cat, parts, cx + dx, cy + dy, yaw, None)
            if p is not None:
                return p
        return None

    def place_front(self, cat, parts, ref: Placed, gap=0.4):
        """Free-standing piece centred in front of ref (coffee table before the sofa)."""
        fx, fy = _front_dir(ref.side)
        fp0 = mjcf.world_footprint(parts, 0.0, 0.0, ref.yaw)
        depth = (fp0[1, 1] - fp0[0, 1]) if ref.side in "NS" else (fp0[1, 0] - fp0[0, 0])
        cx, cy = (ref.fp[0] + ref.fp[1]) / 2
        if ref.side in "NS":
            edge = ref.fp[0, 1] if ref.side == "N" else ref.fp[1, 1]
            y = edge + fy * (gap + depth / 2)
            return self._try(cat, parts, cx, y, ref.yaw, None)
        edge = ref.fp[0, 0] if ref.side == "E" else ref.fp[1, 0]
        x = edge + fx * (gap + depth / 2)
        return self._try(cat, parts, x, cy, ref.yaw, None)

    def place_beside(self, cat, parts, ref: Placed):
        """Same wall as ref, touching its left or right end (nightstands beside the bed)."""
        side = ref.side
        yaw = SIDE_YAW[side]
        fp0 = mjcf.world_footprint(parts, 0.0, 0.0, yaw)
        _, wy, _ = self._wall_pose(parts, side, 0.0) if side in "NS" else (None, None, None)
        ends = [0, 1]
        self.rng.shuffle(ends)
        for e in ends:
            if side in "NS":
                x = (ref.fp[0, 0] - 2 * GAP - fp0[1, 0]) if e == 0 else (ref.fp[1, 0] + 2 * GAP - fp0[0, 0])
                p = self._try(cat, parts, x, wy, yaw, side)
            else:
                wx, _, _ = self._wall_pose(parts, side, 0.0)
                y = (ref.fp[0, 1] - 2 * GAP - fp0[1, 1]) if e == 0 else (ref.fp[1, 1] + 2 * GAP - fp0[0, 1])
                p = self._try(cat, parts, wx, y, yaw, side)
            if p is not None:
                return p
        return None

    def place(self, item: Item):
        parts = mjcf.furniture_parts(item.category, **(item.dims or {}))
        ref = next((p for p in reversed(self.placed) if p.category == item.ref), None)
        if item.mode == "centre":
            return self.place_centre(item.category, parts)
        if item.mode == "front" and ref is not None and ref.side is not None:
            return self.place_front(item.category, parts, ref)
        if item.mode == "beside" and ref is not None and ref.side is not None:
            return self.place_beside(item.category, parts, ref)
        if item.mode == "opposite" and ref is not None and ref.side is not None:
            opp = {"N": "S", "S": "N", "E": "W", "W": "E"}[ref.side]
            p = self.place_wall(item.category, parts, sides=opp)
            if p is not None:
                return p
        if item.mode in ("front", "beside"):
            return None
        return self.place_wall(item.category, parts, sides=item.sides or "NSEW")


# ----------------------------------------------------------------------------------------------
# plans -> MJCF
# ----------------------------------------------------------------------------------------------


def shared_edge(r1, r2, tol=1e-6):
    """(along, c, lo, hi) of the wall segment two rectangles share, or None."""
    a, b = r1, r2
    for c in (a[1], a[3]):
        if abs(c - b[1]) < tol or abs(c - b[3]) < tol:
            lo, hi = max(a[0], b[0]), min(a[2], b[2])
            if hi - lo > tol:
                return "x", c, lo, hi
    for c in (a[0], a[2]):
        if abs(c - b[0]) < tol or abs(c - b[2]) < tol:
            lo, hi = max(a[1], b[1]), min(a[3], b[3])
            if hi - lo > tol:
                return "y", c, lo, hi
    return None


def make_door(rooms, a, b, rng, width=1.0, at=None):
    """Door between rooms a and b on their shared edge; at = fraction along the free range."""
    e = shared_edge(rooms[a].rect, rooms[b].rect)
    if e is None:
        raise ValueError(f"rooms {a} and {b} share no wall")
    along, c, lo, hi = e
    # short walls (a corridor's end) get a narrower door, never under 1 m
    width = min(width, round((hi - lo - 0.2) / ROUND) * ROUND)
    if width < 1.0 - 1e-9:
        raise ValueError(f"wall between rooms {a} and {b} too short for a 1 m door")
    margin = width / 2 + min(0.3, (hi - lo - width) / 2)
    t = rng.uniform(0.2, 0.8) if at is None else at
    s = round((lo + margin + t * (hi - lo - 2 * margin)) / ROUND) * ROUND
    centre = (s, c) if along == "x" else (c, s)
    return DoorSpec(a, b, centre, along, width)


def _wall_lines(rooms, doors):
    """Merge room edges into wall lines; yields (p0, p1, gaps) for SceneWriter.add_wall."""
    lines = {"x": {}, "y": {}}
    for r in rooms:
        x0, y0, x1, y1 = r.rect
        for c in (y0, y1):
            lines["x"].setdefault(round(c, 6), []).append((x0, x1))
        for c in (x0, x1):
            lines["y"].setdefault(round(c, 6), []).append((y0, y1))
    for along, by_c in lines.items():
        for c, ivs in sorted(by_c.items()):
            ivs.sort()
            merged = [list(ivs[0])]
            for lo, hi in ivs[1:]:
                if lo <= merged[-1][1] + 1e-6:
                    merged[-1][1] = max(merged[-1][1], hi)
                else:
                    merged.append([lo, hi])
            for lo, hi in merged:
                gaps = []
                for d in doors:
                    dc = d.centre[1] if along == "x" else d.centre[0]
                    ds = d.centre[0] if along == "x" else d.centre[1]
                    if d.along == along and abs(dc - c) < 1e-6 and lo < ds < hi:
                        gaps.append((ds, d.width))
                p0, p1 = ((lo, c), (hi, c)) if along == "x" else ((c, lo), (c, hi))
                yield p0, p1, gaps


def _door_zone(door, rect):
    """Keep-out rectangle in front of a door inside one room, and the approach point."""
    cx, cy = door.centre
    w = door.width / 2 + 0.15
    x0, y0, x1, y1 = rect
    if door.along == "x":
        into = 1 if abs(cy - y0) < 1e-6 else -1
        zone = np.array(
            [[cx - w, min(cy, cy + into * DOOR_CLEAR_DEPTH)], [cx + w, max(cy, cy + into * DOOR_CLEAR_DEPTH)]]
        )
        point = (cx, cy + into * 0.45)
    else:
        into = 1 if abs(cx - x0) < 1e-6 else -1
        zone = np.array(
            [[min(cx, cx + into * DOOR_CLEAR_DEPTH), cy - w], [max(cx, cx + into * DOOR_CLEAR_DEPTH), cy + w]]
        )
        point = (cx + into * 0.45, cy)
    return zone, point


def build_house(name, rooms, doors, wishes, rng, comment="", pool_per_category=POOL_PER_CATEGORY, starts=()):
    """MJCF text of a house plan. wishes[i]: list of Item for room i. Returns (xml, writer)."""
    w = mjcf.SceneWriter(name, comment)
    for r in rooms:
        w.add_room(r.category, [r.rect])
    for p0, p1, gaps in _wall_lines(rooms, doors):
        w.add_wall(p0, p1, gaps)
    for d in doors:
        w.add_door(d.centre, d.along, d.width)
    for i, r in enumerate(rooms):
        zones, points = [], []
        for d in doors:
            if i in (d.a, d.b):
                z, pt = _door_zone(d, r.rect)
                zones.append(z)
                points.append(pt)
        f = RoomFurnisher(r.rect, zones, points, rng)
        for item in wishes[i]:
            f.place(item)
        for p in f.placed:
            w.add_furniture(p.category, p.x, p.y, p.yaw, parts=p.parts)
    for x, y, yaw in starts:
        w.add_start(x, y, yaw)
    w.add_object_pool({o: pool_per_category for o in V.HOUSE_OBJECTS})
    return w.xml(), w


# ----------------------------------------------------------------------------------------------
# random plans
# ----------------------------------------------------------------------------------------------

WISHES = {
    "kitchen": lambda rng: (
        [
            Item("fridge", sides="NSEW"),
            Item("counter"),
            Item("sink_cabinet"),
            Item("counter"),
            Item("cabinet"),
        ]
        + ([Item("table", "centre", dims={"w": 1.0, "d": 0.7})] if rng.random() < 0.5 else [Item("shelf")])
    ),
    "living_room": lambda rng: [
        Item("sofa"),
        Item("coffee_table", "front", "sofa"),
        Item("tv_stand", "opposite", "sofa"),
        Item("shelf"),
        Item("cabinet"),
        Item("shelf"),
    ][: 4 + int(rng.integers(0, 3))],
    "dining_room": lambda rng: [
        Item("table", "centre", dims={"w": 1.6, "d": 0.9}),
        Item("cabinet"),
        Item(["dresser", "shelf"][int(rng.integers(0, 2))]),
    ],
    "bedroom": lambda rng: (
        [
            Item("bed", dims={"w": [1.0, 1.4][int(rng.integers(0, 2))]}),
            Item("nightstand", "beside", "bed"),
            Item("wardrobe"),
            Item("nightstand", "beside", "bed"),
        ]
        + [Item("dresser"), Item("desk"), Item("shelf")][: int(rng.integers(0, 3))]
    ),
    "bathroom": lambda rng: (
        [Item("sink_cabinet"), Item("cabinet", dims={"w": 0.6, "d": 0.35})]
        + ([Item("shelf")] if rng.random() < 0.5 else [])
    ),
    "office": lambda rng: [Item("desk"), Item("shelf"), Item("cabinet"), Item("shelf")],
    "utility_room": lambda rng: [Item("cabinet"), Item("shelf"), Item("counter", dims={"w": 1.2})],
    "corridor": lambda rng: (
        [Item(["cabinet", "shelf", "dresser"][int(rng.integers(0, 3))], dims={"d": 0.35})]
        if rng.random() < 0.7
        else []
    ),
}


def _split(lo, hi, weights, rng, jitter=0.15):
    """Cut [lo, hi] into len(weights) pieces with lengths ~ weights (jittered), on the ROUND grid."""
    w = np.asarray(weights, float) * rng.uniform(1 - jitter, 1 + jitter, len(weights))
    cuts = lo + np.cumsum(w)[:-1] / w.sum() * (hi - lo)
    cuts = np.round(cuts / 0.05) * 0.05
    return list(zip([lo, *cuts], [*cuts, hi]))


def _transform_plan(rooms, doors, W, H, flip_x, flip_y, transpose):
    """Mirror / transpose a plan in its W x H footprint, so layouts vary beyond one orientation."""

    def pt(x, y):
        x, y = (W - x if flip_x else x), (H - y if flip_y else y)
        return (y, x) if transpose else (x, y)

    def rect(r):
        (ax, ay), (bx, by) = pt(r[0], r[1]), pt(r[2], r[3])
        return (min(ax, bx), min(ay, by), max(ax, bx), max(ay, by))

    rooms = [RoomSpec(r.category, rect(r.rect)) for r in rooms]
    flip_axis = {"x": "y", "y": "x"}
    doors = [
        DoorSpec(d.a, d.b, pt(*d.centre), flip_axis[d.along] if transpose else d.along, d.width)
        for d in doors
    ]
    return rooms, doors


def random_plan(seed: int):
    """(rooms, doors, wishes, rng) for a random house; deterministic in seed.

    Day band (living, dining, kitchen; kitchen always next to dining) above a corridor, night band
    (bedrooms, bathroom, maybe office / utility room) below it, then a random mirror / transpose.
    """
    rng = np.random.default_rng(seed)
    W = round(rng.uniform(13.0, 17.0) / 0.05) * 0.05
    H = round(rng.uniform(9.8, 11.5) / 0.05) * 0.05
    cw = round(rng.uniform(1.4, 1.8) / 0.05) * 0.05
    top = round(rng.uniform(4.4, 5.2) / 0.05) * 0.05
    yc0, yc1 = H - top - cw, H - top
    rooms: list[RoomSpec] = [RoomSpec("corridor", (0.0, yc0, W, yc1))]
    day = ["living_room", "dining_room", "kitchen"]
    if rng.random() < 0.5:
        day = day[::-1]
    dw = {"living_room": 1.6, "dining_room": 1.0, "kitchen": 1.1}
    for cat, (a, b) in zip(day, _split(0.0, W, [dw[c] for c in day], rng)):
        rooms.append(RoomSpec(cat, (a, yc1, b, H)))
    extra = ["office", "bedroom", "utility_room"]
    rng.shuffle(extra)
    n_night = 3 + int(W > 13.5) + int(W > 15.5)
    night = ["bedroom", "bathroom", "bedroom"] + extra[: n_night - 3]
    rng.shuffle(night)
    nw = {"bedroom": 1.3, "bathroom": 0.75, "office": 1.0, "utility_room": 0.7}
    for cat, (a, b) in zip(night, _split(0.0, W, [nw[c] for c in night], rng)):
        rooms.append(RoomSpec(cat, (a, 0.0, b, yc0)))
    corridor = 0
    doors = []
    for i, r in enumerate(rooms):
        if i == corridor:
            continue
        if shared_edge(r.rect, rooms[corridor].rect) is not None:
            width = 1.4 if r.category in ("living_room", "dining_room") else 1.0
            doors.append(make_door(rooms, i, corridor, rng, width))
    idx = {
        r.category: i for i, r in enumerate(rooms) if r.category in ("kitchen", "dining_room", "living_room")
    }
    for a, b in (("kitchen", "dining_room"), ("dining_room", "living_room")):
        if shared_edge(rooms[idx[a]].rect, rooms[idx[b]].rect) is not None:
            doors.append(make_door(rooms, idx[a], idx[b], rng, 1.2))
    # an en-suite bathroom: bathroom next to a bedroom gets a second door with probability 0.4
    for i, r in enumerate(rooms):
        if r.category != "bathroom":
            continue
        for j, q in enumerate(rooms):
            if q.category == "bedroom" and shared_edge(r.rect, q.rect) is not None and rng.random() < 0.4:
                doors.append(make_door(rooms, i, j, rng, 1.0))
                break
    rooms, doors = _transform_plan(
        rooms, doors, W, H, rng.random() < 0.5, rng.random() < 0.5, rng.random() < 0.5
    )
    wishes = [WISHES[r.category](rng) for r in rooms]
    return rooms, doors, wishes, rng


def generate_house(seed: int) -> str:
    """Annotated MJCF text of the random house for `seed`."""
    rooms, doors, wishes, rng = random_plan(seed)
    xml, _ = build_house(
        f"house_seed{seed}",
        rooms,
        doors,
        wishes,
        rng,
        comment=f"generated by python -m hron_jax.scenes --seed {seed}",
    )
    return xml
