"""Top-down pictures of navigation episodes, for eyeballing policies (eval.py's trajectories.png;
`python eval.py --policy oracle --task directed` draws the oracle's).

`plot_episode(env, state, poses, path)` draws the scene (hron_jax.scenes.plot.plot_topdown), the
episode's objects (target: star with its success circle; directed wrong object: cross with its
circle; distractors: dots, goal category ringed), the agent's start (arrow) and trajectory, and the
goal in the title. Host-side (matplotlib), not jittable.
"""

from __future__ import annotations

import jax
import numpy as np

from hron_jax import goals as goal_lib
from hron_jax.scenes import vocabulary as V
from hron_jax.scenes.plot import plot_topdown


def plot_episode(env, state, poses, path=None, title: str | None = None, ax=None):
    """Draw one episode (state: its first EnvState; poses f32[T, 3]); save to `path` if given."""
    import matplotlib

    if ax is None:
        matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    scene = env.scene
    inner = jax.tree.map(np.asarray, state.inner)
    pl = inner.placement
    poses = np.asarray(poses)
    fig = None
    if ax is None:
        size = scene.bounds[1, :2] - scene.bounds[0, :2]
        fig, ax = plt.subplots(figsize=(max(4.0, size[0] * 0.6), max(3.0, size[1] * 0.6)))
    plot_topdown(scene, ax, labels=True, slots=False, objects=False)
    r = env.config.success_distance
    goal = inner.goal
    off = scene.num_rooms + scene.num_furniture
    for j in np.nonzero(pl.active)[0]:
        cat = int(scene.vocab_index[off + j])
        col = V.OBJECT_SHAPES[V.OBJECTS[cat]].rgba[:3]
        x, y = pl.pos[j, :2]
        if j == int(inner.target):
            ax.plot(x, y, '*', ms=12, color=col, mec='k', zorder=12)
            ax.add_patch(matplotlib.patches.Circle((x, y), r, fill=False, ec='g', lw=1.2, zorder=11))
        else:
            ax.plot(x, y, 'o', ms=5, color=col, mec='r' if cat == int(goal[0]) else 'k', mew=1.0, zorder=12)
    if np.all(np.isfinite(inner.wrong_xy)):
        x, y = inner.wrong_xy
        ax.plot(x, y, 'x', ms=10, color='r', mew=2, zorder=12)
        ax.add_patch(matplotlib.patches.Circle((x, y), r, fill=False, ec='r', ls='--', lw=1.0, zorder=11))
    ax.plot(poses[:, 0], poses[:, 1], '-', color='m', lw=1.2, zorder=13)
    ax.plot(poses[:, 0], poses[:, 1], '.', color='m', ms=2.5, zorder=13)
    p0 = poses[0]
    ax.arrow(p0[0], p0[1], 0.4 * np.cos(p0[2]), 0.4 * np.sin(p0[2]), width=0.06, color='b', zorder=14)
    words = [w for w in goal_lib.decode_goal(np.asarray(state.obs['goal'])) if w]
    ax.set_title(title or 'goal: ' + ' '.join(words), fontsize=8)
    if fig is not None:
        fig.tight_layout()
        if path is not None:
            fig.savefig(path, dpi=120)
        plt.close(fig)
    return ax
