"""Plugin-loader entry for the tiler element: gst-launch-1.0 finds it here."""
from plugins.tiler import __gstelementfactory__  # noqa: F401
