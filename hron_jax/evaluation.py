"""Evaluation of trained runs and reference policies: SR / SPL tables, trajectory plots, videos.

Role: everything behind ``eval.py`` (which only calls `main`).

    python eval.py RUN_DIR [--episodes 20] [--greedy] [--video]      # a train.py run (latest ckpt)
    python eval.py RUN_DIR/checkpoints/<U>                          # a given checkpoint
    python eval.py --policy oracle --task directed [--episodes 20]  # reference policies
    python eval.py RUN_DIR --policy random                          # ... on a run's env config

Protocol (the paper: "averaged over 20 episodes across three random seeds"): every seed of the run
(jax.vmap over its parameters) plays the same `episodes` episodes, episode i starting from
env.reset(fold_in(PRNGKey(--seed), i)), so seeds, checkpoints and policies are compared on the same
starts and goals. Each episode runs from reset until it ends (success, directed wrong object, or
the env's max_steps) in an env without auto-reset; the choice task's episodes are one step.
The policy samples from its action distribution (as during training, and as RLlib evaluates by
default; a reactive policy run greedily can loop forever) unless --greedy.

Shapes: `evaluate(...)` returns numpy per-episode metrics [S, E] ('success', 'spl',
'episode_length', 'path_length', 'return'), 'end' [S, E] (index of each episode's last step) and,
for the navigation tasks, 'poses' [S, E, T, 3] before every step and 'last_pose' [S, E, 3] after
the last one, and 'compile_s' / 'run_s' (seconds); `summarize` reduces them to SR / SPL mean, std over seeds
(of the per-seed means) and std over all episodes.

Outputs in --out (default RUN_DIR/eval_<policy>_<greedy|sampled>, or runs/eval_<task>_<policy>...
for a reference policy without a run): eval.md (Markdown table like the paper's), eval.json (summary,
per-seed and per-episode values), trajectories.png (top-down paths of the first --plots episodes
of seed 0 over the house map, hron_jax.envs.viz; for the choice task the scenes with the chosen
side), and with --video an animation of the agent's RGB-D view in episode 0 of seed 0 (mp4 with
ffmpeg, else gif).
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time
from pathlib import Path

import numpy as np

from hron_jax import cli
from hron_jax.envs import TASKS
from hron_jax.envs.base import EPISODE_METRICS
from hron_jax.errors import CheckpointError, UsageError
from hron_jax.rollout import episode_ends, random_policy, unroll
from hron_jax.run_config import DEFAULT_TASK, build_env, build_network, run_label
from hron_jax.run_dir import load_config, restore_params, write_json
from hron_jax.training import FAST_COMPILE, compile_lowered

POLICIES = ('trained', 'oracle', 'random')


# ------------------------------------------------------------------------------------------------
# Policies: policy(env, state, rng, params) -> action for ONE env (vmapped outside).
# ------------------------------------------------------------------------------------------------


def model_policy(network, greedy: bool):
    import jax
    import jax.numpy as jnp

    def policy(env, state, rng, params):
        logits, _ = network.apply(params, state.obs)
        return (jnp.argmax(logits, -1) if greedy else jax.random.categorical(rng, logits)).astype(jnp.int32)

    return policy


def reference_policy(task: str, name: str):
    if name == 'random':
        fn = random_policy
    elif task == 'choice':
        fn = lambda env, state, rng: state.inner.correct_action
    else:
        from hron_jax.envs.navigation import oracle_policy as fn
    return lambda env, state, rng, params: fn(env, state, rng)


# ------------------------------------------------------------------------------------------------
# Rollouts
# ------------------------------------------------------------------------------------------------


def evaluate(
    env, policy, params, num_seeds: int, episodes: int, seed: int = 0, compiler_options: dict | None = None
) -> dict:
    """Run `episodes` episodes for each of `num_seeds` seeds (params: leading seed axis, or None for
    a parameter-free policy). Returns numpy arrays, see the module docstring; 'states' holds the
    first EnvState of every episode [S, E, ...] (for plots)."""
    import jax
    import jax.numpy as jnp

    key = jax.random.PRNGKey(seed)
    reset_keys = jax.vmap(lambda i: jax.random.fold_in(key, i))(jnp.arange(episodes))
    policy_keys = jax.vmap(lambda s: jax.random.fold_in(jax.random.fold_in(key, 10**6), s))(
        jnp.arange(num_seeds)
    )
    record = None
    if hasattr(env, 'agent_pose'):  # navigation: the agent's path, for the trajectory plots
        from hron_jax.envs.navigation import pose_record

        record = pose_record(env)

    def one_seed(params, rng):
        act = lambda s, k: (policy(env, s, k, params), {})
        episode = lambda state, k: unroll(env.step, state, act, k, env.config.max_steps, record=record)[2]
        states = jax.vmap(env.reset)(reset_keys)
        return states, jax.vmap(episode)(states, jax.random.split(rng, episodes))

    run = jax.jit(jax.vmap(one_seed, in_axes=(None if params is None else 0, 0)))
    t0 = time.perf_counter()
    compiled = compile_lowered(run.lower(params, policy_keys), compiler_options)
    t1 = time.perf_counter()
    states, traj = jax.device_get(compiled(params, policy_keys))
    t2 = time.perf_counter()
    finished, end = episode_ends(traj['done'])  # [S, E]
    take = lambda x: np.take_along_axis(np.asarray(x), end[..., None], -1)[..., 0]
    out = {k: take(traj['metrics'][k]).astype(np.float64) for k in EPISODE_METRICS}
    out['finished'] = finished
    out['actions'] = np.asarray(traj['action'])
    out['end'] = end
    if record is not None:
        out['poses'] = np.asarray(traj['pose'])  # before every step [S, E, T, 3]
        out['last_pose'] = np.take_along_axis(  # after the episode's last step
            np.asarray(traj['final_pose']), end[..., None, None], 2
        )[:, :, 0]
        out['d0'] = np.asarray(traj['d0'])[..., 0]
    out['states'] = states
    out['compile_s'], out['run_s'] = t1 - t0, t2 - t1
    return out


def summarize(result: dict) -> dict:
    """SR / SPL (and episode length) statistics: mean over all episodes, sample std (ddof=1, as
    tools/reproduce.py's report) over seeds of the per-seed means (0 for one seed), std over all
    episodes, per-seed means."""
    out = {}
    for k in ('success', 'spl', 'episode_length'):
        v = np.asarray(result[k], np.float64)  # [S, E]
        per_seed = v.mean(1)
        out[k] = {
            'mean': float(v.mean()),
            'std_seeds': float(per_seed.std(ddof=1)) if len(per_seed) > 1 else 0.0,
            'std_episodes': float(v.std()),
            'per_seed': [float(x) for x in per_seed],
        }
    out['seeds'], out['episodes'] = map(int, np.shape(result['success']))
    out['unfinished'] = int((~np.asarray(result['finished'])).sum())
    return out


def markdown_table(rows: list[dict]) -> str:
    """rows: dicts with task, distractors, model, policy, mode, summary (see summarize)."""
    lines = [
        '| Task | Distractors | Model | Policy | Seeds x episodes | SR ↑ | SPL ↑ |',
        '| --- | --- | --- | --- | ---: | --- | --- |',
    ]
    notes = set()
    for r in rows:
        s = r['summary']
        spread = 'std_seeds' if s['seeds'] > 1 else 'std_episodes'
        notes.add(
            'over seeds (sample std, ddof=1, of the per-seed means)' if s['seeds'] > 1 else 'over episodes'
        )
        cell = lambda k: f"{s[k]['mean']:.3f} ± {s[k][spread]:.3f}"
        lines.append(
            f"| {r['task']} | {'yes' if r['distractors'] else 'no'} | {r['model']} | "
            f"{r['policy']} ({r['mode']}) | {s['seeds']} x {s['episodes']} | "
            f"{cell('success')} | {cell('spl')} |"
        )
    lines.append('')
    lines.append('mean over all episodes ± std ' + '; '.join(sorted(notes)) + '.')
    return '\n'.join(lines)


def record_episode(env, policy, params, key, max_steps: int) -> dict:
    """One episode of one env (params without seed axis or None), with its observations:
    {'rgbd': f32[T, H, W, 4], 'action': i32[T], 'reward': f32[T]}, cut at the episode's end."""
    import jax

    @jax.jit
    def run(key):
        act = lambda s, k: (policy(env, s, k, params), {})
        frames = lambda state, action, extras, nxt: {'rgbd': state.obs['rgbd']}
        return unroll(env.step, env.reset(key), act, jax.random.fold_in(key, 1), max_steps, record=frames)[2]

    traj = jax.device_get(run(key))
    n = int(episode_ends(traj['done'])[1]) + 1
    return {k: np.asarray(traj[k])[:n] for k in ('rgbd', 'action', 'reward', 'done')}


# ------------------------------------------------------------------------------------------------
# Pictures
# ------------------------------------------------------------------------------------------------


def _index(tree, *idx):
    import jax

    return jax.tree.map(lambda x: np.asarray(x)[idx], tree)


def plot_trajectories(env, result: dict, path, count: int = 4, seed_index: int = 0) -> None:
    """Top-down paths of the first `count` episodes of one seed (navigation), or the choice scenes
    with the chosen side; one PNG grid."""
    import matplotlib

    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    count = min(count, np.shape(result['success'])[1])
    if count < 1:
        return
    cols = min(count, 2 if 'poses' in result else 4)
    rows = math.ceil(count / cols)
    nav = 'poses' in result
    if nav:
        from hron_jax.envs.viz import plot_episode

        lo, hi = env.scene.bounds[0, :2], env.scene.bounds[1, :2]
        w, h = max(4.0, (hi - lo)[0] * 0.5), max(3.0, (hi - lo)[1] * 0.5)
    else:
        from hron_jax.envs.choice import render

        w = h = 2.6
    fig, axes = plt.subplots(rows, cols, figsize=(w * cols, h * rows), squeeze=False)
    for i in range(rows * cols):
        ax = axes.flat[i]
        if i >= count:
            ax.axis('off')
            continue
        s, e = seed_index, i
        state = _index(result['states'], s, e)
        ok = result['success'][s, e] > 0.5
        if nav:
            n = int(result['end'][s, e]) + 1
            poses = np.concatenate([result['poses'][s, e, :n], result['last_pose'][s, e][None]])
            plot_episode(env, state, poses, ax=ax)
            ax.set_title(
                f"ep {e}: {'success' if ok else 'failure'}, SPL {result['spl'][s, e]:.2f}, "
                f"{n} steps\n" + ax.get_title(),
                fontsize=7,
            )
        else:
            ax.imshow(render(state))
            ax.axis('off')
            side = 'left' if int(result['actions'][s, e, 0]) == 0 else 'right'
            ax.set_title(f"ep {e}: chose {side} ({'correct' if ok else 'wrong'})", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def save_video(frames: dict, path: str, title: str = '', fps: int = 8) -> str:
    """Animate the RGB and depth channels of frames['rgbd'] [T, H, W, 4]; mp4 when ffmpeg is
    available, else a pillow gif (path's suffix is replaced accordingly). Returns the path."""
    import matplotlib

    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    from matplotlib import animation

    from hron_jax.sim import ACTION_NAMES

    rgbd = np.asarray(frames['rgbd'])
    fig, (a0, a1) = plt.subplots(1, 2, figsize=(5.2, 2.9))
    im0 = a0.imshow(np.clip(rgbd[0, ..., :3], 0, 1), interpolation='nearest')
    im1 = a1.imshow(rgbd[0, ..., 3], cmap='viridis', vmin=0, vmax=1, interpolation='nearest')
    a0.set_title('RGB', fontsize=8)
    a1.set_title('depth / max depth', fontsize=8)
    for a in (a0, a1):
        a.axis('off')
    text = fig.suptitle('', fontsize=7)

    def draw(t):
        im0.set_data(np.clip(rgbd[t, ..., :3], 0, 1))
        im1.set_data(rgbd[t, ..., 3])
        act = ACTION_NAMES[int(frames['action'][t])]
        text.set_text(f'{title}\nstep {t}: {act}, reward {float(frames["reward"][t]):+.2f}')
        return im0, im1, text

    anim = animation.FuncAnimation(fig, draw, frames=len(rgbd), blit=False)
    base = os.path.splitext(path)[0]
    if animation.writers.is_available('ffmpeg'):
        path = base + '.mp4'
        anim.save(path, writer=animation.FFMpegWriter(fps=fps), dpi=100)
    else:
        path = base + '.gif'
        anim.save(path, writer=animation.PillowWriter(fps=fps), dpi=80)
    plt.close(fig)
    return path


# ------------------------------------------------------------------------------------------------
# CLI
# ------------------------------------------------------------------------------------------------


def build_parser(prog: str = 'eval.py') -> argparse.ArgumentParser:
    p = cli.ArgumentParser(
        prog=prog,
        description=(
            'Evaluate a train.py run (SR / SPL over episodes and seeds, like the paper\'s tables) or a '
            'reference policy. Writes eval.md, eval.json and trajectories.png.'
        ),
    )
    p.add_argument('run', nargs='?', help='run directory, or RUN_DIR/checkpoints/<update>')
    p.add_argument(
        '--policy',
        choices=POLICIES,
        help="'trained' (default with a run) or a reference policy (oracle: shortest-path follower; random)",
    )
    p.add_argument('--episodes', type=int, default=20, help='episodes per seed (paper: 20)')
    p.add_argument('--greedy', action='store_true', help='argmax actions (default: sample)')
    p.add_argument('--seed', type=int, default=0, help='seed of the episode starts / goals')
    p.add_argument('--num-seeds', type=int, default=1, help='reference policies: seeds (random)')
    p.add_argument('--step', type=int, help='checkpoint update to load (default latest)')
    p.add_argument('--out', help='output directory')
    p.add_argument('--plots', type=int, default=4, help='episodes drawn in trajectories.png')
    p.add_argument(
        '--video',
        nargs='?',
        const='',
        metavar='PATH',
        help='animate the RGB-D view of episode 0 (navigation tasks)',
    )
    p.add_argument(
        '--fast-compile',
        action='store_true',
        help='XLA without LLVM optimisation (as train.py --fast-compile)',
    )
    p.add_argument(
        '--compile-cache',
        metavar='DIR',
        help='persistent XLA compilation cache (default as train.py; \'none\' disables)',
    )
    p.add_argument(
        '--scene',
        help='scene MJCF; with a run: evaluate its policy on this scene instead '
        'of the training one (held-out houses), output dir eval_<policy>_<mode>_<scene>',
    )
    g = p.add_argument_group('env of a reference policy (without a run directory)')
    g.add_argument('--task', choices=TASKS, default=None)
    g.add_argument('--distractors', action='store_true')
    g.add_argument('--premap', action='store_true')
    g.add_argument('--env-option', action='append', metavar='NAME=VALUE')
    return p


def _resolve_run(path: str) -> tuple[Path, int | None]:
    """RUN_DIR or RUN_DIR/checkpoints/<U> -> (run dir, step or None)."""
    p = Path(path)
    if (p / 'config.json').is_file():
        return p, None
    if p.parent.name == 'checkpoints' and p.name.isdigit() and (p.parent.parent / 'config.json').is_file():
        return p.parent.parent, int(p.name)
    if not p.exists():
        raise UsageError(f'{p}: no such run directory')
    raise UsageError(f'{p}: neither a run directory (with config.json) nor RUN_DIR/checkpoints/<update>')


def main(argv=None, prog: str = 'eval.py') -> int:
    cli.tune_malloc()
    try:
        args = build_parser(prog).parse_args(argv)
    except SystemExit as e:  # --help, or a bad option (argparse has printed its one line)
        return e.code
    log = lambda s: print(s, file=sys.stderr, flush=True)
    try:
        for option, value, low in (
            ('--episodes', args.episodes, 1),
            ('--num-seeds', args.num_seeds, 1),
            ('--seed', args.seed, 0),
            ('--plots', args.plots, 0),
            ('--step', args.step, 0),
        ):
            if value is not None and value < low:
                raise UsageError(f'{option}: must be >= {low}, got {value}')
        if args.run:
            run_dir, step = _resolve_run(args.run)
            if args.step is not None:
                step = args.step
            if args.task or args.distractors or args.premap or args.env_option:
                raise UsageError(
                    'with a run directory the env comes from its config.json; drop '
                    '--task / --distractors / --premap / --env-option'
                )
            config = load_config(run_dir)
            if args.scene:  # held-out scenes: the model takes any node count of the vocabulary
                config = cli.config_from_args({'scene': args.scene}, base=config)
            policy_name = args.policy or 'trained'
        else:
            if args.policy in (None, 'trained'):
                raise UsageError('give a run directory, or --policy oracle|random with --task')
            opts = {'task': args.task or DEFAULT_TASK, 'distractors': args.distractors, 'premap': args.premap}
            if args.scene:
                opts['scene'] = args.scene
            if args.env_option:
                opts['env_option'] = args.env_option
            config = cli.config_from_args(opts)
            run_dir, step, policy_name = None, None, args.policy
        cli.setup_compile_cache(args.compile_cache)
        import absl.logging

        absl.logging.set_verbosity(absl.logging.ERROR)
        nav = config.task != 'choice'
        try:
            env = build_env(config, episodic=True)
        except (ValueError, TypeError, OSError) as e:
            raise UsageError(f'cannot build the {config.task} env: {e}') from None
        if policy_name == 'trained':
            network = build_network(config, env)
            params, step = restore_params(run_dir, config, env, network, step)
            policy, num_seeds = model_policy(network, args.greedy), config.num_seeds
        else:
            params, num_seeds = None, args.num_seeds
            policy = reference_policy(config.task, policy_name)
    except (UsageError, CheckpointError) as e:
        print(cli.error_line(prog, e), file=sys.stderr)
        return 2 if isinstance(e, UsageError) else 1

    mode = 'greedy' if args.greedy else 'sampled'
    if policy_name == 'oracle':
        mode = 'deterministic'
    name = policy_name if policy_name == 'oracle' else f'{policy_name}_{mode}'
    if run_dir is not None and args.scene:
        name += '_' + Path(args.scene).stem
    out = (
        Path(args.out)
        if args.out
        else (
            run_dir / f'eval_{name}' if run_dir is not None else Path('runs') / f'eval_{config.task}_{name}'
        )
    )
    out.mkdir(parents=True, exist_ok=True)
    log(
        f'evaluating {policy_name} policy ({mode}) on {config.task}: {num_seeds} seed(s) x '
        f'{args.episodes} episodes'
        + (f', checkpoint {run_dir}/checkpoints/{step}' if step is not None else '')
    )
    fast = args.fast_compile or config.fast_compile
    result = evaluate(
        env, policy, params, num_seeds, args.episodes, args.seed, dict(FAST_COMPILE) if fast else None
    )
    steps = num_seeds * args.episodes * env.config.max_steps
    log(
        f"compiled in {result['compile_s']:.1f} s; played {steps} env steps in {result['run_s']:.1f} s "
        f"({steps / result['run_s']:.0f} steps/s, every episode to the env's max_steps)"
    )
    summary = summarize(result)
    row = dict(
        task=config.task,
        distractors=config.distractors,
        model=run_label(config) if policy_name == 'trained' else '-',
        policy=policy_name,
        mode=mode,
        summary=summary,
    )
    table = markdown_table([row])
    (out / 'eval.md').write_text(table + '\n')
    per_episode = {k: np.asarray(result[k]).tolist() for k in EPISODE_METRICS}
    record = dict(
        run_dir=str(run_dir) if run_dir else None,
        step=step,
        task=config.task,
        model=config.model if policy_name == 'trained' else None,
        policy=policy_name,
        mode=mode,
        eval_seed=args.seed,
        config=config.to_dict(),
        summary=summary,
        per_episode=per_episode,
    )
    write_json(out / 'eval.json', record)
    if args.plots > 0:
        plot_trajectories(env, result, out / 'trajectories.png', args.plots)
    if args.video is not None:
        if not nav:
            log('--video: the choice task has no camera view; skipped')
        else:
            import jax
            import jax.numpy as jnp

            p0 = None if params is None else jax.tree.map(lambda x: jnp.asarray(x[0]), params)
            frames = record_episode(
                env, policy, p0, jax.random.fold_in(jax.random.PRNGKey(args.seed), 0), env.config.max_steps
            )
            from hron_jax.goals import decode_goal

            words = ' '.join(w for w in decode_goal(np.asarray(result['states'].obs['goal'][0, 0])) if w)
            path = save_video(frames, args.video or str(out / 'video.mp4'), f'goal: {words}')
            log(f'video: {path}')
    print(table)
    log(f'wrote {out}/eval.md, eval.json' + (', trajectories.png' if args.plots > 0 else ''))
    return 0
