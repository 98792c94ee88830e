"""The parts of dcuscope that an install may lack: the [pipeline] extra (pyproject.toml).

A DCU that only traces someone else's app and ships its trace installs ``dcuscope`` alone, in
seconds; the commands that run dcuscope's own pipelines (the elements' image work in OpenCV, the
detector in ONNX Runtime) say what to install instead of failing on an import.
"""

from __future__ import annotations

import importlib.util

from dcuscope.core.errors import DcuscopeError

PIPELINE = {"cv2": "opencv-python-headless", "onnxruntime": "onnxruntime"}
"""Module -> the PyPI package of the [pipeline] extra that provides it."""


def require_pipeline(command: str) -> None:
    """Raise DcuscopeError naming the extra when a module of :data:`PIPELINE` cannot be imported."""
    missing = [package for module, package in PIPELINE.items() if importlib.util.find_spec(module) is None]
    if missing:
        raise DcuscopeError(f"dcuscope {command} runs pipelines and needs {' and '.join(missing)}, which this "
                            "install lacks: pip install 'dcuscope[pipeline]' (without it: trace, ship, stats, "
                            "export, compare of traces and the relay)")
