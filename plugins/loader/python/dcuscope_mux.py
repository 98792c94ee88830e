"""Plugin-loader entry for the mux element: gst-launch-1.0 finds it here."""
from plugins.mux import __gstelementfactory__  # noqa: F401
