"""Benchmark: one decision (select + update) of C1 (Exp3) and C2 (the meta-policy).

Run from the repository root::

    .venv/bin/python bench/decide.py                  # 20,000 decisions per learner
    .venv/bin/python bench/decide.py --decisions 100000

Targets (issue 3): p99 of one decision ≤ 30 µs for C1 and ≤ 300 µs for C2. Each decision is
``select(rng)`` then ``update(action, reward)`` on a live learner, timed one by one with
``perf_counter_ns``; learners restart every 12 answers, as a participant's would. Also printed,
for information: the web app's full path per answer (JSON state → learner → decision → JSON
state). Prints figures only; never used as a test assertion.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

_ROOT = Path(__file__).resolve().parents[1]
sys.path[:] = [p for p in sys.path if Path(p or ".").resolve() != _ROOT / "bench"]
sys.path.insert(0, str(_ROOT))

from bench.analysis import cpu_model  # noqa: E402
from models.checkpoints import load_checkpoint, shipped_checkpoint  # noqa: E402
from models.learners.base import Learner  # noqa: E402
from models.learners.exp3 import DEFAULT_EXP3_GAMMA, Exp3  # noqa: E402
from models.learners.meta_policy import MetaPolicyLearner  # noqa: E402

TARGETS_US = {"C1 exp3": 30.0, "C2 meta": 300.0}
"""p99 microseconds allowed per decision."""


def time_decisions(make: Callable[[], Learner], decisions: int, seed: int) -> np.ndarray:
    """Nanoseconds of each select + update, restarting the learner every 12 answers."""
    rng = np.random.default_rng(seed)
    rewards = rng.normal(0.3, 0.3, size=decisions)
    out = np.empty(decisions, dtype=np.int64)
    learner = make()
    for i in range(decisions):
        if i % 12 == 0:
            learner = make()
        start = time.perf_counter_ns()
        action = learner.select(rng)
        learner.update(action, float(rewards[i]))
        out[i] = time.perf_counter_ns() - start
    return out


def time_stored_path(make: Callable[[], Learner], decisions: int, seed: int) -> np.ndarray:
    """Nanoseconds of restore-from-JSON + decision + state to JSON (the app's per-answer path)."""
    rng = np.random.default_rng(seed)
    out = np.empty(decisions, dtype=np.int64)
    state = json.dumps(make().state_dict())
    for i in range(decisions):
        if i % 12 == 0:
            state = json.dumps(make().state_dict())
        start = time.perf_counter_ns()
        learner = make()
        learner.load_state_dict(json.loads(state))
        learner.update(learner.select(rng), 1.0)
        state = json.dumps(learner.state_dict())
        out[i] = time.perf_counter_ns() - start
    return out


def main() -> None:
    """Time both learners and print p50/p99/max per decision."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--decisions", type=int, default=20_000)
    parser.add_argument("--seed", type=int, default=2026)
    args = parser.parse_args()
    checkpoint = load_checkpoint(shipped_checkpoint(4, category="conation"), expected_arms=4)
    learners: dict[str, Callable[[], Learner]] = {
        "C1 exp3": lambda: Exp3(4, gamma=DEFAULT_EXP3_GAMMA),
        "C2 meta": lambda: MetaPolicyLearner(checkpoint),
    }
    print(
        f"# {platform.python_implementation()} {platform.python_version()}, numpy "
        f"{np.__version__}, nproc={os.cpu_count()}, CPU: {cpu_model()}; K = 4, "
        f"{args.decisions} decisions, C2 checkpoint {checkpoint.path.name} "
        f"({checkpoint.sha256[:12]})"
    )
    for name, make in learners.items():
        time_decisions(make, 2000, args.seed)  # warm-up
        ns = time_decisions(make, args.decisions, args.seed)
        p50, p99 = np.percentile(ns, [50, 99]) / 1000
        target = TARGETS_US[name]
        verdict = "met" if p99 <= target else "MISSED"
        stored = np.percentile(time_stored_path(make, args.decisions // 4, args.seed), 99) / 1000
        print(
            f"{name}: select + update p50 {p50:.1f} µs, p99 {p99:.1f} µs, max "
            f"{ns.max() / 1000:.0f} µs (target p99 ≤ {target:g} µs: {verdict}); "
            f"with JSON restore + save p99 {stored:.1f} µs"
        )


if __name__ == "__main__":
    main()
