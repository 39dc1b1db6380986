"""One batch job: build its configuration, run the pipeline into its folder, evaluate; a result dict.

Runnable without Ray (``run_job(job, out_root)``); the Ray runner calls the same function in a
fresh worker process. A job never raises for a failure of its own sequence: the result says
``status: failed`` and a one-line ``reason``. Only ``KeyboardInterrupt`` (Ctrl-C, a cancelled
task) goes through, after the run folder was closed as ``interrupted`` by the pipeline.

Resume: a folder whose ``run.json`` says ``completed`` for the same sequence and configuration
is not run again (the result is read from it and evaluated, ``resumed: True``); one holding a
completed run of another configuration is refused unless ``force``; any other earlier run in
the folder (failed, interrupted, killed) is replaced.
"""

from __future__ import annotations

import json
import os
import socket
import time
from collections.abc import Mapping
from pathlib import Path

from trianflow_vo.batch.manifest import Job
from trianflow_vo.errors import ConfigError

BRANCHES = ("two-view", "pnp", "rotation", "identity", "failed")


def job_config(job: Job):
    """The job's :class:`~trianflow_vo.config.Config`, by the ``run`` command's rule
    (:func:`trianflow_vo.cli.config_flags.build_config`).

    Raises:
        ConfigError: a bad key or value, naming where the sequence was given and its sweep values;
            both intrinsics and a calibration file.
    """
    from trianflow_vo.cli.config_flags import build_config

    try:
        config = build_config(job.config_file, job.overrides, job.shortcuts(), job.no_plot)
        if config.input.intrinsics is not None and config.input.calib is not None:
            raise ConfigError("give either intrinsics or a calibration file, not both", None,
                              "input.intrinsics / input.calib")
    except ConfigError as e:
        where = job.origin + (f" [{', '.join(f'{k}={v}' for k, v in job.sweep)}]" if job.sweep else "")
        raise ConfigError(str(e), where or None) from None
    return config


def _plain(config) -> dict:
    """The configuration as ``run.json`` stores it (JSON round trip: paths as text, tuples as lists)."""
    return json.loads(json.dumps(config.to_dict(), default=str))


def _diff_keys(a: Mapping, b: Mapping) -> list[str]:
    keys = []
    for section in sorted(set(a) | set(b)):
        sa, sb = a.get(section) or {}, b.get(section) or {}
        if not isinstance(sa, Mapping) or not isinstance(sb, Mapping):
            if sa != sb:
                keys.append(section)
            continue
        keys += [f"{section}.{k}" for k in sorted(set(sa) | set(sb)) if sa.get(k) != sb.get(k)]
    return keys


def read_run_json(out_dir: Path) -> dict | None:
    """The folder's ``run.json``, or None when it is missing or unreadable."""
    try:
        doc = json.loads((Path(out_dir) / "run.json").read_text())
    except (OSError, ValueError):
        return None
    return doc if isinstance(doc, dict) else None


def earlier_state(out_dir: Path, seq: str, config) -> tuple[str, dict | None, list[str]]:
    """What the folder holds: ``(state, run.json, differing keys)``.

    ``state`` is ``none`` (no earlier run), ``completed`` (a completed run of this sequence and
    configuration), ``other-config`` (a completed run of another sequence or configuration: the
    differing keys are listed, ``sequence`` first for another path), ``unfinished`` (an earlier run
    with a ``run.json`` that did not complete: failed, interrupted, killed) or ``foreign`` (run
    files such as ``poses.txt`` without a ``run.json``: not known to be a run of ours).
    """
    from trianflow_vo.io.run_dir import earlier_run_files

    doc = read_run_json(out_dir)
    if doc is None:
        return ("foreign" if Path(out_dir).is_dir() and earlier_run_files(Path(out_dir)) else "none"), None, []
    if doc.get("status") != "completed":
        return "unfinished", doc, []
    diff = _diff_keys(doc.get("config") or {}, _plain(config))
    if str((doc.get("sequence") or {}).get("path")) != str(seq):
        diff.insert(0, "sequence")
    return ("completed" if not diff else "other-config"), doc, diff


def _inside(path: Path, folder: Path) -> bool:
    try:
        return path.resolve().is_relative_to(folder.resolve())
    except OSError:
        return False


def check_out_dir(out_dir: Path, seq: str | Path, config) -> None:
    """Refuse a run folder that is (or holds) the sequence, or holds its ground truth or calibration:
    replacing an earlier run there would delete the inputs (a KITTI folder has a ``poses.txt``).

    Raises:
        InputError: naming the folder.
    """
    from trianflow_vo.errors import InputError

    out_dir = Path(out_dir)
    if _inside(Path(seq), out_dir):
        raise InputError(f"the run folder would be (or hold) the sequence {seq}; choose another --out", out_dir)
    for what, p in (("ground truth", config.output.gt), ("calibration", config.input.calib)):
        if p is not None and _inside(Path(p), out_dir):
            raise InputError(f"the run folder holds the {what} {p}; choose another --out", out_dir)


def new_result(job: Job, out_dir: Path, status: str = "failed", reason: str | None = None) -> dict:
    """A result row of ``job`` with nothing measured yet (see :func:`run_job` for the keys)."""
    return {
        "name": job.name, "label": job.label, "sweep": {k: v for k, v in job.sweep}, "seq": job.seq,
        "out_dir": str(out_dir), "status": status, "reason": reason, "resumed": False,
        "frames": None, "frames_skipped": None, "elapsed_s": None, "fps": None, "wall_s": None,
        "peak_rss_mb": None, "branch_counts": None, "gt": None, "eval": None,
        "host": socket.gethostname(), "pid": os.getpid(),
    }


def fill_from_run(result: dict, doc: Mapping | None) -> None:
    """Copy the run's own figures (``run.json`` / the pipeline's summary) into the result.

    A run killed before it could close has a ``run.json`` from its last periodic update;
    its frame count is then the number of poses on disk (``poses.txt`` lines), which is
    never behind it."""
    if not doc:
        return
    result["frames"] = doc.get("frames_processed")
    if doc.get("status") != "completed" and result.get("out_dir"):
        try:
            with open(Path(result["out_dir"]) / "poses.txt", "rb") as f:
                on_disk = sum(1 for line in f if line.strip())
            result["frames"] = max(int(result["frames"] or 0), on_disk)
        except OSError:
            pass
    result["frames_skipped"] = doc.get("frames_skipped")
    result["elapsed_s"] = doc.get("elapsed_s")
    result["fps"] = doc.get("fps")
    result["peak_rss_mb"] = doc.get("peak_rss_mb")
    counts = doc.get("branch_counts")
    if isinstance(counts, Mapping):
        result["branch_counts"] = {b: int(counts.get(b, 0)) for b in BRANCHES}


def evaluate_run(out_dir: Path, gt: str | Path, lengths=None) -> dict:
    """ATE, RPE and KITTI t_err/r_err of the run in ``out_dir`` against ``gt`` (``trianflow-vo eval``'s
    protocol and defaults: 7-DoF alignment, kept frames).

    ``lengths`` None = automatic: the KITTI lengths 100..800 m, or, when the ground-truth path is
    shorter than 100 m, eight round lengths that fit in it (what ``eval`` suggests); the lengths
    used are in the result.

    Returns:
        ``{"ate_rmse", "rpe_trans", "rpe_rot", "t_err", "r_err", "lengths", "num_segments",
        "num_frames", "path_length", "align", "warnings"}`` (units as ``eval``: m, m, deg, %, deg/100 m).

    Raises:
        InputError: as :func:`trianflow_vo.eval.evaluate_files`.
    """
    from trianflow_vo.eval import DEFAULT_LENGTHS, evaluate_files
    from trianflow_vo.eval.evaluate import suggest_lengths

    result = evaluate_files(out_dir, gt, lengths=DEFAULT_LENGTHS if lengths is None else list(lengths))
    m = result.metrics
    if lengths is None and m["num_segments"] == 0:
        auto = suggest_lengths(m["path_length"])
        if auto:
            m = evaluate_files(out_dir, gt, lengths=auto).metrics
    keys = ("ate_rmse", "rpe_trans", "rpe_rot", "t_err", "r_err", "lengths", "num_segments", "num_frames",
            "path_length", "align")
    return {**{k: m.get(k) for k in keys}, "warnings": list(m.get("warnings", ()))}


def run_job(job: Job, out_root: str | Path, config=None, *, force: bool = False) -> dict:
    """Run one job into ``out_root / job.out`` and evaluate it when it has ground truth.

    Args:
        job: from :func:`trianflow_vo.batch.manifest.expand_jobs`.
        out_root: the batch folder ``DIR``.
        config: the job's configuration (a ``Config`` or its ``to_dict()``), or None to build it
            with :func:`job_config`.
        force: run again even when the folder holds a completed run (replacing it).

    Returns:
        The result dict: ``name``, ``label``, ``sweep``, ``seq``, ``out_dir``, ``status``
        (``completed`` | ``failed`` | ``interrupted``), ``reason`` (one line, or None),
        ``resumed``, ``frames``, ``frames_skipped``, ``elapsed_s``, ``fps``, ``wall_s`` (this
        function's time), ``peak_rss_mb`` (of the process), ``branch_counts``, ``gt``, ``eval``
        (see :func:`evaluate_run`, or None), ``host``, ``pid``. A run that completed but whose
        evaluation failed is ``failed`` with the reason ``eval: ...`` (its folder stays completed).
    """
    from trianflow_vo.pipeline import failure_reason

    t0 = time.perf_counter()
    out_dir = Path(out_root) / job.out
    result = new_result(job, out_dir)
    try:
        if config is None:
            config = job_config(job)
        elif isinstance(config, Mapping):
            from trianflow_vo.config import config_from_dict

            config = config_from_dict(config, source=f"batch job {job.label}")
        result["gt"] = None if config.output.gt is None else str(config.output.gt)
        check_out_dir(out_dir, job.seq, config)
        state, doc, diff = earlier_state(out_dir, job.seq, config)
        if state == "completed" and not force:
            result["resumed"] = True
            fill_from_run(result, doc)
        elif state == "other-config" and not force:
            shown = ", ".join(diff[:4]) + (", ..." if len(diff) > 4 else "")
            result["reason"] = (f"{out_dir} holds a completed run of another "
                                f"{'sequence' if diff[0] == 'sequence' else 'configuration'} ({shown}); "
                                "give --force to replace it")
            fill_from_run(result, doc)
            return _done(result, t0)
        elif state == "foreign" and not force:
            result["reason"] = (f"{out_dir} holds run files without a run.json (not a run of trianflow-vo?); "
                                "give --force to replace them")
            return _done(result, t0)
        else:
            from trianflow_vo.pipeline import run

            summary = run(Path(job.seq), out_dir, config, overwrite=force or state == "unfinished")
            fill_from_run(result, summary)
        result["status"] = "completed"
    except KeyboardInterrupt:
        raise
    except MemoryError as exc:  # numpy's allocation failure (the kernel's OOM killer is a crashed worker)
        detail = " ".join(str(exc).split())
        result["reason"] = (f"out of memory{': ' + detail if detail else ''}; use a smaller working size "
                            "(input.size), fewer threads or fewer --workers")
        fill_from_run(result, read_run_json(out_dir))
        return _done(result, t0)
    except Exception as exc:
        result["reason"] = failure_reason(exc)
        fill_from_run(result, read_run_json(out_dir))
        return _done(result, t0)
    if result["gt"] is not None:
        try:
            result["eval"] = evaluate_run(out_dir, result["gt"], job.lengths)
        except Exception as exc:
            result["status"] = "failed"
            result["reason"] = f"eval: {failure_reason(exc)}"
    return _done(result, t0)


def _done(result: dict, t0: float) -> dict:
    result["wall_s"] = time.perf_counter() - t0
    return result


def mark_stopped(out_dir: str | Path, reason: str, status: str = "failed") -> bool:
    """Best effort, for a run killed from outside: when its ``run.json`` still says ``running`` or
    ``interrupted``, set ``status`` and ``error: reason``. ``status`` is ``failed`` (a timeout, a
    crash) or ``interrupted`` (the batch was stopped, and the run was killed before it could close
    its folder itself; a folder it closed as ``interrupted`` is left as it is). Returns whether it
    was changed; never raises (the folder may not be visible from here)."""
    path = Path(out_dir) / "run.json"
    doc = read_run_json(Path(out_dir))
    if doc is None or doc.get("status") not in ("running", "interrupted"):
        return False
    if status == "interrupted" and doc.get("status") == "interrupted":
        return False
    doc.update({"status": status, "error": reason, "signal": None})
    try:
        from trianflow_vo.io.atomic import write_atomic

        write_atomic(path, json.dumps(doc, indent=2, default=str).encode())
    except OSError:
        return False
    return True
