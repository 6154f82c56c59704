"""Fixtures for the engine's tests: small checkpoints written on the fly (no training needed)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from models.checkpoints import Checkpoint, observation_for, write_checkpoint
from models.learners.mlp_policy import init_params


def make_checkpoint(
    directory: Path,
    n_arms: int = 4,
    *,
    rule: str = "natural",
    seed: int = 0,
    hidden: int = 100,
    prior: tuple[float, ...] | None = None,
    config: dict[str, Any] | None = None,
) -> Checkpoint:
    """A checkpoint with randomly initialised weights and plausible step sizes (anchored at
    ``prior`` when given; ``config`` is added to its recorded training arguments)."""
    obs = observation_for("conation")
    params = init_params(np.random.default_rng(seed), obs.shape[0], hidden, n_arms)
    return write_checkpoint(
        directory,
        n_arms=n_arms,
        category="conation",
        mode="online",
        rule=rule,  # type: ignore[arg-type]
        observation=obs,
        params=params,
        step_sizes=np.array([1.0, 0.8, 0.6]),
        baselines=np.array([0.25, 0.3, 0.35]),
        damping=0.05,
        config={"seed": seed} | (config or {}),
        metrics={"note": "test fixture"},
        prior=None if prior is None else np.asarray(prior),
    )


@pytest.fixture
def checkpoint(tmp_path: Path) -> Checkpoint:
    """A K = 4 natural-gradient checkpoint in a temporary directory."""
    return make_checkpoint(tmp_path / "ckpt")
