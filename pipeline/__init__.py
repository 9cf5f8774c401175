"""The processing side of qradar: dithered quantization, PBP localization, the Monte
Carlo of the paper, and (later) the zenoh nodes and wire formats."""
