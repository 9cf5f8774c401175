"""Every PBP target says how likely noise alone makes it (issue 41, item 3): ``p_value``, the
chance that the largest bin of white Gaussian noise in the gate reaches its statistic. On
noise-only frames the p-values are uniform (p < a in a share a of the frames, within 1.25x),
1-bit dithered or not; a strong target's is ~0; it reaches the targets JSON."""

import json

import numpy as np
import pytest

from radar_driver.model import RadarConfig, simulate_frames
from pipeline.dsp.decode import Decoder, DecoderConfig
from pipeline.dsp.localize import cfar_p_value, cfar_threshold
from pipeline.dsp.quantize import QuantizerConfig, quantize_frames

CFG = RadarConfig()


def noise(frames: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    shape = (frames, CFG.n_measurements, 2)
    return 0.1 * (rng.standard_normal(shape) + 1j * rng.standard_normal(shape))


def test_the_p_value_inverts_the_threshold():
    for pfa, cells in ((1e-3, 256), (1e-2, 200)):  # the threshold's union bound is the p-value for small pfa
        assert cfar_p_value(10 * np.log10(cfar_threshold(pfa, cells)), cells) == pytest.approx(pfa, rel=0.01)
    assert cfar_p_value(np.array([-300.0, 300.0]), 256) == pytest.approx([1.0, 0.0])


@pytest.mark.parametrize("alpha", [None, 0.45])
def test_on_noise_alone_the_p_values_are_uniform(alpha):
    g = noise(8000, 3)
    frames = g if alpha is None else quantize_frames(g, QuantizerConfig(alpha=alpha, bits=1), np.arange(len(g)))
    p = Decoder(DecoderConfig(algo="pbp")).decode_batch(frames, CFG, 1).p_value[:, 0]
    for a in (0.01, 0.05, 0.1, 0.5):
        assert a / 1.25 <= (p < a).mean() <= 1.25 * a, (a, (p < a).mean())


def test_a_strong_target_is_sure_and_says_so_in_its_message():
    g = simulate_frames(np.array([[30.3]]), np.array([[10.0]]), np.array([[0.5]]), CFG) + noise(1, 5)
    q = quantize_frames(g, QuantizerConfig(alpha=0.45, bits=1), np.arange(1))
    det = Decoder(DecoderConfig(algo="pbp", auto_k=True)).decode_batch(q, CFG, 3)
    (target, *_) = det.frame(0)
    assert target["p_value"] < 1e-12 and abs(target["range_m"] - 30.3) < CFG.range_resolution_m
    assert json.loads(json.dumps(target))["p_value"] == target["p_value"]
