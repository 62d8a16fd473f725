"""The pipeline: density -> transport (+ filter) -> colour, each stage re-run only when its
inputs change.

A :class:`Pipeline` remembers the last result of each stage together with the part of the
scene it depends on, so a colour change never re-traces photons and an albedo change never
regenerates the density. ``Pipeline.executions`` counts how often each stage really ran."""


import dataclasses
import json
import time
from collections import Counter
from dataclasses import dataclass, field
from typing import Callable, Optional

import numpy as np

from .. import exact_sum
from ..transport import filtering, finish as postprocess, resources
from . import output_contract as contract
from ..array_api import array_module, to_numpy
from ..backends import Backend
from ..optics.bands import Band, reference_band_index
from ..density.generate import check_density_file, file_digest, scene_density
from ..density.octree import Octree
from ..density.resample import box_averages
from ..errors import SceneError
from ..transport.tails import DEPTH_CLASS_NAMES, figures
from ..transport.result import TransportResult
from ..transport.estimate import batch_standard_error, light_from_sums
from ..transport.request import TransportRequest, scene_backend

from .rgba import AUTO_EXPOSURE_MIN_ALPHA, AUTO_EXPOSURE_PERCENTILE, _dominant_source, _dominant_temperature, _voxel_edge, colour_matrix, colour_rgba, scene_opacity_factor


@dataclass
class LightField:
    """Everything a run produces, in the shapes of the output contract.

    Arrays are (nx, ny, nz) per band, index [i, j, k] = x, y, z, on the voxel centres.
    """

    scene: object
    bands: list[Band]
    density: np.ndarray  # float32
    J: np.ndarray  # float32 (nb, nx, ny, nz)
    rel_error: np.ndarray  # float32 (nb, ...)
    emissivity: np.ndarray  # float32 (nb, ...)
    rgba: Optional[np.ndarray]  # uint8 (nx, ny, nz, 4)
    transport: TransportResult
    exposure: float
    reference_band: int
    #: the factor on the reference band's optical depth in rgba's alpha (NaN: no colour)
    opacity_scale: float = float("nan")
    timings: dict = field(default_factory=dict)
    #: peak device memory of the run and peak host RSS of the process (bytes)
    memory: dict = field(default_factory=dict)
    #: SHA-256 of the density file the run read (dust.model = "file"), else ""
    dust_file_sha256: str = ""

    @property
    def spacing(self) -> tuple[float, float, float]:
        """Voxel edges in box units."""
        return tuple(1.0 / n for n in self.density.shape)

    @property
    def origin(self) -> tuple[float, float, float]:
        """Centre of the first voxel (the VTK point of index 0), box units."""
        return tuple(0.5 / n for n in self.density.shape)

    def point_arrays(self) -> dict[str, np.ndarray]:
        """The point-data arrays of the output contract (:mod:`nebula_rt.pipeline.output_contract`)."""
        out = {contract.DENSITY.name(): self.density.astype(np.float32)}
        for b, band in enumerate(self.bands):
            out[contract.J.name(band.name)] = self.J[b]
            out[contract.EMISSIVITY.name(band.name)] = self.emissivity[b]
            out[contract.REL_ERROR.name(band.name)] = self.rel_error[b]
        if self.rgba is not None:
            out[contract.RGBA.name()] = self.rgba
        return out

    def record(self) -> contract.LightFieldData:
        """The run's field data as the output contract's record: energies per band, photons,
        seed, the scene."""
        tr = self.transport
        t = _dominant_temperature(self.scene.stars)
        return contract.LightFieldData(
            band_names=tuple(b.name for b in self.bands),
            band_wavelength_nm=[b.wavelength for b in self.bands],
            band_luminosity=tr.band_luminosity,
            band_extinction=[b.extinction for b in self.bands],
            band_albedo=[b.albedo for b in self.bands],
            band_g=[b.g for b in self.bands],
            reference_band=self.reference_band,
            tau=self.scene.dust.tau,
            energy=tr.energy[:, :4],
            packets=tr.counts if tr.method == "analog" else None,
            biasing_energy=tr.energy[:, 4] if tr.method == "biased" else None,
            transport_method=tr.method,
            error_estimate=tr.error_estimate,
            absorbed_fraction=_fractions(tr.counts, 1),
            escaped_fraction=_fractions(tr.counts, 2),
            # packets stopped at max_scatterings, and the bound on J's bias they leave
            terminated_fraction=tr.terminated_fraction,
            terminated_bias=tr.terminated_bias,
            photons=tr.photons,
            photons_budget=tr.photons_budget or tr.photons,
            achieved_error=tr.achieved_error,
            seed=self.scene.transport.seed,
            batches=tr.batches,
            transport_ranks=tr.ranks,
            estimator=tr.estimator,
            device=tr.device,
            exposure=self.exposure,
            opacity_scale=self.opacity_scale,
            colour_temperature=t if t is not None else 0.0,
            device_memory_peak_bytes=int(self.memory.get("device_peak_bytes", 0)) if self.memory else None,
            **_j_tail_fields(tr),
            scene=_reproducible_scene(self.scene).to_toml(),
            dust_file_sha256=self.dust_file_sha256 or None,
        )

    def field_data(self) -> dict[str, object]:
        """Field data of the output contract, flat ``{name: value}`` (:meth:`record`)."""
        return self.record().to_field_data()


def _j_tail_fields(tr) -> dict:
    """The light field record's heavy-tail fields of J (none unless the run has them)."""
    if tr.tail_j is None:
        return {}
    f = figures(tr.tail_j)
    return {"j_tail_classes": ",".join(DEPTH_CLASS_NAMES), "j_tail_vov": f["vov"],
            "j_tail_largest_share": f["largest_share"], "j_tail_index": f["tail_index"],
            "j_tail_reliable": f["reliable"]}


def _fractions(counts, tally: int) -> list:
    """Packets of ``tally`` (1 absorbed, 2 escaped) over packets emitted, per band."""
    c = np.asarray(counts, dtype=np.float64)
    return [float(c[b, tally] / c[b, 0]) if c[b, 0] > 0 else 0.0 for b in range(c.shape[0])]


def _reproducible_scene(scene):
    """The scene with a relative ``dust.file`` resolved to an absolute path, so that the stored
    scene text reproduces the run wherever it is loaded (with the ``dust_file_sha256`` field
    telling whether the file still holds the same data)."""
    if scene.dust.model != "file" or not scene.dust.file:
        return scene
    path = str(scene.dust_file_path().resolve())
    return dataclasses.replace(scene, dust=dataclasses.replace(scene.dust, file=path))


def dust_file_digest(scene):
    """SHA-256 of the scene's density file (None: not a file model, or no such file)."""
    if scene.dust.model != "file" or not scene.dust.file:
        return None
    p = scene.dust_file_path()
    try:
        return file_digest(p)
    except OSError:
        return None


def _key(obj) -> str:
    return json.dumps(obj, sort_keys=True, default=str)


class Pipeline:
    """Runs scenes, caching each stage on the scene parameters it depends on.

    Parameters
    ----------
    backend : Backend, optional
        Compute backend; by default the one the scene's ``transport.backend`` and
        ``transport.device`` select.
    """

    def __init__(self, backend: Optional[Backend] = None, comm=None):
        self._backend = backend
        self.comm = comm  # several ranks trace together (nebula_rt.backends.parallel); None: this process alone
        self._cache: dict[str, tuple[str, object]] = {}
        self.executions: Counter = Counter()

    def backend_for(self, scene) -> Backend:
        if self._backend is not None:
            return self._backend
        return scene_backend(scene)

    # --- keys: what each stage depends on ------------------------------------------------
    @staticmethod
    def density_key(scene, digest: Optional[str] = None) -> str:
        """What the density depends on; a density file by its content (SHA-256, ``digest`` if
        already computed), not its modification time, which a rewrite may keep."""
        d = scene.to_dict()
        stars = [{"position": s["position"], "bump_radius": s.get("bump_radius", 0.0)} for s in d["stars"]]
        dust = dict(d["dust"])
        if dust.get("model") == "file":
            dust["_file"] = [str(scene.dust_file_path().resolve()), digest or dust_file_digest(scene)]
        return _key([d["grid"]["shape"], dust, stars])

    def transport_key(self, scene, density_key: Optional[str] = None) -> str:
        d = scene.to_dict()
        bands = [b.__dict__ for b in scene.bands.resolve()]
        transport = {k: v for k, v in d["transport"].items()}
        dkey = density_key if density_key is not None else self.density_key(scene)
        return _key([dkey, d["dust"].get("tau"), d["stars"], bands, transport])

    def _cached(self, stage: str, key: str, compute):
        hit = self._cache.get(stage)
        if hit is not None and hit[0] == key:
            return hit[1]
        value = compute()
        self.executions[stage] += 1
        self._cache[stage] = (key, value)
        return value

    # --- stages -----------------------------------------------------------------------------
    def density(self, scene, key: Optional[str] = None):
        """Stage 1: the dust density (float32, (nx, ny, nz)), or an
        :class:`~nebula_rt.density.octree.Octree` for an adaptive ``dust.file``; ``key``: its
        density_key if known."""
        key = key if key is not None else self.density_key(scene)
        return self._cached("density", key, lambda: scene_density(scene, self.backend_for(scene)))

    def light(self, scene, progress=None, cancel=None, density_key: Optional[str] = None,
              _resources_checked: bool = False) -> tuple[TransportResult, np.ndarray, np.ndarray]:
        """Stage 2: transport and, for collision-filter, the smoothing. Returns (result, J, rel).
        (``_resources_checked``: :meth:`run` checked the scene's memory before the density.)"""
        dkey = density_key if density_key is not None else self.density_key(scene)
        return self._cached(
            "transport",
            self.transport_key(scene, dkey),
            lambda: compute_light(scene, self.density(scene, dkey), self.backend_for(scene), progress, cancel,
                                  on_device=True, comm=self.comm, resources_checked=_resources_checked),
        )

    def run(self, scene, progress: Optional[Callable[[int, int], None]] = None,
            cancel: Optional[Callable[[], bool]] = None, colour: bool = True) -> LightField:
        """Run every stage that is out of date and return the light field.

        The arrays are finished on the compute device (:mod:`nebula_rt.transport.finish`); the colour
        stage runs only when the transport or the colour settings changed (or ``colour`` is
        False: no rgba).
        """

        t0 = time.perf_counter()
        resources.check(scene, self.backend_for(scene))  # before the density is allocated
        if scene.dust.model == "file":  # its header and size, before it is hashed
            check_density_file(scene.dust_file_path(), scene.dust.array, tuple(scene.grid.shape))
        digest = dust_file_digest(scene)  # the file is hashed once per run
        dkey = self.density_key(scene, digest)
        rho = self.density(scene, dkey)
        t1 = time.perf_counter()
        # one band has no colour to show: no colour stage, no rgba (render the emissivity
        # with a colour map, or ask for colour explicitly, as the CLI does for a PNG)
        colour = colour and len(scene.bands.resolve()) > 1
        ckey = _key([self.transport_key(scene, dkey), scene.to_dict().get("colour", {})])
        hit = self._cache.get("colour")
        need_colour = colour and not (hit is not None and hit[0] == ckey)
        mean_density = None
        if need_colour and scene.colour.opacity_scale == "auto" and not isinstance(rho, Octree):
            # summed on the device with the density's extremes (None: on the host when finishing)
            mean_density = self.backend_for(scene).density_mean(rho)
        res, J, rel = self.light(scene, progress, cancel, dkey, _resources_checked=True)
        t2 = time.perf_counter()
        light = finish_light_field(scene, rho, res, J, rel, colour=need_colour, mean_density=mean_density)
        if need_colour:
            self.executions["colour"] += 1
            self._cache["colour"] = (ckey, (light.rgba, light.exposure, light.opacity_scale))
        elif colour:
            light.rgba, light.exposure, light.opacity_scale = hit[1]
        t3 = time.perf_counter()
        light.dust_file_sha256 = digest or ""
        light.timings = {"density_s": t1 - t0, "transport_s": t2 - t1, "finish_s": t3 - t2,
                         "kernel_s": res.timings.get("kernel_s", 0.0)}
        return light


def _memory(res: TransportResult, finish_bytes: int, finish_peak: int = 0) -> dict:
    """Peak device memory of a run: the transport's buffers, or, later, the finishing's peak
    (the sums and density it was handed with its outputs, see
    :func:`nebula_rt.transport.finish.finish`), whichever is larger; and the process's peak RSS."""
    import resource

    return {"device_peak_bytes": int(max(res.device_bytes, finish_peak)),
            "transport_device_bytes": int(res.device_bytes), "finish_device_bytes": int(finish_bytes),
            "host_peak_rss_bytes": int(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss) * 1024}


def compute_light(scene, density: np.ndarray, backend: Backend, progress=None, cancel=None, on_device=False,
                  comm=None, resources_checked: bool = False):
    """Transport through ``density`` (and the collision filter if the scene asks for it).

    Returns (TransportResult, J, rel_error). Without ``on_device``: J and rel_error are NumPy
    float64 (n_bands, nx, ny, nz). With ``on_device``: the sums stay on the device
    (``result.device_sums``) and J, rel_error are None, except for the collision filter, whose
    smoothed J and error are CuPy arrays on CUDA, flat device arrays on OpenCL with pyvkfft
    (VkFFT), else NumPy arrays filtered on the host. ``resources_checked``: the caller checked
    the scene's memory on this backend (:func:`nebula_rt.transport.resources.check`: 0.3-0.5
    ms of the thesis headline's host time) and nothing has been allocated since.
    """

    t = scene.transport
    if not resources_checked:
        resources.check(scene, backend)
    if isinstance(density, Octree):  # J per leaf, estimated on the host (finish_tree_light_field)
        if t.estimator == "collision-filter":
            raise SceneError("transport.estimator", t.estimator,
                             '"track-length" on an adaptive density (the collision filter smooths a uniform grid)')
        on_device = False
    # on the device, the sums are finished by finish_light_field, which takes the light the
    # transport may make as its last fold ends (the copies start sooner)
    res = TransportRequest.from_scene(scene).trace(density, backend, progress=progress, cancel=cancel,
                                                  on_device=on_device, comm=comm, make_light=on_device)
    if t.estimator == "collision-filter":
        if res.device_sums is not None and _opencl_fft(backend):
            bands = scene.bands.resolve()
            params = np.stack([res.j_scale, res.sigma_scale, [b.albedo for b in bands]], axis=1)
            J, rel = postprocess.filter_collisions_opencl(res.device_sums, params, res.band_batches, t.filter_radius,
                                                          cancel=cancel)
        elif res.device_sums is not None:
            s1, s2 = res.device_sums.host_sums()
            J0, _ = light_from_sums(s1, s2, res.band_batches, res.estimator, res.j_scale, res.sigma_scale, density)
            J, rel = filter_collisions(J0, s1, s2, res.band_batches, t.filter_radius, cancel)
        else:
            J, rel = filter_collisions(res.J, res.raw_sum, res.raw_m2, res.band_batches, t.filter_radius, cancel)
    else:
        J, rel = res.J, res.rel_error
    return res, J, rel


def _opencl_fft(backend) -> bool:
    """Filter collisions on the OpenCL device: when the backend is OpenCL and pyvkfft imports
    (chosen by measurement, benchmarks/bench_fft.py: 3.9 ms on the device against 1320 ms
    through the host for 3 bands at 128^3 on an H100, with the former 4 transforms per band;
    with the 16 of the local linear fit at the faces, PoCL is 2.6x faster on the device at
    64^3 but 0.5x at 128^3)."""
    if getattr(backend, "name", "") != "opencl":
        return False
    from ..transport import filtering_opencl

    return filtering_opencl.available()


def finish_light_field(scene, rho, res: TransportResult, J=None, rel=None, colour: bool = True,
                       mean_density=None) -> LightField:
    """The light field of a transport result: on the device when the sums are there
    (:func:`nebula_rt.transport.finish.finish`), else with the NumPy reference functions.

    ``J``, ``rel``: the (filtered) light from :func:`compute_light`, or None to take it from the
    device sums. ``mean_density``: the density's mean already summed
    (:meth:`~nebula_rt.backends.base.Backend.density_mean`), for the auto opacity.
    """
    if isinstance(rho, Octree):
        return finish_tree_light_field(scene, rho, res, colour)
    bands = scene.bands.resolve()
    ds = res.device_sums
    if ds is None:
        light, emissivity, rho_x = assemble_light_field(scene, rho, res, J, rel, with_device_emissivity=True)
        if colour:  # (the opacity from the float32 density)
            light.opacity_scale = scene_opacity_factor(scene, bands, rho, mean_density)
            light.rgba, light.exposure = colour_rgba(scene, bands, rho_x, emissivity, res, light.opacity_scale)
        light.memory = _memory(res, 0)
        return light
    params = np.stack([res.j_scale, res.sigma_scale, [b.albedo for b in bands]], axis=1)
    csetup = None
    # the device's colour pass has the linear curve only; another stretch colours on the host
    host_colour = colour and scene.colour.stretch != "linear"
    colour = colour and not host_colour
    if (colour or host_colour) and mean_density is None and scene.colour.opacity_scale == "auto":
        mean_density = _device_mean(ds)
    if colour:
        ref = reference_band_index(bands)
        cfg = scene.colour
        sigma_ref_scale = scene.dust.tau * bands[ref].extinction
        csetup = postprocess.ColourSetup(
            to_rgb=colour_matrix([b.wavelength for b in bands], res.band_luminosity,
                                 _dominant_source(scene.stars), cfg.white_point),
            sigma_ref_scale=sigma_ref_scale,
            voxel_edge=_voxel_edge(ds.shape),
            opacity_scale=scene_opacity_factor(scene, bands, rho, mean_density),
            exposure=cfg.exposure,
            percentile=AUTO_EXPOSURE_PERCENTILE,
            min_alpha=AUTO_EXPOSURE_MIN_ALPHA,
        )
    from_sums = J is None
    if from_sums and ds.sum1 is None:  # spent by an earlier finishing: its float32 light
        J, rel = res.J, res.rel_error
    out = postprocess.finish(ds, params, batches=res.band_batches, collision=res.estimator != "track-length",
                             light=None if J is None else (J, rel), colour=csetup, release=from_sums)
    if from_sums and res.J is None:
        # the sums' memory went to the outputs; a later finishing (a new colour) starts from
        # these float32 arrays, which give the same bits (light_cells rounds J to float32)
        res.J, res.rel_error = out.J, out.rel_error
    light = LightField(
        scene=scene,
        bands=bands,
        density=np.asarray(rho),
        J=out.J,
        rel_error=out.rel_error,
        emissivity=out.emissivity,
        rgba=out.rgba,
        transport=res,
        exposure=out.exposure,
        reference_band=reference_band_index(bands),
        opacity_scale=csetup.opacity_scale if csetup is not None else float("nan"),
    )
    light.memory = _memory(res, out.device_bytes, out.peak_device_bytes)
    if host_colour:
        light.opacity_scale = scene_opacity_factor(scene, bands, rho, mean_density)  # (the float32 density's)
        light.rgba, light.exposure = colour_rgba(scene, bands, np.asarray(rho, np.float64),
                                                 light.emissivity.astype(np.float64), res, light.opacity_scale)
    return light


def _device_mean(ds) -> Optional[float]:
    """The exact mean of the density the transport traced, summed on the device (its copy
    stays with the sums: a density read from a file as well as a generated one); None
    without it."""
    if ds.density is None:
        return None
    return exact_sum.exact_mean(ds.backend.significand_sums(ds.density, ds.nvox), ds.nvox)


def finish_tree_light_field(scene, tree: Octree, res: TransportResult, colour: bool = True) -> LightField:
    """The light field of a run on a tree, on the uniform grid of ``grid.shape`` (the output
    contract's ``vtkImageData``): each voxel the average of the leaves it overlaps, by exact
    overlap volume (:func:`nebula_rt.density.resample.box_averages`), of the density, J and the
    emissivity (formed per leaf, alb x sigma x rho x J, so that its voxel averages keep the
    scattered energy). A voxel inside one leaf has that leaf's values and relative error; over
    several leaves its error is the overlap average of their errors (as if their errors moved
    together: an upper bound, since the leaves' errors are partly independent). Colour on the
    host, as for a transport finished there."""
    bands = scene.bands.resolve()
    shape = tuple(int(n) for n in scene.grid.shape)
    lo, hi, dens = tree.leaves()
    dens = np.asarray(dens, np.float64)
    sig = np.array([scene.dust.tau * b.extinction for b in bands], np.float64)
    alb = np.array([b.albedo for b in bands], np.float64)
    nb = len(bands)
    J = np.empty((nb,) + shape)
    sd = np.empty((nb,) + shape)
    emissivity = np.empty((nb,) + shape)
    for b in range(nb):
        J[b] = box_averages(lo, hi, res.J[b], shape)
        sd[b] = box_averages(lo, hi, res.J[b] * res.rel_error[b], shape)
        emissivity[b] = box_averages(lo, hi, alb[b] * sig[b] * dens * res.J[b], shape)
    rel = np.where(J > 0, sd / np.where(J > 0, J, 1.0), 1.0)
    rho_x = box_averages(lo, hi, dens, shape)
    light = LightField(
        scene=scene,
        bands=bands,
        density=rho_x.astype(np.float32),
        J=J.astype(np.float32),
        rel_error=rel.astype(np.float32),
        emissivity=emissivity.astype(np.float32),
        rgba=None,
        transport=res,
        exposure=float("nan"),
        reference_band=reference_band_index(bands),
    )
    if colour:  # (the opacity from the output's float32 density, as Nebula Colour finds it)
        light.opacity_scale = scene_opacity_factor(scene, bands, light.density)
        light.rgba, light.exposure = colour_rgba(scene, bands, rho_x, emissivity, res, light.opacity_scale)
    light.memory = _memory(res, 0)
    return light


def assemble_light_field(scene, rho, res: TransportResult, J, rel, with_device_emissivity=False):
    """The output-contract arrays (emissivity = albedo x extinction x J) without colour.

    J and rel may live on the device (CuPy); the LightField holds NumPy float32 copies. The
    emissivity is formed from the float32 J, the output's own precision (the device finishing
    does the same: a float64 J changes it by less than float32's rounding, 6e-8). With
    ``with_device_emissivity`` also return the emissivity on J's device (for the colour stage).
    """
    xp = array_module(J)
    J32 = J.astype(xp.float32)
    bands = scene.bands.resolve()
    tau = scene.dust.tau
    rho_x = xp.asarray(rho, dtype=xp.float64)
    sig = xp.asarray([tau * b.extinction for b in bands])[:, None, None, None] * rho_x[None]
    alb = xp.asarray([b.albedo for b in bands])[:, None, None, None]
    emissivity = alb * sig * J32.astype(xp.float64)
    light = LightField(
        scene=scene,
        bands=bands,
        density=np.asarray(rho),
        J=to_numpy(J32),
        rel_error=to_numpy(rel.astype(xp.float32)),
        emissivity=to_numpy(emissivity.astype(xp.float32)),
        rgba=None,
        transport=res,
        exposure=float("nan"),
        reference_band=reference_band_index(bands),
    )
    return (light, emissivity, rho_x) if with_device_emissivity else light


def filter_collisions(J, s1, s2, batches: int, radius: float, cancel=None):
    """Smooth the collision estimate of J with the normalised cubic kernel of ``radius`` (box units).

    ``s1``, ``s2``: the sum of the batch totals (collision counts) and their centred sum of
    squares (``batches`` of them, an int or per band), from which the per-voxel variance of J
    is filtered with the squared kernel: the filtered
    field's statistical error (the filter's bias is not included). Runs on the device of ``J``
    (CuPy FFTs on CUDA). ``cancel`` is polled between the FFTs (the filter of a large grid on
    a CPU takes many seconds).
    """
    xp = array_module(J)
    shape = J.shape[1:]
    kernel = filtering.cubic_kernel(shape, radius)
    se = batch_standard_error(s1, s2, batches)
    scale = xp.where(s1 > 0, J / xp.where(s1 > 0, s1, 1.0), 0.0)
    var = (se * scale) ** 2
    Jf = xp.empty_like(J)
    rel = xp.empty_like(J)
    for b in range(J.shape[0]):
        jf, vf = filtering.normalised_convolution(J[b], kernel, var[b], cancel=cancel)
        Jf[b] = jf
        rel[b] = xp.where(jf > 0, xp.sqrt(vf) / xp.where(jf > 0, jf, 1.0), 1.0)
    return Jf, rel
