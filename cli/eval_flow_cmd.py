"""``trianflow-vo eval-flow``: a flow network against ground-truth flow (EPE, Fl-all).

Parses options, finds the image pairs and their ground truth
(:mod:`trianflow_vo.io.kitti_flow`), runs the network (:mod:`trianflow_vo.predict`),
hands ground truth and predictions to :mod:`trianflow_vo.eval.flow_metrics`, prints the
table and writes the files. numpy, OpenCV and onnxruntime are imported inside the
command, so ``--help`` stays instant.
"""

from __future__ import annotations

import sys
from pathlib import Path

import click

from trianflow_vo.cli.errors import user_errors
from trianflow_vo.cli.predict_cmd import ArgumentError, _Bar

METRICS_JSON = "flow_metrics.json"
PER_PAIR_CSV = "flow_per_pair.csv"


@click.command(
    "eval-flow",
    context_settings={"help_option_names": ["-h", "--help"]},
    epilog="""\b
PAIRS:
  FOLDER     the KITTI flow layout: image_2/NNNNNN_10.png + NNNNNN_11.png (or
             colored_0/, image_0/ for KITTI 2012), ground truth flow_occ/ (all
             pixels, the default) or flow_noc/ (non-occluded pixels) or
             --gt-flow DIR; ground truth named NNNNNN_10.png (KITTI flow PNG:
             uint16 RGB, flow = (value - 2^15) / 64, B = valid) or NNNNNN_10.flo
  LIST.txt   one 'image1 image2 ground_truth' line per pair (paths relative to
             the list; ground truth .png KITTI or .flo Middlebury)
\b
The flow at the network's input size is resized (bilinear) to the ground truth's
size and its values scaled by the size ratio. EPE = mean end-point error over
the valid pixels; Fl-all = % of valid pixels with EPE > 3 px and > 5% of |gt|.
Both are given averaged over pairs (per pair, then the mean: the TrianFlow
authors) and over all valid pixels of all pairs (the KITTI 2015 devkit's Fl-all).
\b
With --out DIR: flow_metrics.json and flow_per_pair.csv (one row per pair).
\b
Examples:
  trianflow-vo eval-flow --flow-model flow.onnx data_scene_flow/training
  trianflow-vo eval-flow --flow-model flow.onnx data_scene_flow/training \\
                         --gt-flow data_scene_flow/training/flow_noc --out eval/
  trianflow-vo eval-flow --flow-model flow.onnx pairs.txt
""",
)
@click.argument("pairs", metavar="PAIRS", type=click.Path(path_type=Path))
@click.option("--flow-model", required=True, type=click.Path(path_type=Path),
              help="ONNX flow network (from `trianflow-vo export`).")
@click.option("--gt-flow", "gt_flow", type=click.Path(path_type=Path), default=None,
              help="Folder of ground-truth flow files named like the first image (KITTI folder only; "
                   "default: flow_occ/, else flow_noc/ beside the images).")
@click.option("--out", "out_dir", type=click.Path(path_type=Path), default=None,
              help=f"Write {METRICS_JSON} and {PER_PAIR_CSV} into this folder (created if needed).")
@click.option("--threads", type=click.IntRange(1, 64), default=2, show_default=True,
              help="CPU threads of onnxruntime.")
@click.option("-q", "--quiet", is_flag=True, help="No progress on stderr.")
def eval_flow(pairs, flow_model, gt_flow, out_dir, threads, quiet):
    """Evaluate a flow network against ground-truth flow (EPE, Fl-all).

    PAIRS is a KITTI flow folder or a list file of 'image1 image2 ground_truth'
    lines. Prints the metrics; every error is one line naming the file.
    """
    if gt_flow is not None and Path(pairs).is_file():
        raise ArgumentError("--gt-flow is for a KITTI folder; a list file names the ground truth on each line")
    with user_errors():
        import json

        from trianflow_vo import predict as P
        from trianflow_vo.errors import InputError
        from trianflow_vo.eval.flow_metrics import evaluate_flow, flow_csv, format_flow_report
        from trianflow_vo.io.atomic import write_atomic
        from trianflow_vo.io.kitti_flow import kitti_flow_pairs, read_flow_file, read_pair_list
        from trianflow_vo.io.sequence import decode_image
        from trianflow_vo.nets.onnx_runtime import OnnxModel

        if Path(pairs).is_dir():
            pair_list, gt_dir = kitti_flow_pairs(pairs, gt_flow)
            gt_desc = str(gt_dir)
        elif Path(pairs).is_file():
            pair_list = read_pair_list(pairs)
            gt_desc = f"listed in {pairs}"
        else:
            raise InputError("no such file or folder", pairs)
        model = OnnxModel(flow_model, "flow", threads)  # validated before any work
        if out_dir is not None:
            P.prepare_out_dir(out_dir)
        bar = None if quiet else _Bar("flow", sys.stderr.isatty())

        def graph_input(path):
            image, reason = decode_image(path)
            if image is None:
                raise InputError(reason, path)
            return model.to_input(image)

        def triples():
            for pair in pair_list:
                pred = P.run_flow(model, graph_input(pair.image1), graph_input(pair.image2))
                gt, valid = read_flow_file(pair.gt)
                yield gt, valid, pred

        report = evaluate_flow(
            triples(), [str(p.image1) for p in pair_list], sources=[str(p.gt) for p in pair_list],
            progress=(lambda done, name: bar(done, len(pair_list), Path(name).name)) if bar else None)
        click.echo(format_flow_report(report))
        if out_dir is not None:
            summary = {**report.to_dict(), "model": model.describe(), "gt": gt_desc, "per_pair": PER_PAIR_CSV}
            write_atomic(Path(out_dir) / PER_PAIR_CSV, flow_csv(report).encode("utf-8"))
            write_atomic(Path(out_dir) / METRICS_JSON, (json.dumps(summary, indent=2) + "\n").encode("utf-8"))
            click.echo(f"wrote {Path(out_dir) / METRICS_JSON} and {PER_PAIR_CSV}")
