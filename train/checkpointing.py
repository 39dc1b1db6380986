"""Training checkpoints: our network checkpoint format plus the state to resume.

A training checkpoint is a checkpoint of :mod:`trianflow_vo.models.checkpoint` (so
``trianflow-vo export --checkpoint`` reads it directly) with one more key::

    "training": {
        "stage": "flow",                  # model.stage of the run
        "iteration": 1200,                # iterations done
        "optimizer": {...},               # torch optimizer state_dict
        "grad_scaler": {...} | None,      # AMP scaler state (CUDA)
        "rng": {"torch": ByteTensor, "cuda": [ByteTensor, ...]},
        "config": {...},                  # TrainConfig.to_dict()
        "data_fingerprint": "ab12...",    # train.data.fingerprint of the training pairs
        "world_size": 2,
    }

Everything in it is a dict, list, string, number or tensor, so it loads with
``torch.load(weights_only=True)``. Files are written atomically (a temporary file renamed
over the old one): an interrupted write never leaves a partial checkpoint.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import torch

from trianflow_vo.errors import ModelError
from trianflow_vo.models.checkpoint import make_checkpoint, read_file
from trianflow_vo.models.depth_net import DepthNet
from trianflow_vo.models.pwc import PWCNet

CHECKPOINT_NAME = "checkpoint.pt"


@dataclass
class TrainingState:
    """What a training checkpoint adds to the networks."""

    stage: str
    iteration: int
    optimizer: dict
    grad_scaler: dict | None
    rng: dict
    config: dict
    data_fingerprint: str
    world_size: int


def rng_state() -> dict:
    """torch's CPU (and CUDA) generator states."""
    state = {"torch": torch.get_rng_state()}
    if torch.cuda.is_available():
        state["cuda"] = torch.cuda.get_rng_state_all()
    return state


def set_rng_state(state: dict) -> None:
    if "torch" in state:
        torch.set_rng_state(state["torch"])
    if "cuda" in state and torch.cuda.is_available():
        torch.cuda.set_rng_state_all(state["cuda"])


def save_training_checkpoint(path: str | Path, flow: PWCNet | None, depth: DepthNet | None,
                             input_size: tuple[int, int], state: TrainingState) -> Path:
    """Write the networks and ``state`` to ``path`` atomically; returns ``path``."""
    path = Path(path)
    ckpt = make_checkpoint(flow, depth, input_size)
    ckpt["training"] = {
        "stage": state.stage, "iteration": int(state.iteration), "optimizer": state.optimizer,
        "grad_scaler": state.grad_scaler, "rng": state.rng, "config": state.config,
        "data_fingerprint": state.data_fingerprint, "world_size": int(state.world_size),
    }
    tmp = path.with_name(path.name + ".tmp")
    try:
        torch.save(ckpt, str(tmp))
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


def read_training_state(path: str | Path) -> tuple[dict, TrainingState]:
    """The raw checkpoint dict and its training state; ModelError (one line naming the file)
    when the file is not a training checkpoint of ours."""
    obj = read_file(path)
    if not isinstance(obj, dict) or "training" not in obj:
        raise ModelError(f"{path}: not a trianflow-vo training checkpoint (no 'training' state to resume from)")
    t = obj["training"]
    need = ("stage", "iteration", "optimizer", "rng", "config", "data_fingerprint")
    missing = [k for k in need if k not in t]
    if missing:
        raise ModelError(f"{path}: training state lacks {', '.join(missing)}")
    return obj, TrainingState(t["stage"], int(t["iteration"]), t["optimizer"], t.get("grad_scaler"), t["rng"],
                              t["config"], str(t["data_fingerprint"]), int(t.get("world_size", 1)))
