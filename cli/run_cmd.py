"""``trianflow-vo run``: parse options, build the Config, call :func:`trianflow_vo.pipeline.run`."""

from __future__ import annotations

import contextlib
import sys
from datetime import datetime
from pathlib import Path

import click

# the configuration rule (SHORTCUTS, build_config) is shared with `batch`; the names stay importable from here
from trianflow_vo.cli.config_flags import SHORTCUTS, build_config  # noqa: F401
from trianflow_vo.cli.config_flags import shortcut_dict as _shortcut_dict  # noqa: F401
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


def _hms(seconds: float) -> str:
    s = int(round(seconds))
    h, rem = divmod(s, 3600)
    m, sec = divmod(rem, 60)
    return f"{h}:{m:02d}:{sec:02d}" if h else f"{m}:{sec:02d}"


class Progress(Observer):
    """One status line on stderr: frames read (processed and skipped) of the total, frames/s, ETA,
    branch counts. The counts and the frame rate come from the run's
    :class:`~trianflow_vo.io.run_writer.RunClock`, the same that ``run.json`` and the summary use."""

    def __init__(self, enabled: bool, clock=None):
        from trianflow_vo.io.run_writer import RunClock

        self.clock = clock if clock is not None else RunClock()
        self.total = 0
        self.enabled = enabled and sys.stderr.isatty()
        self.plain = enabled and not self.enabled
        self.counts: dict[str, int] = {}
        self._printed = -1  # frames read when the plain line was last printed

    def on_start(self, total: int) -> None:
        self.total = total

    def line(self) -> str:
        c = self.clock
        done = c.done
        text = f"{done}/{self.total} frames"
        if c.skipped:
            text += f" ({c.skipped} skipped)"
        fps = c.fps
        text += f"  {fps:5.1f} fps" if fps is not None else "    -- fps"
        eta = c.eta_s()
        if eta is not None and done < self.total:
            text += f"  ETA {_hms(eta)}"
        branches = " ".join(f"{k} {v}" for k, v in self.counts.items() if k != "init")
        return f"{text}  {branches}".rstrip()

    def _draw(self, final: bool = False) -> None:
        done = self.clock.done
        if self.enabled:
            frac = min(done / max(self.total, 1), 1.0)
            bar = "#" * int(24 * frac) + "-" * (24 - int(24 * frac))
            click.echo(f"\r[{bar}] {self.line()}\x1b[K", nl=False, err=True)
        elif self.plain and (final or done % 50 == 0 or done == self.total) and done != self._printed:
            click.echo(self.line(), err=True)
            self._printed = done

    def on_frame(self, rec) -> None:
        self.counts[rec.branch] = self.counts.get(rec.branch, 0) + 1
        self._draw()

    def close(self, interrupted: bool = False) -> None:
        self._draw(final=True)  # skipped frames after the last processed one count too
        if self.enabled:
            click.echo("", err=True)


def default_out_dir(seq: Path) -> Path:
    """Create and return a new folder ``runs/<sequence name>-<date-time>[-n]`` (atomic: two runs
    started at once get two folders)."""
    from trianflow_vo.io.run_dir import make_unique_dir

    stamp = datetime.now().strftime("%Y%m%d-%H%M%S")
    return make_unique_dir(Path("runs"), f"{Path(seq).resolve().name or 'seq'}-{stamp}")


def _remove_if_empty(folder: Path | None, parent_existed: bool = True) -> None:
    """Remove a default run folder the run never wrote into (and ``runs/`` if this run made it)."""
    if folder is None:
        return
    with contextlib.suppress(OSError):
        folder.rmdir()
        if not parent_existed:
            folder.parent.rmdir()


@click.command("run")
@click.argument("seq", type=click.Path(path_type=Path))
@click.option("--out", "out_dir", type=click.Path(path_type=Path), default=None,
              help="Output folder (default: a new folder under ./runs/). A folder holding an earlier run is "
                   "refused unless --overwrite; one in use by a running run always is.")
@click.option("--overwrite", is_flag=True,
              help="Replace the earlier run in --out (its files only: poses.txt, run.json, trajectory.png, ...; "
                   "other files are kept).")
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
                   "multiples of 64; at most 4096 per side, and refused when the per-frame buffers would not "
                   "fit in the available memory).")
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
              help="With --set keyframes.policy=parallax (the earlier rule): median parallax (px, after "
                   "removing rotation) below which PnP/rotation-only is used [keyframes.min_parallax_px; 3].")
@click.option("--window", type=click.IntRange(0, 100), default=None,
              help="Keyframes in the bundle-adjustment window; 0 = no back-end, the paper's pure two-view "
                   "pipeline [backend.window; 6].")
@click.option("--samples", "n_samples", type=click.IntRange(100, 100000), default=None,
              help="Matches drawn per frame pair [sampling.n_samples; 12000].")
@click.option("--seed", type=click.IntRange(min=0), default=None,
              help="Random seed; runs are reproducible [sampling.seed; 0].")
@click.option("--gt", type=click.Path(path_type=Path), default=None,
              help="Ground-truth poses, drawn beside the estimate in trajectory.png and the Rerun recording "
                   "[output.gt].")
@click.option("--rerun", "rerun_path", type=click.Path(path_type=Path), default=None,
              help="Write a Rerun recording (.rrd) [output.rerun]; its folder must exist (or be --out).")
@click.option("--rerun-spawn", is_flag=True, default=None, help="Stream to a live Rerun viewer [output.rerun_spawn].")
@click.option("--no-plot", is_flag=True, help="Do not write trajectory.png [output.plot=false].")
@click.option("-v", "--verbose", count=True, help="Log routine steps too (PnP on small parallax, static camera); "
                                                 "-vv for debugging.")
@click.option("-q", "--quiet", is_flag=True, help="No progress bar and no warnings (errors only).")
def run(seq, out_dir, config_file, overrides, no_plot, verbose, quiet, overwrite, **shortcuts):
    """Estimate the camera trajectory of SEQ.

    SEQ is a KITTI odometry sequence folder (image_0/ or image_2/ with calib.txt),
    a TUM RGB-D folder (rgb.txt), a folder of images or a video file.

    Writes poses.txt (KITTI, camera-to-world), frames.txt (source frame of each
    line), trajectory.tum, frames.tsv, run.json, config.yaml and trajectory.png
    to the output folder, frame by frame: an interrupted run keeps what it did.
    `--config OUT/config.yaml` (or OUT/run.json) repeats a run exactly.
    Ctrl-C and SIGTERM stop the run alike: the outputs are closed with status
    'interrupted' in run.json; exit status 130 (Ctrl-C) or 143 (SIGTERM).
    """
    from trianflow_vo.cli.logs import setup_logging
    from trianflow_vo.io.run_dir import InterruptSignals, exit_code, signal_name
    from trianflow_vo.io.run_writer import RunClock
    from trianflow_vo.pipeline import run as run_pipeline

    setup_logging(-1 if quiet else verbose)
    from trianflow_vo.cli.memory import keep_freed_buffers

    keep_freed_buffers()
    with user_errors():
        config = build_config(config_file, overrides, shortcuts, no_plot)
    if config.input.intrinsics is not None and config.input.calib is not None:
        raise click.UsageError("give either intrinsics or a calibration file, not both "
                               "(input.intrinsics / input.calib)")
    created = None
    runs_existed = Path("runs").is_dir()
    with InterruptSignals():  # Ctrl-C and SIGTERM alike: close the outputs as 'interrupted'
        try:
            with user_errors():
                if out_dir is None:
                    out_dir = created = default_out_dir(seq)
                clock = RunClock()
                progress = Progress(enabled=not quiet, clock=clock)  # closed by the pipeline, like every observer
                summary = run_pipeline(seq, out_dir, config, observers=[progress], overwrite=overwrite,
                                       clock=clock)
        except KeyboardInterrupt as exc:
            _remove_if_empty(created, runs_existed)
            name = signal_name(exc)
            how = "interrupted" if name == "SIGINT" else f"interrupted ({name})"
            where = f"the trajectory so far is in {out_dir}" if out_dir is not None and out_dir.is_dir() \
                else "nothing was written"
            click.echo(f"{how}: {where}", err=True)
            sys.exit(exit_code(exc))  # 130 for Ctrl-C (SIGINT), 143 for SIGTERM
        except BaseException:
            _remove_if_empty(created, runs_existed)  # a default folder the run never wrote into
            raise
    c = summary["branch_counts"]
    if not quiet:
        fps = summary["fps"]
        click.echo(
            f"{summary['frames_processed']} frames ({summary['frames_skipped']} skipped) in "
            f"{summary['elapsed_s']:.1f} s, {'n/a' if fps is None else f'{fps:.1f}'} frames/s; "
            f"two-view {c['two-view']}, pnp {c['pnp']}, "
            f"rotation-only {c['rotation']}, static {c['identity']}, failed {c['failed']}"
        )
    click.echo(f"wrote {out_dir}")
