#!/usr/bin/env bash
# Why a sandboxed child sees no GPU where its parent does (issue 35, first lent H100): the device
# probe child under each of its restrictions alone, and the restriction-free baseline. One call:
#   run(command="bash bench/investigations/gpu_child_diagnose.sh", carry=[".gpu"], timeout_s=240)
set -uo pipefail
cd "$(dirname "$0")/../.."
export PYTHONUNBUFFERED=1 PYTHONDONTWRITEBYTECODE=1 NDRF_DEVICE=${NDRF_DEVICE:-cuda}
PYTHON=${PYTHON:-python3}
export PYTHONPATH="$PWD"
if [ -f .gpu/site.zip ]; then
  [ -d /tmp/ndrf-site ] || "$PYTHON" -m zipfile -e .gpu/site.zip /tmp/ndrf-site
  export PYTHONPATH="$PWD:/tmp/ndrf-site"
fi
SNIPPET='import torch, drjit as dr; print("torch", torch.cuda.is_available(), "drjit", dr.has_backend(dr.JitBackend.CUDA))'
echo "== environment"; env | grep -E -i "cuda|nvidia|^LD_|^PATH" | sort
ls -la /dev/nvidia* 2>&1 | head; grep -i -E "nvidia|/run|/dev " /proc/self/mountinfo | head -20
ldconfig -p | grep -E "libcuda|libnvidia-ml" | head
echo "== plain";                    timeout 60 "$PYTHON" -c "$SNIPPET" 2>&1 | tail -2
echo "== stripped environment";     timeout 60 env -i PATH="$PATH" HOME="$HOME" PYTHONPATH="$PYTHONPATH" LD_LIBRARY_PATH="${LD_LIBRARY_PATH:-}" "$PYTHON" -c "$SNIPPET" 2>&1 | tail -2
echo "== RLIMIT_DATA 8 GiB";        timeout 60 prlimit --data=8589934592 "$PYTHON" -c "$SNIPPET" 2>&1 | tail -2
echo "== RLIMIT_NOFILE 512";        timeout 60 prlimit --nofile=512 "$PYTHON" -c "$SNIPPET" 2>&1 | tail -2
echo "== unshare namespaces";       timeout 60 unshare --net --mount --ipc --propagation private "$PYTHON" -c "$SNIPPET" 2>&1 | tail -2
echo "== /run covered";             timeout 60 unshare --mount --propagation private bash -c "mount -t tmpfs tmpfs /run && $PYTHON -c '$SNIPPET'" 2>&1 | tail -2
echo "== /dev/shm private";         timeout 60 unshare --mount --propagation private bash -c "mount -t tmpfs tmpfs /dev/shm && $PYTHON -c '$SNIPPET'" 2>&1 | tail -2
for sandbox in off auto; do
  echo "== probe child, NDRF_SANDBOX=$sandbox"
  NDRF_SANDBOX=$sandbox timeout 120 "$PYTHON" -c "
import logging, json; logging.basicConfig(level=logging.DEBUG)
from services.jobs.device import probe_device; print(json.dumps(probe_device()))" 2>&1 | grep -v "sandbox\|^DEBUG:asyncio" | tail -15
done
echo "== probe child, NDRF_SANDBOX=auto, child memory 64 GiB"
NDRF_CHILD_MEMORY_BYTES=$((64 << 30)) timeout 120 "$PYTHON" -c "
from services.jobs.device import probe_device; print(probe_device())" 2>&1 | tail -3
