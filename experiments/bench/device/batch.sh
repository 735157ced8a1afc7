#!/usr/bin/env bash
# On the device: slam_repeats.py over the cases, REPEATS runs each, JOBS at a time (1: solo, for frames/s);
# "@7S" in a case stands for the 7-Scenes frames in ~/7s.  $OUT gets NAME.json (every run's metrics) and
# NAME_runs.tar.gz (their logs, trajectories and repeat 0's last render | truth | error).
#   bash experiments/bench/device/batch.sh 1 3 e1 "live:@7S,timing=live,dataset.playback_fps=60"
set -euo pipefail
. experiments/bench/device/env.sh
jobs=$1 reps=$2 name=$3
shift 3
args=()
for c in "$@"; do args+=(--case "${c//@7S/dataset=7scenes\/redkitchen,dataset.path=$HOME\/7s}"); done
python experiments/bench/slam_repeats.py --out ~/runs/"$name" --jobs "$jobs" --repeats "$reps" "${args[@]}" 2>&1 | tail -25
cp ~/runs/"$name"/repeats.json "$OUT/$name.json"
cp ~/runs/"$name"/runs.tar.gz "$OUT/${name}_runs.tar.gz"
