"""trianflow-vo: monocular visual odometry from dense flow and two-view geometry.

The library is usable without click: see :func:`vo.pipeline.run_sequence`.
"""

__version__ = "0.1.0"
