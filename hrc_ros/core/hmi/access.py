"""Who may use the HMI's web server: the security rules of docs/HMI.md, as pure functions.

The server is on a factory floor, so it trusts nothing it is sent and nothing it is not told:

- **Binding.** Loopback by default (127.0.0.0/8, ::1, ``localhost``): only this machine reaches
  the pages. Any other address (a LAN address, ``0.0.0.0``, ``::``, a host name) needs an
  access token of at least `MIN_TOKEN_LENGTH` characters, or the server refuses to start
  (`AccessError`); a host name counts as off loopback, since it may resolve to anything.
- **Token.** When a token is set (off loopback it must be; on loopback it may be), every HTTP
  request and every WebSocket upgrade carries it: ``Authorization: Bearer <token>``, the
  `COOKIE` cookie (HttpOnly, SameSite=Strict: set when a page is opened once with
  ``?token=<token>``, which then redirects to the same page without it), or ``?token=`` itself.
  Compared in constant time; missing or wrong is 401.
- **Host.** On loopback without a token, the Host header must name a loopback host or one of
  `allowed_hosts`: a page of another site whose name is made to resolve to 127.0.0.1 (DNS
  rebinding) then gets 403 instead of the cell.
- **Origin.** A WebSocket upgrade whose Origin is not the page's own (the Host it asked for) nor
  one of `allowed_origins` is refused with 403 (cross-site WebSocket hijacking: a browser sends
  the cookie along with any site's upgrade). A request without an Origin header is no browser
  page (a script, the tests, `curl`) and passes this check; it still needs the token.

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
TOKEN_HINT = ('e.g. python3 -c "import secrets; print(secrets.token_urlsafe(24))", as the '
              'HRC_HMI_TOKEN environment variable or the token parameter')


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
    """What the server does with a request: serve it (status 200), or refuse it with `status`
    and `reason`. `remember` asks it to set the token cookie (the token came in the URL)."""

    status: int
    reason: str = ''
    remember: bool = False

    @property
    def allowed(self) -> bool:
        return self.status == 200


ALLOW = Verdict(200)


class AccessPolicy:
    """The rules above for one server: bound to `host`, with `token` ('' = none)."""

    def __init__(self, host: str, token: str = '', allowed_origins=(), allowed_hosts=()):
        self.host = host
        self.token = token
        self.loopback = is_loopback(host)
        self.allowed_origins = {o.strip().rstrip('/').lower() for o in allowed_origins
                                if o.strip()}
        self.allowed_hosts = {h.strip().lower() for h in allowed_hosts if h.strip()}

    def check_start(self) -> None:
        """`AccessError` when the server must not start with these settings."""
        if self.token and len(self.token) < MIN_TOKEN_LENGTH:
            raise AccessError(f'the access token has {len(self.token)} characters; use at '
                              f'least {MIN_TOKEN_LENGTH} ({TOKEN_HINT})')
        if not self.loopback and not self.token:
            raise AccessError(f'host {self.host!r} is not loopback: the pages would be open to '
                              f'the network without an access token; set one ({TOKEN_HINT}), '
                              'or bind 127.0.0.1')
        for origin in self.allowed_origins:
            parts = urlsplit(origin)
            if parts.scheme not in ('http', 'https') or not parts.netloc or parts.path:
                raise AccessError(f'allowed_origins: {origin!r} is not an origin like '
                                  'https://hmi.example.com or http://10.0.0.5:8080')

    def _token_matches(self, given: str | None) -> bool:
        return given is not None and hmac.compare_digest(given.encode(), self.token.encode())

    def check(self, host_header: str, origin: str | None, authorization: str | None,
              cookie_token: str | None, query_token: str | None,
              websocket: bool = False) -> Verdict:
        """The verdict on one request from its Host and Origin headers and the token wherever
        it came (None: absent)."""
        remember = False
        if self.token:
            bearer = None
            if authorization and authorization[:7].lower() == 'bearer ':
                bearer = authorization[7:].strip()
            if self._token_matches(bearer) or self._token_matches(cookie_token):
                pass
            elif self._token_matches(query_token):
                remember = True
            else:
                given = bearer is not None or cookie_token is not None \
                    or query_token is not None
                return Verdict(401, 'the access token is wrong' if given else
                               'an access token is required: open the page once with '
                               '?token=<token>, or send Authorization: Bearer <token>')
        else:
            name = host_name(host_header or '')
            if not (is_loopback(name) or name in self.allowed_hosts):
                return Verdict(403, f'Host {host_name(host_header or "")!r} is not this '
                               'machine: the HMI on loopback answers localhost and 127.0.0.1 '
                               'only (allowed_hosts adds names)')
        if websocket and origin is not None:
            value = origin.strip().rstrip('/').lower()
            own = {f'http://{(host_header or "").strip().lower()}',
                   f'https://{(host_header or "").strip().lower()}'}
            if value not in own and value not in self.allowed_origins:
                return Verdict(403, f'cross-origin WebSocket refused: Origin {origin[:100]!r} '
                               'is not this page (allowed_origins adds origins)')
        return Verdict(200, remember=remember)
