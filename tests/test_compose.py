"""The container deployment, checked without a Docker engine: what compose would run must exist.

Parses deploy/docker-compose.yml and the Dockerfile and checks them against the package: every
service command is an importable `python -m` module, every healthcheck is a real `gd2p` command,
the router image matches the installed Zenoh, validators scale, recordings persist.
"""
from __future__ import annotations

import argparse
import importlib.metadata
import importlib.util
import re
from pathlib import Path

import pytest
import yaml
import zenoh

import cli.main
import cli.system
from deploy import scale_validators

ROOT = Path(__file__).resolve().parents[1]
COMPOSE_FILE = ROOT / "deploy" / "docker-compose.yml"
SERVICES = ("generator", "validator", "sampler", "planner", "robot_bridge", "recorder")


@pytest.fixture(scope="module")
def compose() -> dict:
    return yaml.safe_load(COMPOSE_FILE.read_text())


def python_module(command: list[str]) -> str:
    assert command[:2] == ["python", "-m"], f"not a `python -m` command: {command}"
    return command[2]


def test_one_container_per_service_plus_the_router(compose):
    assert set(compose["services"]) == {"router", *SERVICES}


@pytest.mark.parametrize("service", SERVICES)
def test_service_command_is_a_runnable_module_that_joins_the_router(compose, service):
    command = compose["services"][service]["command"]
    module = python_module(command)
    assert module == f"services.{service}"
    assert importlib.util.find_spec(module) is not None
    assert importlib.util.find_spec(f"{module}.__main__") is not None, f"{module} cannot run with python -m"
    assert command[command.index("--mode") + 1] == "client"
    assert command[command.index("--connect") + 1] == "tcp/router:7447"


@pytest.mark.parametrize("service", SERVICES)
def test_healthcheck_is_a_gd2p_health_command_for_that_service(compose, service):
    test = compose["services"][service]["healthcheck"]["test"]
    assert test[:2] == ["CMD", "gd2p"]
    assert "cli.system" in cli.main.COMMAND_MODULES  # the module that provides `gd2p health`
    parser = argparse.ArgumentParser(prog="gd2p")
    cli.system.register(parser.add_subparsers())
    args = parser.parse_args(test[2:])
    assert args.func is cli.system.run_health
    assert args.service == service


def test_router_is_the_zenoh_image_of_the_installed_version(compose):
    router = compose["services"]["router"]
    assert router["image"] == f"eclipse/zenoh:{importlib.metadata.version('eclipse-zenoh')}"
    config_mount = next(v for v in router["volumes"] if v.split(":")[1] == router["command"][-1])
    config_file = (COMPOSE_FILE.parent / config_mount.split(":")[0]).resolve()
    config = zenoh.Config.from_file(str(config_file))
    assert config.get_json("mode") == '"router"'
    assert config.get_json("listen/endpoints") == '["tcp/0.0.0.0:7447"]'
    assert config.get_json("scouting/multicast/enabled") == "false"


def test_client_config_retries_until_the_router_is_up():
    config = zenoh.Config.from_file(str(ROOT / "deploy" / "zenoh" / "client.json5"))
    assert config.get_json("mode") == '"client"'
    assert config.get_json("connect/timeout_ms") == "-1"
    assert config.get_json("scouting/multicast/enabled") == "false"


def test_validator_is_scalable(compose):
    validator = compose["services"]["validator"]
    assert "container_name" not in validator  # a fixed name allows only one replica
    assert "ports" not in validator  # so does a fixed host port
    assert validator["deploy"]["replicas"] >= 1


def test_recorder_writes_to_a_persistent_volume(compose):
    recorder = compose["services"]["recorder"]
    record_dir = recorder["command"][recorder["command"].index("--record-dir") + 1]
    volume, mount = recorder["volumes"][0].split(":")[:2]
    assert mount == record_dir
    assert volume in compose["volumes"]


def test_dockerfile_installs_pinned_cpu_torch_first_and_runs_unprivileged():
    dockerfile = (ROOT / "Dockerfile").read_text()
    assert re.search(r"^FROM python:3\.11-slim\s*$", dockerfile, re.M)
    assert re.search(r'^ARG TORCH_INDEX_URL=""\s*$', dockerfile, re.M)
    torch_at = dockerfile.index("torch==2.13.0")
    project_at = dockerfile.index("pip install .")
    assert torch_at < project_at
    users = re.findall(r"^USER\s+(\S+)", dockerfile, re.M)
    assert users and users[-1] not in ("root", "0")


def test_compose_scale_command():
    assert scale_validators.compose_scale_command(3) == [
        "docker", "compose", "-f", str(COMPOSE_FILE), "up", "-d", "--no-recreate", "--scale", "validator=3",
    ]
    with pytest.raises(ValueError):
        scale_validators.compose_scale_command(-1)


def test_compose_scaling_without_docker_fails_clearly(monkeypatch, capsys):
    monkeypatch.setattr(scale_validators.shutil, "which", lambda name: None)
    assert scale_validators.main(["2", "--compose"]) == 1
    assert "docker" in capsys.readouterr().err
