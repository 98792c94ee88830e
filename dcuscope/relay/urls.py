"""URLs of the servers a relay uses (its store, its Redis), as messages and /api/health show them."""

from __future__ import annotations

import re
from urllib.parse import urlsplit, urlunsplit

SECRET_PARAMETERS = re.compile(r"(?i)(^|&)((?:ssl)?password)=[^&]*")
"""Query parameters that hold a secret: libpq's ``password`` and ``sslpassword`` (the client key's)."""


def redact(url: str) -> str:
    """``url`` without its secrets (the password, in the user part or the query), for messages and
    /api/health; the rest (host, database, sslmode, certificate files) is left as it is."""
    parts = urlsplit(url)
    if parts.password is not None:
        parts = parts._replace(netloc=parts.netloc.replace(f":{parts.password}@", ":***@", 1))
    return urlunsplit(parts._replace(query=SECRET_PARAMETERS.sub(r"\1\2=***", parts.query)))
