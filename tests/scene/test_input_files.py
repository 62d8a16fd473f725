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


def _sparse(path, size=100 << 30):
    with open(path, "r+b") as fh:  # the holes take no disk
        fh.truncate(size)


def test_a_density_file_larger_than_its_header_declares_is_refused_before_it_is_hashed(tmp_path, backend):
    """A valid .npy or .vti header followed by 100 GB (a sparse file): the run hashed all of it
    for its cache key before reading the header (minutes of reading zeros). Now its size is
    held against what the header declares, in milliseconds, before the hash."""
    import time

    from nebula_rt.density import check_density_file
    from nebula_rt.pipeline.stages import Pipeline

    npy = tmp_path / "d.npy"
    np.save(npy, np.ones((4, 4, 4)))
    check_density_file(npy, "density", (4, 4, 4))  # the file as written passes
    _sparse(npy)
    t0 = time.monotonic()
    with pytest.raises(SceneError, match=r"holds 107374182400 bytes, its \.npy header declares 640"):
        check_density_file(npy, "density", (4, 4, 4))
    scene = Scene.from_dict({"grid": {"shape": [4, 4, 4]}, "dust": {"model": "file", "file": str(npy)},
                             "transport": {"photons": 1000}})
    with pytest.raises(SceneError, match="header declares"):  # the library's run: before the hash too
        Pipeline(backend).run(scene)
    assert time.monotonic() - t0 < 10
    pytest.importorskip("vtkmodules")
    from nebula_rt.filters.vti import write_vti

    vti = tmp_path / "d.vti"
    write_vti(vti, {"density": np.ones((4, 4, 4), np.float32)}, None, spacing=(0.25,) * 3)
    check_density_file(vti, "density", (4, 4, 4))
    _sparse(vti)
    with pytest.raises(SceneError, match=r"107374182400 bytes, more than the \d+ its header's 1 array\(s\) of 64 points"):
        check_density_file(vti, "density", (4, 4, 4))


def test_the_cli_refuses_a_density_file_in_one_line_before_any_work(tmp_path):
    """A FIFO, a truncated .npy and a density of NaN as dust.file: exit 2 and the one line
    naming dust.file. The file was read only in the trace, after the device was opened and the
    progress bar drawn (two lines), and under mpiexec each rank reported it on its own."""
    fifo = tmp_path / "pipe.npy"
    os.mkfifo(fifo)
    short = tmp_path / "short.npy"
    np.save(short, np.ones((8, 8, 8)))
    short.write_bytes(short.read_bytes()[:300])
    nan = tmp_path / "nan.npy"
    np.save(nan, np.full((8, 8, 8), np.nan))
    for path, words in ((fifo, "FIFO"), (short, "holds 300 bytes"), (nan, "finite")):
        scene = tmp_path / "s.toml"
        scene.write_text(f'[grid]\nshape = [8, 8, 8]\n[dust]\nmodel = "file"\nfile = "{path}"\n'
                         '[transport]\nphotons = 20000\ndevice = "Portable Computing Language"\n')
        p = subprocess.run(RUN + ["render", str(scene), "-o", str(tmp_path / "o.vti")], capture_output=True,
                           text=True, timeout=120)
        assert p.returncode == 2, p.stderr
        lines = p.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("nebula-rt: ") and "dust.file" in lines[0], p.stderr
        assert words in lines[0] and "tracing" not in p.stderr, p.stderr
        assert not (tmp_path / "o.vti").exists()


def test_the_density_file_reader_refuses_a_fifo_and_says_why_in_one_line(tmp_path):
    """nebula_rt.filters.density_file (the .vti reader of ParaView's Python) waited on a FIFO
    for ever; VTK's errors came with a multi-line dump of the pipeline request and a bare
    number."""
    pytest.importorskip("vtkmodules")
    from nebula_rt.filters.density_file import read_density_array
    from nebula_rt.filters.vti import read_vti

    fifo = tmp_path / "pipe.vti"
    os.mkfifo(fifo)
    with pytest.raises(SceneError, match="FIFO"):
        read_density_array(fifo, "density")
    junk = tmp_path / "junk.vti"
    junk.write_bytes(bytes(range(256)) * 4)
    for read in (lambda: read_density_array(junk, "density"), lambda: read_vti(junk)):
        with pytest.raises(ValueError) as e:
            read()
        text = str(e.value)
        assert "\n" not in text and "Error parsing XML" in text and "returned failure" not in text, text
        assert not any(part.strip().isdigit() for part in text.split(";")), text


@pytest.mark.skipif(not os.path.exists("/proc/self/mem"), reason="needs /proc")
def test_a_regular_file_that_cannot_be_read_is_named(tmp_path):
    """A scene file that is regular but fails to read (/proc/self/mem: EIO; a failing disk):
    the command ended with status 1 and 'Input/output error', naming nothing."""
    link = tmp_path / "mem.toml"
    link.symlink_to("/proc/self/mem")
    with pytest.raises(SceneError, match="Input/output error") as e:
        Scene.load(link)
    assert e.value.parameter == "scene file" and e.value.value == str(link)


def test_an_integer_too_long_for_python_is_bad_toml(tmp_path):
    """A scene with a 300,000-digit number: Python's own limit on converting digits (4300)
    raised a ValueError the command reported as an internal error."""
    p = tmp_path / "s.toml"
    p.write_text("[transport]\nphotons = " + "9" * 300_000 + "\n")
    with pytest.raises(SceneError, match=r"not valid TOML here: Exceeds the limit \(4300 digits\)") as e:
        Scene.load(p)
    assert e.value.parameter == "(toml)"


def test_a_huge_value_is_shown_shortened(tmp_path):
    """A 300 kB value (or key) in a scene: the message quoted all of it, a line of 300 kB. It
    shows the start and the length; the exception keeps the value."""
    p = tmp_path / "s.toml"
    p.write_text('[dust]\nmodel = "' + "u" * 300_000 + '"\n')
    with pytest.raises(SceneError) as e:
        Scene.load(p)
    assert len(str(e.value)) < 500 and "(300002 characters)" in str(e.value) and str(e.value).startswith("dust.model")
    assert e.value.value == "u" * 300_000


@pytest.mark.parametrize("text,words", [("", "is empty"), ("  \n\n", "is empty"),
                                        ("offset,delta_bv,delta_bv_err", "no rows|row")])
def test_an_empty_table_or_one_of_a_header_alone_is_refused_as_such(tmp_path, text, words):
    """An empty --table was refused with astropy's "Is a directory: '.'" (the empty text taken
    for a file name), a header line without a newline with "No such file or directory"."""
    from nebula_rt.observe.observed_tables import read_table

    p = tmp_path / "t.csv"
    p.write_text(text)
    with pytest.raises(SceneError) as e:
        read_table(p, option="--table")
    assert e.value.parameter.startswith("--table") and str(p) in str(e.value), e.value
    assert "directory" not in str(e.value) and __import__("re").search(words, str(e.value)), e.value
