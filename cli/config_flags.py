"""The configuration rule of ``trianflow-vo run``, shared by ``run`` and ``batch``.

defaults < ``--config`` < ``--set`` (in order) < explicit shortcut flags (``--stride``, ``--gt``, ...).
A batch job is built by the same rule, so it equals the ``run`` command line with the same
``--config``, ``--set`` and flags. Only :mod:`trianflow_vo.config` is imported (lazily): no click.
"""

from __future__ import annotations

from pathlib import Path

# shortcut flag -> configuration key (a flag given on the command line wins over --config and --set)
SHORTCUTS = {
    "stride": "input.stride", "start": "input.start", "end": "input.end", "size": "input.size",
    "intrinsics": "input.intrinsics", "calib": "input.calib",
    "flow_model": "flow.model", "dis_preset": "flow.dis_preset", "depth_model": "depth.model",
    "scale_from": "scale.source",
    "n_samples": "sampling.n_samples", "seed": "sampling.seed", "min_parallax_px": "keyframes.min_parallax_px",
    "window": "backend.window", "threads": "runtime.threads", "gt": "output.gt", "rerun_path": "output.rerun", "rerun_spawn": "output.rerun_spawn",
}


def shortcut_dict(values: dict) -> dict:
    """Nested config dict of the shortcut flags that were given (None = not given)."""
    out: dict = {}
    for name, key in SHORTCUTS.items():
        v = values.get(name)
        if v is None or v is False:
            continue
        section, field = key.split(".")
        out.setdefault(section, {})[field] = list(v) if isinstance(v, tuple) else (str(v) if isinstance(v, Path) else v)
    return out


def build_config(config_file: str | None, overrides: tuple[str, ...], shortcuts: dict, no_plot: bool):
    """defaults < ``--config`` < ``--set`` < explicit shortcut flags."""
    from trianflow_vo.config import Config, apply_overrides, load_config, merge_dict

    config = load_config(config_file) if config_file else Config()
    config = apply_overrides(config, overrides)
    flags = shortcut_dict(shortcuts)
    if no_plot:
        flags.setdefault("output", {})["plot"] = False
    return merge_dict(config, flags, "command-line flags") if flags else config
