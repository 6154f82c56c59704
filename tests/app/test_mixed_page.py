"""The analysis page's "Mixed models" section and its own page (issue 23)."""

from __future__ import annotations

import pytest

from analysis.adaptation_trust import session_adaptation
from app.db import Database
from app.services import studies
from app.services.analysis_views import study_data
from app.services.privacy.sites import Scope
from app.tables import Role
from bench.seed import seed_study
from models.replies import exp3_belief, heard_probability
from tests.conftest import UserClientFactory


@pytest.fixture
def seeded(database: Database) -> str:
    """A study of 24 participants, unblinded step log included."""
    seed_study(database, name="seeded", participants=24, seed=3)
    return "seeded"


def test_the_analysis_page_loads_the_section_lazily(
    seeded: str, user_client: UserClientFactory
) -> None:
    page = user_client(Role.ANALYST).get(f"/studies/{seeded}/analysis").text
    assert 'id="mixed-models"' in page
    assert f'hx-get="/studies/{seeded}/analysis/mixed" hx-trigger="load"' in page
    assert f'<a href="/studies/{seeded}/analysis/mixed">Open them on their own page</a>' in page


def test_the_section_shows_every_model_of_a_measure(
    seeded: str, user_client: UserClientFactory
) -> None:
    analyst = user_client(Role.ANALYST)
    page = analyst.get(f"/studies/{seeded}/analysis/mixed")
    assert page.status_code == 200
    text = page.text
    assert "<h1>Mixed models</h1>" in text and "<html" in text
    assert text.count("<option value=") == 5
    assert '<option value="trust_1" selected>' in text
    assert "A linear mixed model (REML, random intercept per participant; Satterthwaite df)" in text
    assert "Type III F tests (Satterthwaite df)" in text
    assert "Estimated marginal means (95 % CI)" in text
    assert "A proportional-odds (cumulative logit) model" in text
    assert "Brant" in text
    # The seeded study is unblinded: the adaptation models and their figure are there.
    assert (
        "The robot&#39;s confidence (probability behind its reply): within participants b =" in text
    )
    assert 'id="figure-mixed-trust_1" data-figure-payload=\'{"data": [' in text
    assert "<script>" not in text


def test_htmx_gets_the_section_alone_and_the_slope_comparison_on_request(
    seeded: str, user_client: UserClientFactory
) -> None:
    analyst = user_client(Role.ANALYST)
    section = analyst.get(
        f"/studies/{seeded}/analysis/mixed?measure=trust_3&slope=true",
        headers={"HX-Request": "true"},
    )
    assert section.status_code == 200
    assert section.headers["vary"] == "HX-Request"
    assert section.text.lstrip().startswith('<section class="card mixed-models" id="mixed-models"')
    assert "<html" not in section.text
    assert '<option value="trust_3" selected>' in section.text
    assert (
        "Random slope: <code>trust_3 ~ condition * session + (1 + session_step | participant)"
        in (section.text)
    )
    assert "Letting the session slope vary by participant" in section.text


def test_bad_measures_roles_and_empty_studies(
    seeded: str, exp3_study: str, database: Database, user_client: UserClientFactory
) -> None:
    analyst = user_client(Role.ANALYST)
    wrong = analyst.get(f"/studies/{seeded}/analysis/mixed?measure=nope")
    assert wrong.status_code == 422
    assert "no per-session measure &#39;nope&#39;; choose one of trust_1, trust_2" in wrong.text
    assert (
        user_client(Role.EXPERIMENTER).get(f"/studies/{seeded}/analysis/mixed").status_code == 403
    )
    young = analyst.get(f"/studies/{exp3_study}/analysis/mixed")
    assert young.status_code == 200 and "Nothing to model yet" in young.text
    seed_study(database, name="tiny", participants=2, seed=5)
    tiny = analyst.get("/studies/tiny/analysis/mixed")
    assert tiny.status_code == 200
    assert "cannot be computed because" in tiny.text


def test_the_step_log_carries_the_reply_the_participant_heard(
    seeded: str, database: Database
) -> None:
    with database.read_session() as db:
        dataset = study_data.load_dataset(
            db, scope=Scope.every_site(), study=studies.get_study(db, seeded), for_staff=True
        )
    steps = dataset.steps
    assert {"reply_probability", "reply_level"} <= set(steps.columns)
    assert dataset.protocol["reply_levels"] == ["low", "medium_low", "medium", "high"]
    # Each reply's level came from the probability C1's Exp3 gave the answer it heard (the
    # shipped protocol's basis): its weights' share of the asked question, through the slips.
    heard = [
        heard_probability(exp3_belief(before[action], gamma=0.5, n_arms=4), said_yes=yes, slip=0.05)
        for before, action, yes in zip(
            steps["probs_before"], steps["action"], steps["answer"], strict=True
        )
    ]
    assert steps["reply_probability"].to_numpy() == pytest.approx(heard)
    measures = session_adaptation(
        steps, dataset.protocol["preferred_arms"], reply_levels=dataset.protocol["reply_levels"]
    )
    shares = measures[[f"share_{n}" for n in dataset.protocol["reply_levels"]]]
    assert shares.sum(axis=1).to_numpy() == pytest.approx(1.0)
    assert (measures["share_top"] == measures["share_high"]).all()
