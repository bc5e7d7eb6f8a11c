"""Scene loader: one annotated MJCF file -> `Scene`, the static tables everything else uses.

Role: parse the naming scheme of docs/scene_format.md from a compiled MuJoCo model and return
numpy tables (they become JAX constants in the simulator, sensors, tasks and graph builder).
World-frame positions come from `mj_forward` on a fresh MjData, so nested bodies and rotated
geoms/sites are handled.

Errors: every bad input raises `SceneError` (a ValueError, so CLIs that catch ValueError/OSError print
it as one line) whose message is one line: the path, what is wrong, what to do. The file is checked in
order: it exists and is a file, it is well-formed XML with a <mujoco> root, MuJoCo compiles it, it has
HRON annotations and at least one room, then the per-element rules of docs/scene_format.md.

Shapes (N instances = R rooms + F furniture + O objects, in that order; G geoms; S slots; D doors):
- instance table: names (N,), node_type (N,) int32, category (N,) int32 class id,
  vocab_index (N,) int32, instance_room (N,) int32, body_id (N,), mocap_id (N,),
  body_pos (N, 3), aabb_center (N, 3), aabb_half (N, 3) float64.
- geoms: geom_instance (G,), geom_class (G,) int32, geom_aabb_center / geom_aabb_half (G, 3),
  geom_room (G,) int32.
- rooms: room_floors (R, FMAX, 4) [xmin, ymin, xmax, ymax] padded with (inf, inf, -inf, -inf),
  room_floor_valid (R, FMAX) bool, room_adjacency (R, R) bool.
- doors: door_center / door_half (D, 3), door_rooms (D, 2) int32 (room indices; a door touching more
  than two rooms connects every pair, door_rooms keeps the first two).
- slots: slot_furniture (S,) node index, slot_relation (S,), slot_center / slot_half (S, 3).
- object pool: pool_mocap / pool_node (len(OBJECTS), PMAX) int32 padded with -1, pool_count.
- starts: start_pos (K, 3), start_yaw (K,).
- goals: goals (Q, 4) int32 vocabulary indices (object, relation, furniture, room),
  goal_slots (Q, S) bool: which slots realise each goal for that object.
"""

from __future__ import annotations

import dataclasses
import os
import xml.etree.ElementTree as ET
from typing import Any

import mujoco
import numpy as np

from . import vocabulary as V

_ALLOWED_GEOMS = {
    int(mujoco.mjtGeom.mjGEOM_BOX): "box",
    int(mujoco.mjtGeom.mjGEOM_SPHERE): "sphere",
    int(mujoco.mjtGeom.mjGEOM_CAPSULE): "capsule",
}
_BOX = int(mujoco.mjtGeom.mjGEOM_BOX)
_SPHERE = int(mujoco.mjtGeom.mjGEOM_SPHERE)
_CAPSULE = int(mujoco.mjtGeom.mjGEOM_CAPSULE)
_TOL = 1e-6
# Floor tops must sit at z = 0; a looser tolerance than _TOL because authors type coordinates.
_FLOOR_TOL = 1e-4


class SceneError(ValueError):
    """A scene path that is not a well-formed MJCF file, that MuJoCo rejects, or whose annotations are
    missing or inconsistent. The message is one line: path, problem, fix."""


@dataclasses.dataclass(frozen=True, eq=False)
class Scene:
    """Static tables of one scene. All arrays are numpy; see the module docstring for shapes."""

    path: str
    model: Any  # mujoco.MjModel of the scene file (without the agent)

    names: tuple[str, ...]
    node_type: np.ndarray
    category: np.ndarray
    vocab_index: np.ndarray
    instance_room: np.ndarray
    body_id: np.ndarray
    mocap_id: np.ndarray
    body_pos: np.ndarray
    aabb_center: np.ndarray
    aabb_half: np.ndarray
    num_rooms: int
    num_furniture: int
    num_objects: int

    geom_instance: np.ndarray
    geom_class: np.ndarray
    geom_aabb_center: np.ndarray
    geom_aabb_half: np.ndarray
    geom_room: np.ndarray

    room_floors: np.ndarray
    room_floor_valid: np.ndarray
    room_adjacency: np.ndarray

    door_names: tuple[str, ...]
    door_center: np.ndarray
    door_half: np.ndarray
    door_rooms: np.ndarray

    slot_names: tuple[str, ...]
    slot_furniture: np.ndarray
    slot_relation: np.ndarray
    slot_center: np.ndarray
    slot_half: np.ndarray

    pool_mocap: np.ndarray
    pool_node: np.ndarray
    pool_count: np.ndarray

    start_pos: np.ndarray
    start_yaw: np.ndarray

    bounds: np.ndarray  # (2, 3): min and max corner of all static geoms (rooms, furniture, walls)
    goals: np.ndarray
    goal_slots: np.ndarray

    @property
    def num_nodes(self) -> int:
        return len(self.names)

    @property
    def num_slots(self) -> int:
        return len(self.slot_names)

    def index_of(self, name: str) -> int:
        """Node index of an instance name, e.g. 'furniture:table:0'."""
        try:
            return self.names.index(name)
        except ValueError:
            raise KeyError(f"{self.path}: no instance named {name!r}") from None

    def room_at(self, xy, xp=np):
        """Room index (-1 outside) of points xy (..., 2); pass xp=jax.numpy inside jit."""
        return room_at(self.room_floors, xy, xp)

    def room_area(self) -> np.ndarray:
        """(R,) floor area of each room in m^2 (floor boxes of one room must not overlap)."""
        w = np.where(self.room_floor_valid, self.room_floors[..., 2] - self.room_floors[..., 0], 0.0)
        h = np.where(self.room_floor_valid, self.room_floors[..., 3] - self.room_floors[..., 1], 0.0)
        return (w * h).sum(-1)


def room_at(room_floors, xy, xp=np):
    """Room index containing each point of xy (..., 2), -1 if none; first room wins on overlap.

    room_floors (R, FMAX, 4). Works with numpy or jax.numpy (xp) since padding boxes are empty.
    """
    xy = xp.asarray(xy)
    x = xy[..., None, None, 0]
    y = xy[..., None, None, 1]
    f = xp.asarray(room_floors)
    inside = (x >= f[..., 0]) & (x <= f[..., 2]) & (y >= f[..., 1]) & (y <= f[..., 3])
    in_room = inside.any(-1)  # (..., R)
    return xp.where(in_room.any(-1), xp.argmax(in_room, axis=-1), -1)


def _err(path, msg):
    # MuJoCo's parser messages span lines; callers print the error as a single CLI line.
    return SceneError(" ".join(f"{path}: {msg}".splitlines()))


def _name(model, objtype, i):
    return mujoco.mj_id2name(model, objtype, i) or ""


def _parse_category(path, kind, token, where):
    try:
        V.index(kind, token)
    except KeyError:
        known = ", ".join(V.vocab(kind))
        raise _err(path, f"{where}: unknown {kind} category {token!r}; use one of: {known}") from None
    return token


def _geom_aabb_half(gtype, size, xmat):
    """World AABB half extents of a primitive from its size and rotation matrix (3, 3)."""
    a = np.abs(xmat)
    if gtype == _BOX:
        return a @ size[:3]
    if gtype == _SPHERE:
        return np.full(3, size[0])
    # capsule: cylinder axis is local z
    return a[:, 2] * size[1] + size[0]


_SEE_FORMAT = "a scene is an MJCF <mujoco> XML file, see docs/scene_format.md"


def _check_xml(path):
    """Reject what is not a file or not well-formed MJCF before MuJoCo's raw parser sees it."""
    if os.path.isdir(path):
        xmls = sorted(f for f in os.listdir(path) if f.endswith(".xml"))[:3]
        hint = f"pass one of its .xml files ({', '.join(xmls)})" if xmls else "pass an MJCF .xml scene file"
        raise _err(path, f"is a directory, not a scene file; {hint}")
    if not os.path.exists(path):
        raise _err(
            path, "file not found; check the path (shipped scenes are in scenes/, e.g. scenes/house.xml)"
        )
    try:
        with open(path, "rb") as f:
            text = f.read()
    except OSError as e:
        raise _err(path, f"cannot read the file ({e.strerror}); check its permissions") from e
    if not text.strip():
        raise _err(path, f"the file is empty; {_SEE_FORMAT}")
    try:
        root = ET.fromstring(text)
    except ET.ParseError as e:
        start = text.lstrip(b"\xef\xbb\xbf \t\r\n")
        if not start.startswith(b"<"):
            head = start.split(b"\n")[0][:40].decode("utf-8", "replace").strip()
            raise _err(path, f"not an XML file (it starts with {head!r}); {_SEE_FORMAT}") from None
        line, col = e.position
        reason = str(e).split(":")[0]  # the rest repeats the position
        raise _err(
            path,
            f"broken XML (line {line}, column {col + 1}: {reason}); fix the XML there, or "
            "regenerate the file if it was cut off",
        ) from None
    if root.tag != "mujoco":
        raise _err(path, f"root element is <{root.tag}>, not <mujoco>; {_SEE_FORMAT}")


def _load_model(path):
    _check_xml(path)
    try:
        return mujoco.MjModel.from_xml_path(path)
    except Exception as e:  # MuJoCo raises ValueError with the parser's message
        raise _err(
            path,
            f"MuJoCo cannot load the file: {str(e).strip()}; fix what it reports (see docs/scene_format.md)",
        ) from e


def load_scene(path: str | os.PathLike) -> Scene:
    """Load and validate an annotated scene file. Raises SceneError naming the file and the fix."""
    path = os.fspath(path)
    model = _load_model(path)
    return scene_from_model(model, path)


def scene_from_model(model, path: str = "<model>") -> Scene:
    """Build the Scene tables from an already compiled MjModel (path only used in messages)."""
    # ---- annotated bodies -------------------------------------------------------------------
    rooms, furniture, objects = [], [], []  # (body id, name, category)
    for b in range(1, model.nbody):
        name = _name(model, mujoco.mjtObj.mjOBJ_BODY, b)
        tok = name.split(":")
        if tok[0] not in ("room", "furniture", "object"):
            continue
        if len(tok) != 3:
            raise _err(path, f"body {name!r}: expected '{tok[0]}:<category>:<k>'")
        kind = tok[0]
        cat = _parse_category(path, kind, tok[1], f"body {name!r}")
        entry = (b, name, cat)
        if kind == "room":
            if model.body_jntnum[b] or model.body_mocapid[b] >= 0:
                raise _err(path, f"room {name!r} must be static (no joints, not mocap)")
            rooms.append(entry)
        elif kind == "furniture":
            if model.body_jntnum[b] or model.body_mocapid[b] >= 0:
                raise _err(path, f"furniture {name!r} must be static (no joints, not mocap)")
            furniture.append(entry)
        else:
            if model.body_mocapid[b] < 0:
                raise _err(path, f"object {name!r} must be a mocap body (mocap=\"true\", child of worldbody)")
            objects.append(entry)
    # Missing annotations come first: any later message (no material, ...) would send the author
    # fixing the wrong thing.
    if not (rooms or furniture or objects):
        raise _err(
            path,
            "a MuJoCo model without HRON annotations: no body is named 'room:<category>:<k>', "
            "'furniture:<category>:<k>' or 'object:<category>:<k>'; annotate it as in "
            "docs/scene_format.md",
        )
    if not rooms:
        raise _err(
            path,
            "no room annotations: a scene needs at least one body named 'room:<category>:<k>' "
            "whose box geoms are the floors, see docs/scene_format.md",
        )
    if model.nmat < 1:
        raise _err(path, "no <material> defined; add one to <asset> (mjx.ray needs at least one)")
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)

    instances = rooms + furniture + objects
    kinds = [V.ROOM] * len(rooms) + [V.FURNITURE_NODE] * len(furniture) + [V.OBJECT] * len(objects)
    kind_names = ["room", "furniture", "object"]
    n = len(instances)
    names = tuple(e[1] for e in instances)
    node_type = np.array(kinds, np.int32)
    category = np.array([V.class_id(kind_names[k], e[2]) for k, e in zip(kinds, instances)], np.int32)
    vocab_index = np.array([V.index(kind_names[k], e[2]) for k, e in zip(kinds, instances)], np.int32)
    body_id = np.array([e[0] for e in instances], np.int32)
    mocap_id = np.array([model.body_mocapid[b] for b in body_id], np.int32)
    body_node = np.full(model.nbody, -1, np.int32)
    body_node[body_id] = np.arange(n)

    # ---- geoms: owner instance via nearest annotated ancestor --------------------------------
    owner = np.full(model.nbody, -1, np.int32)
    for b in range(1, model.nbody):  # parents precede children in MuJoCo's body order
        owner[b] = body_node[b] if body_node[b] >= 0 else owner[model.body_parentid[b]]
    geom_instance = np.empty(model.ngeom, np.int32)
    geom_half = np.empty((model.ngeom, 3))
    geom_center = data.geom_xpos.copy()
    for g in range(model.ngeom):
        gtype = int(model.geom_type[g])
        if gtype not in _ALLOWED_GEOMS:
            gname = _name(model, mujoco.mjtObj.mjOBJ_GEOM, g) or f"#{g}"
            tname = mujoco.mjtGeom(gtype).name.replace("mjGEOM_", "").lower()
            raise _err(path, f"geom {gname!r} has unsupported type {tname!r}; use box, sphere or capsule")
        geom_instance[g] = owner[model.geom_bodyid[g]]
        geom_half[g] = _geom_aabb_half(gtype, model.geom_size[g], data.geom_xmat[g].reshape(3, 3))
    geom_class = np.where(geom_instance >= 0, category[np.maximum(geom_instance, 0)], V.STRUCTURE_CLASS)
    geom_class = geom_class.astype(np.int32)

    # ---- instance AABBs -----------------------------------------------------------------------
    body_pos = data.xpos[body_id].copy()
    aabb_center = body_pos.copy()
    aabb_half = np.zeros((n, 3))
    for i in range(n):
        gs = np.nonzero(geom_instance == i)[0]
        if len(gs) == 0:
            raise _err(path, f"{names[i]!r} has no geoms; every instance needs at least one")
        lo = (geom_center[gs] - geom_half[gs]).min(0)
        hi = (geom_center[gs] + geom_half[gs]).max(0)
        aabb_center[i] = (lo + hi) / 2
        aabb_half[i] = (hi - lo) / 2

    # ---- room floors --------------------------------------------------------------------------
    nr = len(rooms)
    floors_per_room = []
    for r in range(nr):
        gs = np.nonzero(geom_instance == r)[0]
        boxes = []
        for g in gs:
            if model.geom_type[g] != _BOX:
                raise _err(path, f"room {names[r]!r}: floor geoms must be boxes")
            top = geom_center[g, 2] + geom_half[g, 2]
            if abs(top) > _FLOOR_TOL:
                raise _err(path, f"room {names[r]!r}: floor box top is at z={top:.4f}; it must be at z=0")
            lo, hi = geom_center[g] - geom_half[g], geom_center[g] + geom_half[g]
            boxes.append([lo[0], lo[1], hi[0], hi[1]])
        floors_per_room.append(boxes)
    fmax = max(len(b) for b in floors_per_room)
    room_floors = np.tile(np.array([np.inf, np.inf, -np.inf, -np.inf]), (nr, fmax, 1))
    room_floor_valid = np.zeros((nr, fmax), bool)
    for r, boxes in enumerate(floors_per_room):
        room_floors[r, : len(boxes)] = boxes
        room_floor_valid[r, : len(boxes)] = True

    # ---- room of furniture --------------------------------------------------------------------
    instance_room = np.full(n, -1, np.int32)
    nf = len(furniture)
    if nf:
        fr = room_at(room_floors, body_pos[nr : nr + nf, :2])
        for j in range(nf):
            if fr[j] < 0:
                x, y = body_pos[nr + j, :2]
                raise _err(
                    path,
                    f"furniture {names[nr + j]!r} at ({x:.2f}, {y:.2f}) is outside every room "
                    "floor; move it or extend a room's floor boxes",
                )
        instance_room[nr : nr + nf] = fr
    geom_room = room_at(room_floors, geom_center[:, :2]).astype(np.int32)
    geom_room[geom_center[:, 2] < -1.0] = -1  # parked pool objects are nowhere

    # ---- sites: doors, slots, starts ---------------------------------------------------------
    door_names, door_c, door_h, door_pairs = [], [], [], []
    slot_names, slot_f, slot_rel, slot_c, slot_h = [], [], [], [], []
    start_p, start_yaw = [], []
    adjacency = np.zeros((nr, nr), bool)
    name_to_node = {nm: i for i, nm in enumerate(names)}
    for s in range(model.nsite):
        name = _name(model, mujoco.mjtObj.mjOBJ_SITE, s)
        tok = name.split(":")
        c = data.site_xpos[s].copy()
        xmat = data.site_xmat[s].reshape(3, 3)
        if tok[0] == "start":
            start_p.append(c)
            start_yaw.append(np.arctan2(xmat[1, 0], xmat[0, 0]))
            continue
        if tok[0] not in ("door", "furniture"):
            continue
        if model.site_type[s] != _BOX:
            raise _err(path, f"site {name!r} must have type=\"box\"")
        h = np.abs(xmat) @ model.site_size[s]
        if not np.allclose(np.sort(np.abs(xmat), 1)[:, :2], 0, atol=1e-6):
            raise _err(path, f"site {name!r} must be axis-aligned (rotations by multiples of 90 deg only)")
        if tok[0] == "door":
            lo, hi = c[:2] - h[:2], c[:2] + h[:2]
            f = room_floors
            overlap = (
                (np.minimum(hi[0], f[..., 2]) - np.maximum(lo[0], f[..., 0]) > _TOL)
                & (np.minimum(hi[1], f[..., 3]) - np.maximum(lo[1], f[..., 1]) > _TOL)
            ).any(-1)
            touched = np.nonzero(overlap)[0]
            if len(touched) < 2:
                raise _err(
                    path,
                    f"door {name!r} touches {len(touched)} room floor(s); its box must reach "
                    "into the floors of both rooms it connects",
                )
            for a in touched:
                for b in touched:
                    if a != b:
                        adjacency[a, b] = True
            door_names.append(name)
            door_c.append(c)
            door_h.append(h)
            door_pairs.append(touched[:2])
            continue
        # furniture:<cat>:<k>:<relation>:<j>
        if len(tok) != 5:
            raise _err(path, f"site {name!r}: expected 'furniture:<category>:<k>:<relation>:<j>'")
        fname = ":".join(tok[:3])
        _parse_category(path, "furniture", tok[1], f"slot {name!r}")
        if tok[3] not in V.RELATIONS:
            raise _err(
                path, f"slot {name!r}: unknown relation {tok[3]!r}; use one of {', '.join(V.RELATIONS)}"
            )
        if fname not in name_to_node:
            raise _err(path, f"slot {name!r}: no furniture body named {fname!r}")
        node = name_to_node[fname]
        if owner[model.site_bodyid[s]] != node:
            raise _err(path, f"slot {name!r} must be a site inside the body {fname!r}")
        slot_names.append(name)
        slot_f.append(node)
        slot_rel.append(V.relation_id(tok[3]))
        slot_c.append(c)
        slot_h.append(h)

    # ---- object pool ----------------------------------------------------------------------------
    nobj_cat = len(V.OBJECTS)
    per_cat = [[] for _ in range(nobj_cat)]
    for i in range(nr + nf, n):
        per_cat[vocab_index[i]].append(i)
    pmax = max([len(p) for p in per_cat] + [1])
    pool_node = np.full((nobj_cat, pmax), -1, np.int32)
    pool_mocap = np.full((nobj_cat, pmax), -1, np.int32)
    for o, p in enumerate(per_cat):
        pool_node[o, : len(p)] = p
        pool_mocap[o, : len(p)] = mocap_id[p]
    pool_count = np.array([len(p) for p in per_cat], np.int32)

    # ---- bounds (static geometry only) -------------------------------------------------------------
    static = np.array(
        [geom_instance[g] < 0 or node_type[geom_instance[g]] != V.OBJECT for g in range(model.ngeom)], bool
    )
    bounds = np.stack(
        [(geom_center[static] - geom_half[static]).min(0), (geom_center[static] + geom_half[static]).max(0)]
    )

    slot_furniture = np.array(slot_f, np.int32).reshape(-1)
    slot_relation = np.array(slot_rel, np.int32).reshape(-1)
    slot_center = np.array(slot_c, np.float64).reshape(-1, 3)
    slot_half = np.array(slot_h, np.float64).reshape(-1, 3)
    goals, goal_slots = goal_table(
        vocab_index, instance_room, slot_furniture, slot_relation, slot_half, pool_count
    )

    return Scene(
        path=path,
        model=model,
        names=names,
        node_type=node_type,
        category=category,
        vocab_index=vocab_index,
        instance_room=instance_room,
        body_id=body_id,
        mocap_id=mocap_id,
        body_pos=body_pos,
        aabb_center=aabb_center,
        aabb_half=aabb_half,
        num_rooms=nr,
        num_furniture=nf,
        num_objects=len(objects),
        geom_instance=geom_instance,
        geom_class=geom_class,
        geom_aabb_center=geom_center,
        geom_aabb_half=geom_half,
        geom_room=geom_room,
        room_floors=room_floors,
        room_floor_valid=room_floor_valid,
        room_adjacency=adjacency,
        door_names=tuple(door_names),
        door_center=np.array(door_c).reshape(-1, 3),
        door_half=np.array(door_h).reshape(-1, 3),
        door_rooms=np.array(door_pairs, np.int32).reshape(-1, 2),
        slot_names=tuple(slot_names),
        slot_furniture=slot_furniture,
        slot_relation=slot_relation,
        slot_center=slot_center,
        slot_half=slot_half,
        pool_mocap=pool_mocap,
        pool_node=pool_node,
        pool_count=pool_count,
        start_pos=np.array(start_p).reshape(-1, 3),
        start_yaw=np.array(start_yaw).reshape(-1),
        bounds=bounds,
        goals=goals,
        goal_slots=goal_slots,
    )


def object_fits(obj_vocab_index: int, slot_half: np.ndarray) -> bool:
    """Whether an object category fits in a slot (3,) half size: full height and footprint."""
    h = V.OBJECT_HALF[obj_vocab_index]
    return bool(np.all(h <= slot_half + 1e-9))


def goal_table(vocab_index, instance_room, slot_furniture, slot_relation, slot_half, pool_count):
    """Valid goal tuples and the slots realising each.

    Returns goals (Q, 4) int32 of vocabulary indices (object, relation, furniture, room), sorted, and
    goal_slots (Q, S) bool. A goal is valid when the pool has that object and some slot of that
    relation on furniture of that category in a room of that category fits the object.
    """
    s = len(slot_furniture)
    table: dict[tuple[int, int, int, int], np.ndarray] = {}
    for o in range(len(V.OBJECTS)):
        if pool_count[o] == 0:
            continue
        for k in range(s):
            if not object_fits(o, slot_half[k]):
                continue
            f = slot_furniture[k]
            key = (o, int(slot_relation[k]), int(vocab_index[f]), int(vocab_index[instance_room[f]]))
            table.setdefault(key, np.zeros(s, bool))[k] = True
    keys = sorted(table)
    goals = np.array(keys, np.int32).reshape(-1, 4)
    goal_slots = np.stack([table[k] for k in keys]) if keys else np.zeros((0, s), bool)
    return goals, goal_slots
