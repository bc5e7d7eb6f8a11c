"""MJCF writing helpers: rooms, walls with door gaps, furniture from primitives, object pool.

Role: turn a floor plan (room rectangles, doors, furniture poses) into one annotated MJCF string in
the format of docs/scene_format.md. Used by the house generator and the hand-designed scenes.

Furniture is described in its own frame: x across its width, y across its depth with the back at +y
and the open front at -y, z up from the floor. `furniture_parts(category, **dims)` returns a list of
`Part`s (boxes or capsules given by their local AABB corners, and relation slots); the writer places
the body at (x, y, 0) with a yaw that is a multiple of 90 degrees. Cavities are open at the front so
the camera can see objects inside (closed doors would make `inside` goals invisible).

Coordinates are rounded to 0.1 mm on output; keep design values on that grid so faces that should
coincide (slot bottom = support top) do so exactly after parsing.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np

from . import vocabulary as V

WALL_HEIGHT = 2.5
WALL_THICKNESS = 0.1
DOOR_HEIGHT = 2.1
FLOOR_THICKNESS = 0.05
PARK_Z = -5.0
ON_TOP_CLEARANCE = 0.3
# Door site half depth across the wall: it reaches this far into both rooms' floors.
DOOR_REACH = 0.3

FLOOR_RGBA = {
    "kitchen": (0.80, 0.81, 0.83, 1.0),
    "bathroom": (0.78, 0.86, 0.88, 1.0),
    "utility_room": (0.70, 0.70, 0.68, 1.0),
    "corridor": (0.66, 0.55, 0.42, 1.0),
}
WOOD_FLOOR = (0.74, 0.60, 0.44, 1.0)


@dataclasses.dataclass(frozen=True)
class Part:
    """One piece of a furniture body in its local frame.

    kind: 'box' or 'capsule' (geoms) or a relation name (slot). lo, hi: local AABB corners (3,).
    A capsule is vertical, its radius half the x extent. rgba only matters for geoms.
    """

    kind: str
    lo: tuple[float, float, float]
    hi: tuple[float, float, float]
    rgba: tuple[float, float, float, float] = (0.5, 0.5, 0.5, 1.0)

    @property
    def is_slot(self) -> bool:
        return self.kind in V.RELATIONS


def _shade(rgba, f):
    return tuple(min(1.0, c * f) for c in rgba[:3]) + (rgba[3],)


def _box(lo, hi, rgba):
    return Part("box", tuple(lo), tuple(hi), rgba)


def _slot(rel, lo, hi):
    return Part(rel, tuple(lo), tuple(hi))


def _top_slot(w_lo, w_hi, d_lo, d_hi, z):
    return _slot("onTop", (w_lo, d_lo, z), (w_hi, d_hi, z + ON_TOP_CLEARANCE))


# ----------------------------------------------------------------------------------------------
# furniture builders (local frame, metres)
# ----------------------------------------------------------------------------------------------


def table(rgba, w=1.4, d=0.8, h=0.75, top=0.04, leg=0.05):
    """Four legs and a top; onTop on the top, under between the legs down to the floor."""
    x, y = w / 2, d / 2
    parts = [_box((-x, -y, h - top), (x, y, h), rgba)]
    leg_rgba = _shade(rgba, 0.8)
    for sx in (-1, 1):
        for sy in (-1, 1):
            cx, cy = sx * (x - 0.03 - leg / 2), sy * (y - 0.03 - leg / 2)
            parts.append(
                _box((cx - leg / 2, cy - leg / 2, 0), (cx + leg / 2, cy + leg / 2, h - top), leg_rgba)
            )
    ix, iy = x - 0.03 - leg, y - 0.03 - leg  # inner faces of the legs
    parts += [_top_slot(-x, x, -y, y, h), _slot("under", (-ix, -iy, 0), (ix, iy, h - top))]
    return parts


def case(
    rgba,
    w,
    d,
    h,
    boards=(),
    base=0.04,
    lift=0.0,
    t=0.02,
    top=0.03,
    top_slot=True,
    max_inside_z=1.5,
    top_overhang=0.0,
):
    """Open-front carcass: sides (reaching the floor, they are the legs), back, bottom, top, boards.

    boards: z of the bottom face of each intermediate board. lift: height of the bottom board above
    the floor; a lift >= 0.08 leaves an `under` slot between the sides. One `inside` slot per cavity
    whose support is below max_inside_z (higher ones are out of the camera's sight).
    """
    x, y = w / 2, d / 2
    ix = x - t  # inner face of the sides
    back = y - t  # inner face of the back
    dark = _shade(rgba, 0.85)
    parts = [
        _box((-x, -y, 0), (-ix, y, h - top), rgba),
        _box((ix, -y, 0), (x, y, h - top), rgba),
        _box((-ix, back, lift), (ix, y, h - top), dark),
        _box((-ix, -y, lift), (ix, back, lift + base), rgba),
        _box((-x - top_overhang, -y - top_overhang, h - top), (x + top_overhang, y, h), _shade(rgba, 1.08)),
    ]
    supports = [lift + base]
    ceilings = []
    for zb in sorted(boards):
        parts.append(_box((-ix, -y, zb), (ix, back, zb + t), rgba))
        ceilings.append(zb)
        supports.append(zb + t)
    ceilings.append(h - top)
    for s, c in zip(supports, ceilings):
        if s <= max_inside_z and c - s >= 0.1:
            parts.append(_slot("inside", (-ix, -y, s), (ix, back, c)))
    if top_slot:
        parts.append(_top_slot(-x - top_overhang, x + top_overhang, -y - top_overhang, y, h))
    if lift >= 0.08:
        parts.append(_slot("under", (-ix, -y, 0), (ix, back, lift)))
    return parts


def desk(rgba, w=1.3, d=0.7, h=0.75, top=0.03, t=0.03):
    """Top on two side panels with a modesty panel at the back; under is the knee space."""
    x, y = w / 2, d / 2
    dark = _shade(rgba, 0.85)
    return [
        _box((-x, -y, h - top), (x, y, h), rgba),
        _box((-x, -y, 0), (-x + t, y, h - top), dark),
        _box((x - t, -y, 0), (x, y, h - top), dark),
        _box((-x + t, y - t, 0.3), (x - t, y, h - top), dark),
        _top_slot(-x, x, -y, y, h),
        _slot("under", (-x + t, -y, 0), (x - t, y - t, h - top)),
    ]


def bed(rgba, w=1.4, d=2.0, h=0.55, frame=0.25, reach=0.9):
    """Legs, mattress box, pillow and a headboard behind the mattress (+y).

    Slots cover the foot end only (depth `reach`): farther in, an object may be more than the 1 m
    success radius from any point the robot can stand on.
    """
    x, y = w / 2, d / 2
    leg = 0.06
    linen = (0.93, 0.92, 0.88, 1.0)
    parts = [_box((-x, -y, frame), (x, y, h), linen)]
    for sx in (-1, 1):
        for sy in (-1, 1):
            cx, cy = sx * (x - leg / 2), sy * (y - leg / 2)
            parts.append(_box((cx - leg / 2, cy - leg / 2, 0), (cx + leg / 2, cy + leg / 2, frame), rgba))
    parts.append(_box((-x, y, 0), (x, y + 0.06, 1.0), rgba))
    parts.append(_box((-x + 0.15, y - 0.45, h), (x - 0.15, y - 0.1, h + 0.1), (0.98, 0.98, 0.96, 1.0)))
    r = min(reach, d)
    parts.append(_top_slot(-x + 0.05, x - 0.05, -y, -y + r, h))
    parts.append(_slot("under", (-x + leg, -y + leg, 0), (x - leg, -y + r, frame)))
    return parts


def sofa(rgba, w=2.0, d=0.9, legs=0.12, seat=0.42, arm=0.18, back=0.22):
    """Seat on short legs, backrest at +y, two armrests; onTop on the seat, under below it."""
    x, y = w / 2, d / 2
    leg = 0.06
    dark = _shade(rgba, 0.8)
    parts = [
        _box((-x, -y, legs), (x, y, seat), rgba),
        _box((-x, y - back, seat), (x, y, 0.85), dark),
        _box((-x, -y, seat), (-x + arm, y - back, 0.62), dark),
        _box((x - arm, -y, seat), (x, y - back, 0.62), dark),
    ]
    for sx in (-1, 1):
        for sy in (-1, 1):
            cx, cy = sx * (x - 0.05 - leg / 2), sy * (y - 0.05 - leg / 2)
            parts.append(
                _box((cx - leg / 2, cy - leg / 2, 0), (cx + leg / 2, cy + leg / 2, legs), (0.2, 0.15, 0.1, 1))
            )
    parts.append(_top_slot(-x + arm, x - arm, -y, y - back, seat))
    ix, iy = x - 0.05 - leg, y - 0.05 - leg
    parts.append(_slot("under", (-ix, -iy, 0), (ix, iy, legs)))
    return parts


def tv_stand(rgba, w=1.5, d=0.5, h=0.5):
    """Low open cabinet with a television standing at the back; onTop covers the front strip."""
    parts = [p for p in case(rgba, w, d, h, lift=0.06, top_slot=False)]
    y = d / 2
    tv = (0.05, 0.05, 0.06, 1.0)
    parts.append(_box((-0.15, y - 0.2, h), (0.15, y - 0.04, h + 0.02), tv))
    parts.append(_box((-0.55, y - 0.13, h + 0.02), (0.55, y - 0.08, h + 0.68), tv))
    parts.append(_top_slot(-w / 2, w / 2, -y, y - 0.2, h))
    return parts


def sink_cabinet(rgba, w=0.8, d=0.55, h=0.85):
    """Cabinet with a faucet (capsule) at the back; onTop covers the counter in front of it."""
    parts = case(rgba, w, d, h, lift=0.0, base=0.08, top=0.04, top_slot=False)
    y = d / 2
    parts.append(Part("capsule", (-0.025, y - 0.13, h), (0.025, y - 0.08, h + 0.25), (0.75, 0.76, 0.78, 1.0)))
    parts.append(_top_slot(-w / 2, w / 2, -y, y - 0.15, h))
    return parts


def _fridge(rgba, w=0.7, d=0.65, h=1.8):
    return case(rgba, w, d, h, boards=(0.45, 0.85, 1.25), base=0.06, t=0.04, top=0.05, top_slot=False)


BUILDERS = {
    "table": lambda c, **k: table(c, **k),
    "coffee_table": lambda c, **k: table(c, **{"w": 1.1, "d": 0.6, "h": 0.45, **k}),
    "desk": lambda c, **k: desk(c, **k),
    "shelf": lambda c, **k: case(c, **{"w": 0.9, "d": 0.35, "h": 1.2, "boards": (0.62,), "lift": 0.18, **k}),
    "cabinet": lambda c, **k: case(c, **{"w": 0.8, "d": 0.45, "h": 0.9, "boards": (0.5,), "lift": 0.1, **k}),
    "nightstand": lambda c, **k: case(c, **{"w": 0.45, "d": 0.4, "h": 0.55, "lift": 0.15, **k}),
    "dresser": lambda c, **k: case(c, **{"w": 1.0, "d": 0.5, "h": 0.85, "boards": (0.45,), "lift": 0.1, **k}),
    "wardrobe": lambda c, **k: case(
        c,
        **{
            "w": 1.2,
            "d": 0.6,
            "h": 2.0,
            "boards": (0.8, 1.5),
            "lift": 0.0,
            "base": 0.1,
            "top_slot": False,
            **k,
        },
    ),
    "counter": lambda c, **k: case(c, **{"w": 1.6, "d": 0.6, "h": 0.9, "base": 0.1, "top": 0.04, **k}),
    "fridge": lambda c, **k: _fridge(c, **k),
    "bed": lambda c, **k: bed(c, **k),
    "sofa": lambda c, **k: sofa(c, **k),
    "tv_stand": lambda c, **k: tv_stand(c, **k),
    "sink_cabinet": lambda c, **k: sink_cabinet(c, **k),
    "rectangle": lambda c, **k: table(c, **{"w": 1.0, "d": 0.6, "h": 0.75, **k}),
}
assert set(BUILDERS) == set(V.FURNITURE)


def furniture_parts(category: str, **dims) -> list[Part]:
    """Local-frame parts of one furniture piece; dims override the category's default sizes."""
    return BUILDERS[category](V.FURNITURE_RGBA[category], **dims)


def local_footprint(parts: Sequence[Part]) -> np.ndarray:
    """(2, 2) local xy AABB [[xmin, ymin], [xmax, ymax]] of the geoms of a furniture piece."""
    lo = np.min([p.lo[:2] for p in parts if not p.is_slot], axis=0)
    hi = np.max([p.hi[:2] for p in parts if not p.is_slot], axis=0)
    return np.stack([lo, hi])


def rotate_xy(xy, yaw_deg):
    """Rotate local xy (..., 2) by a multiple of 90 degrees, exactly."""
    k = int(round(yaw_deg / 90.0)) % 4
    c, s = [(1, 0), (0, 1), (-1, 0), (0, -1)][k]
    xy = np.asarray(xy, float)
    return np.stack([c * xy[..., 0] - s * xy[..., 1], s * xy[..., 0] + c * xy[..., 1]], -1)


def world_footprint(parts, x, y, yaw_deg) -> np.ndarray:
    """(2, 2) world xy AABB of a furniture piece placed at (x, y) with yaw (multiple of 90)."""
    fp = local_footprint(parts)
    corners = np.array(
        [[fp[0, 0], fp[0, 1]], [fp[1, 0], fp[1, 1]], [fp[0, 0], fp[1, 1]], [fp[1, 0], fp[0, 1]]]
    )
    w = rotate_xy(corners, yaw_deg) + [x, y]
    return np.stack([w.min(0), w.max(0)])


# ----------------------------------------------------------------------------------------------
# scene writer
# ----------------------------------------------------------------------------------------------


def _f(v) -> str:
    s = f"{float(v):.4f}".rstrip("0").rstrip(".")
    return "0" if s in ("-0", "") else s


def _vec(v) -> str:
    return " ".join(_f(a) for a in v)


class SceneWriter:
    """Accumulates rooms, walls, doors, furniture, starts and the object pool; `xml()` writes them.

    Instance numbers `<k>` are assigned per category in call order.
    """

    def __init__(self, model_name: str, comment: str = ""):
        self.model_name = model_name
        self.comment = comment
        self._count: dict[str, int] = {}
        self.rooms: list[tuple[str, list]] = []  # (name, [(xmin, ymin, xmax, ymax)])
        self.walls: list[tuple[str, np.ndarray, np.ndarray]] = []  # (name, lo3, hi3)
        self.doors: list[tuple[str, np.ndarray, np.ndarray]] = []  # (name, centre3, half3)
        self.furniture: list[tuple[str, float, float, float, list[Part]]] = []
        self.starts: list[tuple[float, float, float]] = []
        self.pool: list[tuple[str, str]] = []  # (name, object category)

    def _next(self, key: str) -> int:
        k = self._count.get(key, 0)
        self._count[key] = k + 1
        return k

    def add_room(self, category: str, boxes) -> str:
        """A room with floor boxes [(xmin, ymin, xmax, ymax)]; floor top at z = 0."""
        V.index("room", category)
        name = f"room:{category}:{self._next('room:' + category)}"
        self.rooms.append((name, [tuple(b) for b in boxes]))
        return name

    def add_wall_box(self, lo, hi) -> None:
        self.walls.append((f"wall:{len(self.walls)}", np.asarray(lo, float), np.asarray(hi, float)))

    def add_wall(self, p0, p1, gaps=(), height=WALL_HEIGHT, thickness=WALL_THICKNESS) -> None:
        """Axis-aligned wall along p0 -> p1 (xy) centred on the line, with door gaps.

        gaps: [(centre coordinate along the wall, width)]; each gap gets a lintel above DOOR_HEIGHT.
        The ends are extended by half the thickness so perpendicular walls close the corners.
        """
        (x0, y0), (x1, y1) = p0, p1
        horizontal = abs(y1 - y0) < 1e-9
        a0, a1 = (min(x0, x1), max(x0, x1)) if horizontal else (min(y0, y1), max(y0, y1))
        c = y0 if horizontal else x0
        a0 -= thickness / 2
        a1 += thickness / 2
        cuts = sorted((g - w / 2, g + w / 2) for g, w in gaps)
        pieces, cur = [], a0
        for g0, g1 in cuts:
            if g0 - cur > 1e-6:
                pieces.append((cur, g0, 0.0, height))
            pieces.append((g0, g1, DOOR_HEIGHT, height))
            cur = g1
        if a1 - cur > 1e-6:
            pieces.append((cur, a1, 0.0, height))
        for s0, s1, z0, z1 in pieces:
            if horizontal:
                self.add_wall_box((s0, c - thickness / 2, z0), (s1, c + thickness / 2, z1))
            else:
                self.add_wall_box((c - thickness / 2, s0, z0), (c + thickness / 2, s1, z1))

    def add_door(self, centre_xy, along: str, width: float) -> str:
        """Door site in a wall gap: along='x' for a gap in a wall parallel to x."""
        name = f"door:{self._next('door')}"
        hx, hy = (width / 2, DOOR_REACH) if along == "x" else (DOOR_REACH, width / 2)
        self.doors.append(
            (
                name,
                np.array([centre_xy[0], centre_xy[1], DOOR_HEIGHT / 2]),
                np.array([hx, hy, DOOR_HEIGHT / 2]),
            )
        )
        return name

    def add_furniture(self, category: str, x: float, y: float, yaw: float = 0.0, parts=None, **dims) -> str:
        """Furniture body at (x, y, 0) rotated by yaw degrees (multiple of 90)."""
        if abs(yaw / 90.0 - round(yaw / 90.0)) > 1e-9:
            raise ValueError("furniture yaw must be a multiple of 90 degrees")
        parts = furniture_parts(category, **dims) if parts is None else parts
        name = f"furniture:{category}:{self._next('furniture:' + category)}"
        self.furniture.append((name, x, y, yaw, parts))
        return name

    def add_start(self, x: float, y: float, yaw: float = 0.0) -> None:
        self.starts.append((x, y, yaw))

    def add_object_pool(self, counts: dict[str, int]) -> None:
        """Mocap bodies per object category, parked at z = PARK_Z, shapes from OBJECT_SHAPES."""
        for cat, n in counts.items():
            V.index("object", cat)
            for _ in range(n):
                self.pool.append((f"object:{cat}:{self._next('object:' + cat)}", cat))

    # -- output ---------------------------------------------------------------------------------

    def xml(self) -> str:
        out = [f'<mujoco model="{self.model_name}">']
        if self.comment:
            out.insert(0, "<!-- {} -->".format(self.comment.replace("--", "-")))
        out += [
            '  <compiler angle="degree"/>',
            '  <option timestep="0.01"/>',
            "  <visual><global offwidth=\"640\" offheight=\"480\"/></visual>",
            "  <asset>",
            '    <material name="plain" rgba="1 1 1 1" specular="0.1"/>',
            "  </asset>",
            "  <worldbody>",
            '    <light name="sun" directional="true" pos="0 0 10" dir="0 0 -1" diffuse="0.8 0.8 0.8"/>',
        ]
        for name, boxes in self.rooms:
            cat = name.split(":")[1]
            rgba = FLOOR_RGBA.get(cat, WOOD_FLOOR)
            out.append(f'    <body name="{name}">')
            for b in boxes:
                cx, cy = (b[0] + b[2]) / 2, (b[1] + b[3]) / 2
                hx, hy = (b[2] - b[0]) / 2, (b[3] - b[1]) / 2
                out.append(
                    f'      <geom type="box" pos="{_vec((cx, cy, -FLOOR_THICKNESS / 2))}" '
                    f'size="{_vec((hx, hy, FLOOR_THICKNESS / 2))}" rgba="{_vec(rgba)}"/>'
                )
            out.append("    </body>")
        for name, lo, hi in self.walls:
            out.append(
                f'    <geom name="{name}" type="box" pos="{_vec((lo + hi) / 2)}" '
                f'size="{_vec((hi - lo) / 2)}" rgba="{_vec(V.STRUCTURE_RGBA)}"/>'
            )
        for name, c, h in self.doors:
            out.append(
                f'    <site name="{name}" type="box" pos="{_vec(c)}" size="{_vec(h)}" rgba="0.2 0.8 0.2 0.2" '
                'group="4"/>'
            )
        for k, (x, y, yaw) in enumerate(self.starts):
            out.append(
                f'    <site name="start:{k}" pos="{_vec((x, y, 0.1))}" euler="0 0 {_f(yaw)}" size="0.1" '
                'rgba="0.9 0.1 0.9 0.5" group="4"/>'
            )
        for name, x, y, yaw, parts in self.furniture:
            out.append(f'    <body name="{name}" pos="{_vec((x, y, 0))}" euler="0 0 {_f(yaw)}">')
            slot_k: dict[str, int] = {}
            for p in parts:
                lo, hi = np.array(p.lo), np.array(p.hi)
                c, h = (lo + hi) / 2, (hi - lo) / 2
                if p.is_slot:
                    j = slot_k.get(p.kind, 0)
                    slot_k[p.kind] = j + 1
                    out.append(
                        f'      <site name="{name}:{p.kind}:{j}" type="box" pos="{_vec(c)}" size="{_vec(h)}" '
                        'rgba="1 0.6 0 0.15" group="3"/>'
                    )
                elif p.kind == "capsule":
                    r = h[0]
                    out.append(
                        f'      <geom type="capsule" pos="{_vec(c)}" size="{_f(r)} {_f(h[2] - r)}" '
                        f'rgba="{_vec(p.rgba)}"/>'
                    )
                else:
                    out.append(
                        f'      <geom type="box" pos="{_vec(c)}" size="{_vec(h)}" rgba="{_vec(p.rgba)}"/>'
                    )
            out.append("    </body>")
        for i, (name, cat) in enumerate(self.pool):
            shape = V.OBJECT_SHAPES[cat]
            out.append(f'    <body name="{name}" mocap="true" pos="{_vec((0.5 * i, 0, PARK_Z))}">')
            out.append(
                f'      <geom type="{shape.geom}" size="{_vec(shape.size)}" rgba="{_vec(shape.rgba)}" '
                'contype="0" conaffinity="0"/>'
            )
            out.append("    </body>")
        out += ["  </worldbody>", "</mujoco>", ""]
        return "\n".join(out)
