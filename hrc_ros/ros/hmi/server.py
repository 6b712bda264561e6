"""The HMI's web server: aiohttp on an asyncio loop in a thread of its own (docs/HMI.md).

It serves the pages (static HTML, CSS and JavaScript shipped in this package, read into memory
at start: no file system access per request, nothing fetched from elsewhere) and keeps them
live over one WebSocket per page (``/ws?view=worker`` or ``operator``). It knows no ROS: the
HMI node hands it the views to show and the console's growing feeds (the timeline, the event
log), and takes the pages' commands from it; `core.hmi.AccessPolicy` says who may come in and
as whom (the worker's token opens the worker's page only, and queues nothing).

Why aiohttp: one maintained package (in Debian and rosdep as python3-aiohttp) gives the HTTP
server, the WebSocket server with a frame size cap, heartbeats and close codes, and an
asyncio client the tests and the benchmark use; it runs on an event loop this module owns, in
a thread it starts and stops, and never touches the process's signal handlers
(`AppRunner(handle_signals=False)`), which belong to the node's `run()`. FastAPI would add
starlette, pydantic and an ASGI server (uvicorn) whose own serving loop installs signal
handlers and expects to own the process.

Threads. The rclpy executor and this loop never wait for each other:

- page -> ROS: a command (an answer, a task order, a page gone) goes into a bounded
  `queue.Queue` through `submit`; when it is full the page is told "busy" and nothing waits;
  the node drains it when its guard condition wakes it;
- ROS -> pages: `publish_views` stores the latest text of each view and schedules one flush
  (`call_soon_threadsafe`, at most one pending); each page has one slot for the latest view
  and a short bounded deque of replies, and one sender task, so a slow page holds only its own
  latest view, never a queue that grows;
- the console's feeds (`append_feeds`): each a ring of the last `FEEDS[name]` items the node
  handed in, numbered; a console page gets every item after the last one it got, in one
  message, or the whole ring when it is new or fell behind the ring (``reset``), so a page
  opened late has the last ten minutes at once and a slow one skips, never queues;
- `reply` delivers a command's result to the page that sent it.

Bad input. Frames above `max_frame_bytes` close the connection (1009, the cap is checked
against the frame header, before the payload is read); binary frames, malformed JSON and
unknown messages get an error reply; each page has a token bucket (`message_rate`,
`message_burst`), and a page that keeps flooding is closed (1008); at most `max_connections`
pages (503 beyond); a page that stops reading is closed after `SEND_TIMEOUT_S`. Replies to
errors are throttled to one a second per page.
"""

from __future__ import annotations

import asyncio
import json
import secrets
import threading
import time
from collections import Counter, deque
from dataclasses import dataclass
from pathlib import Path
from typing import Callable
from urllib.parse import urlencode

from aiohttp import WSCloseCode, WSMsgType, web

from ...core.hmi.access import COOKIE, OPERATOR, AccessPolicy, may_open, may_order
from ...core.hmi.limits import TokenBucket

STATIC_DIR = Path(__file__).resolve().parent / 'static'
# path -> (file in static/, content type)
PAGES = {
    '/': ('index.html', 'text/html; charset=utf-8'),
    '/operator': ('operator.html', 'text/html; charset=utf-8'),
    '/static/hmi.css': ('hmi.css', 'text/css; charset=utf-8'),
    '/static/hmi.js': ('hmi.js', 'text/javascript; charset=utf-8'),
    '/static/worker.js': ('worker.js', 'text/javascript; charset=utf-8'),
    '/static/operator.js': ('operator.js', 'text/javascript; charset=utf-8'),
    '/static/console.js': ('console.js', 'text/javascript; charset=utf-8'),
    '/static/favicon.svg': ('favicon.svg', 'image/svg+xml'),
    # uPlot (MIT, https://github.com/leeoniya/uPlot, vendor/LICENSE-uPlot.txt): the timeline
    '/static/vendor/uPlot.iife.min.js': ('vendor/uPlot.iife.min.js',
                                         'text/javascript; charset=utf-8'),
    '/static/vendor/uPlot.min.css': ('vendor/uPlot.min.css', 'text/css; charset=utf-8'),
}
# The console's feeds and the items each keeps: the timeline's rows come in batches of at most
# two a second (core.hmi.timeline.FLUSH_S), so this holds more than its ten minutes
FEEDS = {'timeline': 1500, 'events': 200}
VIEWS = ('worker', 'operator')
# the role the guard gave a request (a typed key from aiohttp 3.11 on, a string before)
ROLE = web.RequestKey('role', str) if hasattr(web, 'RequestKey') else 'role'
SECURITY_HEADERS = {
    'Content-Security-Policy': "default-src 'none'; script-src 'self'; style-src 'self'; "
                               "img-src 'self'; connect-src 'self'; frame-ancestors 'none'; "
                               "base-uri 'none'; form-action 'none'",
    'X-Content-Type-Options': 'nosniff',
    'X-Frame-Options': 'DENY',
    'Referrer-Policy': 'no-referrer',
    'Cache-Control': 'no-store',
}
REPLIES_KEPT = 16         # replies waiting for a slow page (older ones are dropped)
SEND_TIMEOUT_S = 10.0     # a page that takes longer to take one message is closed
FLOOD_FACTOR = 5          # a page refused this many bursts' worth of messages is closed
ERROR_REPLY_S = 1.0       # at most one error reply a second per page
OPERATOR_PAGES_KEPT = 8   # of max_connections, kept for the operator's console (half at most)
START_TIMEOUT_S = 10.0
STOP_TIMEOUT_S = 5.0


@dataclass(frozen=True)
class ServerSettings:
    host: str = '127.0.0.1'
    port: int = 8080                 # 0: a free port (see `HmiServer.port`)
    max_connections: int = 1000
    max_frame_bytes: int = 4096
    message_rate: float = 10.0       # messages a second per page ...
    message_burst: int = 20          # ... after this many
    heartbeat_s: float = 20.0        # WebSocket pings: a vanished peer is noticed
    keepalive_s: float = 5.0         # a 'tick' to each page when there is nothing else
    # s a connection may stay open without a whole request (before, aiohttp's 3630: 1,300 idle
    # sockets from anyone held every file the node may open, the token checked only later)
    idle_timeout_s: float = 10.0


@dataclass(frozen=True)
class Command:
    """A page's command for the node: `kind` 'answer' (payload request, accept), 'order'
    (payload fields) or 'bye' (the page went away)."""

    client: str
    view: str
    kind: str
    payload: dict


class Client:
    """One open page."""

    __slots__ = ('id', 'view', 'role', 'ws', 'bucket', 'replies', 'wake', 'sent_version',
                 'refused', 'last_error', 'feed_seq')

    def __init__(self, client_id: str, view: str, role: str, ws: web.WebSocketResponse,
                 bucket: TokenBucket):
        self.id, self.view, self.role, self.ws, self.bucket = client_id, view, role, ws, bucket
        self.feed_seq = dict.fromkeys(FEEDS, 0)       # the last item of each feed it got
        self.replies: deque[str] = deque(maxlen=REPLIES_KEPT)
        self.wake = asyncio.Event()
        self.sent_version = -1
        self.refused = 0
        self.last_error = -float('inf')


def load_pages(static_dir: Path = STATIC_DIR) -> dict[str, tuple[bytes, str]]:
    """The pages' bytes by path; a missing file is a broken install (FileNotFoundError)."""
    return {path: ((static_dir / name).read_bytes(), kind)
            for path, (name, kind) in PAGES.items()}


class HmiServer:
    def __init__(self, settings: ServerSettings, policy: AccessPolicy,
                 submit: Callable[[Command], bool], static_dir: Path = STATIC_DIR):
        self.settings = settings
        self.policy = policy
        self.submit = submit
        self.pages = load_pages(static_dir)
        self.clients: dict[str, Client] = {}
        self.views: dict[str, str] = {view: json.dumps({'type': 'view', 'view': view,
                                                        'connection': 'no connection to the '
                                                        'cell', 'cell': False})
                                      for view in VIEWS}
        self.versions = Counter()
        self.feeds = {name: deque(maxlen=kept) for name, kept in FEEDS.items()}  # (seq, text)
        self.feed_top = dict.fromkeys(FEEDS, 0)
        self.counts: Counter = Counter()
        self.port: int | None = None
        self._lock = threading.Lock()
        self._pending: dict[str, str] | None = None
        self._pending_feeds: dict[str, list] = {name: [] for name in FEEDS}
        self._flush_scheduled = False
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None
        self._runner: web.AppRunner | None = None

    # -- the thread ------------------------------------------------------------------------
    def start(self) -> int:
        """Bind and serve in a thread of its own; the port. OSError when it cannot bind."""
        started = threading.Event()
        failure: list[BaseException] = []
        self._thread = threading.Thread(target=self._serve, args=(started, failure),
                                        name='hmi web server', daemon=True)
        self._thread.start()
        if not started.wait(START_TIMEOUT_S):
            raise OSError(f'the web server did not start within {START_TIMEOUT_S:g} s')
        if failure:
            self._thread.join(STOP_TIMEOUT_S)
            raise failure[0]
        return self.port

    def _serve(self, started: threading.Event, failure: list) -> None:
        loop = asyncio.new_event_loop()
        asyncio.set_event_loop(loop)
        try:
            loop.run_until_complete(self._open())
        except BaseException as exc:  # noqa: BLE001 - handed to start(), which raises it
            failure.append(exc)
            started.set()
            loop.close()
            return
        self._loop = loop
        started.set()
        try:
            loop.run_forever()
        finally:
            loop.run_until_complete(loop.shutdown_asyncgens())
            loop.close()

    async def _open(self) -> None:
        app = web.Application(middlewares=[self._guard], client_max_size=1024)
        app.on_response_prepare.append(self._headers)
        for path in PAGES:
            app.router.add_get(path, self._page)
        app.router.add_get('/ws', self._websocket)
        self._runner = web.AppRunner(app, handle_signals=False, access_log=None,
                                     shutdown_timeout=1.0,
                                     keepalive_timeout=self.settings.idle_timeout_s)
        await self._runner.setup()
        site = web.TCPSite(self._runner, self.settings.host, self.settings.port,
                           reuse_address=True, backlog=256)
        try:
            await site.start()
        except BaseException:
            await self._runner.cleanup()
            raise
        self.port = self._runner.addresses[0][1]

    def stop(self) -> None:
        """Close every page (1001, going away) and the listening socket; join the thread."""
        loop, thread = self._loop, self._thread
        if loop is None or thread is None or not thread.is_alive():
            return
        closing = asyncio.run_coroutine_threadsafe(self._close(), loop)
        try:
            closing.result(STOP_TIMEOUT_S)
        except Exception:  # noqa: BLE001 - stopping anyway
            pass
        loop.call_soon_threadsafe(loop.stop)
        thread.join(STOP_TIMEOUT_S)

    async def _close(self) -> None:
        for client in list(self.clients.values()):
            try:
                await asyncio.wait_for(client.ws.close(code=WSCloseCode.GOING_AWAY,
                                                       message=b'the HMI is stopping'), 1.0)
            except (asyncio.TimeoutError, ConnectionError, RuntimeError):
                pass
        await self._runner.cleanup()

    # -- ROS -> pages (any thread) ---------------------------------------------------------
    def publish_views(self, views: dict[str, str]) -> None:
        """The latest text of each view; pages get it once, whatever the rate of calls."""
        with self._lock:
            self._pending = views
            if self._flush_scheduled or self._loop is None:
                return
            self._flush_scheduled = True
        self._loop.call_soon_threadsafe(self._flush)

    def append_feeds(self, items: dict[str, list[str]]) -> None:
        """New items (JSON texts) of the console's feeds; console pages get them in order."""
        with self._lock:
            for name, texts in items.items():
                pending = self._pending_feeds[name]
                pending.extend(texts)
                del pending[:-FEEDS[name]]
            if self._flush_scheduled or self._loop is None:
                return
            self._flush_scheduled = True
        self._loop.call_soon_threadsafe(self._flush)

    def reply(self, client: str, message: dict) -> None:
        """A command's result for the page that sent it."""
        if self._loop is not None:
            self._loop.call_soon_threadsafe(self._queue_reply, client, json.dumps(message))

    def _flush(self) -> None:
        with self._lock:
            pending, self._pending, self._flush_scheduled = self._pending, None, False
            feeds = {name: texts for name, texts in self._pending_feeds.items() if texts}
            self._pending_feeds = {name: [] for name in FEEDS}
        woken = set()
        for view, text in (pending or {}).items():
            if view in self.views and text != self.views[view]:
                self.views[view] = text
                self.versions[view] += 1
                woken.add(view)
        for name, texts in feeds.items():
            for text in texts:
                self.feed_top[name] += 1
                self.feeds[name].append((self.feed_top[name], text))
            woken.add(OPERATOR)
        for client in self.clients.values():
            if client.view in woken:
                client.wake.set()

    def _queue_reply(self, client_id: str, text: str) -> None:
        client = self.clients.get(client_id)
        if client is not None:
            client.replies.append(text)
            client.wake.set()

    # -- HTTP ------------------------------------------------------------------------------
    @web.middleware
    async def _guard(self, request: web.Request, handler):
        verdict = self.policy.check(request.headers.get('Host', ''),
                                    request.headers.get('Origin'),
                                    request.headers.get('Authorization'),
                                    request.cookies.get(COOKIE), request.query.get('token'),
                                    websocket=request.path == '/ws')
        if verdict.allowed and verdict.remember and request.path != '/ws':
            # the token came in the URL: keep it in a cookie and take it out of the URL, back
            # to a page of ours only (a path '//evil.example/' is another site to a browser)
            query = urlencode([(k, v) for k, v in request.query.items() if k != 'token'])
            page = request.path if request.path in PAGES else '/'
            response = web.HTTPSeeOther(page + (f'?{query}' if query else ''))
            # Secure over HTTPS, the proxy's too (docs/HMI.md's nginx sets X-Forwarded-Proto;
            # proxies in a chain list theirs after the client's): a forged header only keeps
            # the forger's own cookie off plain HTTP
            forwarded = request.headers.get('X-Forwarded-Proto', '').split(',')[0]
            secure = request.secure or forwarded.strip().lower() == 'https'
            response.set_cookie(COOKIE, verdict.token, httponly=True, samesite='Strict',
                                path='/', secure=secure)
            return response
        if verdict.allowed:
            page = request.query.get('view', 'worker') if request.path == '/ws' else \
                OPERATOR if request.path == '/operator' else 'worker'
            verdict = may_open(verdict.role, page)
        if not verdict.allowed:
            self.counts[f'refused_{verdict.status}'] += 1
            return web.Response(status=verdict.status, text=f'{verdict.status}: '
                                f'{verdict.reason}\n')
        request[ROLE] = verdict.role
        return await handler(request)

    async def _headers(self, request: web.Request, response: web.StreamResponse) -> None:
        response.headers.update(SECURITY_HEADERS)
        response.headers['Server'] = 'hrc-hmi'       # not the framework and its version

    async def _page(self, request: web.Request) -> web.Response:
        body, kind = self.pages[request.path]
        return web.Response(body=body, content_type=kind.split(';')[0],
                            charset='utf-8' if 'charset' in kind else None)

    # -- WebSocket -------------------------------------------------------------------------
    async def _websocket(self, request: web.Request) -> web.StreamResponse:
        view = request.query.get('view', 'worker')
        if view not in VIEWS:
            return web.Response(status=400, text=f'400: view must be one of {", ".join(VIEWS)}\n')
        most = self.settings.max_connections
        if view != OPERATOR:       # the operator's console gets in however many workers' are open
            most -= min(OPERATOR_PAGES_KEPT, most // 2)
        if len(self.clients) >= most:
            self.counts['refused_503'] += 1
            return web.Response(status=503, text=f'503: {len(self.clients)} pages are open, the '
                                f'most this HMI serves for a {view} page (max_connections, '
                                f'{OPERATOR_PAGES_KEPT} of them kept for the operator)\n')
        ws = web.WebSocketResponse(max_msg_size=self.settings.max_frame_bytes,
                                   heartbeat=self.settings.heartbeat_s, compress=False)
        await ws.prepare(request)
        client = Client(secrets.token_hex(8), view, request[ROLE], ws,
                        TokenBucket(self.settings.message_rate, self.settings.message_burst,
                                    time.monotonic_ns()))
        self.clients[client.id] = client
        self.counts['opened'] += 1
        client.replies.append(json.dumps({'type': 'hello', 'client': client.id, 'view': view,
                                          'role': client.role,
                                          'max_frame_bytes': self.settings.max_frame_bytes}))
        client.wake.set()
        sender = asyncio.ensure_future(self._sender(client))
        try:
            async for message in ws:
                if message.type == WSMsgType.TEXT:
                    await self._receive(client, message.data)
                elif message.type == WSMsgType.BINARY:
                    self._error(client, 'binary frames are not understood: send JSON text')
                elif message.type == WSMsgType.ERROR:
                    self.counts['frames_refused'] += 1
                    break
        finally:
            self.clients.pop(client.id, None)
            sender.cancel()
            self.counts['closed'] += 1
            self.submit(Command(client.id, view, 'bye', {}))
        return ws

    async def _sender(self, client: Client) -> None:
        ws = client.ws
        try:
            while not ws.closed:
                try:
                    await asyncio.wait_for(client.wake.wait(), self.settings.keepalive_s)
                except asyncio.TimeoutError:
                    client.replies.append('{"type": "tick"}')
                client.wake.clear()
                while client.replies:
                    await asyncio.wait_for(ws.send_str(client.replies.popleft()),
                                           SEND_TIMEOUT_S)
                version = self.versions[client.view]
                if version != client.sent_version:
                    client.sent_version = version
                    await asyncio.wait_for(ws.send_str(self.views[client.view]), SEND_TIMEOUT_S)
                if client.view == OPERATOR:
                    for text in self._feed_messages(client):
                        await asyncio.wait_for(ws.send_str(text), SEND_TIMEOUT_S)
        except asyncio.TimeoutError:
            self.counts['closed_slow'] += 1
            await ws.close(code=WSCloseCode.POLICY_VIOLATION, message=b'the page stopped '
                           b'reading')
        except (ConnectionError, RuntimeError):
            pass         # the page went away: the receiving side cleans up

    def _feed_messages(self, client: Client) -> list[str]:
        """What of each feed this page has not had: the items after its last one, or the
        whole ring (reset) when it is new or the ring moved past it."""
        messages = []
        for name, ring in self.feeds.items():
            seen, top = client.feed_seq[name], self.feed_top[name]
            if top == seen or not ring:
                continue
            reset = seen == 0 or seen < ring[0][0] - 1
            items = [text for seq, text in ring if reset or seq > seen]
            client.feed_seq[name] = top
            messages.append(f'{{"type":"feed","name":"{name}","reset":'
                            f'{"true" if reset else "false"},"items":[{",".join(items)}]}}')
        return messages

    def _error(self, client: Client, text: str) -> None:
        self.counts['bad_messages'] += 1
        now = time.monotonic()
        if now - client.last_error >= ERROR_REPLY_S:
            client.last_error = now
            self._queue_reply(client.id, json.dumps({'type': 'error', 'text': text}))

    async def _receive(self, client: Client, data: str) -> None:
        if not client.bucket.take(time.monotonic_ns()):
            self.counts['rate_limited'] += 1
            client.refused += 1
            if client.refused >= FLOOD_FACTOR * self.settings.message_burst:
                self.counts['closed_flood'] += 1
                await client.ws.close(code=WSCloseCode.POLICY_VIOLATION,
                                      message=b'too many messages')
                return
            self._error(client, f'too many messages: at most {self.settings.message_rate:g} a '
                        'second')
            return
        try:
            message = json.loads(data)
        except (ValueError, RecursionError):
            self._error(client, 'malformed JSON')
            return
        kind = message.get('type') if isinstance(message, dict) else None
        if kind == 'answer':
            payload = {'request': message.get('request'), 'accept': message.get('accept')}
        elif kind == 'order' and not may_order(client.role):
            self.counts['refused_403'] += 1
            self._queue_reply(client.id, json.dumps({
                'type': 'order_result', 'ok': False, 'code': 403, 'status': 'refused',
                'ref': message.get('ref') if isinstance(message.get('ref'), int) else None,
                'text': "refused (403): only the operator queues tasks, and this page has the "
                        "worker's access token"}))
            return
        elif kind == 'order' and client.view == 'operator':
            ref = message.get('ref')
            payload = {'fields': {k: message[k] for k in ('priority', 'duration', 'nature')
                                  if k in message},
                       'ref': ref if isinstance(ref, int) and not isinstance(ref, bool)
                       and 0 <= ref < 2**31 else None}
        elif kind == 'order':
            self._error(client, 'task orders come from the operator page (/operator)')
            return
        else:
            self._error(client, 'unknown message: expected {"type": "answer", ...} or '
                        '{"type": "order", ...}')
            return
        if not self.submit(Command(client.id, client.view, kind, payload)):
            self.counts['busy'] += 1
            self._queue_reply(client.id, json.dumps({
                'type': f'{kind}_result', 'ok': False, 'code': 'busy', 'status': 'refused',
                'request': payload.get('request'), 'ref': payload.get('ref'),
                'accept': payload.get('accept'),
                'text': 'the HMI is busy: nothing was sent, try again'}))

    def stats(self) -> dict:
        """Counts for /diagnostics (read from another thread: a snapshot)."""
        views = Counter(client.view for client in list(self.clients.values()))
        return {'pages_open': sum(views.values()), 'worker_pages': views['worker'],
                'operator_pages': views['operator'], **dict(self.counts)}
