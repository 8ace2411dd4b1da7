"""The layers of the common library, the libraries beside it, and what a service package may be.

shared/ holds the layers every process builds on: `contracts` (messages, codec) at the bottom, `frames`
and `atomic` beside it, then `robots` (arm and hand models, limits), then `world` (objects, perception,
simulation, the push judge); `bus` and `data` sit on the contracts and on `atomic`. Above them, what the
services compute and what the CLI, the evaluation and the benches use as well: `synthesis` (the
generator's pose optimisation), `validation` (push validation and arm rollouts, with their job handler),
`sampling` (the diffusion and nearest-neighbour samplers, their critic and training), `planning` (the
push pipeline), `execution` (the robot contract, the safety executor and a folder per device) and
`data_engine` (objects -> generator -> validator -> pose store, over the bus). `visualisation/` and
`client/` are libraries outside the common library: they may use it, it never uses them, nor any
service, nor the CLI, the evaluation or the deployment.

A `services/<name>/` package is that process: its entry point, its bus adapter and what only it uses.
Nothing outside it imports it (docs/architecture.md, "Where things go").
"""
from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PROJECT = {"shared", "visualisation", "client", "services", "cli", "evaluation", "deploy", "bench", "zenoh"}

# What each layer may import (besides itself and third-party packages other than zenoh).
ALLOWED = {
    "shared.contracts": set(),
    "shared.atomic": set(),
    "shared.frames": {"shared.contracts"},
    "shared.bus": {"shared.contracts", "zenoh"},
    "shared.data": {"shared.atomic"},
    "shared.robots": {"shared.atomic", "shared.contracts", "shared.frames"},
    "shared.world": {"shared.atomic", "shared.contracts", "shared.frames", "shared.robots"},
    "shared.synthesis": {"shared.atomic", "shared.contracts", "shared.frames", "shared.robots", "shared.world"},
    "shared.validation": {"shared.contracts", "shared.frames", "shared.robots", "shared.world", "shared.bus"},
    "shared.sampling": {"shared.atomic", "shared.contracts", "shared.data", "shared.frames", "shared.robots",
                        "shared.world"},
    "shared.planning": {"shared.atomic", "shared.contracts", "shared.frames", "shared.robots", "shared.world"},
    "shared.execution": {"shared.atomic", "shared.contracts", "shared.frames", "shared.robots", "shared.world"},
    "shared.data_engine": {"shared.atomic", "shared.bus", "shared.contracts", "shared.data", "shared.frames",
                           "shared.robots", "shared.world"},
    "visualisation": {"shared.atomic", "shared.contracts", "shared.frames", "shared.robots", "shared.world"},
    "client": {"shared.contracts", "shared.bus", "zenoh"},
}


def _layer(module: str) -> str:
    parts = module.split(".")
    return ".".join(parts[:2]) if parts[0] == "shared" and len(parts) > 1 else parts[0]


def _project_imports(path: Path) -> set[str]:
    names = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module)
    return {name for name in names if name.split(".")[0] in PROJECT}


def test_shared_holds_only_its_layers():
    top = {p.name for p in (ROOT / "shared").iterdir() if p.name != "__pycache__"}
    assert top == {"__init__.py", "atomic.py", "frames.py", "contracts", "bus", "robots", "world", "data", "synthesis",
                   "validation", "sampling", "planning", "execution", "data_engine.py"}


def test_every_layer_imports_only_the_layers_below_it():
    for package in ("shared", "visualisation", "client"):
        for path in (ROOT / package).rglob("*.py"):
            parts = path.relative_to(ROOT).with_suffix("").parts
            if parts == ("shared", "__init__"):
                continue
            layer = _layer(".".join(parts))
            assert layer in ALLOWED, f"{path.relative_to(ROOT)}: a new layer, give it a row in ALLOWED"
            wrong = {name for name in _project_imports(path) if _layer(name) not in ALLOWED[layer] | {layer}}
            assert not wrong, f"{path.relative_to(ROOT)} ({layer}) imports {sorted(wrong)}"


# Outside a service's own package, only its tests may import it. The one exception: the chaos bench runs the
# robot bridge's bus side in its own process, to time a stop at the simulated robot itself (bench/chaos.py).
SERVICE_IMPORTERS_ALLOWED = {("bench/chaos.py", "services.robot_bridge.service")}


def test_nothing_outside_a_service_imports_it():
    """What the CLI, the evaluation, the benches or another service use lives in shared/ (or beside it)."""
    found = set()
    for path in ROOT.rglob("*.py"):
        rel = path.relative_to(ROOT)
        if rel.parts[0] in {"tests", ".venv", "results", "build"} or "site-packages" in rel.parts:
            continue
        own = ".".join(rel.parts[:2]) if rel.parts[0] == "services" else None
        for name in _project_imports(path):
            parts = name.split(".")
            if parts[0] == "services" and len(parts) > 1 and ".".join(parts[:2]) != own:
                found.add((str(rel), name))
    assert found <= SERVICE_IMPORTERS_ALLOWED, sorted(found - SERVICE_IMPORTERS_ALLOWED)


def test_a_service_package_holds_its_process_only():
    """Each services/<name>/ has its entry point; every other module of it is its bus adapter or what only it uses."""
    for package in sorted(p for p in (ROOT / "services").iterdir() if p.is_dir() and p.name != "__pycache__"):
        assert (package / "__main__.py").exists(), f"{package.relative_to(ROOT)} has no entry point"


# The algorithm modules of each service: plain modules that know nothing of Zenoh (only a service's
# bus adapter, its service.py, and the robot bridge's bus_safety.py load it).
ALGORITHMS = ("shared.planning.pipeline", "shared.planning.ranking", "shared.planning.multistep",
              "shared.validation.validator", "shared.validation.rollout", "shared.validation.augment",
              "shared.sampling.sampling", "shared.sampling.train", "shared.sampling.nearest_neighbor",
              "shared.synthesis.synthesis", "shared.execution.executor")


def test_no_algorithm_module_loads_zenoh_even_through_its_imports():
    import subprocess
    import sys

    code = f"import sys, {', '.join(ALGORITHMS)}; loaded = 'zenoh' in sys.modules; print(loaded); sys.exit(loaded)"
    done = subprocess.run([sys.executable, "-c", code], cwd=ROOT, timeout=300, capture_output=True, text=True)
    assert done.returncode == 0, f"an algorithm module loads zenoh: {done.stdout}{done.stderr[-2000:]}"
