"""The maths of qradar: quantize with dither, estimate the noise, back-project (PBP),
decode (PBP, QIHT, cml), calibrate the front end, gate, track and integrate.

Pure functions on numpy arrays, batch axis first: the same call serves one live frame
and a Monte Carlo batch. This package imports numpy, scipy and numba (and
``radar_driver``'s signal model), never the bus, the wire formats or the nodes.
"""
