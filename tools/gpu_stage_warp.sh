#!/usr/bin/env bash
# Bring warp-lang (MJX-Warp physics, SimConfig.physics = 'warp') to the lent GPU machine, which lacks
# it: its wheel (149 MB) is larger than the 64 MiB one device call carries, so it travels in parts,
# one per call, and a warm machine keeps what earlier calls left in /tmp.
#
#   here:    bash tools/gpu_stage_warp.sh split      # .warp/part-aa, part-ab, part-ac (<= 62 MB each)
#                                                    # and .warp/SHA256 (of the whole wheel)
#   device:  run(command="bash tools/gpu_stage_warp.sh stash", carry=[".warp/part-aa", ".warp/SHA256"])
#            run(command="bash tools/gpu_stage_warp.sh stash", carry=[".warp/part-ab"])
#            then the call that measures, carrying the last part with the other wheels, e.g.
#            run(command="bash tools/gpu_stage_warp.sh stash && bash tools/gpu_bench.sh 480 env-warp
#                train32w", carry=[".whl", ".warp/part-ac"])
#            (gpu_lib.sh's setup installs the reassembled wheel into /tmp/site when all parts are
#            there and the checksum matches). The machine goes back after ~30 s idle: make the calls
#            back to back, or the parts are lost with it.
#   install: bash tools/gpu_stage_warp.sh install    # what setup runs: reassemble, check, pip install
set -euo pipefail
cd "$(dirname "$0")/.."
VERSION=1.18.0 # the warp-lang that mujoco-mjx 3.17's [warp] extra pins
STASH=/tmp/warp_parts
PART_BYTES=62000000

case ${1:-} in
  split)
    grep -qx '/.warp/' .git/info/exclude 2>/dev/null || echo '/.warp/' >>.git/info/exclude
    rm -rf .warp && mkdir -p .warp/dl
    python3 -m pip download -q --no-deps --only-binary=:all: --platform manylinux_2_28_x86_64 \
      -d .warp/dl "warp-lang==$VERSION"
    whl=$(ls .warp/dl/warp_lang-*.whl)
    (cd .warp && sha256sum "dl/$(basename "$whl")" | sed "s#dl/##" >SHA256)
    split -b "$PART_BYTES" "$whl" .warp/part-
    rm -rf .warp/dl
    ls -la .warp
    ;;
  stash)
    mkdir -p "$STASH"
    cp -v .warp/part-* .warp/SHA256 "$STASH"/ 2>/dev/null || true
    ls -la "$STASH"
    ;;
  install)
    mkdir -p "$STASH"
    cp .warp/part-* .warp/SHA256 "$STASH"/ 2>/dev/null || true # parts the repo copy still holds
    [[ -f $STASH/SHA256 ]] || { echo "no warp-lang parts in $STASH"; exit 1; }
    name=$(awk '{print $2}' "$STASH/SHA256")
    cat "$STASH"/part-* >"/tmp/$name"
    (cd /tmp && sha256sum -c "$STASH/SHA256") || { echo "warp-lang parts incomplete (checksum)"; exit 1; }
    python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade \
      --target /tmp/site "/tmp/$name"
    ;;
  *)
    echo "usage: $0 split|stash|install" >&2
    exit 2
    ;;
esac
