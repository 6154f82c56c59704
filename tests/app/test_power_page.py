"""The analysis page's "Plan the next study": prefilled from the study where it can be, the
answer of ``trustlab power`` with λ and df, the power curve, and one-line refusals (422)."""

from __future__ import annotations

import html
import json
import re
from urllib.parse import unquote

import pytest
from markupsafe import escape

from analysis.power import PowerDesign, eta2_from_f, f_from_eta2, n_for_power, power_for_n
from analysis.power_pilot import estimate_pilot
from analysis.study import analyse_study
from app.db import Database
from app.services import studies
from app.services.analysis_views import study_data
from app.services.analysis_views.power_view import PlanForm, answer_plan
from app.services.privacy.sites import Scope
from app.tables import Role
from app.web.templating import REFUSAL_HEADER
from bench.seed import seed_study
from tests.conftest import UserClientFactory, sqlite_only

HTMX = {"HX-Request": "true"}
PAPER_SPSS = {
    "effect": "interaction",
    "groups": "2",
    "sessions": "4",
    "size": "eta2",
    "value": ".204",
    "convention": "spss",
    "rho": "",
    "question": "power",
    "n": "24",
}
"""The seed paper's interaction, partial η² = .204 read "as in SPSS", at its N = 24."""


def _field(page: str, name: str) -> str:
    found = re.search(rf'name="{name}"[^>]* value="([^"]*)"', page)
    assert found, name
    return html.unescape(found.group(1))


def _figure(page: str) -> dict:
    found = re.search(r"data-figure-payload='([^']*)'", page)
    assert found
    return json.loads(html.unescape(found.group(1)))


@sqlite_only("rendering a form and its answer: the data are read as every analysis page reads them")
def test_the_analysis_page_plans_from_the_studys_own_data(
    database: Database, user_client: UserClientFactory
) -> None:
    seed_study(database, name="pilot", participants=10, seed=4)
    with database.read_session() as db:
        dataset = study_data.load_dataset(
            db, scope=Scope.every_site(), study=studies.get_study(db, "pilot")
        )
    outcome = analyse_study(dataset).outcomes[0]
    pilot = estimate_pilot(
        outcome.data,
        dv="value",
        within="session",
        between="condition",
        subject="participant",
        replicates=0,
    )
    page = user_client(Role.ANALYST).get("/studies/pilot/analysis")
    assert page.status_code == 200
    text = page.text
    assert "Plan the next study" in text
    assert "Prefilled from this study&#39;s own data: 10 complete participants" in text
    assert f"on {outcome.key} (" in text
    assert float(_field(text, "rho")) == pytest.approx(pilot.estimates["rho"], abs=5e-4)
    assert float(_field(text, "value")) == pytest.approx(pilot.f("interaction"), abs=5e-4)
    assert (_field(text, "groups"), _field(text, "sessions"), _field(text, "n")) == ("2", "4", "10")
    design = PowerDesign(
        "interaction", 2, 4, float(_field(text, "rho")), epsilon=float(_field(text, "epsilon"))
    )
    expected = n_for_power(design, f=float(_field(text, "value")), target=0.8)
    assert f"N = {expected.n_total} ({expected.n_total // 2} per group) reaches power" in text
    figure = _figure(text)
    assert figure["kind"] == "power_curve" and expected.n_total in figure["n"]
    assert "<script>" not in text  # the curve is data, drawn by static/js/figures.js


@sqlite_only("rendering a form and its answer; the study is only looked up")
def test_an_answer_for_htmx_and_the_same_as_a_whole_page(
    database: Database, user_client: UserClientFactory
) -> None:
    seed_study(database, name="tiny", participants=2, seed=5)
    analyst = user_client(Role.ANALYST)
    answer = analyst.get("/studies/tiny/analysis/power", params=PAPER_SPSS, headers=HTMX)
    assert answer.status_code == 200
    text = answer.text
    # the form and its answer, swapped in together (values recomputed show in the form)
    assert text.lstrip().startswith('<div id="power-plan-body"') and "<html" not in text
    assert '<div id="power-answer"' in text
    # G*Power 3.1, "as in SPSS": λ = f² · df2 = .204/.796 · 66 = 16.915, power .933
    # (the same figures test_cli_power.py checks for the command line).
    assert "Power 0.933 to detect the group × session interaction with N = 24." in text
    assert "<td>16.9146</td>" in text and "<td>3.000, 66.000</td>" in text
    assert "trustlab power --effect interaction --groups 2 --sessions 4 --eta2 .204" in text
    # the simulated models, the ordinal one included, are named with their flags
    assert "<code>--simulate 1000 --model ordinal</code>" in text
    whole = analyst.get("/studies/tiny/analysis/power", params=PAPER_SPSS)
    assert whole.status_code == 200 and "<html" in whole.text
    assert "Power 0.933 to detect" in whole.text and _field(whole.text, "value") == ".204"
    # Too few participants to estimate from: the page says why and starts from the paper's design.
    assert "Not prefilled from this study: a pilot needs " in whole.text


BAD_INPUT = [
    ({"rho": "1.2"}, "rho (the correlation among repeated measures) must be between"),
    ({"rho": "abc"}, "rho: 'abc' is not a number"),
    ({"epsilon": "0.2"}, "epsilon must be between 1/(m − 1)"),
    ({"value": "-0.1", "size": "f"}, "the effect size f must be 0 or more"),
    ({"question": "n", "target": "1.5"}, "the target power must be between 0 and 1"),
    ({"groups": "2.5"}, "groups: a whole number from 1 to 50"),
]


@sqlite_only("refused before the data are read")
def test_bad_input_is_one_line_in_the_page_with_422(
    study_name: str, user_client: UserClientFactory
) -> None:
    analyst = user_client(Role.ANALYST)
    for change, words in BAD_INPUT:
        params = {**PAPER_SPSS, "convention": "gpower", "rho": "0.5", **change}
        for headers in ({}, HTMX):
            refused = analyst.get(
                f"/studies/{study_name}/analysis/power", params=params, headers=headers
            )
            assert refused.status_code == 422, change
            message = unquote(refused.headers[REFUSAL_HEADER])
            assert message.startswith(words.split(" (")[0]) and words in message
            assert "\n" not in message and "Traceback" not in refused.text
            assert f'<p class="error" role="alert">{escape(message)}</p>' in refused.text
            assert ("<html" in refused.text) is not bool(headers)


def test_the_page_and_the_command_line_give_the_same_answer() -> None:
    form = PlanForm(effect="within", value="0.2", rho="0.6", epsilon=".333", question="power")
    answer = answer_plan(form)
    direct = power_for_n(
        PowerDesign("within", 2, 4, 0.6, epsilon=1 / 3), f=0.2, n_total=24
    ).to_dict()
    assert answer.result == direct
    assert answer.command == (
        "trustlab power --effect within --groups 2 --sessions 4 --f 0.2 --rho 0.6 "
        "--epsilon .333 --n 24"
    )
    detect = answer_plan(PlanForm(question="effect", value="not read"))
    assert detect.result["question"] == "detectable effect"
    assert "--f" not in detect.command and "--target-power 0.8" in detect.command


def _form(page: str) -> dict[str, str]:
    """The power form's fields as the page gives them back (the hidden ``study`` too)."""
    names = ("groups", "sessions", "value", "rho", "epsilon", "alpha", "n", "target")
    form = {name: _field(page, name) for name in names}
    found = re.search(r'type="hidden" name="study" value="([^"]*)"', page)
    form["study"] = html.unescape(found.group(1)) if found else ""
    for name in ("effect", "size", "convention", "question"):
        chosen = re.search(rf'name="{name}">.*?<option value="([^"]*)" selected', page, re.S)
        assert chosen, name
        form[name] = chosen.group(1)
    return form


@sqlite_only("rendering a form and its answer: the data are read as every analysis page reads them")
def test_a_prefilled_form_says_what_is_the_studys_and_recomputes_what_a_change_made_stale(
    database: Database, user_client: UserClientFactory
) -> None:
    seed_study(database, name="pilot", participants=10, seed=4)
    analyst = user_client(Role.ANALYST)
    page = analyst.get("/studies/pilot/analysis/power").text
    form = _form(page)
    study_epsilon = float(form["epsilon"])
    assert study_epsilon < 1 and "epsilon=" in form["study"]
    assert 'ε (sphericity) <span class="muted small from-study">(this study\'s)</span>' in page
    assert "From this study&#39;s data: groups, sessions, the effect size, ρ, ε, N." in page

    # The PI guide's example typed into the prefilled form: a published partial η² read as in
    # SPSS at N = 24. The study's ε is not applied to it: the documented power, not 0.891.
    typed = {**form, "size": "eta2", "value": ".204", "convention": "spss", "question": "power"}
    answer = analyst.get("/studies/pilot/analysis/power", params={**typed, "n": "24"}, headers=HTMX)
    assert answer.status_code == 200
    text = answer.text
    assert "Power 0.933 to detect the group × session interaction with N = 24." in text
    assert "ε = 1: a partial η² of your own, read as in SPSS" in text
    back = _form(text)
    assert back["epsilon"] == "1" and "epsilon=" not in back["study"]
    assert "yours (or the defaults): the effect size, ε, N." in text
    # Typed back, the study's ε is the person's own choice, and applied.
    again = {**back, "epsilon": form["epsilon"], "n": "24"}
    kept = analyst.get("/studies/pilot/analysis/power", params=again, headers=HTMX).text
    design = PowerDesign("interaction", 2, 4, None, epsilon=study_epsilon, convention="spss")
    expected = power_for_n(design, f=f_from_eta2(0.204), n_total=24).power
    assert f"Power {expected:.3f} to detect" in kept and "Recomputed" not in kept

    # The study's f for another effect, and as an η², when only the effect or size changes.
    pilot = dict(pair.split("=") for pair in form["study"].split(";"))
    within = analyst.get(
        "/studies/pilot/analysis/power", params={**form, "effect": "within"}, headers=HTMX
    ).text
    assert _form(within)["value"] == pilot["f_within"]
    assert "this study&#39;s for the within effect" in within
    as_eta2 = analyst.get(
        "/studies/pilot/analysis/power", params={**form, "size": "eta2"}, headers=HTMX
    ).text
    assert float(_form(as_eta2)["value"]) == pytest.approx(
        eta2_from_f(float(pilot["f_interaction"])), abs=5e-4
    )
    # Another number of sessions: the study's ε was estimated over its own 4.
    six = analyst.get(
        "/studies/pilot/analysis/power", params={**form, "sessions": "6"}, headers=HTMX
    ).text
    assert _form(six)["epsilon"] == "1" and "estimated over its 4 sessions, not 6" in six


def test_the_curves_title_shows_only_the_values_its_test_uses() -> None:
    spss = answer_plan(PlanForm(**{**PAPER_SPSS, "rho": "-0.2", "epsilon": "0.8"}))
    title = spss.figure["layout"]["title"]["text"]
    assert "ρ" not in title and "ε = 0.8" in title and "η² as in SPSS" in title
    assert ("ρ", "−0.2 (not used by this convention)") in spss.rows or any(
        label == "ρ" and "not used" in value for label, value in spss.rows
    )
    between = answer_plan(PlanForm(effect="between", rho="0.5", epsilon="0.8"))
    title = between.figure["layout"]["title"]["text"]
    assert "ρ = 0.50" in title and "ε" not in title
