"""``dcuscope plugin-path``: the folder of dcuscope's GStreamer plugin (the tracer), for GST_PLUGIN_PATH."""

from __future__ import annotations

import argparse
import sys

PLUGIN_EPILOG = """\
example:
  GST_PLUGIN_PATH="$(dcuscope plugin-path)" \\
  GST_TRACERS="dcuscope(node=DCU-1,trace=dcu1.trace.jsonl)" \\
  gst-launch-1.0 videotestsrc num-buffers=300 ! videoconvert ! x264enc ! fakesink
  dcuscope stats dcu1.trace.jsonl

tracer parameters: node (default: the host name), trace (default: NODE.trace.jsonl),
clock (realtime, monotonic or tai; default realtime), capacity (ring size in events).
"""



def add_plugin_path_parser(sub) -> None:
    plugin = sub.add_parser(
        "plugin-path", help="print the folder of dcuscope's GStreamer plugin (the dcuscope tracer), building it if needed",
        description="Print the folder that holds dcuscope's GStreamer plugin, for GST_PLUGIN_PATH: with it any "
                    "GStreamer application, unchanged, is traced per frame by GST_TRACERS=dcuscope.",
        epilog=PLUGIN_EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    plugin.set_defaults(func=_plugin_path)


def _plugin_path(args: argparse.Namespace) -> int:
    from dcuscope.probes.capture.native import BuildError, build

    try:
        print(build().parent)
    except BuildError as exc:
        print(f"dcuscope: error: no GStreamer plugin: {exc}", file=sys.stderr)
        return 1
    return 0
