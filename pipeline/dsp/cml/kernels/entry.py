"""The kernels Python calls that take the layouts' namedtuples
(:mod:`pipeline.dsp.cml.kernels.layout`): each takes them as plain tuples of the same fields
and hands them on as the namedtuples. numba dispatches a plain tuple in a third of the time of
a namedtuple (measured: 2.4 against 7.3 us a call for :func:`add_target`'s arguments, 3.4 us
for the same 44 fields as separate arguments), which at one frame a call is 5 % of a decode."""

from __future__ import annotations

from numba import njit

from pipeline.dsp.cml.kernels import detect as detection, likelihood, refine as refinement, stages
from pipeline.dsp.cml.kernels.layout import JIT, Codes, Decision, Fit, Gate, Grid, Report, Sources, Steps, Targets


@njit(**JIT)
def evaluate(codes, mu, sigma, g, h):
    """:func:`pipeline.dsp.cml.kernels.likelihood.evaluate`."""
    return likelihood.evaluate(Codes(*codes), mu, sigma, g, h)


@njit(**JIT)
def refine(codes, fit, steps):
    """:func:`pipeline.dsp.cml.kernels.refine.refine`."""
    refinement.refine(Codes(*codes), Fit(*fit), Steps(*steps))


@njit(**JIT)
def settled_score(fit, ge):
    """:func:`pipeline.dsp.cml.kernels.refine.settled_score`."""
    refinement.settled_score(Fit(*fit), ge)


@njit(**JIT)
def detect(sources, grid, gate, seed_gate, nu, live, decision) -> bool:
    """:func:`pipeline.dsp.cml.kernels.detect.detect`."""
    return detection.detect(Sources(*sources), Grid(*grid), Gate(*gate), Gate(*seed_gate), nu, live,
                            Decision(*decision))


@njit(**JIT)
def add_target(sources, grid, gate, seed_gate, fit, codes, steps, sigma, decision, new) -> bool:
    """:func:`pipeline.dsp.cml.kernels.stages.add_target`."""
    return stages.add_target(Sources(*sources), Grid(*grid), Gate(*gate), Gate(*seed_gate), Fit(*fit), Codes(*codes),
                             Steps(*steps), sigma, Decision(*decision), Fit(*new))


@njit(**JIT)
def finish(codes, fit, steps, report, out):
    """:func:`pipeline.dsp.cml.kernels.stages.finish`."""
    stages.finish(Codes(*codes), Fit(*fit), Steps(*steps), Report(*report), Targets(*out))


@njit(**JIT)
def warm(codes, start, first, anneal, sigma, report, out, fit):
    """:func:`pipeline.dsp.cml.kernels.stages.warm`."""
    stages.warm(Codes(*codes), start, Steps(*first), Steps(*anneal), sigma, Report(*report),
                Targets(*out), Fit(*fit))


@njit(**JIT)
def result(fit, y, ramps, report, out):
    """:func:`pipeline.dsp.cml.kernels.stages.result`."""
    stages.result(Fit(*fit), y, ramps, Report(*report), Targets(*out))
