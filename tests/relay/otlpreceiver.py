"""A real OTLP/HTTP trace receiver on 127.0.0.1 for tests: POST /v1/traces, protobuf (gzip or not),
decoded with the official definitions (``opentelemetry-proto``'s ExportTraceServiceRequest).

``mode``: ``ok`` answers 200 with an empty ExportTraceServiceResponse; ``stall`` holds every
request unanswered until the receiver stops (a backend that hangs); ``fail`` answers 500. Each
span received is kept as a flat :class:`Span` with its resource's attributes. ``tls``: a server
certificate of tests/tlscerts.py: the receiver takes HTTPS only (a collector with TLS on).
"""

from __future__ import annotations

import gzip
import ssl
import threading
from dataclasses import dataclass
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

from opentelemetry.proto.collector.trace.v1.trace_service_pb2 import (ExportTraceServiceRequest,
                                                                       ExportTraceServiceResponse)
from opentelemetry.proto.common.v1.common_pb2 import AnyValue

PATH = "/v1/traces"


@dataclass(frozen=True)
class Span:
    trace_id: bytes
    span_id: bytes
    parent_id: bytes
    name: str
    start: int
    end: int
    attributes: dict
    resource: dict
    scope: str


def value_of(v: AnyValue):
    kind = v.WhichOneof("value")
    return getattr(v, kind) if kind else None


class OtlpReceiver:
    def __init__(self, mode: str = "ok", tls=None) -> None:
        self.mode = mode
        self.tls = tls
        self.spans: list[Span] = []
        self.requests = 0
        self.gzipped = 0
        self.refused: list[str] = []
        """Requests it could not take (wrong path or content type, undecodable body)."""
        self._lock = threading.Lock()
        self._release = threading.Event()
        self._server = ThreadingHTTPServer(("127.0.0.1", 0), self._handler())
        self._server.daemon_threads = True
        if tls is not None:
            context = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
            context.load_cert_chain(tls.cert, tls.key)
            # A client that refuses the certificate fails its handshake in accept(): socketserver drops it.
            self._server.socket = context.wrap_socket(self._server.socket, server_side=True)
        self._thread = threading.Thread(target=self._server.serve_forever, daemon=True)

    @property
    def url(self) -> str:
        return f"{'https' if self.tls else 'http'}://127.0.0.1:{self._server.server_port}{PATH}"

    def __enter__(self) -> OtlpReceiver:
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._release.set()
        self._server.shutdown()
        self._server.server_close()

    def take(self, body: bytes, encoding: str) -> None:
        if encoding == "gzip":
            body = gzip.decompress(body)
        request = ExportTraceServiceRequest.FromString(body)
        got = []
        for rs in request.resource_spans:
            resource = {a.key: value_of(a.value) for a in rs.resource.attributes}
            for ss in rs.scope_spans:
                for s in ss.spans:
                    got.append(Span(s.trace_id, s.span_id, s.parent_span_id, s.name, s.start_time_unix_nano,
                                    s.end_time_unix_nano, {a.key: value_of(a.value) for a in s.attributes}, resource,
                                    ss.scope.name))
        with self._lock:
            self.requests += 1
            self.gzipped += encoding == "gzip"
            self.spans.extend(got)

    def _handler(self) -> type[BaseHTTPRequestHandler]:
        receiver = self

        class Handler(BaseHTTPRequestHandler):
            def do_POST(self) -> None:  # noqa: N802 - http.server's name
                body = self.rfile.read(int(self.headers.get("Content-Length", 0)))
                if receiver.mode == "stall":
                    receiver._release.wait()
                    return
                if self.path != PATH or self.headers.get("Content-Type") != "application/x-protobuf":
                    receiver.refused.append(f"{self.path} {self.headers.get('Content-Type')}")
                    return self._answer(404 if self.path != PATH else 415, b"")
                if receiver.mode == "fail":
                    return self._answer(500, b"")
                try:
                    receiver.take(body, self.headers.get("Content-Encoding", ""))
                except Exception as exc:  # noqa: BLE001 - reported to the test, answered 400
                    receiver.refused.append(repr(exc))
                    return self._answer(400, b"")
                self._answer(200, ExportTraceServiceResponse().SerializeToString())

            def _answer(self, status: int, body: bytes) -> None:
                self.send_response(status)
                self.send_header("Content-Type", "application/x-protobuf")
                self.send_header("Content-Length", str(len(body)))
                self.end_headers()
                self.wfile.write(body)

            def log_message(self, *args) -> None:
                pass

        return Handler
