# gatv — two commands matter: `make demo` and `make test` (see README).
PYTHON ?= python3.11
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
TSTAMP := $(VENV)/.installed-test
DSTAMP := $(VENV)/.installed-docs
export PYVISTA_OFF_SCREEN := true

.PHONY: demo test test-slow bench gallery docs docs-fast wheel clean

$(PY):
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip

# installing also compiles the numba kernels once (`gatv warmup`): the first demo then starts at full speed
$(STAMP): pyproject.toml | $(PY)
	$(PY) -m pip install -q -e .
	$(PY) -m gatv warmup
	touch $@

$(TSTAMP): pyproject.toml | $(PY)
	$(PY) -m pip install -q -e '.[test]'
	touch $(STAMP) $@

$(DSTAMP): pyproject.toml | $(PY)
	$(PY) -m pip install -q -e '.[docs]'
	touch $(STAMP) $@

demo: $(STAMP)
	mkdir -p demo_out
	$(PY) -m gatv demo --out demo_out/result.json --render demo_out/registration.png

test: $(TSTAMP)
	$(PY) -m pytest -q

test-slow: $(TSTAMP)
	$(PY) -m pytest -q -m slow

bench: $(STAMP)
	$(PY) benchmarks/voting.py
	$(PY) benchmarks/table1.py
	$(PY) benchmarks/table2.py

gallery: $(STAMP)
	$(PY) gallery/make_all.py --out gallery_out

# the Sphinx site (API reference + gallery, rendered off screen) in docs/_build/html
docs: $(DSTAMP)
	$(PY) -m sphinx -b html -q docs docs/_build/html
	@echo "docs: docs/_build/html/index.html"

# the same pages without running the gallery scripts
docs-fast: $(DSTAMP)
	$(PY) -m sphinx -b html -q -D plot_gallery=0 docs docs/_build/html

# a wheel and an sdist in dist/
wheel: | $(PY)
	$(PY) -m pip install -q build
	$(PY) -m build --outdir dist .

clean:
	rm -rf $(VENV) demo_out gallery_out .pytest_cache docs/_build docs/auto_examples dist
