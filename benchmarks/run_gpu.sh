#!/usr/bin/env bash
# GPU verification and benchmarks, as run on a borrowed NVIDIA machine (H100/H200 with CUDA,
# CuPy and NVIDIA's OpenCL driver; no network). Results go to the folder given as $1.
#
#   bash benchmarks/run_gpu.sh OUTDIR [WHEELDIR]
#
# WHEELDIR holds wheels for what the machine lacks (pyopencl and its pure-Python needs,
# colour-science, tomli-w; pmcx for the MCX comparison), fetched elsewhere with
# `pip download --only-binary=:all: --python-version 3.12 ...`.
set -uo pipefail
out="${1:?output folder}"
wheels="${2:-.whl}"
mkdir -p "$out"
export PYTHONUNBUFFERED=1
if compgen -G "$wheels/*.whl" >/dev/null; then
    python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site "$wheels"/*.whl || exit 1
    export PYTHONPATH=/tmp/site${PYTHONPATH:+:$PYTHONPATH}
fi
# NVIDIA's OpenCL through the ICD loader bundled with pyopencl
mkdir -p /tmp/icd && echo libnvidia-opencl.so.1 > /tmp/icd/nvidia.icd && export OCL_ICD_VENDORS=/tmp/icd
python3 -m pip install -q --no-deps --no-build-isolation --no-index -e . >/dev/null || exit 1
nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader | tee "$out/gpu.txt"
python3 -m nebula_rt.cli devices | tee -a "$out/gpu.txt"

physics="tests/test_rng.py tests/test_hg.py tests/test_density_kernel.py tests/test_transport_physics.py tests/test_estimators.py"
NEBULA_RT_TEST_BACKEND=cuda python3 -m pytest -q -p no:cacheprovider $physics 2>&1 | tail -n 15 | tee "$out/tests-cuda.txt"
NEBULA_RT_TEST_DEVICE=NVIDIA python3 -m pytest -q -p no:cacheprovider $physics 2>&1 | tail -n 15 | tee "$out/tests-nvidia-opencl.txt"

python3 benchmarks/bench_transport.py --backend cuda --out "$out/transport-cuda.json" 2>&1 | tee "$out/bench-cuda.txt"
python3 benchmarks/bench_transport.py --backend opencl --device NVIDIA --out "$out/transport-nvidia-opencl.json" 2>&1 | tee "$out/bench-nvidia-opencl.txt"
python3 benchmarks/compare_backends.py --run cuda: --run opencl:NVIDIA --save-dir "$out" --out "$out/compare.json" 2>&1 | tail -n 40
