"""The C2 policy and its one-answer update in torch, and the flat meta-parameter vector.

A differentiable copy of :mod:`models.learners.mlp_policy` (a test checks they agree): MAML needs
gradients *through* the update, and TRPO works on one flat vector holding the network and, in
``online`` mode, the update's own meta-learned step sizes, damping and baselines.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from models.checkpoints import TRACE_GATES
from models.learners.mlp_policy import init_params, param_shapes
from models.pretrain_config import PretrainArgs

DTYPE = torch.float64


Net = dict[str, torch.Tensor]


def policy_logits(net: Net, obs: torch.Tensor, offset: torch.Tensor | None = None) -> torch.Tensor:
    """Logits of the policy network (batched over leading dimensions of the weights), plus an
    anchored policy's ``offset`` (:func:`models.learners.mlp_policy.anchor_offset`)."""
    h = torch.tanh(net["W1"] @ obs + net["b1"])
    logits = (net["W2"] @ h.unsqueeze(-1)).squeeze(-1) + net["b2"]
    return logits if offset is None else logits + offset


def retain(net: Net, initial: Net, retention: torch.Tensor) -> Net:
    """The forgetting step ``θ₀ + ρ (θ − θ₀)`` (:func:`models.learners.mlp_policy.retain`),
    ``retention`` a scalar or one per task."""
    moved = {}
    for name, value in net.items():
        gate = retention.reshape(retention.shape + (1,) * (value.dim() - retention.dim()))
        moved[name] = initial[name] + gate * (value - initial[name])
    return moved


def apply_step(
    net: Net,
    obs: torch.Tensor,
    s: torch.Tensor,
    step_size: torch.Tensor,
    damping: torch.Tensor | None,
    offset: torch.Tensor | None = None,
) -> Net:
    """``θ + α Jᵀ y`` with ``y = (M JJᵀ + λI)⁻¹ s`` (natural) or ``y = s`` (``damping=None``).

    ``s`` is the logit-space direction, e.g. ``(e_a − π)(r − b)`` for one answer; differentiable
    in every argument, so MAML gets exact second-order meta-gradients.
    """
    h = torch.tanh(net["W1"] @ obs + net["b1"])
    n_arms = s.shape[-1]
    eye = torch.eye(n_arms, dtype=s.dtype)
    if damping is not None:
        logits = (net["W2"] @ h.unsqueeze(-1)).squeeze(-1) + net["b2"]
        if offset is not None:
            logits = logits + offset
        pi = torch.softmax(logits, dim=-1)
        fisher = pi.unsqueeze(-1) * (eye - pi.unsqueeze(-2))
        v = net["W2"] * (1.0 - h * h).unsqueeze(-2)
        gram = (h * h).sum(-1).add(1.0)[..., None, None] * eye + (obs @ obs + 1.0) * (
            v @ v.transpose(-1, -2)
        )
        y = torch.linalg.solve(fisher @ gram + damping * eye, s.unsqueeze(-1)).squeeze(-1)
    else:
        y = s
    y = y * step_size.unsqueeze(-1)
    d_pre = (net["W2"].transpose(-1, -2) @ y.unsqueeze(-1)).squeeze(-1) * (1.0 - h * h)
    return {
        "W1": net["W1"] + d_pre.unsqueeze(-1) * obs,
        "b1": net["b1"] + d_pre,
        "W2": net["W2"] + y.unsqueeze(-1) * h.unsqueeze(-2),
        "b2": net["b2"] + y,
    }


# --------------------------------------------------------------------------------------------
# Flat parameter vectors (TRPO works on one vector).


@dataclass(frozen=True)
class Layout:
    """Names and shapes of the meta-parameters packed in one flat vector."""

    shapes: dict[str, tuple[int, ...]]

    @property
    def size(self) -> int:
        """Length of the flat vector."""
        return sum(math.prod(s) for s in self.shapes.values())

    def unflatten(self, theta: torch.Tensor) -> dict[str, torch.Tensor]:
        """Views of ``theta`` with each parameter's shape."""
        out, offset = {}, 0
        for name, shape in self.shapes.items():
            n = math.prod(shape)
            out[name] = theta[offset : offset + n].reshape(shape)
            offset += n
        return out

    def flatten(self, values: dict[str, np.ndarray]) -> torch.Tensor:
        """Pack arrays into one float64 vector in layout order."""
        return torch.cat(
            [
                torch.as_tensor(np.asarray(values[n], dtype=np.float64)).reshape(-1)
                for n in self.shapes
            ]
        )


def layout_for(args: PretrainArgs, obs_dim: int) -> Layout:
    """The meta-parameters of ``args.mode``: the network, plus the online update's own."""
    shapes = dict(param_shapes(obs_dim, args.hidden, args.arms))
    if args.mode == "online":
        baseline = "baseline_logit" if args.bounded_baseline else "baseline"
        shapes.update({"log_step": (args.horizon,), "log_damping": (1,), baseline: (args.horizon,)})
        if args.online_rule == "gradient":
            del shapes["log_damping"]
        if args.forgetting:
            shapes["retention_logit"] = (args.horizon,)
        if args.surprise_gates:
            shapes.update({"surprise_step": (args.horizon,), "surprise_retention": (args.horizon,)})
        if args.surprise_memory:
            shapes["memory_step"] = (args.horizon,)
        if args.question_trace:
            shapes.update({f"trace_{name}": (args.horizon,) for name in TRACE_GATES})
    return Layout(shapes)


def initial_theta(args: PretrainArgs, layout: Layout, rng: np.random.Generator) -> torch.Tensor:
    """Random network weights (as ``random_init`` draws them) and the online update's start."""
    obs_dim = layout.shapes["W1"][1]
    values: dict[str, np.ndarray] = dict(init_params(rng, obs_dim, args.hidden, args.arms))
    if args.mode == "online":
        step, baseline = initial_update(args)
        values["log_step"] = np.full(args.horizon, math.log(step))
        if "log_damping" in layout.shapes:
            values["log_damping"] = np.array([math.log(args.init_damping)])
        if args.bounded_baseline:  # the same start, as a logistic between no and yes
            model = args.feedback_model
            share = (baseline - model.no) / (model.yes - model.no)
            values["baseline_logit"] = np.full(args.horizon, math.log(share / (1.0 - share)))
        else:
            values["baseline"] = np.full(args.horizon, baseline)
        if "retention_logit" in layout.shapes:
            rho = initial_retention(args)
            values["retention_logit"] = np.full(args.horizon, math.log(rho / (1.0 - rho)))
        # Start as if there were no gates.
        gates = ("surprise_step", "surprise_retention", "memory_step")
        for name in gates + tuple(f"trace_{name}" for name in TRACE_GATES):
            if name in layout.shapes:
                values[name] = np.zeros(layout.shapes[name])
    return layout.flatten(values)


def initial_retention(args: PretrainArgs) -> float:
    """The forgetting step's starting ρ: the factor by which the exact filter's switch step
    shrinks a belief toward the prior, ``1 − h K/(K − 1)`` for hazard ``h`` (at most .99, so
    a model without a hazard can still learn to forget a little)."""
    hazard = args.feedback_model.hazard
    return min(0.99, 1.0 - hazard * args.arms / (args.arms - 1))


def initial_update(args: PretrainArgs) -> tuple[float, float]:
    """The online update's starting step size and baseline.

    ``natural_expected`` starts as the exact Bayesian update it can express: step
    ``(μ₁ − μ₀)/σ²`` and baseline ``(μ₁ + μ₀)/2`` (see :mod:`models.learners.mlp_policy`), so
    meta-training begins at the posterior and learns where to depart from it. The score-function
    rules start at ``init_step_size`` (1 unless given) and the expected reward of an answer to a
    uniformly chosen question.
    """
    tasks = args.tasks
    model = args.feedback_model
    if args.online_rule == "natural_expected" and model.kind == "binary":
        # The exact update for a participant who slips at the prior's mean rate: a yes adds, a
        # no subtracts, log((1 − ε)/ε) on the asked question's logit.
        slip = min(max(float(model.slip_values @ model.slip_prior), 0.01), 0.49)
        evidence = math.log((1.0 - slip) / slip)
        step = 2.0 * evidence / (model.yes - model.no)
        start = args.init_step_size if args.init_step_size is not None else step
        return start, (model.yes + model.no) / 2
    if args.online_rule == "natural_expected":
        bayes_step = (tasks.mu_preferred - tasks.mu_other) / tasks.variance
        step = args.init_step_size if args.init_step_size is not None else bayes_step
        return step, (tasks.mu_preferred + tasks.mu_other) / 2
    step = args.init_step_size if args.init_step_size is not None else 1.0
    if model.kind == "binary":
        return step, (model.yes + (args.arms - 1) * model.no) / args.arms
    return step, (tasks.mu_preferred + (args.arms - 1) * tasks.mu_other) / args.arms


def baselines(values: dict[str, torch.Tensor], args: PretrainArgs) -> torch.Tensor:
    """The online update's reward baselines b_1..b_T from the meta-parameters: free, or between
    the rewards of no and yes when ``args.bounded_baseline``."""
    if "baseline_logit" not in values:
        return values["baseline"]
    model = args.feedback_model
    return model.no + (model.yes - model.no) * torch.sigmoid(values["baseline_logit"])
