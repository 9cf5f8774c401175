"""The node runtime and the nodes of the stream: intake before the copy and its budgets
(``intake``, ``budget``), the fair queue, counters and histograms, per-sensor expiry and
memory, the transport (zenoh, or in memory for tests), ``run_nodes`` (``runtime``), the
codec of each input kind (``frame_codec``), and the nodes (``stream``: source, quantize,
localize; ``tracker``: the localizer's tracks)."""
