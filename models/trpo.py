"""The TRPO outer step of MAML-TRPO: conjugate gradient on the KL's curvature, then a line search.

As pytorch-maml-rl's ``MAMLTRPO`` does it (Schulman et al. 2015): the gradient ``g`` of the
surrogate, conjugate gradient on the Hessian-vector product of the mean KL between the old and new
policies, the step scaled so the quadratic KL model equals max-KL, and a backtracking line search
that accepts only a step that improves the surrogate *and* keeps the measured KL within bounds.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol

import torch


class TrpoSettings(Protocol):
    """The step's settings (``PretrainArgs`` has them)."""

    max_kl: float
    cg_iterations: int
    cg_damping: float
    ls_steps: int
    ls_backtrack: float


def conjugate_gradient(
    hvp: Callable[[torch.Tensor], torch.Tensor], b: torch.Tensor, iterations: int
) -> torch.Tensor:
    """Approximately solve ``H x = b`` (H symmetric positive definite) by conjugate gradient."""
    x = torch.zeros_like(b)
    r = b.clone()
    p = b.clone()
    rr = r @ r
    for _ in range(iterations):
        if rr < 1e-20:
            break
        hp = hvp(p)
        alpha = rr / (p @ hp)
        x = x + alpha * p
        r = r - alpha * hp
        rr_new = r @ r
        p = r + (rr_new / rr) * p
        rr = rr_new
    return x


@dataclass
class StepResult:
    """What one TRPO step did."""

    objective: float
    improvement: float
    kl: float
    accepted: bool
    backtracks: int


def trpo_step(
    theta: torch.Tensor,
    surrogate: Callable[[torch.Tensor], tuple[torch.Tensor, torch.Tensor]],
    args: TrpoSettings,
) -> tuple[torch.Tensor, StepResult]:
    """One TRPO meta-update of ``theta``.

    ``surrogate(θ)`` returns (objective to maximise, mean KL from the old policies) on fixed
    draws. The step is the CG solution of ``(H + cg_damping I) x = g`` scaled so that
    ``½ sᵀHs = max_kl``; the line search accepts the first of ``ls_steps`` shrinking steps with a
    positive improvement and a KL ≤ ``max_kl``, else keeps ``theta``.
    """
    theta = theta.detach().requires_grad_(True)
    value, kl = surrogate(theta)
    grad = torch.autograd.grad(value, theta, retain_graph=True)[0]
    kl_grad = torch.autograd.grad(kl, theta, create_graph=True)[0]

    def hvp(v: torch.Tensor) -> torch.Tensor:
        hv = torch.autograd.grad(kl_grad @ v, theta, retain_graph=True)[0]
        return hv + args.cg_damping * v

    direction = conjugate_gradient(hvp, grad.detach(), args.cg_iterations)
    shs = 0.5 * (direction @ hvp(direction))
    old_value = float(value.detach())
    base = theta.detach()
    if not torch.isfinite(shs) or shs <= 0:
        return base, StepResult(old_value, 0.0, 0.0, False, 0)
    full_step = direction * torch.sqrt(args.max_kl / shs)
    with torch.no_grad():
        for k in range(args.ls_steps):
            candidate = base + (args.ls_backtrack**k) * full_step
            new_value, new_kl = surrogate(candidate)
            improvement = float(new_value) - old_value
            if improvement > 0 and float(new_kl) <= args.max_kl:
                return candidate, StepResult(old_value, improvement, float(new_kl), True, k)
    return base, StepResult(old_value, 0.0, 0.0, False, args.ls_steps)
