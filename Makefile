# qradar: `make run` (the main job) and `make test` create .venv and install on first use.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed-stamp
JS_STAMP := tests/js/node_modules/.installed-stamp
OUT    ?= out

.PHONY: run test test-fast js-deps bench montecarlo-quick montecarlo-paper docs-figures clean

$(STAMP): pyproject.toml
	@$(PYTHON) -c 'import sys; sys.exit(0 if sys.version_info >= (3, 11) else "qradar needs Python >= 3.11; set PYTHON=python3.11")'
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --disable-pip-version-check -e '.[test]'
	# cml's and the dither's compiled kernels, into numba's on-disk cache: a node's first frame then loads them (~0.5 s)
	$(PY) -c 'from pipeline.dsp.cml import load_kernels; load_kernels()'
	$(PY) -c 'from pipeline.dsp.dither import load_kernel; load_kernel()'
	@touch $(STAMP)

# The Foxglove test client's node packages (tests/test_foxglove.py), from the committed lock file.
$(JS_STAMP): tests/js/package.json tests/js/package-lock.json
	cd tests/js && npm ci --no-audit --no-fund
	@touch $(JS_STAMP)

js-deps: $(JS_STAMP)

# The main job: simulated K-MD2 -> driver -> 1-bit dithered quantizer -> PBP, over zenoh.
run: $(STAMP)
	$(VENV)/bin/qradar run --duration 15 --calibration recordings/chamber-cal.json

# A short Monte Carlo of the paper's four schemes.
montecarlo-quick: $(STAMP)
	$(VENV)/bin/qradar montecarlo --K 1 2 --runs 4000 --out $(OUT)/montecarlo-quick

# The deterministic figures of docs/ (tests/test_doc_figures.py checks the docs against them).
docs-figures: $(STAMP)
	$(PY) docs/figures/regenerate.py

# The whole suite, slow tests included (CI runs this).
test: $(STAMP) $(JS_STAMP)
	$(PY) -m pytest -q

test-fast: $(STAMP) $(JS_STAMP)
	$(PY) -m pytest -q -m "not slow"

# Every benchmark that runs alone on one host (the list: SUITE in benchmarks/suite.py), each in a
# fresh process; `make bench SHORT=1`: each with its shortest options (a smoke run, a few minutes).
bench: $(STAMP)
	$(PY) benchmarks/suite.py $(if $(SHORT),--short)

# The paper's full run: 320 000 x K runs per scheme, K = 1 and 2, all four schemes.
montecarlo-paper: $(STAMP)
	$(VENV)/bin/qradar montecarlo --K 1 2 --out $(OUT)/montecarlo-paper

clean:
	rm -rf $(VENV) $(OUT) .pytest_cache *.egg-info tests/js/node_modules
