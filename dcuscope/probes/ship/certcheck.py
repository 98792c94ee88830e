"""A node's own certificate (``--relay-cert``), checked before it connects: a relay that asks nodes
for one (``dcuscope relay --tls-client-ca``) refuses one that has expired, is not valid yet, or is
not for client authentication, and all the node would hear is a closed connection; the relay's log
has the reason, but not the date (OpenSSL keeps no certificate it refused). The node says it in one
line instead, from the certificate itself.

The certificate is read with a few lines of DER (RFC 5280: validity and the extendedKeyUsage and
keyUsage extensions), so that a node needs nothing beyond Python's ``ssl``. It checks what OpenSSL
checks of a TLS client's certificate: its dates, an extendedKeyUsage that names clientAuth (or any
purpose) where there is one, a keyUsage with digitalSignature or keyAgreement where there is one.
"""

from __future__ import annotations

import datetime as dt
import re
import ssl
from pathlib import Path

EKU_OID = bytes.fromhex("551d25")  # 2.5.29.37
KEY_USAGE_OID = bytes.fromhex("551d0f")  # 2.5.29.15
ANY_PURPOSE = bytes.fromhex("551d2500")  # 2.5.29.37.0
PURPOSES = {bytes.fromhex("2b0601050507030" + str(k)): name for k, name in
            ((1, "serverAuth"), (2, "clientAuth"), (3, "codeSigning"), (4, "emailProtection"),
             (8, "timeStamping"), (9, "OCSPSigning"))}
"""id-kp-* (1.3.6.1.5.5.7.3.k) by name."""
CLIENT_AUTH = next(oid for oid, name in PURPOSES.items() if name == "clientAuth")
DIGITAL_SIGNATURE, KEY_AGREEMENT = 0x80, 0x08
"""keyUsage bits 0 and 4, in the first byte of its BIT STRING."""


class CertificateUnreadable(ValueError):
    """The file holds no certificate this reader understands."""


def certificate_problem(path: str | Path, now: dt.datetime | None = None) -> str | None:
    """Why a relay would refuse the certificate at ``path`` (the first of a PEM file) as a TLS
    client's: "expired on DATE", "not valid before DATE", "not for client authentication (...)";
    None if it would not. :class:`CertificateUnreadable` if it cannot be read."""
    der = _Der(_first_der(Path(path).read_text(errors="replace")))
    tbs = der.items(der.at(0, len(der.data)))[0]
    fields = der.items(tbs)
    if fields and der.tag(fields[0]) == 0xA0:  # [0] version
        fields = fields[1:]
    if len(fields) < 6:
        raise CertificateUnreadable("not an X.509 certificate")
    not_before, not_after = (der.time(item) for item in der.items(fields[3]))
    now = now or dt.datetime.now(dt.timezone.utc)
    if now > not_after:
        return f"expired on {_day(not_after)}"
    if now < not_before:
        return f"not valid before {_day(not_before)}"
    extensions = next((f for f in fields[6:] if der.tag(f) == 0xA3), None)
    if extensions is None:
        return None
    for ext in der.items(der.inner(extensions)):
        parts = der.items(ext)
        oid, value = der.content(parts[0]), parts[-1]  # the OCTET STRING, after the optional "critical"
        if oid == EKU_OID:
            purposes = [der.content(p) for p in der.items(der.inner(value))]
            if CLIENT_AUTH not in purposes and ANY_PURPOSE not in purposes:
                named = ", ".join(PURPOSES.get(p, "other") for p in purposes) or "none"
                return f"not for client authentication (its extendedKeyUsage is {named}: it needs clientAuth)"
        elif oid == KEY_USAGE_OID:
            bits = der.content(der.inner(value))
            if not (bits[1] if len(bits) > 1 else 0) & (DIGITAL_SIGNATURE | KEY_AGREEMENT):  # after the unused-bit count
                return "not for client authentication (its keyUsage has neither digitalSignature nor keyAgreement)"
    return None


def _first_der(pem: str) -> bytes:
    block = re.search(r"-----BEGIN CERTIFICATE-----.+?-----END CERTIFICATE-----", pem, re.S)
    if block is None:
        raise CertificateUnreadable("no PEM certificate in it")
    try:
        return ssl.PEM_cert_to_DER_cert(block.group(0))
    except ValueError as exc:
        raise CertificateUnreadable(f"a malformed PEM certificate: {exc}") from None


class _Der:
    """DER elements as (where it starts, where its content starts, where it ends) in ``data``."""

    def __init__(self, data: bytes) -> None:
        self.data = data

    def at(self, start: int, end: int) -> tuple[int, int, int]:
        """The element at ``start``, within ``end``."""
        data = self.data
        if start + 2 > end:
            raise CertificateUnreadable("truncated DER")
        length, head = data[start + 1], start + 2
        if length & 0x80:
            n = length & 0x7F
            if not 0 < n <= 4 or head + n > end:
                raise CertificateUnreadable("a DER length it cannot read")
            length, head = int.from_bytes(data[head:head + n], "big"), head + n
        if head + length > end:
            raise CertificateUnreadable("truncated DER")
        return start, head, head + length

    def items(self, element: tuple[int, int, int]) -> list[tuple[int, int, int]]:
        """The elements of a constructed ``element``."""
        out, at = [], element[1]
        while at < element[2]:
            out.append(self.at(at, element[2]))
            at = out[-1][2]
        return out

    def inner(self, element: tuple[int, int, int]) -> tuple[int, int, int]:
        """The one element an OCTET STRING or an explicit tag wraps."""
        return self.at(element[1], element[2])

    def tag(self, element: tuple[int, int, int]) -> int:
        return self.data[element[0]]

    def content(self, element: tuple[int, int, int]) -> bytes:
        return self.data[element[1]:element[2]]

    def time(self, element: tuple[int, int, int]) -> dt.datetime:
        text = self.content(element).decode("ascii", "replace")
        form = "%y%m%d%H%M%SZ" if self.tag(element) == 0x17 else "%Y%m%d%H%M%SZ"  # UTCTime, else GeneralizedTime
        try:
            return dt.datetime.strptime(text, form).replace(tzinfo=dt.timezone.utc)
        except ValueError:
            raise CertificateUnreadable(f"a validity date it cannot read: {text!r}") from None


def _day(when: dt.datetime) -> str:
    return when.strftime("%Y-%m-%d %H:%M:%S UTC")
