"""The one definition of the defaults of every command that localizes or quantizes
(issue 23): ``qradar run``, ``localize``, ``quantize``, ``drive --quantize``, ``source
--quantized`` and ``reprocess``, and of the configurations behind them
(:class:`~pipeline.dsp.quantize.QuantizerConfig`, :class:`~pipeline.dsp.decode.DecoderConfig`,
:class:`~pipeline.nodes.stream.LocalizerConfig`, ``qradar.run.RunConfig``,
``replay.reprocess.ReprocessConfig``). Everything else reads these names; nothing
repeats their values (``tests/test_defaults.py`` parses every command's options).

The default is the decoder and the dither scale that give the best result **off the
range grid** (real reflectors are never on the 0.6 m grid): ``cml`` at its best alpha on
the committed off-grid chamber recording (``qradar reprocess recordings/chamber.mcap
--alpha 0:1:0.05 --algos cml``) and on the off-grid Monte Carlo with sensor noise (docs/science.md,
"Off the grid" and "Recording, replay, re-processing", for the figures and the commands).

The Monte Carlo (``qradar montecarlo``) is not one of these commands: its defaults are the
paper's protocol (PBP, the schemes' own alpha).

Plain values (no imports), so that any module of the package can read them.
"""

#: the decoder of every command that localizes, by name (:class:`pipeline.dsp.decode.Algo`)
DEFAULT_ALGO = "cml"

#: each decoder's best dither scale alpha in [0, 1], what ``qradar run --algo A`` quantizes
#: with unless given ``--alpha``. cml: 0.45, its best on the off-grid chamber recording (mean
#: error over ten dither seeds, alpha in steps of 0.05: 0.228 m, 0.232 m at 0.5, 0.250 m at
#: 0.65, 0.603 m at 1; seed 0 alone is best at 0.65, a draw of the dither) and on the
#: off-grid Monte Carlo with sensor noise 0.1 (K = 1 median 0.304 m; 0.320 m at 0.65, 0.376 m
#: at 1); without sensor noise the full dither is best (docs/science.md). pbp: the paper's best for
#: its noisy chamber (Fig. 5a); qiht: the full dither (its likelihood stage assumes a dither
#: spanning the cell)
BEST_ALPHA = {"pbp": 0.55, "qiht": 1.0, "cml": 0.45}

#: the dither scale of every command that quantizes: the default decoder's best
DEFAULT_ALPHA = BEST_ALPHA[DEFAULT_ALGO]

#: with ``--K auto`` (``localize``, ``run``, ``reprocess``) and ``--count auto`` (the Monte
#: Carlo): the most targets a frame has
DEFAULT_MAX_TARGETS = 4
