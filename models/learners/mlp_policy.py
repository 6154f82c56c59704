"""The C2 policy network and its one-answer update, in numpy, batched over leading dimensions.

The policy is an MLP with one hidden layer over a fixed observation ``x``, one per category::

    h = tanh(W1 x + b1)        logits = W2 h + b2        π = softmax(logits)

Because ``x`` never changes, the network is "just" a parametrisation of a distribution over K
questions; what matters is how that parametrisation moves under a gradient step, which is what
meta-training shapes. ``tanh`` (not ReLU) and a non-zero ``x`` keep every weight on the gradient
path: with a zero or constant-one observation and ReLU units, only the output bias of the
reference MAML code ever learned.

One answer ``(a, r)`` gives a policy-gradient direction ``g = Jᵀ s`` with ``J = ∂logits/∂θ``
and a logit-space direction ``s`` built from the raw reward minus a baseline ``b`` (the normalised
advantage of a single answer is always zero). Two estimators of the gradient:

- the score function of the asked question, ``s = (e_a − π)(r − b)`` (REINFORCE);
- the *expected* policy gradient ``∇ Σ_k π_k Q̂_k`` with ``Q̂_a = r`` for the asked question and
  ``Q̂_k = b`` for the others, which is ``s = π_a (e_a − π)(r − b)``: it does not divide the
  answer by the chance of having asked it.

and two steps:

- natural: ``θ ← θ + α (F + λI)⁻¹ g`` with ``F = Jᵀ (diag π − ππᵀ) J``, the Fisher information
  of the softmax policy. ``F`` has rank < K, so by the push-through identity
  ``(JᵀMJ + λI)⁻¹ Jᵀ = Jᵀ (M JJᵀ + λI)⁻¹`` the step costs one K × K solve, and ``JJᵀ`` has a
  closed form for this network (see :func:`logit_gram`). A natural step moves the
  *distribution* by an amount that does not depend on how the weights happen to be scaled,
  which is why a single answer can move it far enough.
- plain: ``θ ← θ + α g``.

The three rules a checkpoint can name:

``natural_expected`` (C2's default)
    Natural step on the expected gradient. With ``λ → 0`` it adds ``α (r − b)`` to the asked
    question's logit and leaves the others' — the form of the exact Bayesian update, which adds
    ``(μ₁ − μ₀)/σ² · (r − (μ₁ + μ₀)/2)``. Meta-training learns ``α_t``, ``b_t`` and ``λ``;
    a step smaller than Bayes's is a *tempered* posterior, the lever that trades a few tenths of
    an answer for far fewer confidently wrong beliefs (docs/engine.md).
``natural``
    Natural step on the score function: it adds ``α (r − b)/π_a``, so a surprising answer to an
    unlikely question moves the belief most — the source of this rule's confident mistakes.
``gradient``
    Plain step on the score function, used by ``paper``-mode checkpoints (the paper's inner loop).

Everything broadcasts over leading dimensions, so the learner (one participant) and the simulations
(thousands at once) run the same code. The torch copy used in meta-training lives in
``models/pretrain.py``; a test checks the two agree.
"""

from __future__ import annotations

from typing import Literal, get_args

import numpy as np

Params = dict[str, np.ndarray]
"""The network's weights: ``W1`` (…, H, D), ``b1`` (…, H), ``W2`` (…, K, H), ``b2`` (…, K)."""

PARAM_NAMES: tuple[str, str, str, str] = ("W1", "b1", "W2", "b2")
"""The network's weight arrays, in a fixed order (flattening, state dicts, checkpoints)."""

UpdateRule = Literal["natural_expected", "natural", "gradient"]

UPDATE_RULES: tuple[str, ...] = get_args(UpdateRule)
"""Every rule a checkpoint may name (see the module docstring), read off :data:`UpdateRule`."""

HIDDEN_UNITS = 100
"""The issue's network: one hidden layer of 100 units."""


def param_shapes(obs_dim: int, hidden: int, n_arms: int) -> dict[str, tuple[int, ...]]:
    """The shape of each weight array for one network (no batch dimensions)."""
    return {
        "W1": (hidden, obs_dim),
        "b1": (hidden,),
        "W2": (n_arms, hidden),
        "b2": (n_arms,),
    }


def init_params(rng: np.random.Generator, obs_dim: int, hidden: int, n_arms: int) -> Params:
    """Draw a network's weights as torch's ``nn.Linear`` does: U(−1/√fan_in, 1/√fan_in).

    Meta-training starts from this draw and ``random_init`` learners use it, so the Appendix's
    "random initialisation" comparison starts where meta-training started.
    """
    params: Params = {}
    for name, shape in param_shapes(obs_dim, hidden, n_arms).items():
        fan_in = obs_dim if name in ("W1", "b1") else hidden
        bound = 1.0 / np.sqrt(fan_in)
        params[name] = rng.uniform(-bound, bound, size=shape)
    return params


def hidden_and_logits(
    params: Params, obs: np.ndarray, offset: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Return the hidden activations ``h`` (…, H) and the logits (…, K), plus ``offset`` (K,)
    when the checkpoint anchors its policy at the prior (:func:`anchor_offset`)."""
    h = np.tanh(params["W1"] @ obs + params["b1"])
    logits = (params["W2"] @ h[..., None])[..., 0] + params["b2"]
    return h, logits if offset is None else logits + offset


def softmax(logits: np.ndarray) -> np.ndarray:
    """Softmax over the last axis, shifted by the maximum so no exponent overflows."""
    z = np.exp(logits - logits.max(axis=-1, keepdims=True))
    return z / z.sum(axis=-1, keepdims=True)


def probabilities(params: Params, obs: np.ndarray, offset: np.ndarray | None = None) -> np.ndarray:
    """The policy π over the K questions (…, K), float64."""
    return softmax(hidden_and_logits(params, obs, offset)[1])


def anchor_offset(prior: np.ndarray, initial: Params, obs: np.ndarray) -> np.ndarray:
    """The constant ``log prior − f_θ₀(x)`` an anchored policy adds to its network's logits.

    With it the logits are ``log prior + f_θ(x) − f_θ₀(x)``: at the starting weights θ₀ the
    policy *is* the task prior, exactly and by construction (a uniform prior gives a uniform first
    question, whatever the weights), and meta-training can shape only how the policy moves. The
    offset is computed once per learner from its starting weights, so it costs nothing per answer.
    """
    values = np.asarray(prior, dtype=np.float64)
    if not np.all(values > 0):
        raise ValueError("an anchored policy needs a prior above 0 for every question")
    return np.log(values) - hidden_and_logits(initial, obs)[1]


def retain(params: Params, initial: Params, retention: np.ndarray | float) -> Params:
    """``θ₀ + ρ (θ − θ₀)``: the forgetting step that moves the weights back toward the start
    (``retention`` a number, or one per batch row).

    An exact filter with a hazard of changed preference mixes its belief toward the prior after
    every answer, which caps how sure it gets and so keeps it able to leave a belief the next
    answers contradict; this step is that mixing in the network's weights (docs/engine.md, "A
    belief that can be left"). ρ = 1 forgets nothing.
    """
    rho = np.asarray(retention, dtype=np.float64)
    moved = {}
    for name, value in params.items():
        gate = rho.reshape(rho.shape + (1,) * (np.ndim(value) - rho.ndim)) if rho.ndim else rho
        moved[name] = initial[name] + gate * (value - initial[name])
    return moved


def surprise(
    p_asked: np.ndarray | float, reward: np.ndarray | float, yes: float, no: float
) -> np.ndarray:
    """How unexpected an answer was to the policy itself, in [0, 1] for yes/no answers:
    ``|r − r̂| / |yes − no|`` with ``r̂ = no + π_a (yes − no)``, the reward the policy expected if
    its probability of the asked question were its belief that the question is preferred. A
    "no" to the question it is sure of, or a "yes" to one it had written off, is a surprise near 1.
    """
    expected = no + np.asarray(p_asked, dtype=np.float64) * (yes - no)
    return np.abs(np.asarray(reward, dtype=np.float64) - expected) / abs(yes - no)


def logit_gram(params: Params, obs: np.ndarray, h: np.ndarray) -> np.ndarray:
    """``JJᵀ`` (…, K, K) for ``J = ∂logits/∂θ``, in closed form.

    ``∂logit_k/∂W2[k',:] = δ_kk' h``, ``∂logit_k/∂b2 = e_k`` and, through the hidden layer,
    ``∂logit_k/∂(W1, b1) = (W2[k] ⊙ (1 − h²)) ⊗ (x, 1)``, hence
    ``JJᵀ = (|h|² + 1) I + (|x|² + 1) · V Vᵀ`` with ``V = W2 ⊙ (1 − h²)``.
    """
    n_arms = params["b2"].shape[-1]
    v = params["W2"] * (1.0 - h * h)[..., None, :]
    outer = v @ np.swapaxes(v, -1, -2)
    diagonal = (np.sum(h * h, axis=-1) + 1.0)[..., None, None] * np.eye(n_arms)
    return diagonal + (float(obs @ obs) + 1.0) * outer


def update_params(
    params: Params,
    obs: np.ndarray,
    action: np.ndarray,
    reward: np.ndarray,
    *,
    step_size: np.ndarray | float,
    baseline: np.ndarray | float,
    damping: float,
    rule: UpdateRule,
    offset: np.ndarray | None = None,
) -> Params:
    """Return the weights after one answer (``action``, ``reward``); ``params`` is not changed.

    ``action`` and ``reward`` have the batch shape of ``params`` (or are scalars for one network);
    ``offset`` is an anchored policy's (:func:`anchor_offset`).
    """
    h, logits = hidden_and_logits(params, obs, offset)
    pi = softmax(logits)
    n_arms = pi.shape[-1]
    onehot = np.asarray(action)[..., None] == np.arange(n_arms)
    advantage = np.asarray(reward, dtype=np.float64) - baseline
    if rule not in UPDATE_RULES:
        raise ValueError(f"unknown update rule {rule!r}: use one of {', '.join(UPDATE_RULES)}")
    s = (onehot - pi) * advantage[..., None]
    if rule == "natural_expected":
        s = s * np.sum(pi * onehot, axis=-1, keepdims=True)
    if rule != "gradient":
        fisher = pi[..., :, None] * (np.eye(n_arms) - pi[..., None, :])  # diag π − ππᵀ
        system = fisher @ logit_gram(params, obs, h) + damping * np.eye(n_arms)
        y = np.linalg.solve(system, s[..., None])[..., 0]
    else:
        y = s
    y = y * np.asarray(step_size, dtype=np.float64)[..., None]
    # θ += Jᵀ y, written out per weight array.
    d_pre = (np.swapaxes(params["W2"], -1, -2) @ y[..., None])[..., 0] * (1.0 - h * h)
    return {
        "W1": params["W1"] + d_pre[..., :, None] * obs,
        "b1": params["b1"] + d_pre,
        "W2": params["W2"] + y[..., :, None] * h[..., None, :],
        "b2": params["b2"] + y,
    }
