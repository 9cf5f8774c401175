import numpy as np
import pytest
from numpy.testing import assert_allclose, assert_array_equal

from pipeline.errors import ParameterError, PipelineError
from pipeline.dsp.quantize import (
    DITHER_COUNTER,
    DITHER_SEEDSEQ,
    QuantizedFrames,
    QuantizerConfig,
    auto_delta,
    dequantize,
    pack_codes,
    packed_size,
    quantize,
    quantize_frames,
    quantize_real,
    sensor_dither_seed,
    sensor_dither_seeds,
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
    for gen in (DITHER_COUNTER, DITHER_SEEDSEQ):
        a = unit_dither(7, [4, 5, 6], 512, gen)
        assert a.shape == (3, 512, 2)
        assert_array_equal(unit_dither(7, 5, 512, gen)[0], a[1])
        assert not np.array_equal(unit_dither(8, 5, 512, gen)[0], a[1])
        assert np.abs(a.real).max() <= 0.5 and np.abs(a.imag).max() <= 0.5
    # the seedseq generator, bit for bit as before: SeedSequence(seed, spawn_key=(seq,)), real parts then imaginary
    u = np.random.default_rng(np.random.SeedSequence(7, spawn_key=(5,))).random((2, 512, 2)) - 0.5
    assert_array_equal(unit_dither(7, [4, 5, 6], 512, DITHER_SEEDSEQ)[1], u[0] + 1j * u[1])
    assert_array_equal(unit_dither(7, 5, 512), unit_dither(7, 5, 512, DITHER_COUNTER))  # the default


M64 = 2**64 - 1
G, C1, C2 = 0x9E3779B97F4A7C15, 0xBF58476D1CE4E5B9, 0x94D049BB133111EB


def counter_reference(seed: int, seq: int, m: int) -> np.ndarray:
    """docs/wire-formats.md's counter generator in plain Python integers: (M, 2) complex."""
    def mix(z):
        z ^= z >> 30
        z = z * C1 & M64
        z ^= z >> 27
        z = z * C2 & M64
        return z ^ (z >> 31)

    k = mix(seed ^ mix((seq + G) & M64))
    v = []
    for w in range(2 * m):
        x = mix((k + (w + 1) * G) & M64)
        v += [x & 0xFFFFFFFF, x >> 32]  # low half, then high half
    u = np.array(v) * 2.0**-32 - 0.5
    return (u[:2 * m] + 1j * u[2 * m:]).reshape(m, 2)


@pytest.mark.parametrize("seed, seq", [(0, 0), (7, 5), (655087151, 12345), (M64, M64), (2**63, 2**64 - 2)])
def test_counter_generator_is_the_documented_algorithm(seed, seq):
    assert_array_equal(unit_dither(seed, seq, 5)[0], counter_reference(seed, seq, 5))
    # the same in a batch of several seeds and seqs (uint64 arrays)
    batch = unit_dither(np.array([1, seed], np.uint64), np.array([2, seq], np.uint64), 300)
    assert_array_equal(batch[1], counter_reference(seed, seq, 300))
    assert_array_equal(batch[0], counter_reference(1, 2, 300))


def test_counter_generator_statistics():
    """Over many frames: uniform on [-1/2, 1/2) (mean 0, variance 1/12, flat histogram), Re
    and Im uncorrelated, and no correlation between frames of neighbouring seqs, of
    neighbouring seeds (sensors), or between values next to each other in a frame."""
    f, m = 2000, 64
    seqs = np.arange(f, dtype=np.uint64) + np.uint64(2**64 - 1000)  # crossing the wrap of 2**64
    u = unit_dither(np.uint64(2**40 + 17), seqs, m)  # (F, M, 2)
    other = unit_dither(np.uint64(2**40 + 18), seqs, m)  # the next sensor's seed
    x = np.stack([u.real, u.imag], axis=-1).reshape(f, -1)  # (F, 4M)
    y = np.stack([other.real, other.imag], axis=-1).reshape(f, -1)
    n = x.size
    assert abs(x.mean()) < 5 * np.sqrt(1 / 12 / n)
    assert abs(x.var() - 1 / 12) < 1e-3
    assert x.min() >= -0.5 and x.max() < 0.5
    counts = np.histogram(x, bins=32, range=(-0.5, 0.5))[0]
    chi2 = ((counts - n / 32) ** 2 / (n / 32)).sum()
    assert chi2 < 80  # 31 degrees of freedom: p ~ 1e-6

    def corr(a, b):
        return np.corrcoef(a.ravel(), b.ravel())[0, 1]

    bound = 5 / np.sqrt(n)
    assert abs(corr(x[:-1], x[1:])) < bound  # frame s against frame s + 1
    assert abs(corr(x, y)) < bound  # seed against seed + 1, same seqs
    assert abs(corr(x[:, :-1], x[:, 1:])) < bound  # neighbouring values in a frame
    assert abs(corr(u.real, u.imag)) < bound
    # frames are distinct streams, and no frame repeats another's values shifted by one word
    assert len({r.tobytes() for r in x}) == f
    assert not np.any(np.all(x[1:, :-2] == x[:-1, 2:], axis=1))


def test_per_frame_seeds_in_one_batch_equal_one_call_per_sensor(cfg):
    ids = ["ch0", "ch1", "kmd2-0", "ch0", "kmd2-0"]
    seeds = sensor_dither_seeds(3, ids)
    assert seeds.dtype == np.uint64 and seeds.tolist() == [sensor_dither_seed(3, s) for s in ids]
    assert sensor_dither_seeds(2**40, ["a"])[0] == sensor_dither_seed(2**40, "a")  # seed * 2**32 wraps mod 2**64
    seqs = np.array([0, 0, 5, 1, 2**64 - 1], np.uint64)
    g = simulate_frames([[30.0]] * 5, [[10.0]] * 5, [[1.0]] * 5, cfg)
    for gen in (DITHER_COUNTER, DITHER_SEEDSEQ):
        batch = unit_dither(seeds, seqs, 512, gen)
        q = quantize_frames(g, QuantizerConfig(alpha=0.7), seqs, dither_seed=seeds, generator=gen)
        for i, (seed, seq) in enumerate(zip(seeds.tolist(), seqs.tolist())):
            assert_array_equal(batch[i], unit_dither(seed, seq, 512, gen)[0])
            one = quantize_frames(g[i:i + 1], QuantizerConfig(alpha=0.7), [seq], dither_seed=seed, generator=gen)
            assert_array_equal(q.codes[i], one.codes[0])
        assert_array_equal(quantize(g, q.delta, 1, q.dither()), q.codes)


def test_seeds_and_seqs_span_uint64_and_nothing_beyond():
    top = 2**64 - 1
    for gen in (DITHER_COUNTER, DITHER_SEEDSEQ):
        a = unit_dither(top, [top, 0], 8, gen)
        assert a.shape == (2, 8, 2) and not np.array_equal(a[0], a[1])
        assert_array_equal(unit_dither(np.array([top], np.uint64), np.array([top], np.uint64), 8, gen), a[:1])
    for bad in (-1, 2**64, [1, -2], 1.5, [[1]]):
        with pytest.raises(ParameterError, match="seq must be integers in \\[0, 2\\*\\*64\\)"):
            unit_dither(0, bad, 8)
        with pytest.raises(ParameterError, match="dither_seed must be integers"):
            unit_dither(bad, 0, 8)
    with pytest.raises(ParameterError, match="dither_seed has 2 values, expected 1 or one per frame \\(3\\)"):
        unit_dither([1, 2], [1, 2, 3], 8)
    with pytest.raises(ParameterError, match="generator='philox'"):
        unit_dither(0, 0, 8, "philox")


def test_no_numpy_warnings_on_wrapping_arithmetic():
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        unit_dither(2**64 - 1, 2**64 - 1, 4)
        unit_dither(np.array([2**64 - 1], np.uint64), np.array([2**64 - 1], np.uint64), 4)
        sensor_dither_seeds(2**64 - 1, ["a", "b"])


def test_a_batch_may_mix_generators(cfg):
    """Frames of recordings of either version in one batch: each regenerates its own dither."""
    g = simulate_frames([[30.0]] * 4, [[10.0]] * 4, [[1.0]] * 4, cfg)
    gens = np.array([DITHER_SEEDSEQ, DITHER_COUNTER, DITHER_COUNTER, DITHER_SEEDSEQ])
    seqs = np.array([3, 3, 4, 4], np.uint64)
    mixed = unit_dither(9, seqs, 512, gens)
    for i in range(4):
        assert_array_equal(mixed[i], unit_dither(9, seqs[i], 512, gens[i])[0])
    q = quantize_frames(g, QuantizerConfig(alpha=1.0, dither_seed=9), seqs, generator=gens)
    assert_array_equal(quantize(g, q.delta, 1, q.dither()), q.codes)
    for i in range(4):
        one = quantize_frames(g[i:i + 1], QuantizerConfig(alpha=1.0, dither_seed=9), seqs[i:i + 1], generator=gens[i])
        assert_array_equal(one.codes[0], q.codes[i])
        assert one.generator == gens[i]


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


def test_dither_of_a_batch_equals_unit_dither_bit_for_bit_for_every_form_of_seed(cfg):
    """QuantizedFrames.dither skips unit_dither's checks for the counter generator's common
    forms (one int seed, or uint64 seeds per frame): the values must not change."""
    from dataclasses import replace

    g = simulate_frames([[30.0], [12.0], [80.0]], [[10.0], [-5.0], [40.0]], [[1.0], [0.5], [0.2]], cfg)
    seqs = np.array([0, 7, 2**64 - 1], np.uint64)
    for seed in (0, 2**64 - 1, np.uint64(5), sensor_dither_seeds(3, ["a", "b", "c"])):
        q = quantize_frames(g, QuantizerConfig(alpha=0.8), seqs, dither_seed=seed)
        want = unit_dither(seed, seqs, 512) * (q.alpha * q.delta)[:, None, None]
        assert_array_equal(q.dither(), want)
        assert_array_equal(replace(q, seq=seqs.tolist()).dither(), want)  # the checked path: the same
        assert_array_equal(quantize(g, q.delta, 1, q.dither()), q.codes)


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


def test_counter_generator_test_vectors_of_the_docs():
    """The test vectors of docs/wire-formats.md (version 2)."""
    from pipeline.dsp.quantize import counter_keys

    k = counter_keys(np.array([0, 655087151], np.uint64), np.array([0, 41], np.uint64))
    assert k.tolist() == [0x48218226FF3CD4BF, 0x4B8C5DCC28E8F094]
    assert unit_dither(0, 0, 1)[0, 0].tolist() == [-0.3977657603099942 - 0.2190026317257434j,
                                                -0.16194754582829773 - 0.2308697288390249j]
    assert unit_dither(655087151, 41, 1)[0, 0].tolist() == [-0.3218443572986871 - 0.2290043553803116j,
                                                         0.06143485032953322 + 0.04329792223870754j]


def _reference_quantize(f, d, bits, dither=None):
    """The quantizer as the paper writes it, step by step (before the fast paths)."""
    f = f + dither if dither is not None else f
    lam = np.stack([f.real, f.imag], axis=-1)
    half = 1 << (bits - 1)
    q = np.clip(np.floor(lam / np.reshape(d, (-1, 1, 1, 1))), -half, half - 1)
    return (q + half).astype(np.uint8 if bits <= 8 else np.uint16)


@pytest.mark.parametrize("bits", [1, 2, 5, 8, 12, 16])
def test_the_fast_quantizer_and_dequantizer_equal_the_formulas_bit_for_bit(bits):
    rng = np.random.default_rng(bits)
    for scale in (1e-40, 1e-3, 1.0, 1e2):
        f = (rng.standard_normal((5, 64, 2)) + 1j * rng.standard_normal((5, 64, 2))) * scale
        f[0, :4] = [[0.0, -0.0], [1e-320, -1e-320], [-5e-324, 5e-324], [-1e-310j, -0.0j]]  # signed zeros, subnormals
        d = np.abs(rng.standard_normal(5)) * 10.0 ** rng.integers(-3, 300, size=5) + 1e-30
        dither = (rng.standard_normal(f.shape) + 1j * rng.standard_normal(f.shape)) * scale
        for xi in (None, dither):
            codes = quantize(f, d, bits, xi)
            assert codes.dtype == (np.uint8 if bits <= 8 else np.uint16)
            assert_array_equal(codes, _reference_quantize(f, d, bits, xi))
            ref = (codes.astype(float) - ((1 << (bits - 1)) - 0.5)) * d[:, None, None, None]
            z = dequantize(codes, d, bits)
            assert_array_equal(z.view(np.uint64), (ref[..., 0] + 1j * ref[..., 1]).view(np.uint64))


@pytest.mark.parametrize("dtype,bits", [(np.uint8, 1), (np.uint8, 8), (np.uint16, 12), (np.int64, 1), (np.int8, 1)])
@pytest.mark.parametrize("ramps", [1, 2, 7, 300])
def test_ramp_mean_sums_codes_of_any_integer_type_and_layout_exactly(dtype, bits, ramps):
    """The per-ramp integer adds give the sum over the ramps exactly (no wrap, even with
    300 ramps of 8-bit codes), for C and Fortran order alike."""
    rng = np.random.default_rng(ramps)
    codes = rng.integers(0, 1 << bits, (3, ramps * 8, 2, 2)).astype(dtype)
    want = (codes.reshape(3, ramps, 8, 2, 2).sum(axis=1, dtype=np.int64).astype(float) * (1.0 / ramps)
            - ((1 << (bits - 1)) - 0.5)) * np.array([0.5, 1.0, 2.0])[:, None, None, None]
    for c in (codes, np.asfortranarray(codes)):
        q = QuantizedFrames(c, np.array([0.5, 1.0, 2.0]), bits, 1.0, 1, np.arange(3, dtype=np.uint64))
        assert np.array_equal(q.ramp_mean(8), want.view(complex).reshape(3, 8, 2))


def test_a_step_beyond_what_a_frame_may_carry_is_refused_at_the_config():
    from pipeline.dsp.quantize import MAX_DELTA

    assert QuantizerConfig(delta=MAX_DELTA).delta == MAX_DELTA
    with pytest.raises(ParameterError, match="at most 1000"):
        QuantizerConfig(delta=2 * MAX_DELTA)


def test_auto_delta_at_more_bits_uses_their_levels():
    """``delta auto`` was the 1-bit step at every bit count: the codes of 8-bit frames took 2
    of 256 levels and carried one bit (6.6 times the bytes). Now the step of b bits holds
    the frame and its dither in 2^b levels: the codes use them, and the error falls with b."""
    from pipeline.dsp.quantize import QuantizerConfig, auto_delta, quantize_frames
    from radar_driver.scene import resolve_scene

    rng = np.random.default_rng(0)
    scene = resolve_scene("chamber-ideal")
    frames = np.stack([scene.ramps(np.array([i * 0.05, i * 0.05 + 0.025]), rng).reshape(-1, 2) for i in range(20)])
    assert np.allclose(auto_delta(frames, bits=4), auto_delta(frames) / 15)  # 1 bit: the paper's 2 max|Re, Im|
    errors = []
    for bits in (1, 2, 4, 8):
        q = quantize_frames(frames, QuantizerConfig(bits=bits, alpha=0.45), np.arange(20))
        assert np.unique(q.codes).size > 0.9 * 2 ** bits, bits
        errors.append(float(np.sqrt(np.mean(np.abs(q.values() - frames) ** 2))))
    assert all(e2 < e1 / 3 for e1, e2 in zip(errors, errors[1:])), errors
