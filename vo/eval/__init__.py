"""Trajectory evaluation: KITTI segment metric (t_err, r_err), ATE, RPE after alignment.

Public entry points:

- :func:`evaluate` -- arrays in, metrics dict out.
- :func:`evaluate_files` -- run folder / trajectory file + ground-truth file in.
- :func:`align_trajectory` -- the prediction aligned onto the ground truth exactly as
  eval aligns it, for drawing.

- :func:`load_ground_truth` -- the one ground-truth reader (also used by ``run --gt``).

Trajectories are evo's types and evo does the timestamp association, the Umeyama fit and
ATE; the KITTI segment metric, frame-index bookkeeping, re-basing, the scale-only mode,
RPE and the validation of files are ours (see each module for why). evo.core and numpy
are imported here; plotting (matplotlib, ``evo.tools.plot``) lives in :mod:`vo.eval.plot`.
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
