"""``trianflow-vo run``: parse options, build a RunConfig, call :func:`vo.pipeline.run`."""

from __future__ import annotations

import sys
import time
from datetime import datetime
from pathlib import Path

import click

from trianflow_vo.cli.errors import user_errors
from trianflow_vo.cli.options import parse_size


def _parse_intrinsics(ctx, param, value):
    if value is None:
        return None
    from trianflow_vo.errors import InputError
    from trianflow_vo.io.calib import parse_intrinsics

    try:
        return parse_intrinsics(value)
    except InputError as exc:
        raise click.BadParameter(exc.message) from None


class Progress:
    """One status line on stderr: frames done, frames/s, branch counts."""

    def __init__(self, enabled: bool):
        self.total = 0
        self.enabled = enabled and sys.stderr.isatty()
        self.plain = enabled and not self.enabled
        self.counts: dict[str, int] = {}
        self.t0 = time.perf_counter()
        self.n = 0

    def on_start(self, total: int) -> None:
        self.total = total
        self.t0 = time.perf_counter()

    def on_frame(self, rec) -> None:
        self.n += 1
        self.counts[rec.branch] = self.counts.get(rec.branch, 0) + 1
        if not (self.enabled or self.plain):
            return
        fps = self.n / max(time.perf_counter() - self.t0, 1e-9)
        branches = " ".join(f"{k} {v}" for k, v in self.counts.items() if k != "init")
        line = f"{self.n}/{self.total} frames  {fps:5.1f} fps  {branches}"
        if self.enabled:
            frac = self.n / max(self.total, 1)
            bar = "#" * int(24 * frac) + "-" * (24 - int(24 * frac))
            click.echo(f"\r[{bar}] {line}\x1b[K", nl=False, err=True)
        elif self.n % 50 == 0 or self.n == self.total:
            click.echo(line, err=True)

    def close(self, interrupted: bool = False) -> None:
        if self.enabled:
            click.echo("", err=True)


@click.command("run")
@click.argument("seq", type=click.Path(path_type=Path))
@click.option("--out", "out_dir", type=click.Path(path_type=Path), default=None,
              help="Output folder (default: a new folder under ./runs/).")
@click.option("--stride", type=int, default=1, show_default=True, help="Use every N-th frame.")
@click.option("--start", type=int, default=0, show_default=True, help="First source frame index.")
@click.option("--end", type=int, default=None, help="Stop before this source frame index.")
@click.option("--size", callback=parse_size, default=None, metavar="HxW",
              help="Working resolution (default 256x832 for KITTI-like frames, else long side <= 832, multiples of 64).")
@click.option("--intrinsics", callback=_parse_intrinsics, default=None, metavar="FX,FY,CX,CY",
              help="Camera intrinsics at the source resolution (overrides the sequence's calibration).")
@click.option("--calib", type=click.Path(path_type=Path), default=None,
              help="Calibration file: KITTI calib.txt, a 3x3 K, or 'fx fy cx cy'.")
@click.option("--flow-model", type=click.Path(path_type=Path), default=None,
              help="ONNX flow network (from `trianflow-vo export`); default OpenCV DIS flow.")
@click.option("--depth-model", type=click.Path(path_type=Path), default=None,
              help="ONNX depth network; default: depth carried from earlier triangulation.")
@click.option("--threads", type=click.IntRange(1, 64), default=2, show_default=True,
              help="CPU threads for OpenCV and onnxruntime.")
@click.option("--dis-preset", type=click.Choice(["fast", "medium", "fine"]), default="medium", show_default=True,
              help="OpenCV DIS flow setting (weight-free path).")
@click.option("--min-parallax", "min_parallax_px", type=click.FloatRange(0.0, 100.0), default=3.0,
              show_default=True,
              help="Median parallax (px, after removing rotation) below which PnP/rotation-only is used.")
@click.option("--samples", "n_samples", type=click.IntRange(100, 100000), default=6000, show_default=True,
              help="Matches drawn per frame pair.")
@click.option("--seed", type=int, default=0, show_default=True, help="Random seed (runs are reproducible).")
@click.option("--gt", type=click.Path(path_type=Path), default=None,
              help="Ground-truth poses, drawn beside the estimate in trajectory.png and the Rerun recording.")
@click.option("--rerun", "rerun_path", type=click.Path(path_type=Path), default=None,
              help="Write a Rerun recording (.rrd).")
@click.option("--rerun-spawn", is_flag=True, help="Stream to a live Rerun viewer.")
@click.option("--no-plot", is_flag=True, help="Do not write trajectory.png.")
@click.option("-q", "--quiet", is_flag=True, help="No progress bar and no warnings.")
def run(seq, out_dir, stride, start, end, size, intrinsics, calib, flow_model, depth_model, threads, dis_preset,
        min_parallax_px, n_samples, seed, gt, rerun_path, rerun_spawn, no_plot, quiet):
    """Estimate the camera trajectory of SEQ.

    SEQ is a KITTI odometry sequence folder (image_0/ or image_2/ with calib.txt),
    a TUM RGB-D folder (rgb.txt), a folder of images or a video file.

    Writes poses.txt (KITTI, camera-to-world), frames.txt (source frame of each
    line), trajectory.tum, run.json and trajectory.png to the output folder, frame
    by frame: an interrupted run keeps what it did.
    """
    import cv2

    from trianflow_vo.config import RunConfig
    from trianflow_vo.pipeline import run as run_pipeline

    if stride < 1:
        raise click.BadParameter(f"must be >= 1, got {stride}", param_hint="--stride")
    if intrinsics is not None and calib is not None:
        raise click.UsageError("give either --intrinsics or --calib, not both")
    if out_dir is None:
        stamp = datetime.now().strftime("%Y%m%d-%H%M%S")
        out_dir = Path("runs") / f"{Path(seq).resolve().name or 'seq'}-{stamp}"
        n = 1
        base = out_dir
        while out_dir.exists():
            n += 1
            out_dir = Path(f"{base}-{n}")
    cv2.setNumThreads(threads)
    config = RunConfig(seq=seq, out_dir=out_dir, start=start, end=end, stride=stride, intrinsics=intrinsics,
                       calib=calib, size=size, flow_model=flow_model, depth_model=depth_model, threads=threads,
                       seed=seed, n_samples=n_samples, dis_preset=dis_preset, min_parallax_px=min_parallax_px, rerun=rerun_path,
                       rerun_spawn=rerun_spawn, gt=gt, plot=not no_plot, quiet=quiet)

    warnings: list[str] = []

    def warn(msg: str) -> None:
        warnings.append(msg)

    with user_errors():
        progress = Progress(enabled=not quiet)  # closed by the pipeline, like every observer
        try:
            summary = run_pipeline(config, observers=[progress], on_warning=warn)
        except KeyboardInterrupt:
            click.echo(f"interrupted: the trajectory so far is in {out_dir}", err=True)
            sys.exit(130)
        finally:
            if not quiet:
                _print_warnings(warnings)
    c = summary["branch_counts"]
    if not quiet:
        click.echo(
            f"{summary['frames_processed']} frames ({summary['frames_skipped']} skipped) in "
            f"{summary['elapsed_s']:.1f} s, {summary['fps']:.1f} frames/s; two-view {c['two-view']}, pnp {c['pnp']}, "
            f"rotation-only {c['rotation']}, static {c['identity']}, failed {c['failed']}"
        )
    click.echo(f"wrote {out_dir}")


def _print_warnings(warnings: list[str], limit: int = 10) -> None:
    for msg in warnings[:limit]:
        click.echo(f"warning: {msg}", err=True)
    if len(warnings) > limit:
        click.echo(f"warning: ... and {len(warnings) - limit} more (all listed in run.json)", err=True)
