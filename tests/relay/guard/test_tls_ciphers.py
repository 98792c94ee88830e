"""The relay's TLS protocols and ciphers (issue 61, item 4), as Debian's ``sslscan`` finds them against
a real relay process with an RSA and with an EC certificate: Mozilla's "intermediate" configuration,
TLS 1.2 and 1.3 only, and for TLS 1.2 only ECDHE with AES-GCM or ChaCha20 (no RSA key exchange, no
CBC, no SHA-1), whatever the certificate's key.
"""

from __future__ import annotations

import shutil
import subprocess
import xml.etree.ElementTree as ET

import pytest

from tests.relay.helpers import RelayProcess
from tests.tlscerts import TestCA

TLS13 = {"TLS_AES_128_GCM_SHA256", "TLS_AES_256_GCM_SHA384", "TLS_CHACHA20_POLY1305_SHA256"}
TLS12 = {f"ECDHE-{{sig}}-{c}" for c in ("AES128-GCM-SHA256", "AES256-GCM-SHA384", "CHACHA20-POLY1305")}


def sslscan(port: int) -> ET.Element:
    if shutil.which("sslscan") is None:
        raise AssertionError("sslscan not found: `make setup` installs Debian's sslscan")
    done = subprocess.run(["sslscan", "--no-colour", "--xml=-", "--no-heartbleed", "--no-check-certificate",
                           "--no-groups", f"127.0.0.1:{port}"], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    return ET.fromstring(done.stdout).find("ssltest")


@pytest.mark.parametrize("key, sig", [("rsa", "RSA"), ("ec", "ECDSA")])
def test_sslscan_finds_only_mozilla_intermediate(tmp_path, key, sig):
    server = TestCA(tmp_path).issue("relay", key=key)
    relay = RelayProcess(tmp_path / "relay.db", args=["--tls-cert", str(server.cert), "--tls-key", str(server.key)])
    try:
        scan = sslscan(relay.port)
    finally:
        relay.stop()
    enabled = {f"{p.get('type')}{p.get('version')}" for p in scan.iter("protocol") if p.get("enabled") == "1"}
    accepted: dict[str, set[str]] = {}
    for c in scan.iter("cipher"):
        accepted.setdefault(c.get("sslversion"), set()).add(c.get("cipher"))
    print(f"\nsslscan, {key.upper()} certificate: protocols {sorted(enabled)}; "
          + "; ".join(f"{v}: {', '.join(sorted(names))}" for v, names in sorted(accepted.items())))
    assert enabled == {"tls1.2", "tls1.3"}, enabled
    assert accepted == {"TLSv1.3": TLS13, "TLSv1.2": {c.format(sig=sig) for c in TLS12}}, accepted
    assert scan.find("renegotiation") is None or scan.find("renegotiation").get("supported") == "0"
    assert scan.find("compression") is None or scan.find("compression").get("supported") == "0"
