"""``trianflow-vo eval-depth``: a depth network against ground-truth depth (KITTI/Eigen metrics).

Parses options, runs the network over the images (:mod:`trianflow_vo.predict`), hands
ground truth and predictions to :mod:`trianflow_vo.eval.depth_metrics`, prints the
table and writes the files. numpy, OpenCV and onnxruntime are imported inside the
command, so ``--help`` stays instant.
"""

from __future__ import annotations

import sys
from pathlib import Path

import click

from trianflow_vo.cli.errors import user_errors
from trianflow_vo.cli.predict_cmd import ArgumentError, _Bar

#: the choices of --crop (the same as trianflow_vo.eval.depth_metrics.CROPS; not imported here
#: to keep --help fast)
CROP_CHOICES = ("garg", "eigen", "none")
METRICS_JSON = "depth_metrics.json"
PER_IMAGE_CSV = "depth_per_image.csv"


@click.command(
    "eval-depth",
    context_settings={"help_option_names": ["-h", "--help"]},
    epilog="""\b
Ground truth (--gt-depth):
  FOLDER        per image STEM.png (KITTI depth PNG: uint16, metres = value/256,
                0 = none) or STEM.npy (float HxW metres), STEM = the image's stem
  FILE.npz      one stack, key 'data' (or its only array): (N, H, W) maps, map i
                = image i in order (gt_depths.npz of the Eigen-split export
                scripts; maps of several sizes are an object array: --allow-pickle)
  FILE.npy      the same as one array (or one HxW map for one image)
\b
Protocol per image (monodepth2 / TrianFlow authors): prediction resized to the
ground truth's size (bilinear); pixels with ground truth in (min, max) inside
the crop; prediction x median(gt)/median(pred) (unless --no-median-scaling);
clamped to [min, max]; abs rel, sq rel, RMSE, RMSE log, d<1.25, d<1.25^2,
d<1.25^3; then the mean over images. Crop: garg (Garg et al. ECCV16, what
monodepth2 and the authors use on the Eigen split), eigen (Eigen et al. NIPS14),
none.
\b
With --out DIR: depth_metrics.json (means, scaling ratios, settings, model) and
depth_per_image.csv (one row per image).
\b
Examples:
  trianflow-vo eval-depth --depth-model depth.onnx eigen_test/ --gt-depth gt_depths.npz --allow-pickle
  trianflow-vo eval-depth --depth-model depth.onnx frames/ --gt-depth proj_depth/ --out eval/
""",
)
@click.argument("inputs", nargs=-1, required=True, metavar="IMAGES...", type=click.Path(path_type=Path))
@click.option("--depth-model", required=True, type=click.Path(path_type=Path),
              help="ONNX depth network (from `trianflow-vo export`).")
@click.option("--gt-depth", "gt_depth", required=True, type=click.Path(path_type=Path),
              help="Ground-truth depth: a folder of STEM.png/STEM.npy, or an .npz/.npy stack in image order.")
@click.option("--out", "out_dir", type=click.Path(path_type=Path), default=None,
              help=f"Write {METRICS_JSON} and {PER_IMAGE_CSV} into this folder (created if needed).")
@click.option("--min-depth", type=click.FloatRange(min=0.0, min_open=True), default=1e-3, show_default=True,
              help="Ground truth used above this depth (m); the prediction is clamped to it.")
@click.option("--max-depth", type=click.FloatRange(min=0.0, min_open=True), default=80.0, show_default=True,
              help="Ground truth used below this depth (m); the prediction is clamped to it.")
@click.option("--crop", type=click.Choice(CROP_CHOICES), default="garg", show_default=True,
              help="Evaluation crop of the ground truth.")
@click.option("--no-median-scaling", is_flag=True,
              help="Compare the network's depth as it is (no per-image median scaling).")
@click.option("--allow-pickle", is_flag=True,
              help="Let an .npz/.npy ground truth holding an object array be unpickled (trusted files only).")
@click.option("--threads", type=click.IntRange(1, 64), default=2, show_default=True,
              help="CPU threads of onnxruntime.")
@click.option("-q", "--quiet", is_flag=True, help="No progress on stderr.")
def eval_depth(inputs, depth_model, gt_depth, out_dir, min_depth, max_depth, crop, no_median_scaling,
               allow_pickle, threads, quiet):
    """Evaluate a depth network against ground-truth depth (KITTI/Eigen metrics).

    IMAGES... are image files and/or folders of images (read in natural order:
    img2 before img10). Prints the metrics; every error is one line naming the file.
    """
    if min_depth >= max_depth:
        raise ArgumentError(f"--min-depth ({min_depth:g}) must be below --max-depth ({max_depth:g})")
    with user_errors():
        import json

        from trianflow_vo import predict as P
        from trianflow_vo.errors import InputError
        from trianflow_vo.eval.depth_metrics import depth_csv, evaluate_depth, format_depth_report
        from trianflow_vo.io.atomic import write_atomic
        from trianflow_vo.io.depth_png import open_gt_depth
        from trianflow_vo.io.sequence import decode_image
        from trianflow_vo.nets.onnx_runtime import OnnxModel

        images = P.collect_images(inputs)
        gts = open_gt_depth(gt_depth, images, allow_pickle=allow_pickle)
        model = OnnxModel(depth_model, "depth", threads)  # validated before any work
        if out_dir is not None:
            P.prepare_out_dir(out_dir)
        bar = None if quiet else _Bar("depth", sys.stderr.isatty())

        def pairs():
            for path, (_source, load) in zip(images, gts):
                image, reason = decode_image(path)
                if image is None:
                    raise InputError(reason, path)
                pred = P.run_depth(model, image)
                yield load(), pred

        report = evaluate_depth(
            pairs(), [str(p) for p in images], sources=[s for s, _ in gts], min_depth=min_depth,
            max_depth=max_depth, crop=crop, median_scaling=not no_median_scaling,
            progress=(lambda done, name: bar(done, len(images), Path(name).name)) if bar else None)
        click.echo(format_depth_report(report))
        if out_dir is not None:
            summary = {**report.to_dict(), "model": model.describe(), "gt": str(gt_depth),
                       "per_image": PER_IMAGE_CSV}
            write_atomic(Path(out_dir) / PER_IMAGE_CSV, depth_csv(report).encode("utf-8"))
            write_atomic(Path(out_dir) / METRICS_JSON, (json.dumps(summary, indent=2) + "\n").encode("utf-8"))
            click.echo(f"wrote {Path(out_dir) / METRICS_JSON} and {PER_IMAGE_CSV}")
