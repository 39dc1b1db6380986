"""Multi-process data parallelism with PyTorch DDP, launched by ``torchrun``.

``torchrun --nproc_per_node N --no-python trianflow-vo train ...`` starts N processes with
``RANK``, ``LOCAL_RANK``, ``WORLD_SIZE``, ``MASTER_ADDR`` and ``MASTER_PORT`` set; a plain
``trianflow-vo train`` is one process (world size 1, no process group). Backend: NCCL on
CUDA, gloo on CPU. Rank 0 writes every output; the others only compute.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import torch
import torch.distributed as dist


@dataclass(frozen=True)
class World:
    rank: int = 0
    local_rank: int = 0
    size: int = 1
    local_size: int = 1

    @property
    def is_main(self) -> bool:
        return self.rank == 0

    @property
    def distributed(self) -> bool:
        return self.size > 1


def world_from_env(env=None) -> World:
    """The process's place in a torchrun job (world size 1 when not launched by torchrun)."""
    env = os.environ if env is None else env
    size = int(env.get("WORLD_SIZE", "1"))
    return World(rank=int(env.get("RANK", "0")), local_rank=int(env.get("LOCAL_RANK", "0")), size=size,
                 local_size=int(env.get("LOCAL_WORLD_SIZE", str(size))))


def init(world: World, device: torch.device) -> None:
    """Join the process group (no-op for one process)."""
    if not world.distributed or dist.is_initialized():
        return
    backend = "nccl" if device.type == "cuda" else "gloo"
    if device.type == "cuda":
        torch.cuda.set_device(device)
    dist.init_process_group(backend=backend)


def close() -> None:
    if dist.is_available() and dist.is_initialized():
        dist.destroy_process_group()


def barrier(world: World) -> None:
    if world.distributed:
        dist.barrier()


def mean_over_ranks(values: dict[str, float], world: World, device: torch.device) -> dict[str, float]:
    """Each value averaged over all processes (same keys on every rank), in the order of ``values``."""
    if not world.distributed or not values:
        return dict(values)
    keys = sorted(values)  # the same order on every rank for the reduction
    t = torch.tensor([float(values[k]) for k in keys], dtype=torch.float64, device=device)
    dist.all_reduce(t)
    t /= world.size
    reduced = dict(zip(keys, t.tolist()))
    return {k: reduced[k] for k in values}


def sum_over_ranks(value: int, world: World, device: torch.device) -> int:
    if not world.distributed:
        return int(value)
    t = torch.tensor([int(value)], dtype=torch.int64, device=device)
    dist.all_reduce(t)
    return int(t.item())


def any_rank(flag: bool, world: World, device: torch.device) -> bool:
    """True on every rank when ``flag`` is true on any (e.g. one rank was interrupted)."""
    return sum_over_ranks(int(bool(flag)), world, device) > 0
