# shellcheck shell=bash
# Source this file to run ParaView (paraview, pvpython, pvbatch) with the NebulaRT plugin:
#
#   source scripts/pv-env.sh && paraview          # Filters/Sources > NebulaRT
#   source scripts/pv-env.sh && pvpython my_script.py
#
# - PYTHONPATH gets plugin/site in front: its sitecustomize.py fixes ParaView 5.11's plugin
#   loader on Python 3.11 and puts NEBULA_RT_SITE_PACKAGES in front of the system's packages.
# - NEBULA_RT_SITE_PACKAGES: the site-packages of .venv-pv (NebulaRT and its dependencies
#   built for ParaView's Python, without a VTK wheel; scripts/setup.sh creates it). Already
#   set values are kept in front.
# - PV_PLUGIN_PATH gets plugin/ (its only entry file is plugin/NebulaRT.py).
#
# Idempotent: sourcing it twice adds nothing twice. NEBULA_PV_PYTHON names the Python that
# ParaView embeds (default /usr/bin/python3) to find the site-packages folder of .venv-pv.

_nebula_root="$(cd "$(dirname "${BASH_SOURCE[0]:-$0}")/.." && pwd)"
_nebula_py="${NEBULA_PV_PYTHON:-/usr/bin/python3}"
_nebula_pyver="$("$_nebula_py" -c 'import sys; print("%d.%d" % sys.version_info[:2])' 2>/dev/null || echo 3.11)"
_nebula_site="$_nebula_root/.venv-pv/lib/python$_nebula_pyver/site-packages"

_nebula_prepend() {  # _nebula_prepend VAR VALUE: VALUE in front of the :-list VAR, once
    local cur="${!1:-}"
    case ":$cur:" in
        *":$2:"*) ;;
        *) if [[ -n "$cur" ]]; then export "$1=$2:$cur"; else export "$1=$2"; fi ;;
    esac
}

_nebula_prepend PYTHONPATH "$_nebula_root/plugin/site"
_nebula_append_sp="${NEBULA_RT_SITE_PACKAGES:-}"
case ":$_nebula_append_sp:" in
    *":$_nebula_site:"*) ;;
    *) export NEBULA_RT_SITE_PACKAGES="${_nebula_append_sp:+$_nebula_append_sp:}$_nebula_site" ;;
esac
_nebula_prepend PV_PLUGIN_PATH "$_nebula_root/plugin"
if [[ ! -d "$_nebula_site" ]]; then
    echo "pv-env.sh: $_nebula_site is missing: run bash scripts/setup.sh first" >&2
fi
unset -f _nebula_prepend
unset _nebula_root _nebula_py _nebula_pyver _nebula_site _nebula_append_sp
