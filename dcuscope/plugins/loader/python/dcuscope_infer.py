"""Plugin-loader entry for the infer element: gst-launch-1.0 finds it here."""
from dcuscope.plugins.loading import same_sys_path

with same_sys_path():  # the loader keeps a pointer to sys.path, which cv2 replaces: see plugins.loading
    from dcuscope.plugins.infer import __gstelementfactory__  # noqa: F401
