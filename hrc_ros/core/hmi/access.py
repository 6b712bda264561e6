"""Who may use the HMI's web server, and as whom: the security rules of docs/HMI.md, as pure
functions.

The server is on a factory floor, so it trusts nothing it is sent and nothing it is not told:

- **Roles.** Two: the worker (the tablet by the bench: the worker's page, answers to the
  robot's requests) and the operator (the console at /operator, task orders, and the worker's
  page too). Each has its access token; a request's role is that of the token it carries (the
  operator's wins when it carries both). The worker's token gets 403 on /operator, on the
  console's WebSocket and on any task order (`may_open`, `may_order`).
- **Binding.** Loopback by default (127.0.0.0/8, ::1, ``localhost``): only this machine reaches
  the pages. Any other address (a LAN address, ``0.0.0.0``, ``::``, a host name) needs both
  tokens, each of at least `MIN_TOKEN_LENGTH` characters and different, or the server refuses
  to start (`AccessError`); a host name counts as off loopback, since it may resolve to
  anything. On loopback a role without a token is open to anyone on this machine; a worker's
  token without an operator's would leave the console open to whoever has no token, so it is
  refused too.
- **Tokens.** When a role has a token, its requests carry it: ``Authorization: Bearer
  <token>``, the `COOKIE` cookie (HttpOnly, SameSite=Strict: set when a page is opened once
  with ``?token=<token>``, which then redirects to the same page without it; such a link sets
  the browser's role, whatever cookie it had), or ``?token=`` itself. Compared in constant
  time; a wrong one is 401, none where one is needed too.
- **Host.** A request that gets its role without a token (on loopback) must name a loopback
  host or one of `allowed_hosts` in its Host header: a page of another site whose name is made
  to resolve to 127.0.0.1 (DNS rebinding) then gets 403 instead of the cell.
- **Origin.** A WebSocket upgrade whose Origin is not the page's own (the Host it asked for) nor
  one of `allowed_origins` is refused with 403 (cross-site WebSocket hijacking: a browser sends
  the cookie along with any site's upgrade). A request without an Origin header is no browser
  page (a script, the tests, `curl`) and passes this check; it still needs its token.

Everything else (frame size, rates, connection counts) is the server's, in `limits` and the
ring's settings.
"""

from __future__ import annotations

import hmac
import ipaddress
from dataclasses import dataclass
from urllib.parse import urlsplit

COOKIE = 'hrc_hmi_token'
MIN_TOKEN_LENGTH = 16
WORKER, OPERATOR = 'worker', 'operator'
ROLES = (WORKER, OPERATOR)
TOKEN_ENV = {WORKER: 'HRC_HMI_WORKER_TOKEN', OPERATOR: 'HRC_HMI_OPERATOR_TOKEN'}
TOKEN_HINT = ('e.g. python3 -c "import secrets; print(secrets.token_urlsafe(24))", as the '
              'HRC_HMI_WORKER_TOKEN and HRC_HMI_OPERATOR_TOKEN environment variables or the '
              'worker_token and operator_token parameters')


class AccessError(ValueError):
    """The server must not start with these settings; the text says why and what to do."""


def is_loopback(host: str) -> bool:
    """Whether a bind address or Host name is this machine only: ``localhost``, 127.0.0.0/8,
    ::1 (with or without brackets). Host names other than localhost are not: they may resolve
    to anything."""
    host = host.strip().lower().strip('[]')
    if host == 'localhost':
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def host_name(host_header: str) -> str:
    """The host part of a Host header (``name``, ``name:port``, ``[::1]:port``), lower case."""
    value = host_header.strip().lower()
    if value.startswith('['):
        return value[1:].split(']', 1)[0]
    if value.count(':') == 1:
        return value.rsplit(':', 1)[0]
    return value


@dataclass(frozen=True)
class Verdict:
    """What the server does with a request: serve it (status 200) to `role`, or refuse it with
    `status` and `reason`. `remember`: the token came in the URL; the server keeps it in the
    cookie (`token`) and takes it out of the URL."""

    status: int
    reason: str = ''
    remember: bool = False
    role: str = ''
    token: str = ''

    @property
    def allowed(self) -> bool:
        return self.status == 200


class AccessPolicy:
    """The rules above for one server bound to `host`, with each role's token ('' = none)."""

    def __init__(self, host: str, worker_token: str = '', operator_token: str = '',
                 allowed_origins=(), allowed_hosts=()):
        self.host = host
        self.tokens = {WORKER: worker_token, OPERATOR: operator_token}
        self.loopback = is_loopback(host)
        self.allowed_origins = {o.strip().rstrip('/').lower() for o in allowed_origins
                                if o.strip()}
        self.allowed_hosts = {h.strip().lower() for h in allowed_hosts if h.strip()}

    def check_start(self) -> None:
        """`AccessError` when the server must not start with these settings."""
        for role in ROLES:
            token = self.tokens[role]
            if token and len(token) < MIN_TOKEN_LENGTH:
                raise AccessError(f"the {role}'s access token has {len(token)} characters; "
                                  f'use at least {MIN_TOKEN_LENGTH} ({TOKEN_HINT})')
        worker, operator = self.tokens[WORKER], self.tokens[OPERATOR]
        if worker and worker == operator:
            raise AccessError("the worker's and the operator's access tokens are the same: the "
                              "worker's tablet could queue work; give each its own "
                              f'({TOKEN_HINT})')
        missing = [f"the {role}'s" for role in ROLES if not self.tokens[role]]
        if not self.loopback and missing:
            raise AccessError(f'host {self.host!r} is not loopback: the pages would be open to '
                              f'the network without {" and ".join(missing)} access token; set '
                              f'both ({TOKEN_HINT}), or bind 127.0.0.1')
        if worker and not operator:
            raise AccessError("a worker's access token without an operator's would leave the "
                              "operator's console open to anyone without a token: set the "
                              f"operator's too ({TOKEN_HINT})")
        for origin in self.allowed_origins:
            parts = urlsplit(origin)
            if parts.scheme not in ('http', 'https') or not parts.netloc or parts.path:
                raise AccessError(f'allowed_origins: {origin!r} is not an origin like '
                                  'https://hmi.example.com or http://10.0.0.5:8080')

    def _role_of(self, given: str | None) -> str | None:
        """The role whose token `given` is (the operator's first), or None."""
        if given is None:
            return None
        # surrogateescape: aiohttp hands a header's bytes that are not UTF-8 over as lone
        # surrogates, which a strict encode refused with a traceback (a 500 per request)
        presented = given.encode('utf-8', 'surrogateescape')
        for role in (OPERATOR, WORKER):
            token = self.tokens[role]
            if token and hmac.compare_digest(presented, token.encode()):
                return role
        return None

    def check(self, host_header: str, origin: str | None, authorization: str | None,
              cookie_token: str | None, query_token: str | None,
              websocket: bool = False) -> Verdict:
        """The verdict on one request from its Host and Origin headers and the token wherever
        it came (None: absent): allowed, and as whom."""
        remember, role = False, None
        if any(self.tokens.values()):
            bearer = None
            if authorization and authorization[:7].lower() == 'bearer ':
                bearer = authorization[7:].strip()
            roles = {source: self._role_of(given) for source, given in
                     (('bearer', bearer), ('cookie', cookie_token), ('query', query_token))}
            found = [r for r in roles.values() if r is not None]
            if roles['query'] is not None:         # a link with a token: this browser's role
                role, remember = roles['query'], True
            elif found:
                role = OPERATOR if OPERATOR in found else WORKER
            elif bearer is not None or cookie_token is not None or query_token is not None:
                return Verdict(401, 'the access token is wrong')
        if role is None:
            open_roles = [r for r in (OPERATOR, WORKER) if not self.tokens[r]]
            if not open_roles:
                return Verdict(401, 'an access token is required: open the page once with '
                               '?token=<token>, or send Authorization: Bearer <token>')
            role = open_roles[0]
            name = host_name(host_header or '')
            if not (is_loopback(name) or name in self.allowed_hosts):
                return Verdict(403, f'Host {name!r} is not this machine: the HMI on loopback '
                               'answers localhost and 127.0.0.1 only (allowed_hosts adds '
                               'names)')
        if websocket and origin is not None:
            value = origin.strip().rstrip('/').lower()
            own = {f'http://{(host_header or "").strip().lower()}',
                   f'https://{(host_header or "").strip().lower()}'}
            if value not in own and value not in self.allowed_origins:
                return Verdict(403, f'cross-origin WebSocket refused: Origin {origin[:100]!r} '
                               'is not this page (allowed_origins adds origins)')
        return Verdict(200, remember=remember, role=role,
                       token=self.tokens[role] if remember else '')


def may_open(role: str, page: str) -> Verdict:
    """Whether `role` may open `page` ('worker' or 'operator': a page or its WebSocket)."""
    if page == OPERATOR and role != OPERATOR:
        return Verdict(403, "the operator's console needs the operator's access token; this "
                       "browser has the worker's", role=role)
    return Verdict(200, role=role)


def may_order(role: str) -> bool:
    """Only the operator queues tasks."""
    return role == OPERATOR
