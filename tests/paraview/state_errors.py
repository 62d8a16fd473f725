"""Why load_state_safely exists: LoadState without the plugin fails silently.

    pvpython state_errors.py STATE.pvsm      (run WITHOUT PV_PLUGIN_PATH)

1. plain LoadState before the plugin is loaded: no exception, no NebulaRT proxy;
2. load_state_safely of a missing file: StateLoadError;
3. load_state_safely (loads the plugin) expecting a proxy the state lacks: StateLoadError
   naming it; the proxies the state has are there.
"""

import sys

import _common
from paraview import simple
from nebula_rt_paraview.view import StateLoadError, load_state_safely, nebula_proxies, plugin_loaded

state = sys.argv[1]
out = {"plugin_loaded_at_start": plugin_loaded()}

try:
    simple.LoadState(state)
    out["plain_exception"] = None
except Exception as exc:  # noqa: BLE001
    out["plain_exception"] = repr(exc)
out["plain_nebula_proxies"] = {k: len(v) for k, v in nebula_proxies().items()}
out["plain_all_sources"] = len(simple.GetSources())
simple.ResetSession()

try:
    load_state_safely(state + ".missing", ["NebulaLightField"])
    out["missing_file_error"] = None
except StateLoadError as exc:
    out["missing_file_error"] = str(exc)

try:
    load_state_safely(state, {"NebulaLightField": 4, "NebulaSkyImage": 1})
    out["missing_proxy_error"] = None
except StateLoadError as exc:
    out["missing_proxy_error"] = str(exc)
out["safe_nebula_proxies"] = {k: len(v) for k, v in nebula_proxies().items()}
out["plugin_loaded_at_end"] = plugin_loaded()
_common.result(**out)
