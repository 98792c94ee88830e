"""What ``dcuscope relay --otlp URL [--otlp-every N] [--otlp-queue N] [--otlp-timeout S] [--otlp-ca FILE]`` asks for.

Kept apart from the exporter (:mod:`dcuscope.relay.export.otlp`) so that the command line checks its values
without loading the OpenTelemetry SDK.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from urllib.parse import urlsplit

from dcuscope.relay.errors import RelayError

TRACES_PATH = "/v1/traces"
"""OTLP/HTTP's path for traces, added to a URL that names none (``http://collector:4318``)."""
DEFAULT_EVERY = 100
DEFAULT_QUEUE = 2048
DEFAULT_TIMEOUT_S = 10.0
MAX_QUEUE = 1_000_000
"""Frames waiting at most: ~1 KB each with 8 stages, so 1 GB; more is a typo."""
MAX_TIMEOUT_S = 600.0


@dataclass(frozen=True)
class OtlpConfig:
    url: str
    """The OTLP/HTTP traces endpoint (protobuf), e.g. http://127.0.0.1:4318/v1/traces."""
    every: int = DEFAULT_EVERY
    """1 in ``every`` complete frames of each node is sent; 0: only frames over their node's limit."""
    queue: int = DEFAULT_QUEUE
    """Frames waiting for export at most; beyond, frames are dropped (and counted), never waited for."""
    timeout_s: float = DEFAULT_TIMEOUT_S
    """How long one export request (with the exporter's retries) may take before its frames count as dropped."""
    ca: str | None = None
    """With an https URL: the CA certificates (PEM) the collector's certificate must come from; None:
    the exporter's default (``OTEL_EXPORTER_OTLP_CERTIFICATE``, ``REQUESTS_CA_BUNDLE``, else certifi's)."""


def otlp_config(url: str, every: int, queue: int, timeout_s: float, has_limit: bool,
                ca: str | None = None) -> OtlpConfig:
    """The checked configuration; RelayError names the option at fault. ``has_limit``: some
    node has a ``--frame-limit`` (without one, ``--otlp-every 0`` would send nothing)."""
    if every < 0:
        raise RelayError(f"--otlp-every must be 0 (only frames over --frame-limit) or more, not {every}")
    if every == 0 and not has_limit:
        raise RelayError("--otlp-every 0 sends only frames over their node's --frame-limit: give a --frame-limit")
    if not 1 <= queue <= MAX_QUEUE:
        raise RelayError(f"--otlp-queue must be 1..{MAX_QUEUE} frames, not {queue}")
    if not (math.isfinite(timeout_s) and 0 < timeout_s <= MAX_TIMEOUT_S):
        raise RelayError(f"--otlp-timeout must be over 0 and at most {MAX_TIMEOUT_S:.0f} s, not {timeout_s}")
    endpoint = traces_endpoint(url)
    if ca is not None:
        if not endpoint.startswith("https:"):
            raise RelayError(f"--otlp-ca checks a collector's certificate: give an https:// --otlp URL, not {url!r}")
        try:
            open(ca, "rb").close()
        except OSError as exc:
            raise RelayError(f"--otlp-ca {ca}: {exc.strerror}") from None
    return OtlpConfig(endpoint, every, queue, timeout_s, ca)


def traces_endpoint(url: str) -> str:
    """``url`` as the exporter posts to: an http(s) URL with a host; no path means OTLP's /v1/traces."""
    try:
        parts = urlsplit(url)
        port = parts.port  # raises on a port out of range or not a number
    except ValueError as exc:
        raise RelayError(f"--otlp {url!r}: {exc}") from None
    if parts.scheme not in ("http", "https") or not parts.hostname:
        raise RelayError(f"--otlp {url!r}: give an OTLP/HTTP URL, e.g. http://127.0.0.1:4318/v1/traces")
    if port == 0:
        raise RelayError(f"--otlp {url!r}: port 0 cannot be connected to")
    if parts.path in ("", "/"):
        return parts._replace(path=TRACES_PATH).geturl()
    return url
