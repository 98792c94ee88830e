"""Certificates made at test time with the ``openssl`` CLI: a private CA, servers' and nodes'
certificates it signs, and the bad ones a test needs (another CA's, expired, for the wrong name).
Nothing here is ever committed: every file lives in the folder a test gives (``tmp_path``).

    ca = TestCA(tmp_path)                       # ca.cert: the CA's certificate (PEM)
    server = ca.issue("relay", ip="127.0.0.1")  # server.cert, server.key: SAN IP 127.0.0.1, DNS localhost
    node = ca.issue("DCU-1", client=True)       # CN=DCU-1, SAN DNS:DCU-1, clientAuth
    old = ca.issue("relay", expired=True)       # valid on 1-2 January 2000 only
    rsa = ca.issue("relay", key="rsa")          # an RSA (2048-bit) key instead of an EC (P-256) one
"""

from __future__ import annotations

import subprocess
from dataclasses import dataclass
from pathlib import Path

DAYS = 2


@dataclass(frozen=True)
class Issued:
    cert: Path
    key: Path
    name: str


def _openssl(*args: str, cwd: Path) -> None:
    done = subprocess.run(["openssl", *args], cwd=cwd, capture_output=True, text=True, timeout=60)
    if done.returncode != 0:
        raise RuntimeError(f"openssl {args[0]} failed: {done.stderr.strip()[-400:]}")


class TestCA:
    """A private CA in ``folder`` (its own subfolder ``name``)."""

    __test__ = False  # not a pytest class

    def __init__(self, folder: Path, name: str = "ca") -> None:
        self.dir = Path(folder) / name
        self.dir.mkdir(parents=True, exist_ok=True)
        self.cert = self.dir / "ca.pem"
        self.key = self.dir / "ca.key"
        self._serial = 0
        _openssl("req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes",
                 "-keyout", str(self.key), "-out", str(self.cert), "-days", str(DAYS),
                 "-subj", f"/CN=dcuscope test CA {name}",
                 "-addext", "basicConstraints=critical,CA:TRUE", "-addext", "keyUsage=critical,keyCertSign,cRLSign",
                 cwd=self.dir)

    def issue(self, name: str, *, ip: str | None = "127.0.0.1", client: bool = False,
              expired: bool = False, not_yet_valid: bool = False, dns: tuple[str, ...] = (),
              key: str = "ec") -> Issued:
        """A certificate for ``name`` (its CN) signed by this CA: a server's (SAN ``DNS:localhost``,
        ``IP:ip``) or, with ``client``, a node's (SAN ``DNS:name``, clientAuth). ``expired``: valid on
        1-2 January 2000 only; ``not_yet_valid``: from 1 January 2099; ``key``: "ec" (P-256) or "rsa"."""
        self._serial += 1
        stem = self.dir / f"{self._serial:02d}-{''.join(c if c.isalnum() else '_' for c in name)}"
        keyfile, csr, cert, ext = (stem.with_suffix(s) for s in (".key", ".csr", ".pem", ".ext"))
        kind = ["rsa:2048"] if key == "rsa" else ["ec", "-pkeyopt", "ec_paramgen_curve:prime256v1"]
        _openssl("req", "-new", "-newkey", *kind, "-nodes",
                 "-keyout", str(keyfile), "-out", str(csr), "-subj", f"/CN={name}", cwd=self.dir)
        if client:
            sans = [f"DNS:{name}", *(f"DNS:{d}" for d in dns)]
            usage = "clientAuth"
        else:
            sans = ["DNS:localhost", *(f"DNS:{d}" for d in dns)] + ([f"IP:{ip}"] if ip else [])
            usage = "serverAuth"
        ext.write_text(f"subjectAltName={','.join(sans)}\nextendedKeyUsage={usage}\n"
                       "basicConstraints=CA:FALSE\nkeyUsage=critical,digitalSignature,keyEncipherment\n")
        args = ["x509", "-req", "-in", str(csr), "-CA", str(self.cert), "-CAkey", str(self.key),
                "-set_serial", str(1000 + self._serial), "-extfile", str(ext), "-out", str(cert)]
        if expired:  # openssl 3.0's x509 cannot date a certificate back: `openssl ca` can
            self._sign_dated(csr, cert, ext, "20000101000000Z", "20000102000000Z")
        elif not_yet_valid:
            self._sign_dated(csr, cert, ext, "20990101000000Z", "20990102000000Z")
        else:
            _openssl(*args, "-days", str(DAYS), cwd=self.dir)
        return Issued(cert, keyfile, name)

    def _sign_dated(self, csr: Path, cert: Path, ext: Path, start: str, end: str) -> None:
        db = self.dir / "index.txt"
        db.touch()
        (self.dir / "serial").write_text(f"{2000 + self._serial:04X}\n")
        conf = self.dir / "ca.cnf"
        conf.write_text(
            "[ca]\ndefault_ca=test\n[test]\n"
            f"database={db}\nnew_certs_dir={self.dir}\nserial={self.dir / 'serial'}\n"
            f"certificate={self.cert}\nprivate_key={self.key}\ndefault_md=sha256\npolicy=any\n"
            "unique_subject=no\ncopy_extensions=none\n[any]\ncommonName=supplied\n")
        _openssl("ca", "-batch", "-config", str(conf), "-in", str(csr), "-out", str(cert), "-notext",
                 "-startdate", start, "-enddate", end, "-extfile", str(ext),
                 cwd=self.dir)


def served_serial(port: int, host: str = "127.0.0.1") -> int:
    """The serial number of the certificate a TLS server on ``port`` shows now (unverified)."""
    import socket
    import ssl
    context = ssl.SSLContext(ssl.PROTOCOL_TLS_CLIENT)
    context.check_hostname, context.verify_mode = False, ssl.CERT_NONE
    with socket.create_connection((host, port), 10) as raw, context.wrap_socket(raw) as tls:
        der = tls.getpeercert(binary_form=True)
    done = subprocess.run(["openssl", "x509", "-inform", "DER", "-noout", "-serial"], input=der,
                          capture_output=True, timeout=30, check=True)
    return int(done.stdout.decode().strip().split("=", 1)[1], 16)
