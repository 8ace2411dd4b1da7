# One-command set-up: `make demo` and `make test` install everything they need on a fresh machine.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: install browser egl demo test bench chaos clean

install: $(STAMP) browser egl

# The live view's browser test (tests/test_view.py) drives headless Chromium: Debian's chromium and
# chromium-driver, installed when missing (needs root or sudo; skipped with a note otherwise).
browser:
	@if command -v chromium >/dev/null && command -v chromedriver >/dev/null; then :; \
	elif [ "$$(id -u)" = 0 ]; then apt-get update && DEBIAN_FRONTEND=noninteractive apt-get install -y chromium chromium-driver; \
	elif command -v sudo >/dev/null; then sudo apt-get update && sudo DEBIAN_FRONTEND=noninteractive apt-get install -y chromium chromium-driver; \
	else echo "note: chromium / chromium-driver missing and no root: tests/test_view.py's browser tests will skip"; fi

# MuJoCo's depth cameras (shared/execution/robots/mujoco/cameras.py; tests/test_mujoco_world.py) render headless
# through EGL: Debian's libEGL with Mesa's EGL and software OpenGL, installed when missing (as the browser above).
egl:
	@if ldconfig -p | grep -q libEGL_mesa; then :; \
	elif [ "$$(id -u)" = 0 ]; then apt-get update && DEBIAN_FRONTEND=noninteractive apt-get install -y libegl1 libegl-mesa0 libgl1-mesa-dri; \
	elif command -v sudo >/dev/null; then sudo apt-get update && sudo DEBIAN_FRONTEND=noninteractive apt-get install -y libegl1 libegl-mesa0 libgl1-mesa-dri; \
	else echo "note: Mesa's EGL missing and no root: MuJoCo's depth rendering (tests/test_mujoco_world.py) will fail"; fi

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
# .mypy_cache) before the suite. The suite runs on two workers (the machine's two cores), a test module per worker so
# its module-wide fixtures (routers, a running system) start once (the time it saves: CHANGELOG).
test: install
	$(BIN)/ruff check .
	$(BIN)/mypy
	$(BIN)/python -m pytest -q -n 2 --dist loadfile --durations=15

# Break the system on purpose (workers, router, leases, e-stop) and print what a user would feel (docs/safety.md).
chaos: install
	$(BIN)/python bench/chaos.py --json

bench: install
	for b in bench/*.py; do [ $$b = bench/chaos.py ] || $(BIN)/python $$b --json || exit 1; done

clean:
	rm -rf $(VENV) build *.egg-info
