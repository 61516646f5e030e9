# gatv — two commands matter: `make demo` and `make test` (see README).
PYTHON ?= python3.11
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed
TSTAMP := $(VENV)/.installed-test
export PYVISTA_OFF_SCREEN := true

.PHONY: demo test test-slow bench gallery clean

$(PY):
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip

$(STAMP): pyproject.toml | $(PY)
	$(PY) -m pip install -q -e .
	touch $@

$(TSTAMP): pyproject.toml | $(PY)
	$(PY) -m pip install -q -e '.[test]'
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

clean:
	rm -rf $(VENV) demo_out gallery_out .pytest_cache
