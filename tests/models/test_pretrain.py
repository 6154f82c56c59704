"""Meta-training: second-order meta-gradients, the TRPO trust region, seeding, reproducibility."""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import replace
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import torch

from models.checkpoints import PRETRAINED_DIR, load_checkpoint, observation_for
from models.feedback import FeedbackModel
from models.inner_loops import (
    objective_terms,
    online_advantages,
    online_rollout,
    online_surrogate,
    online_surrogate_and_kl,
    paper_rollout,
    paper_surrogate,
    paper_surrogate_and_kl,
    sample_online_batch,
    sample_paper_batch,
)
from models.learners.meta_policy import MetaPolicyLearner
from models.learners.mlp_policy import init_params, update_params
from models.meta_torch import DTYPE, apply_step, initial_theta, layout_for
from models.pretrain import (
    CALIBRATION_SCALES,
    PretrainArgs,
    as_checkpoint,
    calibrate_step_scale,
    filter_score,
    pretrain,
    select_calibrated,
    train,
    with_step_scale,
)
from models.seed_selection import filter_validation
from models.trpo import conjugate_gradient, trpo_step

TINY: dict[str, Any] = {
    "hidden": 6,
    "tasks_per_batch": 6,
    "validation_participants": 50,
    "evaluation_participants": 50,
    "validate_every": 2,
    "calibration_participants": 50,
}


def _setup(mode: str, seed: int = 0, **changes: object):  # type: ignore[no-untyped-def]
    args = PretrainArgs(mode=mode, arms=3, horizon=4, pulls=5, **{**TINY, **changes}).resolved()
    rng = np.random.default_rng(seed)
    obs = torch.as_tensor(observation_for("generic"), dtype=DTYPE)
    layout = layout_for(args, obs.shape[0])
    theta = initial_theta(args, layout, rng)
    return args, rng, obs, layout, theta


def test_torch_step_matches_the_numpy_learner() -> None:
    rng = np.random.default_rng(3)
    obs = observation_for("affection")
    params = init_params(rng, obs.shape[0], 7, 4)
    expected = update_params(
        params,
        obs,
        np.asarray(1),
        np.asarray(0.8),
        step_size=0.6,
        baseline=0.2,
        damping=0.03,
        rule="natural",
    )
    net = {k: torch.as_tensor(v) for k, v in params.items()}
    t_obs = torch.as_tensor(obs)
    pi = torch.softmax(net["W2"] @ torch.tanh(net["W1"] @ t_obs + net["b1"]) + net["b2"], -1)
    s = (torch.eye(4, dtype=DTYPE)[1] - pi) * (0.8 - 0.2)
    got = apply_step(net, t_obs, s, torch.tensor(0.6, dtype=DTYPE), torch.tensor(0.03, dtype=DTYPE))
    for name in expected:
        np.testing.assert_allclose(got[name].numpy(), expected[name], rtol=1e-12, atol=1e-14)


ROBUST: dict[str, Any] = {
    "feedback": FeedbackModel(slips=(0.0, 0.2), slip_weights=(0.5, 0.5), hazard=0.3).to_json(),
    "anchor": True,
    "forgetting": True,
    "surprise_gates": True,
    "bounded_baseline": True,
    "selection": "log_score",
}
"""A feedback model with slips and a hazard large enough that 6 tasks × 4 answers see both."""


@pytest.mark.parametrize(
    ("rule", "robust", "memory", "trace"),
    [
        ("natural_expected", False, False, None),
        ("natural", False, False, None),
        ("gradient", False, False, None),
        ("natural_expected", True, False, None),
        ("gradient", True, False, None),
        ("natural_expected", True, True, None),
        ("natural_expected", True, False, "surprise"),
        ("natural_expected", True, True, "contradiction"),
    ],
)
def test_online_rollout_is_the_deployed_learner(
    rule: str, robust: bool, memory: bool, trace: str | None
) -> None:
    """The differentiable inner loop and the deployed numpy learner (built from the checkpoint
    training would write) take the same 4 steps on 6 tasks: with the paper's Gaussian rewards,
    and with yes/no answers that slip, a preference that changes, the anchor, forgetting, the
    surprise gates, their memory of earlier surprises and their per-question trace."""
    options = {**ROBUST, "surprise_memory": memory, "question_trace": trace} if robust else {}
    args, rng, obs, layout, theta = _setup("online", online_rule=rule, **options)
    batch = sample_online_batch(args, rng)
    if robust:  # the draws exercise what they should
        assert bool(batch.slipped.any()) and bool((batch.preferred != batch.preferred[:, :1]).any())
    if robust:  # gates away from zero, so their arithmetic is compared too
        values = layout.unflatten(theta)
        values["surprise_step"].copy_(torch.linspace(-0.5, 0.5, args.horizon))
        values["surprise_retention"].copy_(torch.linspace(-1.0, 1.0, args.horizon))
        if memory:
            values["memory_step"].copy_(torch.linspace(0.4, -0.6, args.horizon))
        for shift, name in enumerate(("step", "retention", "others_step", "others_retention")):
            if trace is not None:
                values[f"trace_{name}"].copy_(torch.linspace(-1.0 + shift, 1.0, args.horizon))
    with torch.no_grad():
        rollout = online_rollout(theta, layout, obs, args, batch)
    checkpoint = as_checkpoint(theta, layout, args)
    assert (checkpoint.prior is not None) == robust and (checkpoint.retention is not None) == robust
    assert (checkpoint.gates is not None) == robust and checkpoint.remembers == memory
    assert checkpoint.traces == (trace is not None)
    if trace is not None:
        assert checkpoint.gates is not None and checkpoint.gates.trace_kind == trace
    for task in range(args.tasks_per_batch or 0):
        learner = MetaPolicyLearner(checkpoint)
        np.testing.assert_allclose(
            np.exp(rollout.log_probs[0][task].numpy()), learner.probabilities(), rtol=1e-12
        )
        for t in range(args.horizon):
            action = int(rollout.actions[task, t])
            says_yes = (action == int(batch.preferred[task, t])) != bool(batch.slipped[task, t])
            reward = float(says_yes)
            if not robust:
                reward += np.sqrt(args.variance) * float(batch.noise[task, t])
            learner.update(action, reward)
            np.testing.assert_allclose(
                np.exp(rollout.log_probs[t + 1][task].numpy()),
                learner.probabilities(),
                rtol=1e-10,
                atol=1e-12,
            )


def test_legacy_runs_draw_exactly_what_they_drew_before_issue_19() -> None:
    """Without a feedback model the batch is the old one (so old configs reproduce their
    checkpoints): the same draws in the same order, the preference fixed, no slips."""
    args, rng, *_ = _setup("online")
    batch = sample_online_batch(args, rng)
    _, old_rng, *_ = _setup("online")  # the old code's draws, by hand
    b, t = args.tasks_per_batch or 0, args.horizon
    preferred = args.tasks.sample_preferred(old_rng, b)
    np.testing.assert_array_equal(batch.preferred.numpy(), np.repeat(preferred[:, None], t, 1))
    np.testing.assert_array_equal(batch.uniforms.numpy(), old_rng.random((b, t)))
    np.testing.assert_array_equal(batch.noise.numpy(), old_rng.standard_normal((b, t)))
    assert not bool(batch.slipped.any())
    assert rng.random() == old_rng.random()


def test_a_bounded_baseline_stays_between_the_answers_rewards() -> None:
    """However far meta-training pushes it, a yes still adds and a no still subtracts."""
    args, _, _, layout, theta = _setup("online", **ROBUST)
    values = layout.unflatten(theta)
    assert "baseline" not in values
    np.testing.assert_allclose(as_checkpoint(theta, layout, args).baselines, 0.5)
    values["baseline_logit"].copy_(torch.tensor([-80.0, -3.0, 3.0, 80.0]))
    got = as_checkpoint(theta, layout, args).baselines
    assert np.all(got >= 0.0) and np.all(got <= 1.0) and got[1] < 0.5 < got[2]
    with pytest.raises(ValueError, match="yes/no feedback model"):
        PretrainArgs(bounded_baseline=True).resolved()


def test_natural_expected_starts_at_the_bayes_update() -> None:
    args, _, _, layout, theta = _setup("online", variance=0.25)
    values = layout.unflatten(theta)
    # (μ₁ − μ₀)/σ² and (μ₁ + μ₀)/2 for the default rewards N(1, σ²) / N(0, σ²).
    assert torch.allclose(values["log_step"].exp(), torch.full((args.horizon,), 4.0, dtype=DTYPE))
    assert torch.allclose(values["baseline"], torch.full((args.horizon,), 0.5, dtype=DTYPE))
    args, _, _, layout, theta = _setup("online", online_rule="natural")
    assert torch.allclose(
        layout.unflatten(theta)["log_step"].exp(), torch.ones(args.horizon, dtype=DTYPE)
    )


def test_calibration_keeps_the_largest_scale_within_the_limit() -> None:
    args, _, _, layout, theta = _setup("online", calibration_participants=400)
    steps = layout.unflatten(theta)["log_step"].exp()
    scaled = with_step_scale(theta, layout, 0.5)
    assert torch.allclose(layout.unflatten(scaled)["log_step"].exp(), 0.5 * steps)
    assert torch.equal(layout.unflatten(theta)["log_step"].exp(), steps)  # a copy

    loose = replace(args, calibration_limit=0.999)
    same, report = calibrate_step_scale(theta, layout, loose)
    assert torch.equal(same, theta) and report["scale"] == 1.0 and report["within_limit"]

    impossible = replace(args, calibration_limit=1e-12)
    smallest, report = calibrate_step_scale(theta, layout, impossible)
    assert [trial["scale"] for trial in report["trials"]] == list(CALIBRATION_SCALES)
    assert report == {**report, "scale": 0.5, "within_limit": False}
    assert torch.allclose(layout.unflatten(smallest)["log_step"].exp(), 0.5 * steps)

    # A limit between the trials' own figures stops at the first trial within it.
    wrongs = [trial["wrong_95"] for trial in report["trials"]]
    if max(wrongs) > min(wrongs):
        limit = (max(wrongs) + min(wrongs)) / 2
        _, chosen = calibrate_step_scale(theta, layout, replace(args, calibration_limit=limit))
        first = next(t for t in report["trials"] if t["wrong_95"] <= limit)
        assert chosen["scale"] == first["scale"] and chosen["within_limit"]
        assert all(t["wrong_95"] > limit for t in chosen["trials"][:-1])


def test_selection_keeps_the_snapshot_fastest_once_calibrated(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A fast snapshot a little too often wrong can beat a slower one once both are calibrated;
    the search stops where no remaining snapshot can win (calibration only slows a learner)."""
    args, _, _, layout, _ = _setup("online")
    # snapshot id → (validation answers, calibrated answers, within the limit once calibrated)
    table = {
        1: (3.0, 3.30, True),
        2: (3.1, 3.20, True),
        3: (3.15, 3.5, False),
        4: (3.25, 3.0, True),
    }
    calibrated: list[int] = []

    def fake_calibration(theta: torch.Tensor, layout_: object, args_: object) -> tuple[Any, Any]:
        key = int(theta[0])
        calibrated.append(key)
        _, answers, within = table[key]
        trial = {"scale": 0.8, "iterations_to_95": answers, "wrong_95": 0.005}
        return theta * 10, {"scale": 0.8, "within_limit": within, "trials": [trial]}

    monkeypatch.setattr("models.pretrain.calibrate_step_scale", fake_calibration)
    snapshots = [
        (
            {"iteration": 5 * key, "iterations_to_95": answers, "mean_p_correct": 0.9},
            torch.tensor([float(key)]),
        )
        for key, (answers, _, _) in reversed(table.items())
    ]
    chosen = select_calibrated(snapshots, layout, args)
    assert chosen is not None
    (figures, theta), report = chosen
    assert figures["iteration"] == 10 and float(theta[0]) == 20.0  # snapshot 2, scaled
    assert calibrated == [1, 2, 3]  # 4's validation (3.25) cannot beat 3.20 once calibrated
    assert [c["iteration"] for c in report["candidates"]] == [5, 10, 15]

    table.update({key: (v, c, False) for key, (v, c, _) in table.items()})
    calibrated.clear()
    assert select_calibrated(snapshots, layout, args) is None
    assert calibrated == [1, 2, 3, 4]


def _directional_check(fn, theta: torch.Tensor, seed: int) -> tuple[float, float]:  # type: ignore[no-untyped-def]
    """(autograd, central finite difference) directional derivatives of ``fn`` at ``theta``."""
    direction = torch.as_tensor(np.random.default_rng(seed).standard_normal(theta.shape[0]))
    th = theta.clone().requires_grad_(True)
    grad = torch.autograd.grad(fn(th), th)[0]
    eps = 1e-6
    with torch.no_grad():
        fd = (fn(theta + eps * direction) - fn(theta - eps * direction)) / (2 * eps)
    return float(grad @ direction), float(fd)


def test_paper_meta_gradient_matches_finite_differences() -> None:
    args, rng, obs, layout, theta = _setup("paper")
    batch = sample_paper_batch(args, rng)
    with torch.no_grad():
        old = paper_rollout(theta, layout, obs, args, batch)

    def second(th: torch.Tensor) -> torch.Tensor:
        return paper_surrogate(paper_rollout(th, layout, obs, args, batch, fixed=old), old)

    def first(th: torch.Tensor) -> torch.Tensor:
        new = paper_rollout(th, layout, obs, args, batch, fixed=old, first_order=True)
        return paper_surrogate(new, old)

    for seed in range(3):
        auto, fd = _directional_check(second, theta, seed)
        assert auto == pytest.approx(fd, rel=1e-6, abs=1e-9)
        # The first-order approximation misses the path through the inner step: the check
        # above would catch an implementation that silently dropped it.
        auto_first, _ = _directional_check(first, theta, seed)
        assert abs(auto_first - fd) > 1e-4 * max(abs(fd), 1e-3)


@pytest.mark.parametrize(
    ("objective", "rule"),
    [("log_score", "natural_expected"), ("reward", "natural_expected"), ("log_score", "natural")],
)
def test_online_meta_gradient_matches_finite_differences(objective: str, rule: str) -> None:
    args, rng, obs, layout, theta = _setup("online", objective=objective, online_rule=rule)
    batch = sample_online_batch(args, rng)
    with torch.no_grad():
        old = online_rollout(theta, layout, obs, args, batch)
        advantages = online_advantages(objective_terms(old, batch, objective))

    def surrogate(th: torch.Tensor) -> torch.Tensor:
        new = online_rollout(th, layout, obs, args, batch, actions=old.actions)
        return online_surrogate(new, batch, old, advantages, objective)

    for seed in range(3):
        auto, fd = _directional_check(surrogate, theta, seed)
        assert auto == pytest.approx(fd, rel=1e-6, abs=1e-9)


def test_conjugate_gradient_solves_a_spd_system() -> None:
    rng = np.random.default_rng(0)
    a = rng.standard_normal((6, 6))
    h = torch.as_tensor(a @ a.T + 6 * np.eye(6))
    b = torch.as_tensor(rng.standard_normal(6))
    x = conjugate_gradient(lambda v: h @ v, b, 6)
    np.testing.assert_allclose((h @ x).numpy(), b.numpy(), atol=1e-8)


@pytest.mark.parametrize(("mode", "max_kl"), [("paper", 1e-2), ("online", 1e-2), ("online", 1e-4)])
def test_trpo_step_stays_within_max_kl_and_improves(mode: str, max_kl: float) -> None:
    for seed in range(4):
        args, rng, obs, layout, theta = _setup(mode, seed, max_kl=max_kl)
        surrogate: Callable[[torch.Tensor], tuple[torch.Tensor, torch.Tensor]]
        if mode == "paper":
            batch = sample_paper_batch(args, rng)
            with torch.no_grad():
                old = paper_rollout(theta, layout, obs, args, batch)
            surrogate = partial(paper_surrogate_and_kl, layout, obs, args, batch, old)
        else:
            online_batch = sample_online_batch(args, rng)
            with torch.no_grad():
                online_old = online_rollout(theta, layout, obs, args, online_batch)
                adv = online_advantages(objective_terms(online_old, online_batch, args.objective))
            surrogate = partial(
                online_surrogate_and_kl, layout, obs, args, online_batch, online_old, adv
            )
        new_theta, step = trpo_step(theta, surrogate, args)
        with torch.no_grad():
            value_before, _ = surrogate(theta)
            value_after, kl = surrogate(new_theta)
        assert float(kl) <= max_kl
        if step.accepted:
            assert float(value_after) > float(value_before)
            assert not torch.equal(new_theta, theta)
        else:
            assert torch.equal(new_theta, theta)


def test_same_seed_same_run_other_seed_other_run() -> None:
    for mode in ("online", "paper"):
        args = PretrainArgs(mode=mode, arms=3, horizon=3, meta_batches=3, **TINY).resolved()
        a, b = train(args), train(args)
        assert torch.equal(a.theta, b.theta)
        c = train(replace(args, seed=1))
        assert not torch.equal(a.theta, c.theta)


def test_tiny_pretrain_writes_a_usable_checkpoint_and_reruns_reproduce_it(tmp_path: Path) -> None:
    args = PretrainArgs(
        category="cognition", mode="online", arms=3, horizon=3, meta_batches=4, seed=5, **TINY
    )
    first = pretrain(args, tmp_path / "a")
    second = pretrain(args, tmp_path / "b")
    assert first.sha256 == second.sha256
    assert (tmp_path / "a" / "weights.json").read_bytes() == (
        tmp_path / "b" / "weights.json"
    ).read_bytes()
    loaded = load_checkpoint(tmp_path / "a", expected_arms=3)
    assert loaded.config["category"] == "cognition"
    assert loaded.config["seed"] == 5
    assert set(loaded.metrics["evaluation"]) >= {"iterations_to_95", "wrong_95", "p_correct"}
    assert len(loaded.step_sizes) == 3 and loaded.rule == "natural_expected"
    assert loaded.metrics["calibration"]["scale"] in CALIBRATION_SCALES
    learner = MetaPolicyLearner.from_checkpoint(tmp_path / "a", expected_arms=3)
    learner.update(learner.select(np.random.default_rng(0)), 1.0)
    assert learner.answers == 1


def test_bad_arguments_are_refused() -> None:
    with pytest.raises(ValueError, match="mode"):
        PretrainArgs(mode="offline").resolved()
    with pytest.raises(ValueError, match="objective"):
        PretrainArgs(objective="accuracy").resolved()
    with pytest.raises(ValueError, match="horizon"):
        PretrainArgs(horizon=0).resolved()
    with pytest.raises(ValueError, match="preferred prior"):
        PretrainArgs(arms=4, preferred_prior=(1.0, 0.0)).resolved()


def test_the_shipped_paper_recipe_still_trains_and_reruns_reproduce_it(tmp_path: Path) -> None:
    """The shipped paper checkpoint's config.json is a complete recipe: today's code accepts it
    and trains a checkpoint of the same shape and settings, twice to the same bytes.

    Not compared with the shipped bytes themselves: TRPO's line search turns a last-bit
    difference into a different network, and torch/MKL pick their kernels by CPU, so the shipped
    weights (trained on an AMD EPYC) come back bit for bit only on that kind of CPU
    (docs/engine.md, "Retraining")."""
    shipped_dir = PRETRAINED_DIR / "paper" / "conation-k4"
    if not (shipped_dir / "weights.json").exists():
        pytest.fail(f"{shipped_dir} does not ship")
    shipped = load_checkpoint(shipped_dir)
    config = json.loads((shipped_dir / "config.json").read_text())
    config.pop("torch")
    config["preferred_prior"] = (
        None if config["preferred_prior"] is None else tuple(config["preferred_prior"])
    )
    config["evaluation_participants"] = 100  # metrics only: the weights' hash is unaffected
    torch.set_num_threads(1)
    first = pretrain(PretrainArgs(**config), tmp_path / "first")
    second = pretrain(PretrainArgs(**config), tmp_path / "second")
    assert first.sha256 == second.sha256
    assert (first.n_arms, first.hidden, first.rule) == (
        shipped.n_arms,
        shipped.hidden,
        shipped.rule,
    )
    assert {name: value.shape for name, value in first.params.items()} == {
        name: value.shape for name, value in shipped.params.items()
    }
    rerun_config = json.loads((tmp_path / "first" / "config.json").read_text())
    shipped_config = json.loads((shipped_dir / "config.json").read_text())
    for changed in ("torch", "evaluation_participants"):
        rerun_config.pop(changed)
        shipped_config.pop(changed)
    # Arguments added since the checkpoint shipped are recorded too; the shipped ones must match.
    assert {key: rerun_config.get(key) for key in shipped_config} == shipped_config


def test_plain_gradient_variant_trains_without_damping(tmp_path: Path) -> None:
    args = PretrainArgs(
        mode="online", arms=3, horizon=2, meta_batches=2, online_rule="gradient", **TINY
    )
    checkpoint = pretrain(args, tmp_path / "plain")
    assert checkpoint.rule == "gradient"
    assert "log_damping" not in layout_for(args.resolved(), 8).shapes
    with pytest.raises(ValueError, match="online_rule"):
        PretrainArgs(online_rule="newton").resolved()


def test_wrong_penalty_adds_log_of_the_doubt_about_wrong_questions() -> None:
    from models.inner_loops import OnlineBatch, Rollout

    log_probs = [torch.log(torch.tensor([[0.2, 0.5, 0.3]], dtype=DTYPE))] * 2
    rollout = Rollout(log_probs, torch.zeros((1, 1), dtype=torch.long))
    batch = OnlineBatch(
        torch.tensor([[2]]),
        torch.zeros((1, 1)),
        torch.zeros((1, 1)),
        torch.zeros((1, 1), dtype=torch.bool),
    )
    plain = objective_terms(rollout, batch, "log_score")
    penalised = objective_terms(rollout, batch, "log_score", wrong_penalty=2.0)
    assert float(plain[0, 0]) == pytest.approx(np.log(0.3))
    assert float(penalised[0, 0]) == pytest.approx(np.log(0.3) + 2.0 * np.log(1 - 0.5))
    with pytest.raises(ValueError, match="wrong_penalty"):
        PretrainArgs(wrong_penalty=-1.0).resolved()


@pytest.mark.parametrize("calibrate", [False, True])
def test_selection_falls_back_to_the_best_penalised_validation(
    calibrate: bool, monkeypatch: pytest.MonkeyPatch
) -> None:
    """No validation within the selection limit and (when calibrating) no snapshot that
    calibration brings within its limit: the best penalised validation, then calibrated."""
    monkeypatch.setattr("models.pretrain.select_calibrated", lambda *args: None)
    args = PretrainArgs(
        mode="online",
        arms=3,
        horizon=3,
        meta_batches=4,
        wrong_limit=-1.0,
        calibrate=calibrate,
        **{**TINY, "validation_participants": 400},
    ).resolved()
    result = train(args)
    assert len(result.validations) == 2
    best = min(
        result.validations, key=lambda v: v["iterations_to_95"] + 100 * (v["wrong_95"] + 1.0)
    )
    assert result.selected_iteration == best["iteration"]
    assert result.validation["wrong_95"] == best["wrong_95"]
    if calibrate:
        assert result.calibration["scale"] in CALIBRATION_SCALES
        assert "candidates" not in result.calibration
    else:
        assert result.calibration == {}


def test_the_filter_objective_scores_the_policy_against_the_exact_filter() -> None:
    """The beliefs are the forward filter's on each task's own answers (the rewards the rollout
    recorded are the answers its participants gave), the objective is Σ b log π, and its
    meta-gradient is exact (finite differences): the filter's beliefs are constants."""
    from models.inner_loops import filter_beliefs
    from models.learners.belief import BeliefLearner

    args, rng, obs, layout, theta = _setup(
        "online", **{**ROBUST, "objective": "filter", "selection": "filter"}
    )
    batch = sample_online_batch(args, rng)
    with torch.no_grad():
        old = online_rollout(theta, layout, obs, args, batch)
    beliefs = filter_beliefs(old, args)
    assert beliefs.shape == (args.tasks_per_batch, args.horizon, args.arms)
    for task in range(args.tasks_per_batch or 0):
        reference = BeliefLearner(args.arms, args.feedback_model, args.tasks.prior)
        for t in range(args.horizon):
            action = int(old.actions[task, t])
            said_yes = (action == int(batch.preferred[task, t])) != bool(batch.slipped[task, t])
            assert float(old.rewards[task, t]) == float(said_yes)
            reference.update(action, float(said_yes))
            np.testing.assert_allclose(beliefs[task, t].numpy(), reference.probabilities())
    terms = objective_terms(old, batch, "filter", beliefs=beliefs)
    by_hand = (beliefs[:, 1] * old.log_probs[2]).sum(-1)
    np.testing.assert_allclose(terms[:, 1].numpy(), by_hand.numpy(), rtol=1e-14)
    with pytest.raises(ValueError, match="needs the filter's beliefs"):
        objective_terms(old, batch, "filter")
    advantages = online_advantages(terms)

    def surrogate(th: torch.Tensor) -> torch.Tensor:
        new = online_rollout(th, layout, obs, args, batch, actions=old.actions)
        return online_surrogate(new, batch, old, advantages, "filter", beliefs=beliefs)

    auto, fd = _directional_check(surrogate, theta, 0)
    assert auto == pytest.approx(fd, rel=1e-6, abs=1e-9)


def test_filter_selection_records_its_score_and_keeps_the_best() -> None:
    args = PretrainArgs(
        mode="online",
        arms=3,
        horizon=3,
        meta_batches=2,
        **{**TINY, **ROBUST, "objective": "filter", "selection": "filter", "validate_every": 1},
    ).resolved()
    result = train(args)
    scores = [v["filter_score"] for v in result.validations]
    assert len(scores) == 2 and all(s < 0 for s in scores)
    best = max(result.validations, key=lambda v: v["filter_score"])
    assert result.selected_iteration == best["iteration"]
    for bad, message in (
        ({"mode": "paper", "objective": "filter"}, "online mode"),
        ({**ROBUST, "objective": "filter", "wrong_penalty": 0.5}, "log_score objective only"),
    ):
        with pytest.raises(ValueError, match=message):
            PretrainArgs(**bad).resolved()


@pytest.mark.parametrize("trace", [None, "contradiction"])
def test_seed_selection_scores_what_training_validation_scores(trace: str | None) -> None:
    """The numpy score that compares seeds on one fixed validation set
    (:func:`models.seed_selection.filter_validation`) is training's own filter score
    (:func:`models.pretrain.filter_score`) on the same draws, for the deployed learner."""
    args = PretrainArgs(
        mode="online", arms=3, horizon=4, **{**TINY, **ROBUST, "question_trace": trace}
    ).resolved()
    rng = np.random.default_rng(4)
    obs = torch.as_tensor(observation_for(args.category), dtype=DTYPE)
    layout = layout_for(args, obs.shape[0])
    theta = initial_theta(args, layout, rng)
    values = layout.unflatten(theta)
    values["surprise_retention"].copy_(torch.linspace(-1.0, 1.0, args.horizon))
    if trace is not None:
        values["trace_retention"].copy_(torch.linspace(-2.0, 1.0, args.horizon))
    # As written: the config records the model (an in-memory one records nothing).
    checkpoint = replace(as_checkpoint(theta, layout, args), config={"feedback": args.feedback})
    numpy = filter_validation(checkpoint, participants=200, seed=99)
    batch = sample_online_batch(replace(args, tasks_per_batch=200), np.random.default_rng(99))
    assert numpy.filter_score == pytest.approx(
        filter_score(theta, layout, obs, args, batch), rel=1e-10
    )


def test_oversampled_changes_of_mind_are_weighted_back_to_the_model() -> None:
    """Drawn at 4 × the hazard, tasks change their minds more often, and each is weighted by
    its likelihood ratio: the weights average to one and reweight the change counts back to
    the model's (importance sampling keeps the meta-objective the model's own)."""
    model = FeedbackModel(slips=(0.05,), hazard=0.05)
    args = PretrainArgs(
        mode="online",
        arms=3,
        horizon=6,
        **{**TINY, "tasks_per_batch": 20_000, "feedback": model.to_json()},
        change_oversampling=4.0,
    ).resolved()
    batch = sample_online_batch(args, np.random.default_rng(0))
    assert batch.weights is not None
    changes = (batch.preferred[:, 1:] != batch.preferred[:, :-1]).sum(1).double()
    assert float(changes.mean()) == pytest.approx(5 * 0.2, rel=0.05)  # drawn at hazard .2
    expected = (0.05 / 0.2) ** changes * (0.95 / 0.8) ** (5 - changes)
    np.testing.assert_allclose(batch.weights.numpy(), expected.numpy(), rtol=1e-12)
    assert float(batch.weights.mean()) == pytest.approx(1.0, abs=0.03)
    reweighted = float((batch.weights * changes).mean())
    assert reweighted == pytest.approx(5 * 0.05, rel=0.1)  # the model's own rate of changes
    plain = replace(args, change_oversampling=1.0)
    assert sample_online_batch(plain, np.random.default_rng(0)).weights is None
    with pytest.raises(ValueError, match="change_oversampling"):
        PretrainArgs(change_oversampling=0.5).resolved()


def test_the_surrogate_weighs_each_task_by_its_importance_weight() -> None:
    args, rng, obs, layout, theta = _setup("online", **ROBUST)
    batch = sample_online_batch(args, rng)
    with torch.no_grad():
        old = online_rollout(theta, layout, obs, args, batch)
        advantages = online_advantages(objective_terms(old, batch, "log_score"))
        plain = online_surrogate(old, batch, old, advantages, "log_score")
        weights = torch.zeros(args.tasks_per_batch or 0, dtype=DTYPE)
        weights[0] = float(args.tasks_per_batch or 0)  # all the weight on the first task
        first = online_surrogate(old, replace(batch, weights=weights), old, advantages, "log_score")
    assert float(plain) != pytest.approx(float(first))
    only = objective_terms(old, batch, "log_score")[0].mean()
    assert float(first) == pytest.approx(float(only), rel=1e-12)
