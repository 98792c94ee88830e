"""A pipeline that receives an RTSP stream over UDP for a while, then says what it got.

    python -m tests.pipeline.rtsp_receiver CONFIG SECONDS

Run in another network namespace by the lossy-link test: prints one JSON line with the first
source's counters (:func:`dcuscope.pipeline.sourcestats.source_counters`) and its frames' origins.
"""

from __future__ import annotations

import json
import sys
import time
from dataclasses import asdict

from dcuscope.core.gst import Gst
from dcuscope.pipeline.build import build_pipeline
from dcuscope.pipeline.config import load_config
from dcuscope.pipeline.sourcestats import SourceStats
from dcuscope.plugins.frames import read_frames
from dcuscope import plugins


def receive(config: str, seconds: float) -> dict:
    plugins.register()
    built = build_pipeline(load_config(config))
    source = built.sources[0]
    transports = []

    def udp_only(_decodebin, rtspsrc: Gst.Element) -> None:
        # Loss on TCP would be retransmitted, never seen: the stream must come over UDP.
        Gst.util_set_object_arg(rtspsrc, "protocols", "udp")
        transports.append(rtspsrc.get_property("protocols").value_nicks)

    source.origin.connect("source-setup", udp_only)
    origins = []
    source.stamp.get_static_pad("src").add_probe(
        Gst.PadProbeType.BUFFER, lambda _pad, info: origins.extend(f.origin_ns for f in read_frames(info.get_buffer()))
        or Gst.PadProbeReturn.OK)
    stats = SourceStats(built.pipeline)
    built.pipeline.set_state(Gst.State.PLAYING)
    time.sleep(seconds)
    counters = stats.counters()
    built.pipeline.set_state(Gst.State.NULL)
    stats.close()
    return {"counters": {k: asdict(v) for k, v in counters.items()}, "origins": origins, "transports": transports}


if __name__ == "__main__":
    print(json.dumps(receive(sys.argv[1], float(sys.argv[2]))), flush=True)
