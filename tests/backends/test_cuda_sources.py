"""The kernel sources compile as CUDA C (nvcc -ptx), so the CUDA path cannot rot unnoticed on
machines without a GPU. Runs wherever nvcc is installed (it is on the CI machines)."""

import shutil
import subprocess

import pytest

from nebula_rt.backends.kernel_source import kernel_source

NVCC = shutil.which("nvcc")

#: option sets of the transport kernel compiled beside the plain ones: the GPU default, the
#: walk by regions (polarized, with images and per-packet squares), the sorted emission,
#: weighted packets and the tree's walk
TRANSPORT_VARIANTS = [
    ["-DNRT_TRACK_LENGTH=1", "-DNRT_ACC_RED=1", "-DNRT_PREFETCH=1", "-DNRT_GROUP_TALLY=1", "-DNRT_IDX32=1"],
    ["-DNRT_TRACK_LENGTH=1", "-DNRT_GROUP_TALLY=1", "-DNRT_REGIONS=1", "-DNRT_POLAR=3", "-DNRT_PEEL=1",
     "-DNRT_PACKET_SQ=1"],
    ["-DNRT_COLLISION=1", "-DNRT_SORTED=1", "-DNRT_POLAR=1", "-DNRT_PEEL=1"],
    ["-DNRT_TRACK_LENGTH=1", "-DNRT_BIASED=1", "-DNRT_PEEL=1", "-DNRT_POLAR=2"],
    ["-DNRT_TRACK_LENGTH=1", "-DNRT_TREE=1", "-DNRT_PEEL=1"],
]


@pytest.mark.skipif(NVCC is None, reason="nvcc not installed: the CUDA compile check needs the CUDA toolkit")
@pytest.mark.parametrize("name,defines", [
    ("transport.cl", ["-DNRT_TRACK_LENGTH=1"]),
    ("transport.cl", ["-DNRT_COLLISION=1", "-DNRT_ACC_LIMIT_BITS=40"]),
    ("transport.cl", ["-DNRT_TRACK_LENGTH=1", "-DNRT_PEEL=1"]),
    *[("transport.cl", d) for d in TRANSPORT_VARIANTS],
    ("density.cl", []),
    ("density.cl", ["-DNRT_TABLES_CONSTANT=1"]),
    ("sampling.cl", []),
    ("postprocess.cl", []),
])
def test_kernel_compiles_as_cuda(tmp_path, name, defines):
    src = tmp_path / (name.replace(".cl", ".cu"))
    src.write_text(kernel_source(name))
    proc = subprocess.run([NVCC, "-ptx", "-arch=sm_80", "--std=c++14", *defines, "-o", str(tmp_path / "k.ptx"), str(src)],
                          capture_output=True, text=True, check=False)
    assert proc.returncode == 0, proc.stderr
    ptx = (tmp_path / "k.ptx").read_text()
    for kernel in {"transport.cl": ["trace_photons", "fold_batches"], "density.cl": ["generate_density", "significand_sums"],
                   "sampling.cl": ["philox_blocks", "hg_at"],
                   "postprocess.cl": ["finish_voxels", "key_histogram", "select_rank_bins",
                                      "key_histogram_low", "select_level", "bin_chunk_sums"]}[name]:
        assert f".entry {kernel}" in ptx
