"""Trajectory evaluation: KITTI segment metric (t_err, r_err), ATE, RPE after alignment.

Public entry points:

- :func:`evaluate` -- arrays in, metrics dict out.
- :func:`evaluate_files` -- run folder / trajectory file + ground-truth file in.
- :func:`align_trajectory` -- the prediction aligned onto the ground truth exactly as
  eval aligns it, for drawing.

Only numpy is imported here; plotting (matplotlib) lives in :mod:`vo.eval.plot`.
"""

from trianflow_vo.eval.align import ALIGN_MODES, align_trajectory, umeyama
from trianflow_vo.eval.associate import match_frames, match_timestamps
from trianflow_vo.eval.evaluate import EvalResult, evaluate, evaluate_associated, evaluate_files
from trianflow_vo.eval.loader import associate, find_latest_run, load_ground_truth, load_prediction
from trianflow_vo.eval.segments import DEFAULT_LENGTHS, DEFAULT_STEP

__all__ = [
    "ALIGN_MODES",
    "DEFAULT_LENGTHS",
    "DEFAULT_STEP",
    "EvalResult",
    "align_trajectory",
    "associate",
    "evaluate",
    "evaluate_associated",
    "evaluate_files",
    "find_latest_run",
    "load_ground_truth",
    "load_prediction",
    "match_frames",
    "match_timestamps",
    "umeyama",
]
