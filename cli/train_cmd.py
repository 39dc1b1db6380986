"""``trianflow-vo train``: self-supervised training of one TrianFlow stage."""

from __future__ import annotations

import sys
from pathlib import Path

import click

from trianflow_vo.cli.errors import BadConfig, user_errors
from trianflow_vo.cli.run_cmd import _hms, _parse_intrinsics

# shortcut flag -> configuration key (a flag given on the command line wins over --config and --set)
SHORTCUTS = {
    "iters": "optim.iters", "batch": "optim.batch", "size": "data.size", "device": "runtime.device",
    "workers": "data.workers", "seed": "runtime.seed", "flow_source": "model.flow_source",
}
MAIN_TERMS = 3  # loss terms shown on the progress line besides the total


class TrainProgress:
    """One status line on stderr: iteration, seconds per iteration, ETA, total and the main loss terms."""

    def __init__(self, enabled: bool):
        self.tty = enabled and sys.stderr.isatty()
        self.plain = enabled and not self.tty
        self._last_plain = -1

    def __call__(self, info: dict) -> None:
        it, total, start = info["iteration"], info["total"], info["start"]
        sec = info["seconds"]
        terms = info["terms"]
        text = f"{it}/{total} it  {sec:.2f} s/it  ETA {_hms(sec * (total - it))}"
        if "total" in terms:
            text += f"  loss {terms['total']:.4g}"
        main = sorted(((k, v) for k, v in terms.items() if k != "total"), key=lambda kv: -abs(kv[1]))[:MAIN_TERMS]
        text += "".join(f"  {k} {v:.3g}" for k, v in main)
        for k in ("skipped", "depth_failed", "nonfinite"):
            if info.get(k):
                text += f"  {k} {info[k]}"
        if self.tty:
            frac = (it - start) / max(total - start, 1)
            bar = "#" * int(24 * frac) + "-" * (24 - int(24 * frac))
            click.echo(f"\r[{bar}] {text}\x1b[K", nl=False, err=True)
        elif self.plain and (it == total or it - self._last_plain >= max(1, (total - start) // 20)):
            click.echo(text, err=True)
            self._last_plain = it

    def close(self) -> None:
        if self.tty:
            click.echo("", err=True)


def build_train_config(stage: str, config_file: str | None, overrides: tuple[str, ...], shortcuts: dict,
                       resume_config: dict | None = None):
    """Defaults/preset < --config < --set < flags; with ``resume_config`` (the checkpoint's) as the base."""
    from trianflow_vo.config import apply_overrides, merge_dict
    from trianflow_vo.train.config import TrainConfig, load_train_config

    if resume_config is not None:
        cfg = merge_dict(TrainConfig(), resume_config, "the checkpoint's configuration")
    else:
        cfg = load_train_config(config_file, stage)
    cfg = apply_overrides(cfg, list(overrides))
    flags = {}
    for name, key in SHORTCUTS.items():
        v = shortcuts.get(name)
        if v is not None:
            section, k = key.split(".")
            flags.setdefault(section, {})[k] = list(v) if isinstance(v, tuple) else v
    if flags:
        cfg = merge_dict(cfg, flags, "command line")
    return cfg


def _parse_size(ctx, param, value):
    if value is None:
        return None
    try:
        h, w = (int(v) for v in value.lower().split("x"))
    except ValueError:
        raise click.BadParameter(f"{value!r} is not HxW, e.g. 128x416") from None
    return (h, w)


@click.command("train", context_settings={"help_option_names": ["-h", "--help"]})
@click.argument("data", nargs=-1, required=True, type=click.Path(path_type=Path))
@click.option("--stage", type=click.Choice(["flow", "depth", "joint"]), required=True,
              help="flow: the flow net alone; depth: flow net frozen (from --init), depth net trained by "
                   "triangulation; joint: both (from --init).")
@click.option("--out", "out_dir", type=click.Path(path_type=Path), required=True,
              help="Output folder: checkpoint.pt, metrics.csv, tb/, config.yaml, train.json.")
@click.option("--config", "config_file", default=None,
              help="YAML file or preset: kitti, kitti_odometry, nyu (the authors' settings for this stage; "
                   "default kitti).")
@click.option("--set", "overrides", multiple=True, metavar="KEY=VALUE",
              help="Override one configuration key, e.g. --set losses.w_geo=0.1 (repeatable).")
@click.option("--init", "init", type=click.Path(path_type=Path), default=None,
              help="Start from a checkpoint: ours (e.g. the previous stage's checkpoint.pt) or the authors' .pth.")
@click.option("--resume", is_flag=True, help="Continue the run in --out from its checkpoint.pt.")
@click.option("--iters", type=int, default=None, help="Iterations of the stage [optim.iters].")
@click.option("--batch", type=int, default=None, help="Pairs per iteration over all processes [optim.batch].")
@click.option("--size", callback=_parse_size, default=None, metavar="HxW",
              help="Training size, multiples of 64 [data.size].")
@click.option("--device", type=click.Choice(["auto", "cpu", "cuda"]), default=None, help="[runtime.device]")
@click.option("--workers", type=int, default=None, help="Data-loader processes per training process [data.workers].")
@click.option("--seed", type=int, default=None, help="[runtime.seed]")
@click.option("--val", "val", multiple=True, type=click.Path(path_type=Path),
              help="Validation data (repeatable); with ground-truth poses the odometry's ATE is reported too.")
@click.option("--flow-source", type=click.Choice(["net", "dis"]), default=None,
              help="Stage depth: frozen flow net (the paper) or OpenCV DIS (our CPU option) [model.flow_source].")
@click.option("--intrinsics", callback=_parse_intrinsics, default=None, metavar="FX,FY,CX,CY",
              help="Camera intrinsics for image folders and videos without a calibration file.")
@click.option("--calib", type=click.Path(path_type=Path), default=None, help="Calibration file for the data.")
@click.option("--trust-checkpoint", is_flag=True,
              help="Allow --init files that need torch.load(weights_only=False) (runs pickled code).")
@click.option("-q", "--quiet", is_flag=True, help="No progress line.")
def train(data, stage, out_dir, config_file, overrides, init, resume, val, intrinsics, calib, trust_checkpoint,
          quiet, **shortcuts):
    """Train one stage of TrianFlow on DATA (KITTI raw drives, KITTI odometry sequences, TUM RGB-D folders,
    image folders with intrinsics, videos).

    \b
    The three stages, each its own run:
      trianflow-vo train --stage flow  DATA --out runs/flow
      trianflow-vo train --stage depth DATA --out runs/depth --init runs/flow/checkpoint.pt
      trianflow-vo train --stage joint DATA --out runs/joint --init runs/depth/checkpoint.pt
    Several processes (DDP): torchrun --nproc_per_node 2 --no-python trianflow-vo train ...
    Export the networks: trianflow-vo export --checkpoint runs/joint/checkpoint.pt --out-dir models
    """
    import logging

    from trianflow_vo.cli.logs import setup_logging
    from trianflow_vo.train.distributed import world_from_env

    world = world_from_env()
    setup_logging(-1 if quiet or not world.is_main else 0)
    log = logging.getLogger("trianflow_vo.train")
    with user_errors():
        resume_config = None
        if resume:
            if config_file is not None:
                raise BadConfig("--config cannot change a run being resumed: it keeps its own configuration "
                                "(use --set or the flags to change e.g. --iters)")
            from trianflow_vo.train.checkpointing import CHECKPOINT_NAME, read_training_state

            ck = out_dir / CHECKPOINT_NAME
            if ck.is_file():
                resume_config = read_training_state(ck)[1].config
        cfg = build_train_config(stage, config_file, overrides, shortcuts, resume_config)
        if resume_config is not None and cfg.model.stage != stage:
            from trianflow_vo.errors import ModelError

            raise ModelError(f"{out_dir / 'checkpoint.pt'}: a checkpoint of stage '{cfg.model.stage}', not "
                             f"'{stage}': resume it with --stage {cfg.model.stage}")
        from trianflow_vo.train.loop import TrainRequest, prepare, train as run_training

        req = TrainRequest(data=list(data), out_dir=out_dir, config=cfg, init=init, resume=resume, val=list(val),
                           intrinsics=intrinsics, calib=calib, trust_checkpoint=trust_checkpoint,
                           command=" ".join(["trianflow-vo", *sys.argv[1:]]))
        prep = prepare(req)
        progress = TrainProgress(enabled=not quiet and world.is_main)
        try:
            result = run_training(prep, world, on_progress=progress)
        finally:
            progress.close()
    if world.is_main:
        terms = result.last_terms
        loss = f", loss {terms['total']:.4g}" if "total" in terms else ""
        line = (f"{result.status}: stage {stage}, iteration {result.iteration}{loss}; "
                f"checkpoint {result.checkpoint}")
        if result.skipped or result.depth_failed or result.nonfinite:
            line += (f" (skipped samples {result.skipped}, batches with depth terms zeroed {result.depth_failed}, "
                     f"non-finite steps {result.nonfinite})")
        log.info(line) if quiet else click.echo(line, err=True)
    if result.status == "interrupted":
        sys.exit(130)
