"""``dcuscope serve-rtsp CLIP...``: video files served as live RTSP streams (:mod:`dcuscope.pipeline.rtsp`)."""

from __future__ import annotations

import argparse
from pathlib import Path

from dcuscope.commands.options import positive_int


def add_rtsp_parser(sub) -> None:
    rtsp = sub.add_parser("serve-rtsp", help="serve video files as live RTSP streams on loopback (looped, real time)",
                          description="Serve each CLIP at rtsp://HOST:PORT/camN (N from 0), looped forever, "
                                      "re-encoded as H.264 in real time, until Ctrl-C.")
    rtsp.add_argument("clips", type=Path, nargs="+", metavar="CLIP", help="video files")
    rtsp.add_argument("--host", default="127.0.0.1", help="address to listen on (default 127.0.0.1)")
    rtsp.add_argument("--port", type=int, default=8554, help="RTSP port (default 8554)")
    rtsp.add_argument("--bitrate", type=positive_int, default=2000, help="H.264 bitrate in kbit/s (default 2000)")
    rtsp.set_defaults(func=_serve_rtsp, holds_signals=True)


def _serve_rtsp(args: argparse.Namespace) -> int:
    from dcuscope.pipeline.rtsp import serve

    serve(args.clips, host=args.host, port=args.port, bitrate=args.bitrate, announce=lambda line: print(line, flush=True))
    return 0
