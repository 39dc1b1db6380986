"""Exceptions raised by the library. The CLI turns each into a one-line error."""

from __future__ import annotations

from pathlib import Path


class VOError(Exception):
    """Base class of every error the tool reports to users."""


class InputError(VOError):
    """Bad user input: names the file (and line) when there is one."""

    def __init__(self, message: str, path: str | Path | None = None, line: int | None = None):
        self.message = message
        self.path = None if path is None else str(path)
        self.line = line
        super().__init__(self.__str__())

    def __str__(self) -> str:
        where = ""
        if self.path is not None:
            where = self.path + (f":{self.line}" if self.line is not None else "") + ": "
        return where + self.message


class ModelError(VOError):
    """A network model file that cannot be used (metadata, shapes, runtime)."""


class DependencyError(VOError):
    """An optional dependency (onnxruntime, rerun-sdk, evo) is missing."""


class ConfigError(VOError, ValueError):
    """A configuration that cannot be used: one line naming the source, the key and what is valid.

    Formatted ``SOURCE[:LINE]: KEY: MESSAGE`` (``--set KEY: MESSAGE`` when the source is a
    command-line option); ``source``, ``key`` and ``line`` are kept as attributes.
    """

    def __init__(self, message: str, source: str | None = None, key: str | None = None, line: int | None = None):
        self.message = message
        self.source = source
        self.key = key
        self.line = line
        super().__init__(self.__str__())

    def __str__(self) -> str:
        head = self.source or ""
        if self.line is not None:
            head += f":{self.line}"
        if self.key:
            head = f"{head} {self.key}" if head.startswith("-") else (f"{head}: {self.key}" if head else self.key)
        return f"{head}: {self.message}" if head else self.message
