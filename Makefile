# Every set-up step lives here: a fresh machine needs only python3 (3.11+) with its headers,
# a C compiler (gpocc's compiled loops, gpocc/_kernels.c) and make.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed-stamp
KERNELS_STAMP := $(VENV)/.kernels-stamp
DEMO_OUT ?= demo-out

.PHONY: install bytecode demo test lint fuzz bench experiment clean

install: $(KERNELS_STAMP)

# gpocc's byte-code, compiled ahead: an editable install compiles none, and where
# PYTHONDONTWRITEBYTECODE is set (as on this project's machines) every command would
# compile its ~70 modules from source, 0.2-0.5 s of each start. Up-to-date files are
# skipped, so this costs nothing when nothing changed.
bytecode: $(KERNELS_STAMP)
	$(BIN)/python -m compileall -q gpocc

$(STAMP): pyproject.toml setup.py
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q --upgrade pip
	$(BIN)/python -m pip install -q -e '.[test]'
	touch $(STAMP)

# The compiled loops (gpocc/_kernels.c, built by the install above with the system's C
# compiler): rebuilt in place when their source is newer than the library. gpocc refuses
# to load a library older than its source.
$(KERNELS_STAMP): gpocc/_kernels.c $(STAMP)
	@if [ -z "$$(find gpocc -maxdepth 1 -name '_kernels*.so' -newer gpocc/_kernels.c)" ]; then \
		echo "$(BIN)/python -m pip install -q --no-deps -e ."; \
		$(BIN)/python -m pip install -q --no-deps -e .; fi
	touch $(KERNELS_STAMP)

demo: bytecode
	$(BIN)/gpocc info data/sample/intel_sample.mcap --config data/sample/sample.yaml
	$(BIN)/gpocc train data/sample/intel_sample.mcap --config data/sample/sample.yaml --out $(DEMO_OUT)/model.npz --force
	$(BIN)/gpocc map $(DEMO_OUT)/model.npz --resolution 0.1 --out $(DEMO_OUT)/map --force
	@echo "demo map written to $(DEMO_OUT)/map (open preview.png, probability.tif or map.yaml; map.mcap in Foxglove)"

test: bytecode
	$(BIN)/ruff check gpocc tests bench
	$(BIN)/python -m pytest -n 2 -q -rs

lint: $(KERNELS_STAMP)
	$(BIN)/ruff check gpocc tests bench

# Fresh random inputs for the fuzz tests (make test runs a fixed set); FUZZ_EXAMPLES each.
FUZZ_EXAMPLES ?= 2000
fuzz: $(KERNELS_STAMP)
	GPOCC_FUZZ_EXAMPLES=$(FUZZ_EXAMPLES) $(BIN)/python -m pytest -n 2 -q \
		tests/cli/test_fuzz.py tests/io/test_io_messages.py::test_decoding_gives_a_clean_error_or_a_valid_batch

BENCH_STAMP := $(VENV)/.bench-stamp

$(BENCH_STAMP): $(KERNELS_STAMP)
	$(BIN)/python -m pip install -q -e '.[test,bench]'
	touch $(BENCH_STAMP)

# The benchmark suite (bench/run_bench.py): runs every registered benchmark and writes
# docs/benchmarks.md. One benchmark: .venv/bin/python -m bench.run_bench --only NAME --out -
bench: $(BENCH_STAMP) bytecode
	$(BIN)/python -m bench.run_bench

# The bench extra gives the suite its OctoMap rows (left out with a note without it).
# The variants the defaults are compared with on the page ("Against other settings"):
# each changes one default, or (before-count) the three changed last (bench/experiment.py
# VARIANTS). Any list can be given, e.g.
#   make experiment EXPERIMENT_COMPARE="before-count offset-holdout hit-gap-0.25"
# (the variants of offset-holdout, HOLDOUT_BASED, need its run beside them).
EXPERIMENT_COMPARE ?= hard-targets before-count learned-g no-label-weights wide-offset two-draw \
	thin-0.1-n192-offset-beams anisotropic double-precision half-overlap blocks-0.5-n64 \
	no-patch-offset hit-gap-0.1
# The defaults learned with other seeds (bench/experiment.py's SPREAD_SEEDS): the page's
# run-to-run spread. A variant's or seed's run maps with the GP with input noise alone (all
# the page compares); the defaults' run, last, maps with every method.
EXPERIMENT_SPREAD = seed-1 seed-2 seed-3 seed-4
experiment: $(BENCH_STAMP) bytecode
	for v in $(EXPERIMENT_COMPARE) $(EXPERIMENT_SPREAD); do \
		$(BIN)/python -m bench.experiment sim real clean --variant $$v --doc /dev/null > /dev/null || exit 1; done
	$(BIN)/python -m bench.experiment $(addprefix --compare ,$(EXPERIMENT_COMPARE)) --spread

clean:
	rm -rf $(VENV) $(DEMO_OUT) .pytest_cache build gpocc/_kernels*.so
