"""Plugin-loader entry for the infer element: gst-launch-1.0 finds it here."""
from plugins.infer import __gstelementfactory__  # noqa: F401
