"""The self-contained HTML report."""

from __future__ import annotations

import dataclasses
import html
import json
import re
import subprocess
from pathlib import Path

import pytest

from analysis import lmm
from analysis.dataset import StudyDataset
from analysis.mixed_models import analyse_mixed_models
from analysis.report import analysis_provenance, build_report, write_report
from analysis.study import StudyAnalysis, analyse_study
from analysis.synthetic import synthetic_study

CHROMIUM = "/usr/bin/chromium"


@pytest.fixture(scope="module")
def dataset() -> StudyDataset:
    ds = synthetic_study(24, seed=7, dropout_rate=0.25)
    manifest = {
        "data_sha256": "ab" * 32,
        "software": {"trustlab": "0.1.0"},
        "checkpoints": {"meta_policy.pt": "cd" * 32},
        "seeds": {"allocation": 1234},
    }
    return dataclasses.replace(ds, manifest=manifest)


@pytest.fixture(scope="module")
def result(dataset: StudyDataset) -> StudyAnalysis:
    return analyse_study(dataset)


@pytest.fixture(scope="module")
def report(result: StudyAnalysis) -> str:
    return build_report(result)


def test_is_one_offline_document(report: str) -> None:
    assert report.startswith("<!DOCTYPE html>")
    assert '<meta charset="utf-8">' in report
    assert report.count("* plotly.js v") == 1  # the library, inline, once
    assert not re.search(r"<(script|link|img|iframe)[^>]*\s(src|href)=", report)
    # The bundle mentions its CDN (for map tiles we never use); nothing else may.
    bundle_end = report.index("</script>")
    assert "cdn.plot.ly" not in report[bundle_end:]
    assert "https://" not in report[bundle_end:]
    # 5 outcomes × (mean ± CI, trajectories) + adaptation + TIPI + NARS distributions
    assert report.count('class="plotly-graph-div"') == 13
    ids = re.findall(r'<div id="(fig-\d+)" class="plotly-graph-div"', report)
    assert ids == [f"fig-{i}" for i in range(1, 14)]


def test_contains_the_statistics(result: StudyAnalysis, report: str) -> None:
    for outcome in result.outcomes:
        assert outcome.sentences is not None
        for text in outcome.sentences["text"]:
            assert html.escape(text) in report
    assert "Mauchly&#x27;s W" in report
    assert "Type III sums of squares" in report
    assert "type III sums of squares (as SPSS, JASP, jamovi and R&#x27;s afex" in report
    assert "Post-hoc comparisons (Holm)" in report
    assert "Estimated marginal means" in report


def test_lists_exclusions(result: StudyAnalysis, report: str) -> None:
    exclusions = result.exclusions()
    assert len(exclusions)
    for participant in exclusions["participant"].unique():
        assert f">{participant}<" in report
    if len(result.status_exclusions):
        assert "status: withdrawn" in report
    assert "incomplete: no value for session" in report  # merged across outcomes


def test_manifest_section(dataset: StudyDataset, report: str) -> None:
    block = re.search(r'<section id="manifest">.*?<pre>(.*?)</pre>', report, re.S)
    assert block is not None
    manifest = json.loads(html.unescape(block.group(1)))
    assert manifest["provided"] == dict(dataset.manifest)
    assert manifest["protocol"]["study"] == dataset.protocol["study"]
    assert manifest["analysis"]["ss_type"] == 3
    assert manifest["analysis"]["packages"] == analysis_provenance(3, 0.95)["packages"]
    assert set(manifest["analysis"]["packages"]) >= {"pandas", "scipy", "pingouin", "plotly"}


def test_methods_paragraph_in_report(
    dataset: StudyDataset, result: StudyAnalysis, report: str
) -> None:
    n = result.sample["n"]
    assert f"N = {n} participants were analysed" in report
    assert "each participant completed four sessions of three runs" in report
    assert "Gosling, S. D." in report  # instrument sources


def test_deterministic(result: StudyAnalysis, report: str) -> None:
    assert build_report(result) == report


def test_degenerate_outcome_and_escaping(dataset: StudyDataset, tmp_path: Path) -> None:
    flat = dataset.responses.copy()
    flat.loc[flat["item"] == "trust_4", "value"] = 2.0
    protocol = {**dataset.protocol, "study": "<script>alert(1)</script> study"}
    odd = dataclasses.replace(dataset, responses=flat, protocol=protocol)  # type: ignore[arg-type]
    path = write_report(odd, tmp_path / "report.html", ss_type=2)
    text = path.read_text(encoding="utf-8")
    assert "<script>alert(1)</script>" not in text
    assert "&lt;script&gt;alert(1)&lt;/script&gt; study" in text
    assert 'class="problem"' in text
    assert "cannot be computed because all" in text
    assert "Type II sums of squares" in text


def test_report_without_steps_or_questionnaires() -> None:
    ds = synthetic_study(6, seed=1, with_steps=False)
    trust_only = ds.responses[ds.responses["instrument"] == "trust"]
    text = build_report(dataclasses.replace(ds, responses=trust_only, scales=()))
    assert "No adaptation steps have been recorded." in text
    assert "No once-only questionnaire has been answered." in text


@pytest.mark.e2e
def test_figures_render_offline_in_chromium(report: str, tmp_path: Path) -> None:
    # Real browser, no network: every figure must draw its SVG from the inline plotly.js.
    path = tmp_path / "report.html"
    path.write_text(report, encoding="utf-8")
    dom = subprocess.run(
        [
            CHROMIUM,
            "--headless",
            "--no-sandbox",
            "--disable-gpu",
            "--disable-background-networking",
            "--disable-component-update",
            "--no-first-run",
            "--dump-dom",
            path.as_uri(),
        ],
        capture_output=True,
        text=True,
        timeout=90,
        check=True,
    ).stdout
    assert dom.count('class="main-svg"') >= 13


def test_mixed_models_section(
    result: StudyAnalysis, report: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    assert 'id="mixed-models"' not in report  # only when the models are given
    mixed = analyse_mixed_models(result, keys=["trust_1", "trust_5"])
    text = build_report(result, mixed=mixed)
    section = text[text.index('<section id="mixed-models">') :]
    section = section[: section.index("</section>")]
    assert '<a href="#mixed-models">Mixed models</a>' in text
    assert section.count("<h3>") == 2
    assert "A linear mixed model (REML, random intercept per participant; Satterthwaite df)" in (
        section
    )
    assert "excluded for a missing session" in section
    assert "Kept here, excluded by the ANOVA: " in section
    assert "Letting the session slope vary by participant" in section
    assert "A proportional-odds (cumulative logit) model" in section
    assert "within participants b = " in section
    assert section.count('class="plotly-graph-div"') == 2  # trust × confidence, per measure
    # A model that does not converge is one line in the report, never a silent estimate.
    monkeypatch.setattr(lmm, "_GRADIENT_TOL", -1.0)  # no fit is ever close enough
    failed = build_report(result, mixed=analyse_mixed_models(result, keys=["trust_1"]))
    part = failed[failed.index('<section id="mixed-models">') :]
    part = part[: part.index("</section>")]
    assert "random intercept model did not converge (bfgs: " in part
    assert "the random intercept and the random slope model did not converge." in part
    assert "Type III" not in part and "Satterthwaite)</th>" not in part
