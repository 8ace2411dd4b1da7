"""`gd2p` command line: one entry point, one sub-command module per concern.

Each module listed in COMMAND_MODULES exposes `register(subparsers)`, which adds its
sub-commands and sets `func` (called with the parsed args, returns an exit code).
Modules are imported lazily by name so `gd2p --help` stays fast and a heavy import
(torch, pybullet) is paid only by the command that needs it.
"""
from __future__ import annotations

import argparse
import importlib
import os
import sys

COMMAND_MODULES: list[str] = [
    "cli.system",  # up, status, demo, health (platform)
    "cli.recording",  # replay
    "cli.view",  # view (the live view of a running system, in the browser)
    "cli.hands",  # hands info
    "cli.objects",  # objects list
    "cli.validate",  # validate (push validation in PyBullet)
    "cli.show",  # show (picture of an object with hand poses)
    "cli.sampler",  # train, sample, sampler-nn (pose diffusion model, nearest-neighbour index)
    "cli.generate",  # generate (energy-based push-pose synthesis)
    "cli.bridge",  # bridge selftest, bridge estop (robot bridge hardware adapters)
    "cli.dataset",  # dataset build, dataset stats (data engine pose store)
    "cli.push",  # push (push / pull requests to the running system)
    "cli.confirm",  # confirm (release a plan the robot bridge holds: gd2p up --confirm)
    "cli.eval",  # eval (the paper's experiments in simulation), compare (two runs, trial by trial)
    "cli.capture",  # capture (simulated depth-camera capture of an object to a point cloud)
    "cli.critic",  # critic data, critic train (the success critic that orders sampled poses)
]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="gd2p",
        description="GD2P dexterous pushing and pulling: data engine, learning and execution over Zenoh.",
    )
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND")
    subparsers.required = True
    for name in COMMAND_MODULES:
        importlib.import_module(name).register(subparsers)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        code = args.func(args)
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:
        # `gd2p ... --json | head`: the reader went away; exit quietly like other Unix tools.
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 141
    return int(code or 0)


if __name__ == "__main__":
    sys.exit(main())
