"""Robustness table: every clip, stride and seed, plus synthetic stress sequences.

Every back-end or keyframe-policy change must not make this table worse. Each case is
one ``trianflow-vo run`` subprocess (``--quiet --no-plot --threads 2 --seed S --stride K``
plus whatever ``--args`` adds, e.g. ``--window 0``), evaluated against the sequence's
ground truth with the tool's eval library (Sim(3)-aligned ATE, as ``trianflow-vo eval``).

Cases:

- every clip under ``--data`` (default ``../shared/data``) that has a ground truth
  (``poses.txt`` or TUM ``groundtruth.txt``), x ``--strides`` x ``--seeds``;
- the synthetic sequences of ``tests/synthetic_sequences.py`` (highway, pure rotation,
  static, static with noise, stop-and-go, hand-held room, urban turn), rendered once
  into ``benchmarks/out/synthetic/`` (deterministic; re-rendered when the generator's
  source changes), stride 1 x ``--seeds``; for each, the branches the tool may take and
  whether every frame took one of them;
- if the folder exists, every sequence under ``--bench-data`` (default ``../bench_data`` beside the repository, or ``$TRIANFLOW_BENCH_DATA``:
  real clips not used for tuning; ``benchmarks/unseen_clips.py`` writes the two the tables use),
  x ``--strides`` x ``--seeds``.

Per run: frames, ground-truth path length, ATE RMSE and ATE as % of the path, branch
counts (``run.json``), frames/s and median ms per frame (``run.json``), peak RSS
(``run.json``, else the child's own rusage), status. For pure rotation and static
sequences, where ATE in metres means nothing, the rotation error in degrees (predicted
vs true rotation relative to the first frame) and the largest translation from the
first frame (in the run's units) instead.

Usage (from the repository root; ``nice`` on a shared machine)::

    nice -n 5 python benchmarks/bench_robustness.py --label baseline --args "--window 0"
    python benchmarks/bench_robustness.py --label w5 --args "--window 5" --only kitti06,synthetic
    python benchmarks/bench_robustness.py --compare baseline w5

Results go to ``benchmarks/out/robustness-LABEL.json`` (cases of earlier invocations with
the same label are kept unless redone) and one section per invocation is appended to
``--md`` (default ``benchmarks/ROBUSTNESS.md``). ``--compare A B`` prints (and appends)
the per-case ratios B/A of ATE and frames/s; it exits with status 1 when some case got
worse (ATE ratio above ``--tolerance`` and by more than ``--min-diff`` points, in the
median over seeds or in the worst seed, a frame
outside the allowed branches where there was none, or a run that no longer completes), or when
it is higher seed by seed (a paired sign-flip test over the seeds both ran, ``--alpha`` and
``--paired-ratio``; three seeds cannot show that, twelve can: ``--seeds 0,1,2,3,4,5,6,7,8,9,10,11``).
"""

from __future__ import annotations

import argparse
import concurrent.futures
import datetime
import hashlib
import json
import math
import os
import platform
import shlex
import statistics
import subprocess
import sys
import resource
import threading
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
OUT = REPO / "benchmarks" / "out"
THREADS = 2
RUN_TIMEOUT_S = 3600
# synthetic scenario -> frames rendered for the benchmark (scene seed 0, default sizes)
SYNTHETIC = {
    "highway": 100,
    "urban_turn": 60,
    "pure_rotation": 40,
    "static": 20,
    "static_noisy": 20,
    "stop_and_go": 45,
    "handheld_indoor": 150,
}
IMAGE_EXT = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")


# --------------------------------------------------------------------------- cases


def _gt_file(folder: Path) -> Path | None:
    for name in ("poses.txt", "groundtruth.txt"):
        if (folder / name).is_file():
            return folder / name
    return None


def _is_sequence(folder: Path) -> bool:
    if (folder / "rgb.txt").is_file():
        return True
    for sub in ("image_0", "image_2", "color", "rgb", "images", "."):
        d = folder / sub
        if d.is_dir() and any(p.suffix.lower() in IMAGE_EXT for p in d.iterdir()):
            return True
    return False


def discover(root: Path) -> list[Path]:
    """Sub-folders of ``root`` that are sequences with a ground truth, sorted."""
    if not root.is_dir():
        return []
    return sorted(d for d in root.iterdir() if d.is_dir() and _gt_file(d) is not None and _is_sequence(d))


def _synthetic_key(name: str, n_frames: int) -> str:
    src = (REPO / "tests" / "synthetic_sequences.py").read_bytes()
    return hashlib.sha256(src + f"|{name}|{n_frames}|seed0".encode()).hexdigest()[:16]


def ensure_synthetic(names: list[str], cache: Path, log) -> dict[str, Path]:
    """Render the synthetic sequences into ``cache/NAME`` unless an up-to-date copy is there.

    Rendering runs in a subprocess (``python tests/synthetic_sequences.py``): see
    :func:`run_case` on why this process must stay small.
    """
    out = {}
    for name in names:
        folder = cache / name
        key = _synthetic_key(name, SYNTHETIC[name])
        stamp = folder / "cache_key"
        if not (stamp.is_file() and stamp.read_text().strip() == key and (folder / "scenario.json").is_file()):
            t0 = time.perf_counter()
            if folder.exists():
                for p in sorted(folder.rglob("*"), reverse=True):
                    p.unlink() if p.is_file() else p.rmdir()
            cmd = [sys.executable, str(REPO / "tests" / "synthetic_sequences.py"), name, str(folder),
                   "--frames", str(SYNTHETIC[name]), "--seed", "0"]
            p = subprocess.run(cmd, capture_output=True, text=True, cwd=str(REPO))
            if p.returncode != 0:
                raise SystemExit(f"error: rendering synthetic/{name} failed: {p.stderr.strip()[-500:]}")
            stamp.write_text(key + "\n")
            log(f"rendered synthetic/{name}: {SYNTHETIC[name]} frames in {time.perf_counter() - t0:.1f} s")
        out[name] = folder
    return out


def build_cases(args, log) -> list[dict]:
    strides = args.strides
    cases = []
    for folder in discover(args.data):
        for s in strides:
            cases.append({"id": f"{folder.name}/s{s}", "group": "shared", "seq": str(folder), "stride": s,
                          "gt": str(_gt_file(folder)), "kind": "trajectory", "clip": folder.name})
    if not args.no_synthetic:
        for name in SYNTHETIC:
            cases.append({"id": f"synthetic/{name}", "group": "synthetic", "seq": None, "stride": 1, "gt": None,
                          "kind": None, "clip": name})
    bench = discover(args.bench_data)
    if args.bench_data.is_dir():
        log(f"{args.bench_data}: found {', '.join(p.name for p in bench) or 'no sequence with a ground truth'}")
    for folder in bench:
        for s in strides:
            cases.append({"id": f"bench/{folder.name}/s{s}", "group": "bench", "seq": str(folder), "stride": s,
                          "gt": str(_gt_file(folder)), "kind": "trajectory", "clip": folder.name})
    if args.only:
        subs = [x.strip() for x in args.only.split(",") if x.strip()]
        cases = [c for c in cases if any(x in c["id"] for x in subs)]
    syn = [c for c in cases if c["group"] == "synthetic"]
    if syn:
        folders = ensure_synthetic([c["clip"] for c in syn], args.out / "synthetic", log)
        for c in syn:
            folder = folders[c["clip"]]
            meta = json.loads((folder / "scenario.json").read_text())
            c.update(seq=str(folder), gt=str(folder / "poses.txt"), kind=meta["kind"],
                     allowed=meta["allowed_branches"], description=meta["description"])
    return cases


# --------------------------------------------------------------------------- one run


def _tool() -> list[str]:
    exe = Path(sys.executable).parent / "trianflow-vo"
    return [str(exe)] if exe.is_file() else [sys.executable, "-m", "trianflow_vo.cli.main"]


def _own_peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux: KiB


def run_case(case: dict, seed: int, extra: list[str], run_dir: Path, timeout: float) -> dict:
    """One ``trianflow-vo run`` in its own process, then its evaluation (in another one).

    On Linux a child's ``ru_maxrss`` starts from the RSS of the process that spawned it
    (the parent's high-water mark survives fork + exec). ``run.json``'s ``peak_rss_mb`` is
    read from ``VmHWM`` and is the run's own; this process still never renders, evaluates
    or imports numpy itself, and ``launcher_rss_mb`` records its size (the floor of
    ``rusage_peak_rss_mb``).
    """
    run_dir.mkdir(parents=True, exist_ok=True)
    cmd = _tool() + ["run", case["seq"], "--out", str(run_dir), "--overwrite", "--quiet", "--no-plot",
                     "--threads", str(THREADS), "--seed", str(seed), "--stride", str(case["stride"])] + extra
    env = dict(os.environ, OMP_NUM_THREADS=str(THREADS))
    log_path = run_dir.parent / (run_dir.name + ".log")
    t0 = time.perf_counter()
    with open(log_path, "w") as logf:
        p = subprocess.Popen(cmd, stdout=logf, stderr=subprocess.STDOUT, cwd=str(REPO), env=env)
        timer = threading.Timer(timeout, p.kill)
        timer.start()
        try:
            _, status, usage = os.wait4(p.pid, 0)  # the child's own peak RSS
        finally:
            timer.cancel()
        p.returncode = os.waitstatus_to_exitcode(status)
    res = {"seed": seed, "command": shlex.join(cmd), "exit": p.returncode, "wall_s": time.perf_counter() - t0,
           "rusage_peak_rss_mb": usage.ru_maxrss / 1024.0, "launcher_rss_mb": _own_peak_rss_mb()}
    summary = {}
    try:
        summary = json.loads((run_dir / "run.json").read_text())
    except (OSError, ValueError) as exc:
        res["error"] = f"no run.json ({exc.__class__.__name__})"
    tail = log_path.read_text(errors="replace").strip().splitlines()[-2:] if log_path.is_file() else []
    res.update({
        "status": summary.get("status", "failed" if p.returncode else "unknown"),
        "frames": summary.get("frames_processed"),
        "branch_counts": {k: v for k, v in (summary.get("branch_counts") or {}).items()},
        "fps": summary.get("fps"),
        "frame_ms_median": summary.get("frame_ms_median"),
        "peak_rss_mb": summary.get("peak_rss_mb") or res["rusage_peak_rss_mb"],
        "worker_rss_mb": (summary.get("backend") or {}).get("worker_peak_rss_mb"),
        "revisions": (summary.get("revisions") or {}).get("count"),
        "backend": _describe_backend(summary.get("backend")),
    })
    if p.returncode != 0:
        res["error"] = f"exit {p.returncode}: " + " | ".join(tail)
    if summary.get("error"):
        res["error"] = summary["error"]
    if (run_dir / "frames.tsv").is_file():
        res["frame_branches"] = _branches_per_frame(run_dir / "frames.tsv")
        if case.get("allowed") is not None:
            allowed = set(case["allowed"]) | {"init"}
            bad = [b for b in res["frame_branches"] if b not in allowed]
            res["disallowed"] = {b: bad.count(b) for b in sorted(set(bad))}
            res["all_allowed"] = not bad and res["status"] == "completed"
    if (run_dir / "poses.txt").is_file() and case.get("gt"):
        job = json.dumps({"run_dir": str(run_dir), "gt": case["gt"], "kind": case["kind"]})
        e = subprocess.run([sys.executable, str(Path(__file__).resolve()), "--eval-worker", job],
                           capture_output=True, text=True, cwd=str(REPO))
        lines = [ln for ln in e.stdout.splitlines() if ln.startswith("RESULT ")]
        if lines:
            res.update(json.loads(lines[-1][len("RESULT "):]))
        else:
            res["eval_error"] = (e.stderr.strip().splitlines() or [f"exit {e.returncode}"])[-1]
    return res


def _eval_worker(job: dict) -> dict:
    try:
        return evaluate_run(Path(job["run_dir"]), Path(job["gt"]), job["kind"])
    except Exception as exc:  # noqa: BLE001 - reported in the table
        return {"eval_error": f"{exc.__class__.__name__}: {exc}"}


def _describe_backend(b) -> str | None:
    """``name`` and ``window`` of run.json's back-end description (whatever keys it has)."""
    if not isinstance(b, dict):
        return None
    name = str(b.get("name", "?"))
    return name + (f" (window {b['window']})" if "window" in b else "")


def _branches_per_frame(tsv: Path) -> list[str]:
    lines = tsv.read_text().splitlines()
    if not lines:
        return []
    col = lines[0].split("\t").index("branch")
    return [ln.split("\t")[col] for ln in lines[1:] if ln.strip()]


def _rotation_deg(R) -> float:
    return math.degrees(math.acos(max(-1.0, min(1.0, (float(R[0, 0] + R[1, 1] + R[2, 2]) - 1.0) / 2.0))))


def evaluate_run(run_dir: Path, gt_path: Path, kind: str) -> dict:
    """ATE after Sim(3) alignment (the tool's eval), or rotation error / translation for
    sequences without a usable path (pure rotation, static)."""
    import numpy as np

    from trianflow_vo.eval import evaluate_files, load_ground_truth
    from trianflow_vo.io.trajectory import read_frame_indices, read_trajectory

    if kind == "trajectory":
        r = evaluate_files(run_dir, gt_path, align="7dof").metrics
        return {"ate_rmse": r["ate_rmse"], "path_length": r["path_length"],
                "ate_pct": 100.0 * r["ate_rmse"] / r["path_length"] if r["path_length"] else None,
                "rpe_rot": r["rpe_rot"], "num_eval_frames": r["num_frames"]}
    pred = read_trajectory(run_dir / "poses.txt").poses
    frames, _ = read_frame_indices(run_dir / "frames.txt")
    gt = load_ground_truth(gt_path)
    index = {int(f): i for i, f in enumerate(gt.frames)}
    keep = [k for k, f in enumerate(frames) if int(f) in index]
    P = pred[keep]
    G = gt.poses[[index[int(frames[k])] for k in keep]]
    P_rel = np.einsum("ij,njk->nik", np.linalg.inv(P[0]), P)
    G_rel = np.einsum("ij,njk->nik", np.linalg.inv(G[0]), G)
    rot = np.array([_rotation_deg(g[:3, :3].T @ p[:3, :3]) for p, g in zip(P_rel, G_rel)])
    return {"rot_err_max_deg": float(rot.max()), "rot_err_rmse_deg": float(np.sqrt(np.mean(rot ** 2))),
            "gt_rot_max_deg": float(max(_rotation_deg(g[:3, :3]) for g in G_rel)),
            "max_translation": float(np.linalg.norm(P_rel[:, :3, 3], axis=1).max()),
            "gt_path_length": float(np.sum(np.linalg.norm(np.diff(G[:, :3, 3], axis=0), axis=1))),
            "num_eval_frames": len(keep)}


# --------------------------------------------------------------------------- aggregation, report


def _median(xs):
    xs = [x for x in xs if x is not None]
    return statistics.median(xs) if xs else None


def _worker_rss(a: dict) -> str:
    w = a.get("worker_rss_mb")
    return f" +{w:.0f} w" if w else ""


def aggregate(case: dict, runs: list[dict]) -> dict:
    ok = [r for r in runs if r.get("status") == "completed"]
    first = runs[0] if runs else {}
    agg = {
        "n_runs": len(runs), "n_completed": len(ok),
        "frames": first.get("frames"),
        "branches_seed0": first.get("branch_counts"),
        "fps": _median([r.get("fps") for r in ok]),
        "frame_ms_median": _median([r.get("frame_ms_median") for r in ok]),
        "peak_rss_mb": max((r.get("peak_rss_mb") or 0) for r in runs) if runs else None,
        "worker_rss_mb": (max((r.get("worker_rss_mb") or 0) for r in runs) or None) if runs else None,
        "failed_frames_max": max(((r.get("branch_counts") or {}).get("failed", 0) for r in runs), default=None),
        "errors": sorted({r.get("error") or r.get("eval_error") for r in runs} - {None}),
        "backends": sorted({r.get("backend") for r in runs} - {None}),
        "launcher_rss_mb": max((r.get("launcher_rss_mb") or 0.0) for r in runs) if runs else None,
    }
    if case["kind"] == "trajectory":
        pct = [r.get("ate_pct") for r in ok if r.get("ate_pct") is not None]
        agg.update({"path_length": _median([r.get("path_length") for r in ok]),
                    "ate_rmse": _median([r.get("ate_rmse") for r in ok]),
                    "ate_pct": _median(pct), "ate_pct_min": min(pct) if pct else None,
                    "ate_pct_max": max(pct) if pct else None})
    else:
        rot = [r.get("rot_err_max_deg") for r in ok if r.get("rot_err_max_deg") is not None]
        agg.update({"rot_err_max_deg": _median(rot), "rot_err_max_deg_max": max(rot) if rot else None,
                    "max_translation": max((r.get("max_translation") or 0.0 for r in ok), default=None),
                    "gt_rot_max_deg": _median([r.get("gt_rot_max_deg") for r in ok])})
    if case.get("allowed") is not None:
        agg["allowed"] = case["allowed"]
        agg["all_allowed_runs"] = sum(1 for r in runs if r.get("all_allowed"))
        dis: dict[str, int] = {}
        for r in runs:
            for b, n in (r.get("disallowed") or {}).items():
                dis[b] = dis.get(b, 0) + n
        agg["disallowed_total"] = dis
    return agg


def _f(x, fmt="{:.2f}", none="n/a"):
    return none if x is None else fmt.format(x)


def _branches(bc: dict | None) -> str:
    if not bc:
        return "n/a"
    return ", ".join(f"{k} {v}" for k, v in bc.items() if k != "init" and v) or "none"


def _status(agg: dict) -> str:
    s = "ok" if agg["n_completed"] == agg["n_runs"] else f"{agg['n_completed']}/{agg['n_runs']} completed"
    if agg["errors"]:
        s += "; " + "; ".join(e[:120] for e in agg["errors"])
    return s


def markdown_section(meta: dict, cases: list[dict], results: dict) -> str:
    out = [f"## {meta['label']} ({meta['date']})", ""]
    out.append(f"- Code: {meta['git']}; extra args: `{meta['args'] or '(none)'}`; seeds {meta['seeds']}; "
               f"strides {meta['strides']}" + (f"; only `{meta['only']}`" if meta.get("only") else ""))
    out.append(f"- Load average (1/5/15 min) at start {meta['load_start']}, at end {meta['load_end']}; "
               f"{meta['cores']} cores; {meta['threads']} threads per run, {meta['jobs']} run(s) at a time; "
               f"total {meta['elapsed_min']:.1f} min")
    if meta.get("cpu"):
        out.append(f"- CPU: {meta['cpu']}")
    floor = max((a.get("launcher_rss_mb") or 0.0) for a in results.values()) if results else 0.0
    out.append(f"- Peak RSS is run.json's `peak_rss_mb` (VmHWM, the run's own; `+N w`: the bundle adjustment's "
               f"worker process, `backend.worker_peak_rss_mb`); the harness itself stays at {floor:.0f} MB")
    backends = sorted({b for a in results.values() for b in a.get("backends", [])})
    out.append(f"- Back-end the runs report (run.json `backend`): {', '.join(backends) or 'n/a'}")
    out.append(f"- Command: `{meta['command']}`")
    out.append("")
    real = [c for c in cases if c["group"] != "synthetic"]
    if real:
        out.append("| clip | stride | frames | path m | ATE % median [min-max] | ATE m | branches (seed 0) "
                   "| fps median | ms/frame | peak RSS MB | status |")
        out.append("|---|---|---|---|---|---|---|---|---|---|---|")
        for c in real:
            a = results[c["id"]]
            name = ("bench/" if c["group"] == "bench" else "") + c["clip"]
            out.append(f"| {name} | {c['stride']} | {_f(a['frames'], '{}')} | {_f(a.get('path_length'), '{:.1f}')} | "
                       f"{_f(a.get('ate_pct'))} [{_f(a.get('ate_pct_min'))}-{_f(a.get('ate_pct_max'))}] | "
                       f"{_f(a.get('ate_rmse'), '{:.3f}')} | {_branches(a['branches_seed0'])} | "
                       f"{_f(a['fps'], '{:.1f}')} | {_f(a['frame_ms_median'], '{:.0f}')} | "
                       f"{_f(a['peak_rss_mb'], '{:.0f}')}{_worker_rss(a)} | {_status(a)} |")
        out.append("")
    syn = [c for c in cases if c["group"] == "synthetic"]
    if syn:
        out.append("Synthetic sequences (`tests/synthetic_sequences.py`, scene seed 0, stride 1). *Allowed* = "
                   "runs in which every frame took an expected branch. Pure rotation and static: rotation error "
                   "(max over frames, median over seeds) and the largest translation from the first frame "
                   "(run units) instead of ATE.")
        out.append("")
        out.append("| scenario | frames | expected branches | branches (seed 0) | allowed | outside expected "
                   "(all seeds) | error | fps median | status |")
        out.append("|---|---|---|---|---|---|---|---|---|")
        for c in syn:
            a = results[c["id"]]
            if c["kind"] == "trajectory":
                err = (f"ATE {_f(a.get('ate_pct'))} % [{_f(a.get('ate_pct_min'))}-{_f(a.get('ate_pct_max'))}] "
                       f"({_f(a.get('ate_rmse'), '{:.3f}')} m of {_f(a.get('path_length'), '{:.1f}')} m)")
            else:
                err = (f"rot {_f(a.get('rot_err_max_deg'), '{:.3f}')} deg (true rotation up to "
                       f"{_f(a.get('gt_rot_max_deg'), '{:.1f}')} deg), max transl "
                       f"{_f(a.get('max_translation'), '{:.3g}')}")
            out.append(f"| {c['clip']} | {_f(a['frames'], '{}')} | {', '.join(c['allowed'])} | "
                       f"{_branches(a['branches_seed0'])} | {a['all_allowed_runs']}/{a['n_runs']} | "
                       f"{_branches(a['disallowed_total']) if a['disallowed_total'] else '-'} | {err} | "
                       f"{_f(a['fps'], '{:.1f}')} | {_status(a)} |")
        out.append("")
    return "\n".join(out)


def _append_md(path: Path, text: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    if not path.exists():
        path.write_text("# Robustness table (`benchmarks/bench_robustness.py`)\n\n"
                        "One section per invocation, newest last. Speeds are from a shared 2-core machine: "
                        "compare ratios within one invocation or with `--compare`, not absolute frames/s.\n\n")
    with open(path, "a") as f:
        f.write(text.rstrip() + "\n\n")


def _git_state() -> str:
    try:
        head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                              cwd=str(REPO)).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "vo", "cli", "models", "configs"],
                               capture_output=True, text=True, cwd=str(REPO)).stdout.strip()
    except OSError:
        return "unknown"
    return (head or "unknown") + (" + uncommitted changes in vo/cli/models/configs" if dirty else "")


def _load() -> str:
    return " ".join(f"{x:.1f}" for x in os.getloadavg())


def _machine() -> str:
    return " ".join(x for x in (platform.machine(), platform.processor()) if x)


CPU_EXTENSIONS = ("avx512f", "avx2", "fma")


def cpu_description(cpuinfo: str | None = None) -> str:
    """The CPU model and the vector extensions it has of ``CPU_EXTENSIONS``, e.g.
    ``"AMD EPYC (avx2, fma; no avx512f)"``: numpy and OpenBLAS pick their kernels by them, and
    the last bits of a sum differ between kernels. ``cpuinfo``: the text of ``/proc/cpuinfo``
    (read when None; where there is none, ``platform`` names the machine)."""
    if cpuinfo is None:
        try:
            cpuinfo = Path("/proc/cpuinfo").read_text(errors="replace")
        except OSError:
            return _machine() or "unknown"
    model, flags = "", None
    for line in cpuinfo.splitlines():
        key, _, value = line.partition(":")
        key = key.strip()
        if key == "model name" and not model:
            model = value.strip()
        elif key == "flags" and flags is None:
            flags = set(value.split())
    model = model or platform.machine() or "unknown"
    if flags is None:
        return model
    has = [f for f in CPU_EXTENSIONS if f in flags]
    lacks = [f for f in CPU_EXTENSIONS if f not in flags]
    return f"{model} ({', '.join(has) or 'none of ' + ', '.join(CPU_EXTENSIONS)}" + (
        f"; no {', '.join(lacks)})" if has and lacks else ")")


# --------------------------------------------------------------------------- compare


def _results_path(label_or_file: str) -> Path:
    p = Path(label_or_file)
    if p.suffix == ".json" and p.is_file():
        return p
    return OUT / f"robustness-{label_or_file}.json"


def paired_sign_flip_p(log_ratios: list[float], draws: int = 20000) -> float | None:
    """Two-sided p-value that paired log error ratios ``log(B / A)`` (one per seed) centre on
    zero: the share of sign flips whose mean is at least as far from zero as the observed one
    (exact over all 2^n flips for n <= 16, else ``draws`` random flips, seeded). None for n < 2.
    With n seeds the smallest possible p is 2 / 2^n: three seeds can never show a change
    (0.25), twelve can (0.0005)."""
    x = [float(v) for v in log_ratios]
    n = len(x)
    if n < 2:
        return None
    obs = abs(sum(x)) - 1e-12 * (1.0 + sum(abs(v) for v in x))  # ties count as extreme
    if n <= 16:
        hits = sum(1 for mask in range(1 << n)
                   if abs(sum(v if (mask >> i) & 1 else -v for i, v in enumerate(x))) >= obs)
        return hits / float(1 << n)
    import random
    rng = random.Random(0)
    hits = sum(1 for _ in range(draws) if abs(sum(v if rng.random() < 0.5 else -v for v in x)) >= obs)
    return (hits + 1) / (draws + 1)


def _per_seed_error(case: dict) -> dict[int, float]:
    """Seed -> the case's error (ATE % or rotation degrees) of each completed run with one."""
    out = {}
    for r in case.get("runs") or []:
        e = r.get("ate_pct", r.get("rot_err_max_deg"))
        if r.get("status") == "completed" and e is not None and e > 0 and r.get("seed") is not None:
            out[int(r["seed"])] = float(e)
    return out


def paired(case_a: dict, case_b: dict) -> tuple[int, int, float | None, float | None]:
    """The seeds both tables ran: ``(n, B lower in how many, geometric-mean ratio B/A, p)``
    (:func:`paired_sign_flip_p`)."""
    ea, eb = _per_seed_error(case_a), _per_seed_error(case_b)
    seeds = sorted(set(ea) & set(eb))
    if not seeds:
        return 0, 0, None, None
    lr = [math.log(eb[s] / ea[s]) for s in seeds]
    return len(seeds), sum(1 for v in lr if v < 0), math.exp(sum(lr) / len(lr)), paired_sign_flip_p(lr)


def _key_error(a: dict) -> tuple[str, float | None]:
    if "ate_pct" in a:
        return "ATE %", a.get("ate_pct")
    return "rot deg", a.get("rot_err_max_deg")


def compare(label_a: str, label_b: str, tolerance: float, min_diff: float, alpha: float = 0.05,
            paired_ratio: float = 1.05) -> tuple[str, int]:
    pa, pb = _results_path(label_a), _results_path(label_b)
    A = json.loads(pa.read_text())
    B = json.loads(pb.read_text())
    ids = [i for i in A["cases"] if i in B["cases"]]
    only_a = [i for i in A["cases"] if i not in B["cases"]]
    only_b = [i for i in B["cases"] if i not in A["cases"]]
    lines = [f"## compare {label_a} -> {label_b} ({datetime.datetime.now():%Y-%m-%d %H:%M})", "",
             f"- A: `{pa.name}` (args `{A['meta'].get('args', '')}`); B: `{pb.name}` (args "
             f"`{B['meta'].get('args', '')}`); worse = error ratio > {tolerance:g} and by more than "
             f"{min_diff:g} (points of ATE % or degrees), the same for the worst seed, a frame outside "
             "the expected branches where A had none, or fewer completed runs; also when, over the seeds both "
             f"ran, B's error is higher by a geometric-mean ratio above {paired_ratio:g} with a paired sign-flip "
             f"p below {alpha:g} (*paired*: seeds where B is lower / seeds, ratio, p; three seeds cannot reach "
             "p < 0.25, twelve can).", ""]
    ca, cb = A["meta"].get("cpu"), B["meta"].get("cpu")
    if (ca or cb) and ca != cb:
        lines[-1:-1] = [f"- **A and B were measured on different CPUs** (A: {ca or 'not recorded'}; B: "
                        f"{cb or 'not recorded'}). The same code gives other numbers on another CPU (the "
                        "floating-point kernels differ and the chaotic clips amplify it): what differs here "
                        "is not the code's doing alone."]
    lines.append("| case | metric | A | B | B/A | worst seed A | worst seed B | fps A | fps B | fps B/A | allowed A | "
                 "allowed B | paired | verdict |")
    lines.append("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    worse = 0
    for i in ids:
        a, b = A["cases"][i]["summary"], B["cases"][i]["summary"]
        metric, ea = _key_error(a)
        _, eb = _key_error(b)
        ratio = None if ea in (None, 0) or eb is None else eb / ea
        fr = None if not a.get("fps") or b.get("fps") is None else b["fps"] / a["fps"]
        verdict = []
        if ea is not None and eb is not None and eb > ea * tolerance and eb - ea > min_diff:
            verdict.append("worse error")
        if ea is not None and eb is None:
            verdict.append("no error measured")
        # one seed in three can diverge while the median stays put
        wa, wb = (s.get("ate_pct_max", s.get("rot_err_max_deg_max")) for s in (a, b))
        if wa is not None and wb is not None and wb > wa * tolerance and wb - wa > min_diff:
            verdict.append("worse worst seed")
        aa, ab = a.get("all_allowed_runs"), b.get("all_allowed_runs")
        if aa is not None and ab is not None and ab < aa:
            verdict.append("branches")
        if b.get("n_completed", 0) < a.get("n_completed", 0):
            verdict.append("runs failed")
        n, lower, gm, p = paired(A["cases"][i], B["cases"][i])
        if p is not None and p < alpha and gm > paired_ratio:
            verdict.append("worse paired")
        pair = "n/a" if gm is None else f"{lower}/{n}, {gm:.2f}" + ("" if p is None else f", p {p:.3g}")
        if verdict:
            worse += 1
        allowed = (lambda s: "n/a" if s.get("all_allowed_runs") is None
                   else f"{s['all_allowed_runs']}/{s['n_runs']}")
        lines.append(f"| {i} | {metric} | {_f(ea, '{:.3f}')} | {_f(eb, '{:.3f}')} | {_f(ratio)} | "
                     f"{_f(wa, '{:.3f}')} | {_f(wb, '{:.3f}')} | {_f(a.get('fps'), '{:.1f}')} | "
                     f"{_f(b.get('fps'), '{:.1f}')} | {_f(fr)} | {allowed(a)} | "
                     f"{allowed(b)} | {pair} | {'**' + ', '.join(verdict) + '**' if verdict else 'ok'} |")
    lines.append("")
    if only_a or only_b:
        lines.append(f"Not compared (in one file only): A {', '.join(only_a) or '-'}; B {', '.join(only_b) or '-'}.")
        lines.append("")
    lines.append(f"{worse} of {len(ids)} cases worse.")
    return "\n".join(lines), worse


# --------------------------------------------------------------------------- main


def _ints(text: str, what: str) -> list[int]:
    try:
        vals = [int(x) for x in text.split(",") if x.strip()]
    except ValueError:
        raise SystemExit(f"error: --{what} must be comma-separated integers, got {text!r}") from None
    if not vals:
        raise SystemExit(f"error: --{what} is empty")
    return vals


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--label", default=None, help="name of this configuration (default: run-DATE)")
    ap.add_argument("--args", default="", help='extra arguments for every run, e.g. "--window 0 --set a.b=1"')
    ap.add_argument("--only", default=None, help="comma-separated substrings of case ids "
                    "(e.g. kitti06, synthetic, highway, bench/, /s1)")
    ap.add_argument("--seeds", default="0,1,2", help="comma-separated --seed values (default 0,1,2)")
    ap.add_argument("--strides", default="1,2,3", help="strides of the real clips (synthetic: 1)")
    ap.add_argument("--jobs", type=int, default=1, help="runs at a time (default 1: clean frames/s)")
    ap.add_argument("--data", type=Path, default=Path(os.environ.get("TRIANFLOW_SHARED_DATA",
                                                                     REPO.parent / "shared" / "data")))
    ap.add_argument("--bench-data", type=Path,
                    default=Path(os.environ.get("TRIANFLOW_BENCH_DATA", REPO.parent / "bench_data")))
    ap.add_argument("--no-synthetic", action="store_true")
    ap.add_argument("--out", type=Path, default=OUT, help="run folders and the synthetic cache go here")
    ap.add_argument("--json", type=Path, default=None, help="results (default OUT/robustness-LABEL.json)")
    ap.add_argument("--md", type=Path, default=REPO / "benchmarks" / "ROBUSTNESS.md")
    ap.add_argument("--timeout", type=float, default=RUN_TIMEOUT_S, help="seconds per run")
    ap.add_argument("--compare", nargs=2, metavar=("LABEL_A", "LABEL_B"), default=None,
                    help="compare two results (labels or JSON files) instead of running")
    ap.add_argument("--tolerance", type=float, default=1.10, help="--compare: worse when B/A error exceeds this")
    ap.add_argument("--min-diff", type=float, default=0.02,
                    help="--compare: ...and B exceeds A by more than this (ATE %% points or degrees)")
    ap.add_argument("--alpha", type=float, default=0.05,
                    help="--compare: worse also when, paired by seed, B is higher with a sign-flip p below this...")
    ap.add_argument("--paired-ratio", type=float, default=1.05,
                    help="--compare: ...and a geometric-mean error ratio B/A above this")
    ap.add_argument("--no-md", action="store_true", help="do not append to --md")
    ap.add_argument("--eval-worker", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)

    if args.eval_worker is not None:
        print("RESULT " + json.dumps(_eval_worker(json.loads(args.eval_worker)), default=float), flush=True)
        return 0

    if args.compare:
        try:
            text, worse = compare(*args.compare, args.tolerance, args.min_diff, args.alpha, args.paired_ratio)
        except (OSError, ValueError, KeyError) as exc:
            print(f"error: cannot compare: {exc}", file=sys.stderr)
            return 2
        print(text)
        if not args.no_md:
            _append_md(args.md, text)
        return 1 if worse else 0

    args.seeds = _ints(args.seeds, "seeds")
    args.strides = _ints(args.strides, "strides")
    label = args.label or f"run-{datetime.datetime.now():%Y%m%d-%H%M}"
    if not args.data.is_dir():
        print(f"note: shared data not found at {args.data}: no shared clips", file=sys.stderr)
    extra = shlex.split(args.args)

    def log(msg):
        print(msg, flush=True)

    t_start = time.perf_counter()
    meta = {"label": label, "date": f"{datetime.datetime.now():%Y-%m-%d %H:%M}", "git": _git_state(),
            "args": args.args, "seeds": args.seeds, "strides": args.strides, "only": args.only,
            "jobs": args.jobs, "threads": THREADS, "cores": os.cpu_count(), "load_start": _load(),
            "machine": _machine(),
            "cpu": cpu_description(),
            "command": "python benchmarks/bench_robustness.py "
                       + shlex.join(sys.argv[1:] if argv is None else list(argv))}
    cases = build_cases(args, log)
    if not cases:
        print("error: no case selected", file=sys.stderr)
        return 2
    log(f"{len(cases)} cases x {len(args.seeds)} seeds, label {label!r}, extra args {extra}")
    run_root = args.out / "robustness" / label
    jobs = [(c, s) for c in cases for s in args.seeds]
    raw: dict[str, dict[int, dict]] = {c["id"]: {} for c in cases}

    def one(job):
        c, s = job
        rd = run_root / (c["id"].replace("/", "--") + f"-seed{s}")
        r = run_case(c, s, extra, rd, args.timeout)
        if c["kind"] == "trajectory":
            msg = f"ATE {_f(r.get('ate_pct'))} % ({_f(r.get('ate_rmse'), '{:.3f}')} m)"
        else:
            msg = (f"rot err {_f(r.get('rot_err_max_deg'), '{:.3f}')} deg, "
                   f"transl {_f(r.get('max_translation'), '{:.3g}')}")
        extra_msg = ""
        if "all_allowed" in r:
            extra_msg = " allowed" if r["all_allowed"] else f" OUTSIDE {r.get('disallowed')}"
        log(f"{c['id']:40s} seed {s}: {r['status']}, {msg}, {_branches(r.get('branch_counts'))},"
            f" {_f(r.get('fps'), '{:.1f}')} fps{extra_msg}" + (f" [{r['error']}]" if r.get("error") else ""))
        return c, s, r

    if args.jobs > 1:
        with concurrent.futures.ThreadPoolExecutor(args.jobs) as ex:
            for c, s, r in ex.map(one, jobs):
                raw[c["id"]][s] = r
    else:
        for job in jobs:
            c, s, r = one(job)
            raw[c["id"]][s] = r
    results = {c["id"]: aggregate(c, [raw[c["id"]][s] for s in args.seeds]) for c in cases}
    meta["load_end"] = _load()
    meta["elapsed_min"] = (time.perf_counter() - t_start) / 60.0

    json_path = args.json or (OUT / f"robustness-{label}.json")
    data = {"label": label, "meta": meta, "cases": {}}
    if json_path.is_file():  # keep cases of earlier invocations under this label that were not redone
        try:
            old = json.loads(json_path.read_text())
            data["cases"] = old.get("cases", {})
        except ValueError:
            pass
    for c in cases:
        data["cases"][c["id"]] = {"case": c, "meta": meta, "summary": results[c["id"]],
                                  "runs": [raw[c["id"]][s] for s in args.seeds]}
    json_path.parent.mkdir(parents=True, exist_ok=True)
    json_path.write_text(json.dumps(data, indent=2, default=float))
    md = markdown_section(meta, cases, results)
    print()
    print(md)
    if not args.no_md:
        _append_md(args.md, md)
    print(f"\nwrote {json_path}" + ("" if args.no_md else f" and appended to {args.md}"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
