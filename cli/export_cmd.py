"""``trianflow-vo export``: write flow.onnx and depth.onnx from a checkpoint (or random weights).

Beside flow.onnx it writes flow_encoder.onnx and flow_decoder.onnx (the same network split
so that the run computes each frame's pyramid once; ``--no-split``: not), and with
``--quantize int8 --calibration DIR`` int8 versions of the decoder and of depth.onnx.

``--checkpoint`` takes our format (``models/checkpoint.py``) or the TrianFlow authors' own
``.pth`` (``models/authors.py``): the full layout (``depth_net.*`` +
``model_pose.model_flow.*``) gives flow.onnx and depth.onnx, the flow-stage layout
(``fpyramid.*`` + ``pwc_model.*``) flow.onnx only. A bad file is one error line naming it
(and the first offending tensor), exit status 1, and nothing is written into --out-dir.
"""

from __future__ import annotations

from pathlib import Path

import click

from trianflow_vo.cli.errors import user_errors
from trianflow_vo.cli.options import parse_size


@click.command("export")
@click.option("--checkpoint", type=click.Path(dir_okay=False, path_type=Path),
              help="Checkpoint file: trianflow-vo format (models/checkpoint.py) or the TrianFlow "
                   "authors' .pth (full or flow-only layout, models/authors.py).")
@click.option("--random-init", is_flag=True, help="Export freshly initialised networks (for testing).")
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of --random-init and of the check input.")
@click.option("--size", callback=parse_size, metavar="HxW",
              help="Fixed input size of the exported graphs. Default: the checkpoint's input size "
                   "(256x832 with --random-init and for the authors' checkpoints).")
@click.option("--out-dir", required=True, type=click.Path(file_okay=False, path_type=Path),
              help="Directory for flow.onnx and depth.onnx.")
@click.option("--no-split", is_flag=True,
              help="Write flow.onnx only, not the encoder/decoder graphs beside it (flow_encoder.onnx, "
                   "flow_decoder.onnx) with which the run computes each frame's pyramid once.")
@click.option("--quantize", type=click.Choice(["int8"]), default=None,
              help="Also quantise the flow decoder and the depth network to int8 (static, calibrated on "
                   "--calibration frames); their difference to fp32 is printed. flow.onnx and the encoder "
                   "stay fp32.")
@click.option("--calibration", type=click.Path(exists=True, file_okay=False, path_type=Path),
              help="Folder of consecutive frames (or a sequence folder with image_0/) for --quantize.")
@click.option("--calibration-frames", type=int, default=8, show_default=True,
              help="How many frames of --calibration to use (the first ones, consecutive).")
@click.option("--trust-checkpoint", is_flag=True,
              help="Allow torch.load(weights_only=False) for a checkpoint that holds pickled objects "
                   "(this can run code from the file: only for files you trust).")
def export(checkpoint, random_init, seed, size, out_dir, no_split, quantize, calibration, calibration_frames,
           trust_checkpoint):
    """Export flow and depth networks to ONNX and check them against torch."""
    if (checkpoint is None) == (not random_init):
        raise click.UsageError("give exactly one of --checkpoint CKPT or --random-init")
    if quantize and calibration is None:
        raise click.UsageError("--quantize int8 needs --calibration DIR (frames to calibrate on)")
    if quantize and no_split:
        raise click.UsageError("--quantize int8 needs the split flow graphs (drop --no-split)")
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

        from trianflow_vo.models.checkpoint import (
            DEFAULT_SIZE,
            FORMAT_TAG,
            checkpoint_from_dict,
            load_checkpoint,
            random_checkpoint,
        )
        from trianflow_vo.models.export import export_checkpoint

        if random_init:
            ckpt = checkpoint_from_dict(random_checkpoint(seed, size or DEFAULT_SIZE), "<random-init>")
            weights_file = None
        else:
            ckpt = load_checkpoint(checkpoint, trust_pickle=trust_checkpoint)
            weights_file = checkpoint.name
        frames = _calibration_frames(calibration, calibration_frames) if quantize else None
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            try:
                results = export_checkpoint(ckpt, out_dir, size, seed, weights_file=weights_file,
                                            split=not no_split, quantize=quantize, calibration=frames)
            except ValueError as exc:  # size not accepted by a network
                raise click.UsageError(str(exc)) from None
        if ckpt.source != FORMAT_TAG:
            click.echo(f"{checkpoint}: {ckpt.source} layout; input {ckpt.channel_order}, resize {ckpt.resize}, "
                       f"trained at {ckpt.input_size[0]}x{ckpt.input_size[1]}")
        for name, res in results.items():
            if "vs_fp32" in res:
                detail = ", ".join(f"{k} {v:.3g}" for k, v in res["vs_fp32"].items())
                click.echo(f"{name}: {res['path']}  int8 vs fp32 on the calibration frames: {detail}")
                continue
            worst = max(res["max_abs_diff"].values())
            detail = ", ".join(f"{k} {v:.2e}" for k, v in res["max_abs_diff"].items())
            click.echo(f"{name}: {res['path']}  max |onnxruntime - torch| = {worst:.2e} ({detail})")


def _calibration_frames(folder: Path, n: int) -> list:
    """The first ``n`` frames (BGR uint8, consecutive) of ``folder`` (or ``folder/image_0``)."""
    import cv2

    from trianflow_vo.errors import InputError

    src = folder / "image_0" if (folder / "image_0").is_dir() else folder
    files = sorted(p for p in src.iterdir() if p.suffix.lower() in (".png", ".jpg", ".jpeg"))
    if len(files) < 2 or n < 2:
        raise InputError(f"{src}: --quantize needs at least 2 calibration frames, found {len(files)}")
    frames = []
    for f in files[:n]:
        img = cv2.imread(str(f), cv2.IMREAD_COLOR)
        if img is None:
            raise InputError(f"{f}: cannot read the image")
        frames.append(img)
    return frames
