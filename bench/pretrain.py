"""Benchmark: meta-training time, paper mode (target ≤ 10 s) and, on request, online mode.

Run from the repository root::

    .venv/bin/python bench/pretrain.py              # paper mode, conation K = 4, 3 runs
    .venv/bin/python bench/pretrain.py --online     # also time one online-mode run (minutes)

Paper mode uses the issue's configuration (200 meta-batches × 40 tasks, 20 pulls, fast lr 0.5,
max-KL 1e-2, CG 10 × 1e-5, line search 15 × 0.8, discount 0.95); the time is training only (the
final 20,000-participant evaluation written to metrics.json is excluded). One thread, as
``pretrain`` always trains. The shipped checkpoints' recorded training times are listed too.
Prints figures only; never used as a test assertion.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import tempfile
from pathlib import Path

_ROOT = Path(__file__).resolve().parents[1]
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != _ROOT / "bench"]
sys.path.insert(0, str(_ROOT))

import torch  # noqa: E402

from bench.analysis import cpu_model  # noqa: E402
from models.checkpoints import PRETRAINED_DIR, RETIRED_DIR  # noqa: E402
from models.pretrain import PretrainArgs, pretrain  # noqa: E402

PAPER_TARGET_S = 10.0


def timed(args: PretrainArgs) -> tuple[float, str]:
    """Training seconds and the weights' hash of one run into a temporary directory."""
    with tempfile.TemporaryDirectory() as tmp:
        checkpoint = pretrain(args, Path(tmp) / "ckpt")
        return float(checkpoint.metrics["train_seconds"]), checkpoint.sha256


def main() -> None:
    """Time paper-mode training (and online with ``--online``); list recorded times."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--online", action="store_true")
    args = parser.parse_args()
    print(
        f"# {platform.python_implementation()} {platform.python_version()}, torch "
        f"{torch.__version__}, nproc={os.cpu_count()}, CPU: {cpu_model()}"
    )
    paper = PretrainArgs(category="conation", mode="paper", evaluation_participants=100)
    runs = [timed(paper) for _ in range(args.repeats)]
    seconds = [s for s, _ in runs]
    worst = max(seconds)
    print(
        f"paper mode, conation K = 4: median {statistics.median(seconds):.2f} s, worst "
        f"{worst:.2f} s over {args.repeats} runs (target ≤ {PAPER_TARGET_S:g} s: "
        f"{'met' if worst <= PAPER_TARGET_S else 'MISSED'}); identical weights every run: "
        f"{len({h for _, h in runs}) == 1}"
    )
    if args.online:
        online = PretrainArgs(category="conation", mode="online", evaluation_participants=100)
        seconds_online, _ = timed(online)
        print(f"online mode, conation K = 4: {seconds_online:.1f} s")
    print("recorded training times of the shipped checkpoints:")
    for metrics in sorted(PRETRAINED_DIR.rglob("metrics.json")):
        if RETIRED_DIR in metrics.parents:
            continue
        recorded = json.loads(metrics.read_text())
        where = metrics.parent.relative_to(PRETRAINED_DIR)
        print(f"  {where}: {recorded['train_seconds']:.1f} s")


if __name__ == "__main__":
    main()
