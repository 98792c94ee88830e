"""No secret in the relay's log, at any level: every record that reaches the root logger's handlers
(the relay's own, aiohttp's, Socket.IO's, the stores' drivers') is scrubbed before it is written.

:class:`Redact` replaces, in the message and in any traceback's text,

- the value of a credential-like field, however it is written: ``token``, ``auth``,
  ``authorization``, ``cookie``, ``password``, ``secret`` (``clock_secret`` too) and the session
  cookie's name, followed by ``=`` or ``:``, quoted or not (a query, a header, a JSON or Python dict);
- a ``Bearer`` or ``Basic`` credential, and the password of a URL (``scheme://user:PASSWORD@host``);
- every secret the relay was given (``--token``, ``--viewer-tokens``, ``--node-tokens``), wherever
  it appears, even where nothing names it (a client that sends its token as an event's name).

Socket.IO's and Engine.IO's packet logs never carry a packet's contents in the first place
(:class:`dcuscope.relay.api.sio.NoPackets`); this is the net under everything else.
"""

from __future__ import annotations

import logging
import re
from collections.abc import Iterable

from dcuscope.relay.guard.policy import COOKIE

REDACTED = "<redacted>"
MIN_SECRET_CHARS = 6
"""Shorter known secrets are not searched for (a short one would redact ordinary words)."""
_FIELDS = rf"(?:[\w.-]*(?:token|secret|password|passwd)|auth|authorization|cookie|set-cookie|{re.escape(COOKIE)})"
_FIELD = re.compile(
    rf"""(?ix)
    (?P<key>(?P<q>["']?)\b{_FIELDS}(?P=q))     # the field's name, quoted or not
    (?P<sep>\s*[:=]\s*)
    (?P<value>(?:(?:bearer|basic)\s+)?                 # an Authorization header's scheme, and then
              (?:"(?:[^"\\]|\\.)*"|'(?:[^'\\]|\\.)*'|\{{[^{{}}]*\}}|[^\s,;&}}\]\)]+))""")
_SCHEME = re.compile(r"(?i)\b(bearer|basic)\s+[A-Za-z0-9._~+/=-]+")
_URL_PASSWORD = re.compile(r"(?i)\b([a-z][a-z0-9+.-]*://[^/\s:@]*:)[^@\s/]+@")


def redact(text: str, secrets: Iterable[str] = ()) -> str:
    """``text`` with every credential of the module docstring replaced by :data:`REDACTED`."""
    for secret in secrets:
        if secret in text:
            text = text.replace(secret, REDACTED)
    text = _FIELD.sub(lambda m: f"{m['key']}{m['sep']}{_keep_quotes(m['value'])}", text)
    text = _SCHEME.sub(lambda m: f"{m[1]} {REDACTED}", text)
    return _URL_PASSWORD.sub(lambda m: f"{m[1]}{REDACTED}@", text)


def _keep_quotes(value: str) -> str:
    if value[:1] in "\"'":
        return f"{value[0]}{REDACTED}{value[0]}"
    return REDACTED


class Redact(logging.Filter):
    """Scrubs each record's message and traceback (see the module docstring); passes every record."""

    def __init__(self, secrets: Iterable[str] = ()) -> None:
        super().__init__()
        self.secrets = sorted({s for s in secrets if s and len(s) >= MIN_SECRET_CHARS}, key=len, reverse=True)

    def filter(self, record: logging.LogRecord) -> bool:
        if getattr(record, "_redacted", False):  # one record, several handlers
            return True
        record._redacted = True
        message = record.getMessage()
        clean = redact(message, self.secrets)
        if clean != message:
            record.msg, record.args = clean, None
        if record.exc_info and record.exc_info[1] is not None and not record.exc_text:
            record.exc_text = logging.Formatter().formatException(record.exc_info)
        if record.exc_text:
            record.exc_text = redact(record.exc_text, self.secrets)
        if record.stack_info:
            record.stack_info = redact(record.stack_info, self.secrets)
        return True


def install(secrets: Iterable[str] = ()) -> Redact:
    """Put a :class:`Redact` on every handler of the root logger (Python's last-resort one if none),
    after the filters already there (the log's rate bound keys on the unredacted format string)."""
    scrub = Redact(secrets)
    for handler in logging.getLogger().handlers or [logging.lastResort]:
        if handler is not None:
            handler.addFilter(scrub)
    return scrub
