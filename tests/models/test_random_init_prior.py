"""A random initialisation knows no prior (issue 20): an anchored checkpoint's random init starts
uniform, while the checkpoint itself starts at the prior it was meta-trained on."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from models.checkpoints import Checkpoint, observation_for, write_checkpoint
from models.learners.meta_policy import MetaPolicyLearner
from models.learners.mlp_policy import init_params
from models.simulate import BatchMetaPolicy, random_init_params

PRIOR = np.array([0.61, 0.07, 0.18, 0.14])


def _anchored(directory: Path) -> Checkpoint:
    obs = observation_for("conation")
    return write_checkpoint(
        directory,
        n_arms=4,
        category="conation",
        mode="online",
        rule="natural_expected",
        observation=obs,
        params=init_params(np.random.default_rng(3), obs.shape[0], 100, 4),
        step_sizes=np.array([1.0, 0.8]),
        baselines=np.array([0.3, 0.3]),
        damping=0.1,
        config={},
        metrics={},
        prior=PRIOR,
    )


def test_the_checkpoint_starts_at_its_prior_and_a_random_init_at_uniform(tmp_path: Path) -> None:
    checkpoint = _anchored(tmp_path / "c")
    np.testing.assert_allclose(MetaPolicyLearner(checkpoint).probabilities(), PRIOR, rtol=1e-12)
    random = MetaPolicyLearner.random_init(checkpoint, np.random.default_rng(1))
    np.testing.assert_allclose(random.probabilities(), np.full(4, 0.25), rtol=1e-12)
    random.update(1, 1.0)
    restored = MetaPolicyLearner(checkpoint)
    restored.load_state_dict(random.state_dict())
    np.testing.assert_array_equal(restored.probabilities(), random.probabilities())
    restored.reset()
    np.testing.assert_allclose(restored.probabilities(), np.full(4, 0.25), rtol=1e-12)


def test_the_batch_simulation_agrees(tmp_path: Path) -> None:
    checkpoint = _anchored(tmp_path / "c")
    shared = BatchMetaPolicy(checkpoint)
    np.testing.assert_allclose(shared.probabilities()[0], PRIOR, rtol=1e-12)
    params = random_init_params(checkpoint, 5, np.random.default_rng(2))
    randoms = BatchMetaPolicy(checkpoint, params).probabilities()
    np.testing.assert_allclose(randoms, np.full((5, 4), 0.25), rtol=1e-12)
