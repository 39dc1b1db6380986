"""The ``trianflow-vo`` click group.

Subcommands live in their own modules and are imported lazily, so ``--help`` and
every command start fast (no onnxruntime, torch or rerun import at start-up).
"""

from __future__ import annotations

import importlib

import click

from trianflow_vo import __version__

_COMMANDS = {
    "run": ("trianflow_vo.cli.run_cmd", "run", "Estimate a camera trajectory from a sequence (KITTI, TUM, images, video)."),
    "eval": ("trianflow_vo.cli.eval_cmd", "eval_cmd", "Evaluate a trajectory against ground truth (KITTI t_err/r_err, ATE, RPE)."),
    "export": ("trianflow_vo.cli.export_cmd", "export", "Export flow and depth networks to ONNX."),
    "view": ("trianflow_vo.cli.view_cmd", "view", "Open a Rerun recording (.rrd) in the viewer."),
    "predict": ("trianflow_vo.cli.predict_cmd", "predict", "Predict depth and/or optical flow of images with exported networks."),
    "train": ("trianflow_vo.cli.train_cmd", "train", "Train the flow and depth networks self-supervised (TrianFlow's three stages)."),
    "eval-depth": ("trianflow_vo.cli.eval_depth_cmd", "eval_depth", "Evaluate a depth network against ground-truth depth (KITTI/Eigen metrics)."),
    "eval-flow": ("trianflow_vo.cli.eval_flow_cmd", "eval_flow", "Evaluate a flow network against ground-truth flow (EPE, Fl-all)."),
    "batch": ("trianflow_vo.cli.batch_cmd", "batch", "Run many sequences at once on Ray (local or a cluster)."),
}


class LazyGroup(click.Group):
    def list_commands(self, ctx):
        return list(_COMMANDS)

    def get_command(self, ctx, name):
        if name not in _COMMANDS:
            return None
        module, attr, _ = _COMMANDS[name]
        return getattr(importlib.import_module(module), attr)

    def format_commands(self, ctx, formatter):
        rows = [(name, help_) for name, (_, _, help_) in _COMMANDS.items()]
        with formatter.section("Commands"):
            formatter.write_dl(rows)


@click.group(cls=LazyGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="trianflow-vo")
def main():
    """Monocular visual odometry from dense optical flow and two-view geometry (TrianFlow)."""


if __name__ == "__main__":
    main()
