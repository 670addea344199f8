"""Which requests the viewer's server answers: its page only to a Host it is known by, its websocket (the rendered
avatar and the controls) only to a page of its own origin. Other web pages the user has open cannot connect.

A browser lets any page open a websocket to any address, 127.0.0.1 included, and sends the page's origin with it
(cross-site websocket hijacking); a DNS name of an attacker's that turns into 127.0.0.1 (DNS rebinding) reaches
the HTTP side too, with that name as its Host. So a request is answered only when its Host is a loopback name
(localhost, *.localhost, 127.0.0.0/8, ::1), an IP address (which no DNS answer can rebind), the `--host` value,
or the host of an origin passed to `--allow-origin`, each with the port served; and a websocket only when its
Origin is absent (not a browser) or names the same host and port as its Host, or is an allowed origin.

viser has no hook for this: `guarded_server` builds a viser server whose websockets server runs this check before
viser's own request handling (viser's files are left as they are).
"""
from __future__ import annotations

import http
import ipaddress
import sys
import threading
from dataclasses import dataclass, field
from urllib.parse import urlsplit

LOOPBACK_NAMES = ("localhost",)
# The refusals said on stderr, each once (a refused page's client reconnects every second); then no more.
MAX_REPORTED = 64


def _authority(text: str) -> tuple[str, int | None] | None:
    """(lower-case host without brackets, port or None) of `host[:port]`; None when it is not one."""
    try:
        parts = urlsplit(f"//{text}")
        port = parts.port
    except ValueError:
        return None
    if not parts.hostname or parts.username is not None or parts.password is not None or parts.path or parts.query:
        return None
    return parts.hostname, port


def parse_origin(origin: str) -> tuple[str, str, int | None]:
    """(scheme, host, port or None) of an origin `scheme://host[:port]`; ValueError naming it when it is not one."""
    try:
        parts = urlsplit(origin.strip())
        port = parts.port
    except ValueError:
        parts, port = None, None
    if (parts is None or parts.scheme.lower() not in ("http", "https") or not parts.hostname
            or parts.path not in ("", "/") or parts.query or parts.fragment or parts.username is not None):
        raise ValueError(f"{origin!r} is not an origin: expected http(s)://HOST[:PORT], as the browser's address bar "
                         "shows it for the viewer's page (a tunnel's address, say)")
    return parts.scheme.lower(), parts.hostname, port


def _needs_no_naming(name: str) -> bool:
    """A loopback name, or an IP address: names that no DNS answer gives an attacker's page."""
    if name in LOOPBACK_NAMES or name.endswith(".localhost"):
        return True
    try:
        ipaddress.ip_address(name)
    except ValueError:
        return False
    return True


@dataclass
class RequestGuard:
    """The check for a server bound to `host` (the `--host` value) that admits the pages of `allowed_origins`
    (`--allow-origin` values) besides its own."""

    host: str = "127.0.0.1"
    allowed_origins: tuple[str, ...] = ()
    _origins: set = field(init=False, repr=False)
    _reported: set = field(init=False, repr=False, default_factory=set)
    _lock: threading.Lock = field(init=False, repr=False, default_factory=threading.Lock)

    def __post_init__(self):
        self._origins = {parse_origin(origin) for origin in self.allowed_origins}

    def refusal(self, host_values: list[str], origin_values: list[str], websocket: bool, port: int) -> str | None:
        """Why a request to `port` with these Host and Origin header values is refused, or None to answer it."""
        if len(host_values) != 1 or (host := _authority(host_values[0])) is None:
            return f"a request without one valid Host header ({host_values})"
        name, host_port = host
        allowed_hosts = {(o_host, o_port) for _, o_host, o_port in self._origins}
        served = host_port == port and (_needs_no_naming(name) or name == self.host.strip("[]").lower())
        if not served and host not in allowed_hosts:
            return (f"Host {host_values[0]!r}: not a name this viewer is served under (a loopback name, an address, "
                    "--host, or an --allow-origin host, with its port)")
        if not websocket or not origin_values:
            return None
        if len(origin_values) != 1:
            return f"a websocket with {len(origin_values)} Origin headers"
        try:
            origin = parse_origin(origin_values[0])
        except ValueError:
            return f"a websocket from the page of origin {origin_values[0]!r}, which is not this viewer's"
        if origin[1:] == host or origin in self._origins:
            return None
        return (f"a websocket from the page of origin {origin_values[0]!r}, which is not this viewer's "
                f"({host_values[0]}); pass --allow-origin {origin_values[0]} to admit it")

    def in_front_of(self, inner):
        """A websockets `process_request` that refuses (403) what `refusal` refuses, else hands on to `inner`."""

        def process_request(connection, request):
            headers = request.headers
            websocket = "websocket" in headers.get("Upgrade", "").lower()
            why = self.refusal(headers.get_all("Host"), headers.get_all("Origin"), websocket,
                               connection.local_address[1])
            if why is not None:
                self._report(why)
                return connection.respond(http.HTTPStatus.FORBIDDEN, f"refused: {why}\n")
            return inner(connection, request) if inner is not None else None

        return process_request

    def _report(self, why: str) -> None:
        with self._lock:
            if why in self._reported or len(self._reported) >= MAX_REPORTED:
                return
            self._reported.add(why)
        print(f"view: refused {why}", file=sys.stderr, flush=True)


_SERVE_LOCK = threading.Lock()  # one guarded construction at a time: the wrapper below is in place meanwhile


def guarded_server(guard: RequestGuard, **viser_arguments):
    """A `viser.ViserServer(**viser_arguments)` whose websockets server checks each request with `guard` first.

    viser calls websockets.asyncio.server.serve while it starts (on its server thread, before its constructor
    returns); for that time the name holds a wrapper that puts `guard` in front of viser's `process_request`. A
    viser that starts otherwise is refused: the viewer does not serve unchecked."""
    import viser
    import websockets.asyncio.server as websockets_server

    original, wrapped = websockets_server.serve, []

    def serve(handler, *args, process_request=None, **kwargs):
        wrapped.append(handler)
        return original(handler, *args, process_request=guard.in_front_of(process_request), **kwargs)

    with _SERVE_LOCK:
        websockets_server.serve = serve
        try:
            server = viser.ViserServer(**viser_arguments)
        finally:
            websockets_server.serve = original
    if not wrapped:
        server.stop()
        raise RuntimeError(f"viser {viser.__version__} did not start its server through websockets.asyncio.server."
                           "serve, so the viewer cannot check which pages connect; it does not serve. Install a "
                           "viser the project supports (pip install -e '.[viewer]')")
    return server
