"""Windowed bundle adjustment: the back-end of the weight-free pipeline.

* :mod:`~trianflow_vo.ba.tracks`: pixels of a keyframe followed through the
  forward-backward-consistent flow into the next keyframes (sub-pixel, one id each);
* :mod:`~trianflow_vo.ba.graph`: the projection, reprojection factors and Levenberg-Marquardt
  solve shared by every bundle adjustment (the window here, the benchmark's whole-clip one);
* :mod:`~trianflow_vo.ba.window`: one bundle adjustment of a window of keyframes
  on GTSAM (reprojection factors with a robust kernel, gauge held by the oldest poses);
* :mod:`~trianflow_vo.ba.backend`: :class:`~trianflow_vo.ba.backend.WindowBackend`, the
  :class:`~trianflow_vo.backend.Backend` that runs both on each new keyframe.

GTSAM is imported only when a window is solved, so importing this package is cheap.
"""
