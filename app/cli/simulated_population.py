"""Who ``trustlab simulate adaptation --population`` draws its participants from (issue 36).

``--population FILE`` names the *fitted* population: the one ``trustlab pretrain --population``
meta-trains C2 for, fitted by EM from a pilot's logged answers. Drawing the simulated participants
from it evaluates C2 on the distribution it was trained for, which is optimistic: a prior fitted
from a few dozen participants agrees with C2's start more than new participants will (a held-out
check, bench/population.py --held-out, measured C2's gain overstated by 0.23–0.47 answers to .95
in 7 pilots of 8; docs/engine.md, "Seeing it"). So the lab may declare the population it believes
true, separately, in one of two ways:

- ``--true-population FILE``: another population file, e.g. fitted on held-out participants or on
  a later study. It is a file because that is what a lab has: a fit with its source and hash,
  which the output names. The participants answer with its slip rate and hazard and prefer a
  question by its *smoothed* shares, (share · N + 1)/(N + K) (``Population.training_prior``):
  the predictive distribution of a new participant given the file's N, under a uniform Dirichlet
  prior. Its raw shares would repeat the fitted draw's fault on another sample: the shares of a
  few dozen participants are sharper than the truth, and bench/population.py's held-out check
  measured draws from a held-out half's raw shares optimistic by 0.17 answers on average, from
  its smoothed shares within 0.01 of the truth.
- ``--preferred-prior P1,P2,…`` beside ``--population`` (with ``--slip``, ``--hazard`` if the lab
  believes those differ too): a declaration by hand. Unset, the slip rate and hazard are the
  fitted ones (the output says so). The prior is required: it is what a fit overstates, so a
  "declaration" that keeps the fitted prior would still be the optimistic draw.

``--population`` keeps meaning the population C2 was trained for: a checkpoint that records
another population is refused, one that records none (the shipped sets) is reported as not
trained for it. Contradictions are refused in one line (ValueError, exit 2 in the command): two
declarations at once, a declaration without ``--population``, Gaussian answers or several
acceptable questions for a population (whose participants answer yes/no and prefer one question),
and ``--slip``/``--hazard`` without a declared prior.

Every result says which population the participants came from (``population`` in the JSON, a line
in the table and the figure's subtitle), and :func:`caution` gives the warning printed when they
came from the fitted one.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from analysis.population import Population
    from models.checkpoints import Checkpoint
    from models.simulate import Scenario
    from models.tasks import TaskDistribution

__all__ = ["Declared", "PopulationDraw", "caution", "population_participants"]


@dataclass(frozen=True)
class Declared:
    """The participant options of ``simulate adaptation`` as given (None: unset)."""

    preferred_prior: tuple[float, ...] | None = None
    slip: float | None = None
    hazard: float | None = None
    feedback: str | None = None
    acceptable: int = 1


@dataclass(frozen=True)
class PopulationDraw:
    """The participants a simulation draws and the ``population`` record its result carries."""

    category: str
    tasks: TaskDistribution
    scenario: Scenario
    fitted: Population
    fitted_path: Path
    record: dict[str, Any] = field(default_factory=dict)

    @property
    def optimistic(self) -> bool:
        """Whether the participants come from the fitted population itself."""
        return bool(self.record["participants"]["drawn_from"] == "fitted")

    def for_checkpoint(self, checkpoint: Checkpoint) -> PopulationDraw:
        """This draw with what ``checkpoint`` was trained for recorded (and its summary line).

        Raises
        ------
        ValueError
            If the checkpoint was meta-trained for another population (or category): then
            ``--population`` would not be the population C2 was trained for.
        """
        recorded = checkpoint.config.get("population")
        trained = isinstance(recorded, dict)
        if isinstance(recorded, dict) and (
            recorded.get("sha256") != self.fitted.sha256
            or recorded.get("category") != self.category
        ):
            raise ValueError(
                f"checkpoint {checkpoint.path} was trained for population "
                f"{str(recorded.get('sha256'))[:12]}… ({recorded.get('category')}), --population "
                f"names {self.fitted.sha256[:12]}… ({self.category}): give the population C2 was "
                "trained for as --population and the one you believe true as --true-population"
            )
        record = dict(self.record)
        record["c2_trained_for_fitted"] = trained
        record["summary"] = _summary(record, self.fitted_path, trained)
        record["c2"] = (
            f"C2: trained for the fitted population {self.fitted_path}"
            if trained
            else "C2: trained on its own prior, not for the fitted population (to evaluate C2 "
            f"trained for it: trustlab pretrain --population {self.fitted_path}, then "
            "--checkpoint DIR)"
        )
        return PopulationDraw(
            self.category, self.tasks, self.scenario, self.fitted, self.fitted_path, record
        )


def population_participants(
    fitted_path: Path,
    *,
    true_path: Path | None,
    declared: Declared,
    category: str | None,
    arms: int,
    change_after: int | None,
) -> PopulationDraw:
    """The participants ``--population`` and the lab's declaration describe.

    Raises
    ------
    ValueError
        For contradictory options (one line naming them), an unreadable or edited population
        file, a category the files lack, or another K.
    """
    from analysis.population import read_population
    from models.feedback import FeedbackModel
    from models.simulate import Scenario
    from models.tasks import TaskDistribution, check_prior

    _refuse_contradictions(true_path, declared)
    fitted = read_population(fitted_path)
    names = list(fitted.categories)
    if category is None:
        if len(names) != 1:
            raise ValueError(
                f"--population has categories {', '.join(names)}: name one (--category)"
            )
        category = names[0]
    fitted.prior(category, arms)  # the category and its K, checked
    fitted_figures = fitted.categories[category]
    origin: dict[str, Any] = {
        "drawn_from": "declared",
        "declared_by": None,
        "file": None,
        "sha256": None,
    }
    truth = None if true_path is None else read_population(true_path)
    if truth is not None and truth.sha256 == fitted.sha256:
        truth = None  # the fitted population itself, declared true: the fitted draw
    if truth is not None:
        questions = fitted.content["source"].get("questions", {}).get(category)
        try:
            prior = truth.training_prior(category, arms, questions)
        except ValueError as exc:
            raise ValueError(f"--true-population {true_path}: {exc}") from None
        figures = truth.categories[category]
        slip, hazard = float(figures["slip"]), float(figures["hazard"])
        origin |= {"declared_by": "--true-population", "prior_from": "smoothed shares"}
        origin |= {"file": str(true_path), "sha256": truth.sha256}
        origin |= {"source": truth.source_label, "slip_from": "file", "hazard_from": "file"}
    elif declared.preferred_prior is not None:
        try:
            prior = tuple(float(v) for v in check_prior(declared.preferred_prior, arms))
        except ValueError as exc:
            raise ValueError(f"--preferred-prior: {exc}") from None
        slip = float(fitted_figures["slip"]) if declared.slip is None else declared.slip
        hazard = float(fitted_figures["hazard"]) if declared.hazard is None else declared.hazard
        origin |= {"declared_by": "--preferred-prior", "prior_from": "declared"}
        origin |= {"slip_from": "fitted" if declared.slip is None else "declared"}
        origin |= {"hazard_from": "fitted" if declared.hazard is None else "declared"}
    else:
        prior = fitted.prior(category, arms)
        slip, hazard = float(fitted_figures["slip"]), float(fitted_figures["hazard"])
        origin |= {"drawn_from": "fitted", "file": str(fitted_path), "sha256": fitted.sha256}
        origin |= {"prior_from": "shares"}
        origin |= {"source": fitted.source_label, "slip_from": "file", "hazard_from": "file"}
    try:
        model = FeedbackModel(kind="binary", slips=(slip,), hazard=hazard)
    except ValueError as exc:
        raise ValueError(f"--slip / --hazard: {exc}") from None
    origin |= {"prior": [float(v) for v in prior], "slip": slip, "hazard": hazard}
    record = {
        "category": category,
        "fitted": {
            "file": str(fitted_path),
            "sha256": fitted.sha256,
            "source": fitted.source_label,
            "participants": int(fitted_figures["participants"]),
        },
        "participants": origin,
    }
    return PopulationDraw(
        category,
        TaskDistribution(arms, prior),
        Scenario(feedback=model, change_after=change_after),
        fitted,
        Path(fitted_path),
        record,
    )


def _refuse_contradictions(true_path: Path | None, declared: Declared) -> None:
    """The option combinations that say two different things (ValueError naming them)."""
    if declared.feedback not in (None, "binary"):
        raise ValueError(
            f"--feedback {declared.feedback}: a population's participants answer yes/no "
            "(--feedback binary or unset)"
        )
    if declared.acceptable != 1:
        raise ValueError(
            "--acceptable: a population's participants prefer one question; leave it unset "
            "with --population"
        )
    given = [
        name
        for name, value in (
            ("--preferred-prior", declared.preferred_prior),
            ("--slip", declared.slip),
            ("--hazard", declared.hazard),
        )
        if value is not None
    ]
    if true_path is not None and given:
        raise ValueError(
            f"--true-population declares the participants, and so does {', '.join(given)}: "
            "give one declaration (a population file, or --preferred-prior [--slip] [--hazard])"
        )
    if given and declared.preferred_prior is None:
        verb = "declares" if len(given) == 1 else "declare"
        raise ValueError(
            f"{' and '.join(given)} with --population {verb} the true participants only with "
            "--preferred-prior (the fitted prior is what flatters C2), or give --true-population "
            "FILE"
        )


def _summary(record: dict[str, Any], fitted_path: Path, trained: bool) -> str:
    """The one line that says where the participants came from."""
    origin = record["participants"]
    label = f"({record['category']}, sha256 {str(origin['sha256'])[:12]}…"
    if origin["drawn_from"] == "fitted":
        whose = ": the one C2 was trained for)" if trained else "), not one declared true"
        drawn = f"participants: drawn from the fitted population {fitted_path}"
        return f"{drawn} {label}{whose}: optimistic"
    if origin["declared_by"] == "--true-population":
        return (
            f"participants: drawn from the declared true population {origin['file']} {label}; "
            f"its shares smoothed), not from the fitted {fitted_path}"
        )
    prior = "/".join(f"{v:.2f}" for v in origin["prior"])
    rest = ", ".join(
        f"{key} {origin[key]:.3g} "
        + ("(declared)" if origin[key + "_from"] == "declared" else f"(fitted, {fitted_path})")
        for key in ("slip", "hazard")
    )
    return (
        f"participants: drawn from the declared true population: prior {prior} "
        f"(--preferred-prior), {rest}"
    )


def caution(draw: PopulationDraw) -> str | None:
    """The one-line warning for participants drawn from the fitted population (None otherwise)."""
    if not draw.optimistic:
        return None
    return (
        f"the participants are drawn from the fitted population {draw.fitted_path}, so these "
        "figures are optimistic (C2 trained for it starts at its prior; new participants agree "
        "with that less): declare the population you believe true with --true-population FILE "
        "or --preferred-prior P1,P2,… (docs/engine.md, 'Seeing it')"
    )
