"""``trianflow-vo batch``: many sequences (and sweep values) at once on Ray; a summary of them all.

Parses the options, builds every job's configuration up front (a bad key stops the batch before
anything runs: exit 2), runs the jobs with :func:`trianflow_vo.batch.runner.run_batch` and always
writes the summary. Ray is imported only when the command runs (``--help`` stays instant).
"""

from __future__ import annotations

import shlex
import sys
import time
from datetime import datetime
from pathlib import Path

import click

from trianflow_vo.cli.errors import user_errors


def _parse_lengths(ctx, param, value):
    if value is None or value.strip().lower() == "auto":
        return None
    try:
        lengths = sorted({float(x) for x in value.split(",") if x.strip()})
    except ValueError:
        raise click.BadParameter(f"expected 'auto' or comma-separated metres, e.g. 10,20,50; got {value!r}") \
            from None
    if not lengths or any(not (0 < x < float("inf")) for x in lengths):
        raise click.BadParameter(f"lengths must be positive numbers, got {value!r}")
    return tuple(lengths)


class BatchLine:
    """The live view on stderr: runs completed / failed / running / pending, frames/s of the whole batch,
    elapsed time. Redrawn in place on a terminal; elsewhere a line whenever the counts change. Each
    run that does not complete is printed at once with its reason (also with ``--quiet``)."""

    def __init__(self, enabled: bool):
        self.tty = enabled and sys.stderr.isatty()
        self.plain = enabled and not self.tty
        self._last: tuple | None = None
        self.workers: int | None = None

    def text(self, p) -> str:
        from trianflow_vo.cli.run_cmd import _hms

        fps = p.fps
        return (f"{p.completed + p.failed}/{p.total} done ({p.failed} failed), {p.running} running, "
                f"{p.pending} pending  {p.frames} frames  "
                + (f"{fps:.1f} frames/s" if fps is not None else "-- frames/s") + f"  {_hms(p.elapsed_s)}")

    def progress(self, p) -> None:
        self.workers = p.workers
        if self.tty:
            click.echo(f"\r{self.text(p)}\x1b[K", nl=False, err=True)
        elif self.plain:
            key = (p.completed, p.failed, p.running, p.pending)
            if key != self._last:
                self._last = key
                click.echo(self.text(p), err=True)

    def result(self, row: dict) -> None:
        if row["status"] == "completed":
            return
        if self.tty:
            click.echo("\r\x1b[K", nl=False, err=True)
        click.echo(f"{row['status']}: {row['label']}: {row['reason'] or 'no reason given'}", err=True)

    def close(self) -> None:
        if self.tty:
            click.echo("", err=True)


def _command_line(seqs, manifest, out_dir, config_file, overrides, sweeps, workers, address, timeout, force,
                  lengths, no_plot) -> str:
    """The batch as one canonical command line (for summary.md)."""
    args = ["trianflow-vo", "batch", *map(str, seqs)]
    if manifest is not None:
        args += ["--manifest", str(manifest)]
    args += ["--out", str(out_dir)]
    if config_file:
        args += ["--config", config_file]
    for s in overrides:
        args += ["--set", s]
    for s in sweeps:
        args += ["--sweep", s]
    for flag, v in (("--workers", workers), ("--address", address), ("--timeout", timeout)):
        if v is not None:
            args += [flag, f"{v:g}" if isinstance(v, float) else str(v)]
    if lengths is not None:
        args += ["--lengths", ",".join(f"{x:g}" for x in lengths)]
    args += ["--force"] * bool(force) + ["--no-plot"] * bool(no_plot)
    return shlex.join(args)


@click.command("batch", context_settings={"help_option_names": ["-h", "--help"]},
               epilog="""\b
Examples:
  trianflow-vo batch data/kitti06 data/kitti00 --out runs/batch --set input.stride=2
  trianflow-vo batch --manifest seqs.yaml --out runs/b --sweep sampling.seed=0,1,2
  trianflow-vo batch --manifest seqs.csv --out /shared/runs --address auto --timeout 600
""")
@click.argument("seqs", nargs=-1, type=click.Path(path_type=Path))
@click.option("--manifest", type=click.Path(exists=True, dir_okay=False, path_type=Path), default=None,
              help="YAML or CSV list of sequences with optional name, gt, calib or intrinsics, stride, start, end, "
                   "lengths and set (configuration keys) per sequence; relative paths are relative to the file.")
@click.option("--out", "out_dir", type=click.Path(file_okay=False, path_type=Path), required=True,
              help="Batch folder: one run folder DIR/NAME[/KEY=VALUE,...] per job (what `run` writes), "
                   "summary.csv, summary.md, summary.json.")
@click.option("--config", "config_file", metavar="FILE|PRESET", default=None,
              help="Configuration of every job: a YAML file, a run.json/config.yaml, or a preset (as `run`).")
@click.option("--set", "overrides", multiple=True, metavar="SECTION.KEY=VALUE",
              help="Set one configuration key for every job (repeatable); a sequence's own keys win.")
@click.option("--sweep", "sweeps", multiple=True, metavar="SECTION.KEY=V1,V2,...",
              help="Run every sequence with each value (repeatable: the cartesian product of all sweeps).")
@click.option("--workers", type=click.IntRange(min=1), default=None,
              help="Runs at once (default: CPU cores / runtime.threads; on a cluster its CPUs / threads).")
@click.option("--address", default=None, metavar="auto|HOST:PORT|ray://HOST:PORT",
              help="Join a running Ray cluster (`ray start --head`) instead of starting one here: auto (RAY_ADDRESS "
                   "or the cluster started on this machine), its GCS address, or its Ray Client address. The data, "
                   "models and --out must be visible to every worker at the same paths.")
@click.option("--timeout", type=click.FloatRange(min=0.0, min_open=True), default=None, metavar="S",
              help="Stop a run after S seconds (from its task's submission, worker start included): it is failed.")
@click.option("--force", is_flag=True, help="Run again the jobs whose folder already holds a completed run "
                                            "(default: they are skipped, i.e. the batch resumes).")
@click.option("--lengths", default="auto", callback=_parse_lengths, metavar="auto|L1,L2,...",
              help="KITTI segment lengths (m) for runs with ground truth [auto: 100..800, or lengths that fit a "
                   "shorter ground-truth path]; a sequence's own win.")
@click.option("--no-plot", is_flag=True, help="No trajectory.png in the run folders [output.plot=false].")
@click.option("-q", "--quiet", is_flag=True, help="No progress line (runs that fail are still printed).")
def batch(seqs, manifest, out_dir, config_file, overrides, sweeps, workers, address, timeout, force, lengths,
          no_plot, quiet):
    """Run many sequences at once on Ray (local or a cluster).

    SEQ... are sequence folders or videos (as for `run`; the folder name is
    the run's NAME); --manifest lists them with per-sequence ground truth,
    calibration, stride and configuration. Each job runs in a fresh worker
    process and writes DIR/NAME (DIR/NAME/KEY=VALUE,... with --sweep), the
    same files `run` writes; its configuration is that of `run SEQ --config
    ... --set ... --set <sequence's keys> --set <sweep values> --stride ...`.

    A job that fails (bad input, crash, out of memory, --timeout) is reported
    with its reason; the others go on. Re-running the same command skips the
    jobs already completed (unless --force) and runs the others again.
    DIR/summary.csv and DIR/summary.md are always written: per job the
    status, frames, fps, branch counts and, with ground truth, ATE, RPE and
    KITTI t_err/r_err with the lengths used; one overall row.

    Exit status 0 when every job completed, 1 otherwise, 2 for a bad option,
    manifest or configuration key (nothing is run), 130/143 on Ctrl-C/SIGTERM.
    Needs Ray: pip install 'trianflow-vo[batch]'.
    """
    import os

    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")  # no usage-statistics notice or upload unless asked for
    from trianflow_vo.batch.jobs import job_config, new_result
    from trianflow_vo.batch.manifest import expand_jobs, parse_sweeps, read_manifest, sequences_from_args
    from trianflow_vo.batch.runner import BatchInterrupted, import_ray, run_batch
    from trianflow_vo.batch.summary import write_summary
    from trianflow_vo.cli.config_flags import build_config
    from trianflow_vo.cli.memory import keep_freed_buffers
    from trianflow_vo.io.run_dir import InterruptSignals, exit_code

    with user_errors():
        import_ray()
    if not seqs and manifest is None:
        raise click.UsageError("give sequences (SEQ...) or --manifest FILE")
    with user_errors():
        build_config(config_file, overrides, {}, no_plot)  # the batch-wide part, checked once
        entries = (read_manifest(manifest) if manifest is not None else []) + sequences_from_args(seqs)
        jobs = expand_jobs(entries, config_file=config_file, overrides=overrides, sweeps=parse_sweeps(sweeps),
                           lengths=lengths, no_plot=no_plot)
        configs = [job_config(j) for j in jobs]
        out_dir.mkdir(parents=True, exist_ok=True)
    out_root = out_dir.absolute()
    meta = {"command": _command_line(seqs, manifest, out_dir, config_file, overrides, sweeps, workers, address,
                                     timeout, force, lengths, no_plot),
            "started": datetime.now().isoformat(timespec="seconds"),
            "ray": "local" if address is None else address, "workers": workers, "jobs": len(jobs)}
    line = BatchLine(enabled=not quiet)
    got: dict[str, dict] = {}

    def on_result(row: dict) -> None:
        got[row["out_dir"]] = row
        line.result(row)

    t0 = time.perf_counter()
    stopped: BaseException | None = None
    problem: str | None = None
    with InterruptSignals():  # SIGTERM like Ctrl-C: the running jobs are stopped, the summary written
        try:
            results = run_batch(jobs, out_root, configs, workers=workers, address=address, timeout=timeout,
                                force=force, on_progress=line.progress, on_result=on_result,
                                worker_setup=keep_freed_buffers)
        except BatchInterrupted as exc:
            stopped, results = exc, exc.results
        except KeyboardInterrupt as exc:  # before the runner could collect its rows
            stopped, results = exc, []
        except Exception as exc:  # Ray could not start or join the cluster, ...
            from trianflow_vo.errors import VOError
            from trianflow_vo.pipeline import failure_reason

            problem, results = (str(exc) if isinstance(exc, VOError) else failure_reason(exc)), []
        finally:
            line.close()
        by_dir = {r["out_dir"]: r for r in results if r is not None}
        rows = []
        for job in jobs:
            key = str(out_root / job.out)
            row = by_dir.get(key) or got.get(key)
            if row is None:
                row = new_result(job, out_root / job.out, "pending",
                                 f"not run: {problem}" if problem else "not started (batch interrupted)")
            rows.append(row)
        meta["workers"] = workers or line.workers
        with user_errors():
            paths = write_summary(out_root, rows, meta, wall_s=time.perf_counter() - t0)
    done = sum(r["status"] == "completed" for r in rows)
    click.echo(f"{done}/{len(rows)} completed; wrote {paths[0]} and {paths[1]}")
    if stopped is not None:
        click.echo("batch interrupted: running jobs were stopped", err=True)
        sys.exit(exit_code(stopped))
    if problem is not None:
        raise click.ClickException(f"the batch could not run: {problem}")
    sys.exit(0 if done == len(rows) else 1)
