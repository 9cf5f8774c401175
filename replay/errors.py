"""Exception root of the ``replay`` package: every error raised here is a ReplayError."""


class ReplayError(Exception):
    """Root of all replay errors (bad files, missing channels, bad options)."""


class NotMcapError(ReplayError):
    """The file is not an MCAP file."""


class NoQradarChannelsError(ReplayError):
    """The MCAP file holds no qradar channels."""
