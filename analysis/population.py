"""A study's population as a file: the answers a step log holds, the file saved with where it
came from and a hash of its content, and read back verified (issue 20).

The fit itself is the adaptation engine's model (models/population.py); the app joins the two
(app/services/sessions/population_fit.py), since analysis knows only pandas and statistics.

The file is JSON::

    {"format": "trustlab-population", "version": 1,
     "content": {"source": {...}, "categories": {NAME: {"arms", "participants", "answers",
                 "prior", "prior_ci", "slip", "slip_ci", "hazard", "hazard_ci",
                 "log_likelihood", "iterations", "converged"}}, "bootstrap": {...}},
     "sha256": "<SHA-256 of the canonical JSON of content>"}

``source`` names the studies (or the steps CSV) and ``steps_sha256``, the SHA-256 of the step
columns the fit read, sorted and written as CSV (:func:`steps_sha256`; not the hash of the CSV
file itself, and study participants are named ``STUDY/code``), so a
checkpoint trained for the population, and a report, can say exactly where the prior came from.
An edited file no longer matches its hash and is refused.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pandas as pd

if TYPE_CHECKING:
    import plotly.graph_objects as go

FORMAT = "trustlab-population"
VERSION = 1
STEP_COLUMNS = ("participant", "category", "session", "run", "iteration", "action", "answer")
"""The columns of a steps CSV (``trustlab export --format steps-csv``) the fit reads."""
CATEGORY_FIELDS = (
    "arms",
    "participants",
    "prior",
    "prior_ci",
    "slip",
    "slip_ci",
    "hazard",
    "hazard_ci",
)
"""What every category of a population file must give (read_population checks them)."""


def steps_sha256(steps: pd.DataFrame) -> str:
    """SHA-256 of the fit's input: the step columns in their canonical order, as CSV."""
    frame = steps.loc[:, list(STEP_COLUMNS)].sort_values(list(STEP_COLUMNS[:5]), kind="stable")
    return hashlib.sha256(frame.to_csv(index=False).encode("utf-8")).hexdigest()


@dataclass(frozen=True)
class StepAnswers:
    """One category's answers, a row per participant in the order they were given:
    ``actions[n, t]`` the question asked (−1 past a participant's last answer) and
    ``answers[n, t]`` whether they said yes; ``n_arms`` questions."""

    n_arms: int
    actions: np.ndarray
    answers: np.ndarray


def answers_from_steps(
    steps: pd.DataFrame, arms: dict[str, int] | None = None
) -> dict[str, StepAnswers]:
    """Each category's answer sequences, in session, run, iteration order per participant.

    ``arms`` gives each category's K; without it K is read from the ``p_before_*`` columns a
    steps CSV carries (the probabilities the learner logged, one per question).

    Raises
    ------
    ValueError
        Naming the missing columns, or a category whose K cannot be told.
    """
    missing = [column for column in STEP_COLUMNS if column not in steps.columns]
    if missing:
        raise ValueError(f"the steps table lacks the column(s) {', '.join(missing)}")
    result: dict[str, StepAnswers] = {}
    for category, rows in steps.groupby("category", sort=True):
        name = str(category)
        k = (arms or {}).get(name) or _arms_from_probabilities(rows, name)
        ordered = rows.sort_values(["participant", "session", "run", "iteration"], kind="stable")
        position = ordered.groupby("participant", sort=False).cumcount().to_numpy()
        people = pd.Index(pd.unique(ordered["participant"]))
        index = people.get_indexer(ordered["participant"])
        actions = np.full((len(people), int(position.max()) + 1), -1, dtype=np.int64)
        answers = np.zeros(actions.shape, dtype=bool)
        try:
            asked = ordered["action"].astype(int).to_numpy()
            said = ordered["answer"].astype(int).to_numpy()
        except (TypeError, ValueError):
            raise ValueError(
                f"category {name!r}: action and answer must be whole numbers"
            ) from None
        if np.any(asked < 0) or np.any(asked >= k):
            raise ValueError(f"category {name!r}: an action is outside the questions 0..{k - 1}")
        if not np.all((said == 0) | (said == 1)):
            raise ValueError(f"category {name!r}: every answer must be 0 (no) or 1 (yes)")
        actions[index, position] = asked
        answers[index, position] = said == 1
        result[name] = StepAnswers(k, actions, answers)
    return result


def _arms_from_probabilities(rows: pd.DataFrame, category: str) -> int:
    columns = [c for c in rows.columns if str(c).startswith("p_before_")]
    if not columns:
        raise ValueError(
            f"category {category!r}: the number of questions is unknown (no p_before_* columns)"
        )
    return int(rows[columns].iloc[0].notna().sum())


def source_label(source: dict[str, Any]) -> str:
    """A population's ``source`` in a few words: the studies it was fitted from, or the CSV."""
    if "studies" in source:
        return ", ".join(str(name) for name in source["studies"])
    return str(source.get("steps", "an unrecorded source"))


@dataclass(frozen=True)
class Population:
    """A verified population file's content."""

    content: dict[str, Any]
    sha256: str

    @classmethod
    def of(cls, content: dict[str, Any]) -> Population:
        """A population with this content and the hash of it (the fit's result)."""
        return cls(content, _digest(content))

    @property
    def categories(self) -> dict[str, dict[str, Any]]:
        """Each category's fitted figures."""
        return dict(self.content["categories"])

    def prior(
        self, category: str, arms: int, questions: list[str] | None = None
    ) -> tuple[float, ...]:
        """The fitted prior of ``category``, checked against the target's K and, when both the
        population's source and the caller know them, its question texts."""
        fitted = self.categories.get(category)
        if fitted is None:
            raise ValueError(f"the population has no category {category!r}")
        known = self.content["source"].get("questions", {}).get(category)
        if questions is not None and known is not None and list(known) != list(questions):
            raise ValueError(
                f"category {category!r} asks other questions than the study the population was "
                "fitted from: the questions differ"
            )
        if int(fitted["arms"]) != arms:
            raise ValueError(
                f"category {category!r} had {fitted['arms']} questions where the population was "
                f"fitted, {arms} here: the questions differ"
            )
        return tuple(float(v) for v in fitted["prior"])

    def training_prior(
        self, category: str, arms: int, questions: list[str] | None = None
    ) -> tuple[float, ...]:
        """The prior C2 is meta-trained on: the fitted shares as expected counts of N
        participants, smoothed by one pseudo-participant per question (the posterior mean under a
        uniform Dirichlet prior, Laplace's rule of succession).

        Why not the fitted shares themselves: a maximum-likelihood share is 0 for a question no
        pilot participant preferred, and an anchored policy starting at 0 could never learn that
        someone new prefers it; and a small pilot's shares are noisy, so they should move the
        start less than a large pilot's (with N = 6 a .7 share becomes .5, with N = 48 .67).
        """
        shares = np.asarray(self.prior(category, arms, questions))
        n = int(self.categories[category]["participants"])
        return tuple(float(v) for v in (shares * n + 1.0) / (n + arms))

    @property
    def source_label(self) -> str:
        """Where the population came from, in a few words: the studies or the steps CSV."""
        return source_label(self.content["source"])

    def record(self, category: str) -> dict[str, Any]:
        """What a checkpoint (and a learner's config) records about the population it was trained
        for: the file's hash, its source and the category's fitted figures."""
        fitted = self.categories[category]
        return {
            "sha256": self.sha256,
            "source": self.content["source"],
            "category": category,
            "participants": int(fitted["participants"]),
            "prior": list(fitted["prior"]),
            "prior_ci": list(fitted["prior_ci"]),
            "slip": fitted["slip"],
            "slip_ci": list(fitted["slip_ci"]),
            "hazard": fitted["hazard"],
            "hazard_ci": list(fitted["hazard_ci"]),
        }


def _digest(content: dict[str, Any]) -> str:
    canonical = json.dumps(content, sort_keys=True, separators=(",", ":"), allow_nan=False)
    return hashlib.sha256(canonical.encode("utf-8")).hexdigest()


def write_population(path: Path, population: Population) -> None:
    """Write the file (atomically: a half-written file never replaces a good one)."""
    data = {"format": FORMAT, "version": VERSION, "content": population.content}
    data["sha256"] = population.sha256
    temporary = path.with_name(path.name + ".tmp")
    temporary.write_text(json.dumps(data, indent=2, sort_keys=True) + "\n", encoding="utf-8")
    temporary.replace(path)


def read_population(path: Path) -> Population:
    """Read and verify a population file.

    Raises
    ------
    ValueError
        If it is unreadable, not a population file, or edited after its hash was recorded.
    """
    try:
        data = json.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"population file {path} cannot be read: {exc}") from None
    if not isinstance(data, dict) or data.get("format") != FORMAT:
        raise ValueError(f"{path} is not a {FORMAT} file")
    if data.get("version") != VERSION:
        raise ValueError(f"population file {path} has version {data.get('version')!r}")
    content = data.get("content")
    if not isinstance(content, dict) or not isinstance(content.get("categories"), dict):
        raise ValueError(f"population file {path} has no categories")
    digest = _digest(content)
    if digest != data.get("sha256"):
        raise ValueError(
            f"population file {path} does not match its recorded hash (sha256 {digest[:12]}…): "
            "edited after it was fitted; fit it again"
        )
    for name, fitted in content["categories"].items():
        problem = _malformed(fitted)
        if problem:
            raise ValueError(f"population file {path}: category {name!r} {problem}; fit it again")
    if not isinstance(content.get("source"), dict):
        raise ValueError(f"population file {path} records no source; fit it again")
    return Population(content, digest)


def _malformed(fitted: Any) -> str:
    """What is wrong with one category's figures (empty when nothing): a file written by another
    program, or by a version with other fields, can match its own hash and still be unusable."""
    if not isinstance(fitted, dict):
        return "is not a table of figures"
    missing = [key for key in CATEGORY_FIELDS if key not in fitted]
    if missing:
        return f"lacks {', '.join(missing)}"
    arms = fitted["arms"]
    if not isinstance(arms, int) or arms < 2:
        return "has no usable number of questions"
    prior = fitted["prior"]
    intervals = fitted["prior_ci"]
    numbers = isinstance(prior, list) and all(isinstance(v, int | float) for v in prior)
    if not numbers or len(prior) != arms or min(prior) < 0 or abs(sum(prior) - 1) > 1e-6:
        return f"has a prior that is not {arms} probabilities summing to 1"
    if not isinstance(intervals, list) or len(intervals) != arms:
        return "has prior intervals that do not match its prior"
    for key in ("slip", "hazard"):
        if not isinstance(fitted[key], int | float) or not 0 <= fitted[key] < 1:
            return f"has a {key} outside [0, 1)"
    if not isinstance(fitted["participants"], int) or fitted["participants"] < 1:
        return "has no participant count"
    return ""


def prior_figure(population: Population) -> go.Figure:
    """The fitted prior of each category: one bar per question with its bootstrap interval, the
    uniform prior marked, so a reader sees at once which questions the population favours."""
    # Plotly and the figures' palette here only: the exports read source_label from this
    # module and draw nothing (trustlab export, issue 49).
    import plotly.graph_objects as go
    from plotly.subplots import make_subplots

    from analysis.figures import PALETTE

    categories = population.categories
    figure = make_subplots(rows=1, cols=len(categories), subplot_titles=list(categories))
    for column, (name, fitted) in enumerate(categories.items(), start=1):
        prior = np.asarray(fitted["prior"])
        low, high = np.asarray(fitted["prior_ci"]).T
        figure.add_trace(
            go.Bar(
                x=[f"question {k}" for k in range(prior.size)],
                y=prior,
                error_y={
                    "type": "data",
                    "symmetric": False,
                    "array": high - prior,
                    "arrayminus": prior - low,
                },
                marker_color=PALETTE[0],
                name=f"{name} (N = {fitted['participants']})",
                showlegend=column == 1,
                legendgroup="prior",
            ),
            row=1,
            col=column,
        )
        figure.add_hline(y=1 / prior.size, line_dash="dot", line_color="#888888", row=1, col=column)
    level = population.content["bootstrap"]["level"]
    figure.update_layout(
        title=f"Fitted prior over the preferred question, {level:.0%} bootstrap intervals "
        "(dotted: uniform)",
        yaxis={"title": "p(preferred)", "range": [0, 1]},
        paper_bgcolor="white",
        plot_bgcolor="white",
    )
    return figure


def write_prior_figure(path: Path, population: Population) -> None:
    """The figure as a self-contained HTML page (plotly.js inline: nothing loads from a CDN)."""
    html = prior_figure(population).to_html(full_html=True, include_plotlyjs=True)
    temporary = path.with_name(path.name + ".tmp")
    temporary.write_text(html, encoding="utf-8")
    temporary.replace(path)
