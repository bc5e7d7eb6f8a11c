"""Relational object choice task: rewards, graph encoding of the relations, padding, goal, images."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from hron_jax import goals
from hron_jax import graph_types as GT
from hron_jax.envs.base import METRIC_KEYS, AutoResetWrapper, Env
from hron_jax.envs.choice import (
    CIRCLE_CLASS,
    LEFT,
    RECTANGLE_CLASS,
    RIGHT,
    TRIANGLE_CLASS,
    ChoiceConfig,
    ChoiceEnv,
    render,
)

PLAIN = ChoiceEnv(ChoiceConfig())
DISTRACT = ChoiceEnv(ChoiceConfig(distractors=True, image_obs=True, image_size=32))


@pytest.fixture(scope='module')
def batch():
    """200 distractor scenes, each with its layout bits, from one jitted vmapped reset."""
    keys = jax.random.split(jax.random.PRNGKey(0), 200)
    states = jax.jit(jax.vmap(DISTRACT.reset))(keys)
    return jax.tree.map(np.asarray, states)


def _unbatch(tree, i):
    return jax.tree.map(lambda x: x[i], tree)


def test_protocol_and_shapes():
    assert isinstance(PLAIN, Env) and PLAIN.num_actions == 2
    obs = PLAIN.observation_example()
    g = obs['graph']
    assert g.nodes['category'].shape == (4,) and g.nodes['pos'].shape == (4, 3)
    assert g.senders.shape == (4,) and g.edges['edge_type'].shape == (4,)
    assert list(g.n_node) == [4] and list(g.n_edge) == [4]
    assert obs['goal'].shape == (goals.GOAL_DIM,) and obs['goal_classes'].dtype == jnp.int32
    n = DISTRACT.config.num_nodes
    assert n == 79 and DISTRACT.observation_example()['graph'].nodes['mask'].shape == (n,)
    assert DISTRACT.observation_example()['rgb'].shape == (32, 32, 3)


@pytest.mark.parametrize('above_side', [LEFT, RIGHT])
@pytest.mark.parametrize('goal_above', [True, False])
def test_reward_on_hand_built_layouts(above_side, goal_above):
    state = PLAIN.reset_to(jax.random.PRNGKey(3), above_side, goal_above)
    correct = above_side if goal_above else 1 - above_side
    for action, expected in ((correct, 1.0), (1 - correct, 0.0)):
        nxt = PLAIN.step(state, jnp.int32(action))
        assert float(nxt.reward) == expected
        assert float(nxt.done) == 1.0 and float(nxt.info['truncation']) == 0.0
        assert float(nxt.metrics['success']) == expected and float(nxt.metrics['spl']) == expected
        assert float(nxt.metrics['episode_done']) == 1.0
        assert float(nxt.metrics['episode_length']) == 1.0
        assert set(METRIC_KEYS) <= set(nxt.metrics)


def _core(graph):
    """(circle node, its rectangle node, edge type) for the two circle -> rectangle edges."""
    n, e = graph.nodes, graph.edges
    out = []
    for k in range(len(graph.senders)):
        s, r = int(graph.senders[k]), int(graph.receivers[k])
        if e['mask'][k] and n['category'][s] == CIRCLE_CLASS:
            assert n['category'][r] == RECTANGLE_CLASS
            out.append((s, r, int(e['edge_type'][k])))
    return out


def test_edges_encode_the_relation(batch):
    for i in range(len(batch.reward)):
        g = _unbatch(batch.obs['graph'], i)
        inner = _unbatch(batch.inner, i)
        n = g.nodes
        pairs = _core(g)
        assert len(pairs) == 2
        seen_sides = set()
        for c, r, et in pairs:
            assert et in (GT.ON_TOP, GT.UNDER)
            cy, ry = n['pos'][c, 1], n['pos'][r, 1]
            # The edge type matches the geometry: onTop <=> circle entirely above its rectangle.
            if et == GT.ON_TOP:
                assert cy - n['size'][c, 1] / 2 >= ry + n['size'][r, 1] / 2 - 1e-6
            else:
                assert cy + n['size'][c, 1] / 2 <= ry - n['size'][r, 1] / 2 + 1e-6
            # The circle lies over its rectangle's width, both on the same half.
            assert abs(n['pos'][c, 0] - n['pos'][r, 0]) <= n['size'][r, 0] / 2 + 1e-6
            side = RIGHT if n['pos'][c, 0] > 0 else LEFT
            assert (n['pos'][r, 0] > 0) == (side == RIGHT)
            assert (et == GT.ON_TOP) == (side == int(inner.above_side))
            seen_sides.add(side)
            # The reverse edge exists with the reverse type.
            rev = [k for k in range(4) if g.senders[k] == r and g.receivers[k] == c]
            assert len(rev) == 1 and g.edges['edge_type'][rev[0]] == GT.REVERSE_EDGE_TYPE[et]
        assert seen_sides == {LEFT, RIGHT}
        # Every live edge is a legal (type, sender type, receiver type) triple of the HGT.
        assert (
            GT.check_graph_types(
                n['node_type'], g.senders, g.receivers, g.edges['edge_type'], g.edges['mask']
            ).size
            == 0
        )


def test_padding_masks_and_distractors(batch):
    counts = batch.inner.num_distractors
    assert counts.min() == 0 or counts.min() < 10
    assert counts.max() > 60 and counts.max() <= 75
    for i in range(len(counts)):
        n = _unbatch(batch.obs['graph'].nodes, i)
        g = _unbatch(batch.obs['graph'], i)
        valid = int(n['mask'].sum())
        assert valid == 4 + counts[i]
        # The static type layout: the two rectangles in rows 0-1, then the objects, valid ones
        # first; padding is zeroed; edges only touch valid nodes.
        assert DISTRACT.node_type_counts == (0, 2, 77)
        assert (n['node_type'][:2] == GT.FURNITURE).all() and (n['category'][:2] == RECTANGLE_CLASS).all()
        assert (n['node_type'][2:valid] == GT.OBJECT).all()
        assert n['mask'][:valid].all() and not n['mask'][valid:].any()
        assert (n['category'][valid:] == 0).all() and (n['pos'][valid:] == 0).all()
        assert n['mask'][g.senders].all() and n['mask'][g.receivers].all()
        cats = n['category'][:valid]
        assert (cats == CIRCLE_CLASS).sum() == 2 and (cats == RECTANGLE_CLASS).sum() == 2
        assert (cats == TRIANGLE_CLASS).sum() == counts[i]
        tri = n['node_type'][:valid][cats == TRIANGLE_CLASS]
        assert (tri == GT.OBJECT).all()
        assert (n['node_type'][:valid][cats == RECTANGLE_CLASS] == GT.FURNITURE).all()
        # Bounding boxes of distinct shapes do not overlap; all shapes are on the canvas.
        lo = n['pos'][:valid, :2] - n['size'][:valid, :2] / 2
        hi = n['pos'][:valid, :2] + n['size'][:valid, :2] / 2
        assert lo.min() >= -1.0 and hi.max() <= 1.0
        sep = (lo[:, None] >= hi[None] - 1e-6) | (hi[:, None] <= lo[None] + 1e-6)
        overlap = ~sep.any(-1)
        np.fill_diagonal(overlap, False)
        assert not overlap.any()


def test_layout_is_balanced_and_shuffled(batch):
    inner = batch.inner
    for bits in (inner.above_side, inner.goal_above, inner.correct_action):
        assert 0.35 < bits.mean() < 0.65
    # Node order within a type is random: the circles are not always in the same slots, nor the
    # left rectangle (the lower x) in row 0.
    nodes = batch.obs['graph'].nodes
    first_circle = np.argmax(nodes['category'] == CIRCLE_CLASS, axis=1)
    assert len(np.unique(first_circle)) > 5
    assert 0.35 < (nodes['pos'][:, 0, 0] < nodes['pos'][:, 1, 0]).mean() < 0.65


def test_goal_encoding(batch):
    for i in range(20):
        obs = _unbatch(batch.obs, i)
        relation = 'onTop' if batch.inner.goal_above[i] else 'under'
        assert goals.decode_goal(obs['goal']) == ('circle', relation, 'rectangle', None)
        assert list(obs['goal_classes']) == [CIRCLE_CLASS, RECTANGLE_CLASS, -1]
        assert obs['goal'][goals.GOAL_SLICES['room']].sum() == 0
    np.testing.assert_array_equal(
        goals.encode_goal(*goals.goal_indices('circle', 'under', 'rectangle', None)),
        batch.obs['goal'][np.argmin(batch.inner.goal_above)],
    )


def test_image_obs_and_render(batch):
    obs = _unbatch(batch.obs, 0)
    rgb = obs['rgb']
    assert rgb.dtype == np.float32 and 0.0 <= rgb.min() and rgb.max() <= 1.0
    # The pixel at each circle's centre is circle-red.
    n = obs['graph'].nodes
    for c in np.nonzero(n['category'] == CIRCLE_CLASS)[0]:
        x, y = n['pos'][c, :2]
        col = int((x + 1) / 2 * 32)
        row = int((1 - y) / 2 * 32)
        r, g, b = rgb[min(row, 31), min(col, 31)]
        assert r > 0.7 and g < 0.4 and b < 0.4
    img = render(_unbatch(batch, 0), size_px=128)
    assert img.dtype == np.uint8 and img.shape == (128, 128, 3) and img.std() > 0


def test_auto_reset_starts_a_new_scene():
    env = AutoResetWrapper(PLAIN)
    state = env.reset(jax.random.PRNGKey(5))
    wrong = 1 - state.inner.correct_action
    nxt = jax.jit(env.step)(state, wrong)
    assert float(nxt.reward) == 0.0 and float(nxt.done) == 1.0
    assert float(nxt.metrics['episode_done']) == 1.0 and float(nxt.metrics['return']) == 0.0
    # New episode's obs and counters; the pre-reset obs is kept in final_obs.
    assert float(nxt.info['steps']) == 0.0
    assert not np.allclose(nxt.obs['graph'].nodes['pos'], state.obs['graph'].nodes['pos'])
    np.testing.assert_array_equal(
        nxt.info['final_obs']['graph'].nodes['pos'], state.obs['graph'].nodes['pos']
    )
