"""--K auto keeps its promise beside strong targets (issue 41, item 1): cml's count test makes
no more than 2x its pfa of false targets a frame at the default alpha, where it made 0.45 a
frame at noise 0 (0.22 at 0.01, 0.025 at 0.03), and keeps every true target
(``python -m experiments.false_alarms`` for the README's row, 2000 frames a case)."""

import pytest

from experiments.false_alarms import AlarmCase, false_targets

CASES = [AlarmCase(1, 0.0, frames=1500, seed=1), AlarmCase(1, 0.01, frames=1500, seed=2),
         AlarmCase(1, 0.03, frames=1500, seed=3), AlarmCase(2, 0.01, alpha=0.0, frames=1000, seed=4),
         AlarmCase(2, 0.1, alpha=1.0, frames=1000, seed=5), AlarmCase(1, 0.0, bits=None, frames=1500, seed=6),
         AlarmCase(0, 0.1, frames=1500, seed=7)]
#: PBP's cases and their bounds (a few events in 1000-1500 frames): its count test on the residual
#: of its targets' tones, its mean taken over the degrees of freedom the tone fit left
#: (residual.fitted_inside), its floor the quantizer's products the model leaves
#: (residual.product_floor_db), what is left of a tone the fit merged into another not a target
#: (residual.merged_near): 0-2.2x its pfa at alpha 0, 0.45 and 1, noise 0-0.3, beside 0-2
#: targets (5000 frames a case), where without dither it made 1100-3000x (3 false targets a
#: frame) and beside two at alpha 0.45 up to 2.7x; unquantized frames beside two, the targets'
#: tones alone in the model, their bins refined together (residual.refine_jointly): 0x at noise
#: 0-0.03, 1.45x at 0.1-0.3 (20 000 frames), where the 1-bit model with each bin refined alone
#: made 27-35x (3-bit frames keep the quantizer's tones: without them, 1 800x)
PBP_CASES = [(AlarmCase(1, 0.1, frames=1500, seed=8, algo="pbp"), 0.003),
             (AlarmCase(1, 0.03, alpha=1.0, frames=1500, seed=9, algo="pbp"), 0.003),
             (AlarmCase(1, 0.1, bits=None, frames=1500, seed=10, algo="pbp"), 0.003),
             (AlarmCase(0, 0.03, frames=1500, seed=11, algo="pbp"), 0.002),
             (AlarmCase(1, 0.0, frames=1000, seed=12, algo="pbp"), 0.004),
             (AlarmCase(2, 0.03, frames=1000, seed=13, algo="pbp"), 0.003),
             (AlarmCase(1, 0.01, alpha=0.0, frames=1000, seed=14, algo="pbp"), 0.002),
             (AlarmCase(2, 0.03, alpha=0.0, frames=1000, seed=15, algo="pbp"), 0.002),
             (AlarmCase(2, 0.0, bits=None, frames=1000, seed=16, algo="pbp"), 0.002),
             (AlarmCase(2, 0.03, bits=None, frames=1000, seed=17, algo="pbp"), 0.002),
             (AlarmCase(2, 0.1, bits=None, frames=1500, seed=18, algo="pbp"), 0.003),
             (AlarmCase(2, 0.03, bits=3, frames=1000, seed=19, algo="pbp"), 0.003),
             # 2- and 4-bit frames at their own step (delta auto at b bits: the staircase's products
             # are the floor; with the 1-bit floor, 1.57 and 0.12 false targets a frame at 2 and 3 bits)
             (AlarmCase(2, 0.03, bits=2, frames=1000, seed=20, algo="pbp"), 0.003),
             (AlarmCase(1, 0.01, bits=4, frames=1000, seed=21, algo="pbp"), 0.003),
             # ... and from 4 bits fitted as unquantized frames are (residual.FINE_BITS: beside two
             # targets the quantizer's tones fitted apart let 0.04-0.05 a frame through)
             (AlarmCase(2, 0.03, bits=4, frames=1000, seed=22, algo="pbp"), 0.003),
             (AlarmCase(2, 0.03, bits=8, frames=1000, seed=23, algo="pbp"), 0.003)]


@pytest.mark.parametrize("case", CASES, ids=lambda c: f"K{c.k}-a{c.alpha:g}-s{c.sigma:g}-{'1bit' if c.bits else 'unq'}")
def test_false_targets_a_frame_within_twice_the_pfa_beside_strong_targets(case):
    false, found = false_targets(case)
    assert false <= 2 * case.pfa, false
    assert found >= 0.995, found



@pytest.mark.parametrize("case, bound", PBP_CASES, ids=lambda c: f"K{c.k}-a{c.alpha:g}-s{c.sigma:g}"
                         f"{'' if c.bits == 1 else '-unq' if c.bits is None else f'-{c.bits}bit'}"
                         if isinstance(c, AlarmCase) else f"{c:g}")
def test_pbp_false_targets_beside_strong_targets_stay_near_its_promise(case, bound):
    false, found = false_targets(case)
    assert false <= bound and found >= 0.995, (false, found)


def test_pbp_two_targets_whose_quantizer_tones_nearly_meet_make_no_ghost():
    """Targets at 100.3 and 40.2 m: the 1-bit quantizer's -3 nu_1 and 2 nu_1 - nu_2 fall 0.8
    bins apart. The residual's tone model took them for one tone (a bin apart at most) and
    the other read as a target in 27 % of the frames; told apart down to half a bin
    (pipeline.dsp.residual.TONE_SEPARATION_BINS), none."""
    import numpy as np

    from pipeline.dsp.decode import DecoderConfig, decode
    from pipeline.dsp.gate import RangeGate
    from pipeline.dsp.quantize import QuantizerConfig, quantize_frames
    from radar_driver.model import RadarConfig, simulate_frames

    cfg, b, rng = RadarConfig(), 200, np.random.default_rng(8)
    x = np.exp(2j * np.pi * rng.random((b, 2)))
    g = simulate_frames(np.tile([100.3, 40.2], (b, 1)), np.tile([10.0, -20.0], (b, 1)), x, cfg)
    g = g + 0.03 * (rng.standard_normal(g.shape) + 1j * rng.standard_normal(g.shape))
    q = quantize_frames(g, QuantizerConfig(alpha=0.45), np.arange(b))
    det = decode(q.values(), q.dither(), q.delta, 1, cfg, 4,
                 DecoderConfig(algo="pbp", auto_k=True, gate=RangeGate.default(cfg)))
    near = np.abs(det.range_m[:, :, None] - np.array([100.3, 40.2])) <= cfg.range_resolution_m  # (B, 4, 2)
    assert (near & det.present[:, :, None]).any(axis=1).all()  # both found in every frame
    assert (det.present & ~near.any(axis=2)).sum() / b <= 0.01, det.range_m[det.present & ~near.any(axis=2)][:8]


@pytest.mark.parametrize("case", [AlarmCase(1, 0.01, frames=300, seed=20), AlarmCase(2, 0.1, frames=300, seed=25),
                                  AlarmCase(2, 0.01, bits=None, frames=300, seed=26),
                                  AlarmCase(2, 0.01, frames=300, seed=32, algo="pbp")],
                         ids=lambda c: f"{c.algo}-K{c.k}-s{c.sigma:g}-{'1bit' if c.bits else 'unq'}")
def test_k_auto_is_as_accurate_on_the_targets_it_keeps_as_the_count_given(case):
    """Issue 41: ``--K auto`` no less accurate than the count given, within 1.2x (the median
    position error of the true targets both find, on the same frames; docs/science.md's
    table: 1.00 in every case)."""
    from experiments.false_alarms import accuracy

    given, auto = accuracy(case)
    assert auto <= 1.2 * given, (given, auto)


@pytest.mark.parametrize("alpha", [0.0, 0.45])
def test_a_pbp_localizer_counting_on_undithered_1bit_frames_says_so_once_a_sensor(alpha, bus, zenoh_session, caplog):
    """Real nodes: two simulated sensors -> quantize at ``alpha`` -> PBP with ``--K auto``.
    Without dither its count test cannot tell a target 25 dB under the strongest (14 dB
    beside two) from the quantizer's harmonics (docs/science.md): the localizer says so once
    for each sensor and decodes on; with a dither it says nothing."""
    import logging

    from radar_driver.scene import resolve_scene
    from radar_driver.source import SimSourceConfig, SimulatedSource
    from zenoh_helpers import Collector, wait_until

    from pipeline.dsp.quantize import QuantizerConfig
    from pipeline.nodes.stream import LocalizeNode, LocalizerConfig, QuantizeNode, SourceNode

    caplog.set_level(logging.WARNING, logger="qradar.node")
    col = Collector(zenoh_session, "radar/**")
    nodes = [LocalizeNode(bus, LocalizerConfig(k=4, algo="pbp", auto_k=True), session=zenoh_session).start(),
             QuantizeNode(bus, QuantizerConfig(alpha=alpha), session=zenoh_session).start()]
    nodes.append(SourceNode(bus, SimulatedSource(SimSourceConfig(resolve_scene("chamber"), rate_hz=50, id_prefix="u",
                                                                 sensors=2, frames=10)), session=zenoh_session).start())
    try:
        wait_until(lambda: all(len(col.of(f"u{i}/targets")) == 10 for i in range(2)), 30, "every frame's targets")
    finally:
        for node in reversed(nodes):
            node.stop()
    told = [r.getMessage() for r in caplog.records if "without dither" in r.getMessage()]
    if alpha:
        assert not told, told
    else:
        assert len(told) == 2 and {"u0's frames", "u1's frames"} == {m.split(": ")[1][:11] for m in told}, told
        assert all("--algo cml" in m and "--alpha > 0" in m for m in told), told
