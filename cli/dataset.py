"""`gd2p dataset build` and `gd2p dataset stats`: the data engine's pose store.

    gd2p dataset build --split train --hand allegro --per-object 32 --objects 240 --out data/allegro
    gd2p dataset build ... --connect tcp/10.0.0.5:7447      # use a running system's workers instead
    gd2p dataset stats data/allegro --plot joints.png --json

`build` runs generator -> validator (+ 10 Halton copies of each success) -> store for each object,
over the bus. Without `--connect` it brings up its own router with `--generators` generator and
`--workers` validator processes and stops them at the end. Objects already in the store's manifest
are skipped, so an interrupted build (Ctrl-C, a kill, a crash) is resumed by running the same
command again; the result equals an uninterrupted build's.
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

BUILD_WORKER_TIMEOUT_S = 180.0
GENERATION_TIMEOUT_S = 3600.0  # one GenerationJob of a few hundred candidates on a busy core
VALIDATION_TIMEOUT_S = 1800.0
# GenerationJob fields each build round sends (the generator service's limits), by flag.
GENERATION_FLAGS = {"batch_size": "--per-object", "iterations": "--iterations", "hand": "--hand"}


def _default_generators() -> int:
    """Generation dominates the build (measured: ~10x the validation time per object), so give it every core."""
    return max(1, os.cpu_count() or 1)


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("dataset", help="build and inspect the validated push-pose dataset",
                                   description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    commands = parser.add_subparsers(dest="dataset_command", metavar="{build,stats}")
    commands.required = True
    _register_build(commands)
    _register_stats(commands)


def _register_build(commands: argparse._SubParsersAction) -> None:
    build = commands.add_parser("build", help="generate, validate and store push poses for many objects")
    build.add_argument("--split", default="train", choices=("train", "val", "test"), help="object split (default train)")
    build.add_argument("--allow-split", action="store_true",
                       help="allow a split other than train (evaluation data; never train on it)")
    build.add_argument("--hand", required=True, choices=("allegro", "leap"))
    build.add_argument("--per-object", type=positive_int, required=True, help="generator candidates per object (and round)")
    which = build.add_mutually_exclusive_group()
    which.add_argument("--objects", type=positive_int, default=None, help="the first N objects of the split (fixed order)")
    which.add_argument("--object-ids", nargs="+", default=None, help="explicit library ids")
    build.add_argument("--seed", type=int, default=0, help="build seed; each object's seeds derive from it and its id")
    build.add_argument("--iterations", type=positive_int, default=None, help="generator iterations (default: the generator's)")
    build.add_argument("--min-poses", type=non_negative_int, default=0,
                       help="run further rounds while an object has fewer stored poses than this (default 0)")
    build.add_argument("--max-rounds", type=positive_int, default=1, help="at most this many rounds per object (default 1)")
    build.add_argument("--workers", type=positive_int, default=1, help="validator processes to start (default 1; ignored with --connect)")
    build.add_argument("--generators", type=positive_int, default=_default_generators(),
                       help="generator processes to start (default: one per core; ignored with --connect)")
    build.add_argument("--connect", default=None, help="router of a running system (e.g. tcp/127.0.0.1:7447)")
    build.add_argument("--out", type=Path, required=True, help="store directory (created, or resumed)")
    build.add_argument("--no-progress", action="store_true", help="no progress bar")
    build.add_argument("--json", action="store_true", help="print the run's figures as JSON on stdout")
    build.set_defaults(func=run_build)


def _register_stats(commands: argparse._SubParsersAction) -> None:
    stats = commands.add_parser("stats", help="counts, success rates and joint-angle histograms of a store")
    stats.add_argument("directory", type=Path)
    stats.add_argument("--plot", type=Path, default=None, help="save the joint-angle histograms (16 subplots) here")
    stats.add_argument("--json", action="store_true", help="print the statistics as JSON")
    stats.set_defaults(func=run_stats)


# ============================================================================= build
def run_build(args: argparse.Namespace) -> int:
    from services.validator.data_engine import BuildError, BuildSettings, select_objects
    from shared.data.dataset_store import DatasetStore, StoreError

    try:
        check_build_flags(args)
    except FlagError as exc:
        print(exc, file=sys.stderr)
        return 2
    try:
        settings = BuildSettings(hand=args.hand, split=args.split, per_object=args.per_object, seed=args.seed,
                                 iterations=args.iterations, min_poses=args.min_poses, max_rounds=args.max_rounds)
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
    from services.validator.data_engine import BuildError, DataEngine, run_record
    from shared.bus import Dispatcher

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
                record = run_record(build_command_line(args), engine.counters, {"generator": n_generators, "validator": n_validators},
                                    engine.failures)
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
                        ("--max-rounds", args.max_rounds), ("--connect", args.connect)):
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
    from services.validator.data_engine import BuildError
    from shared.bus import BusConfig, BusError, open_session

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
                         "aug ok": f"{100 * rates['augmented_success_rate']:.0f}%", "poses": counters.stored_rows})

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
    print(f"  store {s['store']}: {s['totals']['objects']} objects, {s['totals']['rows']} poses, "
          f"content hash {s['content_hash'][:16]}")
    for object_id, message in s["failures"].items():
        print(f"  failed {object_id}: {message}")


# ============================================================================= stats
def run_stats(args: argparse.Namespace) -> int:
    from shared.data.dataset_store import DatasetStore, StoreError

    try:
        store = DatasetStore.open(args.directory)
        store.verify()
        stats = store_statistics(store)
        if args.plot is not None:
            plot_joint_histograms(store, args.plot)
            stats["plot"] = str(args.plot)
    except StoreError as exc:
        print(f"gd2p dataset stats: error: {exc}", file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps(stats))
    else:
        _print_stats(stats)
    return 0


def store_statistics(store) -> dict:
    """Counts per object, hand and stage; success rates per stage; how many objects reach 1/10/20 poses."""
    table = store.rows(columns=["object_id", "hand", "stage"])
    rows = table.to_pylist() if table.num_columns else []
    per_object: dict[str, dict] = {}
    for object_id, status in store.completed_objects().items():
        per_object[object_id] = {**status.counts, "poses": status.rows, "raw": 0, "augmented": 0}
    by_hand: dict[str, int] = {}
    by_stage = {"raw": 0, "augmented": 0}
    for row in rows:
        by_hand[row["hand"]] = by_hand.get(row["hand"], 0) + 1
        by_stage[row["stage"]] += 1
        per_object[row["object_id"]][row["stage"]] += 1
    totals = store.manifest["totals"]
    poses_per_object = [entry["poses"] for entry in per_object.values()]
    return {
        "directory": str(store.directory),
        "hand": store.manifest["hand"],
        "split": store.manifest["split"],
        "objects": len(per_object),
        "poses": len(rows),
        "by_hand": by_hand,
        "by_stage": by_stage,
        "stages": {k: totals[k] for k in ("generated", "raw_successes", "augmented_validated", "augmented_successes")},
        "success_rates": {
            "raw": totals["raw_successes"] / totals["generated"] if totals["generated"] else 0.0,
            "augmented": totals["augmented_successes"] / totals["augmented_validated"] if totals["augmented_validated"] else 0.0,
        },
        "objects_with_at_least": {str(k): sum(p >= k for p in poses_per_object) for k in (1, 10, 20)},
        "build_wall_s": round(sum(run.get("wall_s", 0.0) for run in store.manifest["runs"]), 1),
        "runs": len(store.manifest["runs"]),
        "content_hash": store.content_hash(),
        "per_object": per_object,
    }


def _print_stats(s: dict) -> None:
    print(f"{s['directory']}: hand {s['hand']}, split {s['split']}, {s['objects']} objects, {s['poses']} poses "
          f"({s['by_stage']['raw']} raw, {s['by_stage']['augmented']} augmented)")
    st = s["stages"]
    print(f"  generated {st['generated']} -> raw successes {st['raw_successes']} ({100 * s['success_rates']['raw']:.1f}%); "
          f"augmented {st['augmented_validated']} -> successes {st['augmented_successes']} "
          f"({100 * s['success_rates']['augmented']:.1f}%)")
    print(f"  built in {s['runs']} run(s), {s['build_wall_s']:.0f} s of wall time")
    print("  objects with >= 1 / 10 / 20 poses: " + " / ".join(str(v) for v in s["objects_with_at_least"].values()))
    print(f"  {'OBJECT':<18} {'GENERATED':>9} {'RAW OK':>7} {'AUG':>6} {'AUG OK':>7} {'POSES':>6}")
    for object_id, c in s["per_object"].items():
        print(f"  {object_id:<18} {c['generated']:>9} {c['raw_successes']:>7} {c['augmented_validated']:>6} "
              f"{c['augmented_successes']:>7} {c['poses']:>6}")


def plot_joint_histograms(store, path: Path) -> None:
    """The paper's appendix figure: one histogram per joint, joint limits as green dashed lines."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from shared.robots.hands import load_hand

    table = store.rows(columns=["pose"])
    poses = (np.asarray(table.column("pose").combine_chunks().flatten().to_numpy(zero_copy_only=False),
                        dtype=np.float64).reshape(-1, 25) if table.num_columns else np.zeros((0, 25)))
    hand = load_hand(store.hand)
    lower, upper = hand.joint_lower.numpy(), hand.joint_upper.numpy()
    joints = poses[:, 9:]
    fig, axes = plt.subplots(4, 4, figsize=(14, 11))
    for j, ax in enumerate(axes.flat):
        ax.hist(joints[:, j], bins=40, range=(lower[j] - 0.1, upper[j] + 0.1), color="tab:blue")
        for limit in (lower[j], upper[j]):
            ax.axvline(limit, color="green", linestyle="--", linewidth=1.2)
        ax.text(0.97, 0.93, str(j), transform=ax.transAxes, ha="right", va="top", fontsize=11, weight="bold")
        ax.set_xlabel("rad", fontsize=8)
        ax.tick_params(labelsize=7)
    fig.suptitle(f"Joint angles of {len(poses)} validated {store.hand} poses ({store.directory.name})")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
