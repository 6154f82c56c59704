"""MAML's inner loops, differentiable for fixed random draws: ``online`` and ``paper`` modes.

``online``: the deployed protocol itself — T sequential single-answer updates per task, by the
checkpoint's rule (:mod:`models.learners.mlp_policy`) — with the per-answer objective (log score
or expected reward) and a surrogate whose gradient also credits *which* questions got asked
(score-function terms), since the actions are sampled.
``paper``: one plain policy-gradient step on 20 pulls per task, then 20 valid pulls, as in the
paper's configuration.

Every function takes the random draws as data (uniforms and noise), so re-evaluating a candidate
meta-step sees exactly the same tasks, actions and rewards.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numpy as np
import torch

from models.learners.belief import BatchBelief
from models.learners.mlp_policy import PARAM_NAMES
from models.meta_torch import DTYPE, Layout, apply_step, baselines, policy_logits, retain
from models.pretrain_config import PretrainArgs


@dataclass(frozen=True)
class OnlineBatch:
    """Random draws of one online meta-batch: tasks, action uniforms, reward noise, slips.

    ``preferred[:, t]`` is the question preferred when answer t + 1 is given (it changes along
    the way when the feedback model has a hazard); ``slipped[:, t]`` whether that answer says the
    opposite of what the participant means. ``weights`` are each task's likelihood ratio between
    the model and the draws when changes of mind were oversampled (else ones), so that weighted
    means estimate the model's own expectations.
    """

    preferred: torch.Tensor  # (B, T) long
    uniforms: torch.Tensor  # (B, T)
    noise: torch.Tensor  # (B, T)
    slipped: torch.Tensor  # (B, T) bool
    weights: torch.Tensor | None = None  # (B,)


@dataclass
class Rollout:
    """The log-probability tables after 0..T answers, the actions taken and the rewards their
    answers gave (empty for a rollout built by hand)."""

    log_probs: list[torch.Tensor]  # T + 1 tensors (B, K)
    actions: torch.Tensor  # (B, T) long
    rewards: torch.Tensor = field(default_factory=lambda: torch.empty(0, dtype=DTYPE))  # (B, T)


def sample_online_batch(args: PretrainArgs, rng: np.random.Generator) -> OnlineBatch:
    """Draw tasks and the uniforms, noise and slips that will decide actions and rewards.

    Without a feedback model (the paper's Gaussian tasks) exactly the draws of the checkpoints
    trained before issue 19 are made, in the same order, so their configs still reproduce them.
    """
    assert args.tasks_per_batch is not None
    b, t = args.tasks_per_batch, args.horizon
    first = args.tasks.sample_preferred(rng, b)
    uniforms = rng.random((b, t))
    noise = rng.standard_normal((b, t))
    preferred = np.repeat(first[:, None], t, axis=1)
    slipped = np.zeros((b, t), dtype=bool)
    weights = None
    if args.feedback is not None:
        model = args.feedback_model
        slipped = rng.random((b, t)) < model.sample_slips(rng, b)[:, None]
        hazard = min(0.5, model.hazard * args.change_oversampling)
        drawn = replace(model, hazard=hazard)
        for step in range(1, t):
            preferred[:, step] = drawn.change_preference(
                rng, preferred[:, step - 1], args.tasks.prior
            )
        if hazard != model.hazard:
            changes = (preferred[:, 1:] != preferred[:, :-1]).sum(axis=1)
            ratio = changes * math.log(model.hazard / hazard) + (t - 1 - changes) * math.log(
                (1.0 - model.hazard) / (1.0 - hazard)
            )
            weights = torch.as_tensor(np.exp(ratio), dtype=DTYPE)
    return OnlineBatch(
        torch.as_tensor(preferred, dtype=torch.long),
        torch.as_tensor(uniforms, dtype=DTYPE),
        torch.as_tensor(noise, dtype=DTYPE),
        torch.as_tensor(slipped),
        weights,
    )


def online_rollout(
    theta: torch.Tensor,
    layout: Layout,
    obs: torch.Tensor,
    args: PretrainArgs,
    batch: OnlineBatch,
    actions: torch.Tensor | None = None,
) -> Rollout:
    """Run the deployed protocol on every task: T answers, one step of ``args.online_rule`` each.

    Actions are drawn from the current policy with the batch's uniforms unless ``actions`` fixes
    them (re-evaluating the same trajectories at other meta-parameters).
    """
    p = layout.unflatten(theta)
    initial = {name: p[name] for name in PARAM_NAMES}
    net = initial
    damping = p["log_damping"].exp().squeeze() if "log_damping" in p else None
    baseline = baselines(p, args)
    retention_logit = p.get("retention_logit")
    gated = "surprise_step" in p
    remembers = "memory_step" in p
    traces = "trace_step" in p
    memory = torch.zeros(batch.preferred.shape[0], dtype=DTYPE)
    trace = torch.zeros(batch.preferred.shape[0], args.arms, dtype=DTYPE)
    offset = None
    if args.anchor:  # log prior − f_θ₀(x): the start is the prior, whatever θ₀ is
        log_prior = torch.as_tensor(np.log(args.tasks.prior), dtype=DTYPE)
        offset = log_prior - policy_logits(initial, obs)
    model = args.feedback_model
    sigma = math.sqrt(model.variance) if model.kind == "gaussian" else 0.0
    n_arms = args.arms
    arange = torch.arange(n_arms)
    log_probs, taken, rewards = [], [], []
    for t in range(args.horizon + 1):
        logp = torch.log_softmax(policy_logits(net, obs, offset), dim=-1)
        if logp.dim() == 1:
            logp = logp.expand(batch.preferred.shape[0], n_arms)
        log_probs.append(logp)
        if t == args.horizon:
            break
        if actions is None:
            cumulative = torch.cumsum(logp.detach().exp(), dim=-1)
            u = batch.uniforms[:, t : t + 1] * cumulative[:, -1:]
            a = torch.clamp((cumulative <= u).sum(-1), max=n_arms - 1)
        else:
            a = actions[:, t]
        taken.append(a)
        says_yes = (a == batch.preferred[:, t]) != batch.slipped[:, t]
        reward = torch.where(says_yes, model.yes, model.no).to(DTYPE)
        if sigma:
            reward = reward + sigma * batch.noise[:, t]
        rewards.append(reward)
        onehot = (a.unsqueeze(-1) == arange).to(DTYPE)
        pi = logp.exp()
        p_asked = (pi * onehot).sum(-1)
        s = (onehot - pi) * (reward - baseline[t]).unsqueeze(-1)
        if args.online_rule == "natural_expected":
            s = s * p_asked.unsqueeze(-1)
        log_step = p["log_step"][t].expand(s.shape[0])
        if gated:  # models.checkpoints.SurpriseGates, the same arithmetic
            u = (reward - (model.no + p_asked * (model.yes - model.no))).abs()
            u = u / abs(model.yes - model.no)
            log_step = log_step + p["surprise_step"][t] * u
            if remembers:
                log_step = log_step + p["memory_step"][t] * memory
            if traces:  # Checkpoint.trace_parts: u q_a and the others' sum
                asked = (trace * onehot).sum(-1)
                repeated, others = u * asked, trace.sum(-1) - asked
                log_step = (
                    log_step + p["trace_step"][t] * repeated + p["trace_others_step"][t] * others
                )
        net = apply_step(net, obs, s, log_step.exp(), damping, offset)
        if retention_logit is not None:
            z = retention_logit[t]
            if gated:
                z = z + p["surprise_retention"][t] * u
            if traces:
                z = z + p["trace_retention"][t] * repeated + p["trace_others_retention"][t] * others
            rho = torch.sigmoid(z)
            net = retain(net, initial, rho)
            if remembers:  # models.checkpoints.Checkpoint.memory_after
                memory = rho * (memory + u)
            if traces and args.question_trace == "contradiction":
                signed = (reward - (model.no + p_asked * (model.yes - model.no))) / (
                    model.yes - model.no
                )
                contradicted = torch.clamp(trace - signed.unsqueeze(-1), min=0.0)
                trace = rho.unsqueeze(-1) * torch.where(onehot.bool(), contradicted, trace)
            elif traces:  # models.checkpoints.Checkpoint.trace_after
                trace = rho.unsqueeze(-1) * (trace + u.unsqueeze(-1) * onehot)
    return Rollout(log_probs, torch.stack(taken, dim=1), torch.stack(rewards, dim=1).detach())


def filter_beliefs(rollout: Rollout, args: PretrainArgs) -> torch.Tensor:
    """(B, T, K): after answers 1..t + 1 of each task, the exact filter's belief about which
    question is preferred at the next answer (:class:`models.learners.belief.BatchBelief`, for
    the model the tasks answer by) — what the reference reports and C2 approximates.

    The filter needs only the history, so the same actions and rewards give the same beliefs at
    every candidate meta-parameter: computed once per meta-batch, they are constants.
    """
    actions = rollout.actions.numpy()
    rewards = rollout.rewards.numpy()
    n, horizon = actions.shape
    belief = BatchBelief(n, args.arms, args.feedback_model, args.tasks.prior)
    beliefs = np.empty((n, horizon, args.arms))
    for t in range(horizon):
        belief.update(actions[:, t], rewards[:, t])
        beliefs[:, t] = belief.probabilities()
    return torch.as_tensor(beliefs, dtype=DTYPE)


def objective_terms(
    rollout: Rollout,
    batch: OnlineBatch,
    objective: str,
    wrong_penalty: float = 0.0,
    beliefs: torch.Tensor | None = None,
) -> torch.Tensor:
    """(B, T) per-answer objective; column t depends on the actions before it only.

    ``filter``: ``Σ_i b_t(i) log π_t(i)`` after answers 1..T, with ``b_t`` the exact filter's
    belief about the next answer's preference (``beliefs``, :func:`filter_beliefs`). Its
    expectation is the log score of the preference at the next answer (the conditional
    expectation given the history: Rao–Blackwell), so it has the log score's optimum — the
    filter itself, where the function class allows — without the noise of scoring against one
    sampled preference; maximising it minimises the mean KL from the filter to the policy.

    ``log_score``: log π(preferred) after answers 1..T, plus ``wrong_penalty ·
    log(1 − max_{a ≠ preferred} π(a))`` when the penalty is positive: a proper score alone is
    optimised by Bayes-like calibration, which is confidently wrong for about 1 % of
    participants; the extra term charges confident wrong beliefs more than slow right ones.
    ``reward``: the expected reward of answers 1..T, ``Σ_a π_{t−1}(a) μ_a``.
    """
    if objective == "filter":
        if beliefs is None:
            raise ValueError("the filter objective needs the filter's beliefs")
        tables = rollout.log_probs[1:]
        return torch.stack([(beliefs[:, t] * lp).sum(-1) for t, lp in enumerate(tables)], dim=1)
    # The question preferred at answer t, which table t (before it) and t + 1 (after it) judge.
    index = batch.preferred.unsqueeze(-1)
    if objective == "log_score":
        tables = rollout.log_probs[1:]
        terms = torch.stack(
            [lp.gather(-1, index[:, t]).squeeze(-1) for t, lp in enumerate(tables)], dim=1
        )
        if wrong_penalty > 0:
            others = torch.stack(
                [lp.exp().scatter(-1, index[:, t], 0.0).amax(-1) for t, lp in enumerate(tables)],
                dim=1,
            )
            terms = terms + wrong_penalty * torch.log1p(-others.clamp(max=1.0 - 1e-12))
        return terms
    tables = rollout.log_probs[:-1]
    return torch.stack(
        [lp.exp().gather(-1, index[:, t]).squeeze(-1) for t, lp in enumerate(tables)], dim=1
    )


def online_surrogate(
    rollout: Rollout,
    batch: OnlineBatch,
    old: Rollout,
    advantages: torch.Tensor,
    objective: str,
    wrong_penalty: float = 0.0,
    beliefs: torch.Tensor | None = None,
) -> torch.Tensor:
    """Mean per-answer objective plus the score-function term of the sampled actions.

    ``Σ_t f_t + Σ_s (π_s(a_s)/π_s^old(a_s) − 1) Â_s`` with ``Â_s`` the baselined objective of the
    answers after ``s``: its gradient at the old parameters is the unbiased meta-gradient (the
    path through the updates *and* through which questions got asked).
    """
    f = objective_terms(rollout, batch, objective, wrong_penalty, beliefs)
    actions = old.actions.unsqueeze(-1)
    score = torch.stack(
        [
            (lp.gather(-1, actions[:, s]) - old_lp.gather(-1, actions[:, s])).squeeze(-1)
            for s, (lp, old_lp) in enumerate(
                zip(rollout.log_probs[:-1], old.log_probs[:-1], strict=True)
            )
        ],
        dim=1,
    )
    per_task = f.sum(1) + ((score.exp() - 1.0) * advantages).sum(1)
    if batch.weights is not None:  # importance weights of oversampled changes of mind
        per_task = per_task * batch.weights
    return per_task.mean() / f.shape[1]


def online_advantages(f: torch.Tensor) -> torch.Tensor:
    """``Â_s = Σ_{t>s} (f_t − mean f_t)``: what asking question ``a_s`` changed later on."""
    centred = (f - f.mean(0, keepdim=True)).detach()
    # Column t of f (answers 1..T) depends on actions 0..t, so action s affects columns s..T−1.
    return torch.flip(torch.cumsum(torch.flip(centred, [1]), 1), [1])


def mean_kl(new: Sequence[torch.Tensor], old: Sequence[torch.Tensor]) -> torch.Tensor:
    """Mean over tables and tasks of KL(old ‖ new) between categorical log-probabilities."""
    total = [(o.exp() * (o - n)).sum(-1).mean() for n, o in zip(new, old, strict=True)]
    return torch.stack(total).mean()


# Paper mode ---------------------------------------------------------------------------------


@dataclass(frozen=True)
class PaperBatch:
    """Random draws of one paper meta-batch."""

    preferred: torch.Tensor  # (B,)
    train_uniforms: torch.Tensor  # (B, N)
    train_noise: torch.Tensor  # (B, N)
    valid_uniforms: torch.Tensor  # (B, N)
    valid_noise: torch.Tensor  # (B, N)


def sample_paper_batch(args: PretrainArgs, rng: np.random.Generator) -> PaperBatch:
    """Draw tasks and the uniforms/noise of their inner (train) and outer (valid) pulls."""
    assert args.tasks_per_batch is not None
    b, n = args.tasks_per_batch, args.pulls

    def draw(shape: tuple[int, int], normal: bool) -> torch.Tensor:
        values = rng.standard_normal(shape) if normal else rng.random(shape)
        return torch.as_tensor(values, dtype=DTYPE)

    preferred = torch.as_tensor(args.tasks.sample_preferred(rng, b), dtype=torch.long)
    return PaperBatch(
        preferred, draw((b, n), False), draw((b, n), True), draw((b, n), False), draw((b, n), True)
    )


def pull(
    logp: torch.Tensor,
    uniforms: torch.Tensor,
    noise: torch.Tensor,
    preferred: torch.Tensor,
    sigma: float,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Actions (B, N) drawn from ``logp`` (B, K) with the uniforms, and their rewards."""
    cumulative = torch.cumsum(logp.detach().exp(), dim=-1).unsqueeze(1)  # (B, 1, K)
    u = uniforms.unsqueeze(-1) * cumulative[..., -1:]
    actions = torch.clamp((cumulative <= u).sum(-1), max=logp.shape[-1] - 1)
    rewards = (actions == preferred.unsqueeze(-1)).to(DTYPE) + sigma * noise
    return actions, rewards


def paper_advantages(rewards: torch.Tensor, discount: float) -> torch.Tensor:
    """Discounted returns over the pulls, minus the per-pull mean over tasks, normalised per task.

    The batch mean at each pull is the baseline (every task's pre-update policy is the same, so it
    estimates the expected return there); normalising per task as the reference code does.
    """
    returns = torch.zeros_like(rewards)
    running = torch.zeros_like(rewards[:, 0])
    for t in range(rewards.shape[1] - 1, -1, -1):
        running = rewards[:, t] + discount * running
        returns[:, t] = running
    advantages = returns - returns.mean(0, keepdim=True)
    centred = advantages - advantages.mean(1, keepdim=True)
    return centred / (centred.std(1, keepdim=True) + 1e-8)


@dataclass
class PaperRollout:
    """Pre- and post-adaptation log-probabilities and the pulls they were computed from."""

    log_probs: list[torch.Tensor]  # [pre (B, K), adapted (B, K)]
    train_actions: torch.Tensor
    train_advantages: torch.Tensor
    valid_actions: torch.Tensor
    valid_advantages: torch.Tensor


def paper_rollout(
    theta: torch.Tensor,
    layout: Layout,
    obs: torch.Tensor,
    args: PretrainArgs,
    batch: PaperBatch,
    fixed: PaperRollout | None = None,
    first_order: bool = False,
) -> PaperRollout:
    """One inner policy-gradient step per task on its train pulls, then the valid pulls.

    The inner gradient ``Jᵀ mean_t (e_{a_t} − π) Â_t`` is exact for a constant observation (every
    pull sees the same π). With ``fixed``, the pulls (and their advantages) of an earlier rollout
    are reused, as MAML-TRPO re-adapts on the same train episodes for every candidate step.
    ``first_order`` treats the inner step as a constant (first-order MAML; the tests use it to
    show the second-order terms matter).
    """
    net = layout.unflatten(theta)
    sigma = math.sqrt(args.variance)
    b = batch.preferred.shape[0]
    logp = torch.log_softmax(policy_logits(net, obs), dim=-1).expand(b, args.arms)
    if fixed is None:
        actions, rewards = pull(
            logp, batch.train_uniforms, batch.train_noise, batch.preferred, sigma
        )
        advantages = paper_advantages(rewards, args.discount)
    else:
        actions, advantages = fixed.train_actions, fixed.train_advantages
    onehot = (actions.unsqueeze(-1) == torch.arange(args.arms)).to(DTYPE)  # (B, N, K)
    s = ((onehot - logp.exp().unsqueeze(1)) * advantages.unsqueeze(-1)).mean(1)
    adapted = apply_step(net, obs, s, torch.full((b,), args.fast_lr, dtype=DTYPE), None)
    if first_order:
        adapted = {k: net[k] + (adapted[k] - net[k]).detach() for k in adapted}
    adapted_logp = torch.log_softmax(policy_logits(adapted, obs), dim=-1)
    if fixed is None:
        valid_actions, valid_rewards = pull(
            adapted_logp, batch.valid_uniforms, batch.valid_noise, batch.preferred, sigma
        )
        valid_advantages = paper_advantages(valid_rewards, args.discount)
    else:
        valid_actions, valid_advantages = fixed.valid_actions, fixed.valid_advantages
    return PaperRollout([logp, adapted_logp], actions, advantages, valid_actions, valid_advantages)


def paper_surrogate(rollout: PaperRollout, old: PaperRollout) -> torch.Tensor:
    """Mean importance-weighted advantage of the valid pulls under the adapted policy."""
    new_lp = rollout.log_probs[1].gather(-1, old.valid_actions)
    old_lp = old.log_probs[1].gather(-1, old.valid_actions)
    return ((new_lp - old_lp).exp() * old.valid_advantages).mean()


def online_surrogate_and_kl(
    layout: Layout,
    obs: torch.Tensor,
    args: PretrainArgs,
    batch: OnlineBatch,
    old: Rollout,
    advantages: torch.Tensor,
    theta: torch.Tensor,
    beliefs: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Online surrogate and KL at ``theta`` on the old trajectories (for :func:`trpo_step`)."""
    new = online_rollout(theta, layout, obs, args, batch, actions=old.actions)
    value = online_surrogate(
        new, batch, old, advantages, args.objective, args.wrong_penalty, beliefs
    )
    return value, mean_kl(new.log_probs, old.log_probs)


def paper_surrogate_and_kl(
    layout: Layout,
    obs: torch.Tensor,
    args: PretrainArgs,
    batch: PaperBatch,
    old: PaperRollout,
    theta: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Paper surrogate and KL (pre- and post-adaptation) at ``theta`` on the old pulls."""
    new = paper_rollout(theta, layout, obs, args, batch, fixed=old)
    return paper_surrogate(new, old), mean_kl(new.log_probs, old.log_probs)
