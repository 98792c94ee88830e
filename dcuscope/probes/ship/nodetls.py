"""How a node checks its relays and proves who it is over ``https://`` (``--relay-ca``,
``--relay-cert``, ``--relay-key`` on ``dcuscope run``, ``ship``, ``trace`` and the simulated node).

A relay named ``https://HOST:PORT`` must show a certificate for HOST that the system's CAs, or
``--relay-ca``'s, signed; ``--relay-cert``/``--relay-key`` present this node's certificate to a relay
that asks for one (``dcuscope relay --tls-client-ca``). ``http://`` relays are spoken to in the clear,
as ever. A relay that fails verification, or refuses the node's certificate, is one the node cannot
use: :func:`tls_failure` says why in a few words, and the node moves on to its next relay, keeping its
events (:mod:`dcuscope.probes.ship.failover`). Before connecting, :func:`tls_from_args` says in one line
whether this node's certificate is one such a relay refuses (expired, not valid yet, not for client
authentication: :mod:`dcuscope.probes.ship.certcheck`), which the relay's refusal cannot tell it.
"""

from __future__ import annotations

import argparse
import logging
import ssl
from dataclasses import dataclass

from dcuscope.probes.ship.certcheck import CertificateUnreadable, certificate_problem
from dcuscope.probes.ship.errors import ExportError

log = logging.getLogger(__name__)
_told: set[str] = set()
"""Certificates whose problem this process has said already."""


@dataclass(frozen=True)
class RelayTls:
    ca: str | None = None
    """PEM file of the CAs a relay's certificate must come from (None: the system's)."""
    cert: str | None = None
    """This node's certificate (PEM), for relays that ask for one."""
    key: str | None = None
    """Its private key (PEM; None: in ``cert``)."""

    def context(self) -> ssl.SSLContext:
        """The client context; :class:`ExportError` names the file that cannot be loaded."""
        try:
            context = ssl.create_default_context(cafile=self.ca)
        except (OSError, ssl.SSLError) as exc:
            raise ExportError(f"--relay-ca {self.ca}: {_reason(exc)}") from None
        if self.cert is not None:
            try:
                context.load_cert_chain(self.cert, self.key)
            except (OSError, ssl.SSLError) as exc:
                raise ExportError(f"--relay-cert {self.cert}: {_reason(exc)}") from None
        return context


def add_tls_arguments(parser: argparse.ArgumentParser | argparse._ArgumentGroup) -> None:
    """``--relay-ca``, ``--relay-cert``, ``--relay-key``."""
    parser.add_argument("--relay-ca", metavar="FILE",
                        help="https:// relays must show a certificate these CAs (PEM) signed (default: the system's)")
    parser.add_argument("--relay-cert", metavar="FILE",
                        help="this node's certificate (PEM), for relays that ask nodes for one (--tls-client-ca)")
    parser.add_argument("--relay-key", metavar="FILE", help="the private key of --relay-cert (PEM)")


def tls_from_args(args: argparse.Namespace) -> RelayTls | None:
    """The options of :func:`add_tls_arguments` (None: none given), checked by loading them once."""
    if not (args.relay_ca or args.relay_cert or args.relay_key):
        return None
    if args.relay_key and not args.relay_cert:
        raise ExportError("--relay-key goes with --relay-cert")
    tls = RelayTls(args.relay_ca, args.relay_cert, args.relay_key)
    tls.context()
    if tls.cert is not None:
        check_own_certificate(tls.cert)
    return tls


def check_own_certificate(cert: str) -> str | None:
    """Say once, in one line, why a relay that asks for node certificates would refuse ``cert``
    (the node still runs: a relay that asks for none takes it); the problem, or None."""
    try:
        problem = certificate_problem(cert)
    except (OSError, CertificateUnreadable):  # OpenSSL loaded it: what it checks, it will say
        return None
    if problem is not None and cert not in _told:
        _told.add(cert)
        log.warning("--relay-cert %s is %s: a relay that asks nodes for a certificate (--tls-client-ca) "
                    "will refuse it", cert, problem)
    return problem


def tls_failure(exc: BaseException) -> str | None:
    """Why a connection failed, where TLS failed it: the relay's certificate, or the relay's
    refusal of this node's (None: no TLS failure)."""
    seen: set[int] = set()
    cause: BaseException | None = exc
    while cause is not None and id(cause) not in seen:
        seen.add(id(cause))
        # aiohttp's errors derive from ssl's too, and hold the one ssl raised.
        inner = getattr(cause, "certificate_error", None) or getattr(cause, "os_error", None)
        if inner is not None:
            cause = inner
            continue
        if isinstance(cause, ssl.SSLCertVerificationError):
            return f"TLS: the relay's certificate failed verification: {cause.verify_message or cause.reason}"
        if isinstance(cause, ssl.SSLError):
            reason = (cause.reason or str(cause)).lower().replace("_", " ")
            if "alert" in reason:
                return f"TLS: the relay refused this node's certificate ({reason})"
            return f"TLS: {reason}"
        cause = cause.__cause__ or cause.__context__
    return None


def _reason(exc: BaseException) -> str:
    if isinstance(exc, ssl.SSLError):
        return exc.reason or str(exc)
    return getattr(exc, "strerror", None) or str(exc)
