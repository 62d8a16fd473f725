"""How the transport by regions is sized: the packets in flight a launch may hold
(:func:`region_capacity`), the region size of a grid (:func:`region_shift_for`) and the
counting sorts' bins, from the device's memory and the measurements noted beside each."""

from __future__ import annotations

import numpy as np

from . import kernel_params
from .transport_setup import TransportSetup

#: region shift that never stops a packet (kernels/transport.cl, NRT_NO_REGIONS)
NO_REGIONS = 31
#: device memory for the packets in flight of the transport by regions (64 B of state, two
#: 8 B keys and one 8 B emission key per packet), at most REGION_STATE_BYTES and
#: REGION_STATE_PER_VOXEL per voxel (within the memory target of 2 x (density + one 64-bit
#: cell per band) + 1 GiB at 256^3 and beyond): a launch of more packets starts new ones as
#: the earlier ones end. On an H200 at 512^3, 128 MiB of state traced 60k packets/ms, 512 MiB
#: 74k (then traced in parts, each ending in a few poorly filled passes); with 1e9 photons
#: (batches of 62.5M that fill it) 512 MiB / 768 MiB / 1 GiB took 9.77 / 9.30 / 9.20 s of
#: kernel time (peaks 3.50 / 3.75 / 4.00 GiB: 1 GiB reaches the 4 GiB memory target)
REGION_STATE_BYTES = 768 << 20
REGION_STATE_PER_VOXEL = 24
#: passes after which a launch's remaining packets are traced to the end in one
MAX_REGION_PASSES = 256
#: the counting sort's bins counted in a work group's local memory (kernels/transport.cl,
#: NRT_LOCAL_BINS); more bins count key by key in global memory, which at 1024^3 by regions
#: of 64 voxels (4097 bins, then past 4096 local ones) lost 23.2k -> 19.0k packets/ms
LOCAL_SORT_BINS = 8192
#: most bins of the emission order's counting sort (NRT_SORTED; tuning key "emission_bins"):
#: the cells and stars of a launch times as many leading direction bins as fit (all 16 bits
#: of one cell and star). On an H200, 2^16 bins against 4096 (12 bits): 512^3 1e8 102.5k /
#: 101.2k, 1024^3 1e7 (packets) 28.7k / 27.8k packets/ms, although more bins than the local
#: ones (NRT_LOCAL_BINS) count one key at a time. A radix sort of the full 64-bit keys took
#: 1.4 ms per chunk of 6.1M packets (0.045 s of 512^3 with 1e8 photons)
EMISSION_MAX_BINS = 1 << 16


def region_shift_of(backend, setup: TransportSetup, tuning: dict) -> int:
    """Side of the regions (as log2 voxels) of the transport by regions, 0 for none: the
    tuning's ``NRT_REGIONS`` where given, else the backend's ``region_shifts`` entry for the
    grid's size ((least voxels, shift) pairs, ascending; none: never). Weighted packets walk
    whole rays for the forced flights and have no region path; nor has a tree's walk."""
    if setup.tree is not None:
        return 0
    return region_shift_for(backend, int(np.prod(setup.density.shape)), setup.biased, tuning)


def packet_state_bytes(polar: bool = False) -> int:
    """Device bytes of one stopped packet's state (nrt_packet, and a polarized packet's Stokes
    state beside it) and keys in the transport by regions."""
    return kernel_params.dtype("nrt_packet").itemsize + REGION_KEY_BYTES + (
        kernel_params.STOKES_STATE_BYTES if polar else 0)


def region_state_bytes(nvox: int, tuning: dict | None = None, polar: bool = False) -> int:
    """Device bytes of the stopped packets' states and keys of the transport by regions."""
    budget = int((tuning or {}).get("region_state_bytes", min(REGION_STATE_BYTES, REGION_STATE_PER_VOXEL * nvox)))
    per = packet_state_bytes(polar)
    return max(1024, budget // per) * per


def region_capacity(backend, nvox: int, biased: bool = False, polar: bool = False) -> int:
    """Packets the transport by regions keeps in flight on a grid of ``nvox`` voxels (0: the
    backend traces this grid without regions)."""
    tuning = backend.transport_tuning
    if not region_shift_for(backend, nvox, biased, tuning):
        return 0
    return region_state_bytes(nvox, tuning, polar) // packet_state_bytes(polar)


#: bytes of keys per packet in flight of the transport by regions: what a pass stopped, the
#: next pass's packets sorted by bin, and the chunk's emission order
REGION_KEY_BYTES = 24


def region_shift_for(backend, nvox: int, biased: bool, tuning: dict | None = None) -> int:
    """:func:`region_shift_of` from the grid's voxel count (for the memory estimate)."""
    tuning = backend.transport_tuning if tuning is None else tuning
    if biased:
        return 0
    if "NRT_REGIONS" in tuning:
        return int(tuning["NRT_REGIONS"])
    shift = 0
    for least, s in getattr(backend, "region_shifts", ()):  # (from voxels, shift), ascending
        shift = int(s) if nvox >= int(least) else shift
    return shift
