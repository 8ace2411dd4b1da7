"""`gd2p critic data`, `gd2p critic train`: the success critic that orders the sampler's poses.

    gd2p critic data --split train --exclude-dataset datasets/allegro-v2 --objects 400 --out data/critic-allegro-train
    gd2p critic data --split val --objects 60 --out data/critic-allegro-val
    gd2p critic train --data data/critic-allegro-train --val data/critic-allegro-val --capture-fraction 0.5 \\
        --out shared/sampling/checkpoints/allegro_critic.pt
    gd2p critic data --split test --objects 60 --out data/critic-allegro-test   # for reporting only
    gd2p critic data --split test --family mug --objects 30 --out data/critic-allegro-test-mug   # unseen family
    gd2p critic eval --data data/critic-allegro-test --captures

`data` labels diffusion samples: per object, one push frame at a yaw drawn from the object's seed, K = 200
samples from the installed sampler checkpoint, `--per-object` of them pushed 20 cm by the validator's
floating hand (what the planner's prescreen does), outcomes recorded. Objects come in the data engine's
fixed order over the split; `--exclude-dataset STORE` leaves out the objects of the sampler's training
store and `--skip N` the first N of the rest (the critic should learn on samples as they look for objects
the sampler never saw). Val objects are only ever used to choose the checkpoint, test objects only to report
it (`critic eval`; `critic train` refuses test data). Resumable: a restarted command skips the objects it has.

`eval` reports a critic checkpoint (default: the installed one) on labelled data: ROC AUC, the success
rate of each object's six best-scored poses and of all its poses, and that of L_dir's six (the order
without a critic).

`train` fits the critic (BPS of the object + pose + where the hand meets the object -> P(success), position
error; `--no-contact` leaves the contact features out, as critics before them were) and keeps the step
with the best ROC AUC on `--val`; it prints that AUC and the success rate of each val object's six
best-scored poses against all of its poses. Under the default perception the planner gives the critic a
camera capture, not the mesh: `--capture-fraction F` trains F of each batch on captures of the records'
objects (3 simulated depth cameras, 2 captures per object, reconstructed the planner's way, the poses
moved into the reconstruction's frame; stored resumably in `<data>/captures`, about 0.5 s per capture
per core) and the val AUC then pools mesh and capture views. `eval --captures` reports mesh and
capture views apart. The sampler service picks up
`shared/sampling/checkpoints/<hand>_critic.pt` (or $GD2P_CRITIC_CHECKPOINT_<HAND>; "none" turns it off)
when it was trained for the installed sampler checkpoint.
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import shlex
import sys
import time
from pathlib import Path

from cli.args import non_negative_int, positive_int, probability


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("critic", help="build data for and train the success critic",
                                   description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    commands = parser.add_subparsers(dest="critic_command", required=True)
    data = commands.add_parser("data", help="label diffusion samples by floating-hand pushes (resumable)",
                               description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    data.add_argument("--split", choices=("train", "val", "test"), default="train",
                      help="objects to label (val: for choosing the checkpoint only; test: for reporting only)")
    data.add_argument("--objects", type=positive_int, required=True, help="how many objects of the split")
    data.add_argument("--skip", type=non_negative_int, default=0, help="leave out the split's first N objects")
    data.add_argument("--family", default=None,
                      help="only objects of this library family (e.g. mug: the family no model trains on)")
    data.add_argument("--exclude-dataset", type=Path, default=None,
                      help="leave out the objects this pose store holds (the sampler's training store: the critic "
                           "should learn on samples for objects the sampler never saw)")
    data.add_argument("--hand", choices=("allegro", "leap"), default="allegro")
    data.add_argument("--per-object", type=positive_int, default=32, help="samples pushed per object (default 32)")
    data.add_argument("--seed", type=non_negative_int, default=0)
    data.add_argument("--workers", type=positive_int, default=2, help="spawn processes (default 2: one per core)")
    data.add_argument("--out", type=Path, required=True)
    data.set_defaults(func=run_data)
    train = commands.add_parser("train", help="train the critic, keep the step with the best val ROC AUC",
                                description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    train.add_argument("--data", type=Path, required=True, nargs="+",
                       help="`gd2p critic data` output(s) of train objects (several: e.g. the same objects at "
                            "another --seed's yaw)")
    train.add_argument("--val", type=Path, required=True, help="`gd2p critic data` output of val objects")
    train.add_argument("--hand", choices=("allegro", "leap"), default="allegro")
    train.add_argument("--steps", type=positive_int, default=2000)
    train.add_argument("--seed", type=non_negative_int, default=0)
    train.add_argument("--no-contact", action="store_true",
                       help="without the contact features (where the hand meets the object): BPS and pose only")
    train.add_argument("--object-dim", type=positive_int, default=None,
                       help="width of the BPS embedding (default: CriticConfig's, 8)")
    train.add_argument("--hidden-dim", type=positive_int, default=None,
                       help="width of the hidden layers (default: CriticConfig's, 64)")
    train.add_argument("--layers", type=positive_int, default=None, help="hidden layers (default: CriticConfig's, 2)")
    train.add_argument("--capture-fraction", type=probability, default=0.0,
                       help="share of each batch on camera captures of the objects instead of their meshes "
                            "(default 0: meshes only; > 0 captures every data directory first)")
    train.add_argument("--workers", type=positive_int, default=2, help="capture processes (default 2: one per core)")
    train.add_argument("--out", type=Path, required=True, help="critic checkpoint to write")
    train.set_defaults(func=run_train)
    report = commands.add_parser("eval", help="ROC AUC and top-6 success of a critic on labelled data",
                                 description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    report.add_argument("--data", type=Path, required=True, help="`gd2p critic data` output")
    report.add_argument("--hand", choices=("allegro", "leap"), default="allegro")
    report.add_argument("--critic", type=Path, default=None, help="critic checkpoint (default: the installed one)")
    report.add_argument("--captures", action="store_true",
                        help="also score camera captures of the objects (built in <data>/captures if missing) and "
                             "report mesh and capture views apart")
    report.add_argument("--workers", type=positive_int, default=2, help="capture processes (default 2)")
    report.set_defaults(func=run_eval)


def run_data(args: argparse.Namespace) -> int:
    from evaluation.critic_data import build
    from shared.data.dataset_store import DatasetStore
    from shared.data_engine import select_objects
    from shared.world.objects.catalog import resolve_library_id

    ids = select_objects(args.split, allow_split=args.split != "train")
    if args.family is not None:
        ids = [i for i in ids if resolve_library_id(i).family == args.family]
    if args.exclude_dataset is not None:
        trained = DatasetStore.open(args.exclude_dataset).completed_objects()
        ids = [i for i in ids if i not in trained]
    ids = ids[args.skip:args.skip + args.objects]
    if not ids:
        family = f" of family {args.family!r}" if args.family else ""
        print(f"gd2p critic data: the {args.split} split has no objects{family} after the first {args.skip}",
              file=sys.stderr)
        return 2
    store = build(args.out, ids, hand=args.hand, per_object=args.per_object, seed=args.seed, workers=args.workers)
    pushes = [s for r in store.records.values() for s in r["success"]]
    print(json.dumps({"out": str(args.out), "objects": len(store.records), "pushes": len(pushes),
                      "success_rate": round(sum(pushes) / max(len(pushes), 1), 4)}))
    return 0


def run_train(args: argparse.Namespace) -> int:
    import torch

    from shared.sampling.checkpoint import checkpoint_id, default_checkpoint_path
    from shared.sampling.critic_train import (
        CriticError,
        CriticTraining,
        manifest_for,
        read_records,
        save_critic,
        train_critic,
    )
    from shared.sampling.sampling import PoseSampler
    from shared.world.objects import split_of

    torch.set_num_threads(1)
    started = time.time()
    sampler_path = default_checkpoint_path(args.hand)
    try:
        train_sources = [(directory, read_records(directory)) for directory in args.data]
        val_records = read_records(args.val)
        train_records = [r for _, records in train_sources for r in records]
    except CriticError as exc:
        print(f"gd2p critic train: {exc}", file=sys.stderr)
        return 2
    if any(split_of(r["object_id"]) == "test" for r in train_records + val_records):
        print("gd2p critic train: test objects are for reporting only (`gd2p critic eval`), never for training or "
              "choosing a checkpoint", file=sys.stderr)
        return 2
    with PoseSampler(sampler_path) as sampler:
        stale = {r["checkpoint_id"] for r in train_records + val_records} - {sampler.checkpoint_id}
        if stale:
            print(f"gd2p critic train: the data was sampled with checkpoint(s) {sorted(stale)}, the installed one is "
                  f"{sampler.checkpoint_id}: rebuild the data with it", file=sys.stderr)
            return 2
        captured = args.capture_fraction > 0
        train = _encode_dirs(train_sources, sampler, "train data", captured, args.workers)
        val = _encode_dirs([(args.val, val_records)], sampler, "val data", captured, args.workers)
    settings = CriticTraining(steps=args.steps, seed=args.seed, capture_fraction=args.capture_fraction)
    asked = {"object_dim": args.object_dim, "hidden_dim": args.hidden_dim, "num_layers": args.layers,
             **({"contact_dim": 0} if args.no_contact else {})}
    config = dataclasses.replace(settings.config, **{k: v for k, v in asked.items() if v is not None})
    settings = dataclasses.replace(settings, config=config)
    model, result = train_critic(train, val, settings, progress=lambda m: print(json.dumps(m), file=sys.stderr))
    command = "gd2p " + " ".join(shlex.quote(a) for a in sys.argv[1:])
    manifest = manifest_for([str(d) for d in args.data], args.val, settings, train, val, result, started, command)
    save_critic(model, args.out, args.hand, checkpoint_id(sampler_path), manifest)
    print(json.dumps({"out": str(args.out), "best_step": result["best_step"], "val": manifest["best_val"]}))
    return 0


def run_eval(args: argparse.Namespace) -> int:
    import numpy as np
    import torch

    from shared.planning import ranking
    from shared.robots.hands import load_hand
    from shared.sampling.checkpoint import default_checkpoint_path
    from shared.sampling.critic_train import (
        CriticError,
        default_critic_path,
        evaluate,
        load_critic,
        read_records,
        top_k_success,
    )
    from shared.sampling.sampling import PoseSampler

    torch.set_num_threads(1)
    path = args.critic or default_critic_path(args.hand)
    try:
        critic = load_critic(path) if path is not None else None
        records = read_records(args.data)
    except CriticError as exc:
        print(f"gd2p critic eval: {exc}", file=sys.stderr)
        return 2
    if critic is None:
        print("gd2p critic eval: no critic installed ($GD2P_CRITIC_CHECKPOINT_<HAND> is 'none')", file=sys.stderr)
        return 2
    with PoseSampler(default_checkpoint_path(args.hand)) as sampler:
        data = _encode_dirs([(args.data, records)], sampler, "data", args.captures, args.workers)
    metrics = evaluate(critic.model, data)
    # L_dir's order (no critic) on the same views; it reads the pose only, so mesh and capture views agree up to
    # the poses' shift into the reconstruction's frame.
    l_dir = ranking.direction_costs(load_hand(args.hand), data.poses.double().numpy())
    metrics["l_dir_top6_success"] = round(top_k_success(-l_dir, data.success.numpy() > 0.5, data.group.numpy()), 4)
    print(json.dumps({"critic": str(path), "data": str(args.data), **metrics}))
    return 0 if np.isfinite(metrics["roc_auc"]) else 1


def _encode_dirs(sources: list[tuple[Path, list]], sampler, what: str, captures: bool, workers: int):
    """The records of each (data directory, its records) encoded (`encode_records`; with `captures`, the
    directory's camera captures built or resumed first), with progress bars: BPS and contact features take
    ~3 s per 1,000 poses."""
    from tqdm import tqdm

    from shared.sampling.critic_train import CriticData, encode_records, record_captures

    parts = []
    for directory, records in sources:
        frame_captures = record_captures(directory, records, workers=workers) if captures else None
        with tqdm(total=len(records), desc=f"encoding {what}", unit="object", file=sys.stderr) as bar:
            parts.append(encode_records(records, sampler, progress=bar.update, captures=frame_captures))
    return CriticData.concat(parts)
