"""The composition root of qradar: the ``qradar`` command and the main job.

The libraries import one way, ``radar_driver`` <- ``pipeline`` <- ``replay`` <- ``qradar``
(tests/test_layering.py checks it): ``radar_driver`` is the sensor (model, codec, serial
session, simulator, frame sources), ``pipeline`` the processing (quantizer, decoders,
wire formats, zenoh nodes), ``replay`` the recordings (MCAP, player, re-processing).
Only this package knows all three: :mod:`qradar.cli` parses commands and delegates,
:mod:`qradar.run` wires the main job (simulated sensors, driver, quantizer, localizer,
recorder) together.

:mod:`qradar.api` is the Python interface (docs/api.md); its names are reachable from
``qradar`` itself (``qradar.open_recording``), imported on first use so that a command
does not pay for them.
"""

from functools import cache


@cache
def _version() -> str:
    """The installed package's version ("0+unknown" from a source tree never installed); read
    on first use: importing ``importlib.metadata`` and scanning site-packages cost every
    process 30 ms of CPU at start, and only ``--version`` and recordings need it."""
    from importlib import metadata

    try:
        return metadata.version("qradar")
    except metadata.PackageNotFoundError:
        return "0+unknown"


#: the names of qradar.api reachable as qradar.<name>
_API = ("Frames", "Quantized", "Targets", "Tracks", "Recording", "open_recording", "quantize", "decode", "montecarlo",
        "alpha_sweep", "MonteCarloConfig", "MonteCarloResult", "ReprocessConfig", "ReprocessResult",
        "QuantizerConfig", "DecoderConfig", "RadarConfig", "Detections", "SimScene", "load_scene",
        "position_error_m", "score", "score_frames", "Score", "FrameScores", "DETECTION_DISTANCE_M", "ReplayError")


#: the public names of ``import qradar`` (``from qradar import *``, tab completion)
__all__ = ["__version__", *_API]


def __dir__() -> list[str]:
    """The module's own names and the API's (imported on first use, listed at once)."""
    return sorted(set(globals()) | set(_API))


def __getattr__(name: str):
    """The names of :mod:`qradar.api`, imported on first use (submodules import as usual), and
    ``__version__``."""
    if name == "__version__":
        return _version()
    if name in _API:
        from importlib import import_module

        return getattr(import_module("qradar.api"), name)
    raise AttributeError(f"module 'qradar' has no attribute {name!r}")
