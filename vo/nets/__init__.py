"""Running exported networks: the ONNX metadata schema and the onnxruntime session.

:mod:`trianflow_vo.nets.onnx_runtime` is the one place that knows the ``trianflow.*``
metadata keys (written by :mod:`trianflow_vo.models.export`, read by
:mod:`trianflow_vo.flow.onnx_flow` and :mod:`trianflow_vo.depth.onnx_depth`) and the
onnxruntime session settings. Nothing here imports torch, and onnxruntime is only
imported when a model is opened.
"""
