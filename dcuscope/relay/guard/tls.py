"""TLS on the relay's port (``dcuscope relay --tls-cert FILE --tls-key FILE [--tls-client-ca FILE]``).

:class:`ServerTls` holds the server's context; :meth:`ServerTls.reload` (SIGHUP) rereads the files,
so a renewed certificate needs no restart: connections accepted after it get the new one, and a
new file that cannot be loaded leaves the old context in place, said in one log line.
:class:`~dcuscope.relay.guard.connections.ConnGuard` hands it each connection whose first byte is a TLS
handshake's; anything else on that port is refused (``refused["plaintext"]``).

With ``--tls-client-ca`` the context asks every client for a certificate (CERT_OPTIONAL: a browser
that has none still gets the page and the API) and fails the handshake of one that CA did not sign;
``/ingest`` then takes only connections that presented a verified one, and the node streams under
the name it gives (:func:`dcuscope.relay.guard.policy.certificate_principal`: its first DNS subjectAltName, else its CN) only.

:func:`refused_certificate` says why a client's certificate failed verification (expired, not yet
valid, unknown CA, wrong purpose), for the connection guard's log line.

Protocols and ciphers are Mozilla's "intermediate" configuration (server side TLS, version 5.7):
TLS 1.2 and 1.3 only; for TLS 1.2 only ECDHE key exchange (forward secrecy) with AES-GCM or
ChaCha20-Poly1305 (:data:`TLS12_CIPHERS`: nothing with RSA key exchange, CBC or SHA-1, whatever the
certificate's key); for TLS 1.3 OpenSSL's suites, which are those three AEADs. Mozilla's list also
names three DHE suites, left out: OpenSSL 3 offers them only with Diffie-Hellman parameters, which
the relay does not load, and every client of a decade has ECDHE.
"""

from __future__ import annotations

import logging
import ssl
from pathlib import Path

from dcuscope.relay.errors import RelayError

log = logging.getLogger(__name__)

TLS12_CIPHERS = ":".join(("ECDHE-ECDSA-AES128-GCM-SHA256", "ECDHE-RSA-AES128-GCM-SHA256",
                          "ECDHE-ECDSA-AES256-GCM-SHA384", "ECDHE-RSA-AES256-GCM-SHA384",
                          "ECDHE-ECDSA-CHACHA20-POLY1305", "ECDHE-RSA-CHACHA20-POLY1305"))
"""Mozilla intermediate's TLS 1.2 ciphers, but its DHE ones (see the module docstring)."""
VERIFY_REASONS = {
    10: "its certificate expired",
    9: "its certificate is not valid yet",
    2: "unknown CA: its certificate comes from a CA that --tls-client-ca does not hold",
    18: "unknown CA: its certificate is self-signed",
    19: "unknown CA: its chain ends in a CA that --tls-client-ca does not hold",
    20: "unknown CA: its certificate comes from a CA that --tls-client-ca does not hold",
    21: "unknown CA: its certificate comes from a CA that --tls-client-ca does not hold",
    26: "wrong purpose: its certificate is not for client authentication (clientAuth)",
    23: "its certificate was revoked",
    7: "its certificate's signature does not verify",
}
"""What a client certificate's verify error (OpenSSL's X509_V_ERR_* code) means to the operator."""


class ServerTls:
    """The relay's TLS context, from PEM files (see the module docstring)."""

    def __init__(self, cert: str | Path, key: str | Path, client_ca: str | Path | None = None) -> None:
        self.cert, self.key = Path(cert), Path(key)
        self.client_ca = Path(client_ca) if client_ca is not None else None
        self.context = self._load()
        """The context new connections are served with (replaced whole by :meth:`reload`)."""

    @property
    def verifies_clients(self) -> bool:
        """Whether nodes must present a certificate ``client_ca`` signed."""
        return self.client_ca is not None

    def reload(self) -> bool:
        """Reread the files; whether the new ones are in use (else the old context stays)."""
        try:
            context = self._load()
        except RelayError as exc:
            log.error("TLS: keeping the certificate in use: %s", exc)
            return False
        self.context = context
        log.warning("TLS: certificate reread from %s", self.cert)
        return True

    def _load(self) -> ssl.SSLContext:
        context = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
        context.minimum_version = ssl.TLSVersion.TLSv1_2
        context.set_ciphers(TLS12_CIPHERS)  # TLS 1.3's suites are set apart, and OpenSSL's are AEADs only
        try:
            context.load_cert_chain(self.cert, self.key)
        except (OSError, ssl.SSLError) as exc:
            raise RelayError(f"--tls-cert {self.cert} --tls-key {self.key}: {_reason(exc)}") from None
        if self.client_ca is not None:
            try:
                context.load_verify_locations(cafile=self.client_ca)
            except (OSError, ssl.SSLError) as exc:
                raise RelayError(f"--tls-client-ca {self.client_ca}: {_reason(exc)}") from None
            context.verify_mode = ssl.CERT_OPTIONAL
        return context


def refused_certificate(exc: ssl.SSLCertVerificationError) -> str:
    """Why the relay refused a client's certificate, with the verifier's own words and code. OpenSSL
    keeps no certificate it refused, so an expired one's date is the node's to say (it checks its
    own before connecting: :mod:`dcuscope.probes.ship.certcheck`)."""
    code, said = exc.verify_code, exc.verify_message or exc.reason or "verification failed"
    meaning = VERIFY_REASONS.get(code, "verification failed")
    return f"refused the client certificate: {meaning}; the verifier said \"{said}\" (X509 error {code})"


def _reason(exc: BaseException) -> str:
    if isinstance(exc, ssl.SSLError):
        return exc.reason or str(exc)
    return getattr(exc, "strerror", None) or str(exc)
