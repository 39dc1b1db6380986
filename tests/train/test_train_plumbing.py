"""Training plumbing with known answers: data order, resume, checkpoints, metrics.csv."""

from __future__ import annotations

import csv

import pytest

torch = pytest.importorskip("torch")

from trianflow_vo.train.checkpointing import (TrainingState, read_training_state, rng_state,  # noqa: E402
                                              save_training_checkpoint)
from trianflow_vo.train.logger import MetricsCSV, truncate_metrics  # noqa: E402
from trianflow_vo.train.loop import ShardedBatches, collate  # noqa: E402


def _take(sampler, n):
    it = iter(sampler)
    return [next(it) for _ in range(n)]


def test_epochs_cover_every_pair_once():
    s = ShardedBatches(10, per_rank=5, rank=0, world=1, seed=3)
    first, second = _take(s, 2)
    assert sorted(k for k, _ in first + second) == list(range(10))
    assert [p for _, p in first + second] == list(range(10))


def test_ranks_split_the_global_batch_without_overlap():
    r0 = _take(ShardedBatches(12, per_rank=2, rank=0, world=2, seed=1), 3)
    r1 = _take(ShardedBatches(12, per_rank=2, rank=1, world=2, seed=1), 3)
    one = _take(ShardedBatches(12, per_rank=4, rank=0, world=1, seed=1), 3)
    for a, b, c in zip(r0, r1, one):
        assert sorted(a + b) == sorted(c)  # together the two processes draw what one process with batch 4 does
        assert not set(a) & set(b)


def test_resume_draws_what_an_uninterrupted_run_draws():
    full = _take(ShardedBatches(7, per_rank=3, rank=0, world=1, seed=5), 9)
    resumed = _take(ShardedBatches(7, per_rank=3, rank=0, world=1, seed=5, start_iteration=4), 5)
    assert resumed == full[4:]
    other = _take(ShardedBatches(7, per_rank=3, rank=0, world=1, seed=6), 9)
    assert other != full


def test_collate_counts_unreadable_samples():
    img = torch.zeros(3, 4, 8)
    K = torch.eye(3)
    good = {"img1": img, "img2": img, "K": K, "K_inv": K}
    batch, skipped = collate([(good, 0), (None, 16), (good, 2)])
    assert batch["img1"].shape == (2, 3, 4, 8) and skipped == 18
    assert collate([(None, 16)]) == (None, 16)


def test_training_checkpoint_round_trip_and_export_reads_it(tmp_path):
    from trianflow_vo.models.checkpoint import load_checkpoint
    from trianflow_vo.models.depth_net import DepthNet

    torch.manual_seed(0)
    net = DepthNet()
    opt = torch.optim.Adam(net.parameters(), lr=1e-4)
    net(torch.rand(1, 3, 64, 64))[0].mean().backward()
    opt.step()
    st = TrainingState("depth", 17, opt.state_dict(), None, rng_state(), {"optim": {"iters": 20}}, "abc", 2)
    path = save_training_checkpoint(tmp_path / "checkpoint.pt", None, net, (64, 64), st)
    assert not (tmp_path / "checkpoint.pt.tmp").exists()
    raw, back = read_training_state(path)  # weights_only=True load
    assert (back.stage, back.iteration, back.data_fingerprint, back.world_size) == ("depth", 17, "abc", 2)
    opt2 = torch.optim.Adam(DepthNet().parameters(), lr=1e-4)
    opt2.load_state_dict(back.optimizer)
    ck = load_checkpoint(path)  # what `export --checkpoint` reads
    assert ck.flow is None and ck.input_size == (64, 64)
    for k, v in net.state_dict().items():
        assert torch.equal(ck.depth.net.state_dict()[k], v)


def test_a_network_checkpoint_is_not_a_training_checkpoint(tmp_path):
    from trianflow_vo.errors import ModelError
    from trianflow_vo.models.checkpoint import make_checkpoint, save_checkpoint
    from trianflow_vo.models.depth_net import DepthNet

    save_checkpoint(tmp_path / "n.pt", make_checkpoint(None, DepthNet(), (64, 64)))
    with pytest.raises(ModelError, match="not a trianflow-vo training checkpoint"):
        read_training_state(tmp_path / "n.pt")


def test_metrics_csv_is_cut_back_on_resume(tmp_path):
    p = tmp_path / "metrics.csv"
    m = MetricsCSV(p, ["photometric"], ["ate_pct"])
    for it in (10, 20, 30):
        m.write({"iteration": it, "photometric": 0.5, "total": 1.0})
    m.close()
    header = truncate_metrics(p, 20)
    assert header[:4] == ["iteration", "seconds", "lr", "photometric"] and header[-1] == "val_ate_pct"
    m = MetricsCSV(p, ["ignored"], [], header)
    m.write({"iteration": 30, "photometric": 0.25, "total": 0.75, "val_ate_pct": 1.5})
    m.close()
    rows = list(csv.DictReader(open(p)))
    assert [r["iteration"] for r in rows] == ["10", "20", "30"]
    assert rows[-1]["photometric"] == "0.25" and rows[-1]["val_ate_pct"] == "1.5" and rows[0]["val_ate_pct"] == ""


def test_validation_odometry_that_never_moves_has_no_ate(tmp_path, monkeypatch):
    """Networks whose flow never passes the two-view tests give a run of rotation-only frames: no
    trajectory to align, so the validation says so instead of an alignment error."""
    import trianflow_vo.pipeline as pipeline
    from trianflow_vo.train import validation

    monkeypatch.setattr(validation, "export_current", lambda *a: (None, None))
    monkeypatch.setattr(pipeline, "run", lambda *a, **k: {"branch_counts": {"init": 1, "two-view": 0, "pnp": 0,
                                                                            "rotation": 50, "identity": 0}})
    with pytest.raises(ValueError, match=r"never left its first pose \(init 1, rotation 50"):
        validation.odometry_ate(tmp_path, tmp_path / "poses.txt", None, None, (64, 192))
