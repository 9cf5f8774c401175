"""One set of defaults (issue 23): every command that localizes or quantizes (``run``,
``localize``, ``quantize``, ``drive --quantize``, ``source --quantized``, ``reprocess``) and
every configuration behind them take the decoder and the dither scale of
:mod:`pipeline.defaults`, and that alpha is the best of a sweep on the committed recording.
(Each option's default is its field's, tests/test_cli_help.py; no help text is parsed.)"""

import inspect
from pathlib import Path

import numpy as np

from pipeline import defaults
from pipeline.dsp.decode import ALGOS, DEFAULT_ALGO, DEFAULT_ALPHA, DecoderConfig, default_alpha
from pipeline.dsp.gate import RangeGate
from pipeline.nodes.stream import LocalizerConfig
from pipeline.dsp.quantize import QuantizerConfig
from qradar.cli import build_parser
from qradar.cli.parts import edge_quantizer, quantizer_of as quantizer_config
from qradar.cli.run_command import run_alpha
from qradar.run import RunConfig
from replay import reprocess
from replay.reprocess import ReprocessConfig, load_raw, parse_alphas, radar_for, sweep, truth_scene

ROOT = Path(__file__).resolve().parents[1]


def parse(*argv):
    return build_parser().parse_args(list(argv))


def test_the_one_definition():
    assert DEFAULT_ALGO == defaults.DEFAULT_ALGO == "cml"
    assert DEFAULT_ALPHA == defaults.DEFAULT_ALPHA == defaults.BEST_ALPHA["cml"] == default_alpha(DEFAULT_ALGO)
    assert set(defaults.BEST_ALPHA) == set(ALGOS) and all(0 <= a <= 1 for a in defaults.BEST_ALPHA.values())


def test_every_command_defaults_to_the_one_definition():
    args = parse("localize")
    assert args.algo == DEFAULT_ALGO

    args = parse("run")
    assert args.algo == DEFAULT_ALGO and run_alpha(args) == DEFAULT_ALPHA
    assert quantizer_config(args, run_alpha(args)).alpha == DEFAULT_ALPHA
    assert run_alpha(parse("run", "--algo", "pbp")) == default_alpha("pbp")  # alpha follows a chosen decoder

    args = parse("quantize")
    assert args.alpha == DEFAULT_ALPHA and quantizer_config(args).alpha == DEFAULT_ALPHA

    for argv in (("drive", "--port", "/dev/null", "--quantize"), ("source", "--quantized")):
        args = parse(*argv)
        quantizer, _ = edge_quantizer(args)
        assert quantizer.alpha == DEFAULT_ALPHA, argv

    args = parse("reprocess", "recordings/chamber.mcap")
    assert args.algos == [DEFAULT_ALGO]
    assert DEFAULT_ALPHA in parse_alphas(args.alpha)  # its sweep holds the default


def test_every_configuration_defaults_to_the_one_definition():
    assert QuantizerConfig().alpha == DEFAULT_ALPHA
    assert DecoderConfig().algo == DEFAULT_ALGO
    assert LocalizerConfig().algo == DEFAULT_ALGO
    assert RunConfig().algo == DEFAULT_ALGO and RunConfig().quantizer.alpha == DEFAULT_ALPHA
    assert ReprocessConfig(Path("x.mcap")).algos == (DEFAULT_ALGO,)
    for fn in (reprocess.run_alpha, reprocess.sweep):
        assert inspect.signature(fn).parameters["algo"].default == DEFAULT_ALGO, fn.__name__


def test_the_default_alpha_is_the_best_of_a_sweep_on_the_committed_recording():
    """cml on recordings/chamber.mcap (off the grid, sensor noise), with the default range
    gate, alpha in steps of 0.1 around the default, the mean error of the two reflectors
    averaged over five dither seeds (one seed's best moves with its draw of the dither: on
    seed 0 alone the best of 0:1:0.05 is 0.65): the default is the best within a step."""
    rec = load_raw(ROOT / "recordings" / "chamber.mcap")
    scene = truth_scene(rec, None)
    radar = radar_for(rec, scene.radar)
    step = 0.1
    alphas = np.round(np.clip(DEFAULT_ALPHA + step * np.arange(-2, 3), 0.0, 1.0), 10)
    errors = np.mean([sweep(rec, radar, scene, alphas, seed=seed, algo=DEFAULT_ALGO, bar=False,
                            gate=RangeGate.default(radar)).mean_error_m.mean(axis=1) for seed in range(5)], axis=0)
    best = alphas[int(np.argmin(errors))]
    assert abs(best - DEFAULT_ALPHA) <= step + 1e-9, dict(zip(alphas.tolist(), np.round(errors, 4).tolist()))
    assert errors.min() < 0.25  # the figure of the README (0.232 m over these five seeds)
