"""``trianflow-vo predict``: depth and flow of images with exported networks (TrianFlow's demo as a tool)."""

from __future__ import annotations

import sys
from pathlib import Path

import click

from trianflow_vo.cli.errors import user_errors


class ArgumentError(click.ClickException):
    """A bad combination of arguments: one line (no usage text), exit status 2 like a usage error."""

    exit_code = 2


class _Bar:
    """``progress(done, total, name)`` for the library: a bar on a terminal, plain lines otherwise."""

    def __init__(self, label: str, tty: bool):
        self.label = label
        self.tty = tty

    def __call__(self, done: int, total: int, name: str) -> None:
        line = f"{self.label} {done}/{total} {name}"
        if self.tty:
            frac = done / max(total, 1)
            bar = "#" * int(24 * frac) + "-" * (24 - int(24 * frac))
            click.echo(f"\r[{bar}] {line}\x1b[K", nl=False, err=True)
            if done == total:
                click.echo("", err=True)
        elif done == total or done % max(1, total // 20) == 0:
            click.echo(line, err=True)


@click.command(
    "predict",
    context_settings={"help_option_names": ["-h", "--help"]},
    epilog="""\b
Outputs (NAME = the image's file stem; for flow, the first image's):
  NAME.depth.npy  float32 HxW depth at the network's input size, as the network
                  outputs it (within the model's depth_range metadata; monocular:
                  up to an unknown scale)
  NAME.depth.png  magma colour map of inverse depth (near = bright), ranged
                  between its 2nd and 98th percentiles
  NAME.flow.npy   float32 HxWx2 forward flow image1 -> image2, in pixels at the
                  network's input size, [..., 0] = dx, [..., 1] = dy
  NAME.flo        the same flow, Middlebury .flo
  NAME.flow.png   colour-wheel image of the flow (hue = direction, saturation =
                  magnitude up to the pair's largest; zero flow is white)
\b
Images are resized to the network's input size with the resize method stored in
the model's metadata; nothing is resized back. With both models: depth for every
image, flow for the pair(s). Files are written as FILE.tmp, then renamed.
\b
Examples:
  trianflow-vo predict --depth-model depth.onnx frames/ --out pred/
  trianflow-vo predict --flow-model flow.onnx 000000.png 000001.png --out pred/
  trianflow-vo predict --depth-model depth.onnx --flow-model flow.onnx \\
                       frames/ --pairs consecutive --out pred/
""",
)
@click.argument("inputs", nargs=-1, required=True, metavar="IMG_OR_FOLDER...", type=click.Path(path_type=Path))
@click.option("--depth-model", type=click.Path(path_type=Path), default=None,
              help="ONNX depth network (from `trianflow-vo export`): depth of every image.")
@click.option("--flow-model", type=click.Path(path_type=Path), default=None,
              help="ONNX flow network: forward flow of the image pair(s).")
@click.option("--pairs", type=click.Choice(["two", "consecutive"]), default="two", show_default=True,
              help="Flow pairs: 'two' = exactly two images in all, one pair; 'consecutive' = every "
                   "consecutive pair of the images in order (e.g. a folder).")
@click.option("--out", "out_dir", required=True, type=click.Path(path_type=Path),
              help="Output folder (created if needed; existing files of the same name are replaced).")
@click.option("--threads", type=click.IntRange(1, 64), default=2, show_default=True,
              help="CPU threads of onnxruntime.")
@click.option("-q", "--quiet", is_flag=True, help="No progress and no summary line (errors only).")
def predict(inputs, depth_model, flow_model, pairs, out_dir, threads, quiet):
    """Predict depth and/or optical flow of images with exported networks.

    IMG_OR_FOLDER... are image files and/or folders of images (png, jpg, jpeg,
    bmp, tif, tiff; read in natural order: img2 before img10). Give
    --depth-model, --flow-model or both. Flow needs exactly two images, unless
    --pairs consecutive. Progress goes to stderr when a folder is given.
    """
    if depth_model is None and flow_model is None:
        raise ArgumentError("give --depth-model DEPTH.onnx, --flow-model FLOW.onnx or both")
    if pairs != "two" and flow_model is None:
        raise ArgumentError(f"--pairs {pairs} needs --flow-model")
    with user_errors():
        from trianflow_vo import predict as P
        from trianflow_vo.errors import InputError
        from trianflow_vo.nets.onnx_runtime import OnnxModel

        images = P.collect_images(inputs)
        pair_list = []
        if flow_model is not None:
            try:
                pair_list = P.flow_pairs(images, pairs)
            except InputError:
                if pairs == "two":
                    raise ArgumentError(f"--flow-model needs exactly 2 images, got {len(images)}; "
                                        "for a sequence add --pairs consecutive") from None
                raise ArgumentError(f"--pairs consecutive needs at least 2 images, got {len(images)}") from None
            P.check_unique_names([a for a, _ in pair_list], P.FLOW_NPY)
        if depth_model is not None:
            P.check_unique_names(images, P.DEPTH_NPY)
        # open (and validate) every model before writing anything
        depth_net = OnnxModel(depth_model, "depth", threads) if depth_model is not None else None
        flow_net = OnnxModel(flow_model, "flow", threads) if flow_model is not None else None
        P.prepare_out_dir(out_dir)

        show = not quiet and any(Path(p).is_dir() for p in inputs)
        tty = sys.stderr.isatty()
        written: list[Path] = []
        try:
            if depth_net is not None:
                written += P.predict_depth(images, depth_net, out_dir, threads,
                                           progress=_Bar("depth", tty) if show else None)
            if flow_net is not None:
                written += P.predict_flow(pair_list, flow_net, out_dir, threads,
                                          progress=_Bar("flow", tty) if show else None)
        except KeyboardInterrupt:
            if show and tty:
                click.echo("", err=True)
            click.echo(f"interrupted: the files already in {out_dir} are complete", err=True)
            sys.exit(130)
    if not quiet:
        what = []
        if depth_net is not None:
            what.append(f"depth of {len(images)} image{'s' * (len(images) != 1)}")
        if flow_net is not None:
            what.append(f"flow of {len(pair_list)} pair{'s' * (len(pair_list) != 1)}")
        click.echo(f"wrote {' and '.join(what)} ({len(written)} files) to {out_dir}")
