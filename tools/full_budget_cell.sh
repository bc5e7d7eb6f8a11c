#!/usr/bin/env bash
# Train and evaluate one cell-seed of docs/reproduction_full_budget.md, as its runs were made.
#
#   cd CHECKOUT && bash /path/to/tools/full_budget_cell.sh TASK MODEL SEED [TRAIN_FLAGS...]
#
# Runs in the current directory's checkout (the full-budget tables freeze one commit for a whole
# table: run it from a worktree of that commit), into runs/full/<task>_<model>/s<seed>:
#   1. train.py to 32,768 env steps (or resume it), then copy the run as
#      runs/full/ckpt32k_<cell><seed>
#      (train.py keeps 3 checkpoints, so the early one must be copied to be evaluated at the end);
#   2. train.py --resume to 1,500,000 env steps (resumes from the last checkpoint after a stop);
#   3. six evaluations (eval.py, sampled actions, eval seed 0): eval_trained (20 episodes, the
#      paper's protocol), eval_200ep, eval_200ep_at_32768, eval_trained_house_{1,2,3} (20 each).
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
run=runs/full/$cell/s$seed
early=runs/full/ckpt32k_${cell}${seed}
mkdir -p runs/full

last_update() { ls "$1/checkpoints" 2>/dev/null | grep -E '^[0-9]+$' | sort -n | tail -1; }

if [[ ! -d $early ]]; then
  if [[ -z $(last_update "$run") ]]; then
    python train.py --task "$task" --model "$model" --seed "$seed" "$@" --total-steps 32768 \
      --out "$run" --no-progress
  elif (($(last_update "$run") < 8)); then
    python train.py --resume "$run" --total-steps 32768 --no-progress
  fi
  (($(last_update "$run") == 8)) || { echo "$run: no checkpoint 8 after 32,768 steps" >&2; exit 1; }
  cp -r "$run" "$early.tmp" && mv "$early.tmp" "$early"
fi
if (($(last_update "$run") < 366)); then
  python train.py --resume "$run" --total-steps 1500000 --no-progress
fi

evaluate() {  # RUN_TO_LOAD OUT_NAME EPISODES [EVAL_FLAGS...]; writes into $run/OUT_NAME
  local src=$1 out=$run/$2 episodes=$3
  shift 3
  [[ -f $out/eval.json ]] || python eval.py "$src" --episodes "$episodes" --out "$out" "$@"
}
evaluate "$run" eval_trained 20
evaluate "$run" eval_200ep 200
evaluate "$early" eval_200ep_at_32768 200
for h in 1 2 3; do
  evaluate "$run" eval_trained_house_$h 20 --scene scenes/house_$h.xml
done
echo "CELL_DONE $cell s$seed"
