"""hron_jax.analysis: attention reductions on hand-built records, world positions against the
scene tables, every figure on a synthetic navigation record (no training), and `collect` on the
choice task with a small untrained model (one compile)."""

from types import SimpleNamespace

import matplotlib

matplotlib.use('Agg')
import matplotlib.pyplot as plt
import numpy as np
import pytest

from hron_jax import analysis as A
from hron_jax import graph_types as GT
from hron_jax.scenes import vocabulary as V

ROOM_C = V.class_id('room', 'kitchen')
TABLE_C = V.class_id('furniture', 'table')
SHELF_C = V.class_id('furniture', 'shelf')
APPLE_C = V.class_id('object', 'apple')
BOOK_C = V.class_id('object', 'book')


def toy_record(task='exploratory', alpha=None, pose=(0.0, 0.0, 0.0)):
    """One episode, one step. Nodes: 0 kitchen, 1 table, 2 shelf, 3 apple (onTop table),
    4 book (dead), 5 padding. Edges (sender -> receiver, type):
      0: 1 -> 0 inRoom, 1: 2 -> 0 inRoom, 2: 3 -> 1 onTop, 3: 0 -> 1 rev_inRoom,
      4: 0 -> 2 rev_inRoom, 5: 1 -> 3 rev_onTop, 6: 4 -> 1 onTop (dead sender), 7: padding."""
    cat = np.array([ROOM_C, TABLE_C, SHELF_C, APPLE_C, BOOK_C, 0])
    ntype = np.array([GT.ROOM, GT.FURNITURE, GT.FURNITURE, GT.OBJECT, GT.OBJECT, 0])
    mask = np.array([1, 1, 1, 1, 0, 0], bool)
    s = np.array([1, 2, 3, 0, 0, 1, 4, 0])
    r = np.array([0, 0, 1, 1, 2, 3, 1, 0])
    et = np.array(
        [GT.IN_ROOM, GT.IN_ROOM, GT.ON_TOP, GT.REV_IN_ROOM, GT.REV_IN_ROOM, GT.REV_ON_TOP, GT.ON_TOP, 0]
    )
    em = np.array([1, 1, 1, 1, 1, 1, 1, 0], bool)
    if alpha is None:
        # Receiver 0 (in-edges 0, 1): 0.8 / 0.2; receiver 1 (in-edges 2, 3): 0.9 / 0.1 (edge 6 is
        # dead); receivers 2, 3 have a single in-edge: 1. Two heads with equal values, two layers.
        a = np.array([0.8, 0.2, 0.9, 0.1, 1.0, 1.0, 0.0, 0.0])
        alpha = np.stack([a, a], -1)[None].repeat(2, 0)  # [L, M, H]
    goal = np.array([APPLE_C, TABLE_C, ROOM_C])  # apple onTop table in kitchen
    pos = np.zeros((6, 3))
    pool = (mask & np.isin(cat, goal)).astype(np.float32)
    e = lambda x: np.asarray(x)[None, None]
    return A.Record(
        task=task,
        pooling='task',
        category=e(cat),
        node_type=e(ntype),
        node_mask=e(mask),
        pos=e(pos),
        senders=e(s),
        receivers=e(r),
        edge_type=e(et),
        edge_mask=e(em),
        alpha=e(alpha),
        pool_weights=e(pool),
        goal_classes=e(goal),
        pose=e(np.asarray(pose, np.float32)),
        action=np.zeros((1, 1), np.int32),
        valid=np.ones((1, 1), bool),
        success=np.ones(1),
        spl=np.ones(1),
        end=np.zeros(1, np.int64),
    )


def test_live_edges_and_uniform_attention():
    rec = toy_record()
    live = A.live_edges(rec)[0, 0]
    np.testing.assert_array_equal(live, [1, 1, 1, 1, 1, 1, 0, 0])  # dead sender, padding out
    u = A.uniform_alpha(rec)[0, 0]
    np.testing.assert_allclose(u, [0.5, 0.5, 0.5, 0.5, 1.0, 1.0, 0.0, 0.0])
    # An illegal (edge type, sender type, receiver type) triple carries no attention either.
    bad = toy_record()
    bad.edge_type[0, 0, 0] = GT.ROOM_CONNECTED  # furniture -> room is not roomConnected
    assert not A.live_edges(bad)[0, 0, 0]
    # Per-relation softmax (the paper's HGT): receiver 1's in-edges 2 (object onTop) and 3
    # (room rev_inRoom) are different relations, so each is alone in its group; receiver 0's two
    # inRoom edges (both furniture -> room) still share one.
    per = toy_record()
    per.hgt_softmax = 'per_relation'
    np.testing.assert_allclose(A.uniform_alpha(per)[0, 0], [0.5, 0.5, 1.0, 1.0, 1.0, 1.0, 0.0, 0.0])


def test_edge_type_mass_and_node_attention():
    rec = toy_record()
    st = A.edge_type_mass(rec)
    assert st['mass'].shape == (2, 2, GT.NUM_EDGE_TYPES)
    np.testing.assert_allclose(st['mass'].sum(-1), 1.0)
    # Total attention = 4 receivers x 1: inRoom 0.8 + 0.2, onTop 0.9, rev_inRoom 0.1 + 1, rev_onTop 1.
    want = np.zeros(GT.NUM_EDGE_TYPES)
    want[[GT.IN_ROOM, GT.ON_TOP, GT.REV_IN_ROOM, GT.REV_ON_TOP]] = [1.0, 0.9, 1.1, 1.0]
    np.testing.assert_allclose(st['mass'][0, 0], want / 4)
    uni = np.zeros(GT.NUM_EDGE_TYPES)
    uni[[GT.IN_ROOM, GT.ON_TOP, GT.REV_IN_ROOM, GT.REV_ON_TOP]] = [1.0, 0.5, 1.5, 1.0]
    np.testing.assert_allclose(st['uniform'], uni / 4)
    assert st['edges'][GT.ON_TOP] == 1  # the dead-sender edge is not counted

    received, uniform = A.node_attention(rec)
    # Node 0 sends edges 3, 4 (0.1 + 1); node 1 sends 0, 5 (0.8 + 1); 2 sends 1; 3 sends 2.
    np.testing.assert_allclose(received[0, 0, 0, :4], [1.1, 1.8, 0.2, 0.9])
    np.testing.assert_allclose(uniform[0, 0, :4], [1.5, 1.5, 0.5, 0.5])
    assert received[0, 0, 0, 4:].sum() == 0


def test_goal_concentration_pool_shares_and_roles():
    rec = toy_record()
    np.testing.assert_array_equal(rec.is_goal[0, 0], [1, 1, 0, 1, 0, 0])
    g = A.goal_concentration(rec)
    assert g['pool_model'][0] == pytest.approx(1.0)  # task pooling: all from goal nodes
    assert g['pool_mean'][0] == pytest.approx(3 / 4)  # mean pooling: 3 of 4 live nodes
    assert g['goal_fraction'][0] == pytest.approx(3 / 4) and g['with_goal'] == 1.0
    # Before any goal-category node is seen the pooled share is undefined: such steps are left out.
    none = toy_record()
    none.goal_classes[:] = BOOK_C
    assert A.goal_concentration(none)['pool_model'].size == 0
    # Goal nodes 0, 1, 3 receive 1.1/1.5, 1.8/1.5, 0.9/0.5; the shelf 0.2/0.5.
    np.testing.assert_allclose(np.sort(g['hgt_goal']), np.sort([1.1 / 1.5, 1.8 / 1.5, 0.9 / 0.5]))
    np.testing.assert_allclose(g['hgt_other'], [0.2 / 0.5])
    roles = A.node_roles(rec)[0, 0]
    np.testing.assert_array_equal(roles, [2, 1, 4, 0, -1, -1])  # room, furniture, other, object
    rs = A.role_shares(rec)
    np.testing.assert_allclose(rs['model'][:3], [1 / 3, 1 / 3, 1 / 3])
    np.testing.assert_allclose(rs['mean'][[0, 1, 2, 4]], [0.25] * 4)
    s = A.summary(rec)
    assert s['pool_goal_share_model'] == 1.0 and s['steps'] == 1


def test_world_positions_match_scene_tables():
    """Positions from the graph builder (agent frame) map back onto the scene's AABB centres."""
    import jax.numpy as jnp

    from hron_jax.envs import DEFAULT_SCENES
    from hron_jax.graph_builder import GraphBuilder, Placement
    from hron_jax.scenes.loader import load_scene

    scene = load_scene(DEFAULT_SCENES['exploratory'])
    gb = GraphBuilder(scene)
    pose = jnp.array([3.7, 5.2, 2.1])
    g = gb.graph(gb.real, Placement.empty(scene.num_objects), pose)
    static = scene.num_rooms + scene.num_furniture
    rec = toy_record(pose=pose)
    rec.pos = np.asarray(g.nodes['pos'])[None, None]
    xy = A.world_positions(rec)[0, 0]
    np.testing.assert_allclose(xy[:static], scene.aabb_center[:static, :2], atol=1e-4)
    # The choice task stores canvas coordinates: returned as they are.
    rec.task = 'choice'
    np.testing.assert_array_equal(A.world_positions(rec)[0, 0], rec.pos[0, 0, :, :2])


def test_figures_draw():
    """Each figure draws what the toy record holds: the values below are worked out by hand from
    toy_record's docstring (as in the tests above), for the HGT record and for a model without
    attention (GCN)."""
    import dataclasses

    from matplotlib.collections import PathCollection
    from matplotlib.colors import to_rgb

    from hron_jax import goals
    from hron_jax.envs import DEFAULT_SCENES
    from hron_jax.scenes.loader import load_scene

    scene = load_scene(DEFAULT_SCENES['exploratory'])
    pose = np.array([2.0, 2.0, 0.5])
    # Layer 1 (the last, which the map and the goal concentration read) has toy_record's attention;
    # layer 0 differs on the in-edges of node 1 (edges 2, 3: 0.6 / 0.4) and of node 0 (0.5 / 0.5).
    a = np.array([0.8, 0.2, 0.9, 0.1, 1.0, 1.0, 0.0, 0.0])
    alpha0 = np.array([0.5, 0.5, 0.6, 0.4, 1.0, 1.0, 0.0, 0.0])
    rec = toy_record(pose=pose, alpha=np.stack([alpha0, a])[..., None].repeat(2, -1))
    goal = np.asarray(
        goals.encode_goal(
            V.index('object', 'apple'),
            V.relation_id('onTop'),
            V.index('furniture', 'table'),
            V.index('room', 'kitchen'),
        )
    )
    rec.env = SimpleNamespace(scene=scene)
    rec.states = SimpleNamespace(obs={'goal': goal[None]})
    rec.pos = np.random.default_rng(0).uniform(-2, 2, rec.pos.shape)
    gcn = toy_record(pose=pose, alpha=np.zeros((0, 8, 1)))  # a model without attention
    gcn.env, gcn.states, gcn.pos = rec.env, rec.states, rec.pos

    # By hand: live nodes 0-3 (kitchen, table, shelf, apple; the book and the padding row are
    # dead), goal-category nodes 0, 1, 3; live edges 0-5 with layer attention a and uniform u.
    c, s = np.cos(pose[2]), np.sin(pose[2])
    p = rec.pos[0, 0, :4, :2]
    world = pose[:2] + np.stack([c * p[:, 0] - s * p[:, 1], s * p[:, 0] + c * p[:, 1]], -1)
    senders, receivers = [1, 2, 3, 0, 0, 1], [0, 0, 1, 1, 2, 3]
    a = a[:6]
    u = np.array([0.5, 0.5, 0.5, 0.5, 1.0, 1.0])
    log_ratio = np.log2(np.array([1.1, 1.8, 0.2, 0.9]) / np.array([1.5, 1.5, 0.5, 0.5]))
    goal_node = np.array([True, True, False, True])
    node_type = [GT.ROOM, GT.FURNITURE, GT.FURNITURE, GT.OBJECT]

    def graph_on_map(fig, colour, width, label):
        ax = fig.axes[0]
        assert 'goal "apple onTop table kitchen" (success)' in ax.get_title()
        # One colour-mapped scatter per node type, together exactly the live nodes at their world
        # positions, coloured by `colour`, goal-category nodes ringed in red.
        scatters = [x for x in ax.collections if isinstance(x, PathCollection) and x.get_array() is not None]
        assert len(scatters) == 3 and sum(len(x.get_offsets()) for x in scatters) == 4
        for sc, nt in zip(scatters, (GT.ROOM, GT.FURNITURE, GT.OBJECT)):
            rows = [i for i in range(4) if node_type[i] == nt]
            np.testing.assert_allclose(sc.get_offsets(), world[rows], atol=1e-9)
            np.testing.assert_allclose(sc.get_array(), colour[rows], atol=1e-9)
            red = np.all(np.isclose(sc.get_edgecolors()[:, :3], to_rgb('r')), -1)
            np.testing.assert_array_equal(red, goal_node[rows])
        # One segment per live edge between its nodes' positions, width 0.3 + 2.5 * weight.
        drawn = {}
        for line in ax.lines:
            xy = line.get_xydata()
            if len(xy) == 2:
                drawn[tuple(np.round(xy.ravel(), 6))] = line.get_linewidth()
        assert len(drawn) == 6
        for e, (i, j) in enumerate(zip(senders, receivers)):
            key = tuple(np.round(np.concatenate([world[i], world[j]]), 6))
            assert drawn[key] == pytest.approx(0.3 + 2.5 * width[e]), e
        bar = [x for x in fig.axes[1:] if x.get_ylabel()]
        assert [x.get_ylabel() for x in bar] == [label]
        return scatters

    scatters = graph_on_map(
        A.plot_graph_on_map(rec), log_ratio, a, 'log2(received attention / uniform), layer 1'
    )
    lim = np.abs(log_ratio).max()
    for sc in scatters:  # a diverging scale centred on "as much as uniform"
        assert (sc.norm.vmin, sc.norm.vcenter, sc.norm.vmax) == pytest.approx((-lim, 0.0, lim))
    graph_on_map(A.plot_graph_on_map(gcn), np.array([1, 1, 0, 1]) / 3, u, 'pooling weight / sum')

    # Edge-type attention: one bar per (layer, present edge type) with the hand-computed share,
    # uniform-attention ticks, and a log-ratio heat map per layer and head with symmetric limits.
    names = ['inRoom', 'onTop', 'rev_inRoom', 'rev_onTop']
    share = np.array([[1.0, 0.6, 1.4, 1.0], [1.0, 0.9, 1.1, 1.0]]) / 4  # [layer, type]
    uniform = np.array([1.0, 0.5, 1.5, 1.0]) / 4
    fig = A.plot_edge_type_attention(rec)
    a0, a1 = fig.axes[:2]
    assert [t.get_text() for t in a0.get_xticklabels()] == names
    assert [b.get_label() for b in a0.containers] == ['layer 0', 'layer 1']
    assert len(a0.patches) == 2 * len(names)
    for b, want in zip(a0.containers, share):
        np.testing.assert_allclose([r.get_height() for r in b], want)
    ticks = [x for x in a0.collections if isinstance(x, PathCollection)]
    assert len(ticks) == 1
    np.testing.assert_allclose(ticks[0].get_offsets(), np.stack([np.arange(4), uniform], -1))
    (im,) = a1.images
    ratio = np.repeat(np.log2(share / uniform), 2, axis=0)  # rows L0 h0, L0 h1, L1 h0, L1 h1
    np.testing.assert_allclose(im.get_array(), ratio, atol=1e-6)
    lo, hi = im.get_clim()
    assert lo == -hi and hi >= np.abs(ratio).max()
    assert [t.get_text() for t in a1.get_yticklabels()] == ['L0 h0', 'L0 h1', 'L1 h0', 'L1 h1']
    assert [t.get_text() for t in a1.get_xticklabels()] == names
    fig = A.plot_edge_type_attention(gcn)
    for ax in fig.axes:
        assert not ax.patches and not ax.images and not ax.axison
        assert [t.get_text() for t in ax.texts] == ['no HGT attention in this model / rollout']

    # Pooling by role: model (task pooling: the three goal nodes, 1/3 each) next to mean pooling
    # (the four live nodes, 1/4 each), labelled with the live-node count per role.
    fig = A.plot_pool_weights(rec)
    (ax,) = fig.axes  # one step: no timeline
    assert [b.get_label() for b in ax.containers] == ['model (task pooling)', 'mean pooling']
    np.testing.assert_allclose([r.get_width() for r in ax.containers[0]], [1 / 3] * 3 + [0] * 3)
    np.testing.assert_allclose([r.get_width() for r in ax.containers[1]], [0.25] * 3 + [0, 0.25, 0])
    assert [t.get_text() for t in ax.get_yticklabels()] == [
        'goal object (1.0)',
        'goal furniture (1.0)',
        'goal room (1.0)',
        'other object (0.0)',
        'other furniture (1.0)',
        'other room (0.0)',
    ]
    # Two steps, the apple not yet seen in the first: the timeline shows each node's share per
    # step, goal-category rows first and in red.
    first = toy_record(pose=pose, alpha=rec.alpha[0, 0])
    first.node_mask[..., 3] = False
    first.pool_weights[..., 3] = 0.0
    first.pos = rec.pos
    steps = {
        f.name: np.concatenate([getattr(first, f.name), getattr(rec, f.name)], 1)
        for f in dataclasses.fields(A.Record)
        if isinstance(getattr(rec, f.name), np.ndarray) and getattr(rec, f.name).shape[:2] == (1, 1)
    }
    two = dataclasses.replace(rec, **steps, end=np.array([1]))
    fig = A.plot_pool_weights(two)
    timeline = fig.axes[1]
    assert [t.get_text() for t in timeline.get_yticklabels()] == ['kitchen', 'table', 'apple', 'shelf']
    assert [t.get_color() for t in timeline.get_yticklabels()] == ['r', 'r', 'r', 'k']
    np.testing.assert_allclose(
        timeline.images[0].get_array(), [[0.5, 1 / 3], [0.5, 1 / 3], [0.0, 1 / 3], [0.0, 0.0]]
    )

    # Goal concentration: per condition one box for the model's pooled goal share (1.0) and one
    # for mean pooling's (3/4); HGT received / uniform for goal nodes vs the shelf.
    def boxes(ax):
        return [(x.get_facecolor()[:3], np.unique(x.get_path().vertices[:, 1])) for x in ax.patches]

    fig = A.plot_goal_concentration({'a': rec, 'b': rec})
    a0, a1 = fig.axes
    assert [t.get_text() for t in a0.get_xticklabels()] == ['a\n(100 % of steps)', 'b\n(100 % of steps)']
    b0 = boxes(a0)
    assert len(b0) == 4
    for (colour, ys), (want_c, want_y) in zip(b0, [('tab:green', 1.0), ('tab:gray', 0.75)] * 2):
        assert colour == pytest.approx(to_rgb(want_c)) and ys == pytest.approx([want_y])
    goal_q = np.percentile(log_ratio[goal_node], [25, 75])
    b1 = boxes(a1)
    assert len(b1) == 4 and a1.get_title() == 'HGT attention received, layer 1'
    for (colour, ys), (want_c, want_y) in zip(b1, [('tab:red', goal_q), ('tab:blue', log_ratio[[2]])] * 2):
        assert colour == pytest.approx(to_rgb(want_c))
        assert [ys.min(), ys.max()] == pytest.approx([want_y.min(), want_y.max()])
    fig = A.plot_goal_concentration({'gcn': gcn})
    a0, a1 = fig.axes
    assert len(a0.patches) == 2 and not a1.patches
    assert [t.get_text() for t in a1.texts] == ['no HGT attention']
    plt.close('all')


def test_collect_choice_records_one_step_episodes():
    """The one-step choice task through collect's generic rollout: T = 1, every step valid, the
    recorded graph is the reset obs, success is whether the action was the correct side."""
    import jax

    from hron_jax.envs.choice import ChoiceConfig, ChoiceEnv
    from hron_jax.models import ModelConfig, make_model

    env = ChoiceEnv(ChoiceConfig(distractors=True, max_distractors=6))
    net = make_model(
        'rgbd_sg_attn',
        2,
        ModelConfig(
            use_rgbd=False,
            hidden=16,
            gnn_layers=2,
            fusion_fc=(16, 16, 16),
            head_fc=(16, 16),
            goal_fc=(16, 16, 16),
        ),
    )
    params = jax.jit(net.init)(jax.random.PRNGKey(0), env.observation_example())
    run = A.Run(
        run_dir=None,
        config=SimpleNamespace(task='choice'),
        env=env,
        network=net,
        params=params,
        step=0,
        seed_index=0,
    )
    rec = A.collect(run, episodes=6, max_steps=50, seed=1)
    n = env.config.num_nodes
    assert rec.category.shape == (6, 1, n) and rec.alpha.shape[:3] == (6, 1, 2)
    assert rec.valid.all() and (rec.end == 0).all() and (rec.pose == 0).all()
    np.testing.assert_array_equal(rec.category[:, 0], rec.states.obs['graph'].nodes['category'])
    np.testing.assert_array_equal(rec.success, rec.action[:, 0] == rec.states.inner.correct_action)
    # Task pooling selects live nodes only.
    assert (rec.pool_weights[~rec.node_mask] == 0).all()
