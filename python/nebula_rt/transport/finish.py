"""Post-processing on the compute device: batch sums -> J, error, emissivity, rgba.

The transport leaves the running sums of the batch totals on the device. One kernel pass
(``kernels/postprocess.cl``, shared by the OpenCL and CUDA backends) turns them into the
float32 output arrays and the opacity, a radix select on the device picks the exposure
percentile, and a second pass writes the colour bytes; only the final arrays are copied back
(into page-locked memory on CUDA). The NumPy functions in :mod:`nebula_rt.transport` and
:mod:`nebula_rt.pipeline` are the reference this module is tested against.

Device layout: flat arrays, band-major, x fastest (the VTK point order); the host arrays
returned are (n_bands, nx, ny, nz) and (nx, ny, nz, 4) views of that layout, so writing them to
VTK needs no copy.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import numpy as np
from . import filtering
from ..array_api import array_module
from ..errors import CancelledError
from ..backends.session import M2_SCALE

#: Bins of one radix-select pass (16 bits of the float32 key) plus one for exact zeros.
_HI_BINS = 1 << 16
#: chunks of 256 bins of a pass (kernels/postprocess.cl, NRT_CHUNKS)
_CHUNKS = 256


@dataclass
class DeviceSums:
    """Transport sums left on the device.

    Attributes
    ----------
    backend : Backend
    shape : (nx, ny, nz)
    n_bands : int
    sum1 : device array, float64, n_bands * nx * ny * nz
        Sum of the batch totals (fixed-point track units or collision counts), band-major,
        x fastest.
    m2 : device array, float32, n_bands * nx * ny * nz
        Their centred sum of squares sum (x - mean)^2, stored times 2^-64
        (``session.M2_SCALE``).
    density : device array, float32, nx * ny * nz
    light : LightOutputs or None
        The light the transport made from these sums as its last fold ended (the relative
        error written over ``m2``): :func:`finish` takes it from there.
    """

    backend: object
    shape: tuple
    n_bands: int
    sum1: object
    m2: object
    density: object
    light: Optional["LightOutputs"] = None

    @property
    def nvox(self) -> int:
        return int(np.prod(self.shape))

    def host_sums(self):
        """(sum, centred sum of squares) as float64 (n_bands, nx, ny, nz) arrays of the
        backend's array module (CuPy on CUDA, NumPy copies otherwise)."""

        if self.sum1 is None:
            raise RuntimeError("the device sums were released by postprocess.finish(release=True)")
        if self.light is not None:
            raise RuntimeError("the device sums were turned into light while the transport folded them "
                               "(the relative error is where their squares were)")
        shape = (self.n_bands,) + tuple(self.shape[::-1])
        if type(self.sum1).__module__.startswith("cupy"):
            s1, m2 = self.sum1, self.m2.astype(self.sum1.dtype) * M2_SCALE
        else:
            s1 = self.backend.to_host(self.sum1)
            m2 = self.backend.to_host(self.m2).astype(np.float64) * M2_SCALE
        return tuple(a.reshape(shape).transpose(0, 3, 2, 1) for a in (s1, m2))


@dataclass
class ColourSetup:
    """What the colour pass needs (see :func:`nebula_rt.pipeline.rgba_from_emissivity`)."""

    to_rgb: np.ndarray  # (3, n_bands)
    sigma_ref_scale: float  # extinction per box unit at density 1, reference band
    voxel_edge: float  # geometric-mean voxel edge, box units
    opacity_scale: float
    exposure: object  # "auto" or float
    percentile: float
    min_alpha: float


@dataclass
class FinishedArrays:
    """Host arrays of the output contract."""

    J: np.ndarray  # float32 (nb, nx, ny, nz)
    rel_error: np.ndarray
    emissivity: np.ndarray
    rgba: Optional[np.ndarray]  # uint8 (nx, ny, nz, 4)
    exposure: float
    device_bytes: int = 0  # device memory the finishing allocated (outputs; colour only if asked)
    peak_device_bytes: int = 0  # the finishing's peak, with the sums and density it was handed


def _device_layout(xp, a):
    """(nb, nx, ny, nz) -> flat band-major, x fastest."""
    return xp.ascontiguousarray(a.transpose(0, 3, 2, 1)).reshape(-1)


def _band_params(band_params, batches) -> np.ndarray:
    """(n_bands, 4) float64: J scale, tau k_b, albedo, batches folded (int or per band)."""
    bp = np.asarray(band_params, np.float64)
    params = np.zeros((bp.shape[0], 4), np.float64)
    params[:, :3] = bp[:, :3]
    params[:, 3] = np.broadcast_to(np.asarray(batches, np.float64), (bp.shape[0],))
    return params


class LightOutputs:
    """J, its relative error and the emissivity of a run's device sums (float32 device arrays,
    ``light_cells`` of kernels/postprocess.cl), made by groups of bands in order, each group's
    copies to the host started as soon as it is made: so the transport can make the light as
    its last fold ends (:func:`nebula_rt.transport.run.run_transport`), and the copies
    overlap the host's work up to the colour pass instead of starting after it.

    ``release``: the relative error is written over the centred sums of squares ``m2`` (the
    sums are spent afterwards). ``light``: (J, rel_error) already computed (filtered), as
    :func:`finish` takes it. ``params``: (n_bands, 4) of :func:`_band_params`, or None to give
    each band's row to :meth:`bands`. ``emissivity_now`` False: the emissivity is made by
    :meth:`emissivity` once the caller has freed the sums (the device peak of a large grid).
    """

    def __init__(self, be, s1, m2, density, shape, n_bands: int, *, collision: bool, release: bool,
                 light=None, params=None, emissivity_now: bool = True):
        self.backend, self.shape, self.n_bands, self.collision = be, tuple(shape), int(n_bands), bool(collision)
        nx, ny, nz = self.shape
        self.nvox = nx * ny * nz
        n = self.n_bands * self.nvox
        self.params = np.zeros((self.n_bands, 4), np.float64) if params is None else np.asarray(params, np.float64)
        dummy64, dummy32 = be.device_zeros(1, np.float64), be.device_zeros(1, np.float32)
        self.J32 = be.device_zeros(n, np.float32)
        if light is None:
            self.mode, self.s1, self.m2, self.j64, self.r64 = 0, s1, m2, dummy64, dummy64
            self.rel32 = m2 if release else be.device_zeros(n, np.float32)
        else:
            self.mode, self.s1, self.m2 = 1, dummy64, dummy32
            if getattr(light[0], "ndim", 0) == 1:  # already in device layout
                self.j64, self.r64 = light[0], light[1]
            else:
                xp = array_module(light[0])
                self.j64 = _device_layout(xp, xp.asarray(light[0], dtype=xp.float64))
                self.r64 = _device_layout(xp, xp.asarray(light[1], dtype=xp.float64))
                if xp is np:
                    self.j64, self.r64 = be.to_device(self.j64), be.to_device(self.r64)
            self.rel32 = be.device_zeros(n, np.float32)
        self.own_rel = self.rel32 is not m2
        self.emis32 = be.device_zeros(n, np.float32) if emissivity_now else None
        self.density = density
        self.hosts = [be.host_empty((self.n_bands, nz, ny, nx), np.float32) for _ in range(3)]
        self.copies: list = []
        self.done = 0  # bands made so far (in order)
        self.d_params = None  # the parameters on the device, once uploaded

    def preset(self, params) -> None:
        """Set every band's parameters and upload them now (while the device traces)."""
        self.params[:] = params
        self.d_params = self.backend.to_device(self.params)

    @property
    def device_bytes(self) -> int:
        """Device memory of the outputs this made (J and the emissivity; the error's too
        unless it went over the squares)."""
        return sum(int(a.nbytes) for a in (self.J32, self.emis32, self.rel32 if self.own_rel else None)
                   if a is not None)

    def bands(self, b0: int, count: int, params=None) -> None:
        """Make bands ``b0 .. b0 + count - 1`` (the next ones; ``params``: their rows of the
        band parameters, where neither the constructor nor :meth:`preset` gave them) and
        start their copies."""
        if b0 != self.done or b0 + count > self.n_bands:
            raise ValueError(f"bands {b0}..{b0 + count - 1} out of order (made: {self.done} of {self.n_bands})")
        if params is not None:
            self.params[b0:b0 + count] = params
            self.d_params = None
        be, nvox = self.backend, self.nvox
        if self.d_params is None:
            self.d_params = be.to_device(self.params)
        d_params = self.d_params
        lo, hi = b0 * nvox, (b0 + count) * nvox
        emis = self.emis32 is not None
        be.launch("postprocess.cl", "light_cells", hi - lo, self.s1, self.m2, self.j64, self.r64, self.density,
                  d_params, np.uint64(nvox), np.uint64(lo), np.uint64(hi), np.int32(self.mode),
                  np.int32(self.collision), np.int32(emis), self.J32, self.rel32,
                  self.emis32 if emis else self.J32)
        # J, the error and the emissivity are final now: their copies overlap what follows
        for arr, h in zip((self.J32, self.rel32, self.emis32) if emis else (self.J32, self.rel32), self.hosts):
            self.copies.append(be.to_host_async(arr[lo:hi], h[b0:b0 + count].reshape(-1)))
        self.done = b0 + count

    def emissivity(self) -> None:
        """Make every band's emissivity from the float32 J (after :meth:`bands`, where the
        constructor deferred it) and start its copy."""
        if self.emis32 is not None:
            return
        be, n = self.backend, self.n_bands * self.nvox
        self.emis32 = be.device_zeros(n, np.float32)
        be.launch("postprocess.cl", "emissivity_cells", n, self.J32, self.density, self.d_params,
                  np.uint64(self.nvox), np.uint64(0), np.uint64(n), self.emis32)
        self.copies.append(be.to_host_async(self.emis32, self.hosts[2].reshape(-1)))

    def wait(self) -> list:
        """The host arrays (J, relative error, emissivity), (n_bands, nx, ny, nz), once their
        copies have arrived."""
        for handle in self.copies:
            self.backend.wait_copy(handle)
        self.copies = []
        return [h.transpose(0, 3, 2, 1) for h in self.hosts]

    def discard(self) -> None:
        """Wait for the copies under way (their host memory must outlive them) and drop them."""
        self.wait()
        self.hosts = []


def finish(ds: DeviceSums, band_params: np.ndarray, *, batches, collision: bool,
           light=None, colour: Optional[ColourSetup] = None, release: bool = False) -> FinishedArrays:
    """Turn device sums (or a filtered J and error) into the output arrays.

    Parameters
    ----------
    ds : DeviceSums
        With ``ds.light`` (a :class:`LightOutputs` the transport made as it folded), J, the
        error and the emissivity are taken from it; ``band_params`` and ``batches`` must then
        be the ones it was made with.
    band_params : ndarray (n_bands, 3)
        J scale, extinction per box unit at density 1 (tau k_b), albedo, per band.
    batches : int or ndarray (n_bands,)
        Batch totals folded (for the batch-means error), per band or for all.
    collision : bool
        The sums are collision counts (J = sum / sigma x scale), else track lengths.
    light : (J, rel_error), optional
        Already computed (e.g. filtered) J and relative error, used instead of the sums:
        (n_bands, nx, ny, nz) NumPy or CuPy arrays, or flat float64 device arrays in the device
        layout (from :func:`filter_collisions_opencl`).
    colour : ColourSetup, optional
        Also compute rgba (else ``rgba`` is None).
    release : bool
        The sums are not needed afterwards: the relative error is written over the centred
        sums of squares and the sums are freed before the emissivity and colour arrays are
        made, so the peak is the sums and J (20 B per cell) rather than the sums and every
        output (``ds`` is then spent).

    Memory (bytes per cell, n_b bands per voxel): the sums 12, J 4, relative error 4 (or the
    squares' memory), emissivity 4, and per voxel the density 4, the brightness key 4 and rgba 4.
    """
    be = ds.backend
    nb, nvox = ds.n_bands, ds.nvox
    n = nb * nvox
    params = _band_params(band_params, batches)
    outs = ds.light
    if outs is not None:
        done = outs.done
        if light is not None or outs.collision != bool(collision) or not np.array_equal(outs.params[:done],
                                                                                         params[:done]):
            raise ValueError("the transport made this light with other band parameters")
        if done < nb:
            outs.bands(done, nb - done, params[done:])
    else:
        outs = LightOutputs(be, ds.sum1, ds.m2, ds.density, ds.shape, nb, collision=collision, release=release,
                            light=light, params=params, emissivity_now=False)
        outs.bands(0, nb)
    c = colour
    d_params = outs.d_params  # (uploaded by outs.bands: the same parameters)
    d_rgb = be.to_device(np.ascontiguousarray(c.to_rgb, np.float64) if c else np.zeros(3 * nb))
    sums_bytes = 0 if ds.sum1 is None else 12 * n
    # (J and, made while the transport folded, the emissivity beside the sums)
    stage_a = (sums_bytes + 4 * nvox + (8 * n if ds.light is not None else 4 * n) + (4 * n if outs.own_rel else 0)
               + (16 * n if outs.mode == 1 else 0))
    del light
    outs.s1 = outs.m2 = outs.j64 = outs.r64 = None  # (read by light_cells only)
    if release or ds.light is not None:
        ds.sum1 = ds.m2 = None  # the float64 sums go before the outputs come
    ds.light = None
    outs.emissivity()
    J32 = outs.J32
    exposure = float("nan")
    h_rgba = d_exposure = None
    key = be.device_zeros(nvox if c else 1, np.float32)
    rgba = be.device_zeros(4 * nvox if c else 1, np.uint8)
    copies = []
    if c is not None:
        const = (np.float64(c.sigma_ref_scale), np.float64(c.voxel_edge), np.float64(c.opacity_scale))

        def run(pass_, exposure_at):
            be.launch("postprocess.cl", "finish_voxels", nvox, J32, ds.density, d_params, d_rgb,
                      np.int32(nb), np.uint64(nvox), np.int32(pass_), np.int32(1), *const,
                      exposure_at, key, rgba)

        run(0, be.device_zeros(1, np.float64))
        # the auto exposure stays on the device for pass 1: a read-back here would wait behind
        # the outputs' copies, which share the bus with it
        if c.exposure == "auto":
            d_exposure = select_on_device(be, key, nvox, c.percentile)
        else:  # (the select's layout: the exposure third)
            d_exposure = be.to_device(np.array([0.0, 0.0, c.exposure], np.float64))
        run(1, d_exposure)
        h_rgba = be.host_empty(tuple(ds.shape[::-1]) + (4,), np.uint8)
        copies.append(be.to_host_async(rgba, h_rgba.reshape(-1)))
    out = outs.wait()
    for handle in copies:
        be.wait_copy(handle)
    if d_exposure is not None:
        exposure = float(be.to_host(d_exposure)[2])
        h_rgba = h_rgba.transpose(2, 1, 0, 3)
    nbytes = sum(int(x.nbytes) for x in (J32, outs.rel32, outs.emis32, key, rgba, d_params, d_rgb))
    stage_b = ((0 if release else sums_bytes) + 4 * nvox
               + sum(int(x.nbytes) for x in (J32, outs.rel32, outs.emis32, key, rgba)))
    return FinishedArrays(J=out[0], rel_error=out[1], emissivity=out[2], rgba=h_rgba, exposure=exposure,
                          device_bytes=nbytes, peak_device_bytes=int(max(stage_a, stage_b)))


def filter_collisions_opencl(ds: DeviceSums, band_params: np.ndarray, batches, radius: float, cancel=None):
    """The collision filter on an OpenCL device (VkFFT through pyvkfft): the unfiltered J and
    its variance from the sums, each band convolved on the device
    (:func:`nebula_rt.transport.filtering_opencl.normalised_convolution_cl`), and the relative error.

    Returns flat float64 device arrays (J, rel_error) in the device layout, for :func:`finish`.
    Same arithmetic as :func:`nebula_rt.pipeline.filter_collisions` up to FFT round-off.
    Measured against the host FFT on an H100's OpenCL (3 bands, 128^3, radius 0.05): 3.9 ms
    against 1320 ms (benchmarks/bench_fft.py), before the local linear fit at the faces
    quadrupled the transforms.
    """
    from .filtering_opencl import normalised_convolution_cl

    be = ds.backend
    nb, nvox = ds.n_bands, ds.nvox
    nx, ny, nz = ds.shape
    params = _band_params(band_params, batches)
    n = nb * nvox
    J0, var = be.device_zeros(n, np.float64), be.device_zeros(n, np.float64)
    be.launch("postprocess.cl", "collision_light", n, ds.sum1, ds.m2, ds.density, be.to_device(params),
              np.uint64(nvox), np.uint64(n), J0, var)
    # a band's x-fastest block is a C-order (nz, ny, nx) array: convolve it with the kernel's
    # axes reversed to match
    kernel = np.ascontiguousarray(filtering.cubic_kernel(ds.shape, radius).transpose(2, 1, 0))
    import pyopencl as cl

    J, var_f = be.device_zeros(n, np.float64), be.device_zeros(n, np.float64)
    band_j, band_v = be.device_zeros(nvox, np.float64), be.device_zeros(nvox, np.float64)
    nbytes = 8 * nvox
    for b in range(nb):  # band blocks copied in and out (the FFT code takes whole buffers)
        if cancel is not None and cancel():  # (polled per band: a band's FFTs are queued at once)
            raise CancelledError("collision filter cancelled")
        cl.enqueue_copy(be.queue, band_j.data, J0.data, src_offset=b * nbytes, byte_count=nbytes)
        cl.enqueue_copy(be.queue, band_v.data, var.data, src_offset=b * nbytes, byte_count=nbytes)
        jf, vf = normalised_convolution_cl(be.queue, band_j.reshape(nz, ny, nx), kernel,
                                           band_v.reshape(nz, ny, nx))
        cl.enqueue_copy(be.queue, J.data, jf.data, dst_offset=b * nbytes, byte_count=nbytes)
        cl.enqueue_copy(be.queue, var_f.data, vf.data, dst_offset=b * nbytes, byte_count=nbytes)
    rel = be.device_zeros(n, np.float64)
    be.launch("postprocess.cl", "relative_error", n, J, var_f, np.uint64(n), rel)
    return J, rel


def select_on_device(be, key, n: int, percentile: float):
    """Queue the radix select of the ``percentile`` of the positive keys of the visible voxels
    (sign bit clear), or of every voxel if none is visible (kernels/postprocess.cl: two
    histogram passes of 2^16 bins and two one-group kernels that find the ranks' bins and the
    level), with no round trip to the host. Returns the device array ``dsel`` (float64):
    [1] the level (-1 when no key is positive), [2] the exposure 1 / level (1 when there is
    no positive level), which pass 1 of ``finish_voxels`` reads in place."""
    hist_vis, hist_all = be.device_zeros(_HI_BINS + 1, np.uint32), be.device_zeros(_HI_BINS + 1, np.uint32)
    chunks = be.device_zeros(2 * _CHUNKS, np.uint32)  # (of the visible voxels', then of all voxels')
    for all_voxels, hist in ((0, hist_vis), (1, hist_all)):
        be.launch("postprocess.cl", "key_histogram", n, key, np.uint64(n), np.int32(all_voxels), hist)
        be.launch("postprocess.cl", "bin_chunk_sums", _HI_BINS, hist, np.uint64(_HI_BINS), chunks,
                  np.int32(all_voxels * _CHUNKS))
    sel, dsel = be.device_zeros(6, np.uint64), be.device_zeros(3, np.float64)
    be.launch("postprocess.cl", "select_rank_bins", 1, hist_vis, hist_all, chunks,
              np.float64(float(percentile) / 100.0), sel, dsel)
    low, low_chunks = be.device_zeros(2 * _HI_BINS, np.uint32), be.device_zeros(2 * _CHUNKS, np.uint32)
    be.launch("postprocess.cl", "key_histogram_low", n, key, np.uint64(n), sel, low)
    be.launch("postprocess.cl", "bin_chunk_sums", 2 * _HI_BINS, low, np.uint64(2 * _HI_BINS), low_chunks, np.int32(0))
    be.launch("postprocess.cl", "select_level", 1, low, low_chunks, sel, dsel)
    return dsel


def auto_exposure_on_device(be, key, n: int, percentile: float) -> float:
    """1 / (the ``percentile`` of the positive brightness keys of the visible voxels, or of all
    voxels if none is visible), interpolated linearly between order statistics as
    ``numpy.percentile`` does; 1.0 when no key is positive (:func:`percentile_of_keys`)."""
    return float(be.to_host(select_on_device(be, key, n, percentile))[2])


def percentile_of_keys(be, key, n: int, percentile: float):
    """The ``percentile`` of the positive keys of the visible voxels (sign bit clear), or of all
    voxels if none is visible, as ``numpy.percentile`` interpolates it; None when no key is
    positive.

    The order statistics are found exactly by a radix select on the keys' bit patterns, on the
    device (:func:`select_on_device`): a histogram of the high 16 bits finds the bin holding
    each rank, a histogram of the low 16 bits inside that bin the value. Only the select's
    three float64 results come to the host.
    """
    level = float(be.to_host(select_on_device(be, key, n, percentile))[1])
    return None if level < 0.0 else level


#: voxels each work item of lit_partial_sums adds up
_LIT_CHUNK = 256


def lit_region_error_on_device(be, s1, m2, density, shape, band_params, batches, collision: bool,
                               lit_fraction: float, lit_percentile: float) -> float:
    """The lit-region error (:func:`nebula_rt.transport.lit_region_error`) of device sums
    (flat: ``s1`` float64 and ``m2`` float32 x 2^-64 cells, band-major, x fastest; ``density``
    float32), with one float of work memory per voxel: the brightness key of a band, its
    percentile by the radix select, then partial sums of the weights over fixed chunks of voxels
    added on the host in order (so the value, which decides when a run stops, is deterministic).
    The key is float32 where the reference forms sigma J in float64: the level and the weights
    agree to float32 rounding."""
    nvox = int(np.prod(shape))
    nb = int(np.asarray(band_params).shape[0])
    d_params = be.to_device(_band_params(band_params, batches))
    key = be.device_zeros(nvox, np.float32)
    n_chunks = -(-nvox // _LIT_CHUNK)
    partial = be.device_zeros(2 * n_chunks, np.float64)
    worst = 0.0
    for b in range(nb):
        level = None
        for use_sigma in (1, 0):  # a band without dust: the light itself decides
            be.launch("postprocess.cl", "lit_keys", nvox, s1, density, d_params, np.int32(b),
                      np.uint64(nvox), np.int32(bool(collision)), np.int32(use_sigma), key)
            level = percentile_of_keys(be, key, nvox, lit_percentile)
            if level is not None:
                break
        if level is None:
            return 1.0  # nothing lit in this band
        be.launch("postprocess.cl", "lit_partial_sums", n_chunks, s1, m2, key, d_params, np.int32(b),
                  np.float64(lit_fraction * level), np.uint64(nvox), np.uint64(_LIT_CHUNK), partial)
        sums = be.to_host(partial).reshape(-1, 2)
        sw, swr = float(np.sum(sums[:, 0])), float(np.sum(sums[:, 1]))
        if not sw > 0.0:
            return 1.0
        worst = max(worst, math.sqrt(swr / sw))
    return worst
