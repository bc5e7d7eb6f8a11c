"""Attention analysis of trained policies: rollouts that record HGT attention and pooling weights,
their reductions (per edge type, per node, goal-relevant vs other nodes), and the figures of
notebooks/attention_analysis.ipynb (which only calls these, so they are tested in
tests/test_analysis.py).

    run = load_run(RUN_DIR)                            # config, env (no auto-reset), model, params
    rec = collect(run, episodes=4, max_steps=200)      # Record of numpy arrays, see below
    edge_type_mass(rec)    -> {'mass': f32[L, H, K], 'uniform': f32[L, H, K], ...}
    node_attention(rec)    -> (received f32[B, T, L, N], uniform f32[B, T, N])
    goal_concentration(rec)-> per valid step: pooling / HGT attention share on goal-category nodes
    world_positions(rec)   -> f32[B, T, N, 2] node xy in the world (canvas for the choice task)
    plot_edge_type_attention, plot_pool_weights, plot_graph_on_map, plot_goal_concentration

Shapes: B episodes, T recorded steps (1 for the one-step choice task), N padded nodes, M padded
edges, L HGT layers, H heads, K = len(graph_types.EDGE_TYPES) edge types.

What is measured. HGT attention alpha[e, h] is a softmax over the live incoming edges of the
edge's receiver (hron_jax.models.gnn.HGTConv, hgt_softmax='joint'), or over those of the edge's
relation (edge type, sender type, receiver type) only ('per_relation', the paper's PyG <= 2.2), so
every receiver hands out exactly one unit of attention per head and layer (per incoming relation
under 'per_relation'). Two reductions
follow from that:
  * per edge type: the share of all attention mass that flows along edges of type k, next to the
    share a *uniform* attention (1 / in-degree per edge, in-degree counted in the same softmax
    group, i.e. mean aggregation) would give on the same graphs. The ratio says which relations a
    layer prefers beyond how common they are.
  * per node: attention *received* = sum of alpha over the node's outgoing edges (how much its
    neighbours listen to it), again next to the uniform value.
Task-driven pooling weights are the fixed 0/1 indicator of goal categories (models/pooling.py);
mean pooling (the "no attention" ablation) puts 1 on every live node. We report both on the same
graphs, normalised to sum to 1, so the share of the pooled graph vector that comes from
goal-category nodes is directly comparable (and shows the dilution by distractors that the paper's
Table I / II argue about).

Host-side analysis (numpy / matplotlib) except `collect`, which jits one rollout program.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

import numpy as np

from hron_jax import graph_types as GT

NODE_TYPE_MARKERS = {GT.ROOM: 's', GT.FURNITURE: 'D', GT.OBJECT: 'o'}
NODE_TYPE_SIZES = {GT.ROOM: 140.0, GT.FURNITURE: 60.0, GT.OBJECT: 40.0}


# ------------------------------------------------------------------------------------------------
# Loading a run
# ------------------------------------------------------------------------------------------------


@dataclasses.dataclass
class Run:
    """A trained run ready for analysis. params: one seed's variables (no seed axis)."""

    run_dir: Path
    config: Any  # hron_jax.run_config.TrainConfig
    env: Any  # built like training, but without auto-reset (episodes end)
    network: Any
    params: Any
    step: int  # checkpoint (updates)
    seed_index: int

    def env_variant(self, **overrides):
        """The run's env with some options changed (e.g. distractors=True); the model accepts any
        node count, so a policy can be probed on scenes it was not trained on."""
        from hron_jax.run_config import build_env

        return build_env(self.config, episodic=True, **overrides)


def load_run(run_dir, step: int | None = None, seed_index: int = 0) -> Run:
    """Restore one seed's parameters of a train.py run (latest checkpoint unless `step`)."""
    import jax

    from hron_jax.run_config import build_env, build_network
    from hron_jax.run_dir import load_config, restore_params

    run_dir = Path(run_dir).resolve()  # orbax restores from absolute paths only
    config = load_config(run_dir)
    env = build_env(config, episodic=True)
    network = build_network(config, env)
    if not network.config.use_graph:
        raise ValueError(f'{run_dir}: model {config.model!r} has no scene-graph branch to analyse')
    params, step = restore_params(run_dir, config, env, network, step)
    if not 0 <= seed_index < config.num_seeds:
        raise ValueError(f'seed_index {seed_index} out of range: the run has {config.num_seeds} seed(s)')
    # Device arrays, not numpy: the model may index parameters with traced values.
    params = jax.tree.map(lambda x: jax.numpy.asarray(np.asarray(x)[seed_index]), params)
    return Run(run_dir, config, env, network, params, step, seed_index)


def train_command(
    run_dir,
    task: str = 'exploratory',
    model: str = 'rgbd_sg_attn',
    total_steps: int = 20480,
    extra: tuple[str, ...] = (),
) -> list[str]:
    """argv of the train.py call that makes an analysis run (documented in the notebook)."""
    import sys

    from hron_jax.paths import REPO_ROOT

    return [
        sys.executable,
        str(Path(REPO_ROOT) / 'train.py'),
        '--task',
        task,
        '--model',
        model,
        '--total-steps',
        str(total_steps),
        '--out',
        str(run_dir),
        '--no-progress',
        *extra,
    ]


# ------------------------------------------------------------------------------------------------
# Rollouts with attention
# ------------------------------------------------------------------------------------------------


@dataclasses.dataclass
class Record:
    """Numpy arrays of B episodes x T steps (see the module docstring for letters).

    graph (the obs the policy acted on): category / node_type i32[B,T,N], node_mask bool[B,T,N],
      pos f32[B,T,N,3] (agent frame; canvas for choice), senders / receivers / edge_type
      i32[B,T,M], edge_mask bool[B,T,M]
    alpha f32[B,T,L,M,H] HGT attention (L = 0 for a GCN), pool_weights f32[B,T,N] (0/1 for task
      pooling, node mask for mean pooling), goal_classes i32[B,T,3]
    pose f32[B,T,3] agent (x, y, yaw) before the step (zeros for choice), action i32[B,T]
    valid bool[B,T]: step t belongs to the episode (up to and including its last step)
    success / spl f32[B], end i32[B] (index of the last step)
    states: the first EnvState of every episode (batched [B]) for drawing; task, env, pooling
    """

    task: str
    pooling: str
    category: np.ndarray
    node_type: np.ndarray
    node_mask: np.ndarray
    pos: np.ndarray
    senders: np.ndarray
    receivers: np.ndarray
    edge_type: np.ndarray
    edge_mask: np.ndarray
    alpha: np.ndarray
    pool_weights: np.ndarray
    goal_classes: np.ndarray
    pose: np.ndarray
    action: np.ndarray
    valid: np.ndarray
    success: np.ndarray
    spl: np.ndarray
    end: np.ndarray
    states: Any = None
    env: Any = None
    hgt_softmax: str = 'joint'  # the softmax groups of alpha (ModelConfig.hgt_softmax)

    @property
    def num_layers(self) -> int:
        return self.alpha.shape[2]

    @property
    def is_goal(self) -> np.ndarray:
        """bool[B,T,N]: live node whose category is one of the goal's (what task pooling selects)."""
        g = self.goal_classes[..., None, :]
        hit = (self.category[..., None] == g) & (g >= 0)
        return hit.any(-1) & self.node_mask


def _split_attention(att: dict, num_layers: int, num_edges: int):
    """(alpha f32[..., L, M, H], pool_weights f32[..., N]) from attention_readout's dict."""
    import jax.numpy as jnp

    enc = att.get('core', {}).get('graph_encoder', {})
    layers = [enc[f'hgt_{i}']['alpha'][0] for i in range(num_layers) if f'hgt_{i}' in enc]
    pw = enc['pool_weights'][0]
    if layers:
        alpha = jnp.stack(layers, axis=-3)
    else:  # GCN: no attention; keep the rank so the reductions still run (on nothing)
        alpha = jnp.zeros(pw.shape[:-1] + (0, num_edges, 1), jnp.float32)
    return alpha, pw


def collect(
    run: Run, episodes: int = 4, max_steps: int | None = None, seed: int = 0, env=None, greedy: bool = False
) -> Record:
    """Roll out `episodes` episodes of run's policy (of `env`, default run.env) and record the
    graph, attention and pooling weights at every step. Episode i starts from
    env.reset(fold_in(PRNGKey(seed), i)), as in eval.py. Actions are sampled unless `greedy`.
    Rollouts run min(max_steps, the env's episode limit) steps (the limit when max_steps is None;
    one for the choice task) and mark the steps after the episode's end invalid."""
    import jax
    import jax.numpy as jnp

    from hron_jax.models import attention_readout
    from hron_jax.rollout import episode_ends, unroll

    env = env or run.env
    network, params = run.network, run.params
    cfg = network.config
    key = jax.random.PRNGKey(seed)
    reset_keys = jax.vmap(lambda i: jax.random.fold_in(key, i))(jnp.arange(episodes))
    num_edges = int(jax.eval_shape(env.reset, key).obs['graph'].senders.shape[-1])
    steps = min(int(max_steps or env.config.max_steps), env.config.max_steps)

    def policy(state, k):
        logits, _, att = attention_readout(network, params, state.obs)
        action = jnp.argmax(logits, -1) if greedy else jax.random.categorical(k, logits)
        alpha, pw = _split_attention(att, cfg.gnn_layers if cfg.gnn == 'hgt' else 0, num_edges)
        return action.astype(jnp.int32), {'alpha': alpha, 'pool_weights': pw}

    def record(state, action, extras, nxt):
        obs, g = state.obs, state.obs['graph']
        # Envs without an agent in a scene (choice) record a zero pose.
        pose = env.agent_pose(state) if hasattr(env, 'agent_pose') else jnp.zeros(3)
        return dict(
            category=g.nodes['category'],
            node_type=g.nodes['node_type'],
            node_mask=g.nodes['mask'],
            pos=g.nodes['pos'],
            senders=g.senders,
            receivers=g.receivers,
            edge_type=g.edges['edge_type'],
            edge_mask=g.edges['mask'],
            goal_classes=obs['goal_classes'],
            pose=pose,
        )

    def episode(k_reset):
        state = env.reset(k_reset)
        return state, unroll(env.step, state, policy, jax.random.fold_in(k_reset, 1), steps, record=record)[2]

    states, traj = jax.jit(jax.vmap(episode))(reset_keys)
    traj = jax.tree.map(np.asarray, jax.device_get(traj))
    _, end = episode_ends(traj['done'])  # [B]
    valid = np.arange(traj['done'].shape[1])[None] <= end[:, None]
    last = lambda x: np.take_along_axis(x, end[:, None], 1)[:, 0]
    return Record(
        task=run.config.task,
        pooling=cfg.pooling,
        hgt_softmax=cfg.hgt_softmax,
        category=traj['category'],
        node_type=traj['node_type'],
        node_mask=traj['node_mask'].astype(bool),
        pos=traj['pos'],
        senders=traj['senders'],
        receivers=traj['receivers'],
        edge_type=traj['edge_type'],
        edge_mask=traj['edge_mask'].astype(bool),
        alpha=traj['alpha'],
        pool_weights=traj['pool_weights'],
        goal_classes=traj['goal_classes'],
        pose=traj['pose'],
        action=traj['action'],
        valid=valid,
        success=last(traj['metrics']['success']),
        spl=last(traj['metrics']['spl']),
        end=end,
        states=jax.device_get(states),
        env=env,
    )


# ------------------------------------------------------------------------------------------------
# Reductions
# ------------------------------------------------------------------------------------------------


def _relation(rec: Record) -> np.ndarray:
    """i32[B,T,M]: each edge's (edge type, sender type, receiver type) triple as an index of
    graph_types.RELATION_TRIPLES, -1 where the triple is not an HGT relation."""
    st = np.take_along_axis(rec.node_type, rec.senders, -1)
    rt = np.take_along_axis(rec.node_type, rec.receivers, -1)
    et = np.clip(rec.edge_type, 0, GT.NUM_EDGE_TYPES - 1)
    return GT.RELATION_INDEX[et, np.clip(st, 0, 2), np.clip(rt, 0, 2)]


def live_edges(rec: Record) -> np.ndarray:
    """bool[B,T,M]: edge live, both endpoints live, and a legal HGT relation (what gets attention)."""
    nm = rec.node_mask
    s_ok = np.take_along_axis(nm, rec.senders, -1)
    r_ok = np.take_along_axis(nm, rec.receivers, -1)
    return rec.edge_mask & s_ok & r_ok & (_relation(rec) >= 0) & rec.valid[..., None]


def _segment_sum(values, index, size):
    """Sum values[..., M] into bins index[..., M] -> [..., size] (leading axes kept)."""
    lead = values.shape[:-1]
    flat_v = values.reshape(-1, values.shape[-1])
    flat_i = index.reshape(-1, index.shape[-1])
    out = np.zeros((flat_v.shape[0], size), np.float64)
    rows = np.repeat(np.arange(flat_v.shape[0]), flat_v.shape[1])
    np.add.at(out, (rows, flat_i.ravel()), flat_v.ravel())
    return out.reshape(lead + (size,))


def uniform_alpha(rec: Record) -> np.ndarray:
    """f32[B,T,M]: 1 / (live in-degree of the receiver, counted within the edge's softmax group:
    all its in-edges, or those of the edge's relation under 'per_relation') on live edges, 0 elsewhere:
    the attention of mean aggregation, the null model that HGT attention is compared with."""
    live = live_edges(rec)
    n = rec.node_mask.shape[-1]
    group, size = rec.receivers, n
    if rec.hgt_softmax == 'per_relation':  # groups: (receiver, relation triple), as HGTConv's
        k = GT.NUM_RELATIONS
        group, size = rec.receivers * k + np.maximum(_relation(rec), 0), n * k
    indeg = _segment_sum(live.astype(np.float64), group, size)
    d = np.take_along_axis(indeg, group, -1)
    return np.where(live, 1.0 / np.maximum(d, 1.0), 0.0)


def edge_type_mass(rec: Record) -> dict:
    """Share of attention mass per edge type, per layer and head, over all valid steps.

    Returns {'mass': f64[L, H, K] (rows sum to 1 where any attention flowed), 'uniform': f64[K]
    (the same share under uniform attention), 'edges': i64[K] live edge count, 'names': K names}.
    """
    live = live_edges(rec)  # [B,T,M]
    K = GT.NUM_EDGE_TYPES
    onehot = (rec.edge_type[..., None] == np.arange(K)) & live[..., None]  # [B,T,M,K]
    L, H = rec.alpha.shape[2], rec.alpha.shape[-1]
    a = np.where(live[:, :, None, :, None], rec.alpha, 0.0)  # [B,T,L,M,H]
    mass = np.einsum('btlmh,btmk->lhk', a.astype(np.float64), onehot.astype(np.float64))
    total = mass.sum(-1, keepdims=True)
    u = np.einsum('btm,btmk->k', uniform_alpha(rec), onehot.astype(np.float64))
    return {
        'mass': np.where(total > 0, mass / np.maximum(total, 1e-12), 0.0).reshape(L, H, K),
        'uniform': u / max(u.sum(), 1e-12),
        'edges': onehot.sum((0, 1, 2)),
        'names': GT.EDGE_TYPES,
    }


def node_attention(rec: Record):
    """(received f64[B,T,L,N], uniform f64[B,T,N]): attention each node receives as a sender
    (sum of alpha over its live out-edges, mean over heads), and the same under uniform attention."""
    live = live_edges(rec)
    n = rec.node_mask.shape[-1]
    a = np.where(live[:, :, None, :], rec.alpha.mean(-1), 0.0)  # [B,T,L,M]
    send = np.broadcast_to(rec.senders[:, :, None, :], a.shape)
    received = _segment_sum(a, send, n)
    uniform = _segment_sum(uniform_alpha(rec), rec.senders, n)
    return received, uniform


def pool_shares(rec: Record) -> dict:
    """Normalised pooling weights f64[B,T,N] of the model and of mean pooling on the same graphs."""

    def norm(w):
        w = np.where(rec.node_mask, w, 0.0).astype(np.float64)
        s = w.sum(-1, keepdims=True)
        return np.where(s > 0, w / np.maximum(s, 1e-12), 0.0)

    return {'model': norm(rec.pool_weights), 'mean': norm(rec.node_mask.astype(np.float64))}


def goal_concentration(rec: Record, layer: int = -1) -> dict:
    """Per valid step (flattened), how much of each quantity sits on goal-category nodes.

    'goal_fraction': fraction of live nodes that are goal-category nodes; 'pool_model' /
    'pool_mean': share of the pooled vector from goal nodes (model's pooling, mean pooling), over
    the steps whose graph holds at least one goal-category node (before that, task pooling pools
    nothing and the share is undefined); 'with_goal': fraction of valid steps that have one;
    'hgt_goal' / 'hgt_other': for HGT layer `layer`, received attention / uniform received attention
    per node (>1 = listened to more than mean aggregation would), for goal and other nodes with a
    live out-edge (flattened over nodes); 'live_nodes': live node count per step.
    """
    v = rec.valid
    goal = rec.is_goal
    live_n = rec.node_mask.sum(-1)
    shares = pool_shares(rec)
    has_goal = v & goal.any(-1)
    out = {
        'goal_fraction': (goal.sum(-1) / np.maximum(live_n, 1))[v],
        'pool_model': (shares['model'] * goal).sum(-1)[has_goal],
        'pool_mean': (shares['mean'] * goal).sum(-1)[has_goal],
        'with_goal': float(has_goal.sum() / max(v.sum(), 1)),
        'live_nodes': live_n[v],
    }
    if rec.num_layers:
        received, uniform = node_attention(rec)
        r = received[:, :, layer]
        has = (uniform > 0) & v[..., None]
        ratio = np.where(has, r / np.maximum(uniform, 1e-12), np.nan)
        out['hgt_goal'] = ratio[has & goal]
        out['hgt_other'] = ratio[has & ~goal]
    else:
        out['hgt_goal'] = out['hgt_other'] = np.zeros(0)
    return out


def world_positions(rec: Record) -> np.ndarray:
    """f64[B,T,N,2] node xy in the world frame: the graph stores positions in the agent frame
    (x ahead, y left; graph_builder), so rotate by the agent's yaw and add its position. The choice
    task's positions are already canvas coordinates."""
    p = rec.pos[..., :2].astype(np.float64)
    if rec.task == 'choice':
        return p
    yaw = rec.pose[..., 2][..., None]
    c, s = np.cos(yaw), np.sin(yaw)
    x = rec.pose[..., None, 0] + c * p[..., 0] - s * p[..., 1]
    y = rec.pose[..., None, 1] + s * p[..., 0] + c * p[..., 1]
    return np.stack([x, y], -1)


def summary(rec: Record, layer: int = -1) -> dict:
    """Scalars for a table / CI: medians of goal_concentration plus episode SR."""
    g = goal_concentration(rec, layer)
    med = lambda x: float(np.nanmedian(x)) if np.size(x) else float('nan')
    return {
        'episodes': int(rec.valid.shape[0]),
        'steps': int(rec.valid.sum()),
        'success_rate': float(np.mean(rec.success)),
        'live_nodes': med(g['live_nodes']),
        'goal_fraction': med(g['goal_fraction']),
        'steps_with_goal_node': g['with_goal'],
        'pool_goal_share_model': med(g['pool_model']),
        'pool_goal_share_mean': med(g['pool_mean']),
        'hgt_ratio_goal': med(g['hgt_goal']),
        'hgt_ratio_other': med(g['hgt_other']),
    }


# ------------------------------------------------------------------------------------------------
# Figures (matplotlib; each returns the Figure)
# ------------------------------------------------------------------------------------------------


def _class_label(cid: int) -> str:
    from hron_jax.scenes import vocabulary as V

    return V.class_name(int(cid)).split(':', 1)[-1]


def plot_edge_type_attention(rec: Record, title: str = ''):
    """Left: attention-mass share per edge type for each HGT layer (heads averaged) with the
    uniform-attention share as black ticks. Right: log2(share / uniform share) per layer and head."""
    import matplotlib.pyplot as plt

    st = edge_type_mass(rec)
    present = np.nonzero(st['edges'] > 0)[0]
    names = [st['names'][k] for k in present]
    L, H = st['mass'].shape[:2]
    fig, (a0, a1) = plt.subplots(1, 2, figsize=(11, 3.4), gridspec_kw=dict(width_ratios=[1.4, 1]))
    if L == 0 or len(present) == 0:
        for a in (a0, a1):
            a.text(0.5, 0.5, 'no HGT attention in this model / rollout', ha='center', va='center')
            a.axis('off')
        return fig
    x = np.arange(len(present))
    width = 0.8 / L
    for l in range(L):
        a0.bar(x + (l - (L - 1) / 2) * width, st['mass'][l].mean(0)[present], width, label=f'layer {l}')
    a0.scatter(x, st['uniform'][present], marker='_', s=400, color='k', zorder=5, label='uniform attention')
    a0.set_xticks(x, names, rotation=30, ha='right', fontsize=8)
    a0.set_ylabel('share of attention mass')
    a0.legend(fontsize=7)
    a0.grid(axis='y', alpha=0.3)
    ratio = np.log2(
        np.maximum(st['mass'][:, :, present], 1e-6) / np.maximum(st['uniform'][present], 1e-6)
    ).reshape(L * H, -1)
    lim = max(1.0, float(np.nanmax(np.abs(ratio))))
    im = a1.imshow(ratio, cmap='RdBu_r', vmin=-lim, vmax=lim, aspect='auto')
    a1.set_xticks(x, names, rotation=30, ha='right', fontsize=8)
    a1.set_yticks(np.arange(L * H), [f'L{l} h{h}' for l in range(L) for h in range(H)], fontsize=8)
    a1.set_title('log2(share / uniform share)', fontsize=9)
    fig.colorbar(im, ax=a1, fraction=0.05)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    return fig


ROLES = ('goal object', 'goal furniture', 'goal room', 'other object', 'other furniture', 'other room')


def node_roles(rec: Record) -> np.ndarray:
    """i32[B,T,N] index into ROLES (-1 for dead nodes): a goal role when the node's category is the
    goal's object / furniture / room category, else 'other' + its node type."""
    role = np.full(rec.category.shape, -1, np.int64)
    other = {GT.OBJECT: 3, GT.FURNITURE: 4, GT.ROOM: 5}
    for nt, r in other.items():
        role = np.where(rec.node_mask & (rec.node_type == nt), r, role)
    for j in (2, 1, 0):  # object wins over furniture wins over room if categories coincide
        g = rec.goal_classes[..., j : j + 1]
        role = np.where(rec.node_mask & (g >= 0) & (rec.category == g), j, role)
    return role


def role_shares(rec: Record) -> dict:
    """Mean over valid steps of the pooled share per role (ROLES), model vs mean pooling."""
    shares = pool_shares(rec)
    role = node_roles(rec)
    v = rec.valid
    out = {}
    for key in ('model', 'mean'):
        out[key] = np.array(
            [(shares[key] * (role == r)).sum(-1)[v].mean() if v.any() else 0.0 for r in range(len(ROLES))]
        )
    out['count'] = np.array([(role == r).sum(-1)[v].mean() if v.any() else 0.0 for r in range(len(ROLES))])
    return out


def plot_pool_weights(rec: Record, episode: int = 0, max_nodes: int = 40, title: str = ''):
    """Left: share of the pooled graph vector per node role (goal object / furniture / room
    category, other nodes by type), mean over all valid steps: the model's pooling next to mean
    pooling on the same graphs, with the mean number of live nodes per role. Right (navigation):
    the model's normalised pooling weight of every node ever live in one episode over its steps,
    goal-category rows labelled in red."""
    import matplotlib.pyplot as plt

    rs = role_shares(rec)
    T = int(rec.end[episode]) + 1
    timeline = T > 1
    fig, axes = plt.subplots(
        1,
        2 if timeline else 1,
        figsize=(12 if timeline else 6, 4.2),
        squeeze=False,
        gridspec_kw=dict(width_ratios=[1, 1.6] if timeline else [1]),
    )
    ax = axes[0, 0]
    y = np.arange(len(ROLES))
    ax.barh(y - 0.2, rs['model'], 0.4, color='tab:green', label=f'model ({rec.pooling} pooling)')
    ax.barh(y + 0.2, rs['mean'], 0.4, color='tab:gray', label='mean pooling')
    ax.set_yticks(y, [f'{r} ({c:.1f})' for r, c in zip(ROLES, rs['count'])], fontsize=8)
    ax.invert_yaxis()
    ax.set_xlim(0, 1)
    ax.set_xlabel('share of the pooled graph vector')
    ax.set_title('pooling by node role (mean live nodes per step)', fontsize=9)
    ax.legend(fontsize=7, loc='lower right')
    ax.grid(axis='x', alpha=0.3)
    if timeline:
        ax = axes[0, 1]
        share = pool_shares(rec)['model'][episode, :T]
        ever = rec.node_mask[episode, :T].any(0)
        nodes = np.nonzero(ever)[0]
        goal_rows = rec.is_goal[episode, :T].any(0)[nodes]
        # Goal-category nodes first, then by node type, so the pooled ones sit together on top.
        order = np.lexsort((rec.node_type[episode, :T].max(0)[nodes], ~goal_rows))
        nodes, goal_rows = nodes[order][:max_nodes], goal_rows[order][:max_nodes]
        labels = [_class_label(c) for c in rec.category[episode, :T][:, nodes].max(0)]
        im = ax.imshow(
            share[:, nodes].T,
            aspect='auto',
            cmap='magma_r',
            vmin=0,
            vmax=max(float(share.max(initial=0)), 1e-6),
            interpolation='nearest',
        )
        ax.set_yticks(np.arange(len(nodes)), labels, fontsize=6)
        for t, g in zip(ax.get_yticklabels(), goal_rows):
            t.set_color('r' if g else 'k')
        ax.set_xlabel('step')
        ax.set_title(f'episode {episode}: model pooling weight / sum per node (live nodes)', fontsize=9)
        fig.colorbar(im, ax=ax, fraction=0.04)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    return fig


def plot_graph_on_map(
    rec: Record, episode: int = 0, step: int | None = None, layer: int = -1, ax=None, title: str | None = None
):
    """The scene graph of one step drawn at its nodes' world positions: over the top-down house
    map (navigation; trajectory so far in magenta, agent arrow) or the choice canvas. Nodes are
    coloured by the HGT attention they receive in `layer` relative to uniform attention (log2;
    node pooling weight when the model has no attention), sized by node type; goal-category nodes
    are ringed in red; edges are drawn with width proportional to their attention."""
    import matplotlib.pyplot as plt
    from matplotlib.colors import TwoSlopeNorm

    b = episode
    t = int(rec.end[b]) if step is None else int(step)
    xy = world_positions(rec)[b, t]
    live_nodes = rec.node_mask[b, t]
    live = live_edges(rec)[b, t]
    fig = None
    if ax is None:
        fig, ax = plt.subplots(figsize=(8, 6) if rec.task != 'choice' else (5, 5))
    if rec.task == 'choice':
        ax.set_xlim(-1.05, 1.05)
        ax.set_ylim(-1.05, 1.05)
        ax.axvline(0.0, color='0.85', ls='--', lw=1)
        ax.set_aspect('equal')
    else:
        from hron_jax.scenes.plot import plot_topdown

        plot_topdown(rec.env.scene, ax, labels=False, slots=False, objects=False)
        poses = rec.pose[b, : t + 1]
        ax.plot(poses[:, 0], poses[:, 1], '-', color='m', lw=1.0, alpha=0.7, zorder=15)
        p = rec.pose[b, t]
        ax.arrow(p[0], p[1], 0.45 * np.cos(p[2]), 0.45 * np.sin(p[2]), width=0.07, color='m', zorder=16)
    if rec.num_layers:
        received, uniform = node_attention(rec)
        r, u = received[b, t, layer], uniform[b, t]
        value = np.where(u > 0, np.log2(np.maximum(r, 1e-6) / np.maximum(u, 1e-6)), 0.0)
        lim = max(1.0, float(np.abs(value[live_nodes]).max(initial=0)))
        norm, cmap, label = (
            TwoSlopeNorm(0.0, -lim, lim),
            'coolwarm',
            f'log2(received attention / uniform), layer {layer % rec.num_layers}',
        )
        a_e = rec.alpha[b, t, layer].mean(-1)
    else:
        value = pool_shares(rec)['model'][b, t]
        norm, cmap, label = None, 'viridis', 'pooling weight / sum'
        a_e = uniform_alpha(rec)[b, t]
    for e in np.nonzero(live)[0]:
        s, r_ = rec.senders[b, t, e], rec.receivers[b, t, e]
        ax.plot(*zip(xy[s], xy[r_]), '-', color='0.3', lw=0.3 + 2.5 * float(a_e[e]), alpha=0.6, zorder=17)
    sc = None
    goal = rec.is_goal[b, t]
    for nt, marker in NODE_TYPE_MARKERS.items():
        m = live_nodes & (rec.node_type[b, t] == nt)
        if not m.any():
            continue
        sc = ax.scatter(
            xy[m, 0],
            xy[m, 1],
            c=value[m],
            cmap=cmap,
            norm=norm,
            marker=marker,
            s=NODE_TYPE_SIZES[nt],
            edgecolors=np.where(goal[m], 'r', 'k').tolist(),
            linewidths=np.where(goal[m], 2.0, 0.5),
            zorder=18,
            vmin=None if norm is not None else 0.0,
        )
    if sc is not None:
        plt.colorbar(sc, ax=ax, fraction=0.04, label=label)
    from hron_jax.goals import decode_goal

    words = ' '.join(w for w in decode_goal(np.asarray(rec.states.obs['goal'][b])) if w)
    ax.set_title(
        title
        if title is not None
        else f'episode {b}, step {t}: goal "{words}" ({"success" if rec.success[b] > 0.5 else "failure"})'
        '\nsquares rooms, diamonds furniture, dots objects; red ring: goal category',
        fontsize=8,
    )
    if fig is not None:
        fig.tight_layout()
    return fig if fig is not None else ax.figure


def plot_goal_concentration(records: dict, layer: int = -1, title: str = ''):
    """Compare conditions (label -> Record, e.g. without / with distractors). Left: share of the
    pooled graph vector from goal-category nodes, model pooling vs mean pooling on the same graphs.
    Right: HGT attention received relative to uniform, goal-category vs other nodes."""
    import matplotlib.pyplot as plt

    labels = list(records)
    stats = {k: goal_concentration(r, layer) for k, r in records.items()}
    fig, (a0, a1) = plt.subplots(1, 2, figsize=(11, 3.6))
    data, pos, ticks, colours = [], [], [], []
    for i, k in enumerate(labels):
        for j, (key, c) in enumerate((('pool_model', 'tab:green'), ('pool_mean', 'tab:gray'))):
            data.append(stats[k][key])
            pos.append(3 * i + j)
            colours.append(c)
        ticks.append(3 * i + 0.5)
    _boxes(a0, data, pos, colours)
    a0.set_xticks(ticks, [f'{k}\n({100 * stats[k]["with_goal"]:.0f} % of steps)' for k in labels], fontsize=8)
    a0.set_ylabel('pooled share from goal-category nodes')
    a0.set_title('steps with a goal-category node in the graph', fontsize=9)
    a0.set_ylim(-0.03, 1.03)
    a0.legend(
        handles=[
            plt.Rectangle((0, 0), 1, 1, color='tab:green', alpha=0.6),
            plt.Rectangle((0, 0), 1, 1, color='tab:gray', alpha=0.6),
        ],
        labels=[f'model ({next(iter(records.values())).pooling} pooling)', 'mean pooling'],
        fontsize=7,
        loc='center right',
    )
    a0.grid(axis='y', alpha=0.3)
    data, pos, colours = [], [], []
    for i, k in enumerate(labels):
        for j, (key, c) in enumerate((('hgt_goal', 'tab:red'), ('hgt_other', 'tab:blue'))):
            data.append(np.log2(np.maximum(stats[k][key], 1e-6)))
            pos.append(3 * i + j)
            colours.append(c)
    if any(np.size(d) for d in data):
        _boxes(a1, data, pos, colours)
        a1.axhline(0.0, color='k', lw=0.8)
        a1.legend(
            handles=[
                plt.Rectangle((0, 0), 1, 1, color='tab:red', alpha=0.6),
                plt.Rectangle((0, 0), 1, 1, color='tab:blue', alpha=0.6),
            ],
            labels=['goal-category nodes', 'other nodes'],
            fontsize=7,
        )
    else:
        a1.text(0.5, 0.5, 'no HGT attention', ha='center', va='center', transform=a1.transAxes)
    a1.set_xticks(ticks, labels, fontsize=8)
    a1.set_ylabel('log2(received / uniform)')
    L = next(iter(records.values())).num_layers
    a1.set_title(f'HGT attention received, layer {layer % L if L else layer}', fontsize=9)
    a1.grid(axis='y', alpha=0.3)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    return fig


def _boxes(ax, data, positions, colours):
    keep = [i for i, d in enumerate(data) if np.size(d)]
    if not keep:
        return
    bp = ax.boxplot(
        [np.asarray(data[i], np.float64) for i in keep],
        positions=[positions[i] for i in keep],
        widths=0.8,
        patch_artist=True,
        showfliers=False,
    )
    for patch, i in zip(bp['boxes'], keep):
        patch.set_facecolor(colours[i])
        patch.set_alpha(0.6)
