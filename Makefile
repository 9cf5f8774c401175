# qradar: `make run` (the main job) and `make test` create .venv and install on first use.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed-stamp
KERNEL_STAMP := $(VENV)/.kernels-stamp
JS_STAMP := tests/js/node_modules/.installed-stamp
OUT    ?= out

.PHONY: run test test-fast js-deps web-vendor bench montecarlo-quick montecarlo-paper docs-figures docs-lab clean

# Set-up, once: a line per step with the time it takes on a 2-core host (4-10 min in all, measured: 8.3 min on a fresh clone of 2026-11-29, make run included).
$(STAMP): pyproject.toml
	@$(PYTHON) -c 'import sys; sys.exit(0 if sys.version_info >= (3, 11) else "qradar needs Python >= 3.11; set PYTHON=python3.11")'
	@echo "qradar set-up, once: a virtual environment in $(VENV), its packages, then cml's compiled kernels"
	$(PYTHON) -m venv $(VENV)
	@echo "installing qradar and its dependencies with pip (numpy, scipy, numba, zenoh, mcap, ...): 1-2 min"
	$(PY) -m pip install --quiet --disable-pip-version-check -e '.[test]'
	@touch $(STAMP)

# cml's and the dither's compiled kernels into numba's cache: on set-up, and again whenever their
# source changed (after a pull, a node would otherwise compile them while frames wait: a run's
# first minutes without targets)
KERNEL_SOURCES := $(wildcard pipeline/dsp/cml/*.py pipeline/dsp/cml/kernels/*.py pipeline/dsp/dither*.py)
$(KERNEL_STAMP): $(STAMP) $(KERNEL_SOURCES)
	@$(PY) -c 'from pipeline.dsp.cml.loading import compile_verbose; compile_verbose()'
	@$(PY) -c 'from pipeline.dsp.dither import load_kernel; load_kernel()'
	@echo "set-up done: the next commands start at once"
	@touch $(KERNEL_STAMP)

# cml's inner kernels that tests/test_cml_{detect,count,kernels}.py call on their own, compiled into
# numba's cache once as the tests call them (tests/inner_kernels.py: ~45 s of CPU on a fresh
# clone, which the first suite paid otherwise), again when their source changed
TEST_KERNEL_STAMP := $(VENV)/.test-kernels-stamp
$(TEST_KERNEL_STAMP): $(KERNEL_STAMP) $(KERNEL_SOURCES) tests/inner_kernels.py
	@echo "compiling the inner kernels the tests call on their own into numba's cache: ~1 min, once"
	@$(PY) tests/inner_kernels.py
	@touch $(TEST_KERNEL_STAMP)

# The Foxglove test client's node packages (tests/test_foxglove.py), from the committed lock file.
$(JS_STAMP): tests/js/package.json tests/js/package-lock.json
	cd tests/js && npm ci --no-audit --no-fund
	@touch $(JS_STAMP)

js-deps: $(JS_STAMP)

# The web page's plotting library, vendored (qradar/web/static/vendor/uplot/README.md): uPlot from
# npm at a pinned version, its tarball checked against the registry's integrity hash, then its
# minified script, its style and its licence copied beside the page.
UPLOT_VERSION   := 1.6.32
UPLOT_INTEGRITY := sha512-KIMVnG68zvu5XXUbC4LQEPnhwOxBuLyW1AHtpm6IKTXImkbLgkMy+jabjLgSLMasNuGGzQm/ep3tOkyTxpiQIw==
UPLOT_DIR       := qradar/web/static/vendor/uplot

web-vendor:
	@tmp=$$(mktemp -d) && trap 'rm -rf "$$tmp"' EXIT && cd "$$tmp" \
	&& npm pack --silent uplot@$(UPLOT_VERSION) >/dev/null \
	&& got="sha512-$$(openssl dgst -sha512 -binary uplot-$(UPLOT_VERSION).tgz | base64 -w0)" \
	&& if [ "$$got" != "$(UPLOT_INTEGRITY)" ]; then \
	     echo "uplot-$(UPLOT_VERSION).tgz: integrity $$got, expected $(UPLOT_INTEGRITY)" >&2; exit 1; fi \
	&& tar xzf uplot-$(UPLOT_VERSION).tgz \
	&& cp package/dist/uPlot.iife.min.js package/dist/uPlot.min.css package/LICENSE "$(CURDIR)/$(UPLOT_DIR)/" \
	&& echo "vendored uplot@$(UPLOT_VERSION) ($(UPLOT_INTEGRITY)) into $(UPLOT_DIR)"

# The main job: simulated K-MD2 (the chamber, calibrated) -> driver -> 1-bit dithered quantizer -> cml, over zenoh.
run: $(KERNEL_STAMP)
	@$(BYTECODE)
	$(VENV)/bin/qradar run --duration 15 --calibration recordings/chamber-cal.json

# A short Monte Carlo of the paper's four schemes.
montecarlo-quick: $(KERNEL_STAMP)
	$(VENV)/bin/qradar montecarlo --K 1 2 --runs 4000 --out $(OUT)/montecarlo-quick

# The deterministic figures of docs/ (tests/test_doc_figures.py checks the docs against them), and
# the web view's screenshot in the README (headless chromium on the README's command).
docs-figures: $(KERNEL_STAMP)
	$(PY) docs/figures/regenerate.py
	$(PY) docs/figures/web_view.py
	$(PY) -m experiments.curves docs/figures

# The whole suite, slow tests included (CI runs this).
# docs/lab.md's tables of the lab file's keys, from the options' definitions (tests/test_lab.py checks them).
docs-lab: $(KERNEL_STAMP)
	$(PY) -c 'from pathlib import Path; from qradar.cli import lab, schema, run_command; \
	  lab.update_docs(Path("docs/lab.md"), schema.Schema("run", run_command.RUN_PARTS))'

# four pytest-xdist workers on this 2-core machine: the process tests wait on their children much
# of the time, so two kept 1.4 cores busy (612-749 s), three 1.5-1.66 (327-385 s), four 1.68
# (264-304 s five times in a row on a fresh clone, 404 s under two busy loops, 2026-11-29, once the
# tests waited on events instead of fixed durations), five no more (334 s against four's 339 s back to
# back, 2026-11-30); the tests that measure time or memory (marked `measure`)
# share one worker, the tests sharing a module's fixture another (--dist loadgroup,
# tests/conftest.py); `make test TEST_WORKERS=0`: one process
TEST_WORKERS ?= 4
TEST_DIST = $(if $(filter 0,$(TEST_WORKERS)),,-n $(TEST_WORKERS) --dist loadgroup)

# qradar's modules compiled to bytecode (__pycache__/, git-ignored) before the tests start their
# hundreds of processes: where PYTHONDONTWRITEBYTECODE is set (this host's environment sets it)
# Python writes none and compiles each module from source in every process, 0.15-0.2 s of CPU a
# start (0.85 -> 0.68 s to import a node's modules); it still reads them, and compileall writes
# only what changed (0.25 s when nothing did; a checkout it cannot write to: skipped)
BYTECODE = $(PY) -m compileall -q -j0 radar_driver pipeline replay qradar experiments benchmarks tests >/dev/null 2>&1 || true

test: $(TEST_KERNEL_STAMP) $(JS_STAMP)
	@$(BYTECODE)
	$(PY) -m pytest -q $(TEST_DIST)

test-fast: $(TEST_KERNEL_STAMP) $(JS_STAMP)
	@$(BYTECODE)
	$(PY) -m pytest -q $(TEST_DIST) -m "not slow"

# Every benchmark that runs alone on one host (the list: SUITE in benchmarks/suite.py), each in a
# fresh process; `make bench SHORT=1`: each with its shortest options (a smoke run, a few minutes).
bench: $(KERNEL_STAMP)
	$(PY) benchmarks/suite.py $(if $(SHORT),--short)

# The paper's full run: 320 000 x K runs per scheme, K = 1 and 2, all four schemes.
montecarlo-paper: $(KERNEL_STAMP)
	$(VENV)/bin/qradar montecarlo --K 1 2 --out $(OUT)/montecarlo-paper

clean:
	rm -rf $(VENV) $(OUT)/* .pytest_cache *.egg-info tests/js/node_modules  # out/ itself stays: outputs go into it
