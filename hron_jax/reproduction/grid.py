"""The experiment grid of Tables I-III and what a run of a cell runs; reads no run dir.

Cell (task x model x distractors x premap, with the paper's SR / SPL), GRID, TABLE_TITLES. The
profiles: PROFILES (train.py options per task), IN_PROCESS (those the in-process runner runs),
PROFILE_EPISODES, PROFILE_TEXT, and the paper's budget (PAPER_BUDGET, PAPER_STEPS).
profile_config(profile, cell) -> the TrainConfig its train.py command builds (train.py's own
parser); profile_steps -> its env steps per seed; train_argv -> that train.py command. What a run
ran, from its TrainConfig: settings -> {aspect: words} (comparable_settings: as the rows of a
table are compared), describe_config -> one line, paper_diff -> the fields where it is not the
paper preset. notes(table, paper_budget) -> the notes under a table; ordering_disagreements /
ordering_sentence compare the order of our rows with the paper's. Also EPISODES (eval episodes per
seed), HELD_OUT / TRAIN_HOUSE (the generalisation table's houses) and ATTENTION_CELLS.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

from hron_jax.labels import paper_label

# ------------------------------------------------------------------------------------------------
# The grid, with the paper's numbers (hron_paper.tex Tables I-III; SR / SPL mean +- std)
# ------------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class Cell:
    table: int
    task: str
    model: str
    distractors: bool = False
    premap: bool = False
    paper_sr: tuple | None = None
    paper_spl: tuple | None = None

    @property
    def name(self) -> str:
        return '_'.join(
            [self.task, self.model] + (['dist'] if self.distractors else []) + (['pm'] if self.premap else [])
        )

    @property
    def label(self) -> str:
        return paper_label(self.model, symbolic=self.task == 'choice', premap=self.premap)


GRID: tuple[Cell, ...] = (
    # Table I: relational object choice, success rate only.
    Cell(1, 'choice', 'rgbd_sg', False, paper_sr=(0.997, 0.003)),
    Cell(1, 'choice', 'rgbd_sg_attn', False, paper_sr=(0.991, 0.009)),
    Cell(1, 'choice', 'rgbd_sg', True, paper_sr=(0.659, 0.002)),
    Cell(1, 'choice', 'rgbd_sg_attn', True, paper_sr=(0.993, 0.007)),
    # Table II: directed object navigation.
    Cell(2, 'directed', 'rgbd', False, paper_sr=(0.450, 0.141), paper_spl=(0.197, 0.039)),
    Cell(2, 'directed', 'rgbd_sg', False, paper_sr=(0.967, 0.024), paper_spl=(0.949, 0.001)),
    Cell(2, 'directed', 'rgbd_sg_attn', False, paper_sr=(0.983, 0.024), paper_spl=(0.958, 0.019)),
    Cell(2, 'directed', 'rgbd', True, paper_sr=(0.417, 0.103), paper_spl=(0.173, 0.105)),
    Cell(2, 'directed', 'rgbd_sg', True, paper_sr=(0.425, 0.025), paper_spl=(0.252, 0.046)),
    Cell(2, 'directed', 'rgbd_sg_attn', True, paper_sr=(0.900, 0.041), paper_spl=(0.864, 0.039)),
    # Table III: exploratory object navigation (no distractors), with and without pre-mapping.
    Cell(3, 'exploratory', 'gcn', paper_sr=(0.423, 0.090), paper_spl=(0.221, 0.068)),
    Cell(3, 'exploratory', 'yang', paper_sr=(0.095, 0.009), paper_spl=(0.0302, 0.0013)),
    Cell(3, 'exploratory', 'rgbd', paper_sr=(0.586, 0.021), paper_spl=(0.309, 0.061)),
    Cell(3, 'exploratory', 'rgbd_mm', paper_sr=(0.554, 0.025), paper_spl=(0.273, 0.025)),
    Cell(3, 'exploratory', 'rgbd_sg', paper_sr=(0.458, 0.135), paper_spl=(0.183, 0.099)),
    Cell(3, 'exploratory', 'rgbd_sg_attn', paper_sr=(0.879, 0.048), paper_spl=(0.577, 0.041)),
    Cell(3, 'exploratory', 'rgbd_mm', premap=True, paper_sr=(0.405, 0.023), paper_spl=(0.404, 0.022)),
    Cell(3, 'exploratory', 'rgbd_sg', premap=True, paper_sr=(0.634, 0.108), paper_spl=(0.402, 0.037)),
    Cell(3, 'exploratory', 'rgbd_sg_attn', premap=True, paper_sr=(0.921, 0.005), paper_spl=(0.738, 0.045)),
)
TABLE_TITLES = {
    1: 'Table I: relational object choice (SR)',
    2: 'Table II: directed object navigation (SR, SPL)',
    3: 'Table III: exploratory object navigation (SR, SPL)',
}

# Profiles: extra train.py options per task (None: the task is not in the profile).
PROFILES = {
    'paper': {
        'choice': ['--preset', 'paper'],
        'directed': ['--preset', 'paper'],
        'exploratory': ['--preset', 'paper'],
    },
    'cpu': {
        'choice': ['--total-steps', '61440', '--model-option', 'hidden=32'],
        'directed': ['--total-steps', '131072'],
        'exploratory': ['--total-steps', '32768'],
    },
    # In-process profiles (IN_PROCESS): one run per cell with the seeds vmapped.
    'gpu': {
        task: ['--preset', 'paper', '--num-seeds', '3'] for task in ('choice', 'directed', 'exploratory')
    },
}
# 'tiny': the paper preset's code path (per-relation HGT softmax, KL penalty, batch advantage
# normalisation) at toy sizes, to run whole tables end to end on the CPU in a test: hidden 16,
# 1 head, 1 GNN layer, FC widths 16, 8x8 camera, 8-step episodes, 2 PPO updates of 4 envs x 4
# steps, 1 epoch, XLA without LLVM optimisation.
_TINY = [
    '--preset', 'paper', '--num-seeds', '2', '--fast-compile',
    '--num-envs', '4', '--num-steps', '4', '--epochs', '1', '--minibatches', '1',
    '--total-steps', '32', '--log-every', '1', '--checkpoint-every', '1000',
] + [
    x
    for opt in (
        'hidden=16', 'heads=1', 'gnn_layers=1', 'conv_features=8,8,8', 'cnn_fc=16,16,16',
        'goal_fc=16,16,16', 'fusion_fc=16,16,16', 'head_fc=16,16', 'map_class_features=4',
        'yang_image_code=8',
    )
    for x in ('--model-option', opt)
]  # fmt: skip
_TINY_NAV = [x for opt in ('image_size=8', 'max_steps=8', 'map.crop=16') for x in ('--env-option', opt)]
PROFILES['tiny'] = {'choice': _TINY, 'directed': _TINY + _TINY_NAV, 'exploratory': _TINY + _TINY_NAV}
# Profiles run by run_cells_in_process (train + eval in this process); the others by train.py /
# eval.py subprocesses, one per seed (run_cell_seed).
IN_PROCESS = ('gpu', 'tiny')
# Eval episodes per seed where a profile differs from EPISODES.
PROFILE_EPISODES = {'tiny': {'choice': 16, 'directed': 2, 'exploratory': 2}}
PROFILE_TEXT = {
    'paper': "`train.py --preset paper`: the paper release's model, camera and PPO settings at the "
    "paper's budget (navigation 1.5 M env steps per seed; choice: the task default, the paper "
    'states none)',
    'cpu': "NOT the paper's settings: the task defaults (preset default) at a fraction of the "
    "paper's budget, sized for a session on the 2-core CPU",
    'gpu': "`train.py --preset paper --num-seeds 3` in this process: one run per cell "
    '(RUNS/<cell>/s0x3), the 3 seeds vmapped, compiled programs reused where the program is the same; '
    'prints compile / train / eval seconds per cell (--total-steps: a shorter budget for a lease)',
    'tiny': "NOT the paper's settings: the paper preset's code path at toy sizes and 2 updates, "
    'in this process like gpu (an end-to-end smoke run of the tables on the CPU)',
}
# The paper's training budget where it states one ("approximately 1.5 million environment steps";
# the results of Tables II and III); the choice task's budget is not stated.
PAPER_BUDGET = {'directed': 1_500_000, 'exploratory': 1_500_000}
# Env steps per seed of the 'paper' profile (choice: the task default).
PAPER_STEPS = {'choice': 200_000, 'directed': 1_500_000, 'exploratory': 1_500_000}


def profile_config(profile: str, cell: Cell):
    """The TrainConfig that profile's train.py command builds for a cell (train.py's own parser)."""
    from hron_jax.cli import build_parser, config_from_args

    args = build_parser().parse_args(train_argv(cell, 0, Path('run'), profile)[2:])
    return config_from_args(vars(args))


def profile_steps(profile: str, task: str) -> int:
    return profile_config(profile, main_cell(task)).ppo.total_timesteps


# ------------------------------------------------------------------------------------------------
# What a run ran: its config in words, and how it compares with the paper's settings
# ------------------------------------------------------------------------------------------------

# Fields that say which cell a run belongs to, not how it was trained (left out when comparing
# a run's config with the paper preset).
_CELL_FIELDS = ('env.distractors', 'env.premap', 'env.task', 'env.metric_map', 'env.image_obs')
# How the physics is computed, not what the paper set: named on its own in `settings`.
_IMPL_FIELDS = ('env.sim.physics', 'env.sim.warp_contacts_per_env', 'env.sim.collider')


def _sci(x: float) -> str:
    """1e-4, 2.5e-4 (a learning rate as the paper and the issue write it)."""
    m, e = f'{x:.2e}'.split('e')
    return f'{m.rstrip("0").rstrip(".")}e{int(e)}'


def _pct(steps: int, of: int) -> str:
    pct = 100 * steps / of
    return f'{pct:.0f}' if pct >= 1 else f'{pct:.1g}'


def paper_diff(cfg) -> list[str]:
    """Dotted fields (env, network, ppo; the budget aside) where a run's config differs from the
    paper preset of its task and model; [] = the run ran the paper's settings."""
    from hron_jax.run_config import config_diff, make_config

    ref = make_config(cfg.task, cfg.model, {'preset': 'paper'})
    return [
        k
        for k in config_diff(ref, cfg)
        if k.split('.')[0] in ('env', 'network', 'ppo')
        and k not in _CELL_FIELDS + _IMPL_FIELDS
        and k != 'ppo.total_timesteps'
    ]


def settings(cfg) -> dict[str, str]:
    """A run's settings in words, one entry per aspect (the model variant aside)."""
    n, p = cfg.network, cfg.ppo
    diff = paper_diff(cfg)
    if not diff:
        preset = f"preset {cfg.preset} (= the paper's settings)"
    elif cfg.preset == 'paper':
        preset = f"preset paper, changed: {', '.join(diff)} (not the paper's settings)"
    else:
        preset = f"preset {cfg.preset} (not the paper's settings)"
    out = {'preset': preset}
    if cfg.task != 'choice':
        out['camera'] = f'camera {cfg.env.camera.width}x{cfg.env.camera.height}'
        out['physics'] = 'physics ' + ('MJX-Warp' if cfg.env.sim.physics == 'warp' else 'MJX (JAX)')
        if cfg.env.sim.collider == 'capsule':  # runs before 2026-12-02 (docs/benchmarks.md, Physics)
            out['physics'] += ', capsule collider'
    if n.use_graph:
        out['graph'] = (
            f'HGT hidden {n.hidden}, {n.heads} heads, {n.gnn_layers} layers, {n.hgt_softmax} softmax'
            if n.gnn == 'hgt'
            else f'GCN hidden {n.hidden}, {n.gnn_layers} layers'
        )
    out['ppo'] = (
        f'PPO {p.num_envs} envs x {p.num_steps} steps, {p.update_epochs} epochs, minibatch '
        f'{p.minibatch_size}, lr {_sci(p.lr)}' + (f', KL penalty {p.kl_coeff:g}' if p.kl_coeff else '')
    )
    budget = f'{p.total_timesteps:,} env steps / seed'
    if cfg.task in PAPER_BUDGET:
        budget += f" ({_pct(p.total_timesteps, PAPER_BUDGET[cfg.task])} % of the paper's 1.5 M)"
    else:
        budget += ' (the paper states no budget for this task)'
    out['budget'] = budget
    return out


def comparable_settings(cfg) -> dict[str, str]:
    """settings() as the rows of a table are compared: GCN or HGT is the model variant's choice, so
    'graph' is the graph network's size whatever its kind, and HGT's attention ('attention') is
    compared among the HGT rows alone."""
    out = settings(cfg)
    n = cfg.network
    if n.use_graph:
        out['graph'] = f'graph network hidden {n.hidden}, {n.gnn_layers} layers'
        if n.gnn == 'hgt':
            out['attention'] = f'HGT {n.heads} heads, {n.hgt_softmax} softmax'
    return out


def describe_config(cfg) -> str:
    """What a run ran, in one line: preset, camera, physics, HGT, PPO, budget."""
    return '; '.join(settings(cfg).values())


def main_cell(task: str) -> Cell:
    """The main model's cell of a task (no distractors, no pre-map)."""
    return next(c for c in GRID if c.task == task and c.model == 'rgbd_sg_attn')


def settings_text(cfg, graph: bool = True) -> str:
    """describe_config without the preset (for text that has already said which preset) and the
    physics (a profile leaves it to the machine: `auto`; each run's own text names it); graph=False
    also without the graph network (text about rows of several models)."""
    drop = ('preset', 'physics') + (() if graph else ('graph',))
    return '; '.join(v for k, v in settings(cfg).items() if k not in drop)


def notes(table: int, paper_budget: bool = False) -> list[str]:
    """Facts about the setup that reading a table needs. paper_budget: every row of the table that
    has runs ran the paper's env steps per seed, or the choice task's default where the paper
    states none (then the notes say so instead of describing the `cpu` profile's shorter budget,
    and Table I's say what training that long measured)."""
    cpu = {t: profile_config('cpu', main_cell(t)) for t in PAPER_STEPS}
    same_function = (
        'Notes. (1) Without distractors the choice scene has exactly 4 nodes, all of goal '
        'categories (2 circles, 2 rectangles), so task-driven pooling and mean pooling select the '
        'same nodes: SG and SG + TD ATTN compute the same function and, from the same seed, train '
        'identically (their rows and curves coincide).'
    )
    if table == 1 and paper_budget:
        return [
            f'{same_function} (2) Budget and settings: every row with runs ran the task default\'s '
            f"{PAPER_STEPS['choice']:,} env steps per seed (the paper states no budget for this task), "
            "with the settings of its Config column (the paper's settings are `train.py --preset "
            "paper`). A seed that has not left chance SR (0.5) by then counts as it is. (3) Trained "
            'this long, a seed that has solved the task can lose it again (the curves\' dips): '
            'deterministic and wrong in one of the four goal x layout cases (SR 0.75) or back at '
            'chance. Measured on 8 vmapped SG seeds without distractors (2026-12-07): with the '
            "task defaults' advantages standardised per minibatch, 6 fell below training SR 0.9 "
            'after first reaching 1.0 and 2 ended below 0.9; standardised per batch (RLlib\'s, the '
            'paper preset\'s) 5 and 3; not standardised (`--ppo-option advantage_norm=none`) none. '
            'Unstandardised advantages learn later, though: 3 vmapped seeds of SG with distractors '
            'left chance in 1 of 3 by 200,000 env steps (at ~151,000), against 2 of 3 in this '
            "table's row (docs/reproduction_full_budget/README.md)."
        ]
    if table == 1:
        c = cpu['choice']
        return [
            f"{same_function} (2) Profile `cpu`, not the paper's "
            f'settings: {settings_text(c)}; the HGT width 32 instead of the release\'s 128 lets '
            'the 12 runs fit ~25 min on 2 shared cores (2026-12-03); at width 128 a 10-update trial of '
            'the distractor setting measured ~42 env steps/s (vs ~280 at width 32, load ~5). A seed '
            'that has not left chance SR (0.5) by the end of this budget counts as it is; the '
            'learning curves show when the others jumped (2026-12-03: between ~15,000 and ~35,000 '
            'env steps, so 20,480, the budget before, left most seeds at chance). (3) The task '
            "defaults' lr is the paper's 1e-4 since 2026-12-03. At 3e-4 the policy turned "
            'deterministic within ~10,000-30,000 env steps, and 3 of 6 seeds of SG + TD ATTN with '
            'distractors froze at SR 0.75 (deterministic and wrong in one of the four goal x layout '
            'cases; Table I at 3e-4: SG 0.670 ± 0.287, SG + TD ATTN 0.820 ± 0.157, n=3). At 1e-4 all '
            '9 seeds tried reached 1.0; SG with distractors left chance in 1 of 3 seeds at 3e-4 '
            '(after ~56,000 env steps) and in none at 1e-4 within this budget; trained to the task '
            "default's 200,000 env steps at 1e-4, three vmapped SG seeds left it at ~148,000-189,000, "
            'so without attention the task is learned later, not never (hron_jax/run_config.py).'
        ]
    if paper_budget and table > 1:
        return [
            "Notes. (1) Budget and settings: every row with runs ran the paper's "
            f"{PAPER_STEPS['directed' if table == 2 else 'exploratory']:,} env steps "
            "per seed, with the settings of its Config column (the paper's settings are `train.py "
            "--preset paper`)."
        ]
    if table == 2:
        c = cpu['directed']
        return [
            "Notes. (1) Budget and settings: the Config column; rows of profile `cpu` (not the paper's "
            f"settings) ran {settings_text(c, graph=False)}, the graph models with {settings(c)['graph']}; "
            f'that is {c.ppo.num_updates} PPO '
            f'updates: with episodes of up to 500 steps each env finishes only a few episodes '
            'during training, so these rows show early learning, not converged policies, and not '
            "under the paper's settings; those and the paper's budget are the `paper` profile "
            '(`train.py --preset paper`; commands and measured cost below, when not run). '
            '(2) The PPO update of the graph models dominates the time on the CPU '
            '(docs/benchmarks.md, `python -m hron_jax.bench train`); graph-free RGB-D only trains ~3x '
            'faster.'
        ]
    if table == 3:
        c = cpu['exploratory']
        return [
            "Notes. (1) Budget and settings: the Config column; rows of profile `cpu` (not the paper's "
            f"settings) ran {settings_text(c, graph=False)}, the HGT models with {settings(c)['graph']}. "
            '(2) Estimates for cells without runs use, in order, the '
            "cell's own runs, its --probe, or (flagged as a proxy) the main model of the same task: "
            'graph-free models (RGB-D only, RGB-D + MM) skip the HGT and will be faster.'
        ]
    return []


# ------------------------------------------------------------------------------------------------
# Comparing the order of the models with the paper's
# ------------------------------------------------------------------------------------------------


def _order(a: float, b: float) -> str:
    return '>' if a > b else ('<' if a < b else '=')


def ordering_disagreements(ours: dict[str, float], paper: dict[str, float], digits: int = 3) -> list:
    """Every pair of rows (labels in both dicts, in `ours`' order) whose order (>, <, =) differs
    between our means and the paper's, as printed (rounded to `digits`): [(a, b, ours_a, ours_b,
    paper_a, paper_b)]. [] = every pair is ordered as in the paper."""
    labels = [k for k in ours if k in paper]
    out = []
    for i, a in enumerate(labels):
        for b in labels[i + 1 :]:
            oa, ob = round(ours[a], digits), round(ours[b], digits)
            pa, pb = round(paper[a], digits), round(paper[b], digits)
            if _order(oa, ob) != _order(pa, pb):
                out.append((a, b, oa, ob, pa, pb))
    return out


def ordering_sentence(what: str, ours: dict[str, float], paper: dict[str, float]) -> str | None:
    """One sentence on how `what` (e.g. 'SR, with distractors') orders the rows against the paper;
    None when fewer than 2 rows ran."""
    n = len([k for k in ours if k in paper])
    pairs = n * (n - 1) // 2
    if not pairs:
        return None
    bad = ordering_disagreements(ours, paper)
    if not bad:
        if pairs == 1:
            return f'{what}: the one pair of rows is ordered as in the paper.'
        return f'{what}: all {pairs} pairs of rows are ordered as in the paper.'
    if pairs == 1:
        head = 'the one pair of rows is'
    else:
        head = f'{len(bad)} of {pairs} pairs of rows {"is" if len(bad) == 1 else "are"}'
    return (
        f'{what}: {head} NOT ordered as in the paper: '
        + '; '.join(
            f'{a} {oa:.3f} {_order(oa, ob)} {b} {ob:.3f} here, '
            f'{pa:.3f} {_order(pa, pb)} {pb:.3f} in the paper'
            for a, b, oa, ob, pa, pb in bad
        )
        + '.'
    )


# ------------------------------------------------------------------------------------------------
# A cell's runs: the train.py command of a seed, eval episodes, houses, attention cells
# ------------------------------------------------------------------------------------------------


def train_argv(
    cell: Cell, seed: int, out: Path, profile: str, extra=(), total_steps: int | None = None
) -> list[str]:
    """The profile's train.py command for one seed of a cell; total_steps: a budget other than the
    profile's (replaces its --total-steps)."""
    opts = PROFILES[profile][cell.task]
    if opts is None:
        raise SystemExit(f'profile {profile!r} does not cover the {cell.task} task; use --profile paper')
    if total_steps is not None:
        i = opts.index('--total-steps') if '--total-steps' in opts else len(opts)
        opts = opts[:i] + ['--total-steps', str(total_steps)] + opts[i + 2 :]
    argv = ['python', 'train.py', '--task', cell.task, '--model', cell.model, '--seed', str(seed)]
    argv += ['--distractors'] if cell.distractors else []
    argv += ['--premap'] if cell.premap else []
    return argv + list(opts) + list(extra) + ['--no-progress', '--out', str(out)]


# Eval episodes per seed: the paper's 20 for navigation; the one-step choice task is cheap, so 200
# there (SR resolution 0.005 instead of 0.05).
EPISODES = {'choice': 200, 'directed': 20, 'exploratory': 20}

# Held-out houses (hron_jax.scenes generator, seeds 1-3) for the exploratory main model.
HELD_OUT = ('scenes/house_1.xml', 'scenes/house_2.xml', 'scenes/house_3.xml')
GENERALISATION_MODELS = ('rgbd_sg_attn',)


# Trained main models whose attention the report draws (seed 0), with --attention.
ATTENTION_CELLS = ('directed_rgbd_sg_attn_dist', 'exploratory_rgbd_sg_attn')


TRAIN_HOUSE = 'scenes/house.xml'
