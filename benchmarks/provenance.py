"""What code a benchmark measured: the git commit and a digest of the sources it ran.

A benchmark run on a lent GPU machine sees a copy of the working tree whose git HEAD may be an
older commit than the files it runs, so its results also carry ``sources_sha256``, a digest of
the kernels and the library (paths and contents). To find the commit a result measured:

    python benchmarks/provenance.py                  # this checkout's digest
    python benchmarks/provenance.py --rev 7f997dd    # the digest of a commit's sources
"""

from __future__ import annotations

import argparse
import fnmatch
import hashlib
import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
#: the sources a result depends on: the kernels and the library
SOURCE_GLOBS = ("kernels/*.cl", "kernels/*.h", "python/nebula_rt/*.py", "python/nebula_rt/*/*.py")


def _digest(files) -> str:
    """Digest of (path, contents) pairs in path order."""
    h = hashlib.sha256()
    for rel, data in sorted(files):
        h.update(rel.encode() + b"\0" + data + b"\0")
    return h.hexdigest()[:16]


def sources_sha256(root: Path = ROOT) -> str:
    """Digest of the source files of a checkout."""
    root = Path(root)
    paths = {p for g in SOURCE_GLOBS for p in root.glob(g) if p.is_file()}
    return _digest((p.relative_to(root).as_posix(), p.read_bytes()) for p in paths)


def sources_sha256_at(rev: str, root: Path = ROOT) -> str:
    """Digest of the source files of commit ``rev``, from git's objects."""
    names = subprocess.run(["git", "ls-tree", "-r", "--name-only", rev], cwd=root, capture_output=True,
                           text=True, check=True).stdout.split()
    chosen = [n for n in names if any(fnmatch.fnmatchcase(n, g) for g in SOURCE_GLOBS)]
    return _digest((n, subprocess.run(["git", "show", f"{rev}:{n}"], cwd=root, capture_output=True,
                                      check=True).stdout) for n in chosen)


def commit(root: Path = ROOT) -> str:
    """The checkout's short HEAD, or "unknown" without git."""
    try:
        return subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=root, capture_output=True, text=True,
                              check=True).stdout.strip() or "unknown"
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def provenance(root: Path = ROOT) -> dict:
    """The fields every benchmark result carries: ``commit`` and ``sources_sha256``."""
    return {"commit": commit(root), "sources_sha256": sources_sha256(root)}


def save(result: dict, path) -> None:
    """Write a benchmark's result as indented JSON to ``path`` (nothing for an empty path)."""
    if path:
        import json

        with open(path, "w") as fh:
            json.dump(result, fh, indent=1)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rev", default=None, help="a commit: the digest of its sources instead of the checkout's")
    args = ap.parse_args(argv)
    if args.rev:
        print(json.dumps({"commit": args.rev, "sources_sha256": sources_sha256_at(args.rev)}))
    else:
        print(json.dumps(provenance()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
