# Sourced by the prepared scripts of a GPU lease (tools/gpu_tables.sh, tools/gpu_bench.sh;
# ../shared/gpu/README.md): time-boxed steps and the setup every device call starts with.
# Needs SECONDS_BOX (the whole script's time box) and OUT set by the caller.
export PYTHONUNBUFFERED=1

left() { echo $((SECONDS_BOX - SECONDS)); }

# step SECONDS CMD...: run CMD time-boxed (TERM, then KILL 10 s later), print its rc.
step() {
  local box=$1
  shift
  if ((box < 5)); then
    echo "== skipped (no time left): $*"
    return 124
  fi
  echo "== [$(date +%T), ${SECONDS}s] (time box ${box}s) $*"
  timeout -k 10 -s TERM "$box" "$@"
  local rc=$?
  echo "== rc $rc after ${SECONDS}s"
  return $rc
}

# setup: install the wheels the GPU machine lacks (carried in .whl/ by fetch-wheels.sh; absent on a
# dev machine), then write what this machine is to $OUT/env.txt.
setup() {
  if compgen -G '.whl/*.whl' >/dev/null; then
    step 120 python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
      --target /tmp/site .whl/*.whl || return 1
    export PYTHONPATH=/tmp/site:$PWD
  fi
  if compgen -G '/tmp/warp_parts/part-*' >/dev/null || compgen -G '.warp/part-*' >/dev/null; then
    step 120 bash tools/gpu_stage_warp.sh install && export PYTHONPATH=/tmp/site:$PWD
  fi
  {
    step 60 python3 -c 'import jax, flax, optax, numpy, mujoco; print("jax", jax.__version__, jax.devices(), "flax",
flax.__version__, "optax", optax.__version__, "numpy", numpy.__version__, "mujoco", mujoco.__version__)'
    python3 -c 'from hron_jax.cli import computes_on_gpu; print("computes_on_gpu", computes_on_gpu())'
    command -v nvidia-smi >/dev/null && nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv
    nproc
  } 2>&1 | tee "$OUT/env.txt"
}
