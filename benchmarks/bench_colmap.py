"""Benchmark: COLMAP (offline structure from motion, through pycolmap) as a reference row.

Runs COLMAP's incremental mapper on the same clips as ``bench_vo.py`` and
evaluates its camera poses with the tool's own evaluation
(:func:`trianflow_vo.eval.evaluate.evaluate`: Sim(3)-aligned ATE RMSE, and ATE as a
percentage of the ground-truth path length of the evaluated frames).

**Benchmark-only dependency**: ``pip install pycolmap`` (measured with 4.2.1). It is
not a dependency of the project and is not listed in ``pyproject.toml``.

Per clip and stride (each case in its own process, COLMAP's log in
``benchmarks/out/colmap/<case>.log``, the evaluated trajectory in
``benchmarks/out/colmap/<case>/poses.txt`` + ``frames.txt``, readable by
``trianflow-vo eval --pred``):

1. The selected frames are linked into a temporary image folder, named by their
   source index (``000042.png``), so that COLMAP's name order is the frame order.
   Frames and intrinsics are selected by the tool's own reader
   (:func:`trianflow_vo.io.sequence.open_sequence`): the ``calib.txt`` line that
   the tool itself uses (``P0`` for ``image_0/``, ``P2`` for ``image_2/``, ``P0``
   for a 7-Scenes-like ``color/`` folder).
2. Feature extraction: SIFT (COLMAP defaults, CPU), one shared ``PINHOLE`` camera
   with the known ``fx, fy, cx, cy``.
3. Sequential matching, overlap 10 (COLMAP's default quadratic overlap on unless
   ``--no-quadratic-overlap``), SIFT brute force with geometric verification.
4. Incremental mapping with ``mapper.init_max_forward_motion = 1.0`` (the default
   0.95 finds no initial pair on forward-moving driving clips) and the intrinsics
   held fixed: no focal length, principal point or extra parameter refinement in
   bundle adjustment or in absolute-pose registration. The camera of the chosen
   model is checked against the input afterwards. ``random_seed`` is fixed.
5. The largest model (most registered images) is taken when several come out;
   the others are reported. Its poses are inverted to camera-to-world, sorted by
   frame, and evaluated against ``poses.txt``. Frames that COLMAP did not
   register (in the largest model) are listed.

Wall time is measured per stage (link, extract, match, map, read poses);
frames/s is the number of selected frames divided by the sum of those stages.

Usage (from the repository root)::

    nice -n 10 python benchmarks/bench_colmap.py [--clips DIR,DIR] [--strides 1,2,3] [--threads 2]
        [--json benchmarks/out/colmap.json] [--md benchmarks/ROBUSTNESS.md] [--no-md]

Default clips: the three shared clips in ``../shared/data`` (KITTI 00 frames
0-150, KITTI 06 frames 0-50, 7-Scenes kitchen frames 0-499), plus every sequence
folder under ``../bench_data`` (beside the repository; or ``$TRIANFLOW_BENCH_DATA``) when that folder exists (``--bench-data``).
Cases run stride by stride (all clips at the first stride first). The JSON is
rewritten after every case; the markdown section is appended to ``--md`` (or
replaces this script's own earlier section there) at the end. ``--md-from-json``
only rewrites the section from an existing JSON.
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
DEFAULT_DATA = ROOT.parent / "shared" / "data"
DEFAULT_CLIPS = ("kitti00-f0000-0150", "kitti06-f0000-0050", "7scenes-kitchen-f0000-0499")
DEFAULT_BENCH_DATA = Path(os.environ.get("TRIANFLOW_BENCH_DATA", Path(__file__).resolve().parents[2] / "bench_data"))
SECTION_PREFIX = "## COLMAP reference"
SEED = 0


# ---------------------------------------------------------------------------
# worker: one clip at one stride, in its own process


def _ranges(idx: list[int], stride: int) -> str:
    """``[3, 4, 5, 9]`` -> ``"3-5, 9"`` (runs of consecutive selected frames)."""
    if not idx:
        return ""
    out, a, b = [], idx[0], idx[0]
    for i in idx[1:]:
        if i == b + stride:
            b = i
        else:
            out.append(f"{a}" if a == b else f"{a}-{b}")
            a = b = i
    out.append(f"{a}" if a == b else f"{a}-{b}")
    return ", ".join(out)


def _cam_from_world(image):
    cfw = image.cam_from_world
    return cfw() if callable(cfw) else cfw


def _worker(job: dict) -> dict:
    import numpy as np
    import pycolmap

    from trianflow_vo.eval.evaluate import evaluate
    from trianflow_vo.eval.loader import load_ground_truth
    from trianflow_vo.io.sequence import open_sequence

    threads, stride = int(job["threads"]), int(job["stride"])
    work = Path(job["work_dir"])
    times: dict[str, float] = {}
    res: dict = {"settings": {}}

    t0 = time.perf_counter()
    seq = open_sequence(job["clip"], stride=stride)
    if seq.files is None:
        raise RuntimeError("a video input is not supported here (image folders only)")
    K = seq.K
    fx, fy, cx, cy = float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])
    img_dir = work / "images"
    img_dir.mkdir(parents=True)
    names, frame_of = [], {}
    for i in seq.indices:
        src = seq.files[i]
        name = f"{i:06d}{src.suffix.lower()}"
        os.symlink(src.resolve(), img_dir / name)
        names.append(name)
        frame_of[name] = i
    db = work / "database.db"
    times["link"] = time.perf_counter() - t0
    res.update({"frames": len(names), "image_size": list(seq.image_size), "K_source": seq.K_source,
                "intrinsics": [fx, fy, cx, cy]})

    pycolmap.set_random_seed(SEED)

    t = time.perf_counter()
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "PINHOLE"
    reader.camera_params = f"{fx!r},{fy!r},{cx!r},{cy!r}"
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.num_threads = threads
    extraction.use_gpu = False
    pycolmap.extract_features(db, img_dir, image_names=names, camera_mode=pycolmap.CameraMode.SINGLE,
                              reader_options=reader, extraction_options=extraction, device=pycolmap.Device.cpu)
    times["extract"] = time.perf_counter() - t

    t = time.perf_counter()
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = threads
    matching.use_gpu = False
    pairing = pycolmap.SequentialPairingOptions()
    pairing.overlap = int(job["overlap"])
    pairing.quadratic_overlap = bool(job["quadratic_overlap"])
    pairing.num_threads = threads
    pycolmap.match_sequential(db, matching_options=matching, pairing_options=pairing, device=pycolmap.Device.cpu)
    times["match"] = time.perf_counter() - t

    t = time.perf_counter()
    opts = pycolmap.IncrementalPipelineOptions()
    opts.num_threads = threads
    opts.random_seed = SEED
    opts.extract_colors = False
    opts.ba_refine_focal_length = False
    opts.ba_refine_principal_point = False
    opts.ba_refine_extra_params = False
    opts.mapper.init_max_forward_motion = float(job["init_max_forward_motion"])
    opts.mapper.abs_pose_refine_focal_length = False
    opts.mapper.abs_pose_refine_extra_params = False
    opts.mapper.num_threads = threads
    opts.mapper.random_seed = SEED
    opts.triangulation.random_seed = SEED
    out_dir = work / "sparse"
    out_dir.mkdir()
    recs = pycolmap.incremental_mapping(db, img_dir, out_dir, opts)
    times["map"] = time.perf_counter() - t

    res["settings"] = {
        "camera_model": "PINHOLE", "camera_mode": "SINGLE", "camera_params": reader.camera_params,
        "feature": "SIFT (COLMAP defaults: max_num_features 8192, CPU)",
        "matching": f"sequential, overlap {pairing.overlap}, quadratic_overlap {pairing.quadratic_overlap}, "
                    "SIFT brute force, geometric verification (defaults)",
        "mapper": {
            "init_max_forward_motion": opts.mapper.init_max_forward_motion,
            "ba_refine_focal_length": opts.ba_refine_focal_length,
            "ba_refine_principal_point": opts.ba_refine_principal_point,
            "ba_refine_extra_params": opts.ba_refine_extra_params,
            "abs_pose_refine_focal_length": opts.mapper.abs_pose_refine_focal_length,
            "abs_pose_refine_extra_params": opts.mapper.abs_pose_refine_extra_params,
            "multiple_models": opts.multiple_models,
            "random_seed": opts.random_seed,
        },
        "threads": threads,
    }

    t = time.perf_counter()
    models = sorted(recs.values(), key=lambda r: r.num_reg_images(), reverse=True)
    res["models"] = [int(r.num_reg_images()) for r in models]
    if not models:
        times["read"] = time.perf_counter() - t
        res.update(_timing(times, len(names)))
        res.update({"registered": 0, "error": "COLMAP built no model (no initial pair found)"})
        return res
    rec = models[0]
    poses, frames = [], []
    for image in rec.images.values():
        if not image.has_pose:
            continue
        T = np.eye(4)
        T[:3, :] = _cam_from_world(image).inverse().matrix()
        poses.append(T)
        frames.append(frame_of[image.name])
    order = np.argsort(frames)
    poses = np.asarray(poses)[order]
    frames = np.asarray(frames, dtype=np.int64)[order]
    cams = [c.params.tolist() for c in rec.cameras.values()]
    times["read"] = time.perf_counter() - t
    res.update(_timing(times, len(names)))

    if job.get("traj_dir"):  # the largest model's trajectory, in the tool's own output format
        from trianflow_vo.io.trajectory import format_kitti_line

        td = Path(job["traj_dir"])
        td.mkdir(parents=True, exist_ok=True)
        (td / "poses.txt").write_text("".join(format_kitti_line(T) + "\n" for T in poses))
        (td / "frames.txt").write_text("".join(f"{i}\n" for i in frames.tolist()))
        res["trajectory"] = str(td / "poses.txt")

    missing = sorted(set(frame_of.values()) - set(frames.tolist()))
    res.update({
        "registered": int(frames.size),
        "unregistered": missing,
        "unregistered_ranges": _ranges(missing, stride),
        "camera_params_after": cams,
        "intrinsics_unchanged": all(np.allclose(c, [fx, fy, cx, cy], rtol=0, atol=1e-9) for c in cams),
        "num_points3D": int(rec.num_points3D()),
        "mean_reprojection_error_px": float(rec.compute_mean_reprojection_error()),
        "mean_track_length": float(rec.compute_mean_track_length()),
    })

    gt_path = seq.ground_truth_path()
    if gt_path is None:
        res["error"] = "no poses.txt"
        return res
    gt = load_ground_truth(gt_path)
    gt_frames = set(gt.frames.tolist())
    selected_with_gt = [i for i in frame_of.values() if i in gt_frames]
    res["frames_with_gt"] = len(selected_with_gt)
    if frames.size < 3:
        res["error"] = f"only {frames.size} frame(s) registered"
        return res
    m = evaluate(poses, frames, gt.poses, gt.frames, align="7dof", lengths=job["lengths"], step=1)
    # path length of the ground truth over every selected frame (registered or not)
    sel = np.asarray(selected_with_gt, dtype=np.int64)
    gt_idx = np.searchsorted(gt.frames, sel)
    p = gt.poses[gt_idx, :3, 3]
    full_len = float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum())
    res.update({
        "evaluated_frames": m["num_frames"],
        "ate_rmse": m["ate_rmse"],
        "ate_max": m["ate_max"],
        "path_length": m["path_length"],
        "path_length_all_selected": full_len,
        "ate_pct": 100.0 * m["ate_rmse"] / m["path_length"],
        "rpe_trans": m["rpe_trans"],
        "rpe_rot": m["rpe_rot"],
        "t_err": m["t_err"],
        "r_err": m["r_err"],
        "sim3_scale": m["scale"],
    })
    return res


def _timing(times: dict, n: int) -> dict:
    total = sum(times.values())
    return {"wall_s": total, "stage_s": dict(times), "fps": n / total if total > 0 else None}


# ---------------------------------------------------------------------------
# parent: cases, table, JSON, markdown


def _git_commit() -> str:
    try:
        rev = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=ROOT, capture_output=True, text=True,
                             check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=ROOT,
                               capture_output=True, text=True).stdout.strip()
        return rev + ("+dirty" if dirty else "")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def _is_sequence(d: Path) -> bool:
    return d.is_dir() and (d / "poses.txt").is_file() and (d / "calib.txt").is_file() and any(
        (d / s).is_dir() for s in ("image_0", "image_2", "color"))


def _clips(args) -> list[Path]:
    if args.clips:
        return [Path(c) for c in args.clips.split(",") if c]
    clips = [Path(args.data) / c for c in DEFAULT_CLIPS]
    bd = Path(args.bench_data)
    if bd.is_dir():
        clips += sorted(d for d in bd.iterdir() if _is_sequence(d))
    return clips


def _lengths(clip: Path) -> list[float]:
    return [1, 2, 3, 4] if "7scenes" in clip.name else [10, 20, 50, 100]


def _run_case(clip: Path, stride: int, args, log_dir: Path) -> dict:
    import tempfile

    case = f"{clip.name}-s{stride}"
    work = Path(tempfile.mkdtemp(prefix=f"colmap-{case}-", dir=args.work_root))
    job = {"clip": str(clip), "stride": stride, "threads": args.threads, "work_dir": str(work),
           "overlap": args.overlap, "quadratic_overlap": not args.no_quadratic_overlap,
           "init_max_forward_motion": args.init_max_forward_motion, "lengths": _lengths(clip),
           "traj_dir": str(log_dir / case)}
    env = dict(os.environ)
    for k in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        env[k] = str(args.threads)
    log = log_dir / f"{case}.log"
    t0 = time.perf_counter()
    with open(log, "w") as lf:
        p = subprocess.run([sys.executable, __file__, "--worker", json.dumps(job)], stdout=subprocess.PIPE,
                           stderr=lf, text=True, env=env, timeout=args.timeout_min * 60 if args.timeout_min else None)
    res = {"case": case, "clip": clip.name, "clip_path": str(clip), "stride": stride, "log": str(log)}
    lines = [ln for ln in p.stdout.splitlines() if ln.startswith("{")]
    if p.returncode == 0 and lines:
        res.update(json.loads(lines[-1]))
    else:
        tail = log.read_text(errors="replace").strip().splitlines()[-3:]
        res["error"] = f"worker exit {p.returncode}: " + " | ".join(tail)
    res["process_wall_s"] = time.perf_counter() - t0
    text = log.read_text(errors="replace")
    res["mapper_log"] = {
        "relaxations": text.count("Relaxing the initialization constraints"),
        "no_initial_pair": text.count("No good initial image pair found"),
        "initial_pairs_tried": text.count("Registering initial image pair"),
        "kept_reconstructions": text.count("Keeping successful reconstruction"),
    }
    if not args.keep_work:
        import shutil

        shutil.rmtree(work, ignore_errors=True)
    else:
        res["work_dir"] = str(work)
    return res


def _notes(r: dict) -> str:
    notes = []
    if r.get("error"):
        notes.append(r["error"])
    if r.get("unregistered"):
        notes.append(f"not registered: {r['unregistered_ranges']}")
    models = r.get("models") or []
    if len(models) > 1:
        notes.append(f"{len(models)} models ({'/'.join(str(m) for m in models)} images), largest used")
    if r.get("frames_with_gt") is not None and r["frames_with_gt"] != r.get("frames"):
        notes.append(f"{r['frames'] - r['frames_with_gt']} selected frame(s) without GT")
    if r.get("evaluated_frames") is not None and r.get("path_length_all_selected") and r.get("unregistered"):
        notes.append(f"% of the {r['path_length']:.1f} m evaluated (of {r['path_length_all_selected']:.1f} m)")
    ml = r.get("mapper_log") or {}
    if ml.get("relaxations"):
        if r.get("registered"):
            notes.append(f"initial pair after {ml['relaxations']} automatic relaxation(s) of the init constraints")
        else:
            notes.append(f"no initial pair even after {ml['relaxations']} automatic relaxation(s)")
    if r.get("intrinsics_unchanged") is False:
        notes.append("intrinsics changed!")
    return "; ".join(notes)


def _f(x, fmt):
    return "—" if x is None else fmt.format(x)


def _table(results: list[dict]) -> str:
    rows = ["| clip | stride | frames | registered | ATE m | ATE % | wall s | frames/s | notes |",
            "|---|---:|---:|---:|---:|---:|---:|---:|---|"]
    for r in results:
        rows.append(
            f"| {r['clip']}{' *' if r.get('from_earlier_run') else ''} | {r['stride']} | {r.get('frames', '—')} | {r.get('registered', '—')} | "
            f"{_f(r.get('ate_rmse'), '{:.3f}')} | {_f(r.get('ate_pct'), '{:.3f}')} | {_f(r.get('wall_s'), '{:.0f}')} | "
            f"{_f(r.get('fps'), '{:.2f}')} | {_notes(r)} |")
    return "\n".join(rows)


def _section(doc: dict) -> str:
    results = doc["results"]
    s = doc["settings"]
    stages = []
    for r in results:
        st = r.get("stage_s")
        if st:
            stages.append(f"{r['case']}: " + ", ".join(f"{k} {v:.0f}" for k, v in st.items() if k in ("extract", "match", "map")))
    lines = [
        f"{SECTION_PREFIX} (pycolmap {doc['pycolmap']}, {doc['date']}, commit {doc['commit']})",
        "",
        "Offline structure from motion on the same clips, for orientation: COLMAP "
        f"({doc['colmap_build']}) through pycolmap, a benchmark-only dependency "
        "(`pip install pycolmap`, not in `pyproject.toml`). Written by `benchmarks/bench_colmap.py`; "
        f"command: `{doc['command']}`.",
        "",
        f"Settings: SIFT (COLMAP defaults, CPU); one PINHOLE camera with the known intrinsics (the `calib.txt` "
        f"line the tool itself reads), held fixed (no focal / principal point / extra refinement in BA or "
        f"registration; checked after mapping); sequential matching, overlap {s['overlap']}, quadratic "
        f"overlap {'on' if s['quadratic_overlap'] else 'off'}; incremental mapper with "
        f"`init_max_forward_motion={s['init_max_forward_motion']}` (default 0.95), colour extraction off, other options default, "
        f"random seed {SEED} (when no initial pair is found, COLMAP relaxes its own initial-pair thresholds "
        f"and retries: counted in the notes); {s['threads']} thread(s), `nice -n {s['nice']}`. The largest model is evaluated "
        "with `trianflow_vo.eval.evaluate` (Sim(3) alignment, ATE RMSE over the registered frames that have "
        "ground truth; ATE % = ATE / GT path length of those frames). Wall = link + feature extraction + "
        "matching + mapping + reading poses; frames/s = selected frames / wall. Shared 2-core machine, other "
        "jobs running: times are indicative.",
        "",
    ]
    if any(r.get("from_earlier_run") for r in results):
        lines += ["Rows marked * come from an earlier run merged in (`--merge`); see the JSON.", ""]
    lines += [_table(results), ""]
    if stages:
        lines += ["Wall seconds per stage (extract, match, map): " + "; ".join(stages) + ".", ""]
    return "\n".join(lines)


def _write_md(path: Path, section: str) -> None:
    """Append the section, or replace this script's own earlier section; never rewrite other sections."""
    if not path.exists():
        path.write_text(section)
        return
    text = path.read_text()
    start = text.find(SECTION_PREFIX)
    if start < 0:
        with open(path, "a") as f:
            f.write(("\n" if text.endswith("\n") else "\n\n") + section)
        return
    nxt = text.find("\n## ", start + 1)
    end = len(text) if nxt < 0 else nxt + 1
    tail = text[end:]
    path.write_text(text[:start] + section + ("\n" + tail if tail else ""))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--worker", help=argparse.SUPPRESS)
    ap.add_argument("--data", default=str(DEFAULT_DATA), help="folder of the shared clips")
    ap.add_argument("--bench-data", default=str(DEFAULT_BENCH_DATA), help="extra sequence folders (if it exists)")
    ap.add_argument("--clips", default="", help="comma-separated sequence folders (instead of the defaults)")
    ap.add_argument("--strides", default="1", help="comma-separated strides, e.g. 1,2,3")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--overlap", type=int, default=10)
    ap.add_argument("--no-quadratic-overlap", action="store_true")
    ap.add_argument("--init-max-forward-motion", type=float, default=1.0)
    ap.add_argument("--timeout-min", type=float, default=120.0, help="per case (0: none)")
    ap.add_argument("--work-root", default=None, help="where the temporary folders go (default: system temp)")
    ap.add_argument("--keep-work", action="store_true", help="keep the COLMAP database and model")
    ap.add_argument("--json", default=str(ROOT / "benchmarks" / "out" / "colmap.json"))
    ap.add_argument("--md", default=str(ROOT / "benchmarks" / "ROBUSTNESS.md"))
    ap.add_argument("--no-md", action="store_true")
    ap.add_argument("--md-from-json", action="store_true", help="only write the markdown section from --json")
    ap.add_argument("--merge", action="store_true",
                    help="keep the results of other cases already in --json (same case: replaced)")
    args = ap.parse_args(argv)

    if args.worker:
        res = _worker(json.loads(args.worker))
        sys.stdout.write(json.dumps(res) + "\n")
        return 0

    json_path, md_path = Path(args.json), Path(args.md)
    if args.md_from_json:
        _write_md(md_path, _section(json.loads(json_path.read_text())))
        print(f"wrote the section to {md_path}")
        return 0

    import pycolmap

    strides = [int(s) for s in args.strides.split(",") if s]
    clips = _clips(args)
    json_path.parent.mkdir(parents=True, exist_ok=True)
    log_dir = json_path.parent / "colmap"
    log_dir.mkdir(exist_ok=True)
    doc = {
        "pycolmap": pycolmap.__version__,
        "colmap_build": getattr(pycolmap, "COLMAP_build", ""),
        "date": datetime.date.today().isoformat(),
        "commit": _git_commit(),
        "command": "nice -n {} python benchmarks/bench_colmap.py {}".format(
            os.nice(0), " ".join(argv if argv is not None else sys.argv[1:])).strip(),
        "settings": {"threads": args.threads, "nice": os.nice(0), "overlap": args.overlap,
                     "quadratic_overlap": not args.no_quadratic_overlap,
                     "init_max_forward_motion": args.init_max_forward_motion, "seed": SEED},
        "results": [],
    }
    kept: list[dict] = []
    if args.merge and json_path.is_file():
        old = json.loads(json_path.read_text())
        new_cases = {f"{c.name}-s{s}" for c in clips for s in strides}
        kept = [r for r in old.get("results", []) if r.get("case") not in new_cases]
        for r in kept:
            r.setdefault("from_earlier_run", f"{old.get('date')}, commit {old.get('commit')}, "
                                             f"command: {old.get('command')}")
        doc["results"] = list(kept)
    print(f"pycolmap {doc['pycolmap']}, {len(clips)} clip(s), strides {strides}, {args.threads} thread(s), "
          f"nice {os.nice(0)}", flush=True)
    for stride in strides:
        for clip in clips:
            t = time.perf_counter()
            try:
                r = _run_case(clip, stride, args, log_dir)
            except subprocess.TimeoutExpired:
                r = {"case": f"{clip.name}-s{stride}", "clip": clip.name, "clip_path": str(clip), "stride": stride,
                     "error": f"timed out after {args.timeout_min:g} min"}
            doc["results"].append(r)
            json_path.write_text(json.dumps(doc, indent=1) + "\n")
            msg = r.get("error") or ""
            print(f"{r['case']}: frames {r.get('frames')}, registered {r.get('registered')}, "
                  f"ATE {_f(r.get('ate_rmse'), '{:.3f}')} m ({_f(r.get('ate_pct'), '{:.3f}')}%), "
                  f"wall {_f(r.get('wall_s'), '{:.0f}')} s, {_f(r.get('fps'), '{:.2f}')} frames/s "
                  f"[{time.perf_counter() - t:.0f} s] {msg}", flush=True)
    doc["results"].sort(key=lambda r: (r["stride"], r["clip"]))
    json_path.write_text(json.dumps(doc, indent=1) + "\n")
    print()
    print(_table(doc["results"]))
    if not args.no_md:
        _write_md(md_path, _section(doc))
        print(f"\nwrote {json_path} and the section in {md_path}")
    else:
        print(f"\nwrote {json_path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
