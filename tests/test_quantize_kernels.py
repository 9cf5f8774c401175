"""The compiled counter dither (pipeline.dsp.dither_kernels, ``engine="numba"``) against its
numpy reference (pipeline.dsp.dither.counter_dither_numpy), bit for bit, and the paths that
reach it: the engine is chosen by the caller, never by the process's state."""

import importlib.util
import sys

import numpy as np
import pytest
from numpy.testing import assert_array_equal

from pipeline.dsp.dither import counter_dither, counter_dither_numpy
from pipeline.dsp.quantize import DITHER_COUNTER, DITHER_SEEDSEQ, QuantizedFrames, unit_dither
from pipeline.errors import ParameterError
from pipeline.wire import QuantizedFrameMsg, quantized_batch

needs_numba = pytest.mark.skipif(importlib.util.find_spec("numba") is None, reason="numba is not installed")


def _seeds_seqs(rng, b):
    seeds = rng.integers(0, 2**64, b, dtype=np.uint64, endpoint=False)
    seqs = rng.integers(0, 2**64, b, dtype=np.uint64, endpoint=False)
    seeds[:2], seqs[:2] = [0, 2**64 - 1][:b], [2**64 - 1, 0][:b]  # the extremes wrap alike
    return seeds, seqs


def _same(a, b):
    """Equal bit for bit (values, signs of zeros, dtype and shape)."""
    return a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()


@needs_numba
@pytest.mark.parametrize("b", [1, 2, 3, 17, 64])
@pytest.mark.parametrize("m", [0, 1, 7, 512])
def test_the_compiled_dither_is_the_numpy_one_bit_for_bit(b, m):
    rng = np.random.default_rng(1000 * b + m)
    seeds, seqs = _seeds_seqs(rng, b)
    ref = counter_dither_numpy(seeds, seqs, m)
    assert _same(counter_dither(seeds, seqs, m, engine="numba"), ref)
    assert _same(counter_dither(seeds, seqs, m), ref)  # numpy's, the default
    # scaled in the kernel: alpha delta of float32 values (as the wire carries them), from tiny to large
    alpha = rng.random(b).astype(np.float32).astype(float)
    delta = np.exp(rng.uniform(np.log(1.2e-38), np.log(1e3), b)).astype(np.float32).astype(float)
    scale = alpha * delta
    assert _same(counter_dither(seeds, seqs, m, scale, engine="numba"), scale[:, None, None] * ref)


@needs_numba
def test_the_compiled_dither_takes_any_layout_of_seeds():
    """A broadcast seed (unit_dither with one seed for the batch) and strided arrays give
    what contiguous ones do."""
    seqs = np.arange(0, 20, 2, dtype=np.uint64)[::2]
    want = counter_dither_numpy(np.full(5, 9, np.uint64), np.ascontiguousarray(seqs), 64)
    assert _same(counter_dither(np.broadcast_to(np.uint64(9), (5,)), seqs, 64, engine="numba"), want)
    assert _same(unit_dither(9, seqs, 64, engine="numba"), want)


def test_without_numba_the_numpy_engine_runs_and_numba_is_refused(monkeypatch):
    rng = np.random.default_rng(5)
    seeds, seqs = _seeds_seqs(rng, 4)
    scale = rng.random(4)
    want = scale[:, None, None] * counter_dither_numpy(seeds, seqs, 32)
    monkeypatch.setitem(sys.modules, "pipeline.dsp.dither_kernels", None)  # its import fails, as without numba
    assert _same(counter_dither(seeds, seqs, 32, scale, engine="numpy"), want)
    assert _same(counter_dither(seeds, seqs, 32), counter_dither_numpy(seeds, seqs, 32))
    with pytest.raises(ParameterError, match="needs numba"):
        counter_dither(seeds, seqs, 32, scale, engine="numba")
    with pytest.raises(ParameterError, match="engine='fortran'"):
        counter_dither(seeds, seqs, 32, scale, engine="fortran")


def _frames(rng, b, generator, seed=None):
    seeds, seqs = _seeds_seqs(rng, b)
    return QuantizedFrames(rng.integers(0, 2, (b, 16, 2, 2), dtype=np.uint8),
                           np.float32(rng.random(b) + 0.1).astype(float), 1,
                           np.float32(rng.random(b) + 0.01).astype(float), seeds if seed is None else seed,
                           seqs, generator)


def test_a_batch_dither_is_the_per_frame_reference_for_every_form_of_generator():
    """QuantizedFrames.dither: one name, a uniform (B,) array of names (taken as one name)
    and a mixed one all give alpha delta u of the numpy reference (seedseq: its own)."""
    rng = np.random.default_rng(6)
    for gen in (DITHER_COUNTER, np.array([DITHER_COUNTER] * 5), np.array([DITHER_SEEDSEQ] * 5),
                np.array([DITHER_COUNTER, DITHER_SEEDSEQ] * 2 + [DITHER_COUNTER])):
        q = _frames(rng, 5, gen)
        names = np.broadcast_to(np.asarray(gen), (5,))
        for j in range(5):
            ref = (counter_dither_numpy(q.dither_seed[j:j + 1], q.seq[j:j + 1], 16) if names[j] == DITHER_COUNTER
                   else unit_dither(q.dither_seed[j], q.seq[j], 16, DITHER_SEEDSEQ))
            assert _same(q.dither()[j], (q.alpha[j] * q.delta[j]) * ref[0])
            if importlib.util.find_spec("numba") is not None:
                assert _same(q.dither("numba")[j], (q.alpha[j] * q.delta[j]) * ref[0])
    q = _frames(rng, 3, DITHER_COUNTER, seed=7)  # one int seed for the batch
    want = (q.alpha * q.delta)[:, None, None] * counter_dither_numpy(np.full(3, 7, np.uint64), q.seq, 16)
    assert _same(q.dither(), want)


def test_quantized_batch_names_one_generator_once():
    def msg(i, gen):
        return QuantizedFrameMsg(f"s{i}", 10 + i, 0, 0, 1, 0.5, 0.25, 3 + i, np.zeros((8, 2, 2), np.uint8), gen)

    one = quantized_batch([msg(i, DITHER_COUNTER) for i in range(3)])
    assert one.generator == DITHER_COUNTER
    mixed = quantized_batch([msg(i, (DITHER_COUNTER, DITHER_SEEDSEQ)[i % 2]) for i in range(3)])
    assert mixed.generator.tolist() == [DITHER_COUNTER, DITHER_SEEDSEQ, DITHER_COUNTER]
    for j, gen in enumerate((DITHER_COUNTER, DITHER_SEEDSEQ, DITHER_COUNTER)):
        assert_array_equal(mixed.dither()[j], msg(j, gen).dither())
    assert_array_equal(one.dither()[1], msg(1, DITHER_COUNTER).dither())


@needs_numba
def test_a_decoder_regenerates_the_quantizers_dither_in_numba():
    """The quantizer draws the counter dither in numpy, already scaled by alpha delta; a
    decoder regenerates it in numba (pipeline.dsp.decode.Decoder.dither_engine), bit for bit:
    the codes quantized again with it are the quantizer's, for one seed or one per frame,
    fixed or per-frame alpha ("auto") and 1 or 3 bits."""
    from pipeline.dsp.decode import Decoder, DecoderConfig
    from pipeline.dsp.quantize import QuantizerConfig, quantize, quantize_frames, sensor_dither_seeds

    rng = np.random.default_rng(8)
    g = (rng.normal(size=(6, 64, 2)) + 1j * rng.normal(size=(6, 64, 2))) * 0.3
    g[0, :3] = 0.0  # zeros: the sign of a zero dither cannot move a code
    seqs = np.array([0, 1, 2**63, 2**64 - 1, 17, 5], np.uint64)
    cases = [(QuantizerConfig(alpha=0.8), 11, None), (QuantizerConfig(bits=3, alpha=1.0), None, None),
             (QuantizerConfig(alpha="auto"), sensor_dither_seeds(2, list("abcdef")),
              np.array([0, 0.05, 0.2, 1e-9, 3.0, 0.1]))]
    engine = Decoder(DecoderConfig(algo="cml")).dither_engine
    assert engine == "numba" and Decoder(DecoderConfig(algo="qiht")).dither_engine == "numba"
    for cfg, seed, sigma in cases:
        q = quantize_frames(g, cfg, seqs, dither_seed=seed, noise_sigma=sigma)
        xi = q.dither(engine)
        assert _same(xi, q.dither("numpy"))
        assert _same(quantize(g, q.delta, cfg.bits, xi), q.codes)
        if cfg.alpha == "auto":  # one alpha per frame
            assert len(set(np.asarray(q.alpha).tolist())) > 2


@needs_numba
def test_every_layout_reaches_the_one_compiled_signature():
    """Broadcast (read-only) seeds and scales, strided sequence numbers and one frame all reach
    the kernel as contiguous writeable arrays: the signature the warm-up loads, no compile at
    a node's first frame."""
    from pipeline.dsp.dither import load_kernel
    from pipeline.dsp.dither_kernels import counter_dither_into

    load_kernel()
    rng = np.random.default_rng(2)
    for b in (1, 6):
        unit_dither(4, np.arange(0, 4 * b, 4, dtype=np.uint64)[::2], 16, engine="numba")
        counter_dither(np.broadcast_to(np.uint64(5), (b,)), np.arange(b, dtype=np.uint64), 8,
                       np.broadcast_to(0.5, (b,)), engine="numba")
        counter_dither(rng.integers(0, 9, b).astype(np.uint64), np.arange(b, dtype=np.uint64), 8, engine="numba")
    assert len(counter_dither_into.signatures) == 1


@needs_numba
def test_seeds_or_scales_of_another_length_are_refused():
    """A seed or scale per frame, or a clear error (the kernel reads one per frame unchecked)."""
    seqs = np.arange(4, dtype=np.uint64)
    with pytest.raises(ParameterError, match="3 seeds and no scales for 4 frames"):
        counter_dither(np.zeros(3, np.uint64), seqs, 8, engine="numba")
    with pytest.raises(ParameterError, match="4 seeds and 2 scales for 4 frames"):
        counter_dither(np.zeros(4, np.uint64), seqs, 8, np.ones(2), engine="numba")


def test_a_process_that_only_quantizes_does_not_import_numba():
    """The quantize node and an edge sensor draw the dither in numpy (bit for bit the
    compiled one): no numba, no ~100 MB, no second of start-up in those processes."""
    import subprocess
    import sys

    code = ("import sys, numpy as np; from pipeline.dsp.quantize import QuantizerConfig, quantize_frames; "
            "quantize_frames(np.ones((2, 8, 2), complex), QuantizerConfig(), np.arange(2, dtype=np.uint64), "
            "dither_seed=3).codes; print('numba' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0 and out.stdout.strip() == "False", out.stderr[-2000:]
