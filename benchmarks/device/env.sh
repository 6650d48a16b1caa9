# Sourced by the device checks here (from the repository root on the GPU machine): installs the
# carried wheels, makes the checkout importable as ``esgs``, unpacks the scene, copies the LPIPS
# weights; defines ROOT, S (the scene) and ``stamp`` (elapsed seconds before a step's title).
ROOT=$(pwd)
T0=$(date +%s)
stamp() { echo "=== [$(( $(date +%s) - T0 )) s] $*"; }
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .devcarry/*.whl || exit 1
mkdir -p /tmp/pkg && ln -sfn "$ROOT" /tmp/pkg/esgs
export PYTHONPATH=/tmp/site:/tmp/pkg TORCH_CUDA_ARCH_LIST=9.0 MAX_JOBS=16 PYTHONUNBUFFERED=1
tar xzf .devcarry/s2.tar.gz || exit 1
mkdir -p ~/.cache/esgs && cp -r .devcarry/cache/lpips ~/.cache/esgs/
S=.devcarry/scenes/mixed_s2
