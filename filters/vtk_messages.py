"""VTK's messages caught instead of printed (pyvista's catcher; it needs pyvista, which
ParaView's Python lacks: :mod:`.density_file` does without it there)."""

from __future__ import annotations

import contextlib
import threading

import pyvista as pv

_VTK_MESSAGES = threading.Lock()


class VtkMessages:
    """Within this block VTK's messages are caught instead of printed; ``errors`` afterwards
    holds the error messages (their text, without VTK's source location)."""

    def __enter__(self) -> "VtkMessages":
        _VTK_MESSAGES.acquire()
        self._stack = contextlib.ExitStack()
        try:
            self._stack.enter_context(pv.vtk_verbosity("off"))  # the logger's copy on stderr
            self._catcher = self._stack.enter_context(pv.VtkErrorCatcher(send_to_logging=False))
        except BaseException:
            self._stack.close()
            _VTK_MESSAGES.release()
            raise
        self.errors: list[str] = []
        return self

    def __exit__(self, *exc) -> None:
        try:
            self._stack.__exit__(*exc)
        finally:
            _VTK_MESSAGES.release()
        self.errors = [str(e.alert).strip() for e in self._catcher.error_events]
