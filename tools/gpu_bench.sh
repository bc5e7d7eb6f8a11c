#!/usr/bin/env bash
# The prepared script of a GPU lease for issue 12's measurements (../shared/gpu/README.md): the
# main model on the exploratory task at GPU batch sizes, each stage time-boxed, rows printed as
# measured. Leaves in $OUT: log (everything printed) and env.txt (devices, versions, nvidia-smi).
#
#   bash tools/gpu_bench.sh [SECONDS] [STAGE...]
#     SECONDS  time box of the whole script (default 540)
#     STAGE    any of (default: all, in this order; all of them take ~20 min, more than one 15-min
#              lease: pick, e.g. `profilebf trainpy env`)
#       env       bench env: physics, 128x128 render, env step at 1024 / 4096 / 8192 envs, with
#                 the row-band culled kernel (default), the same with its candidates picked
#                 without a sort (camera.select=rank: XLA:GPU sorts every top_k here) and one
#                 band per column (the kernel before the bands)
#       env-warp  bench env: physics and env step with MJX's JAX implementation and MJX-Warp at
#                 1024 / 4096 / 8192 envs, 128x128 (needs warp-lang there, staged by
#                 tools/gpu_stage_warp.sh; without it the stage fails with a message saying so)
#       train32w  train32 with Warp physics (the other stages pin MJX's JAX physics; the last
#                 --env-option wins)
#       env-nocull bench env at 1024 envs without culling (every ray tests every geom: if XLA
#                 fuses the test into the min, no candidate tables at all; 21 GB if it does not)
#       profile   bench profile: device ms per source module of one PPO update, 4096 envs x 16
#                 steps, 32x32 camera, 8 minibatches of 8192 (and its compile time), with the
#                 estimated GB moved and implied GB/s per source and op (hlo.kernel_traffic), and
#                 per line of models/gnn.py (what docs/benchmarks.md's "GB moved" estimates: the
#                 k / v table 35 %, attention 32 %, linears 31 % of the HGT layers' bytes)
#       profilex  profile with XLA's (cuDNN) convolutions (conv=xla), against profile, whose 32x32
#                 camera takes patch convolutions since 2026-12-04 (conv=auto): on the H200
#                 (2026-12-04) the first cuDNN convolution's gradient took 310 ms of a 3.3 s update
#       model     bench model: the main model's forward and fwd+grad at batch 8192 (the HGT
#                 layers on the scene's static type layout, as training runs them)
#       train32   bench train: that update as train.py runs it (CUDA graphs on): env steps/s
#       train128  bench train: the same with the 128x128 camera and 32 minibatches of 2048 (8192
#                 need 79 GB at 128x128); convolutions as on a GPU by default (ModelConfig.conv auto:
#                 XLA's / cuDNN)
#       train128p the same with the CPU's patch convolutions (conv=patches), to weigh the two
#       train32bf train32 with the GNN in bfloat16 (gnn_dtype=bfloat16: bf16 k / q / v tables)
#       profilebf profile with gnn_dtype=bfloat16: where the update's time goes then (H100,
#                 2026-12-05: 3,403 ms against float32's 3,347, its gathers' bfloat16 gradient
#                 scatter-adds 1.2 s; they sum in float32 since, lookup.gather_f32: measure that)
#       compile   bench compile at 1024 envs: compile seconds and HLO size per stage on this GPU
#       trainpy   train.py as a user runs it (1024 envs x 16 steps, 8 minibatches, 2 updates,
#                 no compile cache): init / chunk compile seconds from its log, env steps/s in
#                 $OUT/trainpy_metrics.csv
#       evalpy    eval.py on trainpy's run as a user runs it (20 episodes, no compile cache): its
#                 logged compile and play seconds (run after trainpy, which leaves the run)
#       determinism  trainpy twice (the second from the compile cache) and whether both logged the
#                 same numbers (XLA:GPU's float scatter-adds are atomics, in no fixed order)
#       determinism-ops  the same with --xla_gpu_deterministic_ops=true: whether that fixes it, its
#                 env steps/s in the runs' logs and its compile (for an H100 without one, 2026-12-04:
#                 every scatter gets a sort, 9 -> 62 sorts, chunk compile 48.7 -> 114.5 s)
#       trainpy-na  trainpy with XLA:GPU autotuning off (--xla_gpu_autotune_level=0): its share of
#                 the compile (may fail: untuned Triton GEMM tiling failed on the HGT layers' dots
#                 in a compile for an H100 without one, jax 0.10.2; see bench compile)
#       trainpy-nt  trainpy with GEMMs on cuBLAS (--xla_gpu_enable_triton_gemm=false: nothing for
#                 the autotuner to search among Triton tilings): compile seconds and env steps/s
#
# Device call (after ../shared/gpu/fetch-wheels.sh here; never set MUJOCO_GL=egl there):
#   run(command="bash tools/gpu_bench.sh 540", carry=[".whl"], timeout_s=600)
set -uo pipefail
cd "$(dirname "$0")/.."

SECONDS_BOX=${1:-540}
shift $(($# > 0 ? 1 : 0))
STAGES=("$@")
((${#STAGES[@]})) || STAGES=(env env-nocull profile profilex model train32 train32bf profilebf train128 train128p compile trainpy evalpy determinism determinism-ops trainpy-na trainpy-nt env-warp train32w)
OUT=${OUT:-/tmp/gpu_bench_out}
mkdir -p "$OUT"
# shellcheck source=tools/gpu_lib.sh
source tools/gpu_lib.sh

# box SECONDS: SECONDS, or what is left of the script's box less a margin, whichever is smaller.
box() {
  local l=$(($(left) - 15))
  echo $(($1 < l ? $1 : l))
}

# same_metrics A B: whether two runs logged the same numbers (their metrics log less its timings).
same_metrics() {
  python3 - "$1" "$2" <<'PY'
import sys
from hron_jax.run_dir import read_metrics
a, b = ([{k: v for k, v in r.items() if k not in ("wall_time", "steps_per_s")} for r in read_metrics(d)]
        for d in sys.argv[1:])
diff = sorted({k for ra, rb in zip(a, b) for k in ra if ra[k] != rb[k]})
print(f"== same metrics: {bool(a) and len(a) == len(b) and not diff} ({len(a)} / {len(b)} rows; differ: {diff or 'none'})")
PY
}

main() {
  setup || return 1
  # MJX's JAX physics unless a stage says warp: a like-for-like A/B when warp-lang is staged ('auto'
  # would pick warp then); trainpy runs as a user would (auto).
  local batch=(--num-envs 4096 --num-steps 16 --env-option sim.physics=jax)
  local user_run=(--task exploratory --num-envs 1024 --num-steps 16 --minibatches 8 --total-steps 32768
    --log-every 1 --compile-cache none --no-progress)
  for s in "${STAGES[@]}"; do
    case $s in
      env) step "$(box 200)" python3 -m hron_jax.bench env --num-envs 1024 4096 8192 --width 128 \
        --height 128 --backends kernel kernel-rank kernel-columns --collider sphere capsule --native-envs 4 \
        --steps 10 --repeats 2 ;;
      env-warp) step "$(box 200)" python3 -m hron_jax.bench env --num-envs 1024 4096 8192 --width 128 \
        --height 128 --backends kernel --physics jax warp --native-envs 4 --steps 10 --repeats 2 ;;
      train32w) step "$(box 180)" python3 -m hron_jax.bench train "${batch[@]}" --minibatch-size 8192 \
        --image-size 32 --repeats 2 --env-option sim.physics=warp ;;
      env-nocull) step "$(box 60)" python3 -m hron_jax.bench env --num-envs 1024 --width 128 --height 128 \
        --backends kernel-nocull --native-envs 1 --steps 10 --repeats 2 ;;
      profile) step "$(box 200)" python3 -m hron_jax.bench profile "${batch[@]}" --minibatch-size 8192 \
        --image-size 32 --repeats 2 --top 40 --lines models/gnn.py ;;
      profilex) step "$(box 200)" python3 -m hron_jax.bench profile "${batch[@]}" --minibatch-size 8192 \
        --image-size 32 --repeats 2 --top 40 --model-option conv=xla ;;
      model) step "$(box 120)" python3 -m hron_jax.bench model --variants rgbd_sg_attn --batch 8192 \
        --reps 10 ;;
      train32) step "$(box 240)" python3 -m hron_jax.bench train "${batch[@]}" --minibatch-size 8192 \
        --image-size 32 --repeats 2 ;;
      train32bf) step "$(box 180)" python3 -m hron_jax.bench train "${batch[@]}" --minibatch-size 8192 \
        --image-size 32 --repeats 2 --model-option gnn_dtype=bfloat16 ;;
      profilebf) step "$(box 200)" python3 -m hron_jax.bench profile "${batch[@]}" --minibatch-size 8192 \
        --image-size 32 --repeats 2 --model-option gnn_dtype=bfloat16 --lines models/gnn.py ;;
      train128) step "$(box 180)" python3 -m hron_jax.bench train "${batch[@]}" --minibatch-size 2048 \
        --image-size 128 --repeats 2 ;;
      train128p) step "$(box 180)" python3 -m hron_jax.bench train "${batch[@]}" --minibatch-size 2048 \
        --image-size 128 --repeats 2 --model-option conv=patches ;;
      compile) step "$(box 200)" python3 -m hron_jax.bench compile --num-envs 1024 --num-steps 16 \
        --minibatches 8 --env-option sim.physics=jax ;;
      trainpy) step "$(box 220)" python3 train.py "${user_run[@]}" --out /tmp/gpu_bench_run
        cp /tmp/gpu_bench_run/metrics.csv "$OUT/trainpy_metrics.csv" 2>/dev/null ;;
      evalpy) step "$(box 150)" python3 eval.py /tmp/gpu_bench_run --episodes 20 --plots 0 \
        --compile-cache none ;;
      determinism|determinism-ops)
        # The first run compiles (cold: ~90 s on the H200; with deterministic ops XLA sorts every
        # scatter's indices, which more than doubled the compile for an H100 without one), the
        # second loads the first's programs from the cache.
        local flags="" first=150
        [[ $s == determinism-ops ]] && flags="--xla_gpu_deterministic_ops=true" first=280
        for i in 1 2; do
          step "$(box $((i == 1 ? first : 120)))" env XLA_FLAGS="${XLA_FLAGS:-} $flags" python3 train.py \
            "${user_run[@]}" --compile-cache "/tmp/gpu_${s}_cache" --out "/tmp/gpu_${s}_$i"
        done
        echo "== XLA flags '$flags'"
        same_metrics "/tmp/gpu_${s}_1" "/tmp/gpu_${s}_2" ;;
      trainpy-na) step "$(box 220)" env XLA_FLAGS="${XLA_FLAGS:-} --xla_gpu_autotune_level=0" python3 \
        train.py "${user_run[@]}" --out /tmp/gpu_bench_run_na
        cp /tmp/gpu_bench_run_na/metrics.csv "$OUT/trainpy-na_metrics.csv" 2>/dev/null ;;
      trainpy-nt) step "$(box 220)" env XLA_FLAGS="${XLA_FLAGS:-} --xla_gpu_enable_triton_gemm=false" \
        python3 train.py "${user_run[@]}" --out /tmp/gpu_bench_run_nt
        cp /tmp/gpu_bench_run_nt/metrics.csv "$OUT/trainpy-nt_metrics.csv" 2>/dev/null ;;
      *) echo "unknown stage $s (valid: env env-nocull env-warp profile profilex model train32 train32w train32bf profilebf train128 train128p compile trainpy evalpy determinism determinism-ops trainpy-na trainpy-nt)" ;;
    esac
  done
}

main 2>&1 | tee "$OUT/log"
