"""Relational object choice task (paper, "Experimental setup"): a 2D symbolic one-step bandit.

Scene: a canvas [-1, 1]^2 seen by the agent, x to the viewer's right, y up. Each half holds a
rectangle (furniture) and a circle (object) next to it: on one half (random) the circle sits above its
rectangle, on the other half below it. The goal is "circle above rectangle" (relation onTop) or
"circle below rectangle" (relation under), drawn at random. Actions: 0 left, 1 right. Reward 1 if the
chosen half holds the goal configuration, else 0; every episode is one step (terminated, never
truncated). Optionally (``distractors=True``) a uniform number in [0, max_distractors] of triangles
(objects) is scattered over free cells of a grid, so they never overlap the circles and rectangles.

Observation (one env):
    obs['graph']: jraph.GraphsTuple of one padded graph, N = 4 + max_distractors (4 without
        distractors) nodes and E = 4 edges:
        nodes {'category': i32[N] semantic class id (vocabulary.class_id), 'node_type': i32[N]
               (graph_types: object 2, furniture 1), 'pos': f32[N, 3] centre (x right, y up, 0),
               'size': f32[N, 3] full bounding-box extents (w, h, 0), 'mask': bool[N]}
        edges {'edge_type': i32[E], 'mask': bool[E]}, senders/receivers i32[E],
        n_node i32[1] = [N], n_edge i32[1] = [E], globals None.
        Edges: circle -> its rectangle onTop (circle above) or under (circle below), and the reverse
        rev_onTop / rev_under. Rows by node type (`node_type_counts` = (0, 2, N - 2), the static
        layout the HGT layers slice): the two rectangles in rows 0-1, then the objects, each type's
        valid nodes in a random order (so no model can key on slot position) and the object rows'
        padding after them; padding nodes have category 0, node_type 0, zero pos/size, mask False.
        (Padded edges, where a config needs them, would point to node 0 with mask False; here E is
        exact.)
    obs['goal']: f32[GOAL_DIM] one-hots (circle, onTop|under, rectangle, no room), hron_jax.goals.
    obs['goal_classes']: i32[3] = class ids (circle, rectangle, -1).
    obs['rgb'] (only with ``image_obs=True``): f32[S, S, 3] in [0, 1], a rasterised view of the canvas
        (row 0 = top); obs['depth']: f32[S, S, 1] all ones (a flat canvas), for RGB-D models.

``render(state)`` draws one env's scene with matplotlib (uint8[H, W, 3], for docs, not jittable).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import jraph
import numpy as np
from flax import struct

from hron_jax import goals
from hron_jax import graph_types as GT
from hron_jax.envs.base import EnvState, initial_state, next_state
from hron_jax.scenes import vocabulary as V

LEFT, RIGHT = 0, 1
CIRCLE_CLASS = V.class_id('object', 'circle')
RECTANGLE_CLASS = V.class_id('furniture', 'rectangle')
TRIANGLE_CLASS = V.class_id('object', 'triangle')
CIRCLE_IDX = V.index('object', 'circle')
RECTANGLE_IDX = V.index('furniture', 'rectangle')

# Geometry ranges (canvas units, canvas is [-1, 1]^2). Chosen so a pair fits in its half with margin
# and the distractor grid keeps >= 75 free cells whatever the pair layout.
_RECT_W = (0.30, 0.60)
_RECT_H = (0.10, 0.25)
_CIRCLE_R = (0.06, 0.12)
_GAP = (0.0, 0.04)  # vertical gap between circle and rectangle
_MARGIN = 0.05  # keep shapes off the canvas border and the centre line
_GRID = 12  # distractor cells per axis
_TRI = (0.07, 0.12)  # triangle bounding-box side


@dataclasses.dataclass(frozen=True)
class ChoiceConfig:
    distractors: bool = False
    max_distractors: int = 75
    image_obs: bool = False
    image_size: int = 32

    @property
    def num_nodes(self) -> int:
        return 4 + (self.max_distractors if self.distractors else 0)

    @property
    def max_steps(self) -> int:
        """Episode length limit, as NavConfig.max_steps: evaluation and analysis roll every task
        out for config.max_steps steps, and a choice episode always ends after its one step."""
        return 1


@struct.dataclass
class ChoiceInner:
    above_side: jax.Array  # i32: half (0 left, 1 right) whose circle is above its rectangle
    goal_above: jax.Array  # bool: goal relation is "above" (onTop), else "below" (under)
    correct_action: jax.Array  # i32
    num_distractors: jax.Array  # i32


def _uniform(key, lo_hi, shape=()):
    lo, hi = lo_hi
    return jax.random.uniform(key, shape, jnp.float32, lo, hi)


def _pair(key, side, above):
    """One circle/rectangle pair in a half. Returns (circle centre, circle size, rect centre, rect size)."""
    k = jax.random.split(key, 6)
    w, h, r = _uniform(k[0], _RECT_W), _uniform(k[1], _RECT_H), _uniform(k[2], _CIRCLE_R)
    gap = _uniform(k[3], _GAP)
    lo = jnp.where(side == LEFT, -1.0, 0.0) + _MARGIN + w / 2
    hi = jnp.where(side == LEFT, 0.0, 1.0) - _MARGIN - w / 2
    rx = lo + (hi - lo) * jax.random.uniform(k[4])
    # Circle x anywhere over the rectangle's width, so it is clearly above / below *that* rectangle.
    cx = rx + (w / 2 - r) * jax.random.uniform(k[5], (), jnp.float32, -1.0, 1.0)
    pair_h = h + gap + 2 * r
    y0 = -1.0 + _MARGIN + (2.0 - 2 * _MARGIN - pair_h) * jax.random.uniform(jax.random.fold_in(key, 7))
    rect_y = jnp.where(above, y0 + h / 2, y0 + pair_h - h / 2)
    circ_y = jnp.where(above, y0 + pair_h - r, y0 + r)
    zero = jnp.zeros((), jnp.float32)
    return (
        jnp.stack([cx, circ_y, zero]),
        jnp.stack([2 * r, 2 * r, zero]),
        jnp.stack([rx, rect_y, zero]),
        jnp.stack([w, h, zero]),
    )


def _distractors(key, core_pos, core_size, max_n):
    """Up to max_n triangles on distinct grid cells that do not touch the four core shapes."""
    k_n, k_cells, k_jit, k_size = jax.random.split(key, 4)
    cell = 2.0 / _GRID
    centres = -1.0 + cell * (jnp.arange(_GRID, dtype=jnp.float32) + 0.5)
    cx, cy = jnp.meshgrid(centres, centres, indexing='xy')
    cells = jnp.stack([cx.ravel(), cy.ravel()], -1)  # [C, 2]
    # A cell is blocked when its square overlaps a core bounding box grown by a small margin.
    half = core_size[:, :2] / 2 + 0.02  # [4, 2]
    overlap = jnp.all(jnp.abs(cells[:, None, :] - core_pos[None, :, :2]) < half[None] + cell / 2, -1)
    free = ~jnp.any(overlap, -1)  # [C]
    n = jax.random.randint(k_n, (), 0, max_n + 1)
    n = jnp.minimum(n, free.sum())
    # Free cells first, in random order; take the first max_n, of which the first n are used.
    order = jnp.argsort(jax.random.uniform(k_cells, free.shape) + 2.0 * (~free))[:max_n]
    valid = jnp.arange(max_n) < n
    side = _uniform(k_size, _TRI, (max_n,))
    slack = (cell - side)[:, None] / 2
    jitter = jax.random.uniform(k_jit, (max_n, 2), jnp.float32, -1.0, 1.0) * slack
    xy = cells[order] + jitter
    zeros = jnp.zeros((max_n, 1), jnp.float32)
    pos = jnp.concatenate([xy, zeros], -1)
    size = jnp.concatenate([side[:, None], side[:, None], zeros], -1)
    return pos, size, valid, n


def _rasterise(nodes, size_px):
    """f32[S, S, 3] image of the canvas: circles, rectangles, upward triangles on white."""
    centres = -1.0 + (2.0 / size_px) * (jnp.arange(size_px, dtype=jnp.float32) + 0.5)
    px, py = jnp.meshgrid(centres, centres[::-1], indexing='xy')  # row 0 = top (y = +1)
    p = jnp.stack([px, py], -1)[:, :, None, :]  # [S, S, 1, 2]
    c = nodes['pos'][None, None, :, :2]
    half = nodes['size'][None, None, :, :2] / 2
    d = p - c
    cat = nodes['category']
    in_circle = jnp.sum(d * d, -1) <= half[..., 0] ** 2
    in_rect = jnp.all(jnp.abs(d) <= half, -1)
    # Upward triangle: full width at the bottom of its box, apex at the top.
    frac = (d[..., 1] + half[..., 1]) / jnp.maximum(2 * half[..., 1], 1e-6)
    in_tri = (jnp.abs(d[..., 1]) <= half[..., 1]) & (jnp.abs(d[..., 0]) <= half[..., 0] * (1 - frac))
    inside = (
        jnp.where(cat == CIRCLE_CLASS, in_circle, jnp.where(cat == TRIANGLE_CLASS, in_tri, in_rect))
        & nodes['mask']
    )
    colours = jnp.asarray(
        np.stack(
            [
                np.array(V.OBJECT_SHAPES['circle'].rgba[:3]),
                np.array(V.FURNITURE_RGBA['rectangle'][:3]),
                np.array(V.OBJECT_SHAPES['triangle'].rgba[:3]),
            ]
        ),
        jnp.float32,
    )
    kind = jnp.where(cat == CIRCLE_CLASS, 0, jnp.where(cat == RECTANGLE_CLASS, 1, 2))
    node_rgb = colours[kind]  # [N, 3]
    # Later nodes paint over earlier ones; shapes never overlap, so the order does not matter.
    idx = jnp.max(jnp.where(inside, jnp.arange(cat.shape[0]), -1), -1)  # [S, S]
    return jnp.where((idx >= 0)[..., None], node_rgb[jnp.maximum(idx, 0)], 1.0)


class ChoiceEnv:
    """Relational object choice bandit; functional API of hron_jax.envs.base."""

    num_actions = 2

    def __init__(self, config: ChoiceConfig = ChoiceConfig()):
        self.config = config

    @property
    def node_type_counts(self) -> tuple[int, int, int]:
        """The node table's static type layout (envs.base): no rooms, 2 rectangles, the objects."""
        return (0, 2, self.config.num_nodes - 2)

    # -- scene ---------------------------------------------------------------------------------
    def reset_to(self, rng, above_side, goal_above) -> EnvState:
        """Reset with the layout bits given (0/1 side, bool goal); positions still random."""
        cfg = self.config
        above_side = jnp.asarray(above_side, jnp.int32)
        goal_above = jnp.asarray(goal_above, bool)
        k_left, k_right, k_dis, k_perm = jax.random.split(rng, 4)
        pairs = [_pair(k, side, above_side == side) for k, side in ((k_left, LEFT), (k_right, RIGHT))]
        # Core node order before shuffling: circle L, rectangle L, circle R, rectangle R.
        core_pos = jnp.stack([pairs[0][0], pairs[0][2], pairs[1][0], pairs[1][2]])
        core_size = jnp.stack([pairs[0][1], pairs[0][3], pairs[1][1], pairs[1][3]])
        core_cat = jnp.array([CIRCLE_CLASS, RECTANGLE_CLASS, CIRCLE_CLASS, RECTANGLE_CLASS], jnp.int32)
        core_type = jnp.array([GT.OBJECT, GT.FURNITURE, GT.OBJECT, GT.FURNITURE], jnp.int32)
        if cfg.distractors:
            m = cfg.max_distractors
            d_pos, d_size, d_valid, n_dis = _distractors(k_dis, core_pos, core_size, m)
            pos = jnp.concatenate([core_pos, d_pos])
            size = jnp.concatenate([core_size, d_size])
            mask = jnp.concatenate([jnp.ones(4, bool), d_valid])
            cat = jnp.concatenate([core_cat, jnp.full(m, TRIANGLE_CLASS, jnp.int32)])
            ntype = jnp.concatenate([core_type, jnp.full(m, GT.OBJECT, jnp.int32)])
        else:
            pos, size, mask, cat, ntype = core_pos, core_size, jnp.ones(4, bool), core_cat, core_type
            n_dis = jnp.zeros((), jnp.int32)
        cat = jnp.where(mask, cat, 0)
        ntype = jnp.where(mask, ntype, 0)
        pos = jnp.where(mask[:, None], pos, 0.0)
        size = jnp.where(mask[:, None], size, 0.0)

        # Edges between old indices: circle -> rectangle with its relation, and the reverse.
        left_rel = jnp.where(above_side == LEFT, GT.ON_TOP, GT.UNDER)
        right_rel = jnp.where(above_side == RIGHT, GT.ON_TOP, GT.UNDER)
        rev = lambda t: jnp.where(t == GT.ON_TOP, GT.REV_ON_TOP, GT.REV_UNDER)
        senders = jnp.array([0, 1, 2, 3], jnp.int32)
        receivers = jnp.array([1, 0, 3, 2], jnp.int32)
        edge_type = jnp.stack([left_rel, rev(left_rel), right_rel, rev(right_rel)]).astype(jnp.int32)

        # Shuffle within the type layout: rectangles, then valid objects, then padding, each in a
        # random order.
        n = cfg.num_nodes
        group = jnp.where(mask, jnp.where(ntype == GT.OBJECT, 1.0, 0.0), 2.0)
        order = jnp.argsort(jax.random.uniform(k_perm, (n,)) + group)  # new slot -> old
        inv = jnp.zeros(n, jnp.int32).at[order].set(jnp.arange(n, dtype=jnp.int32))  # old -> new
        nodes = {
            'category': cat[order],
            'node_type': ntype[order],
            'pos': pos[order],
            'size': size[order],
            'mask': mask[order],
        }
        graph = jraph.GraphsTuple(
            nodes=nodes,
            edges={'edge_type': edge_type, 'mask': jnp.ones(4, bool)},
            senders=inv[senders],
            receivers=inv[receivers],
            globals=None,
            n_node=jnp.array([n], jnp.int32),
            n_edge=jnp.array([4], jnp.int32),
        )

        relation = jnp.where(goal_above, V.ON_TOP, V.UNDER)
        obs = {
            'graph': graph,
            'goal': goals.encode_goal(CIRCLE_IDX, relation, RECTANGLE_IDX, -1),
            'goal_classes': goals.goal_classes(CIRCLE_IDX, RECTANGLE_IDX, -1),
        }
        if cfg.image_obs:
            obs['rgb'] = _rasterise(nodes, cfg.image_size)
            obs['depth'] = jnp.ones((cfg.image_size, cfg.image_size, 1), jnp.float32)
        # Goal above -> the half whose circle is above; goal below -> the other half.
        correct = jnp.where(goal_above, above_side, 1 - above_side).astype(jnp.int32)
        inner = ChoiceInner(
            above_side=above_side,
            goal_above=goal_above,
            correct_action=correct,
            num_distractors=n_dis.astype(jnp.int32),
        )
        return initial_state(obs, inner)

    # -- API -------------------------------------------------------------------------------------
    def reset(self, rng) -> EnvState:
        k_side, k_goal, k_scene = jax.random.split(rng, 3)
        above_side = jax.random.randint(k_side, (), 0, 2)
        goal_above = jax.random.bernoulli(k_goal)
        return self.reset_to(k_scene, above_side, goal_above)

    def step(self, state: EnvState, action) -> EnvState:
        success = (jnp.asarray(action, jnp.int32) == state.inner.correct_action).astype(jnp.float32)
        # One-step episode: always terminated (never truncated); the obs stays the same scene.
        return next_state(state, state.obs, state.inner, success, 1.0, success=success)

    def observation_example(self):
        return self.reset(jax.random.PRNGKey(0)).obs


def render(state: EnvState, size_px: int = 256) -> np.ndarray:
    """uint8[H, W, 3] matplotlib drawing of one (unbatched) choice env state, with its goal."""
    import matplotlib

    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    from matplotlib import patches

    g = jax.tree.map(np.asarray, state.obs['graph'])
    nodes = g.nodes
    dpi = 100
    fig = plt.figure(figsize=(size_px / dpi, size_px / dpi), dpi=dpi)
    ax = fig.add_axes([0, 0, 1, 1])
    ax.set_xlim(-1, 1)
    ax.set_ylim(-1, 1)
    ax.set_aspect('equal')
    ax.axis('off')
    ax.axvline(0.0, color='0.85', lw=1, ls='--')
    for i in np.nonzero(nodes['mask'])[0]:
        (x, y, _), (w, h, _), c = nodes['pos'][i], nodes['size'][i], int(nodes['category'][i])
        if c == CIRCLE_CLASS:
            ax.add_patch(patches.Circle((x, y), w / 2, color=V.OBJECT_SHAPES['circle'].rgba))
        elif c == RECTANGLE_CLASS:
            ax.add_patch(patches.Rectangle((x - w / 2, y - h / 2), w, h, color=V.FURNITURE_RGBA['rectangle']))
        else:
            ax.add_patch(
                patches.Polygon(
                    [(x - w / 2, y - h / 2), (x + w / 2, y - h / 2), (x, y + h / 2)],
                    color=V.OBJECT_SHAPES['triangle'].rgba,
                )
            )
    obj, rel, fur, _ = goals.decode_goal(state.obs['goal'])
    word = {'onTop': 'above', 'under': 'below'}.get(rel, rel)
    ax.text(
        0.0,
        0.97,
        f'goal: {obj} {word} {fur}',
        ha='center',
        va='top',
        fontsize=8,
        bbox=dict(facecolor='white', edgecolor='0.6', pad=2),
        transform=ax.transData,
    )
    fig.canvas.draw()
    img = np.asarray(fig.canvas.buffer_rgba())[..., :3].copy()
    plt.close(fig)
    return img
