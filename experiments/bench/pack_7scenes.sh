#!/usr/bin/env bash
# Splits the shared 7-Scenes redkitchen frames (62 MB) into two ignored folders for the GPU machine,
# whose calls carry at most 64 MiB with the working tree (about 9 MB):
#   .gpu/k1: colour, poses, intrinsics and depth of frames 0-249 (about 43 MB)
#   .gpu/k2: depth of frames 250-499 (about 19 MB)
# Carry each in its own call and move both into one folder there, e.g.
#   mkdir -p ~/7s && mv .gpu/k1/* ~/7s/      (then, in the next call)   mv .gpu/k2/* ~/7s/
# and run with dataset=7scenes/redkitchen,dataset.path=$HOME/7s.
# Usage, from the project root:  bash experiments/bench/pack_7scenes.sh [SHARED_DATA_DIR]
set -euo pipefail
root=$(git rev-parse --show-toplevel)
src=${1:-$root/../shared/data/7scenes-redkitchen}
grep -qx '/.gpu/' "$root/.git/info/exclude" 2>/dev/null || { mkdir -p "$root/.git/info"; echo '/.gpu/' >> "$root/.git/info/exclude"; }
rm -rf "$root/.gpu/k1" "$root/.gpu/k2"
mkdir -p "$root/.gpu/k1" "$root/.gpu/k2"
cp "$src"/camera-intrinsics.txt "$src"/*.color.jpg "$src"/*.pose.txt "$root/.gpu/k1/"
for i in $(seq 0 499); do
  f=$(printf "frame-%06d.depth.png" "$i")
  if ((i < 250)); then cp "$src/$f" "$root/.gpu/k1/"; else cp "$src/$f" "$root/.gpu/k2/"; fi
done
du -sh "$root/.gpu/k1" "$root/.gpu/k2"
