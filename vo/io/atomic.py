"""Whole-file writes that never leave a half-written file behind."""

from __future__ import annotations

import os
from pathlib import Path


def write_atomic(path: str | Path, data: bytes) -> Path:
    """Write ``data`` to a temporary ``path.<pid>.tmp`` beside ``path``, then rename it to
    ``path``; on any failure ``path`` is untouched and the temporary file removed.

    The temporary name carries the process id, so processes writing the same file at once
    (e.g. the ranks of a distributed run filling one cache) never share a temporary file:
    each rename is atomic and the last one wins. Returns ``path``."""
    path = Path(path)
    tmp = path.with_name(f"{path.name}.{os.getpid()}.tmp")
    try:
        with open(tmp, "wb") as f:
            f.write(data)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path
