#!/usr/bin/env bash
# Here (no GPU), once per checkout: the ignored .gpu/ folders a device session carries.
#   .gpu/a, .gpu/b   warp-lang in two parts (../shared/gpu/pack-warp.sh)
#   .gpu/whl         plyfile and pytorch-msssim wheels (the device has no package index)
#   .gpu/k1, .gpu/k2 the shared 7-Scenes frames (pack_7scenes.sh), only with --7scenes
# Then, on the device (each call copies the working tree, these scripts included):
#   call 1, carry .gpu/a:          bash experiments/bench/device/setup.sh a
#   call 2, carry .gpu/b,.gpu/whl: bash experiments/bench/device/setup.sh b     (warp, wheels, the synthetic office)
#   7-Scenes: call with .gpu/k1:   bash experiments/bench/device/setup.sh k1, then with .gpu/k2: ... k2
#   runs:                          bash experiments/bench/device/batch.sh JOBS REPEATS NAME "case:overrides" ...
# The machine is given back after about 30 s idle: make the calls one after another.
set -euo pipefail
root=$(git rev-parse --show-toplevel)
cd "$root"
[ -f .gpu/a/part-00 ] && [ -f .gpu/b/part-01 ] || bash ../shared/gpu/pack-warp.sh
mkdir -p .gpu/whl
ls .gpu/whl/plyfile-*.whl >/dev/null 2>&1 || python3 -m pip download -q --no-deps -d .gpu/whl plyfile pytorch-msssim
if [ "${1:-}" = "--7scenes" ]; then bash experiments/bench/pack_7scenes.sh; fi
du -sh .gpu/*
