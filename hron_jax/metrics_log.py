"""Training metrics: per-chunk summaries over seeds, the run's log files, learning curves.

    summarize_chunk(metrics {name: f32[S, n]}) -> {name: f64[S]}   one chunk of n updates, S seeds
    log = MetricsLog(run_dir, resume_update)    metrics.jsonl (source of truth), metrics.csv, tb/
    row = log.append(update, summary, wall_time, steps_per_s)      mean / std over seeds + per seed
    pooled_curve(rows, keys, min_episodes) -> (env_steps f64[R], {key: f64[S, R]})
                                                 per seed, episode-weighted over trailing rows
    curve_rows([rows of each run]) -> [{'env_steps', 'success', 'success_std', ...}]  over all seeds
    plot_learning_curves({label: curve rows}, path)  SR and return vs env steps, mean +- std
    recent_success(rows, after_update) -> (SR, episodes)   over the rows after an update
    window_means(rows, size, keys) -> [{'first_update', 'last_update', 'episodes', key, ...}]
                                                 per window of `size` rows, means over seeds

A resumed run rewinds the log to the update it resumes from (rows written after that checkpoint
are replayed by the training that follows), so the files equal those of an uninterrupted run.
"""

from __future__ import annotations

import csv
import json
import math
import os
from pathlib import Path

import numpy as np

from hron_jax.envs.base import EPISODE_METRICS
from hron_jax.run_dir import read_metrics


def summarize_chunk(metrics: dict) -> dict[str, np.ndarray]:
    """{name: f32[S]} from one chunk's PPO metrics {name: [S, n]}: episode metrics averaged over
    the episodes completed in the chunk (NaN if none), 'episodes' summed, 'env_steps' the last
    value, everything else (losses, reward) the mean over updates."""
    m = {k: np.asarray(v, np.float64) for k, v in metrics.items()}
    ep = m['episodes']
    count = ep.sum(-1)
    out = {}
    for k, v in m.items():
        if k in EPISODE_METRICS:
            s = np.where(ep > 0, v, 0.0) * ep
            out[k] = np.where(count > 0, s.sum(-1) / np.maximum(count, 1), np.nan)
        elif k == 'episodes':
            out[k] = count
        elif k == 'env_steps':
            out[k] = v[:, -1]
        else:
            out[k] = v.mean(-1)
    return out


def recent_success(rows: list[dict], after_update: int) -> tuple[float, float]:
    """(success rate, episodes) over the episodes of the rows logged after `after_update`: each
    row's mean success weighted by its episode count (both means over seeds)."""
    after = [r for r in rows if r['update'] > after_update]
    if not after:
        return float('nan'), 0.0
    (w,) = window_means(after, len(after), ('success',))
    return w['success'], w['episodes']


def window_means(
    rows: list[dict],
    size: int,
    keys=('success', 'spl', 'episode_length', 'entropy', 'approx_kl', 'clip_frac'),
) -> list[dict]:
    """The run in windows of `size` logged rows (the last one may be shorter): per window its
    first and last update, last env step, episodes finished, and each key's mean: for the episode
    metrics (EPISODE_METRICS) each row's value weighted by the episodes it finished (NaN when the
    window finished none), for the rest (losses, entropy) plain over rows. Values are the rows'
    means over seeds."""
    out = []
    for i in range(0, len(rows), size):
        w = rows[i : i + size]
        ep = np.array([r.get('episodes') or 0.0 for r in w], np.float64)
        win = {
            'first_update': w[0]['update'],
            'last_update': w[-1]['update'],
            'env_steps': w[-1].get('env_steps'),
            'episodes': float(ep.sum()),
        }
        for k in keys:
            v = np.array([np.nan if r.get(k) is None else r[k] for r in w], np.float64)
            if k in EPISODE_METRICS:
                weight = np.where(np.isfinite(v), ep, 0.0)
                win[k] = float((np.nan_to_num(v) * weight).sum() / weight.sum()) if weight.sum() else math.nan
            else:
                win[k] = float(np.nanmean(v)) if np.isfinite(v).any() else math.nan
        out.append(win)
    return out


def _num(x):
    x = float(x)
    return None if not math.isfinite(x) else x


def _nan_stats(v: np.ndarray):
    v = np.asarray(v, np.float64)
    ok = np.isfinite(v)
    if not ok.any():
        return None, None
    return float(v[ok].mean()), float(v[ok].std())


class MetricsLog:
    """metrics.jsonl (source of truth), metrics.csv and TensorBoard, resumable at an update.
    write=False keeps the rows in memory only (the other processes of a multi-host job)."""

    def __init__(
        self, run_dir: Path, resume_update: int | None, tensorboard: bool = True, write: bool = True
    ):
        self.run_dir = Path(run_dir)
        self.write = write
        self.jsonl = self.run_dir / 'metrics.jsonl'
        self.csv = self.run_dir / 'metrics.csv'
        self.rows: list[dict] = []
        if resume_update is not None:
            # Rows written after the checkpoint we resume from are replayed: drop them.
            self.rows = [r for r in read_metrics(run_dir) if r['update'] <= resume_update]
        self.tb = None
        if not write:
            return
        with open(self.jsonl, 'w') as f:
            for row in self.rows:
                f.write(json.dumps(row) + '\n')
        self._rewrite_csv()
        if tensorboard:
            from tensorboardX import SummaryWriter

            purge = None
            if resume_update is not None:
                purge = (self.rows[-1]['env_steps'] + 1) if self.rows else 0
            self.tb = SummaryWriter(str(self.run_dir / 'tb'), purge_step=purge)

    @property
    def wall_time(self) -> float:
        return self.rows[-1]['wall_time'] if self.rows else 0.0

    def _columns(self) -> list[str]:
        keys = []
        for row in self.rows:
            for k in row:
                if k != 'per_seed' and k not in keys:
                    keys.append(k)
        return keys

    def _rewrite_csv(self) -> None:
        cols = self._columns()
        with open(self.csv, 'w', newline='') as f:
            w = csv.writer(f)
            w.writerow(cols)
            for row in self.rows:
                w.writerow(['' if row.get(k) is None else row.get(k) for k in cols])

    def append(
        self, update: int, summary: dict[str, np.ndarray], wall_time: float, steps_per_s: float
    ) -> dict:
        row = {
            'update': int(update),
            'env_steps': int(summary['env_steps'][0]),
            'wall_time': round(wall_time, 3),
            'steps_per_s': round(steps_per_s, 1),
            'seeds': int(len(summary['env_steps'])),
        }
        for k in sorted(summary):
            if k == 'env_steps':
                continue
            mean, std = _nan_stats(summary[k])
            row[k], row[k + '_std'] = mean, std
        row['per_seed'] = {k: [_num(x) for x in v] for k, v in sorted(summary.items()) if k != 'env_steps'}
        new_cols = any(k not in self._columns() for k in row if k != 'per_seed')
        self.rows.append(row)
        if not self.write:
            return row
        with open(self.jsonl, 'a') as f:
            f.write(json.dumps(row) + '\n')
        if new_cols:
            self._rewrite_csv()
        else:
            with open(self.csv, 'a', newline='') as f:
                csv.writer(f).writerow(['' if row.get(k) is None else row.get(k) for k in self._columns()])
        if self.tb is not None:
            step = row['env_steps']
            for k, v in summary.items():
                if k == 'env_steps':
                    continue
                if row[k] is not None:
                    self.tb.add_scalar(f'train/{k}', row[k], step)
                if len(v) > 1:
                    for i, x in enumerate(v):
                        if math.isfinite(x):
                            self.tb.add_scalar(f'seed{i}/{k}', float(x), step)
            self.tb.add_scalar('perf/steps_per_s', steps_per_s, step)
        return row

    def flush(self) -> None:
        if self.tb is not None:
            self.tb.flush()

    def close(self) -> None:
        if self.tb is not None:
            self.tb.close()
            self.tb = None


# Finished episodes a point of a learning curve rests on, per seed (see pooled_curve).
CURVE_MIN_EPISODES = 20


def pooled_curve(rows: list[dict], keys=('success', 'return'), min_episodes: int = CURVE_MIN_EPISODES):
    """Learning curve of each seed with every point resting on >= min_episodes finished episodes.

    A row's episode metrics are means over the episodes its chunk finished, and early chunks of a
    navigation run finish few (500-step episodes that all start together), so a row alone swings
    between 0 and 1. At each row, per seed, this is the episode-weighted mean of each key over the
    fewest trailing rows (that row included) holding >= min_episodes of that seed's episodes; NaN
    until the seed has finished that many. rows: metrics.jsonl rows (with 'per_seed'; rows without
    it count as one seed). Returns (env_steps f64[R], {key: f64[S, R]}).
    """
    steps = np.asarray([r['env_steps'] for r in rows], np.float64)
    if not rows:
        return steps, {k: np.zeros((1, 0)) for k in keys}

    def per_seed(r, k):
        v = (r.get('per_seed') or {}).get(k)
        v = [r.get(k)] if v is None else v
        return np.asarray([np.nan if x is None else x for x in v], np.float64)

    episodes = np.nan_to_num(np.stack([per_seed(r, 'episodes') for r in rows], 1))  # [S, R]
    out = {}
    for k in keys:
        vals = np.stack([per_seed(r, k) for r in rows], 1)  # [S, R]
        has = (episodes > 0) & np.isfinite(vals)
        ep = np.where(has, episodes, 0.0)
        # Sums over rows j..i are c[i + 1] - c[j] of the cumulative sums (leading 0).
        c_ep = np.concatenate([np.zeros((len(ep), 1)), np.cumsum(ep, 1)], 1)
        c_val = np.concatenate([np.zeros((len(ep), 1)), np.cumsum(np.where(has, vals, 0.0) * ep, 1)], 1)
        pooled = np.full(vals.shape, np.nan)
        for s, (ce, cv) in enumerate(zip(c_ep, c_val)):
            # The latest start j of each window j..i holding >= min_episodes (ce is nondecreasing);
            # -1 where even rows 0..i hold fewer.
            j = np.searchsorted(ce, ce[1:] - min_episodes, side='right') - 1
            ok = j >= 0
            pooled[s, ok] = (cv[1:][ok] - cv[j[ok]]) / (ce[1:][ok] - ce[j[ok]])
        out[k] = pooled
    return steps, out


def curve_rows(runs: list[list[dict]], keys=('success', 'return'), min_episodes: int = CURVE_MIN_EPISODES):
    """The learning curve over every seed of some runs (their metrics.jsonl rows): per env-step
    value, the mean and sample std (ddof=1; None for one seed) over the seeds' pooled_curve points
    there ({'env_steps', key, key + '_std'}; None where no seed has a point yet)."""
    at: dict[int, dict[str, list[float]]] = {}
    for rows in runs:
        steps, pooled = pooled_curve(rows, keys, min_episodes)
        for i, step in enumerate(steps):
            point = at.setdefault(int(step), {k: [] for k in keys})
            for k in keys:
                point[k] += [float(v) for v in pooled[k][:, i] if np.isfinite(v)]
    out = []
    for step in sorted(at):
        row = {'env_steps': step}
        for k, v in at[step].items():
            row[k] = float(np.mean(v)) if v else None
            row[k + '_std'] = float(np.std(v, ddof=1)) if len(v) > 1 else None
        out.append(row)
    return out


def plot_learning_curves(runs: dict[str, list[dict]], path, title: str = '') -> None:
    """SR and return vs env steps, mean +- std over seeds, one line per label: runs {label: rows
    of curve_rows}, so each point rests on >= CURVE_MIN_EPISODES finished episodes per seed."""
    import matplotlib

    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(9, 3.4))
    for label, rows in runs.items():
        x = np.asarray([r['env_steps'] for r in rows], np.float64)
        for ax, key in zip(axes, ('success', 'return')):
            mean = np.asarray([np.nan if r.get(key) is None else r[key] for r in rows])
            std = np.asarray([np.nan if r.get(key + '_std') is None else r[key + '_std'] for r in rows])
            ok = np.isfinite(mean)
            if not ok.any():
                continue
            (line,) = ax.plot(x[ok], mean[ok], lw=1.5, label=label)
            s = np.nan_to_num(std[ok])
            ax.fill_between(x[ok], mean[ok] - s, mean[ok] + s, color=line.get_color(), alpha=0.2, lw=0)
    axes[0].set_ylabel('success rate (SR)')
    axes[0].set_ylim(-0.02, 1.02)
    axes[1].set_ylabel('episode return')
    for ax in axes:
        ax.set_xlabel('environment steps')
        ax.grid(alpha=0.3)
        ax.ticklabel_format(axis='x', style='sci', scilimits=(0, 3))
    if axes[0].get_legend_handles_labels()[0]:
        axes[0].legend(fontsize=7, loc='lower right')
    if title:
        fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    tmp = Path(str(path) + '.tmp.png')
    fig.savefig(tmp, dpi=110)
    plt.close(fig)
    os.replace(tmp, path)
