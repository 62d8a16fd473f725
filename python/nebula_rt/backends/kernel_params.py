"""Parameter structs shared by the kernels and the host: one definition, three languages.

The transport kernel reads a run's constants (grid, seed, batch plan, fixed-point scales,
peel-off camera) from one struct in device memory, and what changes from launch to launch
(photon range, bands, the pass of a run by regions) from a second struct passed by value,
instead of two dozen positional arguments.
The fields are declared here once; :func:`c_struct` writes the C typedef that
:mod:`nebula_rt.backends.kernel_source` pastes into every kernel program (OpenCL C and CUDA C), and
:func:`dtype` the NumPy structured dtype the host fills and uploads. Fields are ordered by
size (8-byte, then 4-byte) and the struct is padded to a multiple of 8 bytes, so the C layout
needs no compiler-specific packing and NumPy's aligned layout is the same; the
``nrt_params_layout`` kernel reports the device's offsets, which a test compares with the
dtype's.
"""

from __future__ import annotations

import functools

import numpy as np

from ..optics.mie import GUIDE_CELLS

_TYPES = {"u64": ("nrt_u64", np.uint64), "i32": ("int", np.int32), "f32": ("float", np.float32)}

#: nrt_trace_params: the constants of one transport run (fields: name, type, count, meaning)
TRACE_PARAMS = (
    ("seed", "u64", 1, "Philox key word 0"),
    ("batch_base", "u64", 1, "packets per batch (the first batch_extra batches hold one more)"),
    ("batch_extra", "u64", 1, "batches holding batch_base + 1 packets"),
    ("cells", "u64", 1, "cells per band of a batch slot: the grid's voxels, or a tree's leaves (NRT_TREE)"),
    ("image_stokes", "u64", 1, "NRT_POLAR: where the Q and U images start in the image buffer, after every "
                               "cell's intensity image (words)"),
    ("state_slots", "u64", 1, "NRT_REGIONS: the state slots; with NRT_POLAR the slots' Stokes states (6 floats "
                              "each) follow them in the same buffer"),
    ("nx", "i32", 1, "grid size along x (voxels)"),
    ("ny", "i32", 1, "grid size along y"),
    ("nz", "i32", 1, "grid size along z"),
    ("n_bands", "i32", 1, "bands of the run"),
    ("n_stars", "i32", 1, "stars"),
    ("max_scatterings", "i32", 1, "a packet is terminated past this many scatterings"),
    ("window_shape", "i32", 3, "NRT_BIASED: cells of the weight windows' depth map along x, y, z"),
    ("sq_shift", "i32", 1, "NRT_PACKET_SQ: squares are added in units of 2^sq_shift (square) track units"),
    ("track_scale", "f32", 1, "fixed-point track units per box unit of path"),
    ("peel_scale", "f32", 1, "fixed-point peel-off units per 1/sr"),
    ("collision_scale", "f32", 1, "fixed-point units per collision of a packet of weight 1"),
    ("peel", "f32", 15, "peel-off camera: direction to the observer, u, v, centre of pixel (0, 0), "
                        "pixel size, W, H (box units)"),
)

#: nrt_packet: a packet suspended where it crosses into another region of the grid
#: (transport by regions, kernels/transport.cl): everything its walk needs to go on with the
#: same bits (1 / d and the face distances are formed again from these, by the walk's own
#: expressions). Its state slot is in the key that points to it.
PACKET_STATE = (
    ("p0", "f32", 3, "start point of the current flight (box units)"),
    ("d", "f32", 3, "direction (unit vector)"),
    ("t_cur", "f32", 1, "distance from p0 to the current voxel's entry"),
    ("tau", "f32", 1, "optical depth left of the current flight"),
    ("ix", "i32", 1, "current voxel along x"),
    ("iy", "i32", 1, "current voxel along y"),
    ("iz", "i32", 1, "current voxel along z"),
    ("scatterings", "i32", 1, "scatterings so far"),
    ("rng_block", "i32", 1, "Philox blocks drawn so far"),
    ("rng_pos", "i32", 1, "next 32-bit word of the current block (8: none left)"),
    ("item", "u64", 1, "the packet: its photon number | its band of the launch << 56"),
    ("peel_score", "u64", 1, "NRT_PEEL: the packet's peel-off units so far (the heavy-tail diagnostic)"),
)

#: nrt_launch: what changes from one launch of the transport kernels to the next, passed by
#: value (kernels/transport.cl: trace_photons, emission_keys); the run's constants stay in
#: nrt_trace_params in device memory
LAUNCH = (
    ("photon_start", "u64", 1, "first photon number of the launch (or of the chunk, by regions)"),
    ("count", "u64", 1, "photons per band of the launch (of the chunk)"),
    ("first_batch", "u64", 1, "batch of slot 0"),
    ("n_resume", "u64", 1, "NRT_REGIONS: stopped packets to go on with"),
    ("n_fresh", "u64", 1, "NRT_REGIONS: new packets of the chunk in this pass"),
    ("fresh0", "u64", 1, "NRT_REGIONS: the chunk's item of the first new packet"),
    ("n_free", "u64", 1, "NRT_REGIONS: free state slots listed after the stopped keys"),
    ("hwm", "u64", 1, "NRT_REGIONS: state slots from here on are unused"),
    ("band0", "i32", 1, "first band of the launch"),
    ("n_lbands", "i32", 1, "bands of the launch"),
    ("region_shift", "i32", 1, "NRT_REGIONS: packets stop at faces of regions of 2^region_shift voxels"),
    ("slots", "i32", 1, "batch slots of the launch"),
)

STRUCTS = {"nrt_trace_params": TRACE_PARAMS, "nrt_packet": PACKET_STATE, "nrt_launch": LAUNCH}
#: bytes of a polarized packet's Stokes state beside its nrt_packet in the transport by regions
#: (q, u, v and the reference direction: kernels/polarization.cl, nrt_stokes)
STOKES_STATE_BYTES = 24

#: Constants the kernels and the host share, pasted into the kernel sources as #defines.
CONSTANTS = (
    ("NRT_TAIL_BINS", 256, "bins of a heavy-tail histogram: half-octaves of a 128-bit score "
                           "(nebula_rt.transport.tails)"),
    ("NRT_TALLY_ANALOG", 4, "64-bit words of an analog tally block's counts (emitted, absorbed, "
                            "escaped, terminated)"),
    ("NRT_TALLY_WEIGHTED", 10, "64-bit words of a weighted tally block's five 128-bit weight sums "
                               "(and the biasing)"),
    ("NRT_MIE_GUIDE", GUIDE_CELLS, "cells of a Mie table's guide table (kernels/polarization.cl, nrt_mie_mu; "
                                   "nebula_rt.optics.mie.guide_table)"),
)
CONSTANT = {name: value for name, value, _ in CONSTANTS}


@functools.lru_cache(maxsize=None)
def dtype(name: str = "nrt_trace_params") -> np.dtype:
    """The NumPy structured dtype of struct ``name`` (C layout, padded to 8 bytes)."""
    fields = STRUCTS[name]
    dt = np.dtype([(f, _TYPES[t][1], (n,)) if n > 1 else (f, _TYPES[t][1]) for f, t, n, _ in fields],
                  align=True)
    size = -(-dt.itemsize // 8) * 8
    return np.dtype({"names": dt.names, "formats": [dt.fields[n][0] for n in dt.names],
                     "offsets": [dt.fields[n][1] for n in dt.names], "itemsize": size})


def c_struct(name: str) -> str:
    """C typedef of struct ``name`` (valid OpenCL C and CUDA C), with the padding explicit."""
    dt = dtype(name)
    lines = ["typedef struct {"]
    end = 0
    for field, t, n, meaning in STRUCTS[name]:
        lines.append(f"    {_TYPES[t][0]} {field}{f'[{n}]' if n > 1 else ''}; /* {meaning} */")
        end = dt.fields[field][1] + dt.fields[field][0].itemsize
    if dt.itemsize > end:
        lines.append(f"    nrt_u32 pad_[{(dt.itemsize - end) // 4}];")
    lines.append(f"}} {name};")
    return "\n".join(lines)


def layout_kernel(name: str) -> str:
    """OpenCL/CUDA C of a kernel ``<name>_layout(p, out)`` writing sizeof and every field's
    offset (bytes) into ``out``: how the device laid the struct out, for the layout test."""
    body = [f"    out[0] = (nrt_u64)sizeof({name});"]
    for i, (field, _t, _n, _m) in enumerate(STRUCTS[name]):
        body.append(f"    out[{i + 1}] = (nrt_u64)((const NRT_GLOBAL char *)&p->{field} - (const NRT_GLOBAL char *)p);")
    return (f"NRT_KERNEL void {name}_layout(const NRT_GLOBAL {name} *p, NRT_GLOBAL nrt_u64 *out)\n{{\n"
            + "\n".join(body) + "\n}")


#: the structs the kernels take by value (the others live in device memory)
BY_VALUE = ("nrt_launch",)


def echo_kernel(name: str) -> str:
    """OpenCL/CUDA C of a kernel ``<name>_echo(v, out)`` copying a struct ``name`` passed by
    value into ``out``: the bytes the kernel received, for the by-value test."""
    return (f"NRT_KERNEL void {name}_echo(const {name} v, NRT_GLOBAL {name} *out)\n{{\n"
            "    *out = v;\n}")


def test_kernels() -> str:
    """The layout kernels of every struct and the echo kernels of those passed by value."""
    return "\n\n".join([layout_kernel(n) for n in STRUCTS] + [echo_kernel(n) for n in BY_VALUE])


def all_structs() -> str:
    """The C text of every shared constant and struct, for the kernel sources."""
    consts = "\n".join(f"#define {name} {value} /* {meaning} */" for name, value, meaning in CONSTANTS)
    return consts + "\n\n" + "\n\n".join(c_struct(n) for n in STRUCTS)


def pack(name: str = "nrt_trace_params", **values) -> np.ndarray:
    """One struct ``name`` as a (1,) structured array with ``values`` filled in; every field
    must be given. Its element (``pack(...)[0]``) is the by-value kernel argument on both
    backends (pyopencl and CuPy pass a structured scalar's bytes)."""
    dt = dtype(name)
    missing = set(dt.names) - set(values)
    extra = set(values) - set(dt.names)
    if missing or extra:
        raise TypeError(f"{name}: missing fields {sorted(missing)}, unknown fields {sorted(extra)}")
    out = np.zeros(1, dt)
    for k, v in values.items():
        out[k] = v
    return out
