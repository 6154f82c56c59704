"""The arguments of one meta-training run, with their defaults for each mode.

Kept apart from the training code so the command line can validate arguments (and the inner
loops can read them) without the training loop. Saved as every checkpoint's config.json.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any

from models.checkpoints import GENERIC, TRACE_KINDS
from models.feedback import FeedbackModel
from models.learners.mlp_policy import HIDDEN_UNITS, UPDATE_RULES
from models.tasks import DEFAULT_VARIANCE, TaskDistribution, check_prior

WRONG_LIMIT = 0.0095
"""Model selection keeps only checkpoints whose validation ``wrong_95`` is at most this."""

CALIBRATION_LIMIT = 0.0075
"""Calibration keeps the largest step scale whose ``wrong_95`` is at most this: the 1 % a lab can
accept of confidently wrong replies, less three standard errors of a 1 % rate measured on the
20,000 calibration participants (3 · √(.01 · .99 / 20000) ≈ .0021, so .0079), rounded down, so
the true rate stays below 1 %."""

OBJECTIVES = ("log_score", "reward", "filter")
"""``online`` meta-objectives (:func:`models.inner_loops.objective_terms`)."""
SELECTIONS = ("answers", "log_score", "filter")
"""How validation picks the snapshot (:attr:`PretrainArgs.selection`)."""


def default_meta_batches(mode: str, online_rule: str) -> int:
    """Outer steps when none are given: the paper's 200 in ``paper`` mode; in ``online`` mode 60
    for ``natural_expected``, which starts at the Bayes update (its validations level off within
    about 50 steps), and 150 for the score-function rules, which start far from it."""
    if mode != "online":
        return 200
    return 60 if online_rule == "natural_expected" else 150


@dataclass
class PretrainArgs:
    """Arguments of one meta-training run (saved as the checkpoint's config.json)."""

    category: str = GENERIC
    """Category name; it fixes the observation vector (``generic`` for any category with K)."""
    arms: int = 4
    """K, the number of questions."""
    mode: str = "online"
    """``online`` (deployed protocol as inner loop) or ``paper`` (the paper's configuration)."""
    seed: int = 0
    """Seeds every random draw (initialisation, tasks, actions, rewards, validation)."""
    objective: str = "log_score"
    """``online`` only: ``log_score`` (log π(preferred) after each answer), ``filter`` (the same
    score taken in expectation under the exact filter's belief about the next answer's
    preference: the same optimum with far less noise, issue 36) or ``reward``."""
    wrong_penalty: float = 0.0
    """``online``, ``log_score`` only: weight of ``log(1 − max wrong π)`` in the objective."""
    online_rule: str = "natural_expected"
    """``online`` only: the one-answer update (``models.learners.mlp_policy.UPDATE_RULES``)."""
    preferred_prior: tuple[float, ...] | None = None
    """Prior over which question is preferred (uniform when unset)."""
    variance: float = DEFAULT_VARIANCE
    """σ² of the simulated rewards."""
    horizon: int = 12
    """``online``: answers per task (the protocol's 12 adaptation iterations)."""
    meta_batches: int | None = None
    """Outer TRPO steps (unset: :func:`default_meta_batches`)."""
    tasks_per_batch: int | None = None
    """Tasks per meta-batch (online 200, paper 40 when unset)."""
    pulls: int = 20
    """``paper``: pulls per task in the inner and in the validation batch."""
    fast_lr: float = 0.5
    """``paper``: step size of the inner policy-gradient step."""
    discount: float = 0.95
    """``paper``: discount of the returns over the pulls."""
    max_kl: float = 1e-2
    """TRPO trust-region size δ (mean KL per policy)."""
    cg_iterations: int = 10
    """Conjugate-gradient iterations for the natural direction."""
    cg_damping: float = 1e-5
    """Damping added to the KL Hessian in conjugate gradient."""
    ls_steps: int = 15
    """Backtracking line-search steps."""
    ls_backtrack: float = 0.8
    """Line-search shrink factor."""
    hidden: int = HIDDEN_UNITS
    """Hidden units of the policy network."""
    init_step_size: float | None = None
    """``online``: starting value of every meta-learned step size (unset: the rule's own start,
    see :func:`models.meta_torch.initial_update`)."""
    init_damping: float = 0.1
    """``online``: starting value of the meta-learned damping λ."""
    validate_every: int = 5
    """``online``: meta-batches between validations (model selection)."""
    validation_participants: int = 10000
    """Simulated participants per validation."""
    wrong_limit: float = WRONG_LIMIT
    """Model selection: the largest acceptable validation ``wrong_95``."""
    calibrate: bool = True
    """``online``: after selection, scale the step sizes down until ``wrong_95`` is within
    ``calibration_limit`` (see :func:`models.pretrain.calibrate_step_scale`)."""
    calibration_participants: int = 20000
    """Simulated participants per calibration trial (a seed of their own)."""
    calibration_limit: float = CALIBRATION_LIMIT
    """Calibration: the largest acceptable ``wrong_95``."""
    evaluation_participants: int = 20000
    """Simulated participants of the final evaluation written to metrics.json."""
    feedback: dict[str, Any] | None = None
    """``online``: the feedback model the tasks answer by (:meth:`FeedbackModel.to_json`); unset:
    the paper's Gaussian rewards with ``variance`` (every checkpoint from before issue 19)."""
    anchor: bool = False
    """``online``: anchor the policy at the task prior, so it starts there exactly
    (:func:`models.learners.mlp_policy.anchor_offset`). Off in the configs of older checkpoints,
    which these defaults reproduce; the command line turns it on."""
    forgetting: bool = False
    """``online``: meta-learn a forgetting step ρ_t after each answer
    (:func:`models.learners.mlp_policy.retain`); the command line turns it on."""
    surprise_gates: bool = False
    """``online``, with ``forgetting``: let each answer's surprise scale its step and the
    forgetting after it (:class:`models.checkpoints.SurpriseGates`); the command line turns it on
    with forgetting."""
    change_oversampling: float = 1.0
    """``online``, models with a hazard: draw the training tasks' changes of mind at this many
    times the model's hazard (at most .5) and weight each task by its likelihood ratio, so the
    meta-objective stays the model's own while C2 sees more changes to learn recovering from
    (importance sampling; 1: draw by the model)."""
    surprise_memory: bool = False
    """``online``, with ``surprise_gates``: let the gates also see the sum of the surprises before
    each answer (:class:`models.checkpoints.SurpriseGates`), so a participant who contradicted
    the policy before gets evidence weighed like a slipper's; the command line turns it on with
    the gates (issue 36)."""
    question_trace: str | None = None
    """``online``, with ``surprise_gates``: keep one trace per question — of every surprise
    (``surprise``) or of contradictions net of confirmations (``contradiction``) — and let the
    gates see a surprise on a question that surprised before (a change of mind) apart from the
    trace on the others (slips) (:class:`models.checkpoints.SurpriseGates`, issue 36); its
    coefficients start at zero, so training starts from the gates without it. None: no trace."""
    bounded_baseline: bool = False
    """``online``, yes/no answers: keep every reward baseline strictly between the rewards of no
    and yes (meta-learned through a logistic), so a yes can never lower the asked question's
    probability nor a no raise it; the command line turns it on for yes/no models."""
    selection: str = "answers"
    """``online``: how validation picks the snapshot. ``answers``: the fewest answers to 95 %
    within the wrong-belief limit, then calibrated (the paper's Gaussian model); ``log_score``:
    the best mean log π(preferred) on the training participants, uncalibrated — with slips and
    changes of mind even the exact filter is sometimes confidently wrong, so a wrong-belief
    limit would only slow the learner; the proper score makes it approximate the filter;
    ``filter``: the best ``filter`` objective on fixed validation draws (the log score without
    the noise of one sampled preference per answer, so snapshots are told apart reliably)."""
    population: dict[str, Any] | None = None
    """The population the run trains for (``trustlab pretrain --population``): its file's
    ``sha256``, its ``source`` and the category's fitted figures, so the checkpoint records
    which earlier participants its ``preferred_prior`` came from (issue 20). Unset: none."""

    def resolved(self) -> PretrainArgs:
        """A copy with the mode-dependent defaults filled in, after checking every value."""
        if self.mode not in ("online", "paper"):
            raise ValueError(f"mode must be 'online' or 'paper', not {self.mode!r}")
        if self.objective not in OBJECTIVES:
            raise ValueError(
                f"objective must be one of {', '.join(OBJECTIVES)}, not {self.objective!r}"
            )
        if self.online_rule not in UPDATE_RULES:
            raise ValueError(
                f"online_rule must be one of {', '.join(UPDATE_RULES)}, not {self.online_rule!r}"
            )
        if self.arms < 2 or self.arms > 64:
            raise ValueError(f"arms must be between 2 and 64, got {self.arms}")
        prior = check_prior(self.preferred_prior, self.arms)
        online = self.mode == "online"
        args = replace(
            self,
            preferred_prior=None if self.preferred_prior is None else tuple(prior.tolist()),
            meta_batches=self.meta_batches or default_meta_batches(self.mode, self.online_rule),
            tasks_per_batch=self.tasks_per_batch or (200 if online else 40),
        )
        positive = {
            "horizon": args.horizon,
            "meta_batches": args.meta_batches,
            "tasks_per_batch": args.tasks_per_batch,
            "pulls": args.pulls,
            "fast_lr": args.fast_lr,
            "max_kl": args.max_kl,
            "cg_iterations": args.cg_iterations,
            "ls_steps": args.ls_steps,
            "hidden": args.hidden,
            "init_step_size": 1.0 if args.init_step_size is None else args.init_step_size,
            "calibration_participants": args.calibration_participants,
            "init_damping": args.init_damping,
            "validate_every": args.validate_every,
            "validation_participants": args.validation_participants,
            "evaluation_participants": args.evaluation_participants,
            "variance": args.variance,
        }
        for name, value in positive.items():
            if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be positive, got {value!r}")
        if not 0 < args.ls_backtrack < 1 or not 0 < args.discount <= 1:
            raise ValueError("ls_backtrack must be in (0, 1) and discount in (0, 1]")
        if args.wrong_penalty < 0 or not math.isfinite(args.wrong_penalty):
            raise ValueError(
                f"wrong_penalty must be a non-negative number, got {args.wrong_penalty}"
            )
        if not 0 < args.calibration_limit < 1:
            raise ValueError(
                f"calibration_limit must be between 0 and 1, got {args.calibration_limit!r}"
            )
        if args.cg_damping < 0:
            raise ValueError("cg_damping must not be negative")
        if args.selection not in SELECTIONS:
            raise ValueError(
                f"selection must be one of {', '.join(SELECTIONS)}, not {args.selection!r}"
            )
        if "filter" in (args.objective, args.selection) and not online:
            raise ValueError("the filter objective and selection are for online mode")
        if args.objective == "filter" and args.wrong_penalty > 0:
            raise ValueError("a wrong-belief penalty is part of the log_score objective only")
        model = args.feedback_model  # raises ValueError for a malformed model
        if not online and (args.feedback is not None or args.anchor or args.forgetting):
            raise ValueError(
                "paper mode trains on the paper's Gaussian feedback with the plain network: "
                "a feedback model, anchoring and forgetting are for online mode"
            )
        if args.bounded_baseline and (args.feedback is None or model.kind != "binary"):
            raise ValueError("a bounded baseline needs a yes/no feedback model")
        if args.surprise_gates and not args.forgetting:
            raise ValueError("surprise gates scale the forgetting step: they need forgetting")
        if not (math.isfinite(args.change_oversampling) and args.change_oversampling >= 1):
            raise ValueError(
                f"change_oversampling must be a number ≥ 1, got {args.change_oversampling!r}"
            )
        if args.surprise_memory and not args.surprise_gates:
            raise ValueError("a surprise memory is part of the surprise gates: it needs them")
        if args.question_trace is not None and args.question_trace not in TRACE_KINDS:
            raise ValueError(
                f"question_trace must be one of {', '.join(TRACE_KINDS)}, "
                f"not {args.question_trace!r}"
            )
        if args.question_trace and not args.surprise_gates:
            raise ValueError("a per-question surprise trace is part of the surprise gates")
        if args.population is not None and (
            not isinstance(args.population.get("sha256"), str) or args.preferred_prior is None
        ):
            raise ValueError("a population run records the population's sha256 and its prior")
        if args.anchor and min(prior) <= 0:
            raise ValueError("an anchored policy needs a prior above 0 for every question")
        if model.kind == "gaussian" and not math.isclose(model.variance, args.variance):
            raise ValueError("a Gaussian feedback model's variance must equal the run's variance")
        return args

    @property
    def feedback_model(self) -> FeedbackModel:
        """The model the training participants answer by."""
        if self.feedback is None:
            return FeedbackModel.paper(self.variance)
        try:
            return FeedbackModel.from_json(self.feedback)
        except ValueError as exc:
            raise ValueError(f"feedback: {exc}") from None

    @property
    def tasks(self) -> TaskDistribution:
        """The task distribution this run trains on."""
        return TaskDistribution(self.arms, self.preferred_prior, variance=self.variance)
