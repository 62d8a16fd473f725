#!/usr/bin/env bash
# Idempotent environment set-up for NebulaRT on Debian 12.
#
#   bash scripts/setup.sh            # install what is missing, skip what is done
#   bash scripts/setup.sh --force    # reinstall the package even if the stamp matches
#
# (a) System libraries for off-screen rendering (nebula_rt.filters.render), installed
#     with apt-get only when missing, and only as root (otherwise the command
#     to run is printed).
#     Also ParaView 5.11 (paraview, python3-paraview), Xvfb and Debian's PoCL
#     OpenCL driver for the ParaView plugin and its tests.
# (b) The virtual environment .venv with `pip install -e ".[io,pocl,test,mpi,observe]"`
#     (observe: reproject, for the observed FITS images of nebula-rt compare --image and their tests).
#     .venv/.nebula-setup-stamp holds the sha256 of pyproject.toml; while it
#     matches, step (b) is skipped.
# (b2) pyvkfft (VkFFT), the optional OpenCL FFTs of the collision filter: it has no
#     wheels on PyPI, so it is built from source into .venv (VKFFT_BACKEND=opencl: its
#     CUDA module would need the CUDA toolkit's NVRTC headers), against the OpenCL headers
#     and ICD loader of (a) (opencl-headers, ocl-icd-opencl-dev, g++); about 30 s on 2
#     cores. Skipped while `import pyvkfft.opencl` works; a failed build is noted in
#     .venv/.nebula-pyvkfft-failed and not retried until pyproject.toml changes (or
#     --force). Without it the filter runs on the host and its device tests are skipped.
#     NEBULA_SKIP_PYVKFFT=1 skips this step.
# (c) The virtual environment .venv-pv for ParaView's Python (/usr/bin/python3,
#     --system-site-packages): NebulaRT's dependencies WITHOUT the vtk wheel
#     (a vtk wheel in front of ParaView's own VTK crashes it) and NebulaRT as an
#     editable install (--no-deps). scripts/pv-env.sh puts it on ParaView's path.
#     Stamped like (b) (sha256 of pyproject.toml and the package list).
#
# Environment: PYTHON (interpreter that creates the venv, default python3),
# NEBULA_VENV (venv folder, default <repo>/.venv), NEBULA_PV_PYTHON (ParaView's
# Python, default /usr/bin/python3), NEBULA_PV_VENV (default <repo>/.venv-pv),
# NEBULA_SKIP_PARAVIEW=1 (skip ParaView, Xvfb and .venv-pv), NEBULA_SKIP_PYVKFFT=1 (skip
# pyvkfft and its build packages).
set -euo pipefail

ROOT="$(cd "$(dirname "${BASH_SOURCE[0]}")/.." && pwd)"
cd "$ROOT"
VENV="${NEBULA_VENV:-$ROOT/.venv}"
STAMP="$VENV/.nebula-setup-stamp"
PYTHON="${PYTHON:-python3}"
PV_PYTHON="${NEBULA_PV_PYTHON:-/usr/bin/python3}"
PV_VENV="${NEBULA_PV_VENV:-$ROOT/.venv-pv}"
PV_STAMP="$PV_VENV/.nebula-setup-stamp"
SKIP_PV="${NEBULA_SKIP_PARAVIEW:-0}"
SKIP_VKFFT="${NEBULA_SKIP_PYVKFFT:-0}"
PYVKFFT_SPEC="pyvkfft==2025.1.1"
PYVKFFT_FAILED="$VENV/.nebula-pyvkfft-failed"
FORCE=0
for arg in "$@"; do
    case "$arg" in
        --force) FORCE=1 ;;
        -h|--help) sed -n '2,34p' "$0"; exit 0 ;;
        *) echo "setup.sh: unknown argument: $arg" >&2; exit 2 ;;
    esac
done

log() { printf '[setup] %s\n' "$*"; }

# --------------------------------------------------------------------------
# (a) system packages
#
# The vtk wheel (9.4+) links no GL or X library: `ldd` on
# vtkmodules/libvtkRenderingOpenGL2.so, libvtkRenderingVolumeOpenGL2.so,
# libvtkglad.so and libvtkx11.so lists only libc/libstdc++/libm. At run time
# libvtkglad dlopens libEGL.so.1 / libGL.so.1 and libvtkx11 dlopens
# libX11.so.6 / libXcursor.so.1. Without DISPLAY the render goes through
# EGL, which (per /proc/self/maps of an off-screen render) needs the GLVND
# loader libEGL.so.1, Mesa's EGL vendor library and Mesa's software
# rasteriser (swrast_dri.so / llvmpipe); apt pulls in the rest (libgbm1,
# libdrm2, libglapi-mesa, libllvm15, xcb libraries).
RENDER_PKGS=(libegl1 libegl-mesa0 libgl1-mesa-dri)
# With a DISPLAY (e.g. under Xvfb) VTK renders through GLX instead.
X11_PKGS=(libgl1 libglx-mesa0 libx11-6 libxcursor1)
# The ParaView plugin (plugin/) and its tests: ParaView 5.11 with its Python
# modules, an X server for pvpython/pvbatch renders, and Debian's PoCL ICD
# (the OpenCL device ParaView's Python sees through the pyopencl wheel). libqt5svg5: Qt's SVG
# image plugin, without which every icon of ParaView's GUI (the toolbars, the Stars table's +
# and -, the abort button, the advanced-properties gear) is an empty square; Debian's paraview
# package does not pull it in. python3-pyqt5: Qt's Python binding for the same Qt that ParaView
# uses (Debian's), through which the plugin enables ParaView's Abort button during a trace and
# hears it (ParaView 5.11 connects that button to nothing; plugin/nebula_rt_paraview/abort.py).
# xdotool: the GUI tests press that button as a user does, with a real mouse click on the X server.
PV_PKGS=(paraview python3-paraview xvfb pocl-opencl-icd libqt5svg5 python3-pyqt5 xdotool)
if [[ "$SKIP_PV" == 1 ]]; then PV_PKGS=(); fi
# Building pyvkfft (b2): the OpenCL headers, the ICD loader's libOpenCL.so and a C++ compiler.
FFT_PKGS=(opencl-headers ocl-icd-opencl-dev g++)
if [[ "$SKIP_VKFFT" == 1 ]]; then FFT_PKGS=(); fi
# Distributed runs (mpiexec; the venv's mpi4py wheel loads the system's Open MPI, the same
# library Debian's ParaView and python3-mpi4py are built with).
MPI_PKGS=(openmpi-bin)

is_installed() {
    # dpkg -s also succeeds for removed packages whose config files remain;
    # the status abbreviation "ii" means installed.
    [[ "$(dpkg-query -W -f='${db:Status-Abbrev}' "$1" 2>/dev/null)" == ii* ]]
}

missing=()
if command -v dpkg-query >/dev/null 2>&1; then
    for pkg in "${RENDER_PKGS[@]}" "${X11_PKGS[@]}" "${PV_PKGS[@]}" "${FFT_PKGS[@]}" "${MPI_PKGS[@]}"; do
        is_installed "$pkg" || missing+=("$pkg")
    done
    # The venv needs an interpreter with venv + ensurepip (Debian splits them out).
    if ! command -v "$PYTHON" >/dev/null 2>&1; then
        missing+=(python3 python3-venv)
        PYTHON=python3
    elif ! "$PYTHON" -c 'import venv, ensurepip' >/dev/null 2>&1; then
        is_installed python3-venv || missing+=(python3-venv)
    fi
    # building pyvkfft (b2) with Debian's own Python needs its C headers (python3-dev)
    if ((${#FFT_PKGS[@]})) && command -v "$PYTHON" >/dev/null 2>&1 &&
       [[ "$(readlink -f "$(command -v "$PYTHON")")" == /usr/bin/* ]] &&
       ! "$PYTHON" -c 'import os, sys, sysconfig; sys.exit(not os.path.exists(os.path.join(sysconfig.get_paths()["include"], "Python.h")))' >/dev/null 2>&1; then
        is_installed python3-dev || missing+=(python3-dev)
    fi
    # .venv-pv is made with ParaView's (the system's) Python: it needs venv + ensurepip too
    if ((${#PV_PKGS[@]})) && [[ -x "$PV_PYTHON" ]] && ! "$PV_PYTHON" -c 'import venv, ensurepip' >/dev/null 2>&1; then
        is_installed python3-venv || [[ " ${missing[*]} " == *" python3-venv "* ]] || missing+=(python3-venv)
    fi
else
    log "no dpkg here: not checking system packages (needed on Debian: ${RENDER_PKGS[*]} ${X11_PKGS[*]})"
fi

if ((${#missing[@]})); then
    if [[ "$(id -u)" -eq 0 ]]; then
        log "installing system packages: ${missing[*]}"
        export DEBIAN_FRONTEND=noninteractive
        apt-get update -qq
        apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
        # python3-venv was needed before the system python3 existed (it comes with paraview)
        if ((${#PV_PKGS[@]})) && [[ -x "$PV_PYTHON" ]] && ! "$PV_PYTHON" -c 'import venv, ensurepip' >/dev/null 2>&1; then
            apt-get install -y -qq --no-install-recommends python3-venv >/dev/null
        fi
    else
        log "missing system packages: ${missing[*]}"
        log "run as root: apt-get update && apt-get install -y --no-install-recommends ${missing[*]}"
    fi
else
    log "system packages present"
fi

# --------------------------------------------------------------------------
# (b) virtual environment
want="$(sha256sum pyproject.toml | cut -d' ' -f1)"
setup_main_venv() {  # (body not indented: it holds here-documents and python -c code)
if [[ ! -x "$VENV/bin/python" ]]; then
    log "creating venv $VENV with $("$PYTHON" --version 2>&1)"
    "$PYTHON" -m venv "$VENV"
fi

log "pip install -e \".[io,pocl,test,mpi,observe]\" (this takes a while the first time; log: $VENV/.nebula-setup-pip.log)"
if ! "$VENV/bin/python" -m pip install --disable-pip-version-check -e ".[io,pocl,test,mpi,observe]" \
        >"$VENV/.nebula-setup-pip.log" 2>&1; then
    tail -n 30 "$VENV/.nebula-setup-pip.log" >&2
    log "pip install failed (full log: $VENV/.nebula-setup-pip.log)"
    exit 1
fi

# Smoke checks from outside the source tree: the package and its kernel
# sources import, and an off-screen render works (warning only: rendering is
# optional for the core library).
(
    cd /
    "$VENV/bin/python" -c "
import importlib.resources as r, nebula_rt
n = sum(1 for p in r.files('nebula_rt.kernels').iterdir() if p.name.endswith(('.cl', '.h', '.cu')))
print('[setup] nebula_rt', nebula_rt.__version__, 'with', n, 'kernel source files')
"
)
if ! (cd / && "$VENV/bin/python" - <<'EOF' >/dev/null 2>&1
import os, tempfile, numpy as np
from nebula_rt.filters.render import render_rgba_png
rgba = np.zeros((4, 4, 4, 4), np.uint8); rgba[..., 2] = 255; rgba[..., 3] = 128
with tempfile.TemporaryDirectory() as d:
    render_rgba_png(os.path.join(d, "t.png"), rgba, (1.0, 1.0, 1.0), window_size=(32, 32))
EOF
); then
    log "WARNING: off-screen rendering does not work here (nebula_rt.filters.render); check the system packages above"
else
    log "off-screen rendering works"
fi

tmp_stamp="$STAMP.tmp.$$"
printf '%s\n' "$want" >"$tmp_stamp"
mv -f "$tmp_stamp" "$STAMP"
log "venv done"
}

if ((FORCE == 0)) && [[ -x "$VENV/bin/python" && -f "$STAMP" && "$(cat "$STAMP")" == "$want" ]]; then
    log "venv up to date ($VENV)"
else
    setup_main_venv
fi

# --------------------------------------------------------------------------
# (b2) pyvkfft, built from source for the OpenCL FFTs of the collision filter
if [[ "$SKIP_VKFFT" == 1 ]]; then
    log "skipping pyvkfft (NEBULA_SKIP_PYVKFFT=1)"
elif "$VENV/bin/python" -c 'import pyvkfft.opencl' >/dev/null 2>&1; then
    log "pyvkfft present (OpenCL FFTs of the collision filter)"
elif ((FORCE == 0)) && [[ -f "$PYVKFFT_FAILED" && "$(cat "$PYVKFFT_FAILED")" == "$want" ]]; then
    log "pyvkfft: its build failed before (log: $VENV/.nebula-pyvkfft-pip.log); not retrying (--force does)"
else
    log "building $PYVKFFT_SPEC from source (about 30 s; log: $VENV/.nebula-pyvkfft-pip.log)"
    if VKFFT_BACKEND=opencl "$VENV/bin/python" -m pip install --disable-pip-version-check "$PYVKFFT_SPEC" \
            >"$VENV/.nebula-pyvkfft-pip.log" 2>&1 &&
       "$VENV/bin/python" -c 'import pyvkfft.opencl' >/dev/null 2>&1; then
        rm -f "$PYVKFFT_FAILED"
        log "pyvkfft built: the collision filter's OpenCL FFT path and its tests are on"
    else
        printf '%s\n' "$want" >"$PYVKFFT_FAILED"
        log "WARNING: pyvkfft did not build (needs ${FFT_PKGS[*]}; log: $VENV/.nebula-pyvkfft-pip.log):" \
            "the collision filter runs on the host and tests/transport/test_filtering_opencl.py is skipped"
    fi
fi

# --------------------------------------------------------------------------
# (c) ParaView's Python packages: .venv-pv
#
# ParaView 5.11 (Debian) embeds the system Python 3.11 and ships its own VTK as
# Python modules in /usr/lib/python3/dist-packages. NebulaRT's dependencies go
# into a venv of that Python, WITHOUT the vtk wheel (it would be imported
# instead of ParaView's VTK and crash); matplotlib >= 3.7 because Debian's 3.6
# is built for numpy 1 and colour-science imports it (numpy 2 comes with
# pyopencl); astropy and speclite for the physical units and the calibrated sky images
# (FITS, WCS, passbands), PyAstronomy for a star's spectral type, miepython for Mie grains.
# plugin/site/sitecustomize.py,
# through scripts/pv-env.sh, puts the venv's site-packages in front inside pvpython, pvbatch
# and paraview.
PV_REQS=(pyopencl colour-science scipy tqdm tomli-w "matplotlib>=3.7" dust_extinction astropy speclite PyAstronomy "miepython>=3.3")
pv_want="$( (sha256sum pyproject.toml | cut -d' ' -f1; printf '%s\n' "${PV_REQS[@]}"; "$PV_PYTHON" --version 2>&1) | sha256sum | cut -d' ' -f1)"

setup_pv_venv() {  # (body not indented: it holds python -c code)
if [[ ! -x "$PV_VENV/bin/python" ]]; then
    log "creating $PV_VENV with $("$PV_PYTHON" --version 2>&1) (--system-site-packages: ParaView's modules)"
    "$PV_PYTHON" -m venv --system-site-packages "$PV_VENV"
fi
log "pip install into $PV_VENV: ${PV_REQS[*]} and NebulaRT (--no-deps -e .) (log: $PV_VENV/.nebula-setup-pip.log)"
if ! { "$PV_VENV/bin/python" -m pip install --disable-pip-version-check "${PV_REQS[@]}" &&
       "$PV_VENV/bin/python" -m pip install --disable-pip-version-check --no-deps -e . ; } \
        >"$PV_VENV/.nebula-setup-pip.log" 2>&1; then
    tail -n 30 "$PV_VENV/.nebula-setup-pip.log" >&2
    log "pip install into $PV_VENV failed (full log: $PV_VENV/.nebula-setup-pip.log)"
    exit 1
fi
if "$PV_VENV/bin/python" -c "import vtkmodules, sys; sys.exit(0 if '$PV_VENV' in vtkmodules.__file__ else 1)" >/dev/null 2>&1; then
    log "WARNING: $PV_VENV holds a vtk wheel: it will shadow ParaView's VTK (pip uninstall vtk there)"
fi
# smoke check: pvpython imports NebulaRT and loads the plugin (warning only)
if command -v pvpython >/dev/null 2>&1; then
    if (cd / && source "$ROOT/scripts/pv-env.sh" && timeout 120 pvpython -c "
import nebula_rt.filters
from paraview.simple import NebulaLightField
print('[setup] pvpython: NebulaRT plugin loads')
" 2>/dev/null | grep -q 'plugin loads'); then
        log "pvpython loads the NebulaRT plugin"
    else
        log "WARNING: pvpython cannot load the NebulaRT plugin; try: source scripts/pv-env.sh && pvpython -c 'import nebula_rt.filters'"
    fi
fi
tmp_stamp="$PV_STAMP.tmp.$$"
printf '%s\n' "$pv_want" >"$tmp_stamp"
mv -f "$tmp_stamp" "$PV_STAMP"
log "ParaView venv done"
}

if [[ "$SKIP_PV" == 1 ]]; then
    log "skipping ParaView's venv (NEBULA_SKIP_PARAVIEW=1)"
elif [[ ! -x "$PV_PYTHON" ]]; then
    log "WARNING: $PV_PYTHON (ParaView's Python) is missing: not making $PV_VENV (install the system packages above)"
elif ((FORCE == 0)) && [[ -x "$PV_VENV/bin/python" && -f "$PV_STAMP" && "$(cat "$PV_STAMP")" == "$pv_want" ]]; then
    log "ParaView venv up to date ($PV_VENV)"
else
    setup_pv_venv
fi
