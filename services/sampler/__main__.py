"""`python -m services.sampler [bus flags] [--worker-id ID] [--checkpoint HAND=PATH ...] [--nn-index HAND=PATH ...]`:
one sampler worker until SIGTERM.

Checkpoints default to $GD2P_SAMPLER_CHECKPOINT_<HAND> or the shipped shared/sampling/checkpoints/<hand>.pt;
nearest-neighbour indexes (sampler "nearest") to $GD2P_SAMPLER_NN_INDEX_<HAND> or the shipped <hand>_nn.npz.
"""
from __future__ import annotations

import argparse
import sys

import torch

from shared.bus import BusConfig, run_worker
from shared.bus.service_cli import configure_service_logging, service_arg_parser
from shared.sampling.server import SERVICE, handlers, job_budget

# Requests handled at once: they wait together in the sampler's batching thread and share network passes.
CONCURRENT_REQUESTS = 8


def _hand_path_arg(text: str) -> tuple[str, str]:
    hand, sep, path = text.partition("=")
    if not sep or not hand or not path:
        raise argparse.ArgumentTypeError(f"expected HAND=PATH, got {text!r}")
    return hand, path


def main(argv: list[str] | None = None) -> int:
    parser = service_arg_parser("sampler", __doc__)
    parser.add_argument("--checkpoint", action="append", type=_hand_path_arg, default=[], metavar="HAND=PATH",
                        help="checkpoint of a hand (repeatable), e.g. allegro=ckpt/allegro.pt")
    parser.add_argument("--nn-index", action="append", type=_hand_path_arg, default=[], metavar="HAND=PATH",
                        help="nearest-neighbour index of a hand (repeatable), e.g. allegro=ckpt/allegro_nn.npz")
    parser.add_argument("--threads", type=int, default=1, help="torch threads (default 1: cores are shared, docs/architecture.md §Compute)")
    args = parser.parse_args(argv)
    configure_service_logging()
    torch.set_num_threads(max(1, args.threads))
    run_worker(SERVICE, handlers(dict(args.checkpoint), dict(args.nn_index)), BusConfig.from_args(args),
               worker_id=args.worker_id, concurrency=CONCURRENT_REQUESTS, capabilities=["ddpm", "ddim", "nearest"],
               job_budget=job_budget)
    return 0


if __name__ == "__main__":
    sys.exit(main())
