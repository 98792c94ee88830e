"""The page's sign-in: a credential typed once becomes a session cookie, never part of an address.

- ``GET /signin``: {required, principal: {role, name} or null}: whether the page must sign in to read,
  and as whom it is signed in (its bearer token or cookie);
- ``POST /signin`` with the form field ``token`` (a viewer's or the admin's): 204 and the cookie
  (HttpOnly, SameSite=Strict, Secure over TLS, :data:`dcuscope.relay.guard.policy.COOKIE_LIFETIME_S`), or 401/403 saying why;
- ``POST /signout``: 204, the cookie cleared;
- ``GET /?token=T`` (the old way in, bookmarks): the same cookie for a valid T, and in any case a
  303 to the same address without the token, so that it leaves the address bar and the history.

SameSite=Strict keeps other sites' pages from posting with the cookie; a POST whose ``Origin`` is
another site is refused besides (it could sign a browser in as someone else).
"""

from __future__ import annotations

from urllib.parse import urlencode

from aiohttp import web

from dcuscope.relay.errors import http_error
from dcuscope.relay.guard.hostcheck import origin_netloc
from dcuscope.relay.guard.policy import COOKIE, COOKIE_LIFETIME_S, Action, Policy, Principal, Refusal, Role, declare


def add_signin_routes(app: web.Application, policy: Policy) -> None:
    async def whoami(request: web.Request) -> web.Response:
        verdict = policy.decide(*policy.principal_of(request, Action.READ), Action.READ)
        signed = verdict if isinstance(verdict, Principal) and verdict.name else None
        return web.json_response({"required": not policy.reads_open,
                                  "principal": {"role": signed.role.value, "name": signed.name} if signed else None})

    async def sign_in(request: web.Request) -> web.Response:
        _same_site(request)
        principal = policy.by_token((await request.post()).get("token"))
        if principal is None:
            refusal = Refusal(401, "unauthorized: wrong credential", "credential_wrong")
        elif principal.role is Role.NODE:
            refusal = Refusal(403, "forbidden: a node's credential may not read", "role")
        else:
            refusal = None
        if refusal is not None:
            policy.refused[refusal.count] += 1
            raise http_error(web.HTTPUnauthorized if refusal.status == 401 else web.HTTPForbidden, refusal.reason)
        response = web.Response(status=204)
        _sign_in(response, request, policy, principal)
        return response

    async def sign_out(request: web.Request) -> web.Response:
        _same_site(request)
        response = web.Response(status=204)
        response.del_cookie(COOKIE, path="/", samesite="Strict", secure=request.secure)
        return response

    declare(app, Action.PUBLIC, app.router.add_get("/signin", whoami), app.router.add_post("/signin", sign_in),
            app.router.add_post("/signout", sign_out))


def from_address(request: web.Request, policy: Policy) -> None:
    """For ``GET /?token=T``: raise a 303 to the address without ``token`` (with the cookie when T may read)."""
    if "token" not in request.query:
        return
    rest = [(k, v) for k, v in request.query.items() if k != "token"]
    response = web.HTTPSeeOther(request.path + ("?" + urlencode(rest) if rest else ""))
    principal = policy.by_token(request.query["token"])
    verdict = policy.decide(principal, True, Action.READ)
    if isinstance(verdict, Principal) and verdict.name and verdict.role is not Role.NODE:
        _sign_in(response, request, policy, verdict)
    elif not policy.reads_open or principal is not None:
        policy.refused["credential_wrong" if principal is None else "role"] += 1
    raise response


def _sign_in(response: web.StreamResponse, request: web.Request, policy: Policy, principal: Principal) -> None:
    """Set the session cookie that signs ``principal`` in (Secure when ``request`` came over TLS)."""
    response.set_cookie(COOKIE, policy.cookie_for(principal), max_age=COOKIE_LIFETIME_S, path="/",
                        httponly=True, samesite="Strict", secure=request.secure)


def _same_site(request: web.Request) -> None:
    origin = request.headers.get("Origin")
    if origin is not None and origin_netloc(origin) != request.headers.get("Host", "").strip().lower():
        raise http_error(web.HTTPForbidden, "forbidden: a sign-in from a page of another site")
