"""The layers of the common library, and the libraries beside it: who may import whom.

shared/ holds the layers every service builds on: `contracts` (messages, codec) at the bottom, `frames`
and `atomic` beside it, then `robots` (arm and hand models, limits), then `world` (objects, perception,
simulation, the push judge); `bus` and `data` sit on the contracts and on `atomic`. `visualisation/`
and `client/` are libraries outside the common library: they may use it, it never uses them, nor any
service, nor the CLI, the evaluation or the deployment.
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
    assert top == {"__init__.py", "atomic.py", "frames.py", "contracts", "bus", "robots", "world", "data"}


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


# The algorithm modules of each service: plain modules that know nothing of Zenoh (only a service's
# bus adapter, its service.py, and the robot bridge's bus_safety.py load it).
ALGORITHMS = ("services.planner.pipeline", "services.planner.ranking", "services.planner.multistep",
              "services.validator.validator", "services.validator.rollout", "services.validator.augment",
              "services.sampler.sampling", "services.sampler.train", "services.sampler.nearest_neighbor",
              "services.generator.synthesis", "services.robot_bridge.executor")


def test_no_algorithm_module_loads_zenoh_even_through_its_imports():
    import subprocess
    import sys

    code = f"import sys, {', '.join(ALGORITHMS)}; loaded = 'zenoh' in sys.modules; print(loaded); sys.exit(loaded)"
    done = subprocess.run([sys.executable, "-c", code], cwd=ROOT, timeout=300, capture_output=True, text=True)
    assert done.returncode == 0, f"an algorithm module loads zenoh: {done.stdout}{done.stderr[-2000:]}"
