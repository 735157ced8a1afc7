# Sourced on the device: the unpacked wheels and the package on the path, the caches outside the tree.
export PYTHONPATH=$HOME/stash:$PWD/src
export WARP_CACHE_PATH=$HOME/cache/warp RGS_CACHE=$HOME/cache/rgs
export OMP_NUM_THREADS=4
