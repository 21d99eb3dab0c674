#!/usr/bin/env bash
# The prepared check of a lent GPU machine (issue 35), in ONE device call of at most 8 minutes.
#
# Before, HERE: bench/gpu_carry.sh (makes .gpu/site.zip: Mitsuba, Dr.Jit and the dependencies the
# device image lacks). Then one call of the device tool, from the repository's root:
#
#   run(command="bash bench/gpu_check.sh", carry=[".gpu"], timeout_s=480)
#
# There: unpacks .gpu/site.zip into /tmp (nothing is installed, nothing downloaded), runs the unit
# tests that touch the device, then python -m bench.gpu_check (the demo, room-open-8 and
# hidden-object jobs; seconds per iteration of prb, ndrf-lhs, ndrf-rhs and Mitsuba's tutorial
# loop), with the CPU's figures of bench/results/gpu_check-cpu.json beside them, and writes ONE
# results file, $OUT/gpu_check-<device>.json (and its .md), to commit under bench/results/.
#
# Here, for the CPU column and to try the script end to end:
#   NDRF_DEVICE=cpu PYTHON=.venv/bin/python OUT=bench/results nice -n 19 bench/gpu_check.sh
#
# Environment: NDRF_DEVICE (default cuda), OUT (default bench/results), PYTHON (default python3),
# GPU_CHECK_SECONDS (the whole script's time, default 450: the call's 480 less a margin; no new
# measurement starts in its last 90 s, so a call is never cut in the middle of its results),
# GPU_CHECK_BUDGET (seconds per example job, default 60).
set -uo pipefail
cd "$(dirname "$0")/.."
started=$(date +%s)

export NDRF_DEVICE=${NDRF_DEVICE:-cuda}
export PYTHONUNBUFFERED=1 PYTHONDONTWRITEBYTECODE=1
PYTHON=${PYTHON:-python3}
OUT=${OUT:-bench/results}
SECONDS_ALL=${GPU_CHECK_SECONDS:-450}
mkdir -p "$OUT"
RESULT="$OUT/gpu_check-$NDRF_DEVICE.json"
TESTS_LOG=$(mktemp /tmp/gpu_check_tests.XXXXXX)

SITE_PATH=""
if [ -f .gpu/site.zip ]; then
  SITE=/tmp/ndrf-site
  rm -rf "$SITE"
  "$PYTHON" -m zipfile -e .gpu/site.zip "$SITE" || { echo "could not unpack .gpu/site.zip" >&2; exit 2; }
  SITE_PATH=":$SITE"
  echo "unpacked .gpu/site.zip into $SITE in $(( $(date +%s) - started )) s"
fi
export PYTHONPATH="$PWD$SITE_PATH"

echo "== machine"
nvidia-smi -L 2>/dev/null || echo "(no nvidia-smi)"
"$PYTHON" - <<'EOF'
import platform, sys
import torch
print("python", platform.python_version(), "torch", torch.__version__, "cuda", torch.version.cuda,
      "devices", torch.cuda.device_count() if torch.cuda.is_available() else 0)
import drjit, mitsuba
print("mitsuba", mitsuba.__version__, "drjit", drjit.__version__, "variants", mitsuba.variants())
EOF

echo "== unit tests that touch the device (NDRF_DEVICE=$NDRF_DEVICE)"
timeout 200 "$PYTHON" -m pytest -q -p no:cacheprovider -o addopts="" -x \
  tests/unit/test_device.py tests/unit/test_transfers.py tests/service/test_device_child.py 2>&1 | tee "$TESTS_LOG"
tests_status=${PIPESTATUS[0]}
echo "tests: exit status $tests_status, $(( $(date +%s) - started )) s since the start"

echo "== jobs and seconds per iteration"
left=$(( SECONDS_ALL - ($(date +%s) - started) ))
beside=()
[ "$NDRF_DEVICE" != cpu ] && beside=(--cpu bench/results/gpu_check-cpu.json)
timeout $(( left > 20 ? left - 10 : 10 )) "$PYTHON" -m bench.gpu_check --out "$RESULT" "${beside[@]}" \
  --deadline $(( left > 100 ? left - 90 : 10 )) --budget "${GPU_CHECK_BUDGET:-60}" --tests-log "$TESTS_LOG"
bench_status=$?
rm -f "$TESTS_LOG"
echo "bench: exit status $bench_status; $RESULT; $(( $(date +%s) - started )) s in all"
[ "$tests_status" = 0 ] && [ "$bench_status" = 0 ]
