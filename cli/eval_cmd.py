"""``trianflow-vo eval``: parse options, call :mod:`vo.eval`, print and write results."""

from __future__ import annotations

from pathlib import Path

import click

from trianflow_vo.cli.errors import user_errors

_DEFAULT_LENGTHS = "100,200,300,400,500,600,700,800"


def _parse_lengths(ctx, param, value: str) -> list[float]:
    try:
        lengths = [float(x) for x in value.split(",") if x.strip()]
    except ValueError:
        raise click.BadParameter(f"expected comma-separated metres, e.g. 10,20,50; got {value!r}") from None
    if not lengths or any(not (x > 0 and x < float("inf")) for x in lengths):
        raise click.BadParameter(f"lengths must be positive numbers, got {value!r}")
    return sorted(set(lengths))


@click.command(
    "eval",
    context_settings={"help_option_names": ["-h", "--help"]},
    epilog="""\b
Examples:
  trianflow-vo eval --gt data/kitti00/poses.txt --lengths 10,20,30,40,50
  trianflow-vo eval --gt gt_poses/09.txt --pred results/09.txt --json m.json --plot m.png
  trianflow-vo eval --gt gt_poses/09.txt --pred runs/09-stride2 --protocol kitti-odom-eval
""",
)
@click.option("--gt", "gt_path", required=True, type=click.Path(exists=True, dir_okay=False, path_type=Path),
              help="Ground truth: KITTI poses (12 numbers per line, line i = frame i), 13 numbers "
                   "(frame index first) or TUM.")
@click.option("--pred", "pred_path", type=click.Path(path_type=Path), default=None,
              help="Run folder (poses.txt + frames.txt) or trajectory file: KITTI 12 numbers "
                   "(frame indices from a frames.txt beside it, else line i = frame i), 13 numbers "
                   "(frame index first, frames may be missing) or TUM. Default: the latest run under ./runs/.")
@click.option("--align", type=click.Choice(["7dof", "6dof", "scale", "none"]), default="7dof", show_default=True,
              help="Alignment of the prediction onto the ground truth.")
@click.option("--lengths", default=_DEFAULT_LENGTHS, show_default=True, callback=_parse_lengths,
              help="Segment lengths in metres, comma-separated (use e.g. 10,20,...,50 for short clips).")
@click.option("--json", "json_path", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Write all metrics to this JSON file.")
@click.option("--plot", "plot_path", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Write a figure: top view (x-z) of ground truth and aligned prediction, errors per length; "
                   "the format is the suffix's: .png, .jpg/.jpeg, .pdf or .svg.")
@click.option("--max-time-diff", type=click.FloatRange(min=0.0), default=0.02, show_default=True,
              help="TUM-to-TUM association: largest timestamp difference (s).")
@click.option("--protocol", type=click.Choice(["kept-frames", "kitti-odom-eval"]), default="kept-frames",
              show_default=True,
              help="Segment start frames of the KITTI metric: every 10th kept frame (kept-frames), or "
                   "ground-truth frames 0, 10, 20, ... with segments whose first or end frame is not predicted "
                   "dropped (kitti-odom-eval, the common script). The same when every frame is predicted.")
@click.option("--allow-partial", is_flag=True,
              help="Evaluate even when fewer than half of the predicted frames have a ground-truth pose "
                   "(refused by default: the prediction or its frames.txt likely belongs to another sequence).")
def eval_cmd(gt_path, pred_path, align, lengths, json_path, plot_path, max_time_diff, protocol, allow_partial):
    """Evaluate a trajectory against ground truth (KITTI t_err/r_err, ATE, RPE).

    \b
    Protocol:
     1. Keep the frames present in both prediction and ground truth, in frame
        order (by frame index; by timestamp when the ground truth is TUM).
     2. Re-base both to their first common frame (that pose becomes identity).
     3. Align: 7dof (default) = Umeyama with scale on the positions, applied to
        whole poses; 6dof = without scale; scale = least-squares scale only;
        none.
     4. KITTI segment metric, as the KITTI devkit: cumulative distance along the
        ground-truth positions of the kept frames; first frames every 10 kept
        frames; for each length (100..800 m by default) whose end frame exists
        (first frame more than that length further along), the relative-pose
        error between ground-truth and predicted motion over the segment.
        t_err = mean translation error / length (%), r_err = mean rotation
        angle / length (deg/100 m); also per length. --protocol
        kitti-odom-eval starts segments at ground-truth frames 0, 10, 20, ...
        instead and drops those whose first or end frame is not predicted.
     5. ATE (m): position error after the same alignment (RMSE, mean, max).
        RPE between consecutive kept frames: translation (m) and rotation
        (deg), RMSE and mean; rotations are orthonormalised (nearest
        rotation, SVD) first. The segment metric uses them as read.

    When the prediction has a pose for every ground-truth frame, these
    defaults reproduce the published KITTI numbers exactly (and both
    protocols agree); with missing or strided frames use --protocol
    kitti-odom-eval to compare with that script's numbers.
    Predicted frames without ground truth are counted in a warning; fewer
    than half matched is refused unless --allow-partial.
    Sequences shorter than the shortest length have no segment: this is
    reported (with suggested --lengths), the other metrics are still given.
    """
    import json

    from trianflow_vo.eval import evaluate_files, find_latest_run
    from trianflow_vo.eval.report import format_report

    for out in (json_path, plot_path):
        if out is not None and not out.resolve().parent.is_dir():
            raise click.ClickException(f"{out}: cannot write there, {out.parent} is not an existing folder")
    with user_errors():
        if plot_path is not None:
            from trianflow_vo.eval.plot import plot_format

            plot_format(plot_path)  # an unknown suffix is refused before any work
        if pred_path is None:
            pred_path = find_latest_run(Path("runs"))
            click.echo(f"using the latest run: {pred_path}", err=True)
        result = evaluate_files(pred_path, gt_path, align=align, lengths=lengths, max_time_diff=max_time_diff,
                                protocol=protocol, allow_partial=allow_partial)
        for line in result.metrics.get("warnings", ()):
            click.echo(f"warning: {line}", err=True)
        click.echo(format_report(result.metrics))
        if json_path is not None:
            try:
                with open(json_path, "w", encoding="utf-8") as fh:
                    json.dump(result.metrics, fh, indent=2)
                    fh.write("\n")
            except OSError as exc:
                raise click.ClickException(f"{json_path}: cannot write: {exc.strerror or exc}") from None
            click.echo(f"wrote {json_path}")
        if plot_path is not None:
            import warnings

            from trianflow_vo.eval.plot import PlotFallbackWarning, plot_evaluation

            try:
                with warnings.catch_warnings(record=True) as caught:
                    warnings.simplefilter("always", PlotFallbackWarning)
                    plot_evaluation(result, plot_path)
            except OSError as exc:
                raise click.ClickException(f"{plot_path}: cannot write: {exc.strerror or exc}") from None
            for w in caught:  # one line on stderr each (evo's plotting unavailable: drawn without it)
                if issubclass(w.category, PlotFallbackWarning):
                    click.echo(f"warning: {w.message}", err=True)
                else:
                    warnings.showwarning(w.message, w.category, w.filename, w.lineno)
            click.echo(f"wrote {plot_path}")
