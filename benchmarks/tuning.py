"""The benchmarks' ``--tuning KEY=VALUE`` option: transport kernel options laid over a
backend's own (``backend.transport_tuning``), for side-by-side runs of one option."""

from __future__ import annotations


def add_tuning_argument(ap) -> None:
    ap.add_argument("--tuning", nargs="*", default=[], metavar="KEY=VALUE",
                    help="transport kernel options (e.g. NRT_TREE_ASCEND=1), as backend.transport_tuning")


def apply_tuning(backend, pairs) -> None:
    """Lay the ``KEY=VALUE`` ``pairs`` (integers) over ``backend``'s transport tuning."""
    backend.transport_tuning = dict(getattr(backend, "transport_tuning", {}) or {},
                                    **{k: int(v) for k, v in (t.split("=", 1) for t in pairs)})
