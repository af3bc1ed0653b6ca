"""``mfvs view``: a live Foxglove WebSocket server for a running stack (Foxglove's SDK serves it): the camera with
the detected and goal corners, the error norm, the twists, the joints against their limits, the arm, camera and tag
in 3D, the services' statuses as logs, and every service's health. Open it in Foxglove ("Open connection",
ws://HOST:PORT) with the layout ``deploy/foxglove/mfvs.json``.
"""
from __future__ import annotations

import threading

import foxglove

from protocol.keys import Keys
from services.observe.foxglove_view import VIEW
from services.runtime.jsonsafe import json_safe
from services.runtime.service import query_health
from services.observe.record import ALL, Tap

DEFAULT_PORT = 8765
#: how often the services' health is asked (s)
HEALTH_PERIOD_S = 1.0
HEALTH_TOPIC = f"{VIEW}/health"


class Viewer(Tap):
    """A WebSocket server on ``host:port`` (0: a free port, :attr:`port` says which) showing the stack while open;
    the services' health once a second on ``/view/health``."""

    def __init__(self, session, keys: Keys, host: str = "127.0.0.1", port: int = DEFAULT_PORT,
                 patterns=ALL) -> None:
        self.host, self.requested_port = host, port
        super().__init__(session, keys, patterns, raw=False, view=True)
        self.health = foxglove.Channel(HEALTH_TOPIC, schema={"type": "object", "title": "mfvs.Health"},
                                       context=self.context)
        self._session, self._keys = session, keys
        self._stop = threading.Event()
        self._health_thread = threading.Thread(target=self._poll_health, name="mfvs-view-health", daemon=True)
        self._health_thread.start()

    def open_sinks(self) -> None:
        self._server = foxglove.start_server(name="mfvs", host=self.host, port=self.requested_port,
                                             context=self.context)
        self.port = self._server.port

    def close_sinks(self) -> None:
        self._stop.set()
        self._server.stop()

    def _poll_health(self) -> None:
        while not self._stop.wait(HEALTH_PERIOD_S):
            try:
                found = query_health(self._session, self._keys, timeout_s=0.8)
            except Exception:  # the session is closing
                return
            services = {name: {"healthy": h.healthy, "state": h.state, "rates_hz": dict(h.rates_hz),
                               "degraded": list(h.degraded), "detail": h.detail} for name, h in found.items()}
            if not self._stop.is_set():
                self.health.log(json_safe({"services": services,
                                            "unhealthy": sorted(k for k, v in services.items()
                                                                if not v["healthy"])}))
