"""``trianflow-vo export``: write flow.onnx and depth.onnx from a checkpoint (or random weights)."""

from __future__ import annotations

from pathlib import Path

import click

from trianflow_vo.cli.errors import user_errors
from trianflow_vo.cli.options import parse_size


@click.command("export")
@click.option("--checkpoint", type=click.Path(dir_okay=False, path_type=Path),
              help="Checkpoint file (trianflow-vo format, see models/checkpoint.py).")
@click.option("--random-init", is_flag=True, help="Export freshly initialised networks (for testing).")
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of --random-init and of the check input.")
@click.option("--size", callback=parse_size, metavar="HxW",
              help="Fixed input size of the exported graphs. Default: the checkpoint's input size "
                   "(256x832 with --random-init).")
@click.option("--out-dir", required=True, type=click.Path(file_okay=False, path_type=Path),
              help="Directory for flow.onnx and depth.onnx.")
def export(checkpoint, random_init, seed, size, out_dir):
    """Export flow and depth networks to ONNX and check them against torch."""
    if (checkpoint is None) == (not random_init):
        raise click.UsageError("give exactly one of --checkpoint CKPT or --random-init")
    with user_errors():
        from trianflow_vo.errors import DependencyError

        try:
            import torch  # noqa: F401
        except ImportError:
            raise DependencyError("export needs torch: pip install 'trianflow-vo[torch]'") from None
        try:
            import onnx  # noqa: F401
        except ImportError:
            raise DependencyError("export needs onnx: pip install 'trianflow-vo[torch]'") from None
        from trianflow_vo.nets.onnx_runtime import require_onnxruntime

        require_onnxruntime()  # the parity check runs the exported files
        import warnings

        from trianflow_vo.models.checkpoint import DEFAULT_SIZE, checkpoint_from_dict, load_checkpoint, random_checkpoint
        from trianflow_vo.models.export import export_checkpoint

        if random_init:
            ckpt = checkpoint_from_dict(random_checkpoint(seed, size or DEFAULT_SIZE), "<random-init>")
        else:
            ckpt = load_checkpoint(checkpoint)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            try:
                results = export_checkpoint(ckpt, out_dir, size, seed)
            except ValueError as exc:  # size not accepted by a network
                raise click.UsageError(str(exc)) from None
        for name, res in results.items():
            worst = max(res["max_abs_diff"].values())
            detail = ", ".join(f"{k} {v:.2e}" for k, v in res["max_abs_diff"].items())
            click.echo(f"{name}: {res['path']}  max |onnxruntime - torch| = {worst:.2e} ({detail})")
