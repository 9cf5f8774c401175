"""Exception root of the ``replay`` package: every error raised here is a ReplayError."""


class ReplayError(Exception):
    """Root of all replay errors (bad files, missing channels, bad options)."""


class NotMcapError(ReplayError):
    """The file is not an MCAP file."""


class NoQradarChannelsError(ReplayError):
    """The MCAP file holds no qradar channels."""


class Damage(ReplayError):
    """Bytes of an MCAP file that do not read as the record they should be (replay.mcapcheck)."""


class UnwritableMessage(ReplayError):
    """A message a recording cannot hold (a time out of range, a file's channels all taken),
    refused before any byte of it is written. ``kind``: ``time``, ``shape`` or ``channels``."""

    def __init__(self, kind: str, reason: str):
        super().__init__(reason)
        self.kind = kind


class OutputExists(ReplayError):
    """An output exists already and the command was not told to replace it (``--force``)."""


class RecordingExists(OutputExists):
    """A recording's path exists already (recordings are created exclusively)."""

    @classmethod
    def at(cls, path) -> "RecordingExists":
        return cls(f"{path} exists: qradar does not overwrite a recording; choose another name or remove it "
                   "(--force replaces it)")


class CalibrationRefused(ReplayError):
    """A calibration whose checks say its inputs are wrong (not written)."""
