"""The container deployment, checked without a Docker engine: what compose would run must exist.

Parses deploy/docker-compose.yml and the Dockerfile and checks them against the package: every
service command is an importable `python -m` module, every healthcheck is a real `gd2p` command,
the router image matches the installed Zenoh, validators scale, recordings persist. The secure
override (deploy/secure/docker-compose.secure.yml) gives each container only its own identity's key.
"""
from __future__ import annotations

import argparse
import ast
import importlib.metadata
import importlib.util
import json
import re
from pathlib import Path, PurePosixPath

import pytest
import yaml
import zenoh

import cli.main
import cli.system
from deploy import scale_validators
from shared.bus.config import ENV_CONFIG

ROOT = Path(__file__).resolve().parents[1]
COMPOSE_FILE = ROOT / "deploy" / "docker-compose.yml"
SECURE_OVERRIDE = ROOT / "deploy" / "secure" / "docker-compose.secure.yml"
SECURE_SOURCE = "${GD2P_SECURE_DIR:-./secure/generated}/"
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


def test_the_image_holds_every_project_package_a_service_imports():
    copied = set(re.findall(r"^COPY\s+(\w+)\s+\./\1\s*$", (ROOT / "Dockerfile").read_text(), re.M))
    project = {p.name for p in ROOT.iterdir() if (p / "__init__.py").is_file()}
    imported = set()
    for path in (ROOT / "services").rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                imported.update(alias.name.split(".")[0] for alias in node.names)
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                imported.add(node.module.split(".")[0])
    assert {"shared", "services", "visualisation"} <= imported & project <= copied


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


def secure_mounts(service: dict) -> dict[str, str]:
    """{file name under /secure: source} of a secure-override service's read-only bind mounts."""
    mounts = {}
    for volume in service["volumes"]:
        source, target, mode = re.fullmatch(r"(.+?):(/[^:]*)(?::(\w+))?", volume).groups()
        if not (target.startswith("/secure") or source.startswith(SECURE_SOURCE.split(":")[0])):
            continue
        assert mode == "ro", f"{volume} is not read-only"
        assert source == SECURE_SOURCE + PurePosixPath(target).name, f"{volume} mounts another file than it names"
        assert PurePosixPath(target).parent == PurePosixPath("/secure"), volume
        mounts[PurePosixPath(target).name] = source
    return mounts


def test_each_secure_container_mounts_only_its_own_identity(tmp_path):
    """Only ca.pem + that identity's certificate, key and config; the router only its own; never ca.key.
    And the configs `python -m deploy.secure --mounted-at /secure` writes read only mounted files."""
    from deploy.secure import prepare
    from deploy.secure import profile as acl

    override = yaml.safe_load(SECURE_OVERRIDE.read_text())
    assert set(override["services"]) == {"router", *SERVICES}
    generated = prepare(tmp_path / "generated", ["tls/0.0.0.0:7447"], connect=["tls/router:7447"],
                        mounted_at="/secure")
    written = {p.name for p in generated.directory.iterdir()}
    assert "ca.key" not in written
    for name, service in override["services"].items():
        mounts = secure_mounts(service)
        config_name = "router.json5" if name == "router" else f"client-{name}.json5"
        assert set(mounts) == {"ca.pem", f"{name}.pem", f"{name}.key", config_name}, name
        assert set(mounts) <= written, f"{name} mounts files `python -m deploy.secure` does not write"
        if name == "router":
            assert service["command"] == ["-c", f"/secure/{config_name}"]
            side = "listen"
        else:
            command = service["command"]
            assert command[command.index("--zenoh-config") + 1] == f"/secure/{config_name}"
            assert service["environment"][ENV_CONFIG] == f"/secure/{config_name}"  # the healthcheck's identity
            # ... which may health-query its own workers (`gd2p health --service NAME --this-host`)
            assert acl.allowed(name, "ingress", "query", f"gd2p/{name}/worker/*/job")
            assert acl.allowed(name, "egress", "reply", f"gd2p/{name}/worker/{name}-1/job")
            side = "connect"
        config = zenoh.Config.from_file(str(generated.directory / config_name))
        read = {json.loads(config.get_json(f"transport/link/tls/{field}"))
                for field in ("root_ca_certificate", f"{side}_certificate", f"{side}_private_key")}
        assert read == {f"/secure/{name}.pem", f"/secure/{name}.key", "/secure/ca.pem"}, name
