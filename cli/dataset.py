"""`gd2p dataset build` and `gd2p dataset stats`: the data engine's pose store.

    gd2p dataset build --split train --hand allegro --per-object 32 --objects 240 --out data/allegro
    gd2p dataset build ... --connect tcp/10.0.0.5:7447      # use a running system's workers instead
    gd2p dataset stats data/allegro --plot joints.png --json

`build` runs generator -> validator (+ 10 Halton copies of each success) -> store for each object,
over the bus, and keeps every validated pose with its outcome: failures beside successes. Each round
of an object places it at its own random yaw in a resting pose (round 0 its default pose, later
rounds one drawn by stability; `--placement default` keeps version 1's yaw 0 in the default pose).
Without `--connect` it brings up its own router with `--generators` generator and `--workers`
validator processes and stops them at the end. Objects already in the store's manifest are skipped,
so an interrupted build (Ctrl-C, a kill, a crash) is resumed by running the same command again;
the result equals an uninterrupted build's.

`stats` reads the successes (what training sees) and, from a version-2 store, the failures too:
counts per object, family and resting pose, success rates per stage, family and yaw, yaw coverage.
"""
from __future__ import annotations

import argparse
import contextlib
import json
import os
import signal
import sys
import tempfile
from collections.abc import Iterator
from pathlib import Path

from cli.args import FlagError, non_negative_int, positive_int, validate_fields
from cli.dataset_stats import run_stats

BUILD_WORKER_TIMEOUT_S = 180.0
GENERATION_TIMEOUT_S = 3600.0  # one GenerationJob of a few hundred candidates on a busy core
VALIDATION_TIMEOUT_S = 1800.0
# GenerationJob fields each build round sends (the generator service's limits), by flag.
GENERATION_FLAGS = {"batch_size": "--per-object", "iterations": "--iterations", "hand": "--hand"}


def _half_the_cores() -> int:
    """Generators and validators each get half the cores by default: with failures kept and 1,000 generator
    iterations a round's generation and validation cost about the same CPU (measured: 3.9 s to generate 8
    candidates, ~5 s to push them and the Halton copies of their successes; CHANGELOG.md "Dataset v2")."""
    return max(1, (os.cpu_count() or 1) // 2)


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("dataset", help="build and inspect the validated push-pose dataset",
                                   description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    commands = parser.add_subparsers(dest="dataset_command", metavar="{build,stats}")
    commands.required = True
    _register_build(commands)
    _register_stats(commands)


def _register_build(commands: argparse._SubParsersAction) -> None:
    build = commands.add_parser(
        "build", help="generate, validate and store push poses for many objects",
        description="Generate push poses for each object (one GenerationJob a round, each round the object at a new "
                    "placement), validate them and 10 Halton copies of each success, and store every validated pose "
                    "with its outcome (failures too) in a version-2 pose store. Re-run the same command to resume.")
    build.add_argument("--split", default="train", choices=("train", "val", "test"), help="object split (default train)")
    build.add_argument("--allow-split", action="store_true",
                       help="allow a split other than train (evaluation data; never train on it)")
    build.add_argument("--hand", required=True, choices=("allegro", "leap"))
    build.add_argument("--per-object", type=positive_int, required=True, help="generator candidates per object (and round)")
    which = build.add_mutually_exclusive_group()
    which.add_argument("--objects", type=positive_int, default=None, help="the first N objects of the split (fixed order)")
    which.add_argument("--object-ids", nargs="+", default=None, help="explicit library ids")
    build.add_argument("--seed", type=int, default=0,
                       help="build seed; each object's seeds and placements derive from it, its id and the round")
    build.add_argument("--iterations", type=positive_int, default=None,
                       help="generator iterations (default: the generator's, 1500; 1000 measured the same validated "
                            "yield for 30%% less generator time)")
    build.add_argument("--min-poses", type=non_negative_int, default=0,
                       help="run further rounds while an object has fewer successful poses than this (default 0)")
    build.add_argument("--min-rounds", type=positive_int, default=1,
                       help="at least this many rounds per object, each a new placement (yaw, resting pose) (default 1)")
    build.add_argument("--max-rounds", type=positive_int, default=None,
                       help="at most this many rounds per object (default: --min-rounds)")
    build.add_argument("--placement", choices=("random", "default"), default="random",
                       help="random (default): each round a random yaw in D, round 0 in the default resting pose, later "
                            "rounds in one drawn by stability; default: yaw 0 in the default pose (the version-1 data)")
    build.add_argument("--workers", type=positive_int, default=_half_the_cores(),
                       help="validator processes to start (default: half the cores; ignored with --connect)")
    build.add_argument("--generators", type=positive_int, default=_half_the_cores(),
                       help="generator processes to start (default: half the cores; ignored with --connect)")
    build.add_argument("--connect", default=None, help="router of a running system (e.g. tcp/127.0.0.1:7447)")
    build.add_argument("--out", type=Path, required=True, help="store directory (created, or resumed)")
    build.add_argument("--no-progress", action="store_true", help="no progress bar")
    build.add_argument("--json", action="store_true", help="print the run's figures as JSON on stdout")
    build.set_defaults(func=run_build)


def _register_stats(commands: argparse._SubParsersAction) -> None:
    stats = commands.add_parser("stats", help="counts, success rates, yaw coverage and joint-angle histograms of a store")
    stats.add_argument("directory", type=Path)
    stats.add_argument("--plot", type=Path, default=None,
                       help="save the joint-angle histograms of the successes (16 subplots) as this PNG, and beside it "
                            "<name>-coverage.png: yaw coverage, poses per family, success rate per family and vs yaw")
    stats.add_argument("--json", action="store_true", help="print the statistics as JSON")
    stats.set_defaults(func=run_stats)


# ============================================================================= build
def run_build(args: argparse.Namespace) -> int:
    from shared.data.dataset_store import DatasetStore, StoreError
    from shared.data_engine import BuildError, BuildSettings, select_objects

    if args.max_rounds is None:  # resolved here, so the recorded command line names it
        args.max_rounds = args.min_rounds
    try:
        check_build_flags(args)
    except FlagError as exc:
        print(exc, file=sys.stderr)
        return 2
    try:
        settings = BuildSettings(hand=args.hand, split=args.split, per_object=args.per_object, seed=args.seed,
                                 iterations=args.iterations, min_poses=args.min_poses, min_rounds=args.min_rounds,
                                 max_rounds=args.max_rounds, placement=args.placement)
        objects = select_objects(args.split, args.objects, args.object_ids, allow_split=args.allow_split)
        store = DatasetStore.create_or_resume(args.out, settings.parameters())
    except (BuildError, StoreError, ValueError) as exc:
        print(f"gd2p dataset build: error: {exc}", file=sys.stderr)
        return 2
    previous = signal.signal(signal.SIGTERM, _raise_keyboard_interrupt)  # a kill stops the workers too
    try:
        return _build(args, settings, objects, store)
    except BuildError as exc:
        print(f"gd2p dataset build: error: {exc}", file=sys.stderr)
        return 1
    finally:
        signal.signal(signal.SIGTERM, previous)
        store.close()


def check_build_flags(args: argparse.Namespace) -> None:
    """FlagError (naming the flags) unless every job the build will send is within the services' limits."""
    from shared.contracts.messages import GenerationJob

    validate_fields(GenerationJob, {"batch_size": args.per_object, "iterations": args.iterations, "hand": args.hand},
                    GENERATION_FLAGS, command="dataset build")


def _raise_keyboard_interrupt(signum, frame) -> None:
    raise KeyboardInterrupt


def _build(args: argparse.Namespace, settings, objects: list[str], store) -> int:
    from shared.bus import Dispatcher
    from shared.data_engine import BuildError, DataEngine, run_record

    with _bus_session(args) as session, \
            Dispatcher(session, "generator", max_in_flight_per_worker=1, timeout_s=GENERATION_TIMEOUT_S) as generators, \
            Dispatcher(session, "validator", max_in_flight_per_worker=2, timeout_s=VALIDATION_TIMEOUT_S) as validators:
        try:
            n_generators = len(generators.wait_for_workers(1, timeout=BUILD_WORKER_TIMEOUT_S))
            n_validators = len(validators.wait_for_workers(1, timeout=BUILD_WORKER_TIMEOUT_S))
        except TimeoutError as exc:
            raise BuildError(str(exc)) from None
        stored = store.completed_objects()
        done_before = sum(oid in stored for oid in objects)
        with _progress_bar(len(objects), done_before, disabled=args.no_progress) as report:
            engine = DataEngine(generators, validators, store, settings,
                                generation_in_flight=n_generators + 1, progress=report)
            interrupted = False
            try:
                engine.run(objects)
            except KeyboardInterrupt:
                interrupted = True
            finally:
                record = run_record(build_command_line(args), engine.counters,
                                    {"generator": n_generators, "validator": n_validators}, engine.failures, settings)
                store.record_run({**record, "interrupted": interrupted, "objects_requested": len(objects)})
    summary = {**record, "interrupted": interrupted, "store": str(args.out), "content_hash": store.manifest["content_hash"],
               "totals": store.manifest["totals"]}
    if args.json:
        print(json.dumps(summary))
    else:
        _print_build_summary(summary)
    return 130 if interrupted else 0


def build_command_line(args: argparse.Namespace) -> list[str]:
    """The build as a command line with every option resolved (defaults included): what reproduces it."""
    command = ["gd2p", "dataset", "build", "--split", args.split, "--hand", args.hand,
               "--per-object", str(args.per_object), "--seed", str(args.seed)]
    if args.object_ids:
        command += ["--object-ids", *args.object_ids]
    elif args.objects is not None:
        command += ["--objects", str(args.objects)]
    for flag, value in (("--iterations", args.iterations), ("--min-poses", args.min_poses),
                        ("--min-rounds", args.min_rounds), ("--max-rounds", args.max_rounds),
                        ("--placement", args.placement), ("--connect", args.connect)):
        if value is not None:
            command += [flag, str(value)]
    if not args.connect:
        command += ["--generators", str(args.generators), "--workers", str(args.workers)]
    if args.allow_split:
        command.append("--allow-split")
    return command + ["--out", str(args.out)]


@contextlib.contextmanager
def _bus_session(args: argparse.Namespace) -> Iterator:
    """A session on the running system (`--connect`), or on a local system started for this build."""
    from shared.bus import BusConfig, BusError, open_session
    from shared.data_engine import BuildError

    if args.connect:
        try:
            session = open_session(BusConfig(mode="client", connect=[args.connect], connect_timeout_ms=10_000))
        except BusError as exc:
            raise BuildError(str(exc)) from None
        with session:
            yield session
        return
    from deploy.launcher import Launcher, LaunchError, free_loopback_endpoint

    scratch = Path(tempfile.mkdtemp(prefix="gd2p-dataset-build-"))
    launcher = Launcher(validators=args.workers, listen=free_loopback_endpoint(), log_dir=scratch / "logs",
                        record_dir=scratch / "recordings")
    # Only the two services a build uses (the sampler, planner, bridge and recorder would idle on the cores).
    launcher.initial_counts = {"generator": args.generators, "validator": args.workers}
    try:
        launcher.start()
        launcher.wait_ready(BUILD_WORKER_TIMEOUT_S)
        yield launcher.session
    except LaunchError as exc:
        raise BuildError(str(exc)) from None
    finally:
        launcher.stop()


@contextlib.contextmanager
def _progress_bar(total: int, done_before: int, disabled: bool) -> Iterator:
    from tqdm import tqdm

    bar = tqdm(total=total, initial=done_before, desc="objects", unit="obj", file=sys.stderr, disable=disabled,
               dynamic_ncols=True)

    def report(counters, finished_object: str | None) -> None:
        rates = counters.rates()
        if finished_object is not None:
            bar.update(1)
        bar.set_postfix({"cand/s": f"{rates['candidates_per_s']:.2f}", "push/s": f"{rates['validated_pushes_per_s']:.1f}",
                         "raw ok": f"{100 * rates['raw_success_rate']:.0f}%",
                         "aug ok": f"{100 * rates['augmented_success_rate']:.0f}%", "poses": counters.successes,
                         "failed": counters.validated_pushes - counters.successes})

    try:
        yield report
    finally:
        bar.close()


def _print_build_summary(s: dict) -> None:
    state = "interrupted (run the same command again to resume)" if s["interrupted"] else "done"
    print(f"{state}: {s['objects_done']} object(s) built this run, {s['objects_skipped']} already stored, "
          f"{s['objects_failed']} failed, in {s['wall_s']:.1f} s")
    print(f"  candidates {s['generated']} ({s['candidates_per_s']:.2f}/s), validated pushes "
          f"{s['validated_pushes']} ({s['validated_pushes_per_s']:.1f}/s)")
    print(f"  success: raw {100 * s['raw_success_rate']:.1f}%, augmented {100 * s['augmented_success_rate']:.1f}%")
    print(f"  {s['successes']} successful poses this run: {s['successes_per_compute_core_h']:.0f} per core-hour of worker "
          f"compute (generation {s['generation_s']:.0f} s, validation {s['validation_s']:.0f} s)")
    print(f"  store {s['store']}: {s['totals']['objects']} objects, {s['totals']['successes']} successful poses, "
          f"{s['totals']['failures']} failed, content hash {s['content_hash'][:16]}")
    for object_id, message in s["failures"].items():
        print(f"  failed {object_id}: {message}")
