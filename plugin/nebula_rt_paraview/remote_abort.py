"""ParaView's Abort button in a client/server session: the press travels to the pvserver.

In a client/server session the NebulaRT algorithms execute in the pvserver, and ParaView (5.11,
and its later versions alike) has no way to tell a server that the client's Abort button was
pressed: the client's abort reaches only algorithms of its own process. So the plugin opens a
second, small channel of its own:

- on the server (rank 0 of a pvserver), :class:`AbortPort` listens on a TCP port (an
  ephemeral one, or ``NEBULA_RT_ABORT_PORT``) and is an abort source of the NebulaRT
  algorithms (``nebula_rt.filters.base.ABORT_SOURCES``): a connection that sends the port's
  secret token, while an algorithm executes, aborts it. With several ranks the ranks decide
  together between launches (any rank's abort stops all), as for a signal.
- The proxies carry the port's address in an information property, ``AbortAddress``
  ("host port token"; information properties travel over ParaView's own connection and are
  not saved in state files), which the client reads when the proxy is made.
- In the GUI, :class:`AbortRelay` listens to the progress messages that a remote session
  sends during an execution: while one of a NebulaRT algorithm's arrives, the Abort button is
  enabled and heard (:class:`.abort.AbortButton`), and a press is sent to the server's port.

Progress messages come at most every :data:`PROGRESS_SECONDS` (the server's progress
handler is set to that while a NebulaRT algorithm executes; ParaView's default is 1 s), and
the server polls between launches of at most about 0.25 s, so a press stops the execution
within about half a second plus the network's delay. Through an SSH tunnel, forward the abort
port as well (fix it with ``NEBULA_RT_ABORT_PORT`` on the server); when the client cannot reach
it, the press is reported on the client's output and the execution runs on.
"""

from __future__ import annotations

import os
import secrets
import select
import socket
import sys
import time
from urllib.parse import urlsplit

#: the environment variable that fixes the server's abort port (default: an ephemeral port)
PORT_VARIABLE = "NEBULA_RT_ABORT_PORT"

#: the least time between two progress messages of the server while a NebulaRT algorithm
#: executes (s): the client hears a press at each
PROGRESS_SECONDS = 0.2

#: the information property that carries the server's abort address (every long-running
#: NebulaRT proxy has it: Nebula Dust Density, Nebula Light Field, Nebula Sky Image)
ADDRESS_PROPERTY = """
<StringVectorProperty name="AbortAddress" command="GetAbortAddress" information_only="1"
    number_of_elements="1" default_values="">
  <SimpleStringInformationHelper/>
  <Documentation>Where the pvserver hears the client's Abort button ("host port token"; empty in
    a built-in session).</Documentation>
</StringVectorProperty>"""

#: the server's abort port, once :func:`install` made one (None elsewhere)
SERVER_PORT: "AbortPort | None" = None

#: the GUI's relay, once :func:`install` made one (None elsewhere)
RELAY: "AbortRelay | None" = None


class Addressed:
    """Mix-in of the proxies' algorithms: ``GetAbortAddress`` for :data:`ADDRESS_PROPERTY`."""

    def GetAbortAddress(self) -> str:  # noqa: N802 - VTK's name
        return SERVER_PORT.address if SERVER_PORT is not None else ""


class AbortPort:
    """The server's abort port: a listening TCP socket, polled (never a thread: nothing runs
    between executions) as an abort source (``start``, ``poll``, ``stop``).

    Parameters
    ----------
    port : int
        the TCP port to listen on (0: one the system chooses).
    """

    def __init__(self, port: int = 0):
        self.token = secrets.token_hex(16)
        self._sock = socket.create_server(("", port), backlog=16)
        self._sock.setblocking(False)
        self.port = self._sock.getsockname()[1]
        self.address = f"{socket.gethostname()} {self.port} {self.token}"
        self._depth = 0
        self._requested = False

    def start(self, algorithm) -> None:
        """An execution begins: presses from before it are dropped, progress set to be sent
        every :data:`PROGRESS_SECONDS`."""
        self._depth += 1
        if self._depth > 1:
            return
        self._take_requests()
        self._requested = False
        _set_progress_interval(PROGRESS_SECONDS)

    def poll(self) -> bool:
        """True once a press arrived during this execution."""
        if not self._requested:
            self._take_requests()
        return self._requested

    def stop(self) -> None:
        self._depth = max(0, self._depth - 1)

    def _take_requests(self) -> None:
        while select.select([self._sock], [], [], 0)[0]:
            try:
                conn, _ = self._sock.accept()
            except (BlockingIOError, InterruptedError):
                return
            with conn:
                conn.settimeout(0.5)  # (the client sends its token at once)
                try:
                    said = conn.recv(256).strip()
                except OSError:
                    continue
            if said == self.token.encode():
                self._requested = True


def _set_progress_interval(seconds: float) -> None:
    try:
        from paraview.modules.vtkRemotingCore import vtkProcessModule
    except ImportError:  # (no ParaView: no progress messages to pace)
        return

    session = vtkProcessModule.GetProcessModule().GetActiveSession()
    handler = session.GetProgressHandler() if session is not None else None
    if handler is not None and handler.GetProgressInterval() > seconds:
        handler.SetProgressInterval(seconds)


def send_abort(address: str, uri: str, timeout: float = 2.0) -> None:
    """Send the abort to the server whose ``AbortAddress`` is ``address``; the host is the
    session URI's (``cs://host:port``: the host the client reached), else the server's own
    name (a reverse connection). Raises OSError when the port cannot be reached."""
    host, port, token = address.split()
    reached = urlsplit(uri).hostname if uri.startswith("cs://") else None
    with socket.create_connection((reached or host, int(port)), timeout=timeout) as conn:
        conn.sendall(token.encode() + b"\n")


class AbortRelay:
    """The GUI's side in a client/server session: hears the Abort button while a remote
    NebulaRT algorithm sends progress, and sends a press to the server.

    Attributes
    ----------
    pressed_at, sent_at, ended_at : float or None
        ``time.monotonic()`` of the last remote execution's press, of its sending and of the
        execution's end (as the client heard it), which the GUI tests compare.
    """

    def __init__(self, button):
        self.button = button  # an abort.AbortButton (its start/poll/stop)
        self._watched = set()
        self._active = None  # the session whose NebulaRT execution is under way
        self.pressed_at = self.sent_at = self.ended_at = None

    def watch(self, session) -> None:
        """Listen to a remote session's progress messages (a built-in session's executions
        reach the button directly)."""
        if session is None or not session.IsA("vtkSMSessionClient") or id(session) in self._watched:
            return
        self._watched.add(id(session))
        handler = session.GetProgressHandler()
        handler.AddObserver("ProgressEvent", lambda h, e: self._on_progress(session, h))
        handler.AddObserver("EndEvent", lambda h, e: self._on_end(session))

    def _on_progress(self, session, handler) -> None:
        if self._active is None:
            if not (handler.GetLastProgressText() or "").startswith("NebulaRT"):
                return
            self._active = session
            self.pressed_at = self.sent_at = self.ended_at = None
            self.button.start(None)
        if self.button.poll() and self.sent_at is None:
            self.pressed_at = self.button.pressed_at
            self.sent_at = time.monotonic()
            self._send(session)

    def _on_end(self, session) -> None:
        if self._active is session:
            self._active = None
            self.button.stop()
            self.ended_at = time.monotonic()

    def _send(self, session) -> None:
        address = _server_address(session)
        try:
            if not address:
                raise OSError("the server has no abort port (is the NebulaRT plugin loaded there?)")
            send_abort(address, session.GetURI())
        except (OSError, ValueError) as exc:
            sys.stderr.write(f"NebulaRT warning: the Abort button could not reach the server ({exc}); the "
                             f"execution runs on (is the server's abort port, {PORT_VARIABLE}, reachable?)\n")


def _server_address(session) -> str:
    """The ``AbortAddress`` of any NebulaRT proxy of ``session`` (the port is the server's,
    one for all; read from the client's copy of the property, no round trip)."""
    from paraview.modules.vtkRemotingServerManager import vtkSMProxyIterator

    it = vtkSMProxyIterator()
    it.SetSession(session)
    it.SetModeToOneGroup()
    it.Begin("sources")
    while not it.IsAtEnd():
        prop = it.GetProxy().GetProperty("AbortAddress")
        if prop is not None and prop.GetNumberOfElements() and prop.GetElement(0):
            return prop.GetElement(0)
        it.Next()
    return ""


def _rank() -> int:
    from nebula_rt.filters.controller import vtk_world

    return vtk_world().rank


def install(button=None):
    """In a pvserver (rank 0): open the abort port and add it to the abort sources. In the
    GUI (``button``, the :class:`.abort.AbortButton`): relay its presses from every remote
    session, present and future. Returns what it made (None in other processes)."""
    global SERVER_PORT, RELAY
    from paraview.modules.vtkRemotingCore import vtkProcessModule

    from nebula_rt.filters import base

    pm = vtkProcessModule.GetProcessModule()
    if pm is None:
        return None
    if pm.GetProcessType() in (vtkProcessModule.PROCESS_SERVER, vtkProcessModule.PROCESS_DATA_SERVER):
        if SERVER_PORT is None and _rank() == 0:
            port = os.environ.get(PORT_VARIABLE, "0")
            try:
                SERVER_PORT = AbortPort(int(port))
            except (OSError, ValueError) as exc:
                sys.stderr.write(f"NebulaRT warning: no abort port ({PORT_VARIABLE}={port!r}: {exc}); the "
                                 "client's Abort button cannot stop executions here\n")
                return None
            base.ABORT_SOURCES.append(SERVER_PORT)
        return SERVER_PORT
    if button is None or pm.GetProcessType() != vtkProcessModule.PROCESS_CLIENT:
        return None
    relay = RELAY = AbortRelay(button)

    def on_connection(obj, event):
        relay.watch(obj.GetSession(obj.GetEventCallDataSessionId()))

    pm.AddObserver("ConnectionCreatedEvent", on_connection)
    relay.watch(pm.GetActiveSession())
    return relay
