"""Training configuration: presets per dataset and stage, overrides, errors."""

from __future__ import annotations

import pytest

from trianflow_vo.config import apply_overrides, load_config
from trianflow_vo.errors import ConfigError
from trianflow_vo.train.config import DATASETS, STAGES, TrainConfig, load_train_config, train_preset_names


def test_every_dataset_has_a_preset_per_stage():
    assert sorted(train_preset_names()) == sorted(f"{d}_{s}" for d in DATASETS for s in STAGES)


@pytest.mark.parametrize("dataset,stage,w_geo,w_pt,w_pj,w_fe,w_ds", [
    # the authors' config files: kitti / kitti_3stage, odo / odo_3stage, nyu / nyu_3stage
    ("kitti", "flow", 1.0, 1.0, 0.1, 0.0, 1e-3),
    ("kitti", "depth", 1.0, 1.0, 0.1, 0.0, 1e-3),
    ("kitti", "joint", 0.002, 0.0, 0.0, 0.01, 0.0),
    ("kitti_odometry", "depth", 0.1, 1.0, 0.1, 0.0, 1e-4),
    ("kitti_odometry", "joint", 0.002, 0.0, 0.0, 0.01, 0.0),
    ("nyu", "depth", 0.0, 1.0, 0.1, 0.0, 1e-4),
    ("nyu", "joint", 0.1, 0.1, 0.01, 0.0, 1e-4),
])
def test_preset_loss_weights_are_the_authors(dataset, stage, w_geo, w_pt, w_pj, w_fe, w_ds):
    cfg = load_train_config(dataset, stage)
    assert cfg.model.stage == stage
    lw = cfg.losses
    assert (lw.w_geo, lw.w_pt_depth, lw.w_pj_depth, lw.w_flow_error, lw.w_depth_smooth) == (w_geo, w_pt, w_pj,
                                                                                           w_fe, w_ds)
    assert (lw.w_ssim, lw.w_flow_smooth) == (0.85, 10.0)
    assert lw.fb_consistency is (dataset != "nyu")
    assert cfg.optim.lr == 1e-4 and cfg.optim.batch == 8
    assert cfg.optim.iters == (400000 if dataset == "nyu" else 200000)
    assert cfg.data.size == ((448, 576) if dataset == "nyu" else (256, 832))
    assert cfg.data.gap == (10 if dataset == "nyu" else 1)  # the authors pair NYUv2 raw frames n and n + 10
    assert cfg.data.exclude_eigen_test is (dataset == "kitti")
    assert lw.depth_failure == "batch"  # the authors zero a failed batch's depth terms


def test_default_is_the_kitti_preset_of_the_stage():
    assert load_train_config(None, "joint") == load_train_config("kitti", "joint")
    assert load_train_config(None, "joint").losses.w_geo == 0.002


def test_stage_follows_the_command_not_the_file(tmp_path):
    f = tmp_path / "my.yaml"
    f.write_text("model:\n  stage: flow\noptim:\n  iters: 12\n")
    cfg = load_train_config(f, "depth")
    assert cfg.model.stage == "depth" and cfg.optim.iters == 12


def test_overrides_and_errors_name_the_key():
    cfg = apply_overrides(TrainConfig(), ["losses.w_geo=0.5", "data.size=128x384", "data.exclude=a,b"])
    assert cfg.losses.w_geo == 0.5 and cfg.data.size == (128, 384) and cfg.data.exclude == ("a", "b")
    with pytest.raises(ConfigError, match="data.size"):
        apply_overrides(TrainConfig(), ["data.size=100x300"])
    with pytest.raises(ConfigError, match="unknown key 'losses.w_nope'"):
        apply_overrides(TrainConfig(), ["losses.w_nope=1"])
    with pytest.raises(ConfigError, match="losses.w_geo"):
        apply_overrides(TrainConfig(), ["losses.w_geo=-1"])
    with pytest.raises(ConfigError, match="unknown stage"):
        load_train_config(None, "posenet")
    with pytest.raises(ConfigError, match="no such file or preset"):
        load_train_config("cityscapes", "flow")


def test_effective_config_round_trips(tmp_path):
    from trianflow_vo.config import write_config_yaml

    cfg = apply_overrides(load_train_config("nyu", "joint"), ["data.exclude=[x, 'y*']", "optim.iters=7"])
    write_config_yaml(cfg, tmp_path / "c.yaml")
    back = load_config(tmp_path / "c.yaml", root=TrainConfig)
    assert back == cfg


def test_shipped_presets_equal_the_objectives_weight_table():
    """The YAML presets (what `--config` reads) and objective.PRESETS (the library's table) agree."""
    import dataclasses

    from trianflow_vo.train.objective import PRESETS, LossWeights

    for dataset in DATASETS:
        for stage in STAGES:
            yaml_weights = LossWeights.from_dict(dataclasses.asdict(load_train_config(dataset, stage).losses))
            assert yaml_weights == PRESETS[dataset][stage], (dataset, stage)
