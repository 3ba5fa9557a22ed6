# The README's two commands: `make book` and `make test`.
PYTHON ?= python3
VENV   ?= .venv
BIN    := $(VENV)/bin
SCALE  ?= small
SEED   ?= 0
# XLA's compiled programs are kept on disk and reused when the same program is compiled
# again (the notebooks' loops in the tests, a re-run notebook): the same executable, the
# same numbers, less waiting.  (JAX keeps programs that took over a second to compile;
# keeping every one made no difference to the tests: the primer's two runs, Flow Lenia's and
# the locomotion tests took 260.7 s either way from an empty cache, AMD EPYC, 2026-12-08.)
export JAX_COMPILATION_CACHE_DIR ?= $(CURDIR)/.jax_cache

.PHONY: book test lab lint venv bench lock clean

venv: $(VENV)/.installed

$(VENV)/.installed: requirements.lock pyproject.toml
	@$(PYTHON) -c 'import sys; sys.exit("qdnb needs Python 3.11 or newer (make ... PYTHON=python3.11)" if sys.version_info < (3, 11) else 0)'
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --disable-pip-version-check -r requirements.lock
	$(BIN)/python -m pip install --quiet --disable-pip-version-check --no-deps -e .
	touch $@

## Execute every notebook at SCALE (tiny | small | paper), then render book/_build/html.
book: venv
	$(BIN)/python -m qdnb book --scale $(SCALE) --seed $(SEED)

## The linter, then every notebook at tiny scale and the unit tests, on two workers
## (pytest-xdist, a test file per worker at a time): the notebooks in three groups, each in
## order on one worker (tests/notebook_runs.py), the unit test files filling in behind them;
## the primer also runs in place from a fresh kernel, as a reader runs it (nbmake: no
## papermill, no runner). The 30 slowest tests are listed at the end, and every test's time
## is written to .test-report.xml (CI prints its summary: .ci/durations.py).
test: venv lint
	$(BIN)/python -m pytest -n 2 --dist loadfile --no-loadscope-reorder tests \
	    --nbmake --nbmake-timeout=1200 notebooks/ch2_primer.ipynb --durations=30 \
	    --junitxml=.test-report.xml

lint: venv
	$(BIN)/python -m ruff check .

## JupyterLab on the notebooks, from the venv (its python3 kernel is the project's).
lab: venv
	$(BIN)/python -m jupyter lab --notebook-dir=notebooks

## Throughput benchmarks (JSON in bench/results/); not part of the tests.
bench: venv
	$(BIN)/python bench/rollout.py

## Re-resolve requirements.lock from pyproject.toml's pinned direct dependencies.
lock:
	rm -rf .lock-venv
	$(PYTHON) -m venv .lock-venv
	.lock-venv/bin/python -m pip install --quiet --disable-pip-version-check .
	{ echo '# Full pinned dependency set of qdnb (Linux x86-64, CPython 3.11), from `make lock`.'; \
	  .lock-venv/bin/python -m pip freeze --exclude qdnb; } > requirements.lock
	rm -rf .lock-venv

clean:
	rm -rf book/_build book/chapters book/_status.md book/_paper_scale.md book/_extra
