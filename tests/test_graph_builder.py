"""Tests of hron_jax.graph_builder: discovery from real camera frames, features, edges, padding,
node-order permutation, pre-mapping, jit/vmap.

Scenes: scenes/symmetric_room.xml (one room, two tables, two shelves, a pool of 2 per object) and
tests/scenes/box_room.xml (kitchen + living room joined by a door, one table). Frames come from the
real ray-cast camera (hron_jax.sensors.Camera on the scene model, geom poses from MuJoCo with the
episode's objects placed), with a 60 deg field of view and a 3 m detection range so that each
pose sees a known set of instances. One jitted renderer per module keeps the suite fast on CPU.
"""

from __future__ import annotations

import dataclasses
import os
import xml.etree.ElementTree as ET

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pytest

from hron_jax import graph_types as GT
from hron_jax.graph_builder import GraphBuilder, GraphConfig, Placement
from hron_jax.paths import REPO_ROOT
from hron_jax.scenes import load_scene
from hron_jax.scenes import vocabulary as V
from hron_jax.sensors import Camera, CameraConfig

ROOT = REPO_ROOT
SYMMETRIC = os.path.join(ROOT, "scenes", "symmetric_room.xml")
BOX_ROOM = os.path.join(ROOT, "tests", "scenes", "box_room.xml")

CAM = CameraConfig(width=32, height=32, vfov_deg=60.0)
# min_pixels counted in the frame's own pixels (pixel_reference=None), so the synthetic frames of any
# size and the 32x32 renders below need exactly 2 pixels; the default rule is tested at the end.
GCFG = GraphConfig(min_pixels=2, detect_range=3.0, pixel_reference=None)

# Episode used throughout (symmetric room): a target on table:1, one object inside shelf:1, one
# under table:0 and a distractor lying on the floor with no furniture (its inRoom edge comes from
# the room under it). Everything else in the pool is unused.
EPISODE = {
    "object:apple:0": ("furniture:table:1", "onTop"),
    "object:bowl:0": ("furniture:shelf:1", "inside"),
    "object:mug:0": ("furniture:table:0", "under"),
    "object:gym_shoe:0": (None, (1.5, -1.5)),
}


# ------------------------------------------------------------------------------------ helpers
def make_placement(scene, episode=EPISODE) -> Placement:
    """Placement from {object name: (furniture name, relation) or (None, floor xy)}."""
    o0 = scene.num_rooms + scene.num_furniture
    active = np.zeros(scene.num_objects, bool)
    pos = np.zeros((scene.num_objects, 3), np.float32)
    pos[:, 2] = -5.0
    furniture = np.full(scene.num_objects, -1, np.int32)
    relation = np.zeros(scene.num_objects, np.int32)
    for name, (fname, rel) in episode.items():
        i = scene.index_of(name) - o0
        half = V.OBJECT_HALF[scene.vocab_index[o0 + i]]
        active[i] = True
        if fname is None:
            pos[i] = (rel[0], rel[1], half[2])
            continue
        f = scene.index_of(fname)
        k = np.nonzero((scene.slot_furniture == f) & (scene.slot_relation == V.relation_id(rel)))[0][0]
        c, h = scene.slot_center[k], scene.slot_half[k]
        pos[i] = (c[0], c[1], c[2] - h[2] + half[2])
        furniture[i] = f
        relation[i] = V.relation_id(rel)
    return Placement(jnp.asarray(active), jnp.asarray(pos), jnp.asarray(furniture), jnp.asarray(relation))


def geom_poses(scene, placement):
    """World geom poses (ngeom, 3), (ngeom, 9) with the episode's objects moved to their places."""
    m = scene.model
    d = mujoco.MjData(m)
    o0 = scene.num_rooms + scene.num_furniture
    for i in range(scene.num_objects):
        if bool(placement.active[i]):
            d.mocap_pos[scene.mocap_id[o0 + i]] = np.asarray(placement.pos[i])
    mujoco.mj_forward(m, d)
    return jnp.asarray(d.geom_xpos, jnp.float32), jnp.asarray(d.geom_xmat, jnp.float32)


def names_of(scene, mask):
    return {scene.names[i] for i in np.nonzero(np.asarray(mask)[: scene.num_nodes])[0]}


def expected_edges(scene, placement, discovered):
    """The legal typed edges among discovered nodes, from the scene tables (independent of the
    builder's edge layout): set of (sender, receiver, type)."""
    disc = np.asarray(discovered)
    out = set()
    for f in range(scene.num_rooms, scene.num_rooms + scene.num_furniture):
        r = int(scene.instance_room[f])
        out |= {(f, r, GT.IN_ROOM), (r, f, GT.REV_IN_ROOM)}
    for a, b in zip(*np.nonzero(scene.room_adjacency)):
        out.add((int(a), int(b), GT.ROOM_CONNECTED))
    o0 = scene.num_rooms + scene.num_furniture
    fwd = {0: (GT.ON_TOP, GT.REV_ON_TOP), 1: (GT.INSIDE, GT.REV_INSIDE), 2: (GT.UNDER, GT.REV_UNDER)}
    for i in range(scene.num_objects):
        if not bool(placement.active[i]):
            continue
        o, f = o0 + i, int(placement.furniture[i])
        if f >= 0:
            a, b = fwd[int(placement.relation[i])]
            out |= {(o, f, a), (f, o, b)}
            r = int(scene.instance_room[f])
        else:
            r = int(scene.room_at(np.asarray(placement.pos[i, :2])))
        out |= {(o, r, GT.IN_ROOM), (r, o, GT.REV_IN_ROOM)}
    return {e for e in out if disc[e[0]] and disc[e[1]]}


def live_edges(g):
    m = np.asarray(g.edges["mask"])
    s, r, t = (np.asarray(x)[m] for x in (g.senders, g.receivers, g.edges["edge_type"]))
    return list(zip(s.tolist(), r.tolist(), t.tolist()))


def check_graph(scene, gb, g, placement, discovered):
    """Invariants every graph must satisfy."""
    mask = np.asarray(g.nodes["mask"])
    assert mask.shape == (gb.max_nodes,)
    np.testing.assert_array_equal(mask, np.asarray(discovered))
    live = live_edges(g)
    assert len(live) == len(set(live)), "duplicate live edge"
    assert set(live) == expected_edges(scene, placement, discovered)
    for s, r, _ in live:
        assert mask[s] and mask[r]
    assert (
        len(
            GT.check_graph_types(
                g.nodes["node_type"], g.senders, g.receivers, g.edges["edge_type"], g.edges["mask"]
            )
        )
        == 0
    )
    dead = ~np.asarray(g.edges["mask"])
    for x in (g.senders, g.receivers, g.edges["edge_type"]):
        assert not np.asarray(x)[dead].any(), "dead edges must point at node 0 with type 0"
    for k in ("category", "node_type", "pos", "size"):
        assert not np.asarray(g.nodes[k])[~mask].any(), f"feature {k!r} leaks from a dead node"


# ------------------------------------------------------------------------------------ fixtures
@pytest.fixture(scope="module")
def sym():
    scene = load_scene(SYMMETRIC)
    cam = Camera(scene.model, CAM, scene.geom_instance, scene.geom_class)
    placement = make_placement(scene)
    xpos, xmat = geom_poses(scene, placement)
    render = jax.jit(cam.render_geoms)
    return dict(
        scene=scene,
        gb=GraphBuilder(scene, GCFG),
        placement=placement,
        frame=lambda pose: render(xpos, xmat, jnp.asarray(pose, jnp.float32)),
    )


@pytest.fixture(scope="module")
def fns():
    """Jitted builder functions, keyed by builder (a builder's tables are jit constants)."""
    cache = {}

    def get(gb):
        if id(gb) not in cache:
            cache[id(gb)] = (gb, jax.jit(gb.update), jax.jit(gb.graph))
        return cache[id(gb)][1:]

    return get


# ------------------------------------------------------------------------------------ tests
def test_nothing_before_a_frame_but_the_agents_room():
    scene = load_scene(BOX_ROOM)
    gb = GraphBuilder(scene, GCFG)
    placement = Placement.empty(scene.num_objects)
    for pose, room in (([-2.0, 1.5, 0.0], "room:kitchen:0"), ([3.0, 3.0, 1.0], "room:living_room:0")):
        disc = gb.reset(placement, jnp.asarray(pose))
        assert names_of(scene, disc) == {room}
        g = gb.graph(disc, placement, jnp.asarray(pose))
        assert not np.asarray(g.edges["mask"]).any()
        check_graph(scene, gb, g, placement, disc)
    # Outside every floor: nothing at all.
    assert not np.asarray(gb.reset(placement, jnp.asarray([9.0, 9.0, 0.0]))).any()


def test_discovery_threshold_and_range():
    """Synthetic frames: too few pixels, or pixels beyond the range, discover nothing."""
    scene = load_scene(BOX_ROOM)
    gb = GraphBuilder(scene, GCFG)
    placement = make_placement(scene, {"object:apple:0": ("furniture:table:0", "onTop")})
    pose = jnp.asarray([-3.5, 0.0, 0.0])
    table, apple1 = scene.index_of("furniture:table:0"), scene.index_of("object:apple:1")
    disc0 = gb.reset(placement, pose)
    inst = np.full((8, 8), -1, np.int32)
    depth = np.full((8, 8), 10.0, np.float32)

    def upd(inst, depth):
        return names_of(scene, gb.update(disc0, placement, pose, jnp.asarray(inst), jnp.asarray(depth)))

    inst[0, 0] = table
    depth[0, 0] = 1.0
    assert upd(inst, depth) == {"room:kitchen:0"}  # 1 pixel < min_pixels
    inst[0, 1] = table
    depth[0, 1] = 3.01
    assert upd(inst, depth) == {"room:kitchen:0"}  # 2nd pixel out of range
    depth[0, 1] = 2.99
    assert upd(inst, depth) == {"room:kitchen:0", "furniture:table:0"}
    inst[1, :2] = apple1  # not in this episode
    depth[1, :2] = 1.0
    assert "object:apple:1" not in upd(inst, depth)


def test_seen_table_is_discovered_with_its_features(sym, fns):
    scene, gb, placement = sym["scene"], sym["gb"], sym["placement"]
    update, graph = fns(gb)
    table = scene.index_of("furniture:table:0")
    zc = scene.aabb_center[table, 2]
    cases = [
        # (pose, hand-computed position of the table centre (-2.2, 0, zc) in the agent frame)
        ((-2.2, -1.5, np.pi / 2), (1.5, 0.0, zc)),  # 1.5 m straight ahead
        ((-3.2, -1.0, np.pi / 4), (np.sqrt(2.0), 0.0, zc)),  # diagonal, straight ahead
    ]
    for pose, want in cases:
        pose = jnp.asarray(pose, jnp.float32)
        disc = gb.reset(placement, pose)
        assert names_of(scene, disc) == {"room:living_room:0"}
        disc = update(disc, placement, pose, sym["frame"](pose).instance, sym["frame"](pose).depth)
        # The far shelf is in view but beyond the 3 m range; the objects are out of view.
        assert names_of(scene, disc) == {"room:living_room:0", "furniture:table:0"}
        g = graph(disc, placement, pose)
        check_graph(scene, gb, g, placement, disc)
        n = g.nodes
        assert int(n["category"][table]) == V.class_id("furniture", "table")
        assert int(n["node_type"][table]) == GT.FURNITURE
        np.testing.assert_allclose(n["pos"][table], want, atol=1e-5)
        np.testing.assert_allclose(n["size"][table], scene.aabb_half[table], atol=1e-6)
        assert set(live_edges(g)) == {(table, 0, GT.IN_ROOM), (0, table, GT.REV_IN_ROOM)}

    # Features follow the agent: from a generic pose, pos = R(-yaw) (centre - agent) for every node.
    pose = jnp.asarray([0.7, -2.1, 2.0], jnp.float32)
    g = graph(jnp.ones(gb.max_nodes, bool), placement, pose)
    c, s = np.cos(2.0), np.sin(2.0)
    centre = scene.aabb_center[: scene.num_furniture + 1]
    d = centre[:, :2] - [0.7, -2.1]
    want = np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], centre[:, 2]], -1)
    np.testing.assert_allclose(g.nodes["pos"][: len(want)], want, atol=1e-5)
    apple = scene.index_of("object:apple:0")
    np.testing.assert_allclose(g.nodes["size"][apple], V.OBJECT_HALF[V.index("object", "apple")])


def test_discovery_over_a_spin_matches_the_frames(sym, fns):
    """Turning on the spot: at every step the discovered set is exactly the agent's room plus every
    active instance some frame so far showed with >= min_pixels pixels in range; live edges are
    exactly the legal ones between discovered nodes; features of undiscovered nodes never leak."""
    scene, gb, placement = sym["scene"], sym["gb"], sym["placement"]
    update, graph = fns(gb)
    active = np.ones(gb.max_nodes, bool)
    active[scene.num_rooms + scene.num_furniture : scene.num_nodes] = np.asarray(placement.active)
    seen = np.zeros(gb.max_nodes, bool)
    seen[0] = True
    disc = gb.reset(placement, jnp.asarray([0.0, 0.3, 0.0]))
    history = []
    for k in range(12):
        pose = jnp.asarray([0.0, 0.3, k * np.pi / 6], jnp.float32)
        f = sym["frame"](pose)
        inst, depth = np.asarray(f.instance), np.asarray(f.depth)
        ok = (inst >= 0) & (depth < GCFG.detect_range)
        seen |= np.bincount(inst[ok], minlength=gb.max_nodes) >= GCFG.min_pixels
        disc = update(disc, placement, pose, f.instance, f.depth)
        np.testing.assert_array_equal(np.asarray(disc), seen & active)
        check_graph(scene, gb, graph(disc, placement, pose), placement, disc)
        history.append(len(names_of(scene, disc)))
    assert history == sorted(history)
    # From the room centre with a 3 m range the spin sees the tables, the floor distractor and the
    # mug under table:0, so object edges of both kinds (relation and floor inRoom) were exercised.
    final = names_of(scene, disc)
    assert {"furniture:table:0", "furniture:table:1", "object:gym_shoe:0", "object:mug:0"} <= final
    assert not any(
        n.startswith("object:") and n.split(":")[1] not in ("apple", "bowl", "mug", "gym_shoe") for n in final
    )


def test_edges_between_rooms_and_floor_objects():
    """box_room: roomConnected needs both rooms; a floor object joins the room it lies in."""
    scene = load_scene(BOX_ROOM)
    gb = GraphBuilder(scene, GCFG)
    placement = make_placement(
        scene, {"object:apple:0": ("furniture:table:0", "under"), "object:apple:1": (None, (3.0, 3.0))}
    )
    kitchen, living = scene.index_of("room:kitchen:0"), scene.index_of("room:living_room:0")
    a0, a1 = scene.index_of("object:apple:0"), scene.index_of("object:apple:1")
    table = scene.index_of("furniture:table:0")
    pose = jnp.asarray([-1.0, 0.0, 0.0])
    disc = gb.reset(placement, pose)

    def see(disc, *ids):
        inst = np.full((4, 4), -1, np.int32)
        inst[: len(ids)] = np.asarray(ids)[:, None]
        return gb.update(disc, placement, pose, jnp.asarray(inst), jnp.ones((4, 4)))

    steps = [
        (a1, set()),  # its room is unknown yet: no edge
        (
            living,
            {
                (kitchen, living, GT.ROOM_CONNECTED),
                (living, kitchen, GT.ROOM_CONNECTED),
                (a1, living, GT.IN_ROOM),
                (living, a1, GT.REV_IN_ROOM),
            },
        ),
        (a0, {(a0, kitchen, GT.IN_ROOM), (kitchen, a0, GT.REV_IN_ROOM)}),  # table unknown yet
        (
            table,
            {
                (table, kitchen, GT.IN_ROOM),
                (kitchen, table, GT.REV_IN_ROOM),
                (a0, table, GT.UNDER),
                (table, a0, GT.REV_UNDER),
            },
        ),
    ]
    have = set()
    for node, new in steps:
        disc = see(disc, node)
        g = gb.graph(disc, placement, pose)
        check_graph(scene, gb, g, placement, disc)
        have |= new
        assert set(live_edges(g)) == have


def test_padding_never_leaks(sym):
    """Larger N_MAX / E_MAX: identical live part, zero padding, identical GNN outputs."""
    from hron_jax.models.config import ModelConfig
    from hron_jax.models.encoders import SceneGraphEncoder

    scene, gb, placement = sym["scene"], sym["gb"], sym["placement"]
    big = GraphBuilder(
        scene,
        dataclasses.replace(GCFG, max_nodes=gb.max_nodes + 9, max_edges=gb.max_edges + 17),
    )
    poses = [jnp.asarray([0.0, 0.3, k * np.pi / 2], jnp.float32) for k in range(4)]
    frames = [sym["frame"](p) for p in poses]
    graphs = []
    for b in (gb, big):
        disc = b.reset(placement, poses[0])
        for p, f in zip(poses, frames):
            disc = b.update(disc, placement, p, f.instance, f.depth)
        graphs.append(b.graph(disc, placement, poses[-1]))
    g, h = graphs
    n, e = gb.max_nodes, gb.max_edges
    assert np.asarray(g.edges["mask"]).sum() > 0 and np.asarray(g.nodes["mask"]).sum() > 2
    for k in g.nodes:
        np.testing.assert_array_equal(g.nodes[k], h.nodes[k][:n])
        assert not np.asarray(h.nodes[k][n:]).any()
    for a, b_ in (
        (g.senders, h.senders),
        (g.receivers, h.receivers),
        (g.edges["edge_type"], h.edges["edge_type"]),
        (g.edges["mask"], h.edges["mask"]),
    ):
        np.testing.assert_array_equal(a, b_[:e])
        assert not np.asarray(b_[e:]).any()
    # The main model's graph branch (HGT + task-driven pooling over the goal's categories) reads
    # the same vector from both graphs.
    goal = jnp.asarray(
        [V.class_id("object", "apple"), V.class_id("furniture", "table"), V.class_id("room", "living_room")]
    )
    enc = SceneGraphEncoder(ModelConfig(hidden=16, heads=2, gnn_layers=2), V.NUM_CLASSES)
    params = jax.jit(enc.init)(jax.random.PRNGKey(0), g, goal)
    apply = jax.jit(enc.apply)
    out_g, out_h = apply(params, g, goal), apply(params, h, goal)
    assert np.abs(np.asarray(out_g)).sum() > 0
    np.testing.assert_allclose(out_g, out_h, rtol=1e-5, atol=1e-6)
    # The static type layout (node_type_counts): every real row has its range's type, the padding
    # rows are dead; HGT layers that slice the table by it read the same vector.
    counts = big.node_type_counts
    assert counts == gb.node_type_counts == (scene.num_rooms, scene.num_furniture, scene.num_objects)
    row_type = np.repeat(np.arange(GT.NUM_NODE_TYPES), counts)
    np.testing.assert_array_equal(np.asarray(big.node_type)[: sum(counts)], row_type)
    live = np.asarray(h.nodes["mask"])
    np.testing.assert_array_equal(
        np.asarray(h.nodes["node_type"])[: sum(counts)][live[: sum(counts)]], row_type[live[: sum(counts)]]
    )
    assert not live[sum(counts) :].any()
    sliced = SceneGraphEncoder(enc.config, V.NUM_CLASSES, counts)
    np.testing.assert_allclose(jax.jit(sliced.apply)(params, h, goal), out_g, rtol=1e-5, atol=1e-6)


def _permuted_scene_file(tmp_path):
    """symmetric_room.xml with its furniture bodies and its object bodies each in reversed order."""
    tree = ET.parse(SYMMETRIC)
    world = tree.getroot().find("worldbody")
    kids = list(world)
    for kind in ("furniture:", "object:"):
        idx = [i for i, el in enumerate(kids) if el.tag == "body" and el.get("name", "").startswith(kind)]
        for i, el in zip(idx, [kids[i] for i in reversed(idx)]):
            kids[i] = el
    for el in list(world):
        world.remove(el)
    world.extend(kids)
    path = tmp_path / "symmetric_permuted.xml"
    tree.write(path)
    return str(path)


def test_node_order_permutation(sym, tmp_path):
    scene, gb, placement = sym["scene"], sym["gb"], sym["placement"]
    perm_scene = load_scene(_permuted_scene_file(tmp_path))
    assert perm_scene.names != scene.names and sorted(perm_scene.names) == sorted(scene.names)
    perm = np.array([perm_scene.index_of(nm) for nm in scene.names])  # old node -> new node
    gp = GraphBuilder(perm_scene, GCFG)
    pplace = make_placement(perm_scene)
    # The geometry is the same, so the permuted scene's instance image is the relabelled one.
    relabel = np.append(perm, -1)
    disc_a = gb.reset(placement, jnp.asarray([0.0, 0.3, 0.0]))
    disc_b = gp.reset(pplace, jnp.asarray([0.0, 0.3, 0.0]))
    for k in range(0, 12, 2):
        pose = jnp.asarray([0.0, 0.3, k * np.pi / 6], jnp.float32)
        f = sym["frame"](pose)
        disc_a = gb.update(disc_a, placement, pose, f.instance, f.depth)
        disc_b = gp.update(disc_b, pplace, pose, jnp.asarray(relabel[np.asarray(f.instance)]), f.depth)
    ga, gb_ = gb.graph(disc_a, placement, pose), gp.graph(disc_b, pplace, pose)
    assert np.asarray(ga.edges["mask"]).sum() >= 4
    for k in ga.nodes:
        np.testing.assert_allclose(np.asarray(gb_.nodes[k])[perm], ga.nodes[k], atol=1e-6)
    name = lambda sc, i: sc.names[i]  # noqa: E731
    edges_a = {(name(scene, s), name(scene, r), t) for s, r, t in live_edges(ga)}
    edges_b = {(name(perm_scene, s), name(perm_scene, r), t) for s, r, t in live_edges(gb_)}
    assert edges_a == edges_b


def test_premap_contents_and_episode_edges(sym, fns):
    scene, placement = sym["scene"], sym["placement"]
    gb = GraphBuilder(scene, GraphConfig(min_pixels=2, detect_range=3.0), premap=True)
    update, graph = fns(gb)
    pose = jnp.asarray([2.2, -1.5, np.pi / 2], jnp.float32)  # in front of table:1 (apple on top)
    disc = gb.reset(placement, pose)
    want = {n for n in scene.names if not n.startswith("object:")}
    assert names_of(scene, disc) == want  # never an object, not even the target
    g = graph(disc, placement, pose)
    check_graph(scene, gb, g, placement, disc)
    assert len(live_edges(g)) == 2 * scene.num_furniture  # furniture <-> room only
    disc = update(disc, placement, pose, sym["frame"](pose).instance, sym["frame"](pose).depth)
    assert names_of(scene, disc) == want | {"object:apple:0"}
    g = graph(disc, placement, pose)
    check_graph(scene, gb, g, placement, disc)
    apple, t1 = scene.index_of("object:apple:0"), scene.index_of("furniture:table:1")
    assert {(apple, t1, GT.ON_TOP), (t1, apple, GT.REV_ON_TOP), (apple, 0, GT.IN_ROOM)} <= set(live_edges(g))

    # A new episode (reset) puts the apple under table:0: its edges change with the placement.
    other = make_placement(scene, {"object:apple:0": ("furniture:table:0", "under")})
    disc = gb.reset(other, pose)
    assert names_of(scene, disc) == want
    t0 = scene.index_of("furniture:table:0")
    disc = disc.at[apple].set(True)  # as if seen
    g = graph(disc, other, pose)
    check_graph(scene, gb, g, other, disc)
    assert {(apple, t0, GT.UNDER), (t0, apple, GT.REV_UNDER)} <= set(live_edges(g))
    assert not {e for e in live_edges(g) if t1 in e[:2] and apple in e[:2]}
    np.testing.assert_allclose(
        g.nodes["pos"][apple, 2], np.asarray(other.pos)[apple - scene.num_rooms - scene.num_furniture, 2]
    )


def test_jit_vmap_batch_matches_single_envs(sym, fns):
    gb, placement = sym["gb"], sym["placement"]
    poses = jnp.asarray([[-2.2, -1.5, np.pi / 2], [2.2, -1.5, np.pi / 2], [0.0, 0.3, np.pi]], jnp.float32)
    frames = [sym["frame"](p) for p in poses]
    inst = jnp.stack([f.instance for f in frames])
    depth = jnp.stack([f.depth for f in frames])
    batch = jax.tree_util.tree_map(lambda x: jnp.broadcast_to(x, (3,) + x.shape), placement)

    @jax.jit
    @jax.vmap
    def step(pl, pose, inst, depth):
        disc = gb.update(gb.reset(pl, pose), pl, pose, inst, depth)
        return disc, gb.graph(disc, pl, pose)

    discs, graphs = step(batch, poses, inst, depth)
    assert graphs.nodes["pos"].shape == (3, gb.max_nodes, 3)
    assert graphs.senders.shape == (3, gb.max_edges)
    for b in range(3):
        disc = gb.update(gb.reset(placement, poses[b]), placement, poses[b], inst[b], depth[b])
        g = gb.graph(disc, placement, poses[b])
        np.testing.assert_array_equal(discs[b], disc)
        for x, y in zip(jax.tree_util.tree_leaves(g), jax.tree_util.tree_leaves(graphs)):
            np.testing.assert_allclose(y[b], x, atol=1e-6)
    # The three poses see different things.
    assert len({tuple(np.asarray(d)) for d in discs}) == 3


def test_capacity_errors():
    scene = load_scene(BOX_ROOM)
    with pytest.raises(ValueError, match="max_nodes"):
        GraphBuilder(scene, GraphConfig(max_nodes=scene.num_nodes - 1))
    with pytest.raises(ValueError, match="max_edges"):
        GraphBuilder(scene, GraphConfig(max_edges=3))


# ------------------------------------------------------------------------ fair discovery rule
def test_frame_min_pixels_scales_with_the_frame():
    """Default rule: min_pixels counted at 128 x 128, i.e. the instance covers >= 2 / 128^2 of the frame
    (at least one pixel); pixel_reference=None counts the frame's own pixels."""
    g = GraphConfig()
    assert (g.min_pixels, g.pixel_reference) == (2, 128)
    want = {(32, 32): 1, (64, 64): 1, (96, 96): 2, (128, 128): 2, (160, 120): 3, (256, 256): 8, (8, 8): 1}
    assert {wh: g.frame_min_pixels(*wh) for wh in want} == want
    assert GraphConfig(min_pixels=1).frame_min_pixels(128, 128) == 1
    assert GraphConfig(min_pixels=3, pixel_reference=64).frame_min_pixels(128, 128) == 12
    assert {GCFG.frame_min_pixels(s, s) for s in (8, 32, 128, 256)} == {2}
    for bad in (dict(pixel_reference=0), dict(min_pixels=0)):
        with pytest.raises(ValueError, match=next(iter(bad))):
            GraphConfig(**bad)

    # update reads the frame size from the instance image: one in-range pixel of the table.
    scene = load_scene(BOX_ROOM)
    placement = Placement.empty(scene.num_objects)
    pose = jnp.asarray([-3.5, 0.0, 0.0])
    table = scene.index_of("furniture:table:0")
    for size, cfg, found in ((32, g, True), (64, g, True), (128, g, False), (32, GCFG, False)):
        gb = GraphBuilder(scene, cfg)
        inst = np.full((size, size), -1, np.int32)
        inst[3, 5] = table
        disc = gb.update(
            gb.reset(placement, pose), placement, pose, jnp.asarray(inst), jnp.ones((size, size))
        )
        assert bool(disc[table]) == found, (size, cfg)


def _apple_approach(size, rules, dists, yaws):
    """box_room, apple on the table top (centre (-2, 0, 0.795)); the agent at (-2 + d, 0) walks at it
    along -x (through the door for d > 2), heading pi + yaw. -> discovered bool[rule, yaw, d] of
    GraphBuilder.update from one fresh state per frame (120 deg camera, 1 m high, size x size)."""
    scene = load_scene(BOX_ROOM)
    placement = make_placement(scene, {"object:apple:0": ("furniture:table:0", "onTop")})
    apple = scene.index_of("object:apple:0")
    np.testing.assert_allclose(np.asarray(placement.pos)[0], (-2.0, 0.0, 0.795), atol=1e-6)
    cam = Camera(scene.model, CameraConfig(width=size, height=size), scene.geom_instance, scene.geom_class)
    xpos, xmat = geom_poses(scene, placement)
    builders = [GraphBuilder(scene, r) for r in rules]
    yy, dd = np.meshgrid(yaws, dists, indexing="ij")
    poses = jnp.asarray(np.stack([-2.0 + dd, 0 * dd, np.pi + yy], -1).reshape(-1, 3), jnp.float32)

    @jax.jit
    def flags(poses):
        def one(pose):
            f = cam.render_geoms(xpos, xmat, pose)
            return jnp.stack(
                [
                    b.update(b.reset(placement, pose), placement, pose, f.instance, f.depth)[apple]
                    for b in builders
                ]
            )

        return jax.lax.map(one, poses, batch_size=128)

    return np.asarray(flags(poses)).reshape(len(yaws), len(dists), len(rules)).transpose(2, 0, 1)


def test_fair_rule_discovers_small_objects_outside_the_success_radius_at_32():
    """Apple (r = 4.5 cm) approached head-on, camera 120 deg vfov, at 8 sub-pixel yaw phases spanning
    half a 32x32 pixel (by the mirror symmetry of the view, that is every phase). Pixel centres are
    uniform in tan-space, pitch p_s = 2 tan(60 deg) / s (p32 = 0.108, p128 = 0.0271), and the apple's
    image contains the disk of radius r / d (d = z-depth = xy distance) and lies in the disk of radius
    r / (d cos(off-axis angle)). Bounds, for every phase:
    - a disk of diameter < 1 pixel holds at most one pixel centre, so 2 frame pixels at 32x32 (the old
      rule) are impossible beyond 2r / p32 = 0.83 m (< 0.9 px at d >= 1 m, off-axis included): the
      old rule can only add the apple's node inside the 1 m success radius;
    - a disk of radius >= 1 pixel holds >= 2 pixel centres: the 128x128 reference (2 pixels) always
      discovers it by r / p128 = 1.66 m; radius >= 1/sqrt(2) pixel holds >= 1: the fair rule (1 pixel
      at 32x32) always does by r / (0.707 p32) = 0.59 m, the old rule by r / p32 = 0.42 m.
    Beyond the guarantees the fair rule's first discovery is point-sampling luck; over the phases its
    median is outside the success radius (bench discovery: 1.35 m at 32x32, 2.64 m at 128x128)."""
    p32 = 2 * np.tan(np.radians(60)) / 32
    yaws = np.arctan((np.arange(8) + 0.5) / 16 * p32)  # the scene is mirror-symmetric about y = 0
    dists = 2.5 / 1.02 ** np.arange(94)  # 2.5 m -> 0.39 m, 2 % steps
    old, fair = _apple_approach(32, [GraphConfig(pixel_reference=None), GraphConfig()], dists, yaws)
    first = lambda f: np.where(f.any(-1), dists[np.argmax(f, -1)], 0.0)  # per phase, 0: never
    assert not old[:, dists >= 1.0].any()
    assert old[:, np.argmin(np.abs(dists - 0.4))].all()
    assert (first(old) <= 0.83).all() and (first(fair) >= first(old)).all()
    assert fair[:, np.argmax(dists <= 0.58)].all()
    assert np.median(first(fair)) > 1.0 > np.median(first(old))
    ref = _apple_approach(128, [GraphConfig()], np.array([3.5, 1.6]), yaws)[0]
    assert ref[:, 1].all() and not ref[:, 0].any()  # 3.5 m: < 1 px (at most 1 centre)
