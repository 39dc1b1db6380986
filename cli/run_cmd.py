"""``trianflow-vo run``: parse options, build the Config, call :func:`trianflow_vo.pipeline.run`."""

from __future__ import annotations

import sys
import time
from datetime import datetime
from pathlib import Path

import click

from trianflow_vo.cli.errors import user_errors
from trianflow_vo.cli.options import parse_size
from trianflow_vo.observer import Observer


def _parse_intrinsics(ctx, param, value):
    if value is None:
        return None
    from trianflow_vo.errors import InputError
    from trianflow_vo.io.calib import parse_intrinsics

    try:
        return parse_intrinsics(value)
    except InputError as exc:
        raise click.BadParameter(exc.message) from None


class Progress(Observer):
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


# shortcut flag -> configuration key (a flag given on the command line wins over --config and --set)
SHORTCUTS = {
    "stride": "input.stride", "start": "input.start", "end": "input.end", "size": "input.size",
    "intrinsics": "input.intrinsics", "calib": "input.calib",
    "flow_model": "flow.model", "dis_preset": "flow.dis_preset", "depth_model": "depth.model",
    "scale_from": "scale.source",
    "n_samples": "sampling.n_samples", "seed": "sampling.seed", "min_parallax_px": "keyframes.min_parallax_px",
    "threads": "runtime.threads", "gt": "output.gt", "rerun_path": "output.rerun", "rerun_spawn": "output.rerun_spawn",
}


def _shortcut_dict(values: dict) -> dict:
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
    flags = _shortcut_dict(shortcuts)
    if no_plot:
        flags.setdefault("output", {})["plot"] = False
    return merge_dict(config, flags, "command-line flags") if flags else config


def default_out_dir(seq: Path) -> Path:
    stamp = datetime.now().strftime("%Y%m%d-%H%M%S")
    out_dir = Path("runs") / f"{Path(seq).resolve().name or 'seq'}-{stamp}"
    n, base = 1, out_dir
    while out_dir.exists():
        n += 1
        out_dir = Path(f"{base}-{n}")
    return out_dir


@click.command("run")
@click.argument("seq", type=click.Path(path_type=Path))
@click.option("--out", "out_dir", type=click.Path(path_type=Path), default=None,
              help="Output folder (default: a new folder under ./runs/).")
@click.option("--config", "config_file", metavar="FILE|PRESET", default=None,
              help="Configuration: a YAML file, a run's run.json or config.yaml (reproduces that run), "
                   "or a shipped preset (default, kitti, indoor). See configs/README.md.")
@click.option("--set", "overrides", multiple=True, metavar="SECTION.KEY=VALUE",
              help="Set one configuration key, e.g. --set sampling.n_samples=8000 (repeatable).")
@click.option("--stride", type=click.IntRange(min=1), default=None, help="Use every N-th frame [input.stride; 1].")
@click.option("--start", type=click.IntRange(min=0), default=None, help="First source frame index [input.start; 0].")
@click.option("--end", type=int, default=None, help="Stop before this source frame index [input.end].")
@click.option("--size", callback=parse_size, default=None, metavar="HxW",
              help="Working resolution [input.size] (default 256x832 for KITTI-like frames, else long side <= 832, "
                   "multiples of 64).")
@click.option("--intrinsics", callback=_parse_intrinsics, default=None, metavar="FX,FY,CX,CY",
              help="Camera intrinsics at the source resolution, overriding the sequence's calibration "
                   "[input.intrinsics].")
@click.option("--calib", type=click.Path(path_type=Path), default=None,
              help="Calibration file: KITTI calib.txt, a 3x3 K, or 'fx fy cx cy' [input.calib].")
@click.option("--flow-model", type=click.Path(path_type=Path), default=None,
              help="ONNX flow network (from `trianflow-vo export`) [flow.model]; default OpenCV DIS flow.")
@click.option("--depth-model", type=click.Path(path_type=Path), default=None,
              help="ONNX depth network [depth.model]; default: depth carried from earlier triangulation.")
@click.option("--scale-from", "scale_from", type=click.Choice(["auto", "triangulation", "keyframe-depth", "depth"]),
              default=None,
              help="Where each step's length comes from [scale.source; auto]: triangulation (depth carried from "
                   "earlier triangulation, no network needed), keyframe-depth (the depth network's prediction of "
                   "the keyframe), depth (the authors' recipe: every pair fitted to the network depth of the new "
                   "frame, PnP on small flow); auto = keyframe-depth with --depth-model, else triangulation.")
@click.option("--threads", type=click.IntRange(1, 64), default=None,
              help="CPU threads for OpenCV and onnxruntime [runtime.threads; 2].")
@click.option("--dis-preset", type=click.Choice(["fast", "medium", "fine"]), default=None,
              help="OpenCV DIS flow setting, weight-free path [flow.dis_preset; medium].")
@click.option("--min-parallax", "min_parallax_px", type=click.FloatRange(0.0, 100.0), default=None,
              help="Median parallax (px, after removing rotation) below which PnP/rotation-only is used "
                   "[keyframes.min_parallax_px; 3].")
@click.option("--samples", "n_samples", type=click.IntRange(100, 100000), default=None,
              help="Matches drawn per frame pair [sampling.n_samples; 6000].")
@click.option("--seed", type=click.IntRange(min=0), default=None,
              help="Random seed; runs are reproducible [sampling.seed; 0].")
@click.option("--gt", type=click.Path(path_type=Path), default=None,
              help="Ground-truth poses, drawn beside the estimate in trajectory.png and the Rerun recording "
                   "[output.gt].")
@click.option("--rerun", "rerun_path", type=click.Path(path_type=Path), default=None,
              help="Write a Rerun recording (.rrd) [output.rerun].")
@click.option("--rerun-spawn", is_flag=True, default=None, help="Stream to a live Rerun viewer [output.rerun_spawn].")
@click.option("--no-plot", is_flag=True, help="Do not write trajectory.png [output.plot=false].")
@click.option("-v", "--verbose", count=True, help="Log routine steps too (PnP on small parallax, static camera); "
                                                 "-vv for debugging.")
@click.option("-q", "--quiet", is_flag=True, help="No progress bar and no warnings (errors only).")
def run(seq, out_dir, config_file, overrides, no_plot, verbose, quiet, **shortcuts):
    """Estimate the camera trajectory of SEQ.

    SEQ is a KITTI odometry sequence folder (image_0/ or image_2/ with calib.txt),
    a TUM RGB-D folder (rgb.txt), a folder of images or a video file.

    Writes poses.txt (KITTI, camera-to-world), frames.txt (source frame of each
    line), trajectory.tum, frames.tsv, run.json, config.yaml and trajectory.png
    to the output folder, frame by frame: an interrupted run keeps what it did.
    `--config OUT/config.yaml` (or OUT/run.json) repeats a run exactly.
    """
    from trianflow_vo.cli.logs import setup_logging
    from trianflow_vo.pipeline import run as run_pipeline

    setup_logging(-1 if quiet else verbose)
    with user_errors():
        config = build_config(config_file, overrides, shortcuts, no_plot)
    if config.input.intrinsics is not None and config.input.calib is not None:
        raise click.UsageError("give either intrinsics or a calibration file, not both "
                               "(input.intrinsics / input.calib)")
    out_dir = out_dir or default_out_dir(seq)
    with user_errors():
        progress = Progress(enabled=not quiet)  # closed by the pipeline, like every observer
        try:
            summary = run_pipeline(seq, out_dir, config, observers=[progress])
        except KeyboardInterrupt:
            click.echo(f"interrupted: the trajectory so far is in {out_dir}", err=True)
            sys.exit(130)
    c = summary["branch_counts"]
    if not quiet:
        click.echo(
            f"{summary['frames_processed']} frames ({summary['frames_skipped']} skipped) in "
            f"{summary['elapsed_s']:.1f} s, {summary['fps']:.1f} frames/s; two-view {c['two-view']}, pnp {c['pnp']}, "
            f"rotation-only {c['rotation']}, static {c['identity']}, failed {c['failed']}"
        )
    click.echo(f"wrote {out_dir}")
