"""What the modules in ``plugins/loader/python`` need to be imported safely by gst-python's loader.

gst-python's plugin loader (``libgstpython.so``, ``gst_python_plugin_load``; GStreamer 1.22 and
still so upstream) fetches ``sys.path`` once, as a *borrowed* pointer
(``PySys_GetObject("path")``), then for each folder of ``GST_PLUGIN_PATH`` inserts
``FOLDER/python`` into that list and imports the ``.py`` files found there, and at the end also
inserts the user's and the system's Python plugin folders. ``import cv2`` rebinds ``sys.path`` to
a copy of itself (OpenCV's bootstrap ends with ``sys.path = save_sys_path``). Importing any of
our elements but framestamp imports cv2, so the list the loader holds is freed under it, and
each of its later ``PyList_Insert`` writes into freed memory: a heap corruption that crashed
``gst-launch-1.0`` much later, e.g. with SIGSEGV inside pymalloc (``PyObject_Malloc``) in the
first inference. A Python plugin folder listed after ours in ``GST_PLUGIN_PATH`` was not even
importable (its folder went into the dead list, not into ``sys.path``).

:func:`same_sys_path` keeps ``sys.path`` the list object it was before an import, so that the
loader's pointer stays valid whatever the imported code does to ``sys.path``.
"""

from __future__ import annotations

import sys
from contextlib import contextmanager
from typing import Iterator


@contextmanager
def same_sys_path() -> Iterator[None]:
    """Whatever the body rebinds ``sys.path`` to, it is the same list object again afterwards,
    holding the new contents."""
    path = sys.path  # our reference also keeps the list alive while the body runs
    try:
        yield
    finally:
        if sys.path is not path:
            path[:] = sys.path
            sys.path = path
