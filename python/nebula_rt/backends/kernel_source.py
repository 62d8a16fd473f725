"""Kernel sources as text, with the shared header inlined.

The OpenCL and CUDA backends compile the same ``.cl`` sources; the header
``nebula_common.h`` is pasted in place of its ``#include`` so a program is one
self-contained string (no include paths to get wrong, and the source text is a
complete cache key). The parameter structs of :mod:`nebula_rt.backends.kernel_params` replace the
``NRT_PARAM_STRUCTS`` line of the header, and their layout kernels the
``NRT_PARAM_LAYOUT_KERNELS`` line of a program that asks for them.
"""

from __future__ import annotations

import functools
import re
from importlib import resources

from . import kernel_params

HEADER = "nebula_common.h"
_INCLUDE = re.compile(r'^\s*#include\s+"([^"]+)"\s*$', re.MULTILINE)


@functools.lru_cache(maxsize=None)
def read_kernel_file(name: str) -> str:
    """Return the text of one file of the ``nebula_rt.kernels`` package data."""
    return resources.files("nebula_rt.kernels").joinpath(name).read_text(encoding="utf-8")


@functools.lru_cache(maxsize=None)
def kernel_source(name: str) -> str:
    """Return kernel ``name`` (e.g. ``"transport.cl"``) with its local includes inlined."""

    def _inline(match: re.Match) -> str:  # (nested: binned.cl includes transport.cl, which includes the header)
        return _INCLUDE.sub(_inline, read_kernel_file(match.group(1)))

    text = _INCLUDE.sub(_inline, read_kernel_file(name))
    text = text.replace("/* NRT_PARAM_STRUCTS */", kernel_params.all_structs())
    return text.replace("/* NRT_PARAM_LAYOUT_KERNELS */", kernel_params.test_kernels())
