#!/usr/bin/env bash
# Issue #47 "Measured", learning at budgets that fit a 2-core machine (docs/results.md "Images and
# observation groups"). One run at a time; every run dir under $OUT (default /tmp/obs47).
#   bash benchmarks/obs47_learning.sh push_cube_critic 262144   # asymmetric vs symmetric critic
#   bash benchmarks/obs47_learning.sh pong 16384                # Pong-v5 (EnvPool), 3 seeds
#   bash benchmarks/obs47_learning.sh car_racing 8192           # CarRacing-v3, one seed
#   bash benchmarks/obs47_learning.sh push_cube_pixels 65536    # pixels (actor) against state
set -euo pipefail
cd "$(dirname "$0")/.."
what=$1
frames=$2
out=${OUT:-/tmp/obs47}
py=${PYTHON:-.venv/bin/python}
export PYTHONPATH=$PWD/src
run() {  # run NAME overrides...
  local name=$1
  shift
  echo "== $name: $*"
  "$py" train.py "$@" "trainer.total_frames=$frames" trainer.save_every=0 "hydra.run.dir=$out/$name" \
    >"$out/$name.log" 2>&1
  grep -E "\[(train|eval)\]" "$out/$name.log" | tail -4
}
mkdir -p "$out"
case $what in
  push_cube_critic)
    for seed in 0 1 2; do
      run "push_cube_asym_s$seed" +experiment=push_cube_ppo seed=$seed trainer.eval_every=131072
      run "push_cube_sym_s$seed" +experiment=push_cube_ppo seed=$seed trainer.eval_every=131072 \
        'policy.critic.observations=[policy]'
    done
    ;;
  pong)
    for seed in 1 2 3; do
      run "pong_s$seed" +experiment=pong_ppo seed=$seed trainer.eval_every=0
    done
    ;;
  car_racing)
    run car_racing_s0 +experiment=car_racing_ppo seed=0 trainer.eval_every=0
    ;;
  push_cube_pixels)
    for seed in 0 1 2; do
      run "push_cube_pixels_s$seed" +experiment=push_cube_pixels seed=$seed trainer.eval_every=0
      run "push_cube_state16_s$seed" +experiment=push_cube_pixels seed=$seed trainer.eval_every=0 \
        'policy.actor.observations=[policy]' '~env.native.observations.camera'
    done
    ;;
  *)
    echo "unknown: $what" >&2
    exit 2
    ;;
esac
