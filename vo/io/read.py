"""Whole-file reads that fail with one line naming the file, never a traceback."""

from __future__ import annotations

from pathlib import Path

from trianflow_vo.errors import InputError


def read_bytes(path: str | Path) -> bytes:
    """The bytes of ``path``.

    Raises:
        InputError: the file is missing, is a folder, or cannot be read (the reason and the file).
    """
    path = Path(path)
    try:
        return path.read_bytes()
    except FileNotFoundError:
        raise InputError("no such file", path) from None
    except IsADirectoryError:
        raise InputError("is a folder, expected a file", path) from None
    except OSError as exc:
        raise InputError(f"cannot read: {exc.strerror or exc}", path) from None
