# Two entry points: `make demo` and `make test`. Both create .venv and install the package on first use.
PYTHON ?= python3
VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: setup demo test bench clean

setup: $(STAMP)

$(STAMP): pyproject.toml requirements/torch.txt
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -r requirements/torch.txt
	$(PY) -m pip install --quiet -e ".[dev,ray]"
	$(PY) -m pip install --quiet --no-deps robosuite==1.5.2
	touch $(STAMP)

demo: $(STAMP)
	$(PY) -m pipeline demo --out-dir out/demo

# one pytest-xdist worker per core, at most 4 (docs/decisions.md): about 6.5 minutes on 2 cores, 12.5 in one process
test: $(STAMP)
	$(PY) -m pytest -q -n auto --maxprocesses 4

bench: $(STAMP)
	$(PY) benchmarks/bench_render.py

clean:
	rm -rf $(VENV) out
