"""Option parsers shared by the commands."""

from __future__ import annotations

import click


def parse_size(ctx, param, value):
    """``HxW`` -> ``(h, w)``; both sides positive multiples of 64 (what the networks need)."""
    if value is None:
        return None
    try:
        h, w = (int(v) for v in value.lower().split("x"))
    except ValueError:
        raise click.BadParameter(f"{value!r} is not HxW (e.g. 256x832)") from None
    if h <= 0 or w <= 0 or h % 64 or w % 64:
        raise click.BadParameter(f"{value!r}: both sides must be positive multiples of 64")
    return h, w
