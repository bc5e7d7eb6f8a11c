"""Reproduce the paper's Tables I-III: train + evaluate the experiment grid, write docs/reproduction.md.

The command line is tools/reproduce.py (`--plan`, `--tables`, `--from-runs`, `--probe`,
`--attention`, the in-process options); what it does lives here, one job a module:

    grid     the cells with the paper's numbers, the profiles, what a run of a cell runs (train.py
             command, TrainConfig, its settings in words), the notes under the tables, and the
             comparison of the models' order with the paper's
    runs     the run-dir layout (RUNS/<cell>/<run>, its evaluations, the reference and probe runs),
             the archive beside the report, and reading run dirs into a cell's numbers
    report   docs/reproduction.md from run dirs only, and the cost estimate of cells without runs
    runner   running cells: train.py / eval.py subprocesses per seed, probes, held-out houses,
             attention figures, and the in-process runner (train + eval of all cells in one process)

Imports go one way: grid <- runs <- report and runner (neither imports the other). Importing any
of them imports no JAX (`tools/reproduce.py --plan` runs on machines without it): what needs JAX
(the training code, train.py's parser, run configs, evaluation) is imported inside the functions.

Grid (the paper's "Baselines and ablation studies" and Tables I-III; grid.GRID): a cell is task x
model x distractors x premap; every cell is trained for `--seeds` seeds (paper: 3) and each seed's
final checkpoint is evaluated on `--episodes` episodes (paper: 20; the same episode starts / goals
for every seed and model, eval.py's protocol).

Runs (runs.py): RUNS/<cell>/s<seed> is a plain train.py run dir (config.json, checkpoints,
metrics.jsonl) with eval.py's output in eval_trained/ and the runner's sidecar repro.json
(commands, process wall times, machine). Seeds are separate train.py processes rather than one
--num-seeds run: on the 2-core CPU a vmapped 3-seed program was slower per seed than three
single-seed programs (the persistent XLA cache makes seeds 1 and 2 skip compilation), and a
single-seed run is by construction identical to seed i of a multi-seed one (hron_jax.training).
--from-runs reads any run dir layout it finds under RUNS/<cell>/ (a multi-seed run counts with all
its seeds).

Archive (runs.py): the report at OUT keeps its runs' small files (config, metrics, evaluations;
ARCHIVED) in git in the folder named as OUT, <OUT without .md>/runs, beside its figures (so
docs/reproduction.md: docs/reproduction/runs). Every call (but --plan / --probe) first restores
the archived runs RUNS lacks, which count as done, and the report's writer saves every run of RUNS
back: a fresh checkout (runs/ is not in git) regenerates the report and adds seeds to it without
retraining what is archived. Each report has its own folder and, unless --runs says otherwise,
its own RUNS (runs/repro for docs/reproduction.md, else runs/<OUT's name>): a report of other runs
(e.g. docs/reproduction_full_budget.md, runs at the paper's 1.5 M env steps) mixes with no other.

In-process profiles ('gpu', 'tiny'; runner.run_cells_in_process): one process trains every cell as
ONE run RUNS/<cell>/s0x<seeds> with the seeds vmapped (`train.py --num-seeds N`; hron_jax.training
caches compiled programs in-process per program-relevant config) and evaluates it with eval.py's
code in the same process, printing compile / train / eval seconds per cell as it finishes;
resumable (finished cells skipped, interrupted ones continue from their checkpoint), stoppable by
--budget-s / --max-updates / SIGTERM. 'gpu' = `--preset paper --num-seeds 3` (--total-steps for a
shorter budget; tools/gpu_tables.sh is the script of a lease); 'tiny' = the same code path at toy
sizes, so the tables run end to end in a test on the CPU (tests/test_reproduce.py).

Profiles (grid.PROFILES): 'paper' = `train.py --preset paper` (hron_jax.run_config.PRESETS: the
paper release's camera 128x128, per-relation HGT softmax and RLlib PPO, 8 envs x 512 steps, 30
epochs, minibatch 128, lr 1e-4, KL penalty; HGT hidden 128, 2 heads, 3 layers) at the paper's
budget (navigation 1.5 M env steps per seed; choice: the task default 200 k, the paper states
none); 'cpu' = what fits a session on the 2-core development machine and is NOT the paper's
settings: the task defaults (camera 32x32, joint HGT softmax, 64 envs, 4 epochs, lr 2.5e-4 / 1e-4)
at a fraction of the budget (choice: HGT hidden 32, 61 440 env steps per seed; directed 131 072 =
32 PPO updates, exploratory 32 768 = 8 updates, i.e. 9 % and 2 % of the paper's 1.5 M). The report
reads every run's config.json (TrainConfig.from_dict, older flat files included) and states in
each row exactly what ran: preset, camera, HGT softmax and sizes, PPO, budget. A run dir that
exists with fewer env steps than its profile asks for is resumed to that budget (`train.py
--resume RUN --total-steps N`) and evaluated again; one trained with other settings than the
profile's is not (an error says which).

Generalisation (beyond the paper): each seed of an exploratory main-model cell is also evaluated
on the generated houses it never saw (grid.HELD_OUT, `eval.py RUN --scene HOUSE`); the report lists
any other exploratory cell whose runs have such evaluations too. Numbers are only ever read from
run dirs: a cell without runs is listed as not run, with its commands and a cost estimate from
measured env steps/s (its own runs, else a --probe run; report.estimate).

Report statistics (report.py): SR / SPL = mean over all episodes of all seeds +- the sample std
(ddof=1) over seeds of the per-seed means, with n (seeds) beside it; one seed has no spread (our
reading of the paper's "averaged over 20 episodes across three random seeds"; the paper's +- are
copied as printed). A sentence on the ordering of the models compares every pair of rows of a
setting with the paper (grid.ordering_disagreements) and names the pairs ordered differently.
"""
