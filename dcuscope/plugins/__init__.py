"""dcuscope's GStreamer elements, one per module, registered in-process by :func:`register`.

``gst-launch-1.0`` finds them through the Python plugin loader: see ``plugins/loader``.
GStreamer is imported by :func:`register` and the element modules, not here, so that the
logic modules (``detection``, ``models``, ``tiling``, ...) load where GStreamer is absent.
"""

import importlib

ELEMENT_MODULES = ("framestamp", "mux", "infer", "tiler", "convert", "osd")

_registered = False


def register() -> None:
    """Register every element with GStreamer for this process (idempotent)."""
    global _registered
    if _registered:
        return
    from dcuscope.core.gst import Gst

    for name in ELEMENT_MODULES:
        module = importlib.import_module(f"dcuscope.plugins.{name}")
        factory, rank, cls = module.__gstelementfactory__
        if Gst.ElementFactory.find(factory) is None:
            Gst.Element.register(None, factory, rank, cls.__gtype__)
    _registered = True
