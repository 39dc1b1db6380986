"""The training command's configuration tree (same machinery as a run's: files, presets, ``--set``).

:class:`TrainConfig` has one section per concern: ``model`` (stage, flow source), ``data``,
``optim``, ``losses`` (the loss weights of the TrianFlow recipe), ``schedule`` (how often to
log, write images, validate and checkpoint) and ``runtime`` (device, seed, threads, AMP).

Presets ship in :mod:`trianflow_vo.train.presets`, one file per dataset and stage:
``kitti_flow``, ``kitti_depth``, ``kitti_joint``, ``kitti_odometry_*``, ``nyu_*`` (the
authors' ``kitti``/``kitti_3stage``, ``odo``/``odo_3stage``, ``nyu``/``nyu_3stage`` configs).
``--config kitti`` with ``--stage depth`` reads ``kitti_depth``. With no ``--config`` the
defaults are the ``kitti`` preset of the chosen stage.

Only the standard library here.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from trianflow_vo.config import ConfigRoot, _multiples_of_64, _opt, _Range, _Section, load_config, preset_names
from trianflow_vo.errors import ConfigError

PRESET_PACKAGE = "trianflow_vo.train.presets"
STAGES = ("flow", "depth", "joint")
DATASETS = ("kitti", "kitti_odometry", "nyu")
HEADER = "# Effective training configuration; reproduce with: trianflow-vo train --stage STAGE DATA --config THIS_FILE"


@dataclass(frozen=True)
class ModelConfig(_Section):
    """Which stage trains which network."""

    NAME = "model"
    stage: Literal["flow", "depth", "joint"] = _opt(
        "flow", "flow = the flow net alone; depth = flow net frozen, depth net trained by triangulation; "
                "joint = both")
    flow_source: Literal["net", "dis"] = _opt(
        "net", "stage depth: where its flow comes from; net = the (frozen) flow network, dis = OpenCV DIS "
               "(our CPU option, not the paper's)")


@dataclass(frozen=True)
class DataConfig(_Section):
    """Training pairs."""

    NAME = "data"
    size: tuple[int, int] = _opt((256, 832), "input (h, w) the frames are resized to (cv2 bilinear)",
                                 check=_multiples_of_64, rule="positive multiples of 64", sep="x",
                                 form="HxW or [h, w]")
    gap: int = _opt(1, "frames between the two images of a pair", range=_Range(1, 100))
    flip: bool = _opt(True, "random horizontal flip (p = 0.5; also mirrors cx), the authors' only augmentation")
    exclude: tuple[str, ...] = _opt((), "drive/sequence names or glob patterns left out of training",
                                    sep=",", form="list of names (or a comma-separated string)")
    exclude_eigen_test: bool = _opt(False, "leave out the Eigen test drives (KITTI raw)")
    static_threshold_px: float = _opt(0.0, "drop pairs whose median DIS flow is below this (pixels at the "
                                           "training size); 0 = keep all", range=_Range(0.0))
    workers: int = _opt(2, "data-loader worker processes per training process; 0 = load in the main process",
                        range=_Range(0, 64))


@dataclass(frozen=True)
class OptimConfig(_Section):
    """Optimiser and length of the run."""

    NAME = "optim"
    lr: float = _opt(1e-4, "Adam learning rate (constant, as the authors)", range=_Range(0.0, lo_open=True))
    batch: int = _opt(8, "pairs per iteration, summed over all processes", range=_Range(1, 4096))
    iters: int = _opt(200000, "iterations of the stage (the authors: 200k, NYUv2 400k)", range=_Range(1))


@dataclass(frozen=True)
class LossConfig(_Section):
    """Loss weights (the authors' names)."""

    NAME = "losses"
    w_ssim: float = _opt(0.85, "SSIM share of the photometric error (the rest is L1)", range=_Range(0.0, 1.0))
    w_flow_smooth: float = _opt(10.0, "second-order edge-aware flow smoothness", range=_Range(0.0))
    w_flow_consis: float = _opt(0.01, "flow consistency (in the authors' configs, switched off in their code: "
                                      "kept for the record, no effect)", range=_Range(0.0))
    w_geo: float = _opt(1.0, "geometric (epipolar band) loss on the flow", range=_Range(0.0))
    w_pt_depth: float = _opt(1.0, "L_d: depth against triangulated points", range=_Range(0.0))
    w_pj_depth: float = _opt(0.1, "projected-depth loss of frame 2", range=_Range(0.0))
    w_flow_error: float = _opt(0.0, "flow towards the rigid flow of the triangulated points", range=_Range(0.0))
    w_depth_smooth: float = _opt(1e-3, "first-order depth smoothness on mean-normalised disparity",
                                 range=_Range(0.0))
    fb_consistency: bool = _opt(True, "valid mask uses the forward-backward check (NYUv2: visibility only)")
    depth_failure: Literal["batch", "item"] = _opt(
        "batch", "when the pose or triangulation of a pair fails: batch = zero the depth terms of the whole batch "
                 "(the authors), item = only that pair's (our option)")


@dataclass(frozen=True)
class ScheduleConfig(_Section):
    """How often the loop logs, draws, validates and saves (in iterations)."""

    NAME = "schedule"
    log_every: int = _opt(10, "a metrics.csv row and TensorBoard scalars", range=_Range(1))
    image_every: int = _opt(500, "TensorBoard images (flow, disparity, masks); 0 = never", range=_Range(0))
    checkpoint_every: int = _opt(1000, "write checkpoint.pt (also at the end and on Ctrl-C)", range=_Range(1))
    val_every: int = _opt(1000, "validate on --val data; 0 = only at the end", range=_Range(0))
    val_pairs: int = _opt(32, "most pairs the validation losses are computed on", range=_Range(1))
    val_odometry: bool = _opt(True, "when the validation data has ground-truth poses, run the odometry with "
                                    "the current networks and report its ATE")


@dataclass(frozen=True)
class TrainRuntimeConfig(_Section):
    """Compute resources and reproducibility."""

    NAME = "runtime"
    device: Literal["auto", "cpu", "cuda"] = _opt("auto", "auto = cuda when available, else cpu")
    seed: int = _opt(0, "seed of weights, data order, flips and match sampling (per process: seed + rank)",
                     range=_Range(0))
    threads: int = _opt(0, "torch CPU threads per process; 0 = cores / processes on this machine",
                        range=_Range(0, 256))
    amp: Literal["auto", "on", "off"] = _opt("auto", "mixed precision; auto = on with cuda, off on cpu")


@dataclass(frozen=True)
class TrainConfig(ConfigRoot):
    """The whole configuration of a training run; ``TrainConfig()`` is the defaults."""

    model: ModelConfig = field(default_factory=ModelConfig)
    data: DataConfig = field(default_factory=DataConfig)
    optim: OptimConfig = field(default_factory=OptimConfig)
    losses: LossConfig = field(default_factory=LossConfig)
    schedule: ScheduleConfig = field(default_factory=ScheduleConfig)
    runtime: TrainRuntimeConfig = field(default_factory=TrainRuntimeConfig)


def train_preset_names() -> list[str]:
    """Shipped training presets, e.g. ``kitti_flow``, sorted."""
    return preset_names(PRESET_PACKAGE)


def load_train_config(path_or_name: str | Path | None, stage: str) -> TrainConfig:
    """The config of ``stage`` from a file, a preset (``kitti`` -> ``kitti_<stage>``) or, with
    ``None``, the ``kitti`` preset of that stage; ``model.stage`` is set to ``stage``.

    Raises ConfigError on an unknown stage, preset or a bad file.
    """
    if stage not in STAGES:
        raise ConfigError(f"unknown stage {stage!r}; stages: {', '.join(STAGES)}", "--stage")
    name = "kitti" if path_or_name is None else path_or_name
    text = str(name)
    if not Path(text).is_file() and text in DATASETS:
        name = f"{text}_{stage}"
    elif not Path(text).is_file() and text not in train_preset_names() and "/" not in text and "." not in text:
        raise ConfigError(f"no such file or preset; presets: {', '.join(DATASETS)} (per stage: "
                          f"{', '.join(train_preset_names())})", text)
    cfg = load_config(name, root=TrainConfig, package=PRESET_PACKAGE)
    if cfg.model.stage != stage:
        from dataclasses import replace

        cfg = replace(cfg, model=replace(cfg.model, stage=stage))
    return cfg
