"""Bounded, seeded fuzzing of every topic's decoder and of the nodes behind them: random
bytes and mutations of valid payloads (bit flips, cuts, extensions, NaN/inf/huge fields,
huge M) must give a WireError naming the source, or a valid message — never another
exception — and a node fed them keeps running and counts each one."""

import json
import struct
import time

import numpy as np
import pytest

from pipeline.nodes.budget import IntakeBudget
from pipeline.errors import WireError
from pipeline.nodes.stream import LocalizeNode, LocalizerConfig, QuantizeNode
from pipeline.dsp.quantize import QuantizerConfig, quantize_frames
from pipeline.wire import (
    COMMON,
    HealthMsg,
    QuantizedFrameMsg,
    RawFrameMsg,
    TargetsMsg,
    decode_health,
    decode_quantized,
    decode_raw,
    decode_targets,
    encode_quantized,
    encode_raw,
)
from radar_driver.scene import resolve_scene
from zenoh_helpers import Collector, wait_until

SCENE = resolve_scene("single")
FRAME = np.tile(SCENE.clean_ramp(0.0), (2, 1)).astype(np.complex64)
CASES = 3000  # per decoder


def valid_payloads() -> dict:
    cid = SCENE.radar.config_id()
    q = quantize_frames(FRAME[None].astype(complex), QuantizerConfig(dither_seed=4), [7])
    target = {"range_m": 12.0, "angle_deg": 10.0, "x_m": 2.0, "y_m": 11.8, "amplitude": 0.5, "statistic_db": 20.0}
    return {
        "raw": (decode_raw, encode_raw(RawFrameMsg("f0", 7, 123, cid, FRAME))),
        "quantized": (decode_quantized, encode_quantized(QuantizedFrameMsg(
            "f0", 7, 123, cid, 1, q.alpha, float(q.delta[0]), int(q.dither_seed), q.codes[0]))),
        "targets": (decode_targets, TargetsMsg("f0", 7, 123, cid, "pbp", 1, "quantized", [target], 456).to_json()),
        "health": (decode_health, HealthMsg("quantize", "f0", 123, 5, 5).to_json()),
    }


def mutations(payload: bytes, rng: np.random.Generator, n: int):
    """n mutated copies: bit flips, cuts, extensions, random header fields, NaN/inf/huge
    floats written over the data, JSON numbers made huge or NaN."""
    specials = [struct.pack("<f", v) for v in (np.nan, np.inf, -np.inf, 3e38)] + \
               [struct.pack("<I", v) for v in (0, 1 << 20, (1 << 20) + 1, 2**32 - 1)] + \
               [struct.pack("<Q", v) for v in (2**63, 2**64 - 1)]
    for i in range(n):
        b = bytearray(payload)
        kind = i % 7
        if kind == 0:  # bit flips
            for pos in rng.integers(0, len(b), rng.integers(1, 8)):
                b[pos] ^= 1 << int(rng.integers(0, 8))
        elif kind == 1:  # cut
            b = b[: int(rng.integers(0, len(b)))]
        elif kind == 2:  # extend
            b += rng.bytes(int(rng.integers(1, 64)))
        elif kind == 3:  # a special value anywhere
            s = specials[int(rng.integers(len(specials)))]
            pos = int(rng.integers(0, max(1, len(b) - len(s))))
            b[pos:pos + len(s)] = s
        elif kind == 4 and payload[:4] == b"QRDR":  # a random header field
            fields = list(COMMON.unpack_from(payload))
            j = int(rng.integers(1, 9))
            fields[j] = int(rng.integers(0, 2**31)) if j < 9 else fields[j]
            try:
                b[: COMMON.size] = COMMON.pack(*fields)
            except struct.error:
                pass
        elif kind == 5 and payload[:1] == b"{":  # JSON: a number made huge, NaN or a string
            obj = json.loads(payload)
            key = list(obj)[int(rng.integers(len(obj)))]
            obj[key] = [1e400, float("nan"), "x", None, [], {}, -1, 2**70][int(rng.integers(8))]
            b = bytearray(json.dumps(obj).encode())
        elif kind == 6 and payload[:1] == b"{":  # JSON text: a number replaced by a huge or negative one
            text = payload.decode()
            digits = [i for i, c in enumerate(text) if c.isdigit()]
            pos = digits[int(rng.integers(len(digits)))]
            b = bytearray((text[:pos] + ["1e400", "-1", "99999999999999999999999", "-0"][i % 4]
                           + text[pos + 1:]).encode())
        else:  # random bytes of the same length
            b = bytearray(rng.bytes(len(b)))
        yield bytes(b)


@pytest.mark.parametrize("topic", ["raw", "quantized", "targets", "health"])
def test_decoders_raise_only_wire_errors(topic):
    decode, payload = valid_payloads()[topic]
    decode(payload, "radar/f0/" + topic)  # the valid one decodes
    rng = np.random.default_rng(12)
    errors = 0
    for mutated in mutations(payload, rng, CASES):
        try:
            msg = decode(mutated, "radar/f0/" + topic)
        except WireError as exc:
            errors += 1
            assert "radar/f0/" + topic in str(exc) and "\n" not in str(exc)
            continue
        if topic == "targets":  # what decodes is valid: finite numbers only
            assert all(np.isfinite(v) for t in msg.targets for v in t.values()), mutated
    assert errors > CASES // 2


def test_nodes_fed_mutations_keep_running_and_count_each(bus, zenoh_session):
    col = Collector(zenoh_session, "radar/*/targets")
    # no intake budget: every mutation is to reach the decoders (the budgets have tests of their own)
    q = QuantizeNode(bus, QuantizerConfig(), session=zenoh_session, intake=IntakeBudget.unlimited()).start()
    loc = LocalizeNode(bus, LocalizerConfig(k=1), session=zenoh_session, intake=IntakeBudget.unlimited()).start()
    try:
        payloads = valid_payloads()
        rng = np.random.default_rng(5)
        sent = {"raw": 0, "quantized": 0}
        for topic in sent:
            for mutated in mutations(payloads[topic][1], rng, 600):
                zenoh_session.put(f"radar/f0/{topic}", mutated)
                sent[topic] += 1
        for i in range(3):  # then good frames of another sensor
            zenoh_session.put("radar/ok/raw", encode_raw(RawFrameMsg("ok", i, time.time_ns(),
                                                                     SCENE.radar.config_id(), FRAME)))
        wait_until(lambda: len(col.of("ok/targets")) == 3, 30, "targets after the fuzz")

        def settled():
            tq, tl = q.totals(), loc.totals()
            return tq["frames_in"] == sent["raw"] + 3 and tl["frames_in"] >= sent["quantized"] + 3

        wait_until(settled, 30, "every mutated payload received")
        def accounted(node):  # every payload published, dropped or counted as an error
            t = node.totals()
            return t["frames_out"] + t["drops"] + t["decode_errors"] + t["invalid_frames"] \
                + t["processing_errors"] + t["over_budget"] + t["refused"] == t["frames_in"]

        for node in (q, loc):  # (the localizer's input also holds the quantizer's outputs)
            wait_until(lambda: accounted(node), 20, f"{node.name} to account for every payload")
            assert not node.errors and node.totals()["worker_restarts"] == 0, node.name
            assert node.totals()["decode_errors"] + node.totals()["invalid_frames"] > 100  # (a flip in the data is valid)
    finally:
        q.stop()
        loc.stop()
