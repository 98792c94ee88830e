"""Plugin-loader entry for the framestamp element: gst-launch-1.0 finds it here."""
from plugins.framestamp import __gstelementfactory__  # noqa: F401
