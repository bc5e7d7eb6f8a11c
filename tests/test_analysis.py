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
    from hron_jax import goals
    from hron_jax.envs import DEFAULT_SCENES
    from hron_jax.scenes.loader import load_scene

    scene = load_scene(DEFAULT_SCENES['exploratory'])
    rec = toy_record(pose=(2.0, 2.0, 0.5))
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
    figs = [
        A.plot_graph_on_map(rec),
        A.plot_edge_type_attention(rec),
        A.plot_pool_weights(rec),
        A.plot_goal_concentration({'a': rec, 'b': rec}),
    ]
    gcn = toy_record(alpha=np.zeros((0, 8, 1)))  # a model without attention
    gcn.env, gcn.states = rec.env, rec.states
    figs += [
        A.plot_graph_on_map(gcn),
        A.plot_edge_type_attention(gcn),
        A.plot_goal_concentration({'gcn': gcn}),
    ]
    assert all(isinstance(f, plt.Figure) for f in figs)
    for f in figs:
        plt.close(f)


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
    params = net.init(jax.random.PRNGKey(0), env.observation_example())
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
