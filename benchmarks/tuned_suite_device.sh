#!/usr/bin/env bash
# The tuned suite (conf/sweep/tuned_1m.yaml: 9 MuJoCo tasks x 5 seeds x 1M steps) on a machine of
# 16 cores: 16 jobs at a time (hydra.launcher.n_jobs), each on the CPU with one torch thread, into
# one fixed sweep dir, so that running this again continues it (finished jobs are skipped). The
# run dirs' small files (metrics.jsonl, .hydra/, config.yaml, status.json, provenance.json,
# train.log, multirun.yaml, and rlexp report's report.md / results.csv; no checkpoints) go to
# $OUT/tuned_suite.tar.gz every PACK_EVERY seconds while it runs and once more at the end, also
# when a timeout's SIGTERM (or Ctrl-C) stops it: a SIGKILL still leaves the last periodic pack.
#   OUT=/tmp/out benchmarks/tuned_suite_device.sh                      # the whole suite
#   OUT=/tmp/out benchmarks/tuned_suite_device.sh env=hopper,walker2d  # a subset (own sweep dir!)
# Environment: PYTHON (default .venv/bin/python, else python), JOBS (16), SWEEP_DIR
# (multirun/tuned_1m), PACK_EVERY (120). Extra arguments are Hydra overrides for every job; a
# subset is another sweep: give it SWEEP_DIR=multirun/tuned_1m_<name> (docs/results.md).
# JOBS=1 runs the job inside the sweep's process (joblib), where a stop signal is forwarded to no
# worker and the job trains on to its budget: use JOBS >= 2 where the stop must checkpoint.
set -u
cd "$(dirname "$0")/.."
PY=${PYTHON:-.venv/bin/python}
[ -x "$PY" ] || PY=python
OUT=${OUT:-.}
JOBS=${JOBS:-16}
SWEEP=${SWEEP_DIR:-multirun/tuned_1m}
PACK_EVERY=${PACK_EVERY:-120}
mkdir -p "$OUT" "$SWEEP"
export MUJOCO_GL=${MUJOCO_GL:-egl} OMP_NUM_THREADS=1 MKL_NUM_THREADS=1

pack() {  # the small files of every run dir, written to a temporary name, then renamed
    [ -d "$SWEEP" ] || return 0
    tar czf "$OUT/tuned_suite.tar.gz.part" --exclude='checkpoints' --exclude='tensorboard' \
        --exclude='*.pt' --exclude='.multirun.lock' -C "$(dirname "$SWEEP")" "$(basename "$SWEEP")" \
        2>/dev/null && mv -f "$OUT/tuned_suite.tar.gz.part" "$OUT/tuned_suite.tar.gz"
}

finish() {
    trap - EXIT INT TERM
    [ -n "${PACKER:-}" ] && kill "$PACKER" 2>/dev/null
    if [ -n "${SWEEP_PID:-}" ] && kill -0 "$SWEEP_PID" 2>/dev/null; then
        # the sweep's whole process group (its joblib workers too), as a terminal's Ctrl-C: each
        # running job saves a checkpoint at the end of its iteration and says interrupted
        kill -TERM -- -"$SWEEP_PID" 2>/dev/null
        for _ in $(seq 90); do kill -0 "$SWEEP_PID" 2>/dev/null || break; sleep 1; done
    fi
    timeout 120 "$PY" -m rlexp report "$SWEEP" --no-plot >"$OUT/report.md" 2>"$OUT/report.err"
    pack
    echo "packed $SWEEP into $OUT/tuned_suite.tar.gz"
}
trap finish EXIT INT TERM

(while sleep "$PACK_EVERY"; do pack; done) &
PACKER=$!

echo "tuned suite: $JOBS jobs at a time into $SWEEP ($(date -u +%FT%TZ), $(nproc) cores)"
setsid "$PY" train.py -m +sweep=tuned_1m hydra.sweep.dir="$SWEEP" hydra.launcher.n_jobs="$JOBS" \
    trainer.device=cpu trainer.progress=false "$@" >"$OUT/suite.log" 2>&1 &
SWEEP_PID=$!  # the leader of its own process group (setsid)
wait "$SWEEP_PID"
echo "sweep exit $? ($(date -u +%FT%TZ))"
