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

test: $(STAMP)
	$(BIN)/python -m pytest -q

# mkdocs-material + mkdocstrings into the same .venv; --strict: any warning fails the build
docs: $(STAMP)
	$(BIN)/python -m pip install --quiet -e '.[docs]'
	NO_MKDOCS_2_WARNING=1 $(BIN)/mkdocs build --strict

# NB: overwrites the committed results in bench/results/ (compare with git diff)
bench: $(STAMP)
	$(BIN)/python bench/speed.py --out bench/results
	$(BIN)/python bench/real_chains.py --out bench/results
	$(BIN)/python bench/milp_scaling.py --out bench/results
	$(BIN)/python bench/hard_instances.py --out bench/results
	$(BIN)/python bench/defence.py --out bench/results

lint: $(STAMP)
	$(BIN)/ruff check src tests bench
	$(BIN)/ruff format --check src tests bench
	$(BIN)/mypy

clean:
	rm -rf $(VENV) build dist site src/*.egg-info .pytest_cache .ruff_cache
