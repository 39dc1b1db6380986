"""Turn library exceptions into one-line click errors (non-zero exit, no traceback)."""

from __future__ import annotations

import contextlib

import click

from trianflow_vo.errors import ConfigError, VOError


class BadConfig(click.ClickException):
    """A bad configuration key or value: one line, exit status 2 (like a bad option)."""

    exit_code = 2


@contextlib.contextmanager
def user_errors():
    """Re-raise our exceptions (and missing files) as ``click.ClickException``."""
    try:
        yield
    except ConfigError as exc:
        raise BadConfig(str(exc)) from None
    except VOError as exc:
        raise click.ClickException(str(exc)) from None
    except FileNotFoundError as exc:
        raise click.ClickException(f"{exc.filename}: no such file or directory") from None
    except OSError as exc:  # permission denied, is a directory, disk full, ...
        where = f"{exc.filename}: " if exc.filename else ""
        raise click.ClickException(f"{where}{exc.strerror or exc}") from None
    except MemoryError:
        raise click.ClickException("out of memory; choose a smaller working size (--size) or fewer threads") \
            from None
