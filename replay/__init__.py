"""Recordings: MCAP writing and tolerant reading, the recorder node, the player, a
recording as a frame source, and offline re-processing. It imports ``radar_driver`` and
``pipeline``, never ``experiments`` or ``qradar``; re-processing does not import zenoh."""
