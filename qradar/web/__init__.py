"""``qradar view --web PORT`` and ``qradar run --web PORT``: the live stream (or a
recording, with play, pause and seek) in a web page that needs nothing installed: each
sensor's range profile per receiver, the targets and tracks in the world's x-y plane with
their ids and uncertainty ellipses, the truth when known, and the nodes' health.

The page (``static/``: HTML, a script, a style and the uPlot plotting library, vendored
with its licence) is package data: no CDN, it works offline. The server is the standard
library's (:mod:`qradar.web.server`, Server-Sent Events); the node is a
:class:`qradar.liveview.LiveView` like the Foxglove view (:mod:`qradar.web.node`); the
events are :mod:`qradar.web.events`; a recording is played by :mod:`qradar.web.recording`.
docs/stream.md, section "Live view in the browser", says what the page shows."""

from .node import WebConfig, WebView

__all__ = ["WebConfig", "WebView"]
