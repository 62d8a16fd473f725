"""Shared behaviour of the NebulaRT VTK algorithms."""

from __future__ import annotations

import numbers
import re
import sys
import warnings

from vtkmodules.util.vtkAlgorithm import VTKPythonAlgorithmBase
from vtkmodules.vtkCommonCore import vtkOutputWindow, vtkStringArray

from nebula_rt.scene import schema
from nebula_rt import scene as _scene
from nebula_rt.optics.bands import reference_band_index
from nebula_rt.errors import CancelledError, NebulaError, NebulaWarning, SceneError

from .properties import inert_properties

#: The flat ``Stars`` property (the filters' and ParaView's table), one row per star:
#: (column header, the star's scene field, component of it or None). The scene's Star
#: declarations give every column its meaning, unit and range; the table writes an omitted
#: field (None) as its ``STAR_NONE_AS`` number.
STAR_COLUMNS = (("X", "position", 0), ("Y", "position", 1), ("Z", "position", 2),
                ("Luminosity", "luminosity", None), ("Temperature", "temperature", None),
                ("Bump Radius", "bump_radius", None))
#: a table's number for an omitted field, and what it means: temperature 0 = no spectrum
#: (every band an equal share)
STAR_NONE_AS = {"temperature": (0.0, "flat spectrum")}


def stars_from_flat(values) -> list[dict]:
    """Scene-file star tables from the flat ``Stars`` vector (a row of ``STAR_COLUMNS`` per
    star).

    A temperature of exactly 0 means no spectrum (flat), as in a scene file; any other value
    goes to the scene's validation (a negative or NaN temperature is an error, not a flat
    spectrum)."""
    width = len(STAR_COLUMNS)
    allowed = (f"must hold {width} numbers per star: "
               + ", ".join(h.lower() + (" ({:g} = {})".format(*STAR_NONE_AS[f]) if f in STAR_NONE_AS else "")
                           for h, f, _c in STAR_COLUMNS))
    try:
        vals = list(values)
    except TypeError:
        raise SceneError("Stars", values, allowed) from None
    if not vals or len(vals) % width or not all(
            isinstance(v, numbers.Real) and not isinstance(v, bool) for v in vals):
        raise SceneError("Stars", vals, allowed)
    out = []
    for i in range(0, len(vals), width):
        star = {}
        if all(float(v) == 0.0 for v in vals[i:i + width]):
            # ParaView's "+" on an emptied table adds a row of blank cells, which reach the
            # property as zeros: a star nobody could mean (no light, in a corner). It is the
            # default star, and the message says so (the cells still show zeros).
            warnings.warn(NebulaWarning(
                f"Stars: row {i // width + 1} is blank (all 0, what '+' gives on an emptied table): it is "
                f"the default star ({', '.join(f'{h} {v:g}' for (h, _f, _c), v in zip(STAR_COLUMNS, default_star_row()))}); "
                "type its values into the row"))
            vals = vals[:i] + default_star_row() + vals[i + width:]
        for (_h, field, comp), v in zip(STAR_COLUMNS, vals[i:i + width]):
            if comp is not None:
                star.setdefault(field, []).append(float(v))
            else:
                star[field] = float(v)
        out.append(star)
    return out


#: field-data string of an output a NebulaRT filter emptied because it failed: the error
FAILURE = "nebula_rt_failure"


def failure_of(data) -> str | None:
    """The error that emptied ``data`` upstream (its ``FAILURE`` field-data string), if any."""
    fd = data.GetFieldData() if data is not None else None
    arr = fd.GetAbstractArray(FAILURE) if fd is not None else None
    return arr.GetValue(0) if arr is not None and arr.GetNumberOfValues() else None


def _arrays_mtime(data) -> int:
    """The latest modification time of a dataset's point and cell arrays (0 for none): what
    changes when its values change (the data object's own time also moves when a pipeline
    only re-negotiates its extent)."""
    if data is None:
        return 0
    if not hasattr(data, "GetCellData"):  # a composite dataset (an AMR hierarchy): its own time
        return int(data.GetMTime())
    times = [0]
    # (a hyper tree grid has cell data only)
    for attrs in (getattr(data, "GetPointData", lambda: None)(), data.GetCellData()):
        if attrs is None:
            continue
        for i in range(attrs.GetNumberOfArrays()):
            arr = attrs.GetAbstractArray(i)
            if arr is not None:
                times.append(arr.GetMTime())
    return max(times)


def _empty(data) -> bool:
    """Whether an input holds nothing to work on: no points (a dataset), no cells (a hyper
    tree grid, an AMR hierarchy)."""
    if data is None:
        return True
    if hasattr(data, "GetNumberOfPoints") and not data.IsA("vtkHyperTreeGrid"):
        return data.GetNumberOfPoints() == 0
    return data.GetNumberOfCells() == 0


def default_star_row() -> list:
    """The Stars property's row (``STAR_COLUMNS``) of the scene's default star."""
    star = _scene.Star()
    row = []
    for _h, field, comp in STAR_COLUMNS:
        v = getattr(star, field)
        row.append(float(STAR_NONE_AS[field][0] if v is None else v if comp is None else v[comp]))
    return row


def default_reference_band():
    """The reference band of the scene's default band preset (where a panel shows Albedo and G
    before they are set)."""
    bands = _scene.BandsConfig().resolve()
    return bands[reference_band_index(bands)]


#: Where a request to abort can come from besides the algorithm's own ``AbortExecute`` flag:
#: objects with ``start(algorithm)`` and ``stop()`` (around each execution) and ``poll() ->
#: bool`` (at each of its abort polls). Plain VTK has none; the ParaView GUI adds its Abort
#: button (``plugin/nebula_rt_paraview/abort.py``).
ABORT_SOURCES: list = []

#: The star fields of the flat Stars property, by scene key.
_STAR_KEY = re.compile(r"^stars\[(\d+)\]\.(\w+)$")


class NebulaAlgorithm(VTKPythonAlgorithmBase):
    """Base class: error reporting, progress, abort and an execution counter.

    Any exception of an execution (NebulaRT's own, the runtime's, a bug) ends it with an empty
    output, ``last_error`` set and one message on VTK's output window; nothing escapes into
    VTK's executive (which would print a traceback and two more errors, and leave the output
    half made). ``PROPERTIES`` maps scene keys to the setters' property names, so a message
    says which property to change (``dust.tau = 1e+39: ... (property Tau)``).
    """

    #: scene key -> property name (subclasses); star keys map to "Stars"
    PROPERTIES: dict = {}

    def __init__(self, **kw):
        super().__init__(**kw)
        self.execution_count = 0
        self.last_error: str | None = None
        #: the NebulaWarning texts of the last execution (also shown as VTK warnings)
        self.last_warnings: list[str] = []

    # -- what an "auto" property chose ---------------------------------------------------------
    def chosen(self, name: str) -> float:
        """The value the last execution used for the "auto or number" property ``name``
        (``Exposure``, ``OpacityScale``): its output's field data of that key (``exposure``,
        ``opacity_scale``), which the filters write whether it was chosen from the data or
        given; NaN before a successful execution. The ParaView proxies hold it in an
        information property, ``<name>Chosen`` (5.11's panel does not show those)."""
        key = re.sub(r"(?<!^)(?=[A-Z])", "_", name).lower()
        out = self.GetOutputDataObject(0) if self.GetNumberOfOutputPorts() else None
        arr = out.GetFieldData().GetArray(key) if out is not None else None
        return float(arr.GetValue(0)) if arr is not None and arr.GetNumberOfTuples() else float("nan")

    def GetExposureChosen(self) -> float:
        return self.chosen("Exposure")

    def GetOpacityScaleChosen(self) -> float:
        return self.chosen("OpacityScale")

    # -- progress and abort ------------------------------------------------------------------
    def _report(self, fraction: float, text: str) -> None:
        self.SetProgressText(text)
        self.UpdateProgress(min(max(float(fraction), 0.0), 1.0))

    def _abort_requested(self) -> bool:
        check = getattr(self, "CheckAbort", None)  # VTK >= 9.3 (ParaView >= 5.12 honours it)
        if check is not None and check():
            return True
        if any([src.poll() for src in ABORT_SOURCES]):  # (every source polled: each may need to run)
            self.SetAbortExecute(1)
        return bool(self.GetAbortExecute())

    def _progress_callback(self, what: str):
        def progress(done: int, total: int) -> None:
            self._report(done / max(total, 1), f"NebulaRT: {what} {done:,} of {total:,} packets per band")
        return progress

    # -- execution -----------------------------------------------------------------------------
    def RequestUpdateExtent(self, request, inInfo, outInfo):
        """Always ask for the whole input, as piece 0 of 1: the transport needs every voxel on
        every rank (a piece-aware reader in a parallel ParaView would otherwise give each rank
        a slab), and a sub-extent request (e.g. from a 2D sky image downstream) would
        re-execute the upstream filters. Letting the upstream make pieces and gathering them
        was measured and not taken: no faster for readers or the Dust Density source, and
        more memory (benchmarks/bench_density_gather.py, docs/domain_decomposition.md)."""
        from vtkmodules.vtkCommonExecutionModel import vtkStreamingDemandDrivenPipeline as sddp

        for port in range(self.GetNumberOfInputPorts()):
            for conn in range(inInfo[port].GetNumberOfInformationObjects()):
                info = inInfo[port].GetInformationObject(conn)
                info.Set(sddp.UPDATE_PIECE_NUMBER(), 0)
                info.Set(sddp.UPDATE_NUMBER_OF_PIECES(), 1)
                info.Set(sddp.UPDATE_NUMBER_OF_GHOST_LEVELS(), 0)
                if info.Has(sddp.WHOLE_EXTENT()):
                    info.Set(sddp.UPDATE_EXTENT(), *info.Get(sddp.WHOLE_EXTENT()))
        return 1

    def RequestData(self, request, inInfo, outInfo):
        self.execution_count += 1
        output = self.GetOutputData(outInfo, 0)
        inp = self.GetInputData(inInfo, 0, 0) if self.GetNumberOfInputPorts() > 0 else None
        # An empty output never satisfies a request for the whole extent, so ParaView runs a
        # failed algorithm again for every consumer of one Apply (the colour filter, the data
        # information, the representation): the same inputs and properties fail the same
        # way, so they are not run (nor reported) again until one of them changes.
        key = (self.GetMTime(), _arrays_mtime(inp))
        if self.last_error is not None and key == getattr(self, "_failed_key", None):
            self._empty_outputs(outInfo, self.last_error)
            return 1
        self._failed_key = None
        self.last_error = None
        self.last_warnings = []
        if self.GetNumberOfInputPorts() > 0:
            if _empty(inp):
                # an upstream NebulaRT filter that failed said why: pass the emptiness on
                # instead of leaving a stale result downstream; an empty input nothing
                # explained (a reader's empty image, an empty source) is reported here
                reason = failure_of(inp)
                if reason is None:
                    self.last_error = reason = f"{type(self).__name__}: " + self.describe_error(SceneError(
                        "input", "an empty image (0 points)",
                        "must be an image with points and arrays (e.g. Nebula Dust Density's output)"))
                    self._failed_key = key
                    vtkOutputWindow.GetInstance().DisplayErrorText(f"NebulaRT error: {self.last_error}\n")
                self._empty_outputs(outInfo, reason)
                return 1
        try:
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always", NebulaWarning)
                for text in inert_properties(self) + self.inert_messages():
                    warnings.warn(text, NebulaWarning)
                for src in ABORT_SOURCES:
                    src.start(self)
                try:
                    self._execute(request, inInfo, outInfo)
                finally:
                    for src in ABORT_SOURCES:
                        src.stop()
                self._crop_to_request(outInfo.GetInformationObject(0), output)
            self._surface_warnings(caught)
            self._report(1.0, "")
        except Exception as exc:  # noqa: BLE001 - every failure ends as a reported empty output
            kind = "cancelled" if isinstance(exc, CancelledError) else "error"
            self._abort_if_distributed(exc)
            if isinstance(exc, CancelledError):
                # VTK 9.2 (ParaView 5.11) does not clear the flag before the next execution:
                # without this every later update would be cancelled at once. Clearing it
                # modifies the algorithm, so the key of this failure is taken after: else the
                # next consumer of the same Apply (the representation, the data information)
                # would start the cancelled trace again from the beginning
                self.SetAbortExecute(0)
                key = (self.GetMTime(), key[1])
            self.last_error = f"{type(self).__name__}: {self.describe_error(exc)}"
            self._failed_key = key
            self._empty_outputs(outInfo, self.last_error)  # no half-made output
            vtkOutputWindow.GetInstance().DisplayErrorText(f"NebulaRT {kind}: {self.last_error}\n")
        # Succeed either way: an empty output (with the error on the output window) lets
        # downstream filters re-execute to empty rather than keep stale data.
        return 1

    def _empty_outputs(self, outInfo, reason: str | None = None) -> None:
        """Empty every output, each carrying ``reason`` (the error that emptied it, the
        field-data string ``FAILURE``), so that the filters downstream pass the emptiness on
        quietly instead of reporting an empty input nobody explained."""
        for port in range(self.GetNumberOfOutputPorts()):
            out = self.GetOutputData(outInfo, port)
            if out is not None:
                out.Initialize()
                if reason is not None:
                    mark = vtkStringArray()
                    mark.SetName(FAILURE)
                    mark.InsertNextValue(reason)
                    out.GetFieldData().AddArray(mark)

    def _abort_if_distributed(self, exc: BaseException) -> None:
        """In a parallel ParaView a failure of one rank's transport (other than a cancel, which
        the ranks decide together) would leave the others waiting in their next reduction:
        the job is ended instead, with the rank and the cause on stderr."""
        if isinstance(exc, CancelledError) or not getattr(self, "distributed", False):
            return
        from .controller import vtk_world

        comm = vtk_world()
        if comm.size < 2:
            return
        sys.stderr.write(f"NebulaRT error (rank {comm.rank} of {comm.size}): {type(self).__name__}: "
                         f"{self.describe_error(exc)}; ending the job\n")
        sys.stderr.flush()
        comm.abort(1)

    @staticmethod
    def _crop_to_request(info, output) -> None:
        """An image output computed whole is cropped to the extent asked of it (the piece of
        this rank in a parallel ParaView, which renders and writes the pieces together)."""
        from vtkmodules.vtkCommonDataModel import vtkImageData
        from vtkmodules.vtkCommonExecutionModel import vtkStreamingDemandDrivenPipeline as sddp

        if not isinstance(output, vtkImageData) or not info.Has(sddp.UPDATE_EXTENT()):
            return
        want = list(info.Get(sddp.UPDATE_EXTENT()))
        have = list(output.GetExtent())
        if want != have and all(want[2 * a] >= have[2 * a] and want[2 * a + 1] <= have[2 * a + 1]
                                and want[2 * a] <= want[2 * a + 1] for a in range(3)):
            output.Crop(want)

    def property_name(self, parameter: str):
        """The property behind a scene key (None if no property sets it)."""
        m = _STAR_KEY.match(parameter)
        if m and hasattr(self, "SetStars"):
            return f"Stars: star {m.group(1)} {m.group(2)}"
        for prop in getattr(self, "BOUND_PROPERTIES", ()):
            if prop.key == parameter:
                return schema.label(prop.key, prop.param)
        return self.PROPERTIES.get(parameter)

    def describe_error(self, exc: BaseException) -> str:
        """A message for ``last_error``: a SceneError with the property that sets its parameter,
        NebulaRT's other errors as they are, anything else with its type (pyopencl's
        LogicError, MemoryError, ...), since its text alone may not say what failed."""
        if isinstance(exc, SceneError):
            bound = any(p.key == exc.parameter for p in getattr(self, "BOUND_PROPERTIES", ()))
            prop = self.property_name(exc.parameter)
            if bound:  # as the panel shows it, then the scene key: "Tau (dust.tau) = 1e+39: ..."
                return f"{prop} ({exc.parameter}) = {exc.value!r}: {exc.allowed}"
            return f"{exc} (property {prop})" if prop and prop != exc.parameter else str(exc)
        if isinstance(exc, NebulaError):
            return str(exc)
        return f"{type(exc).__name__}: {exc}"

    def _surface_warnings(self, caught) -> None:
        """NebulaWarnings go to VTK's output window as warnings (ParaView shows them); any
        other warning is passed on to Python's warning machinery unchanged."""
        for w in caught:
            if issubclass(w.category, NebulaWarning):
                text = f"{type(self).__name__}: {w.message}"
                if text in self.last_warnings:  # (a step asked twice in one execution)
                    continue
                self.last_warnings.append(text)
                vtkOutputWindow.GetInstance().DisplayWarningText(f"NebulaRT warning: {text}\n")
            else:
                warnings.warn_explicit(w.message, w.category, w.filename, w.lineno, source=w.source)

    def inert_messages(self) -> list:
        """Messages for settings that have no effect now beyond the panel's rules
        (:func:`~nebula_rt.filters.properties.inert_properties`); an algorithm with such cases
        overrides this."""
        return []

    def _execute(self, request, inInfo, outInfo) -> None:  # pragma: no cover - abstract
        raise NotImplementedError


def shallow_copy_image(out, inp) -> None:
    """``out.ShallowCopy(inp)`` with field data of its own (ShallowCopy shares the container,
    so adding field data to the output would change the input)."""
    from vtkmodules.vtkCommonDataModel import vtkFieldData

    out.ShallowCopy(inp)
    fd = vtkFieldData()
    fd.ShallowCopy(inp.GetFieldData())
    out.SetFieldData(fd)
