#!/usr/bin/env bash
# The one prepared script for a GPU lease (../shared/gpu/README.md): trains and evaluates cells of the
# paper's tables in ONE process (tools/reproduce.py --profile gpu: `train.py --preset paper --num-seeds 3`,
# seeds vmapped, compiled programs reused, one row per cell with compile / train / eval seconds), time-boxed,
# and leaves in $OUT what comes back (at most 8 files, none in sub-folders):
#   log               everything printed (the per-cell rows as they are measured)
#   env.txt           devices, versions, nvidia-smi
#   reproduction.md   the report (tools/reproduce.py --from-runs) of the runs made here
#   runs.tgz          the runs' small files (config.json, metrics.jsonl, eval.json, eval.md, repro.json,
#                     logs; no checkpoints): here `mkdir -p runs/repro_gpu && tar xzf runs.tgz -C
#                     runs/repro_gpu`, then `tools/reproduce.py --from-runs --runs runs/repro_gpu
#                     --out docs/reproduction_gpu.md` (a report, and its runs' archive, of their own:
#                     docs/reproduction.md's archived runs would be restored into runs/repro_gpu and
#                     mixed with them in the same cells)
#
#   bash tools/gpu_tables.sh [TABLES] [SECONDS] [TOTAL_STEPS] [CELLS]
#     TABLES       tables to run, e.g. "2" or "2 3" (default 2)
#     SECONDS      time box of the whole script (default 540: a 600 s device call with margin)
#     TOTAL_STEPS  env steps per seed (default 8192 = 2 PPO updates of the paper's 8 x 512 rollout: a
#                  cost measurement, not the paper's 1.5 M; "paper" = the profile's own budget)
#     CELLS        regex on cell names (default: all cells of TABLES), e.g. 'directed_rgbd_sg_attn$'
#   env: PROFILE (default gpu; tiny checks the non-GPU steps on a CPU), RUNS (default runs/repro_gpu),
#        OUT (set by the device tool; default /tmp/gpu_tables_out)
#
# Device call (after ../shared/gpu/fetch-wheels.sh here; carry [".whl"]; never set MUJOCO_GL=egl there):
#   run(command="bash tools/gpu_tables.sh 2 540 8192", carry=[".whl"], timeout_s=600)
# A second call on the still-warm machine resumes: finished cells are skipped, interrupted ones continue.
set -uo pipefail
cd "$(dirname "$0")/.."

TABLES=${1:-2}
SECONDS_BOX=${2:-540}
STEPS=${3:-8192}
CELLS=${4:-}
PROFILE=${PROFILE:-gpu}
RUNS=${RUNS:-runs/repro_gpu}
OUT=${OUT:-/tmp/gpu_tables_out}
REPORT_DIR=$RUNS/_report
mkdir -p "$OUT" "$RUNS"
# shellcheck source=tools/gpu_lib.sh
source tools/gpu_lib.sh

main() {
  # 1-2. The wheels the GPU machine lacks; what this machine is (env.txt).
  setup || return 1
  # 3. The cells, in one process: the runner stops training (checkpointed) and leaves the remaining cells
  #    at --budget-s; the time box behind it (SIGTERM: the current chunk finishes and checkpoints, then
  #    the report) leaves room for the evaluation of the last cell and for steps 4-5.
  local box=$(($(left) - 60))
  local budget=$((box - 150))
  ((budget < 30)) && budget=30
  local steps=()
  [[ $STEPS != paper ]] && steps=(--total-steps "$STEPS")
  local cells=()
  [[ -n $CELLS ]] && cells=(--cells "$CELLS")
  # shellcheck disable=SC2086  # TABLES is a list of table numbers
  step "$box" python3 tools/reproduce.py --profile "$PROFILE" --tables $TABLES "${cells[@]}" "${steps[@]}" \
    --budget-s "$budget" --runs "$RUNS" --out "$REPORT_DIR/reproduction.md"
  # 4. The report from whatever runs exist (also after a killed step 3).
  step $(($(left) - 20)) python3 tools/reproduce.py --from-runs --runs "$RUNS" \
    --out "$REPORT_DIR/reproduction.md"
  cp "$REPORT_DIR/reproduction.md" "$OUT/" 2>/dev/null
  # 5. The runs' small files, in one archive (the device returns at most 8 files).
  (cd "$RUNS" && find . -path ./_report -prune -o -type f \( -name config.json -o -name metrics.jsonl \
    -o -name eval.json -o -name eval.md -o -name repro.json -o -name '*.log' \) -print \
    | tar czf "$OUT/runs.tgz" -T -)
  ls -la "$OUT"
}

main 2>&1 | tee "$OUT/log"
