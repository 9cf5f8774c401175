"""The processing side of qradar: the dithered quantizer, the decoders (PBP, QIHT), the
paper's Monte Carlo, the wire formats and the zenoh nodes. It imports ``radar_driver``
and nothing of ``replay`` or ``qradar``; the math modules (quantize, localize, decode,
montecarlo) do not import zenoh."""
