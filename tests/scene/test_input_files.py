"""Input files are checked for what they are before they are read: a FIFO, a device, a folder
or a symlink loop is refused at once by name (a FIFO would block the read forever, /dev/zero
would never end), a file larger than its kind may be is refused before it is read, and UTF-8
text with a byte-order mark reads as text."""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest

from nebula_rt.errors import SceneError
from nebula_rt.input_files import MAX_TABLE_BYTES, check_input_file, read_input_text
from nebula_rt.scene import Scene

RUN = [sys.executable, "-m", "nebula_rt.cli"]


@pytest.fixture()
def fifo(tmp_path):
    p = tmp_path / "pipe.npy"
    os.mkfifo(p)
    return p


@pytest.fixture()
def loop(tmp_path):
    a, b = tmp_path / "a.toml", tmp_path / "b.toml"
    a.symlink_to(b)
    b.symlink_to(a)
    return a


def _special(request, kind, tmp_path):
    if kind == "fifo":
        return request.getfixturevalue("fifo"), "FIFO"
    if kind == "device":
        return "/dev/zero", "character device"
    if kind == "folder":
        return tmp_path, "folder"
    return request.getfixturevalue("loop"), "symbolic link loop"


@pytest.mark.parametrize("kind", ["fifo", "device", "folder", "loop"])
def test_special_files_are_refused_by_name(request, kind, tmp_path):
    path, words = _special(request, kind, tmp_path)
    with pytest.raises(SceneError, match=words) as e:
        check_input_file("dust.file", path, "a .npy or .vti file")
    assert e.value.parameter == "dust.file" and e.value.value == str(path)


def test_missing_and_oversized_files_are_refused(tmp_path):
    with pytest.raises(SceneError, match="no such file"):
        check_input_file("--table", tmp_path / "none.csv")
    big = tmp_path / "big.csv"
    with open(big, "wb") as fh:
        fh.truncate(MAX_TABLE_BYTES + 1)  # sparse: no disk used
    with pytest.raises(SceneError, match=f"more than the {MAX_TABLE_BYTES}"):
        check_input_file("--table", big, "a CSV or ECSV table", MAX_TABLE_BYTES)


def test_utf8_with_a_byte_order_mark_reads_as_text(tmp_path):
    p = tmp_path / "t.csv"
    p.write_bytes(b"\xef\xbb\xbfa,b\n1,2\n")
    assert read_input_text("--table", p) == "a,b\n1,2\n"
    p.write_bytes(b"a,b\n\xff,2\n")
    with pytest.raises(SceneError, match="0xff at offset 4 is not UTF-8"):
        read_input_text("--table", p)


@pytest.mark.parametrize("kind", ["fifo", "device", "folder", "loop"])
def test_a_scene_and_its_density_file_refuse_special_files(request, kind, tmp_path):
    """Scene.load and a file density (hashed for the cache key, then read) refuse at once."""
    path, words = _special(request, kind, tmp_path)
    with pytest.raises(SceneError, match=words):
        Scene.load(path)
    scene = Scene.from_dict({"grid": {"shape": [4, 4, 4]}, "dust": {"model": "file", "file": str(path)}})
    from nebula_rt.pipeline.stages import dust_file_digest
    from nebula_rt.density.generate import load_density_file

    with pytest.raises(SceneError, match=words):
        dust_file_digest(scene)
    with pytest.raises(SceneError, match=words):
        load_density_file(path, "density", (4, 4, 4))


def test_a_npy_header_of_another_shape_is_refused_before_its_data_is_read(tmp_path):
    """A .npy whose header claims 2^40 floats (the file holds none of them) is refused by its
    header, naming the shapes, without allocating."""
    p = tmp_path / "huge.npy"
    with open(p, "wb") as fh:
        np.lib.format.write_array_header_1_0(fh, {"descr": "<f4", "fortran_order": False, "shape": (1 << 14,) * 3})
    with pytest.raises(SceneError, match=r"array shape \(16384, 16384, 16384\) must equal grid.shape \(4, 4, 4\)"):
        from nebula_rt.density.generate import load_density_file

        load_density_file(p, "density", (4, 4, 4))


@pytest.mark.parametrize("option", ["scene", "--table"])
def test_the_cli_refuses_a_fifo_at_once(tmp_path, option):
    """A FIFO as the scene or as --table: exit 2 naming it at once (it used to block)."""
    fifo = tmp_path / ("pipe.toml" if option == "scene" else "pipe.csv")
    os.mkfifo(fifo)
    scene = tmp_path / "s.toml"
    scene.write_text("[grid]\nshape = [8, 8, 8]\n")
    args = ["compare", str(fifo) if option == "scene" else str(scene), "--png", str(tmp_path / "c.png")]
    if option == "--table":
        args += ["--table", str(fifo)]
    p = subprocess.run(RUN + args, capture_output=True, text=True, timeout=120)
    assert p.returncode == 2, p.stderr
    assert "FIFO" in p.stderr and str(fifo) in p.stderr
