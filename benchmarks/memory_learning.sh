#!/usr/bin/env bash
# Issue #48 "Measured", learning on the velocity-hidden tasks (docs/results.md "Memory"): the
# recurrent preset against the MLP preset, seeds 1 2 3, one run at a time, each at its preset's
# budget (CartPoleNoVel 100,000 steps, rl-zoo's; PendulumNoVel 102,400). Run dirs under $OUT
# (default /tmp/memory48); the last lines of each run's log are printed.
#   bash benchmarks/memory_learning.sh cart_pole_novel
#   bash benchmarks/memory_learning.sh pendulum_novel trainer.total_frames=102400
set -euo pipefail
cd "$(dirname "$0")/.."
task=$1
shift
out=${OUT:-/tmp/memory48}
py=${PYTHON:-.venv/bin/python}
export PYTHONPATH=$PWD/src
mkdir -p "$out"
for policy in lstm ppo; do
  for seed in 1 2 3; do
    name="${task}_${policy}_s$seed"
    echo "== $name"
    "$py" train.py "+experiment=${task}_$policy" "seed=$seed" trainer.torch_threads=1 \
      trainer.progress=false "hydra.run.dir=$out/$name" "$@" >"$out/$name.log" 2>&1
    grep -E "\[eval\]|done:" "$out/$name.log" | tail -2
  done
done
