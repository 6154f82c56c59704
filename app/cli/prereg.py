"""``trustlab prereg``: the pre-registration bundle of a study, before its first participant.

Writes into ``--out``: ``prereg.json`` (:func:`analysis.prereg.build_registration`: the frozen
protocol with its SHA-256, hypotheses, planned analyses, exclusion rules, the power analysis and
its inputs, versions and seeds), the same as ``prereg.md`` and ``prereg.html`` for people, and
the protocol itself as ``protocol.toml``. A registration written after participants were
enrolled records how many had been and how many had answered
(:func:`analysis.prereg.data_at_registration`), says so in the files and on stderr, and every
report checked against it repeats it. The files are the study's plan, attached to an OSF
registration; they are written as exports are (owner-only, never through a link, never over an
existing file without ``--force``) and the writing is audited with prereg.json's SHA-256 and the
analysis plan, which every later report of the study checks its analyses against
(:mod:`app.services.analysis_views.registrations`).
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Annotated, Any

import typer

from app.cli.common import JsonFlag, emit_json, open_database, require_current_schema
from app.cli.power import answer_question
from app.errors import InvalidInput

__all__ = ["FILES", "prereg_command", "register"]

FILES = ("prereg.json", "prereg.md", "prereg.html", "protocol.toml")
"""What the bundle holds, in the order it is written."""


def register(cli: typer.Typer) -> None:
    """Add the ``prereg`` command to the ``trustlab`` command line."""
    cli.command("prereg")(prereg_command)


def prereg_command(
    study: Annotated[str, typer.Option("--study", help="Study name.")],
    out: Annotated[
        Path, typer.Option("--out", help="Folder to write the bundle into (made if missing).")
    ],
    power_json: Annotated[
        Path | None,
        typer.Option(
            "--power-json",
            help="The power analysis: a file written by 'trustlab power ... --json'.",
        ),
    ] = None,
    effect: Annotated[
        str | None,
        typer.Option(
            "--effect",
            help="Or compute it here (groups and sessions from the study's protocol): the "
            "effect planned for, between, within or interaction.",
        ),
    ] = None,
    f: Annotated[float | None, typer.Option("--f", help="With --effect: Cohen's f.")] = None,
    eta2: Annotated[
        float | None, typer.Option("--eta2", help="With --effect: partial eta².")
    ] = None,
    convention: Annotated[
        str, typer.Option("--convention", help="With --effect: gpower or spss.")
    ] = "gpower",
    rho: Annotated[
        float | None, typer.Option("--rho", help="With --effect: correlation among sessions.")
    ] = None,
    epsilon: Annotated[
        float | None, typer.Option("--epsilon", help="With --effect: non-sphericity ε.")
    ] = None,
    alpha: Annotated[float, typer.Option("--alpha", help="With --effect: significance level.")] = (
        0.05
    ),
    n: Annotated[int | None, typer.Option("--n", help="With --effect: total N.")] = None,
    target_power: Annotated[
        float | None, typer.Option("--target-power", help="With --effect: the power to reach.")
    ] = None,
    hypothesis: Annotated[
        list[str] | None,
        typer.Option(
            "--hypothesis",
            help="A hypothesis in your words (repeatable); default: the interaction and the "
            "condition effect on the primary measure.",
        ),
    ] = None,
    force: Annotated[bool, typer.Option("--force", help="Replace files that exist.")] = False,
    as_json: JsonFlag = False,
) -> None:
    """Write a study's pre-registration: protocol and its SHA-256, hypotheses, planned analyses,
    exclusion rules, power analysis, versions and seeds (prereg.json, .md, .html). Owner-only
    files; audited; later reports say whether their analyses are the registered ones."""
    from analysis.errors import AnalysisError
    from analysis.prereg import (
        build_registration,
        data_at_registration,
        data_sentence,
        registered_plan,
        registration_html,
        registration_markdown,
    )
    from analysis.report import analysis_provenance
    from app.private_files import new_private_file, refuse_existing, refuse_link
    from app.services import audit, studies
    from app.services.analysis_views import registrations, study_data
    from app.services.audit import Actor
    from app.services.privacy.sites import Scope
    from app.settings import Settings
    from app.tables import utcnow

    targets = [out / name for name in FILES]
    refuse_link(out)
    for target in targets:  # before anything is computed or written
        refuse_link(target)
        if target.exists() and not force:
            raise InvalidInput(f"{target} exists; choose another folder, or --force to replace it")
        refuse_existing(target, replace=force)
    power_options = {"--f": f, "--eta2": eta2, "--rho": rho, "--epsilon": epsilon, "--n": n}
    power_options["--target-power"] = target_power
    given = [name for name, value in power_options.items() if value is not None]
    if power_json is not None and (effect is not None or given):
        raise InvalidInput("give the power analysis as --power-json or as options, not both")
    if effect is None and given:
        raise InvalidInput(f"{given[0]} describes a power analysis: add --effect")
    power = _read_power(power_json) if power_json is not None else None
    database = open_database(Settings())
    require_current_schema(database)
    with database.read_session() as db:
        found = studies.get_study(db, study)
        dataset = study_data.load_dataset(db, study=found, scope=Scope.every_site())
        source, study_id = found.protocol_source, found.id
    try:
        if effect is not None:
            power = answer_question(
                effect=effect,
                groups=len(dataset.protocol["conditions"]),
                sessions=dataset.protocol["sessions"],
                f=f,
                eta2=eta2,
                convention=convention,
                means=None,
                sd=None,
                rho=rho,
                epsilon=epsilon,
                alpha=alpha,
                n=n,
                target_power=target_power,
            ).to_dict()
    except AnalysisError as error:
        raise InvalidInput(str(error)) from None
    plan = registered_plan(dataset)
    data = data_at_registration(dataset)
    if power is not None:
        plan["alpha"] = power["design"]["alpha"]
    registration = build_registration(
        study={"name": study, "title": dataset.protocol["study"]},
        protocol_source=source,
        plan=plan,
        hypotheses=hypothesis or _default_hypotheses(dataset.protocol, plan),
        power=power,
        software={
            **dataset.manifest.get("software", {}),
            **analysis_provenance(plan["ss_type"], plan["confidence"])["packages"],
        },
        seeds=_seeds(dataset.manifest, power),
        created_at=utcnow().isoformat(timespec="seconds"),
        data=data,
    )
    text = json.dumps(registration, indent=2, ensure_ascii=False) + "\n"
    contents = (text, registration_markdown(registration), registration_html(registration), source)
    out.mkdir(mode=0o700, parents=True, exist_ok=True)
    files = {}
    for target, content in zip(targets, contents, strict=True):
        with new_private_file(target, replace=force) as draft:
            draft.write_text(content, encoding="utf-8")
        files[target.name] = hashlib.sha256(target.read_bytes()).hexdigest()
    with database.writing() as db:
        audit.record(
            db,
            actor=Actor.command_line(),
            action=registrations.ACTION,
            study_id=study_id,
            subject=study,
            details={
                "sha256": files["prereg.json"],
                "files": files,
                "registration": {
                    "format": registration["format"],
                    "created_at": registration["created_at"],
                    "data_at_registration": data,
                    "analysis_plan": plan,
                },
            },
        )
        db.commit()
    if data["participants_enrolled"]:  # a pre-registration made after data collection began
        typer.echo(f"note: {data_sentence(registration)} The registration says so.", err=True)
    if as_json:
        emit_json({"study": study, "folder": str(out), "files": files, **data})
        return
    for target in targets:
        typer.echo(f"{target}  sha256 {files[target.name][:16]}…")
    if power is None:
        typer.echo("note: no power analysis registered (--power-json FILE or --effect …)", err=True)


def _read_power(path: Path) -> dict[str, Any]:
    """A ``trustlab power --json`` answer from a file, checked to be one."""
    try:
        value = json.loads(path.read_text(encoding="utf-8"))
    except OSError as error:
        raise InvalidInput(f"--power-json {path}: {error.strerror or error}") from None
    except (json.JSONDecodeError, UnicodeDecodeError):
        raise InvalidInput(f"--power-json {path}: not JSON") from None
    needed = ("power", "n_total", "lambda", "df1", "df2", "design")
    if not isinstance(value, dict) or any(key not in value for key in needed):
        raise InvalidInput(
            f"--power-json {path}: not the output of 'trustlab power --json' (it needs "
            f"{', '.join(needed)})"
        )
    return value


def _default_hypotheses(protocol: Any, plan: dict[str, Any]) -> list[str]:
    """The seed paper's hypotheses, for this study's primary measure and conditions."""
    measures = plan["measures"]
    if not measures:
        return []
    primary = measures[0]
    conditions = " and ".join(f"{c['code']} ({c['label']})" for c in protocol["conditions"])
    others = ", ".join(m["key"] for m in measures[1:])
    hypotheses = [
        f"H1 (condition × session): the change of {primary['key']} (“{primary['label']}”) over "
        f"the {protocol['sessions']} sessions differs between {conditions}.",
        f"H2 (condition): {primary['key']} differs between {conditions}, averaged over sessions.",
    ]
    if others:
        hypotheses.append(
            f"Secondary measures, analysed the same way and reported without correction "
            f"across measures: {others}."
        )
    return hypotheses


def _seeds(manifest: Any, power: dict[str, Any] | None) -> dict[str, Any]:
    seeds: dict[str, Any] = {
        "allocation_seed_sha256": manifest.get("allocation_seed_sha256"),
        "learners": manifest.get("learners"),
    }
    if power is not None:
        pilot = power.get("pilot") or {}
        if pilot:
            seeds["power_bootstrap"] = pilot.get("bootstrap", {}).get("seed")
        simulation = power.get("simulation") or {}
        if simulation:
            seeds["power_simulation"] = simulation.get("seed")
    return seeds
