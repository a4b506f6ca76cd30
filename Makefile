# Two-command quick start: `make demo` and `make test` each build .venv on first use.
PYTHON ?= $(shell command -v python3.11 2>/dev/null || command -v python3)
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed

.PHONY: demo test lint bench docs clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[test]'
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/misdirect reproduce --quick --out results

# Two pytest workers (pytest-xdist), one per core; each on one BLAS thread so that OpenBLAS's
# own threads do not spin against the other worker's (docs/benchmarks.md, "The enumeration's
# kernel"). TEST_WORKERS=0 runs the suite in one process.
TEST_WORKERS ?= 2
test: $(STAMP)
	OPENBLAS_NUM_THREADS=1 $(BIN)/python -m pytest -q -n $(TEST_WORKERS)

# mkdocs-material + mkdocstrings into the same .venv; --strict: any warning fails the build
docs: $(STAMP)
	$(BIN)/python -m pip install --quiet -e '.[docs]'
	NO_MKDOCS_2_WARNING=1 $(BIN)/mkdocs build --strict

# results go to $(BENCH_OUT), results/bench by default (ignored by git); the committed ones
# in bench/results are refreshed with `make bench BENCH_OUT=bench/results` (then git diff)
BENCH_OUT ?= results/bench
bench: $(STAMP)
	$(BIN)/python bench/speed.py --out $(BENCH_OUT)
	$(BIN)/python bench/real_chains.py --out $(BENCH_OUT)
	$(BIN)/python bench/milp_scaling.py --out $(BENCH_OUT)
	$(BIN)/python bench/hard_instances.py --out $(BENCH_OUT)
	$(BIN)/python bench/defence.py --out $(BENCH_OUT)
	$(BIN)/python bench/proofs_on_cycles.py --out $(BENCH_OUT)
	$(BIN)/python bench/covering_bound.py --out $(BENCH_OUT)
	$(BIN)/python bench/enumeration_kernel.py --out $(BENCH_OUT)
	$(BIN)/python bench/stealth_speed.py --out $(BENCH_OUT)
	$(BIN)/python bench/stealth_lagrangian.py --out $(BENCH_OUT)
	$(BIN)/python bench/robust.py --out $(BENCH_OUT)
	$(BIN)/python bench/robust_large.py --out $(BENCH_OUT)
	$(BIN)/python bench/robust_paynt.py --out $(BENCH_OUT) --runs floor
	$(BIN)/python bench/stealth.py --out $(BENCH_OUT)
	$(BIN)/python bench/stealth_automaton.py --out $(BENCH_OUT)

lint: $(STAMP)
	$(BIN)/ruff check src tests bench
	$(BIN)/ruff format --check src tests bench
	$(BIN)/mypy

clean:
	rm -rf $(VENV) build dist site src/*.egg-info .pytest_cache .ruff_cache
