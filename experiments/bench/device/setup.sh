#!/usr/bin/env bash
# On the device, from the project root, one step per call (prepare.sh says which folder each carries):
#   a   keep warp's first part           b   warp + wheels unpacked, the synthetic office generated
#   k1  7-Scenes frames 0-249 to ~/7s     k2  the rest of 7-Scenes to ~/7s
set -euo pipefail
case "$1" in
  a) mkdir -p ~/stash && cp .gpu/a/part-00 ~/stash/ ;;
  b)
    [ -d ~/stash/warp ] || { cat ~/stash/part-00 .gpu/b/part-01 | xz -d | tar -x -C ~/stash; }
    pip install -q --no-index --no-deps --target ~/stash .gpu/whl/*.whl 2>&1 | tail -2
    . experiments/bench/device/env.sh
    python - <<'PY'
import time
import warp as wp
from rgs_warp import load_config, open_dataset
t = time.time()
wp.init()
print("warp", wp.__version__, wp.get_device().name)
for overrides in (["dataset=synthetic/office0_replica_size"],
                  ["dataset=synthetic/office0_replica_size", "dataset.width=640", "dataset.height=360"]):
    print(overrides, len(open_dataset(load_config(overrides))), f"{time.time() - t:.0f} s")
PY
    ;;
  k1 | k2) mkdir -p ~/7s && mv ".gpu/$1"/* ~/7s/ && ls ~/7s | wc -l ;;
  *) echo "setup.sh a|b|k1|k2" >&2; exit 2 ;;
esac
