#!/usr/bin/env bash
# The device checks of a lent or new GPU node in one pass, each step under its own time limit so
# that one stuck step leaves the others' results: the CUDA kernels' test, the GPU tests, the
# iteration bench, then benchmarks/gpu_checks.py's camera part (the whole frame alone and
# 2-4 at once on one GPU), its tomo part (a 2560-wide block on the device, gridded and
# back-projected, and on the host's cores), its warm part (a chain's step on the camera frame under either stop rule) and, while
# BUDGET_S seconds last, its strip part.
#
#   BUDGET_S=540 bash benchmarks/gpu_session.sh OUT_DIR [STRIP_ANGLES]
#
# Writes OUT_DIR/log.txt (every step's tail, with seconds since the start), OUT_DIR/bench/
# (bench_iteration_gpu.*) and OUT_DIR/{camera,tomo,warm,strip}.json. About 9 minutes on an H200
# (session 61; docs/gpu.md); the warm part (session 63, ~2.5 min) comes out of the strip's
# budget. Needs the package importable (pip install -e ".[gpu,test]", or PYTHONPATH set to the
# checkout) and a CUDA device.
set -u -o pipefail
out=${1:?usage: gpu_session.sh OUT_DIR [STRIP_ANGLES]}
angles=${2:-41}
mkdir -p "$out"
log=$out/log.txt
py=${PYTHON:-python3}
export PYTHONUNBUFFERED=1 PWF_DASK_CUDA_KERNELS=0
t0=$(date +%s)
step() { echo "== [$(($(date +%s) - t0)) s] $*" | tee -a "$log"; }
{ nvidia-smi -L; "$py" -c "import cupy, numpy; print('cupy', cupy.__version__, 'numpy', numpy.__version__)"; } 2>&1 | tee -a "$log"
step "CUDA kernels' test"
PWF_DASK_CUDA_KERNELS=1 timeout 90 "$py" -m pytest -m gpu tests/test_kernels.py tests/test_tomography_fsc.py tests/test_solver.py -k "kernel and device" -q -p no:cacheprovider -rfE 2>&1 | tail -20 | tee -a "$log"
step "pytest -m gpu (device tests)"
timeout 120 "$py" -m pytest -m gpu -k device -q -p no:cacheprovider -n 8 -rfE 2>&1 | tail -20 | tee -a "$log"
step "bench iteration (CUDA kernels timed beside the default)"
timeout 170 "$py" -m pwf_dask.cli bench iteration --device gpu --out "$out/bench" 2>&1 | tail -30 | tee -a "$log"
step "camera: the paper preset's whole 2160 x 2560 frame, alone and 2-4 at once"
timeout 150 "$py" -m benchmarks.gpu_checks "$out" camera 2>&1 | tail -8 | tee -a "$log"
step "tomo: 801 angles x 8 rows x 2560 px, device and host"
timeout 90 "$py" -m benchmarks.gpu_checks "$out" tomo 2>&1 | tail -8 | tee -a "$log"
step "warm: a chain's step on the camera frame, either stop rule"
timeout 200 "$py" -m benchmarks.gpu_checks "$out" warm 2>&1 | tail -8 | tee -a "$log"
left=$((${BUDGET_S:-540} - ($(date +%s) - t0)))
if [ "$left" -gt 60 ]; then
    step "strip $angles ($left s left)"
    timeout "$left" "$py" -m benchmarks.gpu_checks "$out" strip "$angles" 2>&1 | grep '^{' | tail -3 | tee -a "$log"
fi
step "end"
