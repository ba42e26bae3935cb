# Every set-up step lives here: a fresh machine needs only python3 (3.11+) and make.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed-stamp
DEMO_OUT ?= demo-out

.PHONY: install demo test lint bench experiment clean

install: $(STAMP)

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e '.[test]'
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/gpocc info data/sample/intel_sample.mcap --config data/sample/sample.yaml
	$(BIN)/gpocc train data/sample/intel_sample.mcap --config data/sample/sample.yaml --out $(DEMO_OUT)/model.npz --force
	$(BIN)/gpocc map $(DEMO_OUT)/model.npz --resolution 0.1 --out $(DEMO_OUT)/map --force
	@echo "demo map written to $(DEMO_OUT)/map (open preview.png, probability.tif or map.yaml)"

test: $(STAMP)
	$(BIN)/ruff check gpocc tests bench
	$(BIN)/python -m pytest -n 2 -q -rs

lint: $(STAMP)
	$(BIN)/ruff check gpocc tests bench

BENCH_STAMP := $(VENV)/.bench-stamp

$(BENCH_STAMP): $(STAMP)
	$(BIN)/python -m pip install -q -e '.[test,bench]'
	touch $(BENCH_STAMP)

bench: $(BENCH_STAMP)
	$(BIN)/python bench/run_bench.py

experiment: $(STAMP)
	$(BIN)/python bench/experiment.py

clean:
	rm -rf $(VENV) $(DEMO_OUT) .pytest_cache
