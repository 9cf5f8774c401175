"""MCAP recording, replay and offline re-processing (see the MCAP issue)."""
