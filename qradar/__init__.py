"""The composition root of qradar: the ``qradar`` command and the main job.

The libraries import one way, ``radar_driver`` <- ``pipeline`` <- ``replay`` <- ``qradar``
(tests/test_layering.py checks it): ``radar_driver`` is the sensor (model, codec, serial
session, simulator, frame sources), ``pipeline`` the processing (quantizer, decoders,
wire formats, zenoh nodes), ``replay`` the recordings (MCAP, player, re-processing).
Only this package knows all three: :mod:`qradar.cli` parses commands and delegates,
:mod:`qradar.run` wires the main job (simulated sensors, driver, quantizer, localizer,
recorder) together.
"""
