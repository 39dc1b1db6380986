"""summary.csv / summary.md / summary.json from result rows with known numbers (pure, no Ray)."""

from __future__ import annotations

import csv
import io
import json

import pytest

from trianflow_vo.batch.summary import (
    COLUMNS,
    OVERALL,
    overall_row,
    render_csv,
    render_markdown,
    summary_rows,
    write_summary,
)


def _result(name, status="completed", frames=10, fps=5.0, counts=(8, 1, 0, 0, 0), ev=None, reason=None,
            resumed=False, sweep=None, rss=100.0):
    return {
        "name": name, "label": name, "sweep": sweep or {}, "seq": f"/data/{name}", "out_dir": f"/out/{name}",
        "status": status, "reason": reason, "resumed": resumed, "frames": frames, "frames_skipped": 0,
        "elapsed_s": None if frames is None else frames / fps, "fps": fps, "wall_s": 3.0, "task_s": 4.0,
        "peak_rss_mb": rss,
        "branch_counts": None if counts is None else dict(zip(("two-view", "pnp", "rotation", "identity", "failed"),
                                                              counts)),
        "gt": None, "eval": ev,
    }


EV_A = {"ate_rmse": 0.5, "rpe_trans": 0.2, "rpe_rot": 0.1, "t_err": 4.0, "r_err": 2.0, "lengths": [10.0, 20.0],
        "num_segments": 6}
EV_B = {"ate_rmse": 1.5, "rpe_trans": 0.4, "rpe_rot": 0.3, "t_err": None, "r_err": None, "lengths": [100.0],
        "num_segments": 0}


@pytest.fixture
def results():
    return [
        _result("a", frames=20, fps=10.0, counts=(15, 3, 1, 0, 0), ev=EV_A, rss=150.0),
        _result("b", frames=30, fps=15.0, counts=(25, 4, 0, 0, 0), ev=EV_B, resumed=True, rss=120.0),
        _result("c", status="failed", frames=None, fps=None, counts=None, reason="InputError: /x: no images"),
    ]


def test_rows_and_overall_known_numbers(results):
    rows = summary_rows(results)
    assert [r["name"] for r in rows] == ["a", "b", "c"]
    assert rows[0]["two_view"] == 15 and rows[0]["pnp"] == 3 and rows[0]["rotation"] == 1
    assert rows[0]["lengths"] == "10 20" and rows[0]["t_err"] == 4.0
    assert rows[2]["two_view"] is None and rows[2]["ate_rmse"] is None
    o = overall_row(rows, wall_s=10.0)
    assert o["name"] == OVERALL and o["status"] == "2/3 completed" and o["reason"] == "1 not completed"
    assert o["frames"] == 50 and o["two_view"] == 40 and o["pnp"] == 7 and o["rotation"] == 1
    assert o["fps"] == pytest.approx(20 / 10.0)  # only frames this batch processed (b was resumed)
    assert o["resumed"] == 1 and o["task_s"] == 10.0 and o["peak_rss_mb"] == 150.0
    assert o["ate_rmse"] == pytest.approx(1.0) and o["rpe_rot"] == pytest.approx(0.2)
    assert o["t_err"] == pytest.approx(4.0)  # mean over the runs that have it (b has no segment)
    assert o["num_segments"] == 6


def test_overall_all_resumed_has_no_rate():
    rows = summary_rows([_result("a", resumed=True)])
    assert overall_row(rows, 0.5)["fps"] is None


def test_csv_round_trip(results):
    rows = summary_rows(results)
    text = render_csv(rows, overall_row(rows, 10.0))
    got = list(csv.DictReader(io.StringIO(text)))
    assert list(got[0]) == list(COLUMNS) and len(got) == 4
    assert got[-1]["name"] == OVERALL and got[-1]["frames"] == "50"
    assert got[2]["status"] == "failed" and got[2]["reason"] == "InputError: /x: no images"
    assert got[1]["resumed"] == "true" and got[1]["ate_rmse"] == "1.5" and got[1]["t_err"] == ""


def test_markdown_table_failures_and_sweep_column(results):
    rows = summary_rows(results)
    md = render_markdown(rows, overall_row(rows, 10.0), {"command": "trianflow-vo batch a b c --out o", "workers": 2})
    lines = md.splitlines()
    table = [ln for ln in lines if ln.startswith("| ")]
    assert len(table) == 1 + 3 + 1  # header, 3 runs, overall
    assert "sweep" not in table[0]
    assert table[1].split(" | ")[:4] == ["| a", "completed", "20", "10.0"]
    assert "completed (resumed)" in table[2] and table[-1].startswith("| **ALL**")
    assert "- c: failed — InputError: /x: no images" in lines
    assert "`trianflow-vo batch a b c --out o`" in md and "- workers: 2" in md
    swept = summary_rows([_result("a", sweep={"sampling.seed": "1"})])
    md2 = render_markdown(swept, overall_row(swept, 1.0))
    head = next(ln for ln in md2.splitlines() if ln.startswith("| name"))
    assert "| sweep |" in head and "sampling.seed=1" in md2
    assert "## Not completed" not in md2


def test_markdown_escapes_pipes():
    rows = summary_rows([_result("a", status="failed", reason="x | y\nz")])
    md = render_markdown(rows, overall_row(rows, 1.0))
    assert "x \\| y z" in md


def test_write_summary_files(tmp_path, results):
    paths = write_summary(tmp_path, results, {"command": "c"}, wall_s=10.0)
    assert [p.name for p in paths] == ["summary.csv", "summary.md", "summary.json"]
    assert not list(tmp_path.glob("*.tmp"))
    doc = json.loads((tmp_path / "summary.json").read_text())
    assert doc["meta"]["wall_s"] == 10.0 and doc["overall"]["frames"] == 50
    assert doc["results"][0]["eval"]["lengths"] == [10.0, 20.0] and len(doc["rows"]) == 3


def test_frames_of_a_killed_run_come_from_the_poses_on_disk(tmp_path):
    """A run killed between two run.json updates: the summary counts the poses it wrote."""
    from trianflow_vo.batch.jobs import fill_from_run

    (tmp_path / "poses.txt").write_text("1 0 0 0 0 1 0 0 0 0 1 0\n" * 11)
    row = {"out_dir": str(tmp_path)}
    fill_from_run(row, {"status": "running", "frames_processed": 0})
    assert row["frames"] == 11
    row = {"out_dir": str(tmp_path)}
    fill_from_run(row, {"status": "completed", "frames_processed": 12})
    assert row["frames"] == 12  # a closed run's own count stands
