# One-command set-up: `make demo` and `make test` install everything they need on a fresh machine.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: install demo test bench chaos clean

install: $(STAMP)

# torch first: the pinned CPU wheel is on local disk; any other resolution pulls a multi-GB CUDA build.
$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/pip install --upgrade pip >/dev/null
	$(BIN)/pip install torch==2.13.0
	$(BIN)/pip install -e '.[test]'
	touch $(STAMP)

demo: install
	$(BIN)/gd2p demo

# Lint (ruff, whole tree) and type-check (mypy, all product code, strict on shared/, visualisation/, client/; cached in
# .mypy_cache) before the suite.
test: install
	$(BIN)/ruff check .
	$(BIN)/mypy
	$(BIN)/python -m pytest -q

# Break the system on purpose (workers, router, leases, e-stop) and print what a user would feel (docs/safety.md).
chaos: install
	$(BIN)/python bench/chaos.py --json

bench: install
	for b in bench/*.py; do [ $$b = bench/chaos.py ] || $(BIN)/python $$b --json || exit 1; done

clean:
	rm -rf $(VENV) build *.egg-info
