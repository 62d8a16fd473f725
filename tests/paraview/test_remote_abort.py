"""The server's side of the client/server Abort (plugin/nebula_rt_paraview/remote_abort.py),
with real sockets: what it accepts as a press and when. The GUI's side, with ParaView and a
real click, is tests/paraview/test_paraview_gui.py's
``test_abort_stops_a_trace_in_a_pvserver_within_a_second``."""

from __future__ import annotations

import importlib.util
import socket
import time
from pathlib import Path

import pytest


def _module():
    """The module loaded as a file: it needs only the standard library until it is installed
    in a ParaView process."""
    path = Path(__file__).resolve().parents[2] / "plugin" / "nebula_rt_paraview" / "remote_abort.py"
    spec = importlib.util.spec_from_file_location("remote_abort", path)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.fixture()
def port():
    mod = _module()
    p = mod.AbortPort(0)
    yield mod, p
    p._sock.close()


def _say(port, text: bytes):
    with socket.create_connection(("localhost", port.port), timeout=5) as conn:
        conn.sendall(text)


def _polled(port, seconds: float = 2.0) -> bool:
    """Poll as an execution does (between launches) until it says abort or time is up."""
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        if port.poll():
            return True
        time.sleep(0.02)
    return False


def test_the_token_during_an_execution_aborts_it(port):
    mod, p = port
    host, number, token = p.address.split()
    assert int(number) == p.port and token == p.token and len(token) == 32 and host
    p.start(None)
    assert not p.poll()
    mod.send_abort(p.address, f"cs://localhost:{p.port + 1}")  # (the host is the session URI's)
    assert _polled(p)
    assert p.poll()  # (it stays said until the execution ends)
    p.stop()


def test_anything_but_the_token_is_ignored(port):
    _, p = port
    p.start(None)
    _say(p, b"0" * 32 + b"\n")
    _say(p, b"")
    _say(p, p.token[:-1].encode() + b"\n")
    assert not _polled(p, 0.5)
    p.stop()


def test_a_press_before_an_execution_does_not_abort_it(port):
    mod, p = port
    mod.send_abort(p.address, f"cs://localhost:{p.port}")
    time.sleep(0.2)
    p.start(None)
    assert not _polled(p, 0.5)
    p.stop()
    # a nested execution's start does not drop the press of the one that contains it
    p.start(None)
    mod.send_abort(p.address, f"cs://localhost:{p.port}")
    assert _polled(p)
    p.start(None)
    assert p.poll()
    p.stop()
    p.stop()


def test_an_unreachable_server_is_an_error_to_report():
    mod = _module()
    with socket.socket() as s:
        s.bind(("localhost", 0))
        free = s.getsockname()[1]
    with pytest.raises(OSError):
        mod.send_abort(f"localhost {free} {'0' * 32}", f"cs://localhost:{free}")
