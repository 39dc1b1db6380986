"""The training loop of one stage: data, networks, optimiser, logging, checkpoints, validation.

:func:`prepare` checks everything that can be checked before a file is written (data,
``--init`` checkpoint against the stage, ``--resume`` state, the output folder); then
:func:`train` runs the iterations. The losses are :func:`trianflow_vo.train.objective.compute_losses`;
the data :mod:`trianflow_vo.train.data`; this module only orders them.

Reproducibility: every random choice of an iteration comes from ``(seed, rank, iteration)``
(the data order from ``(seed, epoch)``, each sample's flip from its position in the data
stream), so ``--resume`` continues exactly where the run stopped, and a run is the same
on every machine for the same world size.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import os
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from trianflow_vo.errors import InputError, ModelError
from trianflow_vo.train import distributed as dist_util
from trianflow_vo.train.checkpointing import (CHECKPOINT_NAME, TrainingState, read_training_state, rng_state,
                                              save_training_checkpoint, set_rng_state)
from trianflow_vo.train.config import HEADER, TrainConfig

log = logging.getLogger("trianflow_vo.train")

METRICS_NAME = "metrics.csv"
STATUS_NAME = "train.json"
CONFIG_NAME = "config.yaml"
TB_DIR = "tb"
MAX_RETRIES = 16  # consecutive unreadable samples replaced by the next ones before a batch is given up


@dataclass
class TrainRequest:
    """What the user asked for (the CLI builds it)."""

    data: list[Path]
    out_dir: Path
    config: TrainConfig
    init: Path | None = None
    resume: bool = False
    val: list[Path] = field(default_factory=list)
    intrinsics: tuple[float, float, float, float] | None = None
    calib: Path | None = None
    trust_checkpoint: bool = False
    command: str = ""


@dataclass
class Prepared:
    request: TrainRequest
    config: TrainConfig
    sources: list
    val_sources: list
    init_nets: dict  # {"flow": state_dict, "depth": state_dict} from --init
    resume_state: TrainingState | None
    resume_nets: dict
    init_source: str | None


@dataclass
class TrainResult:
    status: str  # completed | interrupted
    iteration: int
    checkpoint: Path | None
    last_terms: dict[str, float]
    skipped: int
    depth_failed: int
    nonfinite: int
    seconds_per_iter_median: float | None


# -- sampling -----------------------------------------------------------------------------------------------------
def _mix(*values: int) -> int:
    """A 63-bit seed from integers (splitmix-style), stable across runs and platforms."""
    h = 0x9E3779B97F4A7C15
    for v in values:
        h ^= (int(v) + 0x9E3779B97F4A7C15 + (h << 6) + (h >> 2)) & 0xFFFFFFFFFFFFFFFF
        h = (h * 0xBF58476D1CE4E5B9) & 0xFFFFFFFFFFFFFFFF
    return h & 0x7FFFFFFFFFFFFFFF


class ShardedBatches:
    """Infinite batches of ``(pair index, draw position)`` for one process.

    The global stream of pairs is a sequence of epochs, each a permutation of all pairs
    seeded by ``(seed, epoch)``; iteration ``it`` takes positions ``[it * B, (it + 1) * B)``
    of that stream (``B`` = batch summed over processes), and process ``rank`` every
    ``world``-th of them. Starting at ``start_iteration`` gives what a run that never
    stopped would have drawn.
    """

    def __init__(self, n_pairs: int, per_rank: int, rank: int, world: int, seed: int, start_iteration: int = 0,
                 shuffle: bool = True):
        if n_pairs < 1:
            raise ValueError("no pairs to draw from")
        self.n, self.per_rank, self.rank, self.world = n_pairs, per_rank, rank, world
        self.seed, self.it, self.shuffle = seed, start_iteration, shuffle
        self._perm: dict[int, np.ndarray] = {}

    def _epoch(self, e: int) -> np.ndarray:
        if e not in self._perm:
            self._perm = {e: (np.random.default_rng(_mix(self.seed, e)).permutation(self.n) if self.shuffle
                              else np.arange(self.n))}
        return self._perm[e]

    def batch(self, it: int) -> list[tuple[int, int]]:
        g = self.per_rank * self.world
        out = []
        for j in range(self.per_rank):
            p = it * g + j * self.world + self.rank
            out.append((int(self._epoch(p // self.n)[p % self.n]), p))
        return out

    def __iter__(self):
        while True:
            yield self.batch(self.it)
            self.it += 1


class StreamPairs(torch.utils.data.Dataset):
    """The pair dataset addressed by ``(pair index, draw position)``: the flip of a sample is
    drawn from ``(seed, position)``; an unreadable pair is replaced by the next ones (at most
    :data:`MAX_RETRIES`), and how many were replaced is returned with it."""

    def __init__(self, dataset, seed: int, flip: bool):
        self.ds, self.seed, self.flip = dataset, seed, flip

    def __len__(self) -> int:
        return len(self.ds)

    def __getitem__(self, key):
        k, pos = key
        for tries in range(MAX_RETRIES):
            kk = (k + tries) % len(self.ds)
            flip = bool(np.random.default_rng(_mix(self.seed, pos, tries)).random() < 0.5) if self.flip else False
            item = self.ds.get(kk, flip=flip)
            if item is not None:
                return item, tries
        return None, MAX_RETRIES


def collate(items):
    """``[(sample | None, skipped), ...]`` -> ``(batch dict | None, skipped)``."""
    skipped = sum(s for _, s in items)
    good = [it for it, _ in items if it is not None]
    if not good:
        return None, skipped
    batch = {k: torch.stack([g[k] for g in good]) for k in ("img1", "img2", "K", "K_inv")}
    return batch, skipped


# -- networks -----------------------------------------------------------------------------------------------------
def _needs(stage: str, flow_source: str) -> dict[str, str]:
    """Which networks a stage builds: name -> 'train' | 'frozen' | 'init-required'."""
    if stage == "flow":
        return {"flow": "train"}
    if stage == "depth":
        return {"depth": "train"} if flow_source == "dis" else {"flow": "frozen", "depth": "train"}
    return {"flow": "train", "depth": "train"}


def _state_dicts_of(ckpt) -> dict:
    out = {}
    if ckpt.flow is not None:
        out["flow"] = ckpt.flow.net.state_dict()
    if ckpt.depth is not None:
        out["depth"] = ckpt.depth.net.state_dict()
    return out


def prepare(req: TrainRequest) -> Prepared:
    """All checks before anything is written. Raises InputError / ModelError / ConfigError."""
    from trianflow_vo.models.checkpoint import checkpoint_from_dict, load_checkpoint
    from trianflow_vo.train.data import open_training_sources

    cfg = req.config
    stage = cfg.model.stage
    out = Path(req.out_dir)
    ckpt_path = out / CHECKPOINT_NAME
    resume_state, resume_nets = None, {}
    if req.resume:
        if not ckpt_path.is_file():
            raise InputError(f"nothing to resume: no {CHECKPOINT_NAME} in it", out)
        raw, resume_state = read_training_state(ckpt_path)
        if resume_state.stage != stage:
            raise ModelError(f"{ckpt_path}: a checkpoint of stage '{resume_state.stage}', not '{stage}': "
                             f"resume it with --stage {resume_state.stage}")
        resume_nets = _state_dicts_of(checkpoint_from_dict(raw, str(ckpt_path)))
    elif ckpt_path.exists() or (out / METRICS_NAME).exists():
        raise InputError(f"holds a training run already ({CHECKPOINT_NAME} / {METRICS_NAME}); continue it with "
                         "--resume, or choose another --out", out)
    elif out.exists() and not out.is_dir():
        raise InputError("exists and is not a folder", out)

    needs = _needs(stage, cfg.model.flow_source)
    init_nets, init_source = {}, None
    if req.init is not None and not req.resume:
        ck = load_checkpoint(req.init, trust_pickle=req.trust_checkpoint)
        init_nets, init_source = _state_dicts_of(ck), ck.source
        if tuple(ck.input_size) != tuple(cfg.data.size):
            log.info(f"--init {req.init}: trained at {ck.input_size[0]}x{ck.input_size[1]}, training now at "
                     f"{cfg.data.size[0]}x{cfg.data.size[1]}")
    if not req.resume:
        for name, role in needs.items():
            if role == "frozen" and name not in init_nets:
                what = "no --init" if req.init is None else f"--init {req.init} holds no {name} network"
                raise ModelError(f"stage '{stage}' trains on a frozen {name} network from stage 1, but {what}; "
                                 f"give --init with the flow stage's checkpoint" +
                                 (" (or --flow-source dis)" if stage == "depth" else ""))
            if stage == "joint" and name not in init_nets:
                what = "no --init" if req.init is None else f"--init {req.init} holds no {name} network"
                raise ModelError(f"stage 'joint' starts from both networks of stages 1-2, but {what}; give "
                                 "--init with the depth stage's checkpoint")
        if stage == "flow" and req.init is not None and "flow" not in init_nets:
            raise ModelError(f"{req.init}: holds no flow network to start stage 'flow' from")
    sources = open_training_sources(req.data, intrinsics=req.intrinsics, calib=req.calib)
    val_sources = open_training_sources(req.val, intrinsics=req.intrinsics, calib=req.calib) if req.val else []
    return Prepared(req, cfg, sources, val_sources, init_nets, resume_state, resume_nets, init_source)


def _device(cfg: TrainConfig, world: dist_util.World) -> torch.device:
    want = cfg.runtime.device
    if want == "cuda" or (want == "auto" and torch.cuda.is_available()):
        if not torch.cuda.is_available():
            raise InputError("--device cuda: no CUDA device is available to torch")
        return torch.device("cuda", world.local_rank % max(torch.cuda.device_count(), 1))
    return torch.device("cpu")


def _build_nets(prep: Prepared, device: torch.device, seed: int):
    from trianflow_vo.models.depth_net import DepthNet
    from trianflow_vo.models.pwc import PWCNet

    cfg = prep.config
    needs = _needs(cfg.model.stage, cfg.model.flow_source)
    torch.manual_seed(seed)  # the same initial weights on every process
    nets = {}
    if "flow" in needs:
        nets["flow"] = PWCNet()
    if "depth" in needs:
        nets["depth"] = DepthNet()
    src = prep.resume_nets or prep.init_nets
    for name, net in nets.items():
        if name in src:
            net.load_state_dict(src[name])
        net.to(device)
        role = needs[name]
        net.train(role == "train")
        for p in net.parameters():
            p.requires_grad_(role == "train")
    return nets, needs


class Trainee(torch.nn.Module):
    """The networks of a stage as one module (what DDP wraps); ``forward`` returns the losses."""

    def __init__(self, nets: dict, stage: str, weights, use_dis: bool):
        super().__init__()
        self.flow_net = nets.get("flow")
        self.depth_net = nets.get("depth")
        self.stage, self.weights, self.use_dis = stage, weights, use_dis

    def forward(self, img1, img2, K, K_inv, flows, generator):
        from trianflow_vo.train.objective import compute_losses

        out = compute_losses(self.stage, img1, img2, K, K_inv, self.weights, flow_net=self.flow_net,
                             depth_net=self.depth_net, flows=flows, generator=generator)
        return out.total, out


def dis_flows(img1: torch.Tensor, img2: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """OpenCV DIS forward and backward flow ``(N, 2, H, W)`` of ``(N, 3, H, W)`` [0, 1] BGR images."""
    import cv2

    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    fw, bw = [], []
    for a, b in zip(img1.cpu().numpy(), img2.cpu().numpy()):
        ga = np.ascontiguousarray(cv2.cvtColor((a.transpose(1, 2, 0) * 255).astype(np.uint8), cv2.COLOR_BGR2GRAY))
        gb = np.ascontiguousarray(cv2.cvtColor((b.transpose(1, 2, 0) * 255).astype(np.uint8), cv2.COLOR_BGR2GRAY))
        fw.append(dis.calc(ga, gb, None).transpose(2, 0, 1))
        bw.append(dis.calc(gb, ga, None).transpose(2, 0, 1))
    return (torch.from_numpy(np.stack(fw)).to(img1.device), torch.from_numpy(np.stack(bw)).to(img1.device))


def loss_weights(cfg: TrainConfig):
    from trianflow_vo.train.objective import LossWeights

    return LossWeights.from_dict(dataclasses.asdict(cfg.losses))


# -- the loop -----------------------------------------------------------------------------------------------------
def _threads(cfg: TrainConfig, world: dist_util.World) -> int:
    return cfg.runtime.threads or max(1, (os.cpu_count() or 1) // max(world.local_size, 1))


def _peak_rss_mb() -> float:
    from trianflow_vo.io.run_writer import peak_rss_mb  # the process's own peak (VmHWM), not an inherited one

    return peak_rss_mb()


def train(prep: Prepared, world: dist_util.World | None = None,
          on_progress: Callable[[dict], None] | None = None) -> TrainResult:
    """Run the stage; rank 0 writes ``checkpoint.pt``, ``metrics.csv``, ``tb/``, ``config.yaml`` and
    ``train.json`` in the output folder. Ctrl-C / SIGTERM: checkpoint, status ``interrupted``.

    torch's and OpenCV's thread counts are set for the run (``runtime.threads``) and restored after."""
    import cv2

    before = (torch.get_num_threads(), cv2.getNumThreads())
    try:
        return _train(prep, world, on_progress)
    finally:
        torch.set_num_threads(before[0])
        cv2.setNumThreads(before[1])


def _train(prep: Prepared, world: dist_util.World | None, on_progress: Callable[[dict], None] | None
           ) -> TrainResult:
    import cv2

    from trianflow_vo.config import write_config_yaml
    from trianflow_vo.io.run_dir import InterruptSignals
    from trianflow_vo.train.data import PairDataset, fingerprint
    from trianflow_vo.train.logger import MetricsCSV, TensorBoard, truncate_metrics

    world = world or dist_util.world_from_env()
    cfg, req = prep.config, prep.request
    device = _device(cfg, world)
    dist_util.init(world, device)
    threads = _threads(cfg, world)
    torch.set_num_threads(threads)
    cv2.setNumThreads(threads)
    stage = cfg.model.stage
    seed = cfg.runtime.seed
    use_dis = stage == "depth" and cfg.model.flow_source == "dis"
    amp = device.type == "cuda" and cfg.runtime.amp != "off"
    if cfg.runtime.amp == "on" and device.type != "cuda":
        log.warning("runtime.amp=on needs CUDA: training in float32 on the CPU")

    size = tuple(cfg.data.size)
    exclude = list(cfg.data.exclude)
    if cfg.data.exclude_eigen_test:
        from trianflow_vo.train.data import eigen_test_scenes

        exclude += eigen_test_scenes()
    static = None
    if cfg.data.static_threshold_px > 0:
        from trianflow_vo.train.data import StaticFilter

        static = StaticFilter(threshold_px=cfg.data.static_threshold_px, cache_dir=Path(req.out_dir) / "cache")
    dataset = PairDataset(prep.sources, size=size, gap=cfg.data.gap, flip=False, exclude=exclude,
                          static_filter=static, seed=seed)
    if len(dataset) == 0:
        raise InputError("no training pairs left (after the gap, exclusions and the static filter)",
                         ", ".join(str(p) for p in req.data))
    fp = fingerprint(dataset)
    if prep.resume_state is not None and prep.resume_state.data_fingerprint != fp:
        log.warning("the training data differ from the run being resumed (data fingerprint changed)")
    if cfg.optim.batch % world.size:
        raise InputError(f"optim.batch {cfg.optim.batch} is not divisible by the {world.size} processes")
    per_rank = cfg.optim.batch // world.size

    nets, needs = _build_nets(prep, device, seed)
    model = Trainee(nets, stage, loss_weights(cfg), use_dis).to(device)
    trainable = [p for p in model.parameters() if p.requires_grad]
    optimizer = torch.optim.Adam(trainable, lr=cfg.optim.lr)
    scaler = torch.amp.GradScaler("cuda", enabled=amp)
    start = 0
    if prep.resume_state is not None:
        st = prep.resume_state
        optimizer.load_state_dict(st.optimizer)
        if st.grad_scaler and amp:
            scaler.load_state_dict(st.grad_scaler)
        set_rng_state(st.rng)
        start = st.iteration
    ddp_model = model
    if world.distributed:
        from torch.nn.parallel import DistributedDataParallel

        # every trained parameter is in every step's graph (the objective's zero-weight anchor), so DDP
        # needs no search for unused ones
        ddp_model = DistributedDataParallel(model, device_ids=[device.index] if device.type == "cuda" else None,
                                            find_unused_parameters=False)

    sampler = ShardedBatches(len(dataset), per_rank, world.rank, world.size, seed, start)
    stream = StreamPairs(dataset, seed, cfg.data.flip)
    loader = torch.utils.data.DataLoader(stream, batch_sampler=sampler, num_workers=cfg.data.workers,
                                         collate_fn=collate, persistent_workers=cfg.data.workers > 0,
                                         pin_memory=device.type == "cuda")

    out = Path(req.out_dir)
    main = world.is_main
    csv_log = tb = None
    val_loader = None
    if prep.val_sources:
        val_ds = PairDataset(prep.val_sources, size=size, gap=cfg.data.gap, flip=False, seed=seed)
        if len(val_ds):
            vs = ShardedBatches(len(val_ds), min(per_rank, cfg.schedule.val_pairs), 0, 1, seed, shuffle=False)
            val_loader = (val_ds, vs)
    val_gt = next(((s.path, s.ground_truth_path) for s in prep.val_sources
                   if getattr(s, "ground_truth_path", None)), None)
    val_names = []
    if val_loader is not None:
        val_names.append("total")
    if val_gt is not None and cfg.schedule.val_odometry:
        val_names += ["ate_rmse", "ate_pct"]

    status_doc = {
        "command": req.command, "stage": stage, "status": "running", "out_dir": str(out),
        "data": [str(p) for p in req.data], "val": [str(p) for p in req.val], "pairs": len(dataset),
        "data_fingerprint": fp, "init": None if req.init is None else str(req.init), "init_format": prep.init_source,
        "resumed_from": None if prep.resume_state is None else prep.resume_state.iteration,
        "device": str(device), "amp": amp, "world_size": world.size, "threads_per_process": threads,
        "batch": cfg.optim.batch, "batch_per_process": per_rank, "iterations": cfg.optim.iters,
        "config": cfg.to_dict(), "warnings": [],
    }
    if use_dis:
        status_doc["warnings"].append("stage depth takes its flow from OpenCV DIS (model.flow_source=dis): our "
                                      "CPU option, not the paper's recipe")
    if main:
        out.mkdir(parents=True, exist_ok=True)
        write_config_yaml(cfg, out / CONFIG_NAME, HEADER)
        tb = TensorBoard(out / TB_DIR, purge_step=start if start else None)

    def write_status(**kw):
        if main:
            status_doc.update(kw)
            tmp = out / (STATUS_NAME + ".tmp")
            tmp.write_text(json.dumps(status_doc, indent=2) + "\n")
            tmp.replace(out / STATUS_NAME)

    saved = {"iteration": start if prep.resume_state is not None else None}

    def save(it: int) -> Path | None:
        if not main:
            return None
        saved["iteration"] = it
        st = TrainingState(stage, it, optimizer.state_dict(), scaler.state_dict() if amp else None, rng_state(),
                           cfg.to_dict(), fp, world.size)
        return save_training_checkpoint(out / CHECKPOINT_NAME, nets.get("flow"), nets.get("depth"), size, st)

    def compute(batch, it, train_mode=True):
        img1 = batch["img1"].to(device, non_blocking=True)
        img2 = batch["img2"].to(device, non_blocking=True)
        K = batch["K"].to(device)
        K_inv = batch["K_inv"].to(device)
        flows = dis_flows(img1, img2) if use_dis else None
        gen = torch.Generator(device="cpu").manual_seed(_mix(seed, world.rank, it, 0 if train_mode else 1))
        cv2.setRNGSeed(int(_mix(seed, world.rank, it, 2) & 0x7FFFFFFF))
        with torch.autocast(device.type, dtype=torch.float16, enabled=amp):
            return (ddp_model if train_mode else model)(img1, img2, K, K_inv, flows, gen)

    def validate(it: int) -> dict[str, float]:
        res: dict[str, float] = {}
        if not main:
            return res
        was = {k: n.training for k, n in nets.items()}
        for n in nets.values():
            n.eval()
        try:
            if val_loader is not None:
                from trianflow_vo.train.validation import validation_losses

                ds, vs = val_loader
                vstream = StreamPairs(ds, seed, False)
                n_batches = 2 * math.ceil(cfg.schedule.val_pairs / vs.per_rank)  # bounded: unreadable pairs
                batches = (collate([vstream[k] for k in vs.batch(i)]) for i in range(n_batches))
                means, n = validation_losses(lambda b: compute(b, it, train_mode=False)[1], batches,
                                             cfg.schedule.val_pairs, device)
                res.update(means)
            if val_gt is not None and cfg.schedule.val_odometry:
                from trianflow_vo.train.validation import odometry_ate

                try:
                    res.update(odometry_ate(Path(val_gt[0]), Path(val_gt[1]), nets.get("flow"), nets.get("depth"),
                                            size, threads=threads))
                except Exception as exc:  # a failed validation run must not end the training
                    msg = f"validation odometry at iteration {it} failed: {' '.join(str(exc).split())[:300]}"
                    log.warning(msg)
                    status_doc["warnings"].append(msg)
        finally:
            for k, n in nets.items():
                n.train(was[k] and needs[k] == "train")
        if tb is not None:
            tb.scalars(it, res, "val/")
        return res

    if main:
        header = truncate_metrics(out / METRICS_NAME, start) if start else None
    times: list[float] = []
    counts = {"skipped": 0, "depth_failed": 0, "nonfinite": 0}
    interval: dict[str, float] = {}
    interval_n = 0
    interval_s = 0.0
    last_terms: dict[str, float] = {}
    it = start
    status, error = "completed", None
    ckpt = None
    write_status(status="running", iteration=start)
    data_iter = iter(loader)
    with InterruptSignals():
        try:
            while it < cfg.optim.iters:
                t0 = time.perf_counter()
                batch, skipped = next(data_iter)
                counts["skipped"] += skipped
                have = batch is not None
                if world.distributed:
                    have = not dist_util.any_rank(not have, world, device)
                if not have:
                    it += 1
                    continue
                total, outp = compute(batch, it)
                optimizer.zero_grad(set_to_none=True)
                scaler.scale(total).backward()
                bad = not bool(torch.isfinite(total.detach()))
                if world.distributed:
                    bad = dist_util.any_rank(bad, world, device)
                if bad:
                    counts["nonfinite"] += 1
                    optimizer.zero_grad(set_to_none=True)
                else:
                    scaler.step(optimizer)
                    scaler.update()
                counts["depth_failed"] += int(outp.depth_zeroed)
                it += 1
                dt = time.perf_counter() - t0
                times.append(dt)
                for k, v in outp.terms.items():
                    interval[k] = interval.get(k, 0.0) + float(v)
                interval_n += 1
                interval_s += dt
                if it % cfg.schedule.log_every == 0 or it == cfg.optim.iters:
                    means = dist_util.mean_over_ranks({k: v / interval_n for k, v in interval.items()}, world,
                                                      device)
                    sec = interval_s / interval_n  # mean wall time per iteration since the last row
                    interval, interval_n, interval_s = {}, 0, 0.0
                    last_terms = means
                    totals = {k: dist_util.sum_over_ranks(counts[k], world, device)
                              for k in ("skipped", "depth_failed")}  # every process's, not rank 0's alone
                    row = {"iteration": it, "seconds": sec, "lr": cfg.optim.lr, **means, **totals}
                    do_val = (cfg.schedule.val_every and it % cfg.schedule.val_every == 0) or it == cfg.optim.iters
                    if do_val and val_names:
                        vres = validate(it)
                        dist_util.barrier(world)
                        row.update({f"val_{k}": v for k, v in vres.items()})
                    if main:
                        if csv_log is None:
                            terms = [k for k in means if k != "total"]
                            csv_log = MetricsCSV(out / METRICS_NAME, terms, val_names, header)
                        csv_log.write(row)
                        tb.scalars(it, {k: v for k, v in means.items()}, "loss/")
                        tb.scalars(it, {"lr": cfg.optim.lr, "time/iteration_s": sec}, "")
                    if on_progress is not None and main:
                        on_progress({"iteration": it, "total": cfg.optim.iters, "start": start,
                                     "seconds": float(np.median(times[-50:])), "terms": means, **counts})
                if main and cfg.schedule.image_every and it % cfg.schedule.image_every == 0:
                    tb.images(it, outp.visuals)
                if it % cfg.schedule.checkpoint_every == 0 and it < cfg.optim.iters:
                    ckpt = save(it)
                    write_status(iteration=it, checkpoint_iteration=saved["iteration"], **counts)
        except KeyboardInterrupt:
            status = "interrupted"
        except Exception as exc:
            from trianflow_vo.pipeline import failure_reason

            status, error = "failed", failure_reason(exc)
            raise
        finally:
            with _deferred_signals():
                if status != "failed":
                    ckpt = save(it)
                if csv_log is not None:
                    csv_log.close()
                if tb is not None:
                    tb.flush()
                    tb.close()
                med = float(np.median(times)) if times else None
                write_status(status=status, error=error, iteration=it, checkpoint_iteration=saved["iteration"],
                             seconds_per_iter_median=med,
                             peak_rss_mb=_peak_rss_mb(), last_terms=last_terms, **counts)
    dist_util.close()
    return TrainResult(status, it, ckpt, last_terms, counts["skipped"], counts["depth_failed"],
                       counts["nonfinite"], float(np.median(times)) if times else None)


class _deferred_signals:
    """Ignore a second Ctrl-C while the final checkpoint is written (the file stays whole anyway)."""

    def __enter__(self):
        import signal
        import threading

        self._saved = {}
        if threading.current_thread() is threading.main_thread():
            for s in (signal.SIGINT, signal.SIGTERM):
                self._saved[s] = signal.signal(s, signal.SIG_IGN)
        return self

    def __exit__(self, *exc):
        import signal

        for s, h in self._saved.items():
            signal.signal(s, h)
