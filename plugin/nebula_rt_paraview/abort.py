"""ParaView's Abort button, heard while a NebulaRT algorithm executes in the GUI.

ParaView 5.11 runs a filter on the GUI's own thread and lets Qt process no event until the
filter returns; the Abort button beside its progress bar stays disabled, and its signal is
connected to nothing (the abort of running filters came with VTK 9.3's
``vtkAlgorithm::CheckAbort``, which ParaView 5.12 drives). So in the GUI, while a NebulaRT
algorithm executes, :class:`AbortButton`

- enables that button and hears its press, a flag that the algorithm's abort poll reads
  (``nebula_rt.filters.base.ABORT_SOURCES``; the polls come between kernel launches, which last
  at most about 0.25 s, and in every filter stage),
- at each poll, at most every :data:`EVENT_SECONDS`, lets Qt deliver the window system's
  pending events (repaints, the mouse), but no timer and no socket notifier: nothing that
  ParaView schedules (a deferred render, auto-apply, a server's message) runs inside the
  executing filter,
- swallows every keyboard and mouse input meant for another widget meanwhile, so that nothing a
  user clicks can start inside the executing filter (ParaView itself delivers those clicks once
  the filter returns, which is as useless),
- and restores the button (disabled, disconnected) when the execution ends.

Qt is reached through PyQt5 built for the same Qt library that ParaView links (Debian's
``python3-pyqt5``; ``scripts/setup.sh``). Without PyQt5, or without a QApplication (pvpython,
pvbatch, pvserver, plain VTK), nothing is installed and nothing changes.
"""

from __future__ import annotations

import time

#: the least time between two deliveries of the GUI's pending events during an execution (s)
EVENT_SECONDS = 0.05


class AbortButton:
    """ParaView's progress-bar Abort button as an abort source of the NebulaRT algorithms
    (``start(algorithm)``, ``poll() -> bool``, ``stop()``; see
    :data:`nebula_rt.filters.base.ABORT_SOURCES`).

    Attributes
    ----------
    pressed_at, stopped_at : float or None
        ``time.monotonic()`` of the last execution's press of the button (None: not pressed)
        and of its end, which the GUI tests compare.
    """

    def __init__(self, qt):
        self._qt = qt
        self._button = None
        self._blocker = None
        self._depth = 0
        self._last_events = 0.0
        self.pressed_at = None
        self.stopped_at = None
        self._broken = None  # the Qt error that turned this source off, if one did

    def _find_button(self):
        QtWidgets = self._qt.QtWidgets
        app = QtWidgets.QApplication.instance()
        if app is None:
            return None
        for w in app.allWidgets():
            if w.objectName() == "AbortButton" and isinstance(w, QtWidgets.QAbstractButton):
                parent = w.parentWidget()
                if parent is not None and parent.metaObject().className() == "pqProgressWidget":
                    return w
        return None

    def _guarded(self, step, *args):
        """Run a step; a Qt error turns this source off (said once on stderr) instead of
        failing the executing filter: the filters then run as without a GUI."""
        if self._broken is not None:
            return None
        try:
            return step(*args)
        except Exception as exc:  # noqa: BLE001 - the GUI's state is ParaView's, not ours
            import sys

            self._broken = exc
            self._button = None
            sys.stderr.write(f"NebulaRT warning: the Abort button cannot be reached ({exc!r}); "
                             "traces run to the end\n")
            return None

    def start(self, algorithm) -> None:
        """An execution begins: the button enabled and heard (nested executions share it)."""
        self._guarded(self._start)

    def poll(self) -> bool:
        """True once the button was pressed during this execution; delivers the GUI's pending
        window-system events first (at most every :data:`EVENT_SECONDS`)."""
        return bool(self._guarded(self._poll))

    def stop(self) -> None:
        """The execution ended: the button disabled, the input let through."""
        self._guarded(self._stop)

    def _start(self) -> None:
        self._depth += 1
        if self._depth > 1:
            return
        self.pressed_at = self.stopped_at = None
        self._button = self._find_button()
        if self._button is None:
            return
        app = self._qt.QtWidgets.QApplication.instance()
        self._blocker = _InputBlocker(self._qt, self._button, self._on_press)
        app.installEventFilter(self._blocker)
        self._button.setEnabled(True)
        self._button.repaint()
        self._last_events = 0.0

    def _on_press(self) -> None:
        if self.pressed_at is None:
            self.pressed_at = time.monotonic()

    def _poll(self) -> bool:
        if self._button is None:
            return False
        now = time.monotonic()
        if now - self._last_events >= EVENT_SECONDS:
            self._last_events = now
            loop = self._qt.QtCore.QEventLoop
            self._qt.QtCore.QCoreApplication.processEvents(
                loop.AllEvents | loop.X11ExcludeTimers | loop.ExcludeSocketNotifiers)
        return self.pressed_at is not None

    def _stop(self) -> None:
        self._depth = max(0, self._depth - 1)
        if self._depth:
            return
        self.stopped_at = time.monotonic()
        button, self._button = self._button, None
        if button is None:
            return
        button.setEnabled(False)
        app = self._qt.QtWidgets.QApplication.instance()
        if app is not None and self._blocker is not None:
            app.removeEventFilter(self._blocker)
        self._blocker = None


def _InputBlocker(qt, button, on_press):
    """A Qt event filter (made here: its class needs PyQt5) that hears a press of ``button``
    and swallows keyboard and mouse input meant for any other widget, and every shortcut.

    The press is recognised by its position where it first arrives, at the top-level window:
    ParaView's own event filter (pqProgressManager) swallows every mouse press there while a
    filter executes, before Qt could forward it to the button. (Application event filters run
    newest first, so this one sees the press before ParaView's.)"""
    QEvent = qt.QtCore.QEvent
    blocked = {QEvent.MouseButtonPress, QEvent.MouseButtonRelease, QEvent.MouseButtonDblClick, QEvent.KeyPress,
               QEvent.KeyRelease, QEvent.Wheel, QEvent.ShortcutOverride, QEvent.Shortcut, QEvent.ContextMenu,
               QEvent.Drop, QEvent.TabletPress}
    address = qt.sip.unwrapinstance(button)  # (PyQt may wrap one widget in several objects)

    class InputBlocker(qt.QtCore.QObject):
        def eventFilter(self, obj, event):  # noqa: N802 - Qt's name
            kind = event.type()
            if kind not in blocked:
                return False
            if kind == QEvent.MouseButtonPress and not obj.isWidgetType():
                if button.isVisible() and button.rect().contains(button.mapFromGlobal(event.globalPos())):
                    on_press()
                return True
            if kind in (QEvent.Shortcut, QEvent.ShortcutOverride):
                return True
            return bool(obj.isWidgetType() and qt.sip.unwrapinstance(obj) != address)

    return InputBlocker()


def install() -> AbortButton | None:
    """Add ParaView's Abort button to the NebulaRT algorithms' abort sources, where this
    process has a Qt GUI and PyQt5 (once); returns the source, or None."""
    from nebula_rt.filters import base

    for src in base.ABORT_SOURCES:
        if isinstance(src, AbortButton):
            return src
    try:
        from PyQt5 import QtCore, QtWidgets, sip
    except ImportError:
        return None
    if QtWidgets.QApplication.instance() is None:
        return None

    class Qt:
        pass

    Qt.QtCore, Qt.QtWidgets, Qt.sip = QtCore, QtWidgets, sip
    src = AbortButton(Qt)
    base.ABORT_SOURCES.append(src)
    return src
