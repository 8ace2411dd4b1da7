"""`gd2p eval EXPERIMENT [--quick] --out results/`: reproduce the paper's experiments in simulation.

    gd2p eval methods --out results/          # GD2P vs baselines, the 14 development objects x 3 directions x 5 trials, 3 cameras
    gd2p eval methods --cameras 0             # ... the system told the object's mesh (and a pose off by the world's error)
    gd2p eval methods --world exact           # ... executed in the planner's own world (for comparison)
    gd2p eval methods --world exact --tag v2  # the `exact` run beside `methods-real-v2` (same tag, same models)
    gd2p eval methods --methods gd2p,nearest  # only these methods (a run can be extended with more later)
    gd2p eval leap --out results/             # the same protocol with the LEAP hand on the xArm7
    gd2p eval closed-loop --out results/      # open loop vs corrective pushes vs pushes watched and stopped
    gd2p eval suite --out results/            # every task (paper, pose, wall, corner, clutter, tall, ...), default + baselines
    gd2p eval suite --tasks round,pose --world mujoco  # some tasks, executed in MuJoCo
    gd2p eval closed-loop --tasks wall --methods gd2p-closed-critic-p24,fixed-corrected  # one task's run alone
    gd2p eval multistep --out results/        # pushing to a goal around an obstacle (RRT* + pushes)
    gd2p eval data-size --world exact --out results/  # test objects covered vs training-data fraction
    gd2p eval data-size --dataset datasets/allegro-v2 --yaw random --train-steps 20000 --lr 1e-3 --seeds 0 --tag v2  # v2
    gd2p eval sampler-quality --out results/  # diffusion vs nearest neighbour on the whole test split, 3 cameras
    gd2p eval sampler-quality --world exact --split val --yaw random --objects 36 --checkpoint CKPT --tag NAME  # choose
    gd2p eval sampler-diagnosis --out results/  # training objects: samples vs stored poses, shuffled BPS, BPS paths
    gd2p eval all --quick --out /tmp/r        # a small slice of every experiment, a few minutes each
    gd2p eval methods --split final           # the final split: once per release, settings frozen on val (see below)

Splits (`--split`): `dev` (default) is the development split: the 14 objects every change has been measured
on (the object library's `test` split; `--split test` still works, as an alias that says so), so its figures
are development figures. `val` is for choosing settings. `final` is the final split: 72 objects drawn for it
(5 fresh draws of each procedural family and 12 of `round`, a family nothing trains on), frozen by content
hash, with placements and world draws of their own; methods / leap / closed-loop / suite only, from a clean tree,
every run logged in results/final/LOG.md, good or bad. Nothing else can load its objects.

World (`--world`, every experiment but sampler-diagnosis): `real` (default) executes every plan in a world drawn
per trial that the planner does not know - friction, mass, centre of mass, the arm's controller, and
the object off its told pose (shared/world/sim/world.py documents each range), and the system does not get the
object's mesh: it sees the object through 3 simulated depth cameras (`--cameras`, 0 for the mesh), each off its
calibration by a few mm and tenths of a degree; `mujoco` draws the same and executes in MuJoCo, with MuJoCo's own
contact model and its own draws of the hand (finger stiffness, damping, per-finger friction), while the planner
still predicts in PyBullet; `exact` executes in the planner's own world, told the mesh. While a plan runs the robot
sees the object only through its cameras (`--tracking image`, the default): rendered depth frames with the arm and
hand in view, the model registered in them, or "lost"; each trial records the tracker's error against the truth. Results go to `<out>/<experiment>-<world>[-cameraN]/`
(`...-<tag>/` with `--tag`); a `real` report of methods / leap / closed-loop gives the `exact` rates of the run
of the same name and models in `<out>` beside its own. sampler-quality and data-size push their poses by the
floating hand in a world drawn per object (the same for every pose source) and the sources sample for the
cameras' reconstruction; their exact runs keep their first names (`<out>/sampler-quality[-val]...`,
`<out>/data-size...`), a real run is `<out>/sampler-quality-real-camera3...` with the exact run of the same
name beside it, and `data-size-real-camera3...` measures its models in both worlds.

Each experiment writes `<out>/<experiment>/report.md`, `summary.json`, its records and plots, and
refreshes the index `<out>/README.md` (one row per run; for results/, docs/results.md too). Every
finished trial is recorded at once: re-running the same command resumes where a killed run stopped;
different settings into the same directory are refused.
Runs in this process and `--workers` spawn processes (no running system needed).
"""
from __future__ import annotations

import argparse
import importlib
import re
import signal
import sys
from pathlib import Path

from cli.args import positive_float
from evaluation.tasks import TASKS

EXPERIMENTS: dict[str, str] = {  # name -> "module:function(out, quick, workers) -> report path"
    "methods": "evaluation.methods:run_methods",
    "leap": "evaluation.methods:run_leap",
    "closed-loop": "evaluation.methods:run_closed_loop",
    "suite": "evaluation.suite:run_suite",
    "multistep": "evaluation.multistep:run",
    "data-size": "evaluation.data_size:run",
    "sampler-quality": "evaluation.sampler_quality:run",
    "sampler-diagnosis": "evaluation.sampler_diagnosis:run",
}
TRIAL_EXPERIMENTS = ("methods", "leap", "closed-loop", "suite")
WORLD_EXPERIMENTS = ("methods", "leap", "closed-loop", "suite", "multistep")  # these also take --cameras and --tag
COVERAGE_EXPERIMENTS = ("sampler-quality", "data-size")  # --world and --cameras too: where the poses are pushed
# `dev`: the development split (the library's `test` split, what `test` named before the final split existed; `test` stays an
# alias that says so); `final`: the final split (evaluation/final_run.py).
SPLIT_CHOICES = ("dev", "test", "val", "unseen", "final")


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser("eval", help="reproduce the paper's experiments in simulation (resumable)",
                                   description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("experiment", choices=[*EXPERIMENTS, "all"], help="which experiment ('all': each in turn)")
    parser.add_argument("--out", type=Path, default=Path("results"), help="results directory (default results/)")
    parser.add_argument("--quick", action="store_true", help="a small slice of the protocol (minutes, for CI)")
    parser.add_argument("--workers", type=int, default=2, help="worker processes (default 2: one per core here)")
    parser.add_argument("--view", nargs="?", type=int, const=8090, default=None, metavar="PORT",
                        help="watch the trials in the live view on PORT (default 8090): one trial at a time, in this "
                             "process (--workers 1)")
    parser.add_argument("--trials", type=int, default=None,
                        help="methods / leap / closed-loop: trials per object and direction (default: the paper's 5); a run can "
                             "later be extended to more trials in the same --out")
    parser.add_argument("--world", choices=("real", "mujoco", "exact"), default="real",
                        help="the execution world, every experiment but sampler-diagnosis (default real; mujoco: executed "
                             "in MuJoCo with its own drawn physics while the planner predicts in PyBullet; see above)")
    parser.add_argument("--tracking", choices=("image", "truth"), default="image",
                        help="how the robot sees the object while it pushes (methods, leap, closed-loop): image (default) "
                             "registers it in depth frames rendered with the arm and hand in view, or reports it lost; "
                             "truth is the true pose with 2 mm / 1 degree noise (the tracker before images; "
                             "<out>/<experiment>-<world>[-cameraN]-truthtrack/)")
    parser.add_argument("--cameras", type=int, choices=(0, 1, 2, 3), default=None,
                        help="every experiment but sampler-diagnosis: 1-3: the system sees the object only through that many "
                             "simulated depth cameras and plans (or samples) for its own reconstruction "
                             "(<out>/<experiment>-<world>-cameraN/, multistep-<world>[-closed]-cameraN/); 0 tells it the "
                             "object's mesh and a pose off by the world's pose error (<out>/<experiment>-<world>/). "
                             "Default: 3 under `real`, 0 under `exact`")
    parser.add_argument("--split", choices=SPLIT_CHOICES, default="dev",
                        help="methods / leap / closed-loop: the 14 development objects (dev, the default; results in "
                             "<out>/<experiment>-<world>[-cameraN]/ as before; `test` is an alias), 14 val objects (for tuning "
                             "settings, <out>/<experiment>-<world>-val/), 6 development objects of the mug family that no "
                             "model trains on (<out>/<experiment>-<world>-unseen/) or the final split (final: once per "
                             "release, from a clean tree, logged in results/final/LOG.md; <out>/<experiment>-<world>"
                             "[-cameraN]-final/); multistep: dev (default) or 3 val objects of the development objects' "
                             "footprints (<out>/multistep-<world>[-closed][-cameraN]-val/); sampler-quality: the whole "
                             "development (the library's test split) or val split")
    parser.add_argument("--methods", type=_method_list, default=None,
                        help="methods / leap / closed-loop: comma-separated methods to run (methods' default: every "
                             "method but the tuning candidates; closed-loop's: gd2p, gd2p-corrected, gd2p-closed, "
                             "gd2p-closed-critic-p24; leap's: gd2p): gd2p, gd2p-unranked, gd2p-random, gd2p-corrected, "
                             "gd2p-closed, gd2p-closed-critic-p24, gd2p-closed-fast, nearest, nearest-ranked, "
                             "nearest-closed-critic, fixed, fingertip-corrected, nearest-corrected, fixed-corrected, grasp, grasp-ranked; tuning "
                             "candidates (val): gd2p-robust, gd2p-closed-tight, gd2p-closed-3cm, gd2p-closed-loose, "
                             "gd2p-closed-looser, gd2p-closed-b24x6, gd2p-closed-b12x4, gd2p-closed-b12x4-ddim, "
                             "gd2p-closed-critic-guided, gd2p-closed-critic-p8, gd2p-closed-critic-p0, gd2p-closed-critic-p0x4, "
                             "gd2p-closed-critic-p0-ddim, gd2p-a30, gd2p-a10, gd2p-closed-critic-slide, fixed-corrected-slide, gd2p-closed-critic-noslide, gd2p-closed-critic-rrt; "
                             "sampler-quality: ddpm100, ddim10, nn (default), "
                             "nn-fill (the nearest frames up to K = 200 poses), ddpm100-critic, nn-fill-critic (in the success "
                             "critic's order: $GD2P_CRITIC_CHECKPOINT_<HAND>, else the shipped critic), and with --critic-guidance "
                             "ddpm100-guided, ddpm100-guided-critic, nn-fill-climbed-critic (steered up that critic's gradient)")
    parser.add_argument("--checkpoint", type=Path, default=None,
                        help="sampler-quality: the diffusion checkpoint to measure (default the shipped Allegro one; its poses "
                             "are pushed with the hand it was trained for); name its results with --tag. Refused elsewhere: methods / "
                             "leap / closed-loop / multistep take their models from $GD2P_SAMPLER_CHECKPOINT_<HAND>")
    parser.add_argument("--nn-index", type=Path, default=None,
                        help="sampler-quality: the nearest-neighbour index to measure (default the shipped one); elsewhere "
                             "refused: $GD2P_SAMPLER_NN_INDEX_<HAND> names another index")
    parser.add_argument("--yaw", choices=("zero", "random"), default="zero",
                        help="sampler-quality / data-size: each object at yaw 0 in the push frame (default, the paper's "
                             "protocol) or turned by a seeded random yaw (<out>/sampler-quality[-val]-random-yaw/, "
                             "<out>/data-size-random-yaw/; data-size then takes its objects one shape family after another)")
    parser.add_argument("--noise-scale", type=float, default=None,
                        help="sampler-quality: the diffusion sampling temperature in (0, 1] (initial and DDPM step noise "
                             "multiplied by it; default $GD2P_SAMPLER_NOISE_SCALE, else 1, the plain reverse process); name its results with --tag")
    parser.add_argument("--critic-guidance", type=float, default=None, metavar="SCALE",
                        help="sampler-quality: steer the methods ddpm100-guided, ddpm100-guided-critic and "
                             "nn-fill-climbed-critic up the success critic's log P(success): each guided step moves a pose by "
                             "SCALE x the gradient in normalised pose units (at most 0.2); name its results with --tag")
    parser.add_argument("--guided-steps", type=int, default=None, metavar="N",
                        help="sampler-quality, with --critic-guidance: guide the last N of the 100 denoising steps (default "
                             "10); retrieval's poses climb the gradient N times")
    parser.add_argument("--objects", type=int, default=None,
                        help="sampler-quality: only this many objects of the split, one shape family after another "
                             "(default: all of them); data-size: this many test objects (default 40)")
    parser.add_argument("--tag", default=None,
                        help="suffix of the results directory: sampler-quality / data-size: a non-shipped "
                             "--checkpoint, another --dataset; methods / leap / closed-loop / multistep: a run with other "
                             "models (<out>/<experiment>-<world>[-closed][-cameraN][-split]-TAG/)")
    parser.add_argument("--dataset", type=Path, default=None,
                        help="data-size: the training store whose objects are subsampled (default data/allegro-train)")
    parser.add_argument("--train-steps", type=int, default=None,
                        help="data-size: optimiser steps per model (default 2000, the first shipped checkpoint's)")
    parser.add_argument("--lr", type=positive_float, default=None,
                        help="data-size: learning rate of every model (default 1e-4, the paper's)")
    parser.add_argument("--seeds", type=_seed_list, default=None,
                        help="data-size: comma-separated training seeds, one model per fraction and seed (default 0,1,2)")
    parser.add_argument("--tasks", type=_task_list, default=None,
                        help="suite: comma-separated tasks (default all: " + ", ".join(TASKS) + "); each is a "
                             "closed-loop run of its own, <out>/closed-loop-<world>...-<task>/ (the paper's task: "
                             "the closed-loop run itself). closed-loop: one task, its run alone (default paper)")
    parser.add_argument("--closed-loop", action="store_true",
                        help="multistep: watch every push and stop it when the object strays from its predicted "
                             "path (PlannerOptions.closed_loop), into <out>/multistep-<world>-closed/")
    parser.set_defaults(func=run)
    register_compare(subparsers)


def _method_list(text: str) -> tuple[str, ...]:
    from evaluation.push_protocol import METHODS
    from evaluation.sampler_quality import METHOD_KEYS

    names = tuple(n.strip() for n in text.split(",") if n.strip())
    unknown = [n for n in names if n not in METHODS and n not in METHOD_KEYS]
    if not names or unknown:
        raise argparse.ArgumentTypeError(f"unknown method(s) {', '.join(unknown) or '(none given)'}; "
                                         f"known: {', '.join(METHODS)}; sampler-quality: {', '.join(METHOD_KEYS)}")
    return names


def _task_list(text: str) -> tuple[str, ...]:
    tasks = tuple(t.strip() for t in text.split(",") if t.strip())
    unknown = [t for t in tasks if t not in TASKS]
    if not tasks or unknown:
        raise argparse.ArgumentTypeError(f"unknown task(s) {', '.join(unknown) or '(none given)'}; known: {', '.join(TASKS)}")
    return tasks


def _seed_list(text: str) -> tuple[int, ...]:
    try:
        seeds = tuple(int(v) for v in text.split(",") if v.strip())
    except ValueError:
        raise argparse.ArgumentTypeError(f"seeds are comma-separated integers, got {text!r}") from None
    if not seeds or len(set(seeds)) != len(seeds):
        raise argparse.ArgumentTypeError(f"give one or more distinct seeds, got {text!r}")
    return seeds


def _data_size_options(args: argparse.Namespace) -> dict:
    options: dict = {"yaw": args.yaw, "tag": args.tag, "objects": args.objects, "train_steps": args.train_steps,
                     "lr": args.lr, "seeds": args.seeds}
    if args.dataset is not None:
        options["dataset_dir"] = args.dataset
    return options


def _methods_refusal(methods: tuple[str, ...] | None, experiments: list[str]) -> str | None:
    """Why `--methods` does not fit the experiments run, or None."""
    from evaluation.push_protocol import METHODS
    from evaluation.sampler_quality import METHOD_KEYS

    if methods is None:
        return None
    for name in experiments:
        known = METHOD_KEYS if name == "sampler-quality" else METHODS if name in TRIAL_EXPERIMENTS else None
        wrong = [m for m in methods if known is not None and m not in known]
        if wrong:
            return f"{name} has no method(s) {', '.join(wrong)}; its methods: {', '.join(known or ())}"
    return None


def _guidance_refusal(args: argparse.Namespace) -> str | None:
    """Why the critic guidance flags cannot be used as given, or None."""
    from shared.sampling.diffusion import DiffusionConfigError, GradientGuidance

    if args.guided_steps is not None and args.critic_guidance is None:
        return "--guided-steps needs --critic-guidance"
    if args.critic_guidance is None:
        return None
    try:
        GradientGuidance.of(args.critic_guidance, args.guided_steps)
    except DiffusionConfigError as exc:
        return f"--critic-guidance / --guided-steps: {exc}"
    return None


def _sampler_quality_options(args: argparse.Namespace, split: str) -> dict:
    options = {"split": split, "checkpoint": args.checkpoint, "nn_index": args.nn_index, "yaw": args.yaw,
               "tag": args.tag, "objects": args.objects}
    if args.noise_scale is not None:
        options["noise_scale"] = args.noise_scale
    if args.critic_guidance is not None:
        from shared.sampling.diffusion import GradientGuidance

        options["guidance"] = GradientGuidance.of(args.critic_guidance, args.guided_steps)
    if args.methods is not None:
        options["methods_to_run"] = args.methods
    return options


def experiment_function(name: str):
    module, function = EXPERIMENTS[name].split(":")
    return getattr(importlib.import_module(module), function)


def run(args: argparse.Namespace) -> int:
    from evaluation.coverage import CoverageError
    from evaluation.final_run import FinalRunError, run_final
    from evaluation.methods import DEFAULT_CAMERAS
    from evaluation.report import command_line, write_index
    from evaluation.store import ResultStoreError

    # A stopped evaluation must not leave its worker processes running: SystemExit unwinds the pool's
    # context, which terminates them (finished trials are already on disk).
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(143))
    if args.workers < 1:
        print("gd2p eval: --workers must be >= 1", file=sys.stderr)
        return 2
    for flag, value in (("--trials", args.trials), ("--objects", args.objects), ("--train-steps", args.train_steps)):
        if value is not None and value < 1:
            print(f"gd2p eval: {flag} must be >= 1", file=sys.stderr)
            return 2
    if args.tag is not None and not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9._-]{0,63}", args.tag):
        print(f"gd2p eval: --tag names a directory: letters, digits, '.', '_', '-' (got {args.tag!r})", file=sys.stderr)
        return 2
    # `all` is a slice of each of the paper's experiments; the suite runs closed-loop again per task
    names = [n for n in EXPERIMENTS if n != "suite"] if args.experiment == "all" else [args.experiment]
    if args.tasks is not None and names not in (["suite"], ["closed-loop"]):
        print("gd2p eval: --tasks applies to suite and closed-loop only", file=sys.stderr)
        return 2
    if args.tasks is not None and names == ["closed-loop"] and len(args.tasks) != 1:
        print("gd2p eval closed-loop: --tasks takes one task (its run alone); the suite runs several", file=sys.stderr)
        return 2
    if args.split == "test":
        print("gd2p eval: --split test is the development split, now named dev (the same objects, seeds and results "
              "directories); the held-out measurement is --split final", file=sys.stderr)
    split = "test" if args.split in ("dev", "test") else args.split  # the object library's name for dev
    if split == "final" and args.experiment not in TRIAL_EXPERIMENTS:
        print(f"gd2p eval: --split final applies to {', '.join(TRIAL_EXPERIMENTS)} one at a time (the final split is "
              "measured by the trial protocol, once per release)", file=sys.stderr)
        return 2
    if args.view is not None:
        from evaluation import local_system
        from visualisation.live import LiveView

        if args.workers != 1:
            print("gd2p eval: --view runs one trial at a time in this process (--workers 1)", file=sys.stderr)
            args.workers = 1
        view = LiveView(port=args.view, title="GD2P evaluation")
        print(f"live view: {view.url}", file=sys.stderr, flush=True)
        local_system.set_view(view)
        import atexit

        atexit.register(view.close)
    data_size_only = [flag for flag, value in (("--dataset", args.dataset), ("--train-steps", args.train_steps),
                                               ("--lr", args.lr), ("--seeds", args.seeds)) if value is not None]
    if split == "unseen" and any(name not in TRIAL_EXPERIMENTS for name in names):
        print(f"gd2p eval: --split unseen applies to {', '.join(TRIAL_EXPERIMENTS)} (sampler-quality measures the mugs "
              "within the test split)", file=sys.stderr)
        return 2
    if args.cameras is not None and not any(name in WORLD_EXPERIMENTS + COVERAGE_EXPERIMENTS for name in names):
        print(f"gd2p eval: --cameras applies to {', '.join(WORLD_EXPERIMENTS + COVERAGE_EXPERIMENTS)} (sampler-diagnosis "
              "measures training objects as the dataset stores them)", file=sys.stderr)
        return 2
    if data_size_only and args.experiment != "data-size":
        print(f"gd2p eval: {', '.join(data_size_only)} apply to data-size only", file=sys.stderr)
        return 2
    model_flags = [flag for flag, value in (("--checkpoint", args.checkpoint), ("--nn-index", args.nn_index),
                                            ("--noise-scale", args.noise_scale), ("--critic-guidance", args.critic_guidance),
                                            ("--guided-steps", args.guided_steps)) if value is not None]
    if (refusal := _guidance_refusal(args)) is not None:
        print(f"gd2p eval: {refusal}", file=sys.stderr)
        return 2
    if args.noise_scale is not None and not 0.0 < args.noise_scale <= 1.0:
        print(f"gd2p eval: --noise-scale must be in (0, 1], got {args.noise_scale}", file=sys.stderr)
        return 2
    if model_flags and args.experiment != "sampler-quality":
        # a trial experiment's planner takes its models from the sampler service, which reads these variables
        print(f"gd2p eval: {', '.join(model_flags)} apply to sampler-quality only; to run {args.experiment} with other "
              "models set GD2P_SAMPLER_CHECKPOINT_<HAND> / GD2P_SAMPLER_NN_INDEX_<HAND> / GD2P_SAMPLER_NOISE_SCALE and "
              "name the run with --tag",
              file=sys.stderr)
        return 2
    if (refusal := _methods_refusal(args.methods, names)) is not None:
        print(f"gd2p eval: {refusal}", file=sys.stderr)
        return 2
    for name in names:
        options = {"trials": args.trials} if args.trials is not None and name in TRIAL_EXPERIMENTS else {}
        if name in WORLD_EXPERIMENTS + COVERAGE_EXPERIMENTS:
            options["world"] = args.world
        if args.methods is not None and name in TRIAL_EXPERIMENTS:
            options["methods"] = args.methods
        if name in WORLD_EXPERIMENTS + COVERAGE_EXPERIMENTS:
            options["cameras"] = DEFAULT_CAMERAS[args.world] if args.cameras is None else args.cameras
        if split not in ("test", "final") and (name in TRIAL_EXPERIMENTS or (name == "multistep" and split == "val")):
            options["split"] = split
        if args.tag is not None and name in WORLD_EXPERIMENTS:
            options["tag"] = args.tag
        if args.tracking != "image" and name in TRIAL_EXPERIMENTS:
            options["tracking"] = args.tracking
        if args.closed_loop and name == "multistep":
            options["closed_loop"] = True
        if args.tasks is not None and name in ("suite", "closed-loop"):
            options["tasks"] = args.tasks
        if name == "sampler-quality":
            options.update(_sampler_quality_options(args, split))
        if name == "data-size" and args.experiment == "data-size":
            options.update(_data_size_options(args))
        try:
            if split == "final":
                report = run_final(name, experiment_function(name), args.out, quick=args.quick, workers=args.workers,
                                   command=command_line(), options=options)
            else:
                report = experiment_function(name)(args.out, quick=args.quick, workers=args.workers, **options)
        except (ResultStoreError, CoverageError, FinalRunError) as exc:
            print(f"gd2p eval {name}: {exc}", file=sys.stderr)
            return 2
        print(f"{name}: {report}")
    print(f"index: {write_index(args.out)}")
    return 0


def register_compare(subparsers: argparse._SubParsersAction) -> None:
    from evaluation import compare

    parser = subparsers.add_parser("compare", help="two evaluation runs of one protocol, trial by trial (or object by object: sampler-quality)",
                                   description=compare.__doc__ + "\n    gd2p compare results/closed-loop-real:gd2p "
                                   "results/methods-real-v2:gd2p --out cmp.md",
                                   formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run_a", metavar="RUN_A", help="DIR[:METHOD] (the method defaults to gd2p)")
    parser.add_argument("run_b", metavar="RUN_B", help="DIR[:METHOD]; the difference reported is B - A")
    parser.add_argument("--across-worlds", action="store_true",
                        help="match trials by the request alone (object, direction, trial, seed), whatever world "
                             "executed them: e.g. results/methods-exact-v2:gd2p against results/methods-real-v2:gd2p")
    parser.add_argument("--out", type=Path, default=None, help="also write the markdown report here")
    parser.set_defaults(func=run_compare)


def run_compare(args: argparse.Namespace) -> int:
    from evaluation.compare import CompareError, compare, load_run, parse_run
    from evaluation.report import command_line
    from shared.atomic import atomic_write_text

    try:
        report = compare(load_run(*parse_run(args.run_a)), load_run(*parse_run(args.run_b)), args.across_worlds,
                         command=command_line())
    except CompareError as exc:
        print(f"gd2p compare: {exc}", file=sys.stderr)
        return 2
    print(report)
    if args.out is not None:
        atomic_write_text(args.out, report)
    return 0
