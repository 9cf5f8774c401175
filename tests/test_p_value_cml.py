"""Every cml target says how likely noise alone makes it (pipeline/dsp/significance.py):
``p_value``, a score test of the frame given the other targets. On noise-only frames the
p-values are uniform unquantized (p < a in a share a of the frames, within 1.25x) and valid
for codes (never more than 1.25 a; conservative, not less than a / 2); beside a strong
target the weaker target's are uniform unquantized and valid for codes; a strong target's is
~0, warm-started or not, and it reaches the targets JSON."""

import json

import numpy as np
import pytest

from experiments.p_values import frames_of, shares as experiment_shares
from pipeline.dsp.decode import Decoder, DecoderConfig
from pipeline.dsp.gate import RangeGate
from pipeline.dsp.localize import cfar_p_value
from pipeline.dsp.quantize import QuantizerConfig, quantize_frames
from pipeline.dsp.significance import STATIC_CELLS_PER_BIN, code_cells, code_score, moving_p_value, p_value
from radar_driver.model import RadarConfig, simulate_frames

CFG = RadarConfig()
GATE = RangeGate.default(CFG)
LEVELS = (0.05, 0.1, 0.5)


def shares(p: np.ndarray) -> list[float]:
    """The share of ``p`` below each of LEVELS over the level."""
    return experiment_shares(p, LEVELS)


def test_the_p_value_of_the_static_search_is_the_count_tests_and_the_moving_one_falls():
    x = np.array([2.0, 6.0, 9.0])
    assert p_value(x, 200.0, False) == pytest.approx(cfar_p_value(10 * np.log10(x), STATIC_CELLS_PER_BIN * 200.0))
    p = moving_p_value(np.linspace(0.0, 20.0, 201), 250.0)
    assert np.all(np.diff(p) <= 0) and p[0] == pytest.approx(1.0) and p[-1] < 1e-10
    assert np.isnan(p_value(np.array([np.nan]), 200.0, True)).all()


@pytest.mark.parametrize("bits", [1, 2, 3])
def test_the_code_score_is_the_logistic_likelihoods_derivatives(bits):
    rng = np.random.default_rng(bits)
    codes = rng.integers(0, 1 << bits, (2, 64, 2, 2))
    lo, hi = code_cells(codes, np.array([0.5, 0.25]), bits)
    lam, sigma = 0.6 * rng.standard_normal(lo.shape), np.array([0.1, 0.3])
    t = (sigma / 1.702)[:, None, None, None]

    def prob(v):
        f = lambda e: 1.0 / (1.0 + np.exp(-np.clip((e - v) / t, -700, 700)))  # noqa: E731
        return f(hi) - f(lo)
    g, h = code_score(lam, lo, hi, sigma)
    with np.errstate(divide="ignore", invalid="ignore"):  # cells of probability 0 in float64 (left out below)
        lp = [np.log(prob(lam + d)) for d in (-1e-4, 0.0, 1e-4)]
        dg, dh = (lp[2] - lp[0]) / 2e-4, -(lp[2] - 2 * lp[1] + lp[0]) / 1e-8
    fine = (prob(lam) > 1e-3) & (prob(lam) < 1 - 1e-3)  # where differences of the CDF are exact enough
    assert fine.mean() > 0.5
    assert g[fine] == pytest.approx(dg[fine], rel=1e-4, abs=1e-4)
    assert h[fine] == pytest.approx(dh[fine], rel=1e-3, abs=1e-3)
    assert np.abs(g).max() <= 1.702 / sigma.min() * (1 + 1e-12)  # bounded by 1 / T
    assert (h >= 0).all()


@pytest.mark.parametrize("alpha, motion", [(None, True), (0.45, True), (None, False)])
def test_on_noise_alone_cml_p_values_are_uniform_or_conservative(alpha, motion):
    frames, _ = frames_of(2000, 3, alpha)
    p = Decoder(DecoderConfig(algo="cml", gate=GATE, motion=motion)).decode_batch(frames, CFG, 1).p_value[:, 0]
    assert np.isfinite(p).all()
    if alpha is None:  # measured 1.10, 0.98, 0.86 (20 000 frames: 1.00, 0.98, 0.91); static model 0.99, 0.94, 0.93
        assert all(1 / 1.25 <= s <= 1.25 for s in shares(p)), shares(p)
    else:  # codes: measured 0.81, 0.72, 0.51
        assert all(0.5 <= s <= 1.25 for s in shares(p)), shares(p)


@pytest.mark.parametrize("alpha", [None, 0.45])
def test_beside_a_strong_target_the_weaker_ones_p_value_holds(alpha):
    frames, r = frames_of(2000 if alpha is None else 1000, 7, alpha, strong=True)
    det = Decoder(DecoderConfig(algo="cml", gate=GATE)).decode_batch(frames, CFG, 2)
    err = np.abs(det.range_m - r)
    true = np.arange(2)[None, :] == np.argmin(err, axis=1)[:, None]  # the target's estimate: the nearer one
    found = err[true] < 0.6
    assert found.mean() > 0.99 and (det.p_value[true][found] < 1e-6).all()  # a split beside it: 2e-10
    p = det.p_value[~true & det.present]
    if alpha is None:  # the other target projected out: the noise-only p-values (measured 1.06, 0.94, 0.92)
        assert all(1 / 1.25 <= s <= 1.25 for s in shares(p)), shares(p)
    else:  # the strong target's codes leave structure the test reads as noise: conservative (0.18, 0.23, 0.17)
        assert all(s <= 1.25 for s in shares(p)), shares(p)


def test_a_strong_cml_target_is_sure_warm_or_cold_and_says_so_in_its_message():
    rng = np.random.default_rng(5)
    g = simulate_frames(np.array([[30.3]]), np.array([[10.0]]), np.array([[0.5]]), CFG)
    g = g + 0.1 * (rng.standard_normal(g.shape) + 1j * rng.standard_normal(g.shape))
    q = quantize_frames(g, QuantizerConfig(alpha=0.45, bits=1), np.arange(1))
    decoder = Decoder(DecoderConfig(algo="cml", auto_k=True, gate=GATE))
    cold = decoder.decode_batch(q, CFG, 3)
    warm = decoder.decode(q.codes, q.dither(), q.delta, 1, CFG, 3, init_range_m=np.array([[30.3, np.nan, np.nan]]))
    for det in (cold, warm):
        (target, *others) = det.frame(0)
        assert not others and abs(target["range_m"] - 30.3) < CFG.range_resolution_m
        assert target["p_value"] < 1e-12 and json.loads(json.dumps(target))["p_value"] == target["p_value"]


@pytest.mark.parametrize("range_m, velocity_mps", [((5, 140), 0.125), ((5, 140), 1.5), ((1.5, 2.5), 0.0),
                                                   ((148, 150), 0.0)])
def test_a_target_moving_at_a_blind_speed_or_near_the_gates_ends_is_sure(range_m, velocity_mps):
    """0.125 m/s: a blind speed of the static model; 1.2 and 150 m: the live gate's ends
    (1-bit, amplitude 0.3 in noise 0.1, --K auto)."""
    rng = np.random.default_rng(4)
    r = rng.uniform(*range_m, (60, 1))
    g = simulate_frames(r, rng.uniform(-50, 50, (60, 1)), np.full((60, 1), 0.3), CFG,
                        velocity_mps=np.full((60, 1), velocity_mps))
    g = g + 0.1 * (rng.standard_normal(g.shape) + 1j * rng.standard_normal(g.shape))
    q = quantize_frames(g, QuantizerConfig(alpha=0.45, bits=1), np.arange(60))
    det = Decoder(DecoderConfig(algo="cml", auto_k=True, gate=GATE)).decode_batch(q, CFG, 4)
    hit = (np.abs(det.range_m - r) < 0.6) & det.present
    assert hit.any(axis=1).all() and (det.p_value[hit] < 1e-100).all()


def test_without_the_uncertainty_the_targets_are_the_same_positions_only():
    """``DecoderConfig(uncertainty=False)`` (a Monte Carlo, ``qradar localize
    --no-uncertainty``): the same targets, without sigma_* and p_value; ``p_values=False``:
    the same sigma_*, no p_value."""
    from qradar.cli import build_parser
    from pipeline.nodes.stream import LocalizerConfig

    rng = np.random.default_rng(6)
    r = rng.uniform(5, 140, (20, 2))
    g = simulate_frames(r, rng.uniform(-50, 50, (20, 2)), np.full((20, 2), 0.5), CFG)
    g = g + 0.1 * (rng.standard_normal(g.shape) + 1j * rng.standard_normal(g.shape))
    q = quantize_frames(g, QuantizerConfig(alpha=0.45, bits=1), np.arange(20))
    full, bare = (Decoder(DecoderConfig(algo="cml", auto_k=True, gate=GATE, uncertainty=u)).decode_batch(q, CFG, 4)
                  for u in (True, False))
    assert bare.present.sum() >= 30 and np.array_equal(full.present, bare.present)
    for name in ("range_m", "angle_deg", "amplitude"):
        np.testing.assert_array_equal(getattr(full, name), getattr(bare, name))
    assert np.isfinite(full.p_value[full.present]).all() and np.isfinite(full.sigma_range_m[full.present]).all()
    assert np.isnan(bare.sigma_range_m).all() and np.isnan(bare.p_value).all()  # as PBP's: NaN, not in the JSON
    assert {"range_m", "sigma_range_m", "p_value"} <= set(full.frame(0)[0])
    ellipses = Decoder(DecoderConfig(algo="cml", auto_k=True, gate=GATE, p_values=False)).decode_batch(q, CFG, 4)
    np.testing.assert_array_equal(ellipses.sigma_range_m, full.sigma_range_m)  # the uncertainty alone
    assert ellipses.p_value is None or np.isnan(ellipses.p_value).all()
    assert not {"sigma_range_m", "sigma_angle_deg", "cov_range_angle", "p_value"} & set(bare.frame(0)[0])

    args = build_parser().parse_args(["localize", "--no-uncertainty"])
    assert args.schema.build(LocalizerConfig, args, k=2, auto_k=False).decoder().uncertainty is False
    args = build_parser().parse_args(["localize"])
    assert args.schema.build(LocalizerConfig, args, k=2, auto_k=False).decoder().uncertainty is True
    with pytest.raises(Exception, match="uncertainty=1 must be True or False"):
        DecoderConfig(uncertainty=1)
    with pytest.raises(Exception, match="p_values='no' must be True or False"):
        DecoderConfig(p_values="no")
