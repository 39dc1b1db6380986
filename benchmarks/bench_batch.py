"""Cost of ``trianflow-vo batch``: overhead of a Ray task against a direct run, and 1 vs 2 workers.

(a) Overhead per task, one clip, repeated and alternated:
    - ``run (CLI)``: ``trianflow-vo run`` as a subprocess (interpreter start and imports included);
    - ``Ray task``: the same job as one task of :func:`trianflow_vo.batch.runner.run_batch` on an
      already running local Ray (``task_s``: submission to result, fresh worker included);
    - inside each: the job's own time (``wall_s`` of :func:`trianflow_vo.batch.jobs.run_job`,
      the same pipeline), so ``task_s - wall_s`` is what Ray adds.
    Also the start and shutdown of a local Ray (once per batch).
(b) Scaling: the same set of short sequences (default: 4 clips of ~50 frames) as one batch
    with 1 worker x 1 thread, 2 workers x 1 thread, and 1 worker x 2 threads; batch wall time
    (Ray already running), repeated and alternated; medians.

The load average and the CPU share a busy loop gets (``_cpu_share``: below 1.0 when the host
gives the cores to others) are recorded before, between and after: both change the figures.

    python benchmarks/bench_batch.py --repeats 3 --json /tmp/bench_batch.json
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
DATA = Path(os.environ.get("TRIANFLOW_SHARED_DATA", REPO.parent / "shared" / "data"))


def _loadavg() -> list[float]:
    try:
        return [round(x, 2) for x in os.getloadavg()]
    except OSError:
        return []


def _cpu_share(seconds: float = 1.0) -> float:
    """CPU time a busy single-threaded loop gets per wall second (1.0 = a whole core; less when the
    host gives the machine's cores to others: that time is not in the load average)."""
    t0, c0 = time.perf_counter(), time.process_time()
    x = 0
    while time.perf_counter() - t0 < seconds:
        x += 1
    return round((time.process_time() - c0) / (time.perf_counter() - t0), 2)


def _jobs(specs, overrides):
    from trianflow_vo.batch.manifest import expand_jobs, sequence_from_fields

    seqs = [sequence_from_fields(s, Path.cwd(), f"bench {i}") for i, s in enumerate(specs, 1)]
    return expand_jobs(seqs, overrides=overrides)


def overhead(seq: Path, repeats: int, size: str | None, threads: int) -> dict:
    import ray

    from trianflow_vo.batch.runner import run_batch

    sets = [f"runtime.threads={threads}", "output.plot=false"] + ([f"input.size=[{size.replace('x', ',')}]"]
                                                                  if size else [])
    cli, task, inside_task, inside_cli = [], [], [], []
    t = time.perf_counter()
    ray.init(address="local", num_cpus=2, include_dashboard=False, log_to_driver=False, logging_level=logging.ERROR)
    t_init = time.perf_counter() - t
    try:
        for _ in range(repeats):
            with tempfile.TemporaryDirectory() as tmp:
                # direct: the `run` command in its own process
                args = [sys.executable, "-m", "trianflow_vo.cli", "run", str(seq), "--out", f"{tmp}/cli", "-q"]
                for s in sets:
                    args += ["--set", s]
                t = time.perf_counter()
                subprocess.run(args, check=True, capture_output=True)
                cli.append(time.perf_counter() - t)
                inside_cli.append(json.loads(Path(f"{tmp}/cli/run.json").read_text())["wall_s"])
                # the same as one Ray task
                (row,) = run_batch(_jobs([{"path": str(seq), "name": "task"}], sets), f"{tmp}/b", workers=1)
                assert row["status"] == "completed", row
                task.append(row["task_s"])
                inside_task.append(row["wall_s"])
    finally:
        t = time.perf_counter()
        ray.shutdown()
        t_down = time.perf_counter() - t
    med = statistics.median
    return {"clip": seq.name, "repeats": repeats, "size": size or "auto", "threads": threads,
            "ray_init_s": t_init, "ray_shutdown_s": t_down,
            "run_cli_s": med(cli), "run_cli_pipeline_s": med(inside_cli),
            "ray_task_s": med(task), "ray_task_job_s": med(inside_task),
            "ray_overhead_s": med([a - b for a, b in zip(task, inside_task)]),
            "cli_overhead_s": med([a - b for a, b in zip(cli, inside_cli)]),
            "raw": {"run_cli_s": cli, "ray_task_s": task, "ray_task_job_s": inside_task}}


def scaling(specs, repeats: int, size: str | None) -> dict:
    import ray

    from trianflow_vo.batch.runner import run_batch

    base = ["output.plot=false"] + ([f"input.size=[{size.replace('x', ',')}]"] if size else [])
    variants = {"1 worker x 1 thread": (1, 1), "2 workers x 1 thread": (2, 1), "1 worker x 2 threads": (1, 2)}
    walls: dict[str, list[float]] = {k: [] for k in variants}
    shares: dict[str, list[float]] = {k: [] for k in variants}
    frames: dict[str, int] = {}
    ray.init(address="local", num_cpus=2, include_dashboard=False, log_to_driver=False, logging_level=logging.ERROR)
    try:
        for rep in range(repeats):
            order = list(variants) if rep % 2 == 0 else list(reversed(variants))
            for name in order:
                workers, threads = variants[name]
                jobs = _jobs(specs, [*base, f"runtime.threads={threads}"])
                shares[name].append(_cpu_share(0.5))
                with tempfile.TemporaryDirectory() as tmp:
                    t = time.perf_counter()
                    rows = run_batch(jobs, tmp, workers=workers)
                    walls[name].append(time.perf_counter() - t)
                assert all(r["status"] == "completed" for r in rows), [r["reason"] for r in rows]
                frames[name] = sum(r["frames"] for r in rows)
    finally:
        ray.shutdown()
    med = {k: statistics.median(v) for k, v in walls.items()}
    one = med["1 worker x 1 thread"]
    return {"sequences": [s.get("name") or Path(s["path"]).name for s in specs], "repeats": repeats,
            "size": size or "auto",
            "variants": {k: {"wall_s": med[k], "frames": frames[k], "frames_per_s": frames[k] / med[k],
                             "speed_up": one / med[k], "raw": walls[k], "cpu_share": shares[k]}
                         for k in variants}}


def markdown(over: dict, scale: dict, load: dict) -> str:
    o = over
    lines = [f"Machine: {platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}; "
             f"load average before {load['before']}, between {load['between']}, after {load['after']}; "
             f"CPU share of a busy loop before / between / after: {load['cpu_share']}.", "",
             f"### Overhead per task ({o['clip']}, size {o['size']}, {o['threads']} threads, median of "
             f"{o['repeats']})", "",
             "| | time (s) |", "|---|---:|",
             f"| `trianflow-vo run` (subprocess) | {o['run_cli_s']:.2f} |",
             f"| of which the run itself (run.json wall_s) | {o['run_cli_pipeline_s']:.2f} |",
             f"| Ray task (submission to result) | {o['ray_task_s']:.2f} |",
             f"| of which the job (run_job wall_s) | {o['ray_task_job_s']:.2f} |",
             f"| Ray overhead per task (task - job) | {o['ray_overhead_s']:.2f} |",
             f"| process start + imports of the CLI (run - run itself) | {o['cli_overhead_s']:.2f} |",
             f"| local Ray start / shutdown (once per batch) | {o['ray_init_s']:.2f} / {o['ray_shutdown_s']:.2f} |",
             "", f"### Scaling ({', '.join(scale['sequences'])}; size {scale['size']}; median of {scale['repeats']})",
             "", "| variant | batch wall (s) | frames/s | speed-up vs 1x1 | walls (s) | CPU share before each |",
             "|---|---:|---:|---:|---|---|"]
    for k, v in scale["variants"].items():
        raw = " ".join(f"{x:.1f}" for x in v["raw"])
        lines.append(f"| {k} | {v['wall_s']:.1f} | {v['frames_per_s']:.1f} | {v['speed_up']:.2f} | {raw} | "
                     f"{' '.join(f'{x:.2f}' for x in v['cpu_share'])} |")
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--clip", type=Path, default=DATA / "kitti06-f0000-0050")
    ap.add_argument("--size", default=None, help="HxW working size (default: automatic, 256x832 for KITTI)")
    ap.add_argument("--threads", type=int, default=2, help="threads of the overhead runs")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
    k00 = DATA / "kitti00-f0000-0150"
    specs = [{"path": str(DATA / "kitti06-f0000-0050"), "name": "k06"},
             {"path": str(k00), "name": "k00a", "end": 50},
             {"path": str(k00), "name": "k00b", "start": 50, "end": 100},
             {"path": str(k00), "name": "k00c", "start": 100}]
    load = {"before": _loadavg(), "cpu_share": [_cpu_share()]}
    over = overhead(args.clip, args.repeats, args.size, args.threads)
    load["between"] = _loadavg()
    load["cpu_share"].append(_cpu_share())
    scale = scaling(specs, args.repeats, args.size)
    load["after"] = _loadavg()
    load["cpu_share"].append(_cpu_share())
    doc = {"overhead": over, "scaling": scale, "loadavg": load}
    if args.json:
        args.json.write_text(json.dumps(doc, indent=2))
    print(markdown(over, scale, load))


if __name__ == "__main__":
    main()
