#!/usr/bin/env bash
# The first measurement of `--set device=cuda` (RunConfig.device), prepared on a machine without a GPU.
#
#   benchmarks/gpu_check.sh [OUT_DIR]      (from the repository root, on a CUDA machine)
#
# Prints the GPU's name, then trains cn3 for each of the paper's five variants on DEVICE, one
# compile=true run, the same six again with precision=bf16 on DEVICE (skipped, saying why, where the
# device has no native bfloat16), and the six float32 ones on the CPU, printing env-steps/s from each
# run's summary.json, the DEVICE/CPU ratio and the bf16/fp32 ratio on DEVICE (a compile=true run's
# rate includes its one-off compile), and each bf16 run's final paper metric beside its fp32 twin's
# (one seed: a smoke check that bf16 learns, not a comparison). Stops at the first
# failed run (its log's tail is printed). About 3-6 minutes at the default budget (a guess: no GPU
# has run it yet; DEVICE=cpu EPISODES=64 takes ~70 s on 2 cores); every run directory and log stays
# under OUT_DIR.
#
#   VENV=.venv        the venv with hammer installed (its bin/hammer and bin/python are used)
#   DEVICE=cuda       cuda, cuda:N, or cpu (a dry run of this script on a machine without a GPU)
#   EPISODES=1000     episode budget per run (25 env steps each)
#   RUN_TIMEOUT=240   seconds one run may take before the script gives up
#   PRECISIONS="fp32 bf16"   the precisions run on DEVICE (the CPU pass is float32)
set -euo pipefail

VENV=${VENV:-.venv}
DEVICE=${DEVICE:-cuda}
EPISODES=${EPISODES:-1000}
RUN_TIMEOUT=${RUN_TIMEOUT:-240}
PRECISIONS=${PRECISIONS:-fp32 bf16}
OUT=${1:-$(mktemp -d "${TMPDIR:-/tmp}/gpu_check.XXXXXX")}
PY="$VENV/bin/python"
HAMMER="$VENV/bin/hammer"
VARIANTS=(hammer-rl hammer-backprop il random centralized)  # the paper's cn3 grid
mkdir -p "$OUT"

"$PY" - "$DEVICE" <<'EOF'
import sys

import torch

dev = torch.device(sys.argv[1])
print(f"torch {torch.__version__} (cuda {torch.version.cuda}), {torch.get_num_threads()} CPU threads")
if dev.type == "cuda":
    if not torch.cuda.is_available():
        sys.exit(f"DEVICE={sys.argv[1]}: torch sees no CUDA device; fix: run on a GPU machine, or DEVICE=cpu")
    print(f"device: {torch.cuda.get_device_name(dev)}, native bf16: "
          f"{torch.cuda.is_bf16_supported(including_emulation=False)}")
else:
    print("device: cpu (DEVICE=cpu: a dry run of this script)")
EOF

# run NAME DEVICE VARIANT [--set k=v ...]: one training run; prints and records its env-steps/s
run() {
    local name=$1 dev=$2 variant=$3
    shift 3
    local dir="$OUT/$name"
    if ! timeout "$RUN_TIMEOUT" "$HAMMER" train --preset cn3 --variant "$variant" --episodes "$EPISODES" \
            --run-dir "$dir" --quiet --set "device=$dev" "$@" >"$dir.log" 2>&1; then
        echo "FAILED: $name (exit status above 0 or over ${RUN_TIMEOUT}s); the end of $dir.log:" >&2
        tail -n 25 "$dir.log" >&2
        exit 1
    fi
    local sps
    sps=$("$PY" -c 'import json, sys; print(round(json.load(open(sys.argv[1]))["env_steps_per_s_this_session"]))' \
        "$dir/summary.json")
    printf '%-34s %8s env-steps/s\n' "$name" "$sps"
    echo "$name $sps" >>"$OUT/results.txt"
}

# bf16_unsupported DEVICE: why DEVICE has no native bfloat16 (empty when it has; the refusal's own test)
bf16_unsupported() {
    "$PY" -c 'import sys, torch; from hammer.learning.precision import bf16_unsupported as why
print(why(torch.device(sys.argv[1])) or "")' "$1"
}

: >"$OUT/results.txt"
passes=()
for p in $PRECISIONS; do passes+=("device:$p:$DEVICE"); done
passes+=("cpu:fp32:cpu")
for pass in "${passes[@]}"; do  # run names device-*, device-bf16-* and cpu-* (distinct also when DEVICE=cpu)
    IFS=: read -r tag precision dev <<<"$pass"  # the device last: cuda:N holds a colon
    [ "$precision" = fp32 ] || tag="$tag-$precision"
    if [ "$precision" = bf16 ] && [ "${HAMMER_ALLOW_EMULATED_BF16:-}" != 1 ]; then
        why=$(bf16_unsupported "$dev")
        if [ -n "$why" ]; then
            echo "--- bf16 on $dev: skipped ($why; HAMMER_ALLOW_EMULATED_BF16=1 runs it emulated)"
            continue
        fi
    fi
    echo "--- on $dev, precision $precision ($EPISODES episodes per run)"
    for v in "${VARIANTS[@]}"; do
        run "$tag-$v" "$dev" "$v" --set "precision=$precision"
    done
    run "$tag-hammer-rl-compile" "$dev" hammer-rl --set compile=true --set "precision=$precision"
done

echo "--- $DEVICE / cpu (env-steps/s ratio; above 1: the device is faster)"
"$PY" - "$OUT/results.txt" <<'EOF'
import sys

sps = dict(line.split() for line in open(sys.argv[1]))
for name in [n for n in sps if n.startswith("device-") and not n.startswith("device-bf16-")]:
    what = name.removeprefix("device-")
    print(f"{what:34s} {float(sps[name]) / float(sps['cpu-' + what]):8.2f}")
EOF
if grep -q '^device-bf16-' "$OUT/results.txt"; then
    echo "--- bf16 / fp32 on $DEVICE (env-steps/s ratio; final paper metric of the last 500 episodes, fp32 -> bf16)"
    "$PY" - "$OUT" <<'EOF'
import json
import sys
from pathlib import Path

out = Path(sys.argv[1])
sps = dict(line.split() for line in open(out / "results.txt"))
for name in [n for n in sps if n.startswith("device-bf16-")]:
    what = name.removeprefix("device-bf16-")
    m = [json.loads((out / n / "summary.json").read_text())["final_paper_metric_last500"] for n in (f"device-{what}", name)]
    print(f"{what:34s} {float(sps[name]) / float(sps['device-' + what]):8.2f}   {m[0]:8.2f} -> {m[1]:8.2f}")
EOF
fi
echo "runs and logs: $OUT"
