"""Scenes: shipped files load, meet their size targets, slots are geometrically valid (checked by
ray casting in stock MuJoCo), rooms and slots are reachable, the generator is deterministic, sampled
episodes are cluttered at the paper's scale (90-140 nodes when fully explored) with a unique goal,
and malformed or mis-annotated files raise SceneError naming the file and the problem. CPU; the
episode tests build each house's placement tables (geodesic fields) and compile its sampler."""

from __future__ import annotations

import functools
import os

import mujoco
import numpy as np
import pytest

from hron_jax.paths import REPO_ROOT
from hron_jax.scenes import SceneError, load_scene, walkable
from hron_jax.scenes import vocabulary as V
from hron_jax.scenes.generator import generate_house
from hron_jax.scenes.houses import SHIPPED

ROOT = REPO_ROOT
SCENES = os.path.join(ROOT, "scenes")
SHIPPED_FILES = sorted(SHIPPED)
HOUSES = [f for f in SHIPPED_FILES if f.startswith("house")]
EPS = 1e-4  # ray start offset into a slot


@functools.cache
def scene(name):
    return load_scene(os.path.join(SCENES, name))


@functools.cache
def sim(name):
    s = scene(name)
    d = mujoco.MjData(s.model)
    mujoco.mj_forward(s.model, d)
    return s.model, d


def ray(name, p, v):
    """(distance or inf, node index of the geom hit or -2 for nothing)."""
    m, d = sim(name)
    gid = np.zeros(1, np.int32)
    dist = mujoco.mj_ray(m, d, np.asarray(p, float), np.asarray(v, float), None, 1, -1, gid)
    if dist < 0:
        return np.inf, -2
    return dist, int(scene(name).geom_instance[gid[0]])


def _grid_xy(c, h, n=3):
    """n x n points over a slot's xy extent, 1 mm inside its border."""
    xs = np.linspace(c[0] - h[0] + 1e-3, c[0] + h[0] - 1e-3, n)
    ys = np.linspace(c[1] - h[1] + 1e-3, c[1] + h[1] - 1e-3, n)
    return [(x, y) for x in xs for y in ys]


# ---- files --------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", SHIPPED_FILES)
def test_shipped_scene_loads(name):
    m = mujoco.MjModel.from_xml_path(os.path.join(SCENES, name))  # stock MuJoCo
    assert m.nmat >= 1
    assert set(np.unique(m.geom_type)) <= {
        int(mujoco.mjtGeom.mjGEOM_BOX),
        int(mujoco.mjtGeom.mjGEOM_SPHERE),
        int(mujoco.mjtGeom.mjGEOM_CAPSULE),
    }
    s = scene(name)
    assert s.model.ngeom == m.ngeom == len(s.geom_instance) == len(s.geom_class)
    assert s.num_nodes == s.num_rooms + s.num_furniture + s.num_objects
    assert np.all(s.node_type[: s.num_rooms] == V.ROOM)
    assert np.all(V.CLASS_NODE_TYPE[s.category] == s.node_type)
    assert np.all((s.geom_class == V.STRUCTURE_CLASS) == (s.geom_instance < 0))
    fur = slice(s.num_rooms, s.num_rooms + s.num_furniture)
    assert np.all(s.instance_room[fur] >= 0)
    assert np.all(s.room_at(s.body_pos[fur, :2]) == s.instance_room[fur])


def test_shipped_files_are_up_to_date():
    for name, fn in SHIPPED.items():
        with open(os.path.join(SCENES, name)) as f:
            assert f.read() == fn(), f"{name} differs from its builder: run python -m hron_jax.scenes --all"


def test_default_house_is_a_real_home():
    s = scene("house.xml")
    room_types = {V.ROOMS[i] for i in s.vocab_index[: s.num_rooms]}
    fur_types = {V.FURNITURE[i] for i in s.vocab_index[s.num_rooms : s.num_rooms + s.num_furniture]}
    assert s.num_rooms >= 8 and len(room_types) >= 5
    assert s.num_furniture >= 30 and len(fur_types) >= 10
    assert s.room_area().sum() >= 120
    assert 200 <= s.model.ngeom <= 400
    assert {"kitchen", "dining_room", "bedroom", "bathroom", "corridor", "living_room"} <= room_types


def test_room_adjacency_matches_doors():
    s = scene("house.xml")
    idx = {s.names[r]: r for r in range(s.num_rooms)}
    A = s.room_adjacency
    assert np.array_equal(A, A.T) and not A.diagonal().any()
    assert A[idx["room:kitchen:0"], idx["room:dining_room:0"]]
    assert A[idx["room:bedroom:0"], idx["room:bathroom:0"]]  # en suite
    assert A[idx["room:corridor:0"], idx["room:office:0"]]
    assert not A[idx["room:kitchen:0"], idx["room:bedroom:0"]]
    assert not A[idx["room:living_room:0"], idx["room:bathroom:0"]]
    sym = scene("symmetric_room.xml")
    assert sym.num_rooms == 1 and len(sym.door_names) == 0 and not sym.room_adjacency.any()


@pytest.mark.parametrize("name", HOUSES)
def test_doors_connect_rooms_into_one_graph(name):
    s = scene(name)
    assert len(s.door_names) >= s.num_rooms - 1
    assert np.all(s.door_rooms[:, 0] != s.door_rooms[:, 1])
    assert np.all(s.door_half[:, :2].max(1) * 2 >= 1.0)  # doorway >= 1 m wide
    seen, todo = {0}, [0]
    while todo:
        r = todo.pop()
        for q in np.nonzero(s.room_adjacency[r])[0]:
            if q not in seen:
                seen.add(int(q))
                todo.append(int(q))
    assert seen == set(range(s.num_rooms))


# ---- slots ------------------------------------------------------------------------------------


def _furniture_geoms(s, f):
    g = np.nonzero(s.geom_instance == f)[0]
    return s.geom_aabb_center[g], s.geom_aabb_half[g]


@pytest.mark.parametrize("name", SHIPPED_FILES)
def test_on_top_slots_rest_on_a_free_top_face(name):
    s = scene(name)
    for k in np.nonzero(s.slot_relation == V.ON_TOP)[0]:
        f, c, h = s.slot_furniture[k], s.slot_center[k], s.slot_half[k]
        bottom = c[2] - h[2]
        gc, gh = _furniture_geoms(s, f)
        covers = (
            (np.abs(gc[:, 2] + gh[:, 2] - bottom) < 1e-6)
            & np.all(gc[:, :2] - gh[:, :2] <= c[:2] - h[:2] + 1e-6, 1)
            & np.all(gc[:, :2] + gh[:, :2] >= c[:2] + h[:2] - 1e-6, 1)
        )
        assert covers.any(), f"{s.slot_names[k]}: no top face of the furniture under the slot"
        for x, y in _grid_xy(c, h):
            dist, node = ray(name, (x, y, bottom + EPS), (0, 0, 1))
            assert not (node == f and dist < 2 * h[2]), f"{s.slot_names[k]}: furniture above the slot"
            dist, node = ray(name, (x, y, bottom + EPS), (0, 0, -1))
            assert node == f and dist < 2 * EPS, f"{s.slot_names[k]}: not supported at ({x}, {y})"


@pytest.mark.parametrize("name", SHIPPED_FILES)
def test_inside_slots_are_enclosed_cavities(name):
    s = scene(name)
    for k in np.nonzero(s.slot_relation == V.INSIDE)[0]:
        f, c, h = s.slot_furniture[k], s.slot_center[k], s.slot_half[k]
        hits = [ray(name, c, v)[1] == f for v in ((1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0))]
        # back and both sides closed; the front stays open so the camera can see inside
        assert sum(hits) >= 3, f"{s.slot_names[k]}: cavity open on {4 - sum(hits)} sides"
        dist, node = ray(name, c, (0, 0, 1))
        assert node == f and abs(dist - h[2]) < 1e-6, f"{s.slot_names[k]}: no board or top above"
        dist, node = ray(name, c, (0, 0, -1))
        assert node == f and abs(dist - h[2]) < 1e-6, f"{s.slot_names[k]}: no support below"
        for x, y in _grid_xy(c, h):  # the whole slot: free up to the ceiling, supported below
            dist, node = ray(name, (x, y, c[2] - h[2] + EPS), (0, 0, 1))
            assert node == f and abs(dist - (2 * h[2] - EPS)) < 1e-6, (
                f"{s.slot_names[k]}: ceiling at ({x}, {y})"
            )
            dist, node = ray(name, (x, y, c[2] - h[2] + EPS), (0, 0, -1))
            assert node == f and dist < 2 * EPS, f"{s.slot_names[k]}: not supported at ({x}, {y})"


@pytest.mark.parametrize("name", SHIPPED_FILES)
def test_under_slots_are_covered_and_on_the_floor(name):
    s = scene(name)
    for k in np.nonzero(s.slot_relation == V.UNDER)[0]:
        f, c, h = s.slot_furniture[k], s.slot_center[k], s.slot_half[k]
        assert abs(c[2] - h[2]) < 1e-6, f"{s.slot_names[k]}: bottom not on the floor"
        for x, y in _grid_xy(c, h):
            dist, node = ray(name, (x, y, EPS), (0, 0, 1))
            assert node == f and abs(dist - (2 * h[2] - EPS)) < 1e-6, (
                f"{s.slot_names[k]}: not covered at ({x}, {y})"
            )


@pytest.mark.parametrize("name", SHIPPED_FILES)
def test_goal_tuples_have_matching_slots(name):
    s = scene(name)
    assert len(s.goals) > 0 and s.goal_slots.shape == (len(s.goals), s.num_slots)
    for (o, rel, fc, rc), slots in zip(s.goals, s.goal_slots):
        assert slots.any()
        for k in np.nonzero(slots)[0]:
            f = s.slot_furniture[k]
            assert s.slot_relation[k] == rel and s.vocab_index[f] == fc
            assert s.vocab_index[s.instance_room[f]] == rc
            assert np.all(V.OBJECT_HALF[o] <= s.slot_half[k] + 1e-9)
            assert s.pool_count[o] > 0


def test_symmetric_room_is_mirrored():
    s = scene("symmetric_room.xml")
    assert np.allclose(s.start_pos[0, :2], (0, -2)) and np.isclose(s.start_yaw[0], np.pi / 2)
    static = s.geom_aabb_center[:, 2] > -1
    boxes = np.round(np.concatenate([s.geom_aabb_center, s.geom_aabb_half], 1)[static], 6)
    mirrored = boxes * np.array([-1, 1, 1, 1, 1, 1])
    assert sorted(map(tuple, boxes)) == sorted(map(tuple, mirrored))
    slots = np.round(np.concatenate([s.slot_center, s.slot_half, s.slot_relation[:, None]], 1), 6)
    assert sorted(map(tuple, slots)) == sorted(map(tuple, slots * np.array([-1, 1, 1, 1, 1, 1, 1])))
    fur = [s.names[i].split(":")[1] for i in range(s.num_rooms, s.num_rooms + s.num_furniture)]
    assert sorted(fur) == ["shelf", "shelf", "table", "table"]
    goals = {(V.OBJECTS[o], V.RELATIONS[r], V.FURNITURE[f]) for o, r, f, _ in s.goals}
    for obj in ("apple", "bowl", "gym_shoe"):
        for rel, fur_cat in (
            ("onTop", "table"),
            ("under", "table"),
            ("onTop", "shelf"),
            ("inside", "shelf"),
            ("under", "shelf"),
        ):
            assert (obj, rel, fur_cat) in goals


@pytest.mark.parametrize("name", SHIPPED_FILES)
def test_object_pool_parked_below_floor(name):
    s = scene(name)
    m, d = sim(name)
    obj = np.nonzero(s.node_type == V.OBJECT)[0]
    assert np.all(d.xpos[s.body_id[obj], 2] < -1) and np.all(s.mocap_id[obj] >= 0)
    assert np.all(s.pool_count[[V.OBJECTS.index(o) for o in V.HOUSE_OBJECTS]] >= 2)
    assert np.all(s.pool_count[[V.OBJECTS.index(o) for o in V.SYMBOLIC_OBJECTS]] == 0)
    assert s.bounds[0, 2] > -1  # bounds ignore the parked pool


@pytest.mark.parametrize("name", SHIPPED_FILES)
def test_rooms_doors_and_slots_reachable(name):
    s = scene(name)
    reach, xs, ys = walkable.scene_reachability(s, radius=walkable.ROBOT_RADIUS)
    X, Y = np.meshgrid(xs, ys)
    rooms = s.room_at(np.stack([X, Y], -1))
    assert set(np.unique(rooms[reach])) == set(range(s.num_rooms)), "some room unreachable"
    if len(s.door_names):
        assert np.all(walkable.nearest_reachable_distance(reach, xs, ys, s.door_center[:, :2]) < 0.1)
    corners = np.concatenate(
        [
            s.slot_center[:, :2] + s.slot_half[:, :2] * np.array(sgn) * 0.95
            for sgn in ((1, 1), (1, -1), (-1, 1), (-1, -1))
        ]
    )
    far = walkable.nearest_reachable_distance(reach, xs, ys, corners)
    names = [s.slot_names[i % s.num_slots] for i in np.nonzero(far >= 1.0)[0]]
    assert not names, f"slot corners beyond the 1 m success radius: {names}"


def test_room_at_numpy_and_jax():
    import jax.numpy as jnp

    s = scene("house.xml")
    pts = np.array([[1.0, 8.0], [12.0, 2.0], [-5.0, 0.0]])
    expect = [s.index_of("room:living_room:0"), s.index_of("room:office:0"), -1]
    assert list(s.room_at(pts)) == expect
    assert list(np.asarray(s.room_at(jnp.asarray(pts), xp=jnp))) == expect


# ---- generator --------------------------------------------------------------------------------


def test_generator_is_deterministic_and_varied(tmp_path):
    a, b, c = generate_house(11), generate_house(11), generate_house(12)
    assert a == b and a != c
    p = tmp_path / "house_11.xml"
    p.write_text(a)
    s = load_scene(p)
    assert s.num_rooms >= 7 and s.num_furniture >= 15 and s.room_area().sum() >= 100


# ---- episodes: clutter, goal uniqueness, scene scale (hron_jax.envs.placement) ------------------

N_EPISODES = 32


@functools.cache
def tables(name):
    """The scene's EpisodeTables with the default settings (what NavigationEnv builds)."""
    from hron_jax.envs import placement as P
    from hron_jax.sim import Simulator

    return P.build_tables(scene(name), Simulator.from_file(os.path.join(SCENES, name)).mj_model)


@functools.cache
def exploratory_sampler(name):
    import jax

    from hron_jax.envs import placement as P

    t = tables(name)
    return jax.jit(jax.vmap(lambda k: P.sample_exploratory(k, t)))


def exploratory_episodes(name, keys):
    import jax

    return jax.tree.map(np.asarray, exploratory_sampler(name)(keys))


def _keys(seed, n=N_EPISODES):
    import jax

    return jax.random.split(jax.random.PRNGKey(seed), n)


def _satisfies_goal(s, pl, goal):
    """bool[O]: active pool objects whose (category, relation, furniture category, room category)
    is the goal tuple (room -1: any), from the placement's furniture nodes (not the slot tables)."""
    off = s.num_rooms + s.num_furniture
    f = np.maximum(pl.furniture, 0)
    return (
        pl.active
        & (pl.furniture >= 0)
        & (s.vocab_index[off:] == goal[0])
        & (pl.relation == goal[1])
        & (s.vocab_index[f] == goal[2])
        & ((goal[3] < 0) | (s.vocab_index[s.instance_room[f]] == goal[3]))
    )


def _check_clutter_episodes(name, eps):
    """Per episode: 90-140 nodes once fully explored, one object per slot inside a usable slot
    that fits it, exactly one object (the target) satisfying the goal tuple. Returns per episode
    (confounders: active non-targets of the goal's category, near misses: those of them on the
    goal's furniture category or in the goal's room)."""
    s, t = scene(name), tables(name)
    off = s.num_rooms + s.num_furniture
    conf, near = [], []
    for i in range(len(eps.goal)):
        pl = type(eps.placement)(*(a[i] for a in eps.placement))
        goal, target, slots = eps.goal[i], int(eps.target[i]), eps.slot[i]
        active = np.nonzero(pl.active)[0]
        assert 90 <= off + len(active) <= 140, (name, i, off + len(active))
        assert len(set(slots[active].tolist())) == len(active) and np.all(slots[~pl.active] == -1)
        cat = s.vocab_index[off + active]
        assert np.all(t.slot_usable[slots[active], cat])
        assert np.all(pl.furniture[active] == s.slot_furniture[slots[active]])
        assert np.all(pl.relation[active] == s.slot_relation[slots[active]])
        half = V.OBJECT_HALF[cat]
        c, h = s.slot_center[slots[active]], s.slot_half[slots[active]]
        assert np.all(np.abs(pl.pos[active, :2] - c[:, :2]) <= h[:, :2] - half[:, :2] + 1e-5)
        np.testing.assert_allclose(pl.pos[active, 2], c[:, 2] - h[:, 2] + half[:, 2], atol=1e-5)
        sat = _satisfies_goal(s, pl, goal)
        assert np.nonzero(sat)[0].tolist() == [target], (name, i, goal, np.nonzero(sat)[0])
        same = active[(cat == goal[0]) & (active != target)]
        f = pl.furniture[same]
        conf.append(len(same))
        shared = (s.vocab_index[f] == goal[2]) | (s.vocab_index[s.instance_room[f]] == goal[3])
        near.append(int(shared.sum()))
    return np.array(conf), np.array(near)


def test_house_episodes_are_cluttered_and_goals_unique():
    """house.xml: every sampled exploratory episode has 90-140 nodes when fully explored (47 rooms
    + furniture, the target and 64 clutter objects: 112), objects of every house category in all
    three relations, exactly one object satisfying the goal tuple, and confounders: in at least
    90% of the episodes (measured: all) other instances of the goal's category, in at least half
    (measured: ~80%) one on the goal's furniture category or in the goal's room."""
    import jax
    import jax.numpy as jnp

    from hron_jax.graph_builder import GraphBuilder

    name = "house.xml"
    s = scene(name)
    eps = exploratory_episodes(name, _keys(0))
    conf, near = _check_clutter_episodes(name, eps)
    assert (conf >= 1).mean() >= 0.9 and (near >= 1).mean() >= 0.5, (conf, near)
    off = s.num_rooms + s.num_furniture
    for i in range(len(eps.goal)):
        act = eps.placement.active[i]
        assert set(s.vocab_index[off:][act].tolist()) == {V.OBJECTS.index(o) for o in V.HOUSE_OBJECTS}
        assert set(eps.placement.relation[i][act].tolist()) == {V.ON_TOP, V.INSIDE, V.UNDER}
    # The graph builder's fully explored graph (every node discovered) has exactly these nodes.
    gb = GraphBuilder(s)
    pl0 = jax.tree.map(lambda a: jnp.asarray(a[0]), eps.placement)
    g = gb.graph(jnp.ones(gb.max_nodes, bool), pl0, jnp.asarray(eps.pose[0]))
    assert int(g.nodes["mask"].sum()) == off + int(eps.placement.active[0].sum()) == 112
    assert gb.max_nodes == s.num_nodes == 47 + 72


@pytest.mark.parametrize("name", [f for f in HOUSES if f != "house.xml"])
def test_generated_house_episodes_are_cluttered_and_goals_unique(name):
    """The generated houses (26-31 pieces of furniture): 90-140 nodes too (measured 98-104)."""
    eps = exploratory_episodes(name, _keys(1, 16))
    conf, _ = _check_clutter_episodes(name, eps)
    assert (conf >= 1).mean() >= 0.9, conf


def test_episodes_are_deterministic_per_key():
    import jax
    import jax.numpy as jnp

    keys = _keys(0)
    a = exploratory_episodes("house.xml", keys)
    half = N_EPISODES // 2
    b = exploratory_episodes("house.xml", jnp.concatenate([keys[:half], keys[:half]]))
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)):
        np.testing.assert_array_equal(x[:half], y[:half])  # same key, same episode
        np.testing.assert_array_equal(y[:half], y[half:])  # wherever it sits in the batch
    assert not np.array_equal(a.placement.pos[:half], a.placement.pos[half:])


def test_clutter_keeps_the_other_draws_of_a_key():
    """Clutter draws from its own stream: goal, target and start of a key do not depend on it."""
    import jax

    from hron_jax.envs import placement as P

    t = tables("house.xml")
    keys = _keys(0)
    bare = jax.tree.map(
        np.asarray, jax.jit(jax.vmap(lambda k: P.sample_exploratory(k, t, num_clutter=0)))(keys)
    )
    full = exploratory_episodes("house.xml", keys)
    assert np.all(bare.placement.active.sum(1) == 1) and np.all(full.placement.active.sum(1) == 65)
    for f in ("goal", "target", "target_xy", "target_field", "pose"):
        np.testing.assert_array_equal(getattr(bare, f), getattr(full, f))


def test_directed_pairs_use_the_papers_objects():
    """Directed task: pairs only for bowl, gym shoe and apple (all three present), no clutter by
    default (the paper's symmetric room), and clutter on request keeps the goal unique."""
    import jax

    from hron_jax.envs import placement as P

    name = "symmetric_room.xml"
    s, t = scene(name), tables(name)
    assert {V.OBJECTS[o] for o in t.pairs[:, 0]} == {"bowl", "gym_shoe", "apple"}
    keys = _keys(0, 16)
    both = jax.jit(jax.vmap(lambda k: (P.sample_directed(k, t), P.sample_directed(k, t, 2, num_clutter=8))))
    bare, eps = jax.tree.map(np.asarray, both(keys))  # one compile for both
    assert np.all(bare.placement.active.sum(1) == 2)
    for i in range(len(keys)):
        pl = type(eps.placement)(*(a[i] for a in eps.placement))
        assert 2 + 2 + 1 <= pl.active.sum() <= 2 + 2 + 8
        assert np.nonzero(_satisfies_goal(s, pl, eps.goal[i]))[0].tolist() == [int(eps.target[i])]
        active = np.nonzero(pl.active)[0]
        assert len(set(eps.slot[i][active].tolist())) == len(active)


def test_stats_of_the_default_house():
    from hron_jax.scenes.__main__ import scene_stats

    st = scene_stats(os.path.join(SCENES, "house.xml"), tables=tables("house.xml"))
    assert (st["rooms"], st["furniture"], st["pool"], st["slots"]) == (9, 38, 72, 117)
    assert st["static_nodes"] == 47 and st["active_objects"] == 65 and st["explored_nodes"] == 112
    assert st["max_nodes"] == 119 and st["same_category"] >= 1


# ---- errors -----------------------------------------------------------------------------------

_GOOD_ROOM = '<body name="room:kitchen:0"><geom type="box" pos="0 0 -0.025" size="2 2 0.025"/></body>'


def _xml(body, material=True):
    asset = '<asset><material name="m"/></asset>' if material else ""
    return f"<mujoco>{asset}<worldbody>{body}</worldbody></mujoco>"


@pytest.mark.parametrize(
    "xml, words",
    [
        (
            '<mujoco><worldbody><geom type="box" size="1 1 1" bogus="1"/></worldbody></mujoco>',
            ["MuJoCo cannot load", "unrecognized attribute: 'bogus'"],
        ),
        (_xml('<geom type="box" size="1 1 0.1"/>'), ["without HRON annotations"]),
        (
            _xml(
                _GOOD_ROOM
                + '<body name="furniture:table:0" pos="5 5 0"><geom type="box" size=".5 .5 .4"/></body>'
            ),
            ["furniture:table:0", "outside every room"],
        ),
        (
            _xml('<body name="room:garage:0"><geom type="box" pos="0 0 -0.025" size="2 2 0.025"/></body>'),
            ["unknown room category 'garage'"],
        ),
        (
            _xml(_GOOD_ROOM + '<body name="furniture:piano:0"><geom type="box" size=".5 .5 .4"/></body>'),
            ["unknown furniture category 'piano'"],
        ),
        (
            _xml(
                _GOOD_ROOM + '<body name="furniture:table:0"><geom type="box" size=".5 .5 .4"/>'
                '<site name="furniture:table:0:beside:0" type="box" size=".1 .1 .1"/></body>'
            ),
            ["unknown relation 'beside'"],
        ),
        (
            _xml(
                _GOOD_ROOM + '<body name="furniture:table:0"><geom type="box" size=".5 .5 .4"/>'
                '<site name="furniture:table:0:onTop:0" type="sphere" size=".1"/></body>'
            ),
            ["furniture:table:0:onTop:0", 'type="box"'],
        ),
        (
            _xml(_GOOD_ROOM + '<body name="furniture:table:0"><geom type="cylinder" size=".5 .4"/></body>'),
            ["unsupported type 'cylinder'"],
        ),
        (_xml(_GOOD_ROOM, material=False), ["no <material>"]),
        (
            _xml(_GOOD_ROOM + '<site name="door:0" type="box" pos="0 0 1" size=".5 .3 1"/>'),
            ["door:0", "touches 1 room"],
        ),
        (
            _xml(_GOOD_ROOM + '<body name="object:apple:0"><geom type="sphere" size=".05"/></body>'),
            ["object:apple:0", "mocap"],
        ),
    ],
)
def test_errors_name_file_and_problem(tmp_path, xml, words):
    p = tmp_path / "bad_scene.xml"
    p.write_text(xml)
    with pytest.raises(SceneError) as e:
        load_scene(p)
    msg = str(e.value)
    assert str(p) in msg and "\n" not in msg
    for w in words:
        assert w in msg, msg


_BOX_ROOM = os.path.join(ROOT, "tests", "scenes", "box_room.xml")


def _truncated():
    with open(_BOX_ROOM) as f:
        return f.read()[:300]


# What a new user may pass instead of a scene: (file content, or None for a directory / no file; the
# key phrase of the error). Each must be one SceneError line, never MuJoCo's raw parser text.
@pytest.mark.parametrize(
    "content, phrase",
    [
        ("hello world\nthis is not xml\n", "not an XML file (it starts with 'hello world')"),
        (b"\x89PNG\r\n\x1a\n\x00\x00", "not an XML file"),
        ("", "the file is empty"),
        ("  \n", "the file is empty"),
        (_truncated(), "broken XML (line 6, column 7: unclosed token)"),
        (
            "<mujoco><worldbody><geom type='box' size='1 1 1'></worldbody>",
            "broken XML (line 1, column 52: mismatched tag)",
        ),
        ("<html><body>hi</body></html>", "root element is <html>, not <mujoco>"),
        (
            _xml('<geom type="box" size="1 1 0.1"/>', material=False),
            "a MuJoCo model without HRON annotations",
        ),
        (
            _xml('<body name="furniture:table:0"><geom type="box" size=".5 .5 .4"/></body>', material=False),
            "no room annotations: a scene needs at least one body named 'room:<category>:<k>'",
        ),
        (None, "is a directory, not a scene file"),
        ("missing", "file not found"),
    ],
    ids=[
        "text",
        "binary",
        "empty",
        "blank",
        "truncated",
        "mismatched",
        "html",
        "plain_mujoco",
        "no_rooms",
        "directory",
        "missing",
    ],
)
def test_bad_input_is_one_clear_scene_error(tmp_path, content, phrase):
    p = tmp_path / "scene.xml"
    if content is None:
        p.mkdir()
    elif isinstance(content, bytes):
        p.write_bytes(content)
    elif content != "missing":
        p.write_text(content)
    with pytest.raises(SceneError) as e:
        load_scene(p)
    msg = str(e.value)
    assert isinstance(e.value, ValueError)  # CLIs catch ValueError and exit 2 with this line
    assert msg.startswith(f"{p}: ") and "\n" not in msg, msg
    assert phrase in msg, msg
    assert "XML_ERROR" not in msg and "ParseXML" not in msg and "<material>" not in msg, msg


def test_directory_error_names_its_scenes():
    with pytest.raises(SceneError, match=r"pass one of its \.xml files \(house\.xml, "):
        load_scene(SCENES)


def test_nested_and_rotated_bodies_use_world_frame(tmp_path):
    p = tmp_path / "nested.xml"
    p.write_text(
        _xml(
            _GOOD_ROOM + '<body name="furniture:cabinet:0" pos="1 0.5 0" euler="0 0 90">'
            '<geom type="box" pos="0 0 0.4" size="0.3 0.2 0.4"/>'
            '<body name="drawer" pos="0.5 0 0"><geom type="box" pos="0 0 0.1" size="0.1 0.1 0.1"/>'
            '<site name="furniture:cabinet:0:onTop:0" type="box" pos="0 0 0.3" size="0.1 0.1 0.1"/>'
            '</body></body>'
        )
    )
    s = load_scene(p)
    f = s.index_of("furniture:cabinet:0")
    assert list(s.geom_instance) == [0, f, f]
    assert np.allclose(s.slot_center[0], (1.0, 1.0, 0.3)) and np.allclose(s.slot_half[0], 0.1)
    assert np.allclose(s.geom_aabb_half[1], (0.2, 0.3, 0.4))  # rotated by 90 degrees
    assert s.instance_room[f] == 0


def test_missing_file_and_fixture():
    with pytest.raises(SceneError, match="file not found"):
        load_scene("/nonexistent/scene.xml")
    s = load_scene(_BOX_ROOM)
    assert s.room_adjacency[0, 1] and len(s.goals) == 2
    assert s.room_floors.shape == (2, 2, 4) and s.room_floor_valid.tolist() == [[True, False], [True, True]]
    assert list(s.room_at([[3.0, 3.5], [1.0, 3.5], [-1.0, 0.0]])) == [1, -1, 0]
    assert np.allclose(s.room_area(), [16.0, 20.0])
