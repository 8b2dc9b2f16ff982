"""Files that appear complete or not at all, and the one order of frame files. No Ray, no MLflow.

- ``atomic_path(path)``: write under a temporary name, renamed into place only when the block succeeds.
- ``natural_key(name)``: the one order of frame and clip files (``frame_2`` before ``frame_10``, case-blind).

Whole output directories, and the locks that keep one job per directory, are `aniformer.cli.outputs`.
"""

from __future__ import annotations

import contextlib
import os
import re
import tempfile
from collections.abc import Iterator
from pathlib import Path

ATOMIC_TMP = re.compile(r"^\..+\.[a-z0-9_]{8}\.tmp$")  # atomic_path's temporary files


def plain_mode(bits: int) -> int:
    """`bits` under this process's umask: the mode a plain open() or mkdir() would give (mkstemp and
    mkdtemp make private files)."""
    umask = os.umask(0)
    os.umask(umask)
    return bits & ~umask


def natural_key(name: str) -> list:
    """Sort key that orders frame_2 before frame_10, ignoring case."""
    return [int(part) if part.isdigit() else part.lower() for part in re.split(r"(\d+)", name)]


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path beside `path`; rename it into place only if the block succeeds."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    os.chmod(tmp, plain_mode(0o666))
    try:
        yield Path(tmp)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
