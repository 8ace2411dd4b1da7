"""Shared pytest fixtures: an in-process Zenoh router on a free loopback port."""
from __future__ import annotations

import contextlib
import importlib.util
import json
import os
import socket
import sys
from pathlib import Path
from types import ModuleType

import pytest

os.environ.setdefault("OMP_NUM_THREADS", "1")
# MuJoCo picks its OpenGL platform when first imported: the tests render its depth cameras headless.
os.environ.setdefault("MUJOCO_GL", "egl")

# The robot bridge of the bus tests about planning, execution, confirmation and the view sees the object through the
# truth tracker (`--tracking truth`): a third of the time of rendering and registering depth frames at 10 Hz. The
# image tracker's own path through the bus is tested in test_interfaces.py, test_image_tracking.py and
# test_closed_loop.py.
TRUTH_TRACKED = {"tracking": "truth"}


def load_bench(name: str) -> ModuleType:
    """bench/<name>.py as a module: bench/ is not a package, so the script is loaded from its file (registered
    under `bench_<name>`, which its dataclasses look their module up by)."""
    path = Path(__file__).resolve().parent.parent / "bench" / f"{name}.py"
    spec = importlib.util.spec_from_file_location(f"bench_{name}", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def router_config(endpoint: str):
    import zenoh

    cfg = zenoh.Config()
    cfg.insert_json5("mode", json.dumps("router"))
    cfg.insert_json5("listen/endpoints", json.dumps([endpoint]))
    cfg.insert_json5("scouting/multicast/enabled", "false")
    cfg.insert_json5("scouting/gossip/enabled", "false")
    return cfg


@contextlib.contextmanager
def running_router():
    """An embedded router on a free loopback port for the duration of the block; yields its endpoint."""
    import zenoh

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    session = zenoh.open(router_config(endpoint))
    try:
        yield endpoint
    finally:
        session.close()


@pytest.fixture()
def zenoh_router():
    """Start an embedded router; yields its endpoint, e.g. 'tcp/127.0.0.1:40123'."""
    with running_router() as endpoint:
        yield endpoint


@pytest.fixture(scope="module")
def module_router():
    """One router for a whole test module (when the module's workers take seconds to start)."""
    with running_router() as endpoint:
        yield endpoint
