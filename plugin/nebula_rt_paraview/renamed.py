"""Names that changed, kept working in pvpython scripts with a FutureWarning.

paraview.simple names a property after its label (spaces removed) and a reader after its
label, so where a label and an XML name differed a script and a state file used two names for
one thing. The labels now give the XML names; what scripts used before still works:

============================================  ==========================================
former name (paraview.simple)                 name now (VTK, state files, pvpython, docs)
============================================  ==========================================
``NebulaLightField.TransportMethod``          ``Method``
``NebulaRTfitresult(...)``                    ``NebulaFitResultReader(...)``
============================================  ==========================================

Importing this module installs them (as importing ``defaults`` installs the displays; the
plugin's entry file imports both). The properties go through ParaView's own hook for renamed properties
(``paraview._backwardscompatibilityhelper``: ``setattr`` / ``getattr``, which
``servermanager.Proxy`` asks about a name it does not know), the reader through a function
added to ``paraview.simple``. Nothing is stored under a former name: state files always held
the XML names.
"""

from __future__ import annotations

import warnings

#: (proxy XML name, former python name) -> property name now
PROPERTIES = {("NebulaLightField", "TransportMethod"): "Method"}
#: former paraview.simple function -> proxy name now
FUNCTIONS = {"NebulaRTfitresult": "NebulaFitResultReader"}


def _warn(old: str, new: str) -> None:
    # FutureWarning: shown by default (a DeprecationWarning is hidden outside __main__)
    warnings.warn(f"NebulaRT: {old!r} is now called {new!r}; the former name will be removed",
                  FutureWarning, stacklevel=4)


def _renamed(proxy, pname):
    try:
        xml = proxy.SMProxy.GetXMLName()
    except AttributeError:
        return None
    return PROPERTIES.get((xml, pname))


def install() -> None:
    """Teach pvpython the former names (idempotent). The former function goes into
    paraview.simple only where that module is already imported (or being imported: a plugin
    on PV_PLUGIN_PATH loads while pvpython imports it): importing it here, while ParaView
    loads the plugin, would build its functions before the plugin's proxies exist."""
    import sys

    try:
        from paraview import _backwardscompatibilityhelper as bc
    except ImportError:
        return
    simple = sys.modules.get("paraview.simple")
    if simple is not None:
        for old, new in FUNCTIONS.items():
            if not hasattr(simple, old):
                setattr(simple, old, _former_function(simple, old, new))
    if getattr(bc, "_nebula_rt_renamed", False):
        return
    former_set, former_get = bc.setattr, bc.getattr

    def setattr_(proxy, pname, value):
        new = _renamed(proxy, pname)
        if new is None:
            return former_set(proxy, pname, value)
        _warn(pname, new)
        proxy.__setattr__(new, value)
        raise bc.Continue()

    def getattr_(proxy, pname):
        new = _renamed(proxy, pname)
        if new is None:
            return former_get(proxy, pname)
        _warn(pname, new)
        return proxy.__getattribute__(new) if hasattr(type(proxy), new) else proxy.GetPropertyValue(new)

    bc.setattr, bc.getattr = setattr_, getattr_
    bc._nebula_rt_renamed = True


def _former_function(simple, old: str, new: str):
    def former(*args, **kwargs):
        _warn(old, new)
        return getattr(simple, new)(*args, **kwargs)
    former.__name__ = old
    former.__doc__ = f"Former name of :func:`{new}` (FutureWarning)."
    return former


install()
