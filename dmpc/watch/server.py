"""Serving the page: a Bokeh server in this process, on loopback unless told otherwise.

The server runs on the main thread's event loop until Ctrl-C (or SIGTERM); the bus observer
feeds the run's state from a thread of its own, and a run folder is polled from the loop.
Every browser tab gets its own document (:mod:`.page`); BokehJS is served from the Bokeh
package itself, so the page needs no internet.
"""
from __future__ import annotations

import ipaddress
import sys
from collections.abc import Callable

from dmpc.watch.state import RunState

POLL_MS = 500  # how often a run folder is read for new steps


def url_host(address: str) -> str:
    """The host part of the page's URL for a listen address."""
    if address in ("0.0.0.0", "::", ""):
        return "127.0.0.1"
    try:
        if ipaddress.ip_address(address).version == 6:
            return f"[{address}]"
    except ValueError:
        pass
    return address


def origins(address: str, port: int) -> list[str]:
    """The hosts a browser may open the page's websocket from, for a page served on ``address``
    and ``port``.

    On loopback: ``localhost`` and ``127.0.0.1``. On another address: that address too, and
    every host when listening on all interfaces (the page is read-only; the address is the
    user's choice).
    """
    hosts = [f"localhost:{port}", f"127.0.0.1:{port}"]
    if address in ("0.0.0.0", "::"):
        return ["*"]
    if address not in ("127.0.0.1", "localhost"):
        hosts.append(f"{url_host(address)}:{port}")
    return hosts


class WatchServer:
    """The page's web server.

    Parameters
    ----------
    state : RunState
    live : bool
        The run is watched over the bus.
    address : str
        The address to listen on (``127.0.0.1`` by default).
    port : int
        0 for any free port.
    poll : callable, optional
        Called every ``POLL_MS`` ms on the server's loop (reads a run folder).
    """

    def __init__(self, state: RunState, live: bool, address: str = "127.0.0.1", port: int = 0,
                 poll: Callable[[], None] | None = None) -> None:
        from bokeh.application import Application
        from bokeh.application.handlers.function import FunctionHandler
        from bokeh.server.server import BaseServer
        from bokeh.server.tornado import BokehTornado
        from bokeh.server.util import bind_sockets
        from tornado.httpserver import HTTPServer
        from tornado.ioloop import IOLoop, PeriodicCallback

        from dmpc.watch.page import page_factory  # start-up time: bokeh once the server starts, as above

        self._loop = IOLoop.current()
        # bound first: the websocket origins name the port
        sockets, self._port = bind_sockets(address, port)
        app = Application(FunctionHandler(page_factory(state, live)))
        self.url = f"http://{url_host(address)}:{self._port}/"
        tornado = BokehTornado({"/": app}, extra_websocket_origins=origins(address, self._port))
        http = HTTPServer(tornado)
        http.start(1)
        http.add_sockets(sockets)
        self._server = BaseServer(self._loop, tornado, http)
        self._poll = PeriodicCallback(poll, POLL_MS) if poll is not None else None

    @property
    def port(self) -> int:
        return self._port

    def serve(self, on_ready: Callable[[str], None] | None = None) -> None:
        """Serve until Ctrl-C or SIGTERM (raised as KeyboardInterrupt), then stop; ``on_ready`` is called
        with the page's address once it is served."""
        self._server.start()
        if self._poll is not None:
            self._poll.start()
        if on_ready is not None:
            self._loop.add_callback(on_ready, self.url)
        try:
            self._loop.start()
        except KeyboardInterrupt:
            pass
        finally:
            self.stop()

    def stop(self) -> None:
        if self._poll is not None:
            self._poll.stop()
        try:
            self._server.stop()
        except Exception:  # noqa: BLE001 - stopping twice, or a half-started server
            pass
        self._loop.stop()


def announce(url: str) -> None:
    """Print the live view's address ``url``."""
    print(f"live view: {url} (Ctrl-C to stop)", file=sys.stdout, flush=True)
