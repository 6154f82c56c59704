"""Each condition keeps one colour everywhere (issue 21, defect 3): by its place in the protocol,
whatever has been enrolled, on the dashboard, the analysis page and in the report; every chart
has a legend, even with one condition."""

from __future__ import annotations

from typing import Any

from analysis.figures import PALETTE
from analysis.report import build_report
from analysis.study import analyse_study
from app.services import studies
from app.services.analysis_views.study_data import load_dataset
from app.services.privacy.sites import Scope
from tests.conftest import Lab


def _colours_of(traces: list[dict[str, Any]], name: str) -> set[str]:
    found = set()
    for trace in traces:
        if trace.get("name") == name or trace.get("legendgroup") == name:
            for part in ("marker", "line"):
                colour = (trace.get(part) or {}).get("color")
                if isinstance(colour, str) and colour.startswith("#"):
                    found.add(colour)
    return found


def test_c2_keeps_its_colour_with_only_c2_enrolled(lab: Lab) -> None:
    # Enrol until C2 comes up: the blocks hold 2 or 4 (drawn), so the first two can both be C1,
    # but a C2 comes within the first three.
    c2 = ""
    for _ in range(3):
        code = lab.enrol_and_assign()
        listed = lab.experimenter.get(f"/api/v1/studies/{lab.study}/participants").json()
        if any(p["code"] == code and p["condition"] == "C2" for p in listed):
            c2 = code
            break
    assert c2, "no C2 among the first three allocations"
    lab.experimenter.put(
        f"/api/v1/stations/{lab.station}/participant", json={"study": lab.study, "code": c2}
    )
    for _ in ("familiarisation", "session 1"):
        lab.start_session()
        lab.run_session()
    lab.fill_pending_questionnaires()
    data = lab.experimenter.get(f"/studies/{lab.study}/dashboard.json").json()
    adaptation = data["adaptation"]
    assert _colours_of(adaptation["data"], "C2") == {PALETTE[1]}
    assert not _colours_of(adaptation["data"], "C1")  # nobody of C1 has answered
    assert adaptation["layout"]["showlegend"] is True
    trust = data["measures"][0]["payload"]
    assert _colours_of(trust["data"], "C2") == {PALETTE[1]}
    assert trust["layout"]["showlegend"] is True
    assert all(trace["type"] == "scatter" for trace in trust["data"])  # dodged means, not bars
    with lab.database.read_session() as db:
        result = analyse_study(
            load_dataset(db, scope=Scope.every_site(), study=studies.get_study(db, lab.study))
        )
    assert result.colors == {"C1": PALETTE[0], "C2": PALETTE[1]}
    report = build_report(result)
    # The adaptation figure of the report: C2's curve in C2's colour, though C1 has no steps.
    adaptation = report[report.index('id="adaptation"') :]
    assert PALETTE[1] in adaptation[: adaptation.index("</section>")]
    assert PALETTE[0] not in adaptation[: adaptation.index("</section>")]
