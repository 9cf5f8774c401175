import numpy as np
import pytest
from numpy.testing import assert_allclose, assert_array_equal

from pipeline.errors import ParameterError, PipelineError
from pipeline.quantize import (
    QuantizerConfig,
    auto_delta,
    dequantize,
    pack_codes,
    packed_size,
    quantize,
    quantize_frames,
    quantize_real,
    unit_dither,
    unpack_codes,
)
from radar_driver.model import simulate_frames


def test_paper_quantizer_values():
    lam = np.array([-1.2, -0.2, 0.0, 0.3, 0.99, 1.0, 2.5])
    assert_allclose(quantize_real(lam, 1.0), [-1.5, -0.5, 0.5, 0.5, 0.5, 1.5, 2.5])


def test_b_bit_levels_saturate():
    f = np.array([[[-5.0 + 0.1j, 0.2 - 0.7j], [3.9 + 9.0j, -0.01 + 0j]]])  # (1, 2, 2)
    codes = quantize(f, 1.0, bits=3)
    assert codes.dtype == np.uint8 and codes.shape == (1, 2, 2, 2)
    # levels q + 1/2 for q in [-4, 3]
    assert_allclose(dequantize(codes, 1.0, 3), [[[-3.5 + 0.5j, 0.5 - 0.5j], [3.5 + 3.5j, -0.5 + 0.5j]]])
    one = dequantize(quantize(f, 1.0, bits=1), 1.0, 1)
    assert set(np.unique(np.r_[one.real.ravel(), one.imag.ravel()])) <= {-0.5, 0.5}
    assert quantize(f, 1.0, bits=12).dtype == np.uint16


def test_dithered_quantizer_is_unbiased(rng):
    delta = 2.0
    lam = np.array([-0.9, -0.35, 0.0, 0.2, 0.77])
    n = 200_000
    xi = rng.uniform(-delta / 2, delta / 2, (n, lam.size))
    mean = quantize_real(lam + xi, delta).mean(axis=0)
    assert_allclose(mean, lam, atol=0.01)
    # without dither the 1-bit quantizer is biased: every input maps to +-delta/2
    assert_allclose(quantize_real(lam, delta), [-1.0, -1.0, 1.0, 1.0, 1.0])


def test_dither_keeps_one_bit_when_delta_covers_the_signal(cfg, rng):
    g = simulate_frames([[30.0, 60.0]], [[10.0, -40.0]], [[1.0, 0.4j]], cfg)
    delta = auto_delta(g)
    xi = delta[:, None, None] * (rng.uniform(-0.5, 0.5, g.shape) + 1j * rng.uniform(-0.5, 0.5, g.shape))
    lam = g + xi
    vals = np.r_[quantize_real(lam.real, delta[0]).ravel(), quantize_real(lam.imag, delta[0]).ravel()]
    assert set(np.unique(vals)) <= {-delta[0] / 2, delta[0] / 2}


def test_auto_delta_is_smallest_one_bit_step():
    f = np.zeros((2, 3, 2), complex)
    f[0, 1, 1] = 0.3 - 0.8j
    f[1, 2, 0] = -0.5 + 0.1j
    assert_allclose(auto_delta(f), [1.6, 1.0])
    assert_allclose(auto_delta(f, margin=0.25), [2.0, 1.25])
    assert auto_delta(np.zeros((1, 4, 2), complex))[0] > 0


def test_dither_reproducible_from_seed_and_sequence():
    a = unit_dither(7, [4, 5, 6], 512)
    assert a.shape == (3, 512, 2)
    assert_array_equal(unit_dither(7, 5, 512)[0], a[1])
    assert not np.array_equal(unit_dither(8, 5, 512)[0], a[1])
    assert np.abs(a.real).max() <= 0.5 and np.abs(a.imag).max() <= 0.5
    # explicitly: SeedSequence(seed, spawn_key=(seq,)), real parts then imaginary parts
    u = np.random.default_rng(np.random.SeedSequence(7, spawn_key=(5,))).random((2, 512, 2)) - 0.5
    assert_array_equal(a[1], u[0] + 1j * u[1])


def test_quantize_frames_regenerates_its_dither(cfg):
    g = simulate_frames([[30.0], [12.0]], [[10.0], [-5.0]], [[1.0], [0.5]], cfg)
    qcfg = QuantizerConfig(bits=1, alpha=0.55, dither_seed=3)
    q = quantize_frames(g, qcfg, seq=[10, 11])
    assert q.codes.shape == (2, 512, 2, 2)
    assert_array_equal(quantize(g, q.delta, 1, q.dither()), q.codes)
    none = quantize_frames(g, QuantizerConfig(alpha=0.0), seq=[10, 11])
    assert_array_equal(none.codes, quantize(g, none.delta, 1))
    fixed = quantize_frames(g, QuantizerConfig(bits=4, delta=0.25), seq=[0, 1])
    assert_allclose(fixed.delta, [0.25, 0.25])


@pytest.mark.parametrize("bits", [1, 2, 3, 5, 8, 11, 16])
def test_pack_unpack_round_trip(bits, rng):
    codes = rng.integers(0, 1 << bits, (4, 37, 2, 2))
    packed = pack_codes(codes, bits)
    n = 37 * 4
    assert packed.shape == (4, packed_size(n, bits)) and packed.dtype == np.uint8
    assert_array_equal(unpack_codes(packed, bits, n).reshape(codes.shape), codes)


def test_pack_exact_bytes():
    assert pack_codes(np.array([[1, 0, 1, 1, 0, 0, 0, 1, 1]]), 1).tolist() == [[0b10110001, 0b10000000]]
    # 3-bit codes 5, 2, 7 -> 101 010 111 -> 10101011 1(0000000)
    assert pack_codes(np.array([[5, 2, 7]]), 3).tolist() == [[0xAB, 0x80]]
    # a 1-bit frame of M = 512 on two antennas is 256 bytes
    assert packed_size(512 * 2 * 2, 1) == 256


@pytest.mark.parametrize(
    "call, fragment",
    [
        (lambda f: quantize(f, 1.0, bits=0), "bits=0"),
        (lambda f: quantize(f, 0.0, bits=1), "delta must be finite and > 0"),
        (lambda f: quantize(f, -1.0, bits=1), "delta"),
        (lambda f: quantize(f, np.ones(3), bits=1), "delta must be a scalar or of shape \\(2,\\)"),
        (lambda f: quantize(f, 1.0, bits=1, dither=np.zeros((2, 8, 2))), "dither shape"),
        (lambda f: quantize(f[0], 1.0, bits=1), "shape \\(B, M, 2\\)"),
        (lambda f: QuantizerConfig(alpha=1.5), "alpha=1.5"),
        (lambda f: QuantizerConfig(alpha=-0.1), "alpha"),
        (lambda f: QuantizerConfig(delta="big"), "delta='big'"),
        (lambda f: QuantizerConfig(bits=17), "bits=17"),
        (lambda f: quantize_frames(f, QuantizerConfig(), seq=[1, 2, 3]), "seq has shape"),
        (lambda f: unpack_codes(np.zeros((1, 3), np.uint8), 1, 100), "need 13 bytes"),
        (lambda f: pack_codes(np.array([[4]]), 2), "codes must lie in"),
        (lambda f: dequantize(np.full((1, 1, 2, 2), 2), 1.0, 1), "beyond the 2 levels"),
    ],
)
def test_bad_parameters_raise_clear_value_errors(call, fragment):
    f = np.ones((2, 4, 2), complex)
    with pytest.raises(ParameterError, match=fragment) as info:
        call(f)
    assert isinstance(info.value, ValueError) and isinstance(info.value, PipelineError)
