"""Experiments on simulated frames, apart from recordings: the paper's Monte Carlo (Sec. 5,
:mod:`.montecarlo`), what a run of it writes (:mod:`.report`) and its figures
(:mod:`.plots`: polar error maps, error against M, detection, error against frames). It
imports ``radar_driver``, ``pipeline`` and ``replay`` (the one overwrite policy, the
progress bar), never ``qradar``, and loads no bus, port or file format."""
