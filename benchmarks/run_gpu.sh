#!/usr/bin/env bash
# GPU verification and benchmarks, as run on an NVIDIA GPU machine (H100/H200 with CUDA,
# CuPy and NVIDIA's OpenCL driver; no network). Results go to the folder given as $1.
#
#   bash benchmarks/run_gpu.sh OUTDIR [WHEELDIR] [STEPS]
#
# WHEELDIR holds wheels for what the machine lacks (pyopencl and its pure-Python needs,
# colour-science, tomli-w, astropy, speclite, PyAstronomy, miepython, dust_extinction (built
# with `pip wheel`: no wheel on PyPI); pmcx and pmcxcl for the MCX comparison), fetched elsewhere
# with `pip download --only-binary=:all: --python-version 3.12 --no-deps ...`.
# STEPS (default "tests bench neb128 compare profile"; also "tests-cuda", "binned", "thick", "thick-grid", "trust", "scaling", "large", "regions", "regcaps", "profile-regions", "layout", "sorted", "probe", "ranks", "ranks-thesis", "ranks-weak", "tests-mpi", "e2e1e9", "biasing", "fit", "fitprof", "tune",
# "stages", "timeline", "headline", "kernel-probes", "small-regions", "stages-former", "timeline-former", "density", "polarization", "polarization-ocl", "mcx", "mcx1024", "ncu-thesis", "ncu-source", "tree", "tree-targets", "tree-ascend", "trade", "presets", "empty", "fft", "pinte") selects what runs. Everything printed
# goes to OUTDIR/log.txt as well; JSON and .npz results beside it.
set -uo pipefail
out="${1:?output folder}"
wheels="${2:-.whl}"
steps="${3-tests bench neb128 compare profile}"  # ("": no step, set-up only)
mkdir -p "$out"
exec > >(tee -a "$out/log.txt") 2>&1
export PYTHONUNBUFFERED=1
if compgen -G "$wheels/*.whl" >/dev/null; then
    python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site "$wheels"/*.whl || exit 1
    export PYTHONPATH=/tmp/site${PYTHONPATH:+:$PYTHONPATH}
fi
# NVIDIA's OpenCL through the ICD loader bundled with pyopencl
mkdir -p /tmp/icd && echo libnvidia-opencl.so.1 > /tmp/icd/nvidia.icd && export OCL_ICD_VENDORS=/tmp/icd
python3 -m pip install -q --no-deps --no-build-isolation --no-index -e . >/dev/null || exit 1
nvidia-smi --query-gpu=name,driver_version,memory.total --format=csv,noheader
python3 -m nebula_rt.cli devices
git rev-parse --short HEAD 2>/dev/null || true

physics="tests/transport/test_importance.py tests/backends/test_rng.py tests/backends/test_hg.py tests/density/test_density_kernel.py tests/transport/test_transport_physics.py tests/transport/test_estimators.py tests/transport/test_postprocess.py tests/transport/test_target_error.py tests/observe/test_sky_physics.py tests/backends/test_kernel_options.py tests/transport/test_filter_boundary.py tests/transport/test_terminated.py tests/observe/test_peel_off_physics.py tests/transport/test_band_independence.py tests/transport/test_resources.py tests/transport/test_extremes.py tests/backends/test_memory_layout.py tests/transport/test_biased_transport.py tests/backends/test_regions.py tests/transport/test_tail_diagnostic.py tests/transport/test_trust_slab.py tests/transport/test_transport_request.py tests/transport/test_tree_transport.py"
if [[ " $steps " == *" tests "* ]]; then
    echo "== physics tests, CUDA"; NEBULA_RT_TEST_BACKEND=cuda python3 -m pytest -q -p no:cacheprovider $physics tests/backends/test_cuda_sources.py 2>&1 | tail -n 8
    echo "== physics tests, NVIDIA OpenCL"; NEBULA_RT_TEST_DEVICE=NVIDIA python3 -m pytest -q -p no:cacheprovider $physics 2>&1 | tail -n 3
fi
if [[ " $steps " == *" tests-mpi "* ]]; then
    # CUDA ranks under mpiexec: the same bits on 1, 2 and 3 ranks, sums of GPU arrays (NCCL where
    # each rank has a GPU of its own, else through the host)
    echo "== MPI tests, CUDA ranks"; NCCL_NVLS_ENABLE=0 NEBULA_RT_TEST_BACKEND=cuda python3 -m pytest -q -p no:cacheprovider \
        tests/test_mpi.py -k "same_bits and (plain or packets or biased) or device_arrays or nccl_loads or allreduce" 2>&1 | tail -n 8
fi
if [[ " $steps " == *" thick "* ]]; then
    # light through thick slabs against the exact answer (tests/oracles), CUDA and NVIDIA OpenCL;
    # the former weighted packets too where a copy of that commit's python/ (with its kernels
    # as nebula_rt/kernels) lies in .former/
    echo "== thick slab tests, CUDA"; NEBULA_RT_TEST_BACKEND=cuda python3 -m pytest -q -p no:cacheprovider \
        tests/transport/test_thick_slab.py tests/transport/test_biased_transport.py tests/backends/test_cuda_sources.py 2>&1 | tail -n 4
    kw="--albedos 0.6 --gs 0.6 --taus 10 20 30 60 --photons ${THICK_PHOTONS:-1e6} --seeds 16"
    echo "== thick slab, CUDA"; python3 benchmarks/bench_thick_slab.py --backend cuda $kw --methods biased analog --out "$out/thick-slab-cuda.json"
    echo "== thick slab, NVIDIA OpenCL"; python3 benchmarks/bench_thick_slab.py --backend opencl --device NVIDIA $kw --methods biased analog --out "$out/thick-slab-nvidia-opencl.json"
    if [[ -d .former/python ]]; then
        echo "== thick slab, former weighted packets, CUDA"
        PYTHONPATH=.former/python${PYTHONPATH:+:$PYTHONPATH} python3 benchmarks/bench_thick_slab.py --backend cuda $kw --methods biased --label former --out "$out/thick-slab-former-cuda.json"
    fi
fi
if [[ " $steps " == *" thick-grid "* ]]; then
    # every target case of the thick slab with the method a user gets, THICK_SEEDS seeds each for the
    # coverage of the stated errors pooled per depth; the reflected light with the stars' and the
    # observer's windows beside analog packets
    kw="--photons ${THICK_PHOTONS:-1e6} --seeds ${THICK_SEEDS:-64}"
    echo "== thick slab, every case, CUDA"; python3 benchmarks/bench_thick_slab.py --backend cuda $kw --methods auto --out "$out/thick-slab-grid-cuda.json"
    echo "== reflected by thick slabs, CUDA"; python3 benchmarks/bench_thick_slab.py --backend cuda --photons ${THICK_PHOTONS:-1e6} --seeds 16 \
        --sides above --albedos 0.3 0.6 0.9 --gs 0.6 --taus 10 30 --methods biased analog --importance stars observer --out "$out/thick-slab-reflected-cuda.json"
    echo "== reflected by thick slabs, NVIDIA OpenCL"; python3 benchmarks/bench_thick_slab.py --backend opencl --device NVIDIA --photons ${THICK_PHOTONS:-1e6} --seeds 16 \
        --sides above --albedos 0.6 --gs 0.6 --taus 10 30 --methods biased --importance stars observer --out "$out/thick-slab-reflected-nvidia-opencl.json"
fi
if [[ " $steps " == *" trust "* ]]; then
    # the TRUST I slab against the independent oracle (its answers reused from TRUST_ORACLE, a JSON
    # file bench_trust_slab.py wrote on a CPU, where given)
    for be in "cuda" "opencl --device NVIDIA"; do
        tag=${be%% *}; [[ $tag == opencl ]] && tag=nvidia-opencl
        echo "== TRUST I slab, $be"; python3 benchmarks/bench_trust_slab.py --backend $be --photons ${TRUST_PHOTONS:-2e6} \
            ${TRUST_ORACLE:+--oracle $TRUST_ORACLE} --out "$out/trust-slab-$tag.json" 2>&1 | tail -n 3
    done
fi
if [[ " $steps " == *" tests-cuda "* ]]; then
    echo "== physics tests, CUDA"; NEBULA_RT_TEST_BACKEND=cuda python3 -m pytest -q -p no:cacheprovider $physics tests/backends/test_cuda_sources.py 2>&1 | tail -n 8
fi
if [[ " $steps " == *" bench "* ]]; then
    echo "== thesis scene, CUDA"; python3 benchmarks/bench_transport.py --backend cuda --out "$out/transport-cuda.json"
    echo "== thesis scene, NVIDIA OpenCL"; python3 benchmarks/bench_transport.py --backend opencl --device NVIDIA --out "$out/transport-nvidia-opencl.json"
fi
if [[ " $steps " == *" neb128 "* ]]; then
    echo "== neb128, CUDA vs pmcx"; python3 benchmarks/bench_neb128.py --backend cuda --mcx pmcx --out "$out/neb128-cuda.json"
    echo "== neb128, NVIDIA OpenCL"; python3 benchmarks/bench_neb128.py --backend opencl --device NVIDIA --mcx none --out "$out/neb128-nvidia-opencl.json"
fi
if [[ " $steps " == *" pinte "* ]]; then
    # the Pinte et al. 2009 polarization benchmark at tau 1e6 against the published cuts, CUDA
    # PINTE_PHOTONS per inclination; without it, a probe at 87.1 degrees (1e6 packets) sizes the run
    # to PINTE_SECONDS (default 400) of kernel time for both inclinations, at most 4e8 packets each.
    # At most PINTE_SCATTERINGS (default 10, as the PoCL runs) scatterings per packet: in the
    # tau 1e6 disk, forced scattering would otherwise keep a packet for up to 1000
    photons=${PINTE_PHOTONS:-}
    # PINTE_SEED (default 1): runs of other seeds add up (bench_pinte2009.py --from-images
    # PREFIX1,PREFIX2,...), so the packets the benchmark needs can be traced in several commands
    common="--backend cuda --height ${PINTE_HEIGHT:-0.5} --max-scatterings ${PINTE_SCATTERINGS:-10} --seed ${PINTE_SEED:-1}"
    img="$out/pinte-img-s${PINTE_SEED:-1}"
    if [[ -z "$photons" ]]; then
        echo "== Pinte et al. 2009, probe"; timeout 200 python3 benchmarks/bench_pinte2009.py $common --photons 1e6 --inclinations 87.1 \
            --out "$out/pinte-probe.json" | tail -n 5
        photons=$(python3 -c "import json; k = json.load(open('$out/pinte-probe.json'))['inclinations']['87.1']['kernel_s']; print(f'{min(4e8, 1e6 / k * ${PINTE_SECONDS:-400} / 2):.3g}')") || photons=""
    fi
    if [[ -n "$photons" ]]; then
        echo "== Pinte et al. 2009, tau 1e6, CUDA, $photons packets"; python3 benchmarks/bench_pinte2009.py $common --photons $photons \
            --inclinations ${PINTE_INCLINATIONS:-69.5,87.1} --images "$img" --out "$out/pinte-cuda.json" --plot "$out/pinte-cuda.png"
    fi
    python3 benchmarks/bench_pinte2009.py --backend cuda --from-images "$img" --inclinations ${PINTE_INCLINATIONS:-69.5,87.1} \
        --bin 20 --out "$out/pinte-cuda-20au.json" \
        --plot "$out/pinte-cuda-20au.png" | tail -n 6
fi
if [[ " $steps " == *" tune "* ]]; then
    variants=$(cd kernels && ls transport_*.cl 2>/dev/null | tr '\n' ' ')
    echo "== transport kernel tuning, CUDA (variants: ${variants:-none})"
    python3 benchmarks/tune_cuda.py --variant $variants --out "$out/tune-cuda.json"
fi
if [[ " $steps " == *" stages "* ]]; then
    echo "== stage profile, thesis 128^3, CUDA"; python3 benchmarks/profile_stages.py
fi
if [[ " $steps " == *" timeline "* ]]; then
    # the thesis headline call by call, as issued and with the device synchronised around each
    echo "== timeline, thesis 128^3, CUDA"; python3 benchmarks/profile_timeline.py --backend cuda --out "$out/timeline-cuda.json"
fi
if [[ " $steps " == *" trade "* ]]; then
    echo "== speed vs accuracy, CUDA"; python3 benchmarks/trade_study.py --backend cuda --out "$out/trade-study-cuda.json"
fi
if [[ " $steps " == *" presets "* ]]; then
    echo "== quality presets, CUDA"; python3 benchmarks/trade_study.py --presets --backend cuda --out "$out/quality-presets-cuda.json"
fi
if [[ " $steps " == *" empty "* ]]; then
    echo "== empty space, CUDA"; python3 benchmarks/bench_empty_space.py --backend cuda --grid 128 --photons 2.1e7 --out "$out/empty-space-cuda.json"
fi
if [[ " $steps " == *" fft "* ]]; then
    echo "== collision filter FFT on NVIDIA OpenCL: host vs pyvkfft"
    python3 benchmarks/bench_fft.py --device NVIDIA --grid 64 128 --out "$out/fft-nvidia-opencl.json"
fi
if [[ " $steps " == *" scaling "* ]]; then
    echo "== scaling, CUDA"; python3 benchmarks/bench_scaling.py --backend cuda --out "$out/scaling-cuda.json"
fi
if [[ " $steps " == *" large "* ]]; then
    # 64^3..1024^3 x 1e7/1e8 photons, 1 band against pmcx and 3 bands (memory target), and the
    # atomic-add microbenchmark; each configuration in its own process. About 7 min on an H200
    # (355 s measured without n1024-p1e8-b3, which adds about 1 min: --skip n1024-p1e8-b3 drops it)
    echo "== large grids, CUDA vs pmcx, 1 and 3 bands, atomic adds"
    python3 benchmarks/bench_large_grids.py --bands 1 3 --out "$out/large-grids-cuda.json"
fi
if [[ " $steps " == *" regions "* ]]; then
    # the transport by regions: none, 32, 64 and 128 voxels a side, 1e8 photons (about 3 min)
    echo "== transport by regions, region size, CUDA"
    python3 benchmarks/bench_regions.py --backend cuda --grids 128 256 512 1024 --shifts 0 5 6 7 --photons 1e8 \
        --repeats 1 --tail 135168 --out "$out/regions-cuda.json"
fi
if [[ " $steps " == *" regcaps "* ]]; then
    # the transport kernel's register cap against occupancy, by regions at 512^3 and without at 128^3
    echo "== register caps, CUDA"
    python3 benchmarks/bench_regions.py --backend cuda --grids 128 --shifts 0 --regcaps ${REGCAPS:-0 96 80 72 64} \
        --photons 3e7 --repeats 2 --out "$out/regcaps-128-cuda.json"
    python3 benchmarks/bench_regions.py --backend cuda --grids 512 --shifts 6 --regcaps ${REGCAPS:-0 96 80 72 64} \
        --photons 1e8 --repeats 1 --tail 135168 --out "$out/regcaps-512-cuda.json"
fi
if [[ " $steps " == *" profile-regions "* ]] && command -v ncu >/dev/null; then
    # what limits a region pass: ncu on the 2nd and 6th trace_photons launches of 512^3 (the
    # first part's passes 2 and 6: packets spread over many regions), and on a 128^3 launch
    # without regions for comparison (L2 hit rate, atomics, warp activity, stalls)
    echo "== ncu: region passes, 512^3 neb medium, CUDA"
    for skip in 1 5; do
        ncu --target-processes all -k regex:trace_photons -s $skip -c 1 --section SpeedOfLight \
            --section MemoryWorkloadAnalysis --section WarpStateStats --section SchedulerStats --section Occupancy \
            python3 benchmarks/bench_regions.py --backend cuda --grids 512 --shifts 6 --photons 6e6 --repeats 1 --warmup 0 \
            2>&1 | grep -v "^==PROF==" | tail -n 90
    done
    echo "== ncu: 128^3 without regions, CUDA"
    ncu --target-processes all -k regex:trace_photons -s 0 -c 1 --section SpeedOfLight \
        --section MemoryWorkloadAnalysis --section WarpStateStats --section SchedulerStats --section Occupancy \
        python3 benchmarks/bench_regions.py --backend cuda --grids 128 --shifts 0 --photons 6e6 --repeats 1 --warmup 0 \
        2>&1 | grep -v "^==PROF==" | tail -n 90
fi
if [[ " $steps " == *" layout "* ]]; then
    echo "== memory layout, sorted packet order and transport physics, CUDA"
    NEBULA_RT_TEST_BACKEND=cuda python3 -m pytest -q -p no:cacheprovider tests/backends/test_memory_layout.py \
        tests/transport/test_transport_physics.py tests/backends/test_kernel_options.py -k "not every_option" 2>&1 | tail -n 4
fi
if [[ " $steps " == *" sorted "* ]]; then
    # packet order: plain, sorted by first direction in 256^2 bins, in 1024^2 bins (Morton order);
    # MCX once, in the same session
    i=0
    for tuning in "NRT_SORTED=0" "NRT_SORTED=1" "NRT_SORTED=1 NRT_SORT_BITS=10"; do
        echo "== large grids, 1e8 photons, $tuning"
        python3 benchmarks/bench_large_grids.py --grids 256 512 1024 --photons 1e8 --bands 1 --repeats 3 \
            --skip micro $([[ $i -gt 0 ]] && echo "mcx") --mcx-max-grid 512 \
            --tuning $tuning --out "$out/sorted-$i.json" 2>&1 | tail -n 8
        i=$((i + 1))
    done
fi
if [[ " $steps " == *" probe "* ]]; then
    # what the deposits and the density loads cost at 256^3 and 512^3 (kernel probes: the light
    # fields are wrong by design, the kernel times are what counts); MCX once, same session
    i=0
    for tuning in "NRT_SORTED=1" "NRT_SORTED=0" "NRT_PROBE_DEPOSIT=1" "NRT_PROBE_DEPOSIT=2" \
                  "NRT_PROBE_UNIFORM=1" "NRT_PROBE_DEPOSIT=1 NRT_PROBE_UNIFORM=1"; do
        echo "== probe, 1e8 photons, $tuning"
        python3 benchmarks/bench_large_grids.py --grids 256 512 --photons 1e8 --bands 1 --repeats 3 \
            --skip $([[ $i -gt 0 ]] && echo "mcx") micro --mcx-max-grid 512 \
            --tuning $tuning --out "$out/probe-$i.json" 2>&1 | grep -E "kernel|mcx|MCX" | tail -n 6
        i=$((i + 1))
    done
fi
if [[ " $steps " == *" ranks "* ]] || [[ " $steps " == *" ranks-thesis "* ]] || [[ " $steps " == *" ranks-weak "* ]]; then
    # several ranks, a GPU each (NCCL sums the slots on the GPUs); on fewer GPUs than ranks the
    # ranks share them: the code path (sums through the host), not scaling. NVLink multicast off.
    export NCCL_NVLS_ENABLE=0 TORCH_SYMM_MEM_DISABLE_MULTICAST=1 NVSHMEM_DISABLE_NVLS=1
    gpus=$(nvidia-smi -L | wc -l)
    ranks="1"; for r in 2 4 8; do [[ $r -le $gpus ]] && ranks="$ranks $r"; done
    [[ $gpus -lt 2 ]] && ranks="1 2"
    if ! command -v mpiexec >/dev/null; then
        echo "== ranks: no mpiexec on this machine"
    elif [[ " $steps " == *" ranks "* ]]; then
        # bit-identity and strong scaling, neb medium at 512^3 (about 5 min on 8 GPUs); then
        # the all-reduce through the host on all GPUs, for comparison
        big="1e9 1e10"; [[ $gpus -lt 2 ]] && big="1e8"
        echo "== ranks $ranks on $gpus GPU(s), CUDA, neb medium 512^3, photons $big"
        python3 benchmarks/bench_ranks.py --ranks $ranks --backend cuda --grid 512 --photons $big \
            --out "$out/ranks-neb512-strong.json" 2>&1 | tail -n 12
        echo "== ranks ${ranks##* }, all-reduce through the host"
        python3 benchmarks/bench_ranks.py --ranks ${ranks##* } --backend cuda --grid 512 --photons 1e9 --allreduce host \
            --out "$out/ranks-neb512-host.json" 2>&1 | tail -n 3
    fi
    if [[ " $steps " == *" ranks-thesis "* ]] && command -v mpiexec >/dev/null; then
        # the thesis scene at 512^3, 3 bands, end to end: bits of every output array, strong scaling
        echo "== ranks $ranks, thesis scene 512^3, 3 bands, 1e9 photons per band"
        python3 benchmarks/bench_ranks.py --ranks $ranks --backend cuda --scene thesis --grid 512 --photons 1e9 \
            --out "$out/ranks-thesis512-strong.json" 2>&1 | tail -n 6
    fi
    if [[ " $steps " == *" ranks-weak "* ]] && command -v mpiexec >/dev/null; then
        echo "== ranks $ranks, weak scaling: 1e9 photons per rank, neb medium 512^3"
        python3 benchmarks/bench_ranks.py --ranks $ranks --backend cuda --grid 512 --photons 1e9 --weak \
            --out "$out/ranks-neb512-weak.json" 2>&1 | tail -n 6
    fi
fi
if [[ " $steps " == *" biasing "* ]]; then
    echo "== analog vs biased transport, figure of merit over optical depth, CUDA"
    python3 benchmarks/bench_biasing.py --backend cuda --grid 64 --photons 1e7 --seeds 4 --forced-flights 1 2 4 8 \
        --taus 0.1 0.3 1 3 10 20 30 60 \
        --out "$out/biasing-cuda.json" --plot "$out/biasing-cuda.png" 2>&1 | tail -n 30
fi
if [[ " $steps " == *" fitprof "* ]]; then
    echo "== where a fit's trace spends its time, thesis 128^3, CUDA"
    python3 benchmarks/profile_fit_trace.py --backend cuda --shape 128 --photons 2.1e6 --out "$out/fit-trace-profile-cuda.json" 2>&1 | tail -n 45
fi
if [[ " $steps " == *" fit "* ]]; then
    echo "== fit of the thesis scene, 3 free parameters, CUDA (64^3, then the thesis's 128^3)"
    python3 benchmarks/bench_fit.py --backend cuda --out "$out/fit-cuda-64.json" 2>&1 | tail -n 14
    python3 benchmarks/bench_fit.py --backend cuda --shape 128 --photons 2.1e6 --out "$out/fit-cuda-128.json" 2>&1 | tail -n 14
fi
if [[ " $steps " == *" e2e1e9 "* ]]; then
    echo "== 512^3, 1e9 photons, end to end (target: 5 s), and the atomic adds beside it"
    python3 benchmarks/bench_large_grids.py --grids 512 --photons 1e9 --bands 1 --repeats 2 --repeat-below-s 100 --skip mcx \
        --out "$out/e2e-512-1e9.json" 2>&1 | tail -n 16
fi
if [[ " $steps " == *" binned "* ]]; then
    # binned deposits (the transport tuning) beside the walk, the probe of the method and pmcxcl
    echo "== binned deposits: CUDA tests"
    NEBULA_RT_TEST_BACKEND=cuda python3 -m pytest -q -p no:cacheprovider tests/transport/test_binned_deposits.py 2>&1 | tail -n 3
    echo "== the walk and pmcxcl"
    python3 benchmarks/bench_mcx.py --backend cuda --codes nebula pmcxcl --media uniform turbulent --grids 64 128 256 512 \
        --photons 2.1e7 --out "$out/mcx-walk.json" | grep -v saved
    echo "== binned deposits"
    python3 benchmarks/bench_mcx.py --backend cuda --codes nebula --media uniform turbulent --grids 64 128 256 512 \
        --photons 2.1e7 --tuning binned_deposits=1 --out "$out/mcx-binned.json" | grep -v saved
    echo "== binned deposits, majorants on 4^3 cells"
    python3 benchmarks/bench_mcx.py --backend cuda --codes nebula --media uniform turbulent --grids 64 128 256 512 \
        --photons 2.1e7 --tuning binned_deposits=1 binned_majorant=4 --out "$out/mcx-binned-maj4.json" | grep -v saved
    echo "== the probe"
    python3 benchmarks/probe_binned_deposits.py --backend cuda --media uniform turbulent --grids 64 128 256 512 --blocks 16 \
        --photons 2.1e7 --modes binned --out "$out/probe.json" | grep grid
    echo "== 512^3 x 1e9, binned deposits"
    python3 benchmarks/bench_large_grids.py --grids 512 --photons 1e9 --bands 1 --repeats 1 --skip mcx micro \
        --tuning binned_deposits=1 --out "$out/e2e-512-1e9-binned.json" 2>&1 | tail -n 4
fi
if [[ " $steps " == *" compare "* ]]; then
    echo "== same seed on CUDA and NVIDIA OpenCL"
    python3 benchmarks/compare_backends.py --run cuda: --run opencl:NVIDIA --save-dir "$out" --out "$out/compare.json" | grep -E '"(a|b|max_count|median|z_std)'
    echo "== same seed on CUDA and NVIDIA OpenCL, biased transport"
    python3 benchmarks/compare_backends.py --run cuda: --run opencl:NVIDIA --set 'transport.method="biased"' \
        --save-dir "$out" --out "$out/compare-biased.json" | grep -E '"(a|b|max_count|median|z_std)'
fi
if [[ " $steps " == *" mcx "* ]]; then
    # NebulaRT, pmcx and pmcxcl (NVIDIA OpenCL) on the uniform and the lognormal medium, each
    # configuration in its own process (about 8 min on an H200; MCX_GRIDS / MCX_PHOTONS narrow it;
    # MCX_TUNING="NRT_GROUP_TALLY=0 ..." sets NebulaRT's kernel options, MCX_TAG names the file)
    echo "== beside MCX and MCX-CL: uniform and turbulent media"
    python3 benchmarks/bench_mcx.py --backend cuda --grids ${MCX_GRIDS:-64 128 256 512} --photons ${MCX_PHOTONS:-1e7 1e8} \
        --repeats 3 ${MCX_TUNING:+--tuning $MCX_TUNING} --out "$out/mcx-cuda${MCX_TAG:-}.json"
fi
if [[ " $steps " == *" mcx1024 "* ]]; then
    echo "== beside MCX and MCX-CL at 1024^3"
    # (pmcxcl returned nothing within 7 minutes at 1024^3 on an H200: each configuration gets
    # 200 s, so that the turbulent medium's runs follow)
    python3 benchmarks/bench_mcx.py --backend cuda --grids 1024 --photons 1e8 --repeats 1 --timeout 200 \
        --out "$out/mcx-cuda-1024.json"
fi
if [[ " $steps " == *" kernel-probes "* ]]; then
    # where the thesis headline's kernel time goes: the probes of kernels/transport.cl (no
    # deposits, 32-bit deposits, no density traffic, no deposits near the star) and register
    # caps, on the thesis scene at 128^3 and the neb medium at 128^3 and 256^3
    hot="NRT_PROBE_HOT_X=64 NRT_PROBE_HOT_Y=64 NRT_PROBE_HOT_Z=64"
    echo "== transport kernel probes, thesis 128^3, CUDA"
    python3 benchmarks/profile_kernels.py --scene examples/scenes/thesis-default.toml --grids 128 --photons 2.1e6 \
        --tuning "" "NRT_PROBE_DEPOSIT=1" "NRT_PROBE_DEPOSIT=2" "NRT_PROBE_UNIFORM=1" "NRT_PROBE_DEPOSIT=1 NRT_PROBE_UNIFORM=1" \
        "NRT_PROBE_HOT_HALF=-1 $hot" "NRT_PROBE_HOT_HALF=1 $hot" "NRT_PROBE_HOT_HALF=3 $hot" "NRT_PROBE_HOT_HALF=8 $hot" \
        "NRT_GROUP_TALLY=0" "max_registers=64" "max_registers=96" "max_registers=0" \
        "NRT_HOT_HALF=0" "NRT_HOT_HALF=1" "NRT_HOT_HALF=3" "NRT_HOT_HALF=4" --out "$out/thesis-probes.json" 2>&1 | grep -v Warning
    python3 benchmarks/profile_kernels.py --scene examples/scenes/thesis-default.toml --grids 128 --photons 2.1e6 \
        --free-running --out "$out/thesis-free-running.json" 2>&1 | tail -n 2
    # 4x the packets in one launch: what does not grow with them (the launch's tail) shows
    python3 benchmarks/profile_kernels.py --scene examples/scenes/thesis-default.toml --grids 128 --photons 8.4e6 \
        --out "$out/thesis-probes-8.4e6.json" 2>&1 | grep -v Warning
    echo "== transport kernel probes, neb medium, CUDA"
    python3 benchmarks/profile_kernels.py --grids 64 128 --photons 2.1e7 --tuning "" "NRT_PROBE_DEPOSIT=1" \
        "NRT_HOT_HALF=0" "NRT_HOT_HALF=1" "NRT_HOT_HALF=3" --out "$out/neb-probes.json" 2>&1 | grep -v Warning
fi
if [[ " $steps " == *" stages-former "* ]]; then
    # the stage profile as built and with the former commit's python/ (its kernels as
    # nebula_rt/kernels) in .former/, in turn on the same GPU
    for v in "" former "" former; do
        echo "== stage profile, thesis 128^3, CUDA, ${v:-as built}"
        PYTHONPATH=${v:+.former/python:}$PYTHONPATH python3 benchmarks/profile_stages.py 2>&1 \
            | grep -E "^run |^   [a-z]|^fixed cost" | grep -v "^   ncalls"
    done
fi
if [[ " $steps " == *" density "* ]]; then
    # the density kernel alone, the noise's tables in constant memory and where each backend
    # reads them now (CUDA: global memory; OpenCL: each group's local copy)
    echo "== density kernel, thesis turbulence, CUDA"; python3 benchmarks/profile_density.py --out "$out/density-cuda.json"
    echo "== density kernel, thesis turbulence, NVIDIA OpenCL"
    python3 benchmarks/profile_density.py --backend opencl --device NVIDIA --out "$out/density-opencl.json"
fi
if [[ " $steps " == *" headline "* ]]; then
    # the thesis headline end to end, repeated: as built with the light made while the
    # transport folds and after it (interleaved in one process), and the former commit's
    # python/ and kernels (.former/, see stages-former), each twice in turn
    for i in 1 2; do
        for v in "" former; do
            echo "== headline end to end, thesis 128^3, CUDA, ${v:-as built}"
            PYTHONPATH=${v:+.former/python:}$PYTHONPATH python3 benchmarks/bench_headline.py --backend cuda \
                --label "${v:-as built}" ${v:+--modes while} --out "$out/headline-${v:-built}-$i.json" 2>&1 | grep -v Warning
        done
    done
fi
if [[ " $steps " == *" timeline-former "* ]]; then
    # the headline's calls as issued, as built and with .former/ (see stages-former), in turn
    for v in "" former "" former; do
        echo "== timeline, thesis 128^3, CUDA, ${v:-as built}"
        PYTHONPATH=${v:+.former/python:}$PYTHONPATH python3 benchmarks/profile_timeline.py --backend cuda \
            --list 16 --out "$out/timeline-${v:-built}.json" 2>&1 | sed -n '/^== as_issued/,/^== serialised/p'
    done
fi
if [[ " $steps " == *" small-regions "* ]]; then
    # regions of 8-64 voxels at 128^3 and 256^3 as a compaction of the walks: a pass stops each
    # packet at a region face and the next pass's warps hold only packets still walking (one
    # packet per work item leaves about half of a warp's lanes idle); state memory for every
    # packet of the launch, so that no packet waits for a slot
    big="region_state_bytes=805306368"
    echo "== small regions, thesis 128^3, CUDA"
    python3 benchmarks/profile_kernels.py --scene examples/scenes/thesis-default.toml --grids 128 --photons 2.1e6 \
        --free-running --tuning "" "NRT_REGIONS=4 region_tail=4096 $big" "NRT_REGIONS=5 region_tail=4096 $big" \
        --out "$out/small-regions-thesis.json" 2>&1 | grep -v Warning
    echo "== small regions, neb medium, CUDA"
    python3 benchmarks/profile_kernels.py --grids 128 256 --photons 2.1e7 --free-running \
        --tuning "" "NRT_REGIONS=4 region_tail=4096 $big" "NRT_REGIONS=5 region_tail=4096 $big" \
        --out "$out/small-regions-neb.json" 2>&1 | grep -v Warning
fi
if [[ " $steps " == *" polarization-ocl "* ]]; then
    echo "== cost of polarization, NVIDIA OpenCL"
    python3 benchmarks/bench_polarization.py --backend opencl --device NVIDIA --grid 128 --photons 2.1e7 \
        --out "$out/polarization-nvidia-opencl.json"
fi
if [[ " $steps " == *" polarization "* ]]; then
    # polarized packets (bands.polarization): their tests on CUDA and NVIDIA OpenCL, their cost
    # against intensity alone, and the unpolarized kernel against the former commit's (a copy of
    # its python/ in .former/) on the neb medium and the thesis scene
    pol_tests="tests/optics/test_polarized_scattering.py tests/optics/test_mie.py tests/transport/test_polarized_transport.py tests/backends/test_kernel_options.py"
    echo "== polarization tests, CUDA"; NEBULA_RT_TEST_BACKEND=cuda python3 -m pytest -q -p no:cacheprovider $pol_tests 2>&1 | tail -n 4
    echo "== polarization tests, NVIDIA OpenCL"; NEBULA_RT_TEST_DEVICE=NVIDIA python3 -m pytest -q -p no:cacheprovider $pol_tests 2>&1 | tail -n 4
    echo "== cost of polarization, CUDA"
    python3 benchmarks/bench_polarization.py --backend cuda --grid 64 128 256 --photons 2.1e7 --out "$out/polarization-cuda.json"
    echo "== cost of polarization, weighted packets, CUDA"
    python3 benchmarks/bench_polarization.py --backend cuda --grid 128 --photons 2.1e7 --methods biased \
        --out "$out/polarization-biased-cuda.json"
    echo "== cost of polarization, 512^3 (by regions), CUDA"
    python3 benchmarks/bench_polarization.py --backend cuda --grid 512 --photons 1e8 --repeat 2 \
        --out "$out/polarization-512-cuda.json"
    echo "== cost of polarization, NVIDIA OpenCL"
    python3 benchmarks/bench_polarization.py --backend opencl --device NVIDIA --grid 128 --photons 2.1e7 \
        --out "$out/polarization-nvidia-opencl.json"
    if [[ -d .former/python ]]; then
        for v in "" former; do
            echo "== unpolarized kernel ${v:-as built}: thesis 128^3 and the neb medium, CUDA"
            pp=${v:+.former/python:}
            PYTHONPATH=$pp$PYTHONPATH python3 benchmarks/profile_kernels.py --scene examples/scenes/thesis-default.toml \
                --grids 128 --photons 2.1e6 --out "$out/thesis-${v:-built}.json" 2>&1 | grep -v Warning
            PYTHONPATH=$pp$PYTHONPATH python3 benchmarks/profile_kernels.py --grids 64 128 256 --photons 2.1e7 \
                --out "$out/neb-${v:-built}.json" 2>&1 | grep -v Warning
        done
    fi
fi
if [[ " $steps " == *" tree "* ]]; then
    # the transport on octrees made from the thesis density against that grid, CUDA and NVIDIA OpenCL
    echo "== trees against their grid, CUDA"
    python3 benchmarks/bench_tree.py --backend cuda --grid 128 --photons 2.1e6 --out "$out/tree-128-cuda.json" 2>&1 | grep -v Warning
    python3 benchmarks/bench_tree.py --backend cuda --grid 256 --photons 1e7 --roots 16 --tolerances 0 0.2 1 \
        --out "$out/tree-256-cuda.json" 2>&1 | grep -v Warning
    echo "== trees against their grid, NVIDIA OpenCL"
    python3 benchmarks/bench_tree.py --backend opencl --device NVIDIA --grid 128 --photons 2.1e6 \
        --out "$out/tree-128-nvidia-opencl.json" 2>&1 | grep -v Warning
fi
if [[ " $steps " == *" tree-targets "* ]]; then
    # #33's targets: the thesis's turbulence on an octree of 2^10 effective resolution where the
    # dust is dense (<= 50M leaves) against the uniform 512^3 (speed) and 1024^3 (the light) grids
    echo "== tree targets, CUDA"
    python3 benchmarks/bench_tree_targets.py --backend cuda --depth ${TREE_DEPTH:-10} --photons ${TREE_PHOTONS:-1e8} \
        --out "$out/tree-targets-cuda.json" 2>&1 | grep -v Warning
fi
if [[ " $steps " == *" tree-ascend "* ]]; then
    # the tree walk's next leaf from the root grid (NRT_TREE_ASCEND=0) or from the lowest shared
    # ancestor (1), side by side: trees of the thesis density at 128^3, and the 2^10 target tree
    for a in 0 1; do
        echo "== trees against their grid, CUDA, NRT_TREE_ASCEND=$a"
        python3 benchmarks/bench_tree.py --backend cuda --grid 128 --photons 2.1e6 --tuning NRT_TREE_ASCEND=$a \
            --out "$out/tree-128-cuda-ascend$a.json" 2>&1 | grep -v Warning
    done
    for a in 0 1; do
        echo "== tree targets (no 1024^3 grid), CUDA, NRT_TREE_ASCEND=$a"
        python3 benchmarks/bench_tree_targets.py --backend cuda --depth 10 --photons 1e8 --skip-fine-grid \
            --tuning NRT_TREE_ASCEND=$a --out "$out/tree-targets-cuda-ascend$a.json" 2>&1 | grep -v Warning
    done
fi
if [[ " $steps " == *" ncu-thesis "* ]] && command -v ncu >/dev/null; then
    echo "== ncu: transport kernel, thesis 128^3 (its first launch)"
    ncu --target-processes all -k regex:trace_photons -s 0 -c 1 --section SpeedOfLight --section Occupancy \
        --section LaunchStats --section MemoryWorkloadAnalysis --section WarpStateStats --section SchedulerStats \
        --section SourceCounters --section ComputeWorkloadAnalysis --section InstructionStats \
        python3 benchmarks/profile_kernels.py --scene examples/scenes/thesis-default.toml --grids 128 --photons 2.1e6 \
        --tuning "${NCU_TUNING:-}" > "$out/ncu-thesis${NCU_TUNING:+-${NCU_TUNING// /-}}.txt" 2>&1
    grep -v "^==PROF==" "$out/ncu-thesis${NCU_TUNING:+-${NCU_TUNING// /-}}.txt" | tail -n 150
fi
if [[ " $steps " == *" ncu-source "* ]] && command -v ncu >/dev/null; then
    # where the thesis kernel's instructions and stalls go, per SASS line (built with -lineinfo)
    echo "== ncu source counters: transport kernel, thesis 128^3 (its first launch)"
    ncu --target-processes all -k regex:trace_photons -s 0 -c 1 --section SourceCounters --section WarpStateStats \
        --import-source yes -f -o "$out/ncu-source" \
        python3 benchmarks/profile_kernels.py --scene examples/scenes/thesis-default.toml --grids 128 --photons 2.1e6 \
        --lineinfo > "$out/ncu-source.log" 2>&1
    ncu --import "$out/ncu-source.ncu-rep" --page source --csv --print-source sass > "$out/ncu-sass.csv" 2>"$out/ncu-sass.err"
    python3 benchmarks/ncu_source_summary.py "$out/ncu-sass.csv" --top 40 --out "$out/ncu-source-summary.json"
fi
if [[ " $steps " == *" profile "* ]] && command -v ncu >/dev/null; then
    echo "== ncu: transport kernel, neb128 2.1M photons (one batch)"
    ncu --target-processes all -k regex:trace_photons -s 1 -c 1 --section SpeedOfLight --section Occupancy \
        --section LaunchStats --section MemoryWorkloadAnalysis --section WarpStateStats \
        python3 benchmarks/bench_neb128.py --backend cuda --photons 2.1e6 --mcx none 2>&1 | grep -v "^==PROF==" | tail -n 120
fi
