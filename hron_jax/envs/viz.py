"""Top-down pictures of navigation episodes, for eyeballing policies (the oracle in particular).

    python -m hron_jax.envs.viz --task directed --seed 0 --out oracle_directed.png [--policy random]

`plot_episode(env, state, poses, path)` draws the scene (hron_jax.scenes.plot.plot_topdown), the
episode's objects (target: star with its success circle; directed wrong object: cross with its
circle; distractors: dots, goal category ringed), the agent's start (arrow) and trajectory, and the
goal in the title. `run_episode(env, policy, seed)` runs one episode of a NavigationEnv built
with auto_reset=False and returns (first state, poses f32[T + 1, 3], last metrics).
Host-side (matplotlib), not jittable.
"""
from __future__ import annotations

import argparse

import jax
import jax.numpy as jnp
import numpy as np

from hron_jax import goals as goal_lib
from hron_jax.scenes import vocabulary as V
from hron_jax.scenes.plot import plot_topdown


def run_episode(env, policy, seed: int = 0, max_steps: int | None = None):
    """One episode from reset(PRNGKey(seed)) until done (or max_steps). Needs auto_reset=False."""
    if env.config.auto_reset:
        raise ValueError('run_episode needs an env built with auto_reset=False')
    from hron_jax.envs.navigation import make_rollout
    n = max_steps or env.config.max_steps
    key = jax.random.PRNGKey(seed)
    state = jax.jit(env.reset)(key)
    _, traj = jax.jit(make_rollout(env, policy, n))(state, jax.random.fold_in(key, 1))
    done = np.asarray(traj['done']) > 0.5
    end = int(np.argmax(done)) + 1 if done.any() else n
    poses = np.concatenate([np.asarray(traj['pose'])[:end], np.asarray(traj['final_pose'])[end - 1:end]])
    metrics = {k: float(np.asarray(v)[end - 1]) for k, v in traj['metrics'].items()}
    return state, poses, metrics


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
            ax.plot(x, y, 'o', ms=5, color=col, mec='r' if cat == int(goal[0]) else 'k', mew=1.0,
                    zorder=12)
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


def main(argv=None):
    from hron_jax.envs import make_env
    from hron_jax.envs.navigation import oracle_policy, random_policy

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument('--task', default='directed', choices=('directed', 'exploratory'))
    ap.add_argument('--scene', default=None)
    ap.add_argument('--seed', type=int, default=0)
    ap.add_argument('--policy', default='oracle', choices=('oracle', 'random'))
    ap.add_argument('--distractors', action='store_true')
    ap.add_argument('--out', default=None)
    args = ap.parse_args(argv)
    env = make_env(args.task, args.scene, image_size=16, auto_reset=False,
                   distractors=args.distractors)
    policy = oracle_policy if args.policy == 'oracle' else random_policy
    state, poses, metrics = run_episode(env, policy, args.seed)
    out = args.out or f'{args.policy}_{args.task}_{args.seed}.png'
    words = ' '.join(w for w in goal_lib.decode_goal(np.asarray(state.obs['goal'])) if w)
    title = (f'{args.task} {args.policy}: {words}\nsuccess {metrics["success"]:.0f} '
             f'SPL {metrics["spl"]:.3f} path {metrics["path_length"]:.2f} m '
             f'd0 {float(state.inner.d0):.2f} m steps {metrics["episode_length"]:.0f}')
    plot_episode(env, state, poses, out, title)
    print(title)
    print(out)


if __name__ == '__main__':
    main()
