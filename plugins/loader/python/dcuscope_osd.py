"""Plugin-loader entry for the osd element: gst-launch-1.0 finds it here."""
from plugins.osd import __gstelementfactory__  # noqa: F401
