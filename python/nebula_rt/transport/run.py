"""Photon transport stage: batches of packets on a backend -> mean intensity per band.

Normalisation
-------------
Each band b of total luminosity L_b is traced with N packets of equal energy q_b ~= L_b / N
(analog transport: a packet is scattered with probability albedo, else absorbed, so every
packet keeps its energy). The track-length estimator of the mean intensity of voxel v is

    J_v = q_b * (sum of path lengths in v) / (4 pi V_v)

(box units: J is luminosity per box-unit area per steradian), so a point source in vacuum
gives J = L / (16 pi^2 r^2). The collision estimator replaces the path length by
(number of interactions in v) / sigma_v, sigma_v the extinction per box unit.

Exact energy bookkeeping
------------------------
Packet counts are exact integers. q_b is L_b / N rounded to 53 - bit_length(N) significant
bits, so every energy count * q_b and every sum of them is exact in float64:
emitted = absorbed + escaped + terminated holds bit for bit. The rounding changes q_b by
less than 2^-(52 - bit_length(N)) relative (2^-31 for 2.1M packets).

Error estimate
--------------
Packets are traced in M batches of (nearly) equal size; for each cell (voxel and band) the
device keeps the sum of the batch totals X_k (float64) and their centred sum of squares
Q = sum (X_k - mean)^2 (Welford's update as each batch is folded, float32), and the standard
error of the total is sqrt(M / (M - 1) * Q) (batch means). ``rel_error`` = SE / total, and
1.0 where nothing was tallied. The batch slots are folded as soon as a launch is done, so the
memory is the sums and at most a launch's slots, never one slot per batch."""

from __future__ import annotations

import math
import time
from typing import Callable, Optional

import numpy as np

from ..backends import Backend
from ..errors import AccumulatorOverflowError, CancelledError, TimeLimitError
from ..backends.parallel import Serial, any_rank, device_reducer, share
from .finish import DeviceSums, LightOutputs, _band_params
from .tails import (
    IMAGE_ERROR_LIMIT, J_ERROR_LIMIT, TAIL_BINS, check_histograms, class_cells)

from .plan import (BIASED_TALLY_NAMES, MIN_BATCHES, Tallies, TransportPlan, WEIGHT_UNIT, light_while_folding,
                   plan_transport, spare_slot_bytes)
from .result import TransportResult, exact_packet_energy, terminated_bias, warn_if_heavy_tailed, warn_if_terminated
from .estimate import _PeelSums, _current_error, _j_scale, light_from_sums
from . import tree as tree_run


#: A launch lasts at most about this long (sized by the speed measured on the run's earlier
#: launches), so that a cancel (Ctrl-C) or a time limit is honoured within it; a group of
#: batches is then traced in several launches, which gives the same bits (absolute packet
#: indices, integer deposits).
LAUNCH_SECONDS = 0.25


class _Launcher:
    """Traces a group of batches in launches of at most about ``LAUNCH_SECONDS``, polling the
    cancel callback before each and the deadline between them."""

    def __init__(self, session, backend, cancel, deadline: float, progress_of=None):
        self.session, self.cancel, self.deadline = session, cancel, deadline
        self.progress_of = progress_of  # () -> (packets per band done, total), for messages
        self.first = max(1, int(getattr(backend, "first_launch_packets", 1 << 21)))
        self.rate = None  # packets (all bands) per second of the latest launch
        self.kernel_s = 0.0

    def poll(self) -> None:
        if self.cancel is not None and self.cancel():
            if self.progress_of is None:
                raise CancelledError("transport cancelled")
            done, total = self.progress_of()
            raise CancelledError(f"transport cancelled after {done:,} of {total:,} packets per band")

    def run(self, start: int, count: int, base: int, extra: int, first_batch: int, n_slots: int,
            bands: tuple[int, int], on_progress=None):
        """Trace packets [start, start + count) of ``bands`` (first band, number) into slots
        0..n_slots-1; ``on_progress(traced)`` after each launch but the last (a group traced in
        several launches reports as it goes).

        Returns (tallies, overflow, traced): the group's tallies and overflow flags so far and
        the packets per band traced from ``start`` (less than ``count`` only when the deadline
        passed between two launches).
        """
        nb = bands[1]
        traced = 0
        tallies = overflow = None
        while traced < count:
            self.poll()
            if traced and time.perf_counter() >= self.deadline:
                # finish the packets still in flight (transport by regions), adding none
                tallies, overflow = self._launch(start + traced, 0, base, extra, first_batch, n_slots,
                                                 False, bands)
                break
            chunk = max(1, min(count - traced, self._budget(nb) // nb))
            tallies, overflow = self._launch(start + traced, chunk, base, extra, first_batch, n_slots,
                                             traced == 0, bands, drain=traced + chunk >= count)
            traced += chunk
            if on_progress is not None and traced < count:
                on_progress(traced)
        self.poll()  # a cancel that came during the last launch
        return tallies, overflow, traced

    def _budget(self, nb: int) -> int:
        """Packets (all bands) of the next launch: the first launch's, then what the measured
        speed traces in ``LAUNCH_SECONDS``."""
        return self.first if self.rate is None else max(nb, int(self.rate * LAUNCH_SECONDS))

    def _launch(self, start, chunk, base, extra, first_batch, n_slots, fresh, bands, drain=True):
        """One launch, timed (its speed sizes the next); ``drain`` False: not the group's last
        (:meth:`TransportSession.run_group`)."""
        tk = time.perf_counter()
        out = self.session.run_group(start, chunk, base, extra, first_batch, n_slots, fresh=fresh, bands=bands,
                                     drain=drain)
        dt = time.perf_counter() - tk
        self.kernel_s += dt
        if chunk:
            self.rate = chunk * bands[1] / max(dt, 1e-6)
        return out

    def run_together(self, comm, start: int, count: int, base: int, extra: int, first_batch: int,
                     n_slots: int, bands: tuple[int, int], cancel, on_progress=None):
        """With several ranks: trace this rank's ``count`` packets of a group in as many
        launches as rank 0 needs for its share (each about ``LAUNCH_SECONDS``), every rank the
        same number, and check after each launch whether any rank was cancelled (then all
        raise :class:`CancelledError`). Returns (tallies, overflow): ``count`` may be 0."""
        nb = bands[1]
        launches = max(1, -(-count * nb // max(self._budget(nb), 1))) if comm.rank == 0 else None
        launches = int(comm.bcast(launches))
        tallies = overflow = None
        traced = 0
        for i in range(launches):
            chunk = count * (i + 1) // launches - count * i // launches
            if chunk:
                tallies, overflow = self._launch(start + traced, chunk, base, extra, first_batch, n_slots,
                                                 traced == 0, bands, drain=i + 1 == launches)
                traced += chunk
                if on_progress is not None and i + 1 < launches:
                    on_progress(traced * comm.size)
            if any_rank(comm, cancel is not None and cancel()):
                raise CancelledError("transport cancelled")
        if tallies is None:
            tallies, overflow = self.session.empty_group(n_slots, bands)
        return tallies, overflow



# One function though long (about 160 lines): the launch loop's state (the launches left, the
# tallies, the folds, the error target's next check, the time limit, cancelling between
# launches, the ranks' sums) is read and changed by every step, in this order; cut into
# pieces, each would take and return that same state.
def run_transport(plan: TransportPlan, backend: Backend, *, progress=None, cancel=None,
                  started: Optional[float] = None, comm=None, make_light: bool = False) -> Tallies:
    """The tracing stage: trace the plan's batches, folding each launch's slots into the
    device sums, until every batch is in, the error target is met or the time limit
    (counted from ``started``) comes. Returns the :class:`Tallies`; its session stays open.
    ``make_light``: the sums will be finished on the device; where
    :func:`~nebula_rt.transport.plan.light_while_folding` allows, the light is made as the
    last fold ends and its copies to the host started (``Tallies.light``).

    ``comm`` (:mod:`nebula_rt.backends.parallel`) with several ranks: each rank traces its share of
    every group's packets, the ranks' slots and tallies are added before each fold, and the
    decisions to stop (time limit, cancel: any rank's) are made together between groups, so
    every rank folds the one-rank run's sums."""

    comm = comm if comm is not None else Serial()
    distributed = comm.size > 1
    if comm.rank != 0:
        progress = None
    t0 = time.perf_counter() if started is None else started
    setup, launches = plan.setup, plan.launches
    shape, nb, photons = plan.shape, plan.n_bands, plan.photons
    batches = launches.batches
    base, extra = batches.base, batches.extra
    slots, groups = launches.slots, launches.band_groups  # groups: bands traced together
    targeted = plan.target_error > 0.0
    track_scale = setup.track_scale
    peel_sums = None if plan.peel is None else _PeelSums(nb, plan.peel.size, plan.peel_bins)
    stokes_sums = (None if plan.peel is None or setup.stokes_images == 1 else
                   _PeelSums(nb * (setup.stokes_images - 1), plan.peel.size, plan.peel_bins))
    # python ints: exact whatever the photon count (and 128-bit weight sums)
    counts = np.zeros((nb, len(BIASED_TALLY_NAMES) if setup.biased else 4), dtype=object)
    session = backend.transport_session(setup, slots, launches.bands_per_launch)
    out = Tallies(session=session, counts=np.zeros((nb, 4), np.int64), folded=np.zeros(nb, np.int64),
                  band_done=np.zeros(nb, np.int64), peel_sums=peel_sums, stokes_sums=stokes_sums,
                  device_bytes=session.device_bytes(),
                  setup_s=time.perf_counter() - t0,
                  tail_hist=np.zeros((nb, setup.tail_hists, TAIL_BINS), np.uint64))
    folded, band_done = out.folded, out.band_done
    # several ranks on GPUs: the slots are added on the device (collective: every rank)
    reducer = device_reducer(comm, backend) if distributed else None
    if distributed:
        mapped = reducer is None and backend.map_host(session.d_acc, 1) is not None
        out.reduce_path = reducer.kind if reducer is not None else ("mapped" if mapped else "copied")
    make_light = (make_light and not distributed and getattr(backend, "light_while_folding", True)
                  and light_while_folding(plan.estimator, nb * int(np.prod(shape)),
                                          spare_slot_bytes(backend, int(np.prod(shape)), launches,
                                                           16 if setup.biased else 8),
                                          light_field=setup.light_field, packets=setup.packet_sq,
                                          peel=plan.peel is not None, tree=setup.tree is not None,
                                          targeted=targeted))
    if make_light:
        def make_light_arrays():
            """The light's arrays, made while the device traces the first launch rather than
            after the last fold."""
            out.light = LightOutputs(backend, session.d_sum1, session.d_m2, session.d_density, shape, nb,
                                     collision=False, release=True)
            out.device_bytes += out.light.device_bytes  # (beside the slots and sums)
            # the parameters of a run whose every batch folds (the only run whose light is made
            # in the transport: fold_group checks them against the counts)
            out.light.preset(light_params(plan, np.full(nb, photons), np.full(nb, len(batches))))

        session.while_tracing = make_light_arrays
    deadline = t0 + plan.time_limit if plan.time_limit > 0 else math.inf
    done = 0  # packets per band traced (all bands)
    # several ranks: no rank stops on its own within a group (the others would wait for it)
    launcher = _Launcher(session, backend, None if distributed else cancel,
                         math.inf if distributed else deadline, lambda: (done, photons))

    def trace_group(start, count, first_batch, n, group, on_progress=None, base_=None, extra_=None):
        """Trace a group (this rank's share of it) and, with several ranks, add the ranks'."""
        b_, e_ = (base, extra) if base_ is None else (base_, extra_)
        if not distributed:
            return launcher.run(start, count, b_, e_, first_batch, n, group, on_progress)
        lo, mine = share(start, count, comm)
        tallies, overflow = launcher.run_together(comm, lo, mine, b_, e_, first_batch, n, group, cancel,
                                                  on_progress)
        tr = time.perf_counter()
        tallies, overflow = session.reduce_group(comm, n, group, tallies, overflow, reducer)
        out.reduce_s += time.perf_counter() - tr
        return tallies, overflow, count

    def stop_together() -> bool:
        """With several ranks: whether any rank was cancelled (all raise) or rank 0's clock
        passed the time limit (all stop), decided between groups."""
        if not distributed:
            return time.perf_counter() >= deadline
        if any_rank(comm, cancel is not None and cancel()):
            raise CancelledError(f"transport cancelled after {done:,} of {photons:,} packets per band")
        return bool(comm.bcast(time.perf_counter() >= deadline))
    next_check = 0  # packets per band after which the error is checked next (targeted runs)
    redo: list[tuple[int, int, tuple[int, int]]] = []

    def take(tallies, overflow, images, ranges, group):
        """Fold the finished batches ``ranges`` [(start, count)] of a launch's slots (bands
        ``group``) into the counts."""
        b0, nlb = group
        kept = [k for k in range(len(ranges)) if not overflow[k]]
        if images is not None and kept:  # (in batch order, as one add per batch)
            images = images[kept]
            if images.ndim == 5:  # polarized: I, then Q and U, signed sums (64-bit: two's complement)
                m, _, k, w, h = images.shape
                qu = images[:, :, 1:]
                qu = qu.view(np.int64) if qu.dtype == np.uint64 else qu
                stokes_sums.add_batches(qu.reshape(m, nlb * (k - 1), w, h), b0 * (k - 1))
                images = images[:, :, 0]
            peel_sums.add_batches(images, b0)
        for k, (b_start, b_count) in enumerate(ranges):
            if overflow[k]:
                redo.append((b_start, b_count, group))
                continue
            folded[b0:b0 + nlb] += 1
            counts[b0:b0 + nlb] += session.counts_of(tallies[k])
            if setup.tail_hists:
                out.tail_hist[b0:b0 + nlb] += tallies[k][:, setup.tally_base:].reshape(nlb, setup.tail_hists, TAIL_BINS)
            band_done[b0:b0 + nlb] += b_count

    def fold_group(group, n, tallies, overflow, ranges, last=False):
        """Fold a group's first ``n`` slots on the device and its tallies on the host
        (``last``: no launch follows unless a slot overflowed, so the slots that did not stay
        as they are; with ``make_light`` the group's light is then made and its copies to the
        host started)."""
        final = last and not redo and not np.any(overflow[:n])
        session.fold(n, group, int(folded[group[0]]), packets=sum(c for _, c in ranges), clear=not final)
        b0, nlb = group
        if final and make_light:  # the light's launch and copies first, the host's bookkeeping after
            if setup.unchecked_adds and b0 + nlb == nb:  # (before the copies: see there)
                session.read_overflow_seen()
            out.light.bands(b0, nlb)
        images = session.take_images(n, group)[:len(ranges)] if plan.peel is not None else None
        take(tallies, overflow, images, ranges, group)
        if final and make_light and not np.array_equal(out.light.params[b0:b0 + nlb],
                                                       light_params(plan, band_done, folded)[b0:b0 + nlb]):
            raise RuntimeError("the light was made with band parameters other than the run's")

    try:
        # batches in groups of consecutive ones, each group's bands traced in one or more
        # launches and folded before the next group's
        first = 0
        while first < len(batches):
            n = min(slots, len(batches) - first)
            start = batches.start(first)
            count = batches.start(first + n) - start
            cut = None  # packets of the group every band finished, when the time limit came
            for gi, group in enumerate(groups):
                tallies, overflow, traced = trace_group(
                    start, count, first, n, group,
                    None if progress is None else (lambda k, gi=gi: progress(done + (gi * count + k) // len(groups), photons)))
                if traced < count:  # the time limit came: keep the batches every band finished
                    # earlier band groups traced all n; they must end where this one does
                    finished = batches.batches_within(first, start + traced) if gi == 0 else 0
                    fold_group(group, finished, tallies, overflow, batches[first:first + finished])
                    cut = batches.start(first + finished) - start
                    break
                fold_group(group, n, tallies, overflow, batches[first:first + n],
                           last=first + n >= len(batches) and gi == len(groups) - 1)
            if cut is not None:
                if cut == 0 and len(groups) > 1:
                    raise TimeLimitError(
                        f"transport.time_limit = {plan.time_limit!r}: the bands are traced one group after "
                        "another on this grid, and the time limit came before every band had finished a "
                        "batch; raise it or lower transport.batch_size")
                redo.clear()  # no time left to re-trace
                break
            done += count
            if progress is not None:
                progress(done, photons)
            first += n
            if first >= len(batches) or stop_together():
                break
            if targeted and int(folded.min()) >= MIN_BATCHES and done >= next_check:
                out.achieved_error = _current_error(backend, session.device_arrays(), shape, folded,
                                                    plan.estimator, plan.band_luminosity, done,
                                                    track_scale * setup.fold_scale, plan.nvox_inv,
                                                    plan.sigma_scale, plan.albedo,
                                                    setup.collision_scale * setup.fold_scale)
                if out.achieved_error <= plan.target_error:
                    break
                # the error falls as 1/sqrt(N): check again near where it should reach the
                # target (never before 10 % more packets), so the checks cost O(log N)
                predicted = done * (out.achieved_error / plan.target_error) ** 2
                next_check = max(int(done * 1.1), int(0.9 * predicted))
        # A batch whose fixed-point cell would have passed 2^63 was not folded. Same packets,
        # same random numbers: tracing it in two halves gives the same integer deposits with
        # more headroom each (each half then counts as a batch of the error estimate).
        if redo and setup.packet_sq:  # packet_scales keeps every cell below the limit
            raise AccumulatorOverflowError("a voxel tally of the error estimate by packets reached 2^63; "
                                           'set transport.error_estimate = "batches"')
        while redo:
            b_start, b_count, group = redo.pop()
            if b_count == 1:
                raise AccumulatorOverflowError(
                    "a single packet overflowed a 64-bit fixed-point voxel tally; "
                    "reduce dust.tau or transport.max_scatterings"
                )
            half = b_count // 2
            for h_start, h_count in ((b_start, half), (b_start + half, b_count - half)):
                # one batch covering the whole range: base 2^62 puts every packet in batch 0
                tallies, overflow, traced = trace_group(h_start, h_count, 0, 1, group, None, 1 << 62, 0)
                if traced < h_count:  # the time limit came: what is folded is the result
                    redo.clear()
                    break
                fold_group(group, 1, tallies, overflow, [(h_start, h_count)])
        if out.photons == 0:
            raise TimeLimitError(
                f"transport.time_limit = {plan.time_limit!r}: no batch of {base} packets per band "
                "finished within the time limit; raise it or lower transport.batch_size"
            )
    except BaseException:
        if out.light is not None:
            out.light.discard()
        session.close()
        raise
    out.counts = counts if setup.biased else np.array(counts.tolist(), dtype=np.int64)
    out.kernel_s = launcher.kernel_s
    return out


def _packet_energies(plan: TransportPlan, band_done) -> np.ndarray:
    """Each band's packet energy (exact, from the packets folded: a band whose overflowed
    batch the time limit left unfinished has fewer)."""
    return np.array([exact_packet_energy(L, int(n)) for L, n in zip(plan.band_luminosity, band_done)])


def light_params(plan: TransportPlan, band_done, folded) -> np.ndarray:
    """(n_bands, 4) float64: the finishing's parameters of a track-length run's bands (J
    scale, extinction per box unit at density 1, albedo, batches folded) as
    :func:`~nebula_rt.transport.finish.finish` forms them from the result."""
    fs = plan.setup.fold_scale
    j_scale = _j_scale(_packet_energies(plan, band_done), plan.estimator, plan.setup.track_scale * fs,
                       plan.nvox_inv, plan.setup.collision_scale * fs)
    return _band_params(np.stack([j_scale, plan.sigma_scale, plan.albedo], axis=1), folded)


def estimate_light(plan: TransportPlan, tallies: Tallies, backend: Backend, *, on_device: bool = False) -> TransportResult:
    """The estimate stage: J and its error (or the device sums, ``on_device``), the packet
    energies from the packets folded, the peel-off image and the error reached, from a
    plan's tallies (whose session must still be open)."""
    session, folded, band_done = tallies.session, tallies.folded, tallies.band_done
    shape, nb, estimator = plan.shape, plan.n_bands, plan.estimator
    photons = tallies.photons
    q = _packet_energies(plan, band_done)
    fs = plan.setup.fold_scale  # statistics units per cell unit
    if plan.setup.packet_sq:  # the error estimate by packets: batches of one packet
        folded = band_done.copy()
    j_scale = _j_scale(q, estimator, plan.setup.track_scale * fs, plan.nvox_inv, plan.setup.collision_scale * fs)
    peel_image = peel_error = peel_groups = stokes = stokes_error = stokes_groups = None
    if plan.peel is not None:  # packet energy x (phase x attenuation) per pixel area
        peel_image, peel_error, peel_groups = tallies.peel_sums.finish(
            q / (plan.setup.peel_scale * plan.peel.pixel_size**2))
    if tallies.stokes_sums is not None:  # Q and U of each band, in the units of its image
        k = plan.setup.stokes_images - 1
        stokes, stokes_error, stokes_groups = tallies.stokes_sums.finish(
            np.repeat(q / (plan.setup.peel_scale * plan.peel.pixel_size**2), k))
        stokes, stokes_error = (a.reshape((nb, k) + a.shape[1:]) for a in (stokes, stokes_error))
        if stokes_groups is not None:
            stokes_groups = stokes_groups.reshape(stokes_groups.shape[0], nb, k, -1)
    achieved = float("nan")
    if plan.target_error > 0.0:
        achieved = _current_error(backend, session.device_arrays(), shape, folded, estimator, plan.band_luminosity,
                                  photons, plan.setup.track_scale * fs, plan.nvox_inv, plan.sigma_scale,
                                  plan.albedo, plan.setup.collision_scale * fs)
        # the stopping rule uses the statistical error alone (more packets do not shrink the
        # bias); the error reported adds the terminated packets' bias bound
        achieved = math.hypot(achieved, float(np.max(terminated_bias(tallies.counts))))
    has_image = plan.setup.peel is not None
    present = np.ones((nb, plan.setup.tail_hists), bool)
    if plan.setup.tail_classes:  # a depth class the grid does not reach has nothing to check
        present[:, int(has_image):] = class_cells(plan.setup.window, plan.setup.tail_edges) > 0
    limits = [IMAGE_ERROR_LIMIT] * int(has_image) + [J_ERROR_LIMIT] * plan.setup.tail_classes
    checks = check_histograms(tallies.tail_hist, band_done, limits, present) if tallies.tail_hist is not None else None
    tail_image = [row[0] for row in checks] if checks is not None and has_image else None
    tail_j = ([row[int(has_image):] for row in checks] if checks is not None and plan.setup.tail_classes
              else None)
    if not plan.setup.light_field:  # a peel-off image alone: no J was deposited
        device_sums = J = rel = s1 = s2 = None
    elif on_device and plan.setup.tree is not None:
        raise ValueError("a run on a tree estimates J on the host (on_device=False)")
    elif on_device:
        s1, s2, d_rho = session.release_sums()
        light = tallies.light if tallies.light is not None and tallies.light.done else None
        device_sums = DeviceSums(backend, shape, nb, s1, s2, d_rho, light=light)
        if tallies.light is not None and light is None:  # (its arrays made, the light not: a
            tallies.light.discard()  # batch traced again after the last fold, or a time limit)
        tallies.light = None
        J = rel = None
    else:
        device_sums = None
        s1, s2 = session.sums()
        J, rel = light_from_sums(s1, s2, folded, estimator, j_scale, plan.sigma_scale, plan.setup.density)
        if plan.setup.tree is not None:  # per leaf (n_bands, n_leaves), J over each leaf's volume
            J, rel, s1, s2 = (a.reshape(nb, -1) for a in (J, rel, s1, s2))
            J = J / tree_run.leaf_volumes(plan.setup.tree)[None, :]
    return TransportResult(
        J=J,
        rel_error=rel,
        counts=tallies.counts,
        packet_energy=q,
        band_luminosity=plan.band_luminosity,
        star_band_luminosity=plan.star_band_luminosity,
        photons=photons,
        batches=int(folded.min()),
        band_batches=folded,
        estimator=estimator,
        raw_sum=None if on_device else s1,
        raw_m2=None if on_device else s2,
        j_scale=j_scale,
        sigma_scale=plan.sigma_scale,
        device_sums=device_sums,
        achieved_error=achieved,
        photons_budget=plan.photons,
        device_bytes=tallies.device_bytes,
        peel_image=peel_image,
        peel_error=peel_error,
        peel_bin_batches=peel_groups,
        peel_stokes=stokes,
        peel_stokes_error=stokes_error,
        peel_stokes_bin_batches=stokes_groups,
        device=backend.device_name,
        timings={"setup_s": tallies.setup_s, "kernel_s": tallies.kernel_s, "reduce_s": tallies.reduce_s},
        reduce_path=tallies.reduce_path,
        method="biased" if plan.setup.biased else "analog",
        importance=plan.setup.importance if plan.setup.biased else "",
        error_estimate="packets" if plan.setup.packet_sq else "batches",
        weight_unit=WEIGHT_UNIT if plan.setup.biased else 1.0,
        tail_image=tail_image,
        tail_j=tail_j,
        tail_hist=tallies.tail_hist,
    )


def trace_request(density: np.ndarray, request, backend: Backend, *,
                  progress: Optional[Callable[[int, int], None]] = None,
                  cancel: Optional[Callable[[], bool]] = None, on_device: bool = False, comm=None,
                  _acc_limit_bits: int = 63, _checked_adds: bool = False, make_light: bool = False) -> TransportResult:
    """Trace ``request`` (a :class:`~nebula_rt.transport.request.TransportRequest`) through
    ``density`` on ``backend``: plan, run, estimate, and the warnings about trust (see
    :func:`nebula_rt.transport.trace` for every parameter; ``make_light``: the device sums
    go to :func:`~nebula_rt.transport.finish.finish` next, which may take the light made as
    they were folded, ``result.device_sums.light``).

    ``_acc_limit_bits`` (tests: a lower headroom limit) and ``_checked_adds`` (every deposit
    checked from the start) exercise the overflow paths.
    """
    t0 = time.perf_counter()
    plan = plan_transport(density, request, backend, checked_adds=_checked_adds, acc_limit_bits=_acc_limit_bits)
    make_light = make_light and on_device
    tallies = run_transport(plan, backend, progress=progress, cancel=cancel, started=t0, comm=comm,
                            make_light=make_light)
    try:
        if plan.setup.unchecked_adds and tallies.session.overflow_seen():
            # a cell reached the headroom limit unnoticed during a launch: trace again with
            # every add checked (same packets, same bits as a checked run)
            if tallies.light is not None:
                tallies.light.discard()
            tallies.session.close()
            plan = plan_transport(density, request, backend, checked_adds=True, acc_limit_bits=_acc_limit_bits)
            tallies = run_transport(plan, backend, progress=progress, cancel=cancel, started=t0, comm=comm,
                                    make_light=make_light)
        result = estimate_light(plan, tallies, backend, on_device=on_device)
    finally:
        if tallies.light is not None:  # (not handed on: an error came first)
            tallies.light.discard()
        tallies.session.close()
    warn_if_terminated(result.counts, list(plan.band_names), plan.setup.max_scatterings)
    warn_if_heavy_tailed(result, list(plan.band_names))
    result.ranks = 1 if comm is None else int(comm.size)
    result.timings["total_s"] = time.perf_counter() - t0
    return result
