"""Same poses, no slower: the working tree against an earlier revision, on the shared clips.

Checks out ``--rev`` (default: the last commit before the house refactor) into a
temporary git worktree, then runs every case with both, alternating old/new
``--repeats`` times so that machine noise hits both alike. Reports, per case,
whether ``poses.txt`` is byte-identical (fixed seed) and the median frames/s of
each (from ``run.json``), with their ratio. Writes ``benchmarks/HOUSE.md``.

The old revision must be from before the rename to ``trianflow_vo`` (it is run
as ``python -m cli.main`` from its worktree); the new one is this checkout's
installed ``trianflow-vo``.

With ``--old-args`` no revision is checked out: *old* is this checkout run with those
extra arguments (e.g. a previous default restored with ``--set``), *new* is it with
``--new-args`` (default none), and the table goes to ``--md`` (default: stdout only).

Usage (from the repository root, with the project installed)::

    python benchmarks/compare_revisions.py [--rev 5e04a6f] [--repeats 3] [--data ../shared/data]
    python benchmarks/compare_revisions.py --old-args "--set runtime.blas_threads=2" --md /tmp/ab.md
"""

from __future__ import annotations

import argparse
import json
import shlex
import shutil
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
# name: (folder, extra run arguments)
CASES = {
    "kitti00 s1": ("kitti00-f0000-0150", ["--stride", "1"]),
    "kitti00 s3": ("kitti00-f0000-0150", ["--stride", "3"]),
    "kitti06 s1": ("kitti06-f0000-0050", ["--stride", "1"]),
    "7scenes s1 (300 frames)": ("7scenes-kitchen-f0000-0499", ["--stride", "1", "--end", "300"]),
    "7scenes s3 fine (150 frames)": ("7scenes-kitchen-f0000-0499", ["--stride", "3", "--end", "150",
                                                                     "--dis-preset", "fine"]),
}


def _run(cmd: list[str], cwd: Path, out: Path) -> dict:
    if out.exists():
        shutil.rmtree(out)
    p = subprocess.run([*cmd, "--out", str(out), "--quiet", "--no-plot"], cwd=cwd, capture_output=True, text=True)
    if p.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)} failed: {p.stderr.strip()[-500:]}")
    return json.loads((out / "run.json").read_text())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rev", default="5e04a6f")
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--data", type=Path, default=REPO.parent / "shared" / "data")
    ap.add_argument("--md", type=Path, default=None, help="markdown table (default: benchmarks/HOUSE.md when "
                    "comparing revisions, none with --old-args)")
    ap.add_argument("--old-args", default=None, help="compare this checkout with these extra run arguments "
                    "(old) against --new-args (new) instead of a revision")
    ap.add_argument("--new-args", default="")
    args = ap.parse_args()
    if args.old_args is not None:
        _compare_args(args)
        return
    args.md = args.md or REPO / "benchmarks" / "HOUSE.md"
    tmp = Path(tempfile.mkdtemp(prefix="compare-"))
    old = tmp / "old"
    subprocess.run(["git", "worktree", "add", "--detach", str(old), args.rev], cwd=REPO, check=True,
                   capture_output=True)
    try:
        if "trianflow_vo" in (old / "pyproject.toml").read_text():
            raise SystemExit(f"{args.rev} already uses the trianflow_vo layout; pick an earlier revision")
        rows = _alternate(args, tmp, lambda seq, extra: ([sys.executable, "-m", "cli.main", "run", seq, *extra], old),
                          lambda seq, extra: (["trianflow-vo", "run", seq, *extra], REPO))
        _write_md(args.md, f"Working tree (on {_head()}) against {args.rev}",
                  f"python benchmarks/compare_revisions.py --rev {args.rev} --repeats {args.repeats}", rows)
    finally:
        subprocess.run(["git", "worktree", "remove", "--force", str(old)], cwd=REPO, capture_output=True)
        shutil.rmtree(tmp, ignore_errors=True)


def _alternate(args, tmp: Path, old_cmd, new_cmd) -> list[tuple]:
    """Every case run ``args.repeats`` times with the old and the new command in turn: rows
    ``(name, poses byte-identical, old median frames/s, new median frames/s, new / old)``.
    ``old_cmd(seq, extra)`` / ``new_cmd(seq, extra)`` give ``(command, working folder)``."""
    rows = []
    for name, (folder, extra) in CASES.items():
        seq = str(args.data / folder)
        fps = {"old": [], "new": []}
        same = True
        for _ in range(args.repeats):
            o = _run(*old_cmd(seq, extra), tmp / "o")
            n = _run(*new_cmd(seq, extra), tmp / "n")
            fps["old"].append(o["fps"])
            fps["new"].append(n["fps"])
            same &= (tmp / "o" / "poses.txt").read_bytes() == (tmp / "n" / "poses.txt").read_bytes()
        mo, mn = statistics.median(fps["old"]), statistics.median(fps["new"])
        rows.append((name, same, mo, mn, mn / mo))
        print(f"{name}: poses {'identical' if same else 'DIFFER'}, frames/s old {mo:.1f} new {mn:.1f} "
              f"(x{mn / mo:.2f})", flush=True)
    return rows


def _head() -> str:
    """This checkout's short commit."""
    return subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO, capture_output=True,
                          text=True).stdout.strip()


def _write_md(path: Path | None, title: str, command: str, rows: list[tuple]) -> None:
    lines = [f"# {title}: poses and speed",
             "",
             f"`{command}`; seed 0, 2 threads, old and new runs alternated; frames/s is the median over the "
             "repeats (end to end, decoding included).",
             "",
             "| case | poses.txt | old frames/s | new frames/s | new / old |",
             "|---|---|---:|---:|---:|"]
    lines += [f"| {n} | {'byte-identical' if s else '**differ**'} | {a:.1f} | {b:.1f} | {r:.2f} |"
              for n, s, a, b, r in rows]
    if path is not None:
        path.write_text("\n".join(lines) + "\n")
        print(f"wrote {path}")
    else:
        print("\n".join(lines))


def _compare_args(args) -> None:
    """This checkout with ``--old-args`` (old) against it with ``--new-args`` (new), alternated."""
    old_extra, new_extra = shlex.split(args.old_args), shlex.split(args.new_args)
    tmp = Path(tempfile.mkdtemp(prefix="compare-"))
    try:
        rows = _alternate(args, tmp, lambda seq, extra: (["trianflow-vo", "run", seq, *extra, *old_extra], REPO),
                          lambda seq, extra: (["trianflow-vo", "run", seq, *extra, *new_extra], REPO))
        cmd = f"python benchmarks/compare_revisions.py --old-args {shlex.quote(args.old_args)}"
        if args.new_args:
            cmd += f" --new-args {shlex.quote(args.new_args)}"
        _write_md(args.md, f"Working tree (on {_head()}): `{args.new_args or 'defaults'}` against "
                  f"`{args.old_args}`", f"{cmd} --repeats {args.repeats}", rows)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
