"""Intake budgets: a sender's share of a node is bounded where its messages arrive, new
sensor ids are admitted at a bounded rate, every refused frame is counted, and a crowd of
one-frame ids costs no publisher declarations."""

from __future__ import annotations

import json
import logging
import subprocess
import time

import pytest
import zenoh

from pipeline.nodes.budget import IntakeBudget, KeyBudget, TokenBucket
from pipeline.errors import ParameterError
from pipeline.nodes.counters import NO_SENSOR, UNKNOWN_SENSOR
from pipeline.nodes.runtime import PUBLISHER_AFTER
from pipeline.nodes.stream import QuantizeNode
from pipeline.dsp.quantize import QuantizerConfig
from pipeline.wire import decode_health, decode_quantized
from test_hardening import raw
from zenoh_helpers import QRADAR, Collector, wait_until

BLOCK = zenoh.CongestionControl.BLOCK


# -- the buckets ----------------------------------------------------------------------------------
def test_a_token_bucket_holds_its_burst_and_refills_at_its_rate():
    b = TokenBucket(rate=10.0, capacity=5.0, now=0.0)
    assert [b.take(0.0) for _ in range(6)] == [True] * 5 + [False]
    assert not b.take(0.05)  # half a token
    assert b.take(0.1) and not b.take(0.1)
    assert [b.take(100.0) for _ in range(6)] == [True] * 5 + [False]  # never more than the burst


def test_a_key_budget_refuses_by_rate_then_by_bytes_and_takes_nothing_it_refuses():
    kb = KeyBudget(IntakeBudget(rate_hz=4, bytes_per_s=1000, burst_s=1.0), now=0.0)
    assert [kb.admit(0.0, 100) for _ in range(4)] == [None] * 4
    assert kb.admit(0.0, 100) == "messages/s"
    kb = KeyBudget(IntakeBudget(rate_hz=4, bytes_per_s=1000, burst_s=1.0), now=0.0)
    assert kb.admit(0.0, 900) is None and kb.admit(0.0, 200) == "bytes/s"
    assert kb.frames.tokens == 3  # the refused message took no message token
    assert kb.admit(0.0, 100) is None


@pytest.mark.parametrize("bad", [dict(rate_hz=-1), dict(bytes_per_s=float("inf")), dict(burst_s=0),
                                 dict(burst_s=120), dict(new_sensors_burst=0), dict(new_sensors_per_s="x")])
def test_budgets_are_checked_on_load(bad):
    with pytest.raises(ParameterError, match="intake budget"):
        IntakeBudget(**bad)


# -- at a node --------------------------------------------------------------------------------------
def test_a_flood_is_cut_where_it_arrives_and_every_frame_is_counted(bus, zenoh_session):
    """200 frames of one key at once against a budget of 20/s (burst 1 s): 20 go in (and one
    more for each 50 ms the flood takes to arrive: 21 once in a suite on a loaded host), the
    rest are over budget, the honest sensor loses nothing, and the frames the budget dropped
    are not counted again as missing (only a real gap is)."""
    col = Collector(zenoh_session, "radar/*/quantized")
    q = QuantizeNode(bus, QuantizerConfig(), session=zenoh_session, health_period_s=0.2,
                     intake=IntakeBudget(rate_hz=20, burst_s=1.0)).start()
    try:
        evil = zenoh_session.declare_publisher("radar/evil/raw", congestion_control=BLOCK)
        start = time.monotonic()
        for i in range(200):
            evil.put(raw("evil", i))
        for i in range(10):
            zenoh_session.put("radar/good/raw", raw("good", i))
        wait_until(lambda: len(col.of("good/quantized")) == 10, 10, "the honest frames")
        wait_until(lambda: q.totals()["frames_in"] == 210, 10, "every frame counted in")
        refilled = int(20 * (time.monotonic() - start))  # tokens the bucket can have gained meanwhile
        with q._lock:
            ev, good = q.stats["evil"], q.stats["good"]
            admitted = ev.frames_in - ev.over_budget
            assert (ev.frames_in, good.over_budget, good.drops) == (200, 0, 0)
            assert 20 <= admitted <= 20 + refilled, (admitted, refilled)
            assert ev.frames_missing == 0  # the budget's drops are not also "missing"
        wait_until(lambda: len(col.of("evil/quantized")) == admitted, 10, "the flood's admitted frames")
        time.sleep(1.2)  # the bucket refills; a real gap after the budget's drops still counts
        evil.put(raw("evil", 205))
        wait_until(lambda: len(col.of("evil/quantized")) == admitted + 1, 10, "the next admitted frame")
        with q._lock:
            assert q.stats["evil"].frames_missing == 5  # 200..204: never sent
        assert [decode_quantized(p).seq for p in col.of("evil/quantized")][:20] == list(range(20))
    finally:
        q.stop()


def test_new_sensor_ids_are_admitted_at_a_bounded_rate_into_a_bounded_state(bus, zenoh_session):
    """300 new ids with one valid frame each against an admission of 50 (burst) + 1/s: the
    first 50 get state, the others are refused and counted in the unknown senders'
    aggregate, whose health says so; every frame is counted once; no publisher is declared
    for a one-frame id."""
    health = Collector(zenoh_session, f"radar/{UNKNOWN_SENSOR}/health")
    col = Collector(zenoh_session, "radar/*/quantized")
    q = QuantizeNode(bus, QuantizerConfig(), session=zenoh_session, health_period_s=0.2,
                     intake=IntakeBudget(new_sensors_per_s=1.0, new_sensors_burst=50)).start()
    try:
        for i in range(300):
            zenoh_session.put(f"radar/n{i}/raw", raw(f"n{i}", 0))
        wait_until(lambda: (t := q.totals())["frames_in"] == 300 and t["refused"] + t["frames_out"] == 300, 10,
                   "every frame counted in, and out or refused")
        t = q.totals()
        assert t["refused"] >= 240 and t["refused"] + t["frames_out"] == 300 and t["over_budget"] == 0
        with q._lock:
            assert len(set(q.stats) - {NO_SENSOR}) == t["frames_out"] <= 55
            assert q.stats[NO_SENSOR].refused == t["refused"]
        wait_until(lambda: len(col.of("/quantized")) == t["frames_out"], 10, "the admitted frames' output")
        assert q._n_publishers == 0 and not q._publishers  # put without a declaration
        wait_until(lambda: any(decode_health(p).refused == t["refused"] for p in health.of("/health")), 5,
                   "the unknown senders' health")
    finally:
        q.stop()


def test_a_sensor_gets_a_declared_publisher_once_it_has_sent_enough(bus, zenoh_session):
    col = Collector(zenoh_session, "radar/s1/quantized")
    q = QuantizeNode(bus, QuantizerConfig(), session=zenoh_session).start()
    try:
        for i in range(PUBLISHER_AFTER + 5):
            zenoh_session.put("radar/s1/raw", raw("s1", i))
            if i == 2:
                wait_until(lambda: len(col.of("quantized")) == 3, 10, "3 frames")
                assert "s1" not in q._publishers
        wait_until(lambda: len(col.of("quantized")) == PUBLISHER_AFTER + 5, 10, "every frame")
        assert "quantized" in q._publishers["s1"] and q._n_publishers >= 1
        assert [decode_quantized(p).seq for p in col.of("quantized")] == list(range(PUBLISHER_AFTER + 5))
    finally:
        q.stop()


def test_the_log_summarises_what_it_rate_limits(bus, zenoh_session, caplog):
    """1000 bad frames from one key and 10 from another give two warnings at most for the
    first second and a summary line naming both senders and the count."""
    q = QuantizeNode(bus, QuantizerConfig(), session=zenoh_session).start()
    try:
        with caplog.at_level(logging.WARNING, logger="qradar.node"):
            zenoh_session.put("radar/a1/raw", raw("a1", 0))  # a1 and b2 get state
            zenoh_session.put("radar/b2/raw", raw("b2", 0))
            wait_until(lambda: q.totals()["frames_out"] == 2, 10, "two frames")
            for i in range(1000):
                zenoh_session.put("radar/a1/raw", b"x" * 7)
            for i in range(10):
                zenoh_session.put("radar/b2/raw", b"x" * 7)
            wait_until(lambda: q.totals()["invalid_frames"] == 1010, 10, "the bad frames")
            assert len([r for r in caplog.records if "invalid_frames" in r.getMessage()]) <= 2
            q.log_summary()
        lines = [r.getMessage() for r in caplog.records if "in the last" in r.getMessage()]
        assert len(lines) == 1 and "1010 invalid_frames" in lines[0], lines
        assert "1000 from a1" in lines[0] and "10 from b2" in lines[0]
    finally:
        q.stop()


def test_the_intake_options_reach_the_node_and_are_checked():
    bad = subprocess.run([*QRADAR, "quantize", "--budget-rate", "-3"], capture_output=True,
                         text=True, timeout=60)
    assert bad.returncode == 2 and "--budget-rate" in bad.stderr
    help_text = subprocess.run([*QRADAR, "localize", "--help"], capture_output=True,
                               text=True, timeout=60).stdout
    for opt in ("--budget-rate", "--budget-mb", "--admit-rate"):
        assert opt in help_text


def test_budget_drops_widen_a_gap_only_by_their_number(bus, zenoh_session):
    """The frames a budget dropped are in the sequence, not missing: a forged jump after them
    is still out of line (implausible_seq), and the honest next frame counts nothing."""
    q = QuantizeNode(bus, QuantizerConfig(), session=zenoh_session,
                     intake=IntakeBudget(rate_hz=5, burst_s=1.0)).start()
    try:
        for i in range(10):  # 5 in, 5 over budget
            zenoh_session.put("radar/h/raw", raw("h", i))
        wait_until(lambda: q.totals()["frames_in"] == 10, 10, "10 frames")
        time.sleep(0.5)  # room for two more
        zenoh_session.put("radar/h/raw", raw("h", 2**63))
        zenoh_session.put("radar/h/raw", raw("h", 10))
        wait_until(lambda: q.totals()["frames_in"] == 12, 10, "12 frames")
        t = q.totals()
        assert (t["over_budget"], t["frames_missing"], t["seq_resets"], t["implausible_seq"]) == (5, 0, 0, 1)
    finally:
        q.stop()


def test_json_totals_carry_the_budget_counters(bus, zenoh_session):
    q = QuantizeNode(bus, QuantizerConfig(), session=zenoh_session).start()
    try:
        t = q.totals()
        assert {"over_budget", "refused"} <= set(t) and json.dumps(t)
    finally:
        q.stop()
