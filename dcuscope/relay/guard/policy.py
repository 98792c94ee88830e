"""Who may do what on the relay: the one access policy every entry point asks.

A request's credential (``Authorization: Bearer TOKEN``, the page's session cookie, a verified TLS
client certificate, or ``?token=`` on ``/ingest`` for old nodes only) names a :class:`Principal`:

- ADMIN: ``--token``; reads, and streams under any node name;
- VIEWER: a line of ``--viewer-tokens``; reads only (the page's data, ``GET /api/*``, ``/metrics``);
- NODE: a line of ``--node-tokens``, or a client certificate (:func:`certificate_principal`);
  streams under its own name only, reads nothing.

Each route declares its :class:`Action` where it is added (:func:`declare`, :func:`add_read`);
:meth:`Policy.middleware` runs before every handler and refuses a route that declared none, so a
new endpoint cannot forget to be guarded. PUBLIC: the page's shell and static files, the favicon,
sign-in and sign-out. READ is open to anyone while the relay has neither ``--token`` nor
``--viewer-tokens``; INGEST while it has no credential of any kind. SOCKET: the Socket.IO transport,
whose ``/ui`` namespace asks :meth:`Policy.check` for READ as a browser connects.

Refusals: 401 without a valid credential (and at ``/ingest`` for any credential that may not stream,
which ends a node's tries), 403 for a valid one of the wrong role; each counted in ``refused`` by
reason and logged as one line (bounded by :mod:`dcuscope.relay.guard.lograte`), never with the credential.

The page signs in once (:mod:`dcuscope.relay.guard.signin`) and holds a cookie, not the token: NAME, ROLE
and EXPIRY signed with HMAC-SHA256 keyed by the credential itself, so relays sharing the same token
files accept each other's cookies, and a credential taken off a file invalidates its cookies.
"""

from __future__ import annotations

import base64
import enum
import hashlib
import hmac
import logging
import time
from collections import Counter
from collections.abc import Mapping
from dataclasses import dataclass

from aiohttp import web

from dcuscope.relay.errors import RelayError, http_error
from dcuscope.relay.guard.auth import Credentials

COOKIE = "dcuscope_session"
COOKIE_LIFETIME_S = 12 * 3600
ADMIN_NAME = "admin"

log = logging.getLogger(__name__)


class Role(enum.Enum):
    ADMIN = "admin"
    VIEWER = "viewer"
    NODE = "node"


class Action(enum.Enum):
    PUBLIC = "public"
    READ = "read"
    INGEST = "ingest"
    SOCKET = "socket"
    """The Socket.IO transport: its namespaces' connect handlers ask for READ."""


ALLOWED = {Role.ADMIN: {Action.READ, Action.INGEST}, Role.VIEWER: {Action.READ}, Role.NODE: {Action.INGEST}}


@dataclass(frozen=True)
class Principal:
    role: Role
    name: str

    @property
    def node(self) -> str | None:
        """The only node name it may stream under (None: any, the admin's)."""
        return self.name if self.role is Role.NODE else None


ANONYMOUS = Principal(Role.VIEWER, "")
"""Who a request without a credential is while the relay asks for none (never in a cookie)."""


@dataclass(frozen=True)
class Refusal:
    status: int
    reason: str
    """The HTTP answer's text: what was wrong, never the credential."""
    count: str
    """Its key in ``refused`` (/api/health, /metrics)."""


_ACTIONS = web.AppKey("access_actions", dict)
PRINCIPAL = web.RequestKey("principal", Principal)
"""Who a request let through is (``request[PRINCIPAL]``)."""


def declare(app: web.Application, action: Action, *routes: web.AbstractRoute | web.AbstractResource) -> None:
    """Say which action a request to each of ``routes`` is (the middleware refuses undeclared ones)."""
    if _ACTIONS not in app:
        app[_ACTIONS] = {}
    for route in routes:
        app[_ACTIONS][getattr(route, "resource", None) or route] = action


def add_read(app: web.Application, path: str, handler) -> None:
    """``GET path``, for READ principals."""
    declare(app, Action.READ, app.router.add_get(path, handler))


def actions(app: web.Application) -> Mapping[web.AbstractResource, Action]:
    """Every resource's declared action (what the middleware goes by)."""
    return app.get(_ACTIONS, {})


def certificate_principal(peercert: Mapping | None) -> Principal | None:
    """The NODE a verified client certificate (``ssl.SSLSocket.getpeercert()``'s dict) names: its first
    DNS subjectAltName, else its subject's commonName, is the node name it may stream under."""
    if not peercert:
        return None
    names = [value for kind, value in peercert.get("subjectAltName", ()) if kind == "DNS"]
    for rdn in peercert.get("subject", ()):
        names += [value for key, value in rdn if key == "commonName"]
    names = [n for n in names if isinstance(n, str) and n and n.isprintable()]
    return Principal(Role.NODE, names[0]) if names else None


def certificate_of(request: web.BaseRequest) -> Principal | None:
    """The NODE of the client certificate the request's TLS connection verified, if any."""
    transport = request.transport
    return certificate_principal(transport.get_extra_info("peercert")) if transport is not None else None


class Policy:
    """The credentials a relay takes and what each may do; counts refusals in ``refused``."""

    def __init__(self, credentials: Credentials = Credentials(), refused: Counter | None = None,
                 certified: bool = False) -> None:
        self._by_token: list[tuple[bytes, Principal]] = []
        self._keys: dict[tuple[Role, str], bytes] = {}
        if credentials.admin is not None:
            self._add(credentials.admin, Principal(Role.ADMIN, ADMIN_NAME))
        for name, secret in credentials.viewers.items():
            self._add(secret, Principal(Role.VIEWER, name))
        for name, secret in credentials.nodes.items():
            self._add(secret, Principal(Role.NODE, name))
        self.reads_open = credentials.admin is None and not credentials.viewers
        """Anyone may read (the loopback demo; :mod:`dcuscope.relay.guard.hostcheck` guards it then)."""
        self.ingest_open = self.reads_open and not credentials.nodes
        self.refused = refused if refused is not None else Counter()
        self.certified = certified
        """Nodes must present a client certificate the relay's ``--tls-client-ca`` signed, whose name
        they stream under (the TLS layer verified it; a token presented beside it must not say otherwise)."""

    def _add(self, secret: str, principal: Principal) -> None:
        if any(hmac.compare_digest(secret.encode("utf-8", "surrogateescape"), known) for known, _ in self._by_token):
            raise RelayError(f"{principal.role.value} {principal.name!r} has a token another credential has too")
        self._by_token.append((secret.encode("utf-8", "surrogateescape"), principal))
        self._keys[(principal.role, principal.name)] = secret.encode("utf-8", "surrogateescape")

    def by_token(self, presented: object) -> Principal | None:
        """Whose token ``presented`` is, or None. Every credential is compared, each in constant time,
        so the time taken says nothing about which matched."""
        if not isinstance(presented, str):
            return None
        given = presented.encode("utf-8", "surrogateescape")
        found = None
        for secret, principal in self._by_token:
            if hmac.compare_digest(given, secret):
                found = principal
        return found

    # --- the session cookie -------------------------------------------------------------------

    def cookie_for(self, principal: Principal, now: float | None = None) -> str:
        """The cookie value that signs ``principal`` in for :data:`COOKIE_LIFETIME_S`."""
        expiry = int((time.time() if now is None else now) + COOKIE_LIFETIME_S)
        body = f"{principal.role.value}\n{principal.name}\n{expiry}".encode()
        return f"{_b64(body)}.{_b64(self._sign(principal, body))}"

    def by_cookie(self, value: object, now: float | None = None) -> Principal | None:
        """The principal a cookie of :meth:`cookie_for` signs in, if its signature holds and it has not expired."""
        if not isinstance(value, str) or value.count(".") != 1:
            return None
        try:
            body, mac = (base64.urlsafe_b64decode(part + "=" * (-len(part) % 4)) for part in value.split("."))
            role_name, name, expiry = body.decode().split("\n")
            role, expires = Role(role_name), int(expiry)
        except ValueError:  # bad base64, UTF-8, fields, role or number: a forged or stale cookie
            return None
        principal = next((p for _, p in self._by_token if p.role is role and p.name == name), None)
        if principal is None or principal.role is Role.NODE or expires < (time.time() if now is None else now):
            return None
        return principal if hmac.compare_digest(mac, self._sign(principal, body)) else None

    def _sign(self, principal: Principal, body: bytes) -> bytes:
        return hmac.new(self._keys[(principal.role, principal.name)], b"dcuscope session\n" + body, hashlib.sha256).digest()

    # --- decisions ----------------------------------------------------------------------------

    def principal_of(self, request: web.Request, action: Action) -> tuple[Principal | None, bool]:
        """Whom ``request`` presents itself as, and whether it presented any credential: its bearer
        token, else its session cookie, else (``/ingest``: old nodes) ``?token=``, else its client certificate."""
        header = request.headers.get("Authorization", "")
        if header.startswith("Bearer "):
            return self.by_token(header[len("Bearer "):].strip()), True
        cookie = request.cookies.get(COOKIE)
        if cookie and action is not Action.INGEST:
            return self.by_cookie(cookie), True
        if action is Action.INGEST and "token" in request.query:
            return self.by_token(request.query["token"]), True
        cert = certificate_of(request)
        return cert, cert is not None

    def _certified(self, cert: Principal | None, principal: Principal | None, presented: bool) -> Principal | Refusal:
        """The verdict at ``/ingest`` when nodes must present a certificate (``certified``): the node the
        certificate names, unless a token beside it is wrong, a viewer's, or another node's."""
        if cert is None:
            return Refusal(403, "forbidden: /ingest takes a client certificate signed by the relay's --tls-client-ca",
                           "certificate_missing")
        if principal is None and presented:
            return Refusal(401, "unauthorized: wrong or expired credential", "credential_wrong")
        if principal is not None and principal is not cert:
            if principal.role is Role.VIEWER:
                return Refusal(401, "unauthorized: a viewer's credential may not stream", "role")
            if principal.role is Role.NODE and principal.name != cert.name:
                return Refusal(403, f"forbidden: the certificate names node {cert.name!r}, the token {principal.name!r}",
                               "role")
        return cert

    def decide(self, principal: Principal | None, presented: bool, action: Action) -> Principal | Refusal:
        """What the policy says of ``principal`` (None: none or an invalid credential) asking for ``action``."""
        if action is Action.PUBLIC:
            return principal or ANONYMOUS
        is_open = self.reads_open if action is Action.READ else self.ingest_open
        if principal is None:
            if is_open:  # as before roles: an open relay ignores whatever it is shown
                return ANONYMOUS
            if presented:
                return Refusal(401, "unauthorized: wrong or expired credential", "credential_wrong")
            return Refusal(401, "unauthorized: a credential is required", "credential_missing")
        if action in ALLOWED[principal.role]:
            return principal
        if action is Action.INGEST:
            # 401, not 403: a node's shipper ends its tries on 401 and says why.
            return Refusal(401, f"unauthorized: a {principal.role.value}'s credential may not stream", "role")
        if is_open and principal.role is not Role.NODE:
            return ANONYMOUS
        return Refusal(403, f"forbidden: a {principal.role.value}'s credential may not {action.value}", "role")

    def check(self, request: web.Request, action: Action) -> Principal | Refusal:
        """:meth:`decide` for ``request``; a refusal is counted and logged (one line, no credential)."""
        principal, presented = self.principal_of(request, action)
        if action is Action.INGEST and self.certified:
            verdict = self._certified(certificate_of(request), principal, presented)
        else:
            verdict = self.decide(principal, presented, action)
        if isinstance(verdict, Refusal):
            self.refused[verdict.count] += 1
            log.info("access: %s %s from %s refused (%d): %s", request.method, request.path[:100], request.remote,
                     verdict.status, verdict.reason)
        return verdict

    @web.middleware
    async def middleware(self, request: web.Request, handler) -> web.StreamResponse:
        resource = request.match_info.route.resource
        if resource is None:  # no such path or method: aiohttp's 404 or 405 tells nothing
            return await handler(request)
        action = actions(request.app).get(resource)
        if action is None:
            self.refused["undeclared"] += 1
            log.error("access: route %s declares no action: refused", resource.canonical)
            raise http_error(web.HTTPForbidden, "forbidden: this route declares no access rule")
        if action in (Action.PUBLIC, Action.SOCKET):
            return await handler(request)
        verdict = self.check(request, action)
        if isinstance(verdict, Refusal):
            kind = web.HTTPUnauthorized if verdict.status == 401 else web.HTTPForbidden
            raise http_error(kind, verdict.reason)
        request[PRINCIPAL] = verdict
        return await handler(request)


def _b64(data: bytes) -> str:
    return base64.urlsafe_b64encode(data).rstrip(b"=").decode()
