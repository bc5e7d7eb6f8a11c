#!/usr/bin/env bash
# Train and evaluate one cell-seed of docs/reproduction_full_budget.md, as its runs were made.
#
#   cd CHECKOUT && bash /path/to/tools/full_budget_cell.sh TASK MODEL SEED [TRAIN_FLAGS...]
#
# Runs in the current directory's checkout (the full-budget tables freeze one commit for a whole
# table: run it from a worktree of that commit), into runs/full/<task>_<model>/s<seed>, with the
# settings of the task's `cpu` profile (hron_jax.reproduction.grid.PROFILES) but its budget:
#   1. train.py to the profile's budget (exploratory 32,768 env steps, directed 131,072, choice
#      61,440) or resume it, then copy the run as runs/full/ckpt<early>_<cell><seed>
#      (train.py keeps 3 checkpoints, so the early one must be copied to be evaluated at the end);
#   2. train.py --resume to the paper's budget (navigation 1,500,000 env steps; choice 200,000, the
#      task default: the paper states none); resumes from the last checkpoint after a stop;
#   3. evaluations (eval.py, sampled actions, eval seed 0): navigation eval_trained (20 episodes,
#      the paper's protocol), eval_200ep, eval_200ep_at_<early>, eval_trained_house_{1,2,3} (20
#      each); choice eval_trained and eval_200ep_at_61440 (200 episodes each, the choice protocol).
# Every step is skipped when its output exists, so rerunning after an interruption continues.
# Prints CELL_DONE <cell> s<seed> at the end. TRAIN_FLAGS go to the first train.py (--distractors;
# --premap: the pre-mapped cells).
set -euo pipefail
task=$1 model=$2 seed=$3
shift 3
cell=${task}_${model}
# The grid's cell names (hron_jax.reproduction.grid):
[[ " $* " == *" --distractors "* ]] && cell=${cell}_dist
[[ " $* " == *" --premap "* ]] && cell=${cell}_pm
# The `cpu` profile's train.py options (its budget; choice also its HGT width), and the env steps
# and update numbers of the early copy and of the end, from the grid (one home for them).
mapfile -t profile < <(python -c "from hron_jax.reproduction.grid import PROFILES
print('\n'.join(PROFILES['cpu']['$task']))")
read -r early_steps early_update total_steps last < <(python -c "
from hron_jax.reproduction.grid import PAPER_STEPS, main_cell, profile_config
p = profile_config('cpu', main_cell('$task')).ppo
print(p.total_timesteps, p.num_updates, PAPER_STEPS['$task'], PAPER_STEPS['$task'] // p.batch_size)")
run=runs/full/$cell/s$seed
early=runs/full/ckpt$((early_steps / 1024))k_${cell}${seed}
mkdir -p runs/full

last_update() { ls "$1/checkpoints" 2>/dev/null | grep -E '^[0-9]+$' | sort -n | tail -1; }

if [[ ! -d $early ]]; then
  if [[ -z $(last_update "$run") ]]; then
    python train.py --task "$task" --model "$model" --seed "$seed" "$@" "${profile[@]}" --out "$run" \
      --no-progress
  elif (($(last_update "$run") < early_update)); then
    python train.py --resume "$run" --total-steps $early_steps --no-progress
  fi
  (($(last_update "$run") == early_update)) ||
    { echo "$run: no checkpoint $early_update after $early_steps env steps" >&2; exit 1; }
  cp -r "$run" "$early.tmp" && mv "$early.tmp" "$early"
fi
if (($(last_update "$run") < last)); then
  python train.py --resume "$run" --total-steps $total_steps --no-progress
fi

evaluate() {  # RUN_TO_LOAD OUT_NAME EPISODES [EVAL_FLAGS...]; writes into $run/OUT_NAME
  local src=$1 out=$run/$2 episodes=$3
  shift 3
  [[ -f $out/eval.json ]] || python eval.py "$src" --episodes "$episodes" --out "$out" "$@"
}
if [[ $task == choice ]]; then
  evaluate "$run" eval_trained 200
  evaluate "$early" eval_200ep_at_$early_steps 200
else
  evaluate "$run" eval_trained 20
  evaluate "$run" eval_200ep 200
  evaluate "$early" eval_200ep_at_$early_steps 200
  for h in 1 2 3; do
    evaluate "$run" eval_trained_house_$h 20 --scene scenes/house_$h.xml
  done
fi
echo "CELL_DONE $cell s$seed"
