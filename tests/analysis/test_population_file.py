"""Population files: fitted from a steps table, saved with their source and hash, verified."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from analysis.population import (
    answers_from_steps,
    read_population,
    steps_sha256,
    write_population,
)
from app.services.sessions.population_fit import fit_population


def _steps(
    n: int = 30,
    seed: int = 0,
    categories: tuple[tuple[str, int], ...] = (("conation", 4), ("cognition", 3)),
) -> pd.DataFrame:
    """A steps table as `trustlab export --format steps-csv` writes it: by default two
    categories, K = 4 and 3, participants who mostly prefer question 0 and slip now and then."""
    rng = np.random.default_rng(seed)
    rows = []
    for person in range(n):
        for category, k in categories:
            preferred = 0 if rng.random() < 0.7 else int(rng.integers(1, k))
            for session, run, iteration in [(s, r, r) for s in range(3) for r in range(1, 4)]:
                action = int(rng.integers(0, k))
                answer = (action == preferred) != (rng.random() < 0.05)
                row = {
                    "participant": f"P{person:03d}",
                    "condition": "C1",
                    "category": category,
                    "session": session,
                    "run": run,
                    "iteration": iteration + 3 * session,
                    "action": action,
                    "answer": int(answer),
                    "reward": float(answer),
                }
                row |= {f"p_before_{i}": (1 / k if i < k else np.nan) for i in range(4)}
                rows.append(row)
    return pd.DataFrame(rows).sample(frac=1.0, random_state=1)  # any row order


def test_sequences_follow_session_run_and_iteration_order() -> None:
    steps = _steps(8)
    sequences = answers_from_steps(steps)
    assert {name: s.n_arms for name, s in sequences.items()} == {"conation": 4, "cognition": 3}
    first = steps[(steps.participant == "P000") & (steps.category == "conation")]
    first = first.sort_values(["session", "run", "iteration"])
    people = list(
        pd.unique(steps[steps.category == "conation"].sort_values("participant").participant)
    )
    row = people.index("P000")
    np.testing.assert_array_equal(sequences["conation"].actions[row], first["action"].to_numpy())
    with pytest.raises(ValueError, match=r"lacks the column.*answer"):
        answers_from_steps(steps.drop(columns=["answer"]))
    with pytest.raises(ValueError, match="number of questions is unknown"):
        answers_from_steps(steps.drop(columns=[f"p_before_{i}" for i in range(4)]))


def test_a_fitted_file_round_trips_and_refuses_edits(tmp_path: Path) -> None:
    steps = _steps()
    ticks: list[int] = []
    population = fit_population(
        steps, {"studies": ["pilot"]}, replicates=10, progress=lambda: ticks.append(1)
    )
    assert len(ticks) == 20  # 10 refits per category
    conation = population.categories["conation"]
    assert conation["participants"] == 30 and conation["answers"] == 270
    assert conation["prior"][0] > 0.5 and conation["prior_ci"][0][0] <= conation["prior"][0]
    assert population.content["source"] == {
        "studies": ["pilot"],
        "steps_sha256": steps_sha256(steps),
    }
    path = tmp_path / "pilot.population.json"
    write_population(path, population)
    again = read_population(path)
    assert again.sha256 == population.sha256 and again.prior("cognition", 3) == tuple(
        population.categories["cognition"]["prior"]
    )
    with pytest.raises(ValueError, match="questions differ"):
        again.prior("cognition", 4)
    with pytest.raises(ValueError, match="no category 'affection'"):
        again.prior("affection", 4)
    data = json.loads(path.read_text())
    data["content"]["categories"]["conation"]["prior"][0] = 0.99
    path.write_text(json.dumps(data))
    with pytest.raises(ValueError, match="does not match its recorded hash"):
        read_population(path)
    path.write_text("not json")
    with pytest.raises(ValueError, match="cannot be read"):
        read_population(path)


def test_the_steps_hash_ignores_row_order_and_sees_a_changed_answer() -> None:
    steps = _steps(10)
    assert steps_sha256(steps) == steps_sha256(steps.sample(frac=1.0, random_state=5))
    changed = steps.copy()
    changed.iloc[0, changed.columns.get_loc("answer")] ^= 1
    assert steps_sha256(changed) != steps_sha256(steps)


def test_a_category_with_too_few_participants_says_how_many_are_needed() -> None:
    with pytest.raises(ValueError, match=r"category 'cognition': 3 participant.*at least 6"):
        fit_population(_steps(3), {"steps": "x.csv"}, replicates=2)


def test_the_question_texts_must_match_when_both_are_known() -> None:
    source = {"studies": ["pilot"], "questions": {"cognition": ["a", "b", "c"]}}
    population = fit_population(_steps(), source, replicates=2)
    assert len(population.prior("cognition", 3, ["a", "b", "c"])) == 3
    with pytest.raises(ValueError, match="asks other questions"):
        population.prior("cognition", 3, ["a", "b", "x"])


def test_a_file_with_its_hash_but_missing_figures_is_refused(tmp_path: Path) -> None:
    from analysis.population import Population, _digest

    good = fit_population(_steps(30), {"steps": "x"}, replicates=2)
    for damage, message in (
        (lambda c: c["categories"]["conation"].pop("prior"), "lacks prior"),
        (lambda c: c["categories"]["conation"].update(prior=[0.5, 0.6, 0, 0]), "summing to 1"),
        (lambda c: c["categories"]["conation"].update(slip=2), "slip outside"),
        (lambda c: c.pop("source"), "records no source"),
    ):
        content = json.loads(json.dumps(good.content))
        damage(content)
        path = tmp_path / "damaged.json"
        write_population(path, Population(content, _digest(content)))
        with pytest.raises(ValueError, match=message):
            read_population(path)
