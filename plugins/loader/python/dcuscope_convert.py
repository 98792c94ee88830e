"""Plugin-loader entry for the convert element: gst-launch-1.0 finds it here."""
from plugins.convert import __gstelementfactory__  # noqa: F401
