"""``trustlab languages``: the interface's message catalogues, for translators and labs.

``list`` shows the shipped languages and whether each is complete; ``check`` says, one line per
message, what keeps a catalogue from being used; ``update`` writes a language's ``.po`` file from
the sources (new messages untranslated, gone ones dropped, translations kept), which also starts
a new language (docs/languages.md).
"""

from __future__ import annotations

from typing import Annotated

import typer

from app.cli.common import JsonFlag, emit_json
from app.cli.errors import fail

languages_cli = typer.Typer(
    help="The participants' interface languages (message catalogues).", no_args_is_help=True
)


def register(cli: typer.Typer) -> None:
    """Attach these commands to the top-level ``trustlab`` command."""
    cli.add_typer(languages_cli, name="languages")


def _problems(language: str) -> list[str]:
    from app.i18n import catalogues

    try:
        return catalogues.catalogue_problems(catalogues.read_catalog(language))
    except catalogues.CatalogueError as exc:
        return [str(exc)]


@languages_cli.command("list")
def list_languages(as_json: JsonFlag = False) -> None:
    """The interface languages shipped, each with its name, direction and completeness."""
    from app.i18n import catalogues
    from app.i18n.languages import direction, native_name

    rows = [
        {
            "language": code,
            "name": native_name(code),
            "direction": direction(code),
            "problems": len(_problems(code)),
        }
        for code in catalogues.ui_languages()
    ]
    if as_json:
        emit_json(rows)
        return
    for row in rows:
        state = "complete" if not row["problems"] else f"{row['problems']} problems"
        typer.echo(f"{row['language']:<6} {row['name']:<24} {row['direction']}  {state}")


@languages_cli.command("check")
def check(
    language: Annotated[str, typer.Argument(help="A language code, e.g. sv.")],
) -> None:
    """Whether LANGUAGE's catalogue can be used: every message translated, none fuzzy, every
    placeholder kept. Exit status 1 with one line per problem otherwise."""
    from app.i18n.languages import UnknownLanguage, check_code, native_name

    try:
        check_code(language)
    except UnknownLanguage as exc:
        fail(str(exc), code=2)
    problems = _problems(language)
    for problem in problems:
        typer.echo(f"{language}: {problem}", err=True)
    if problems:
        raise typer.Exit(1)
    typer.echo(f"{language}: complete ({native_name(language)})")


@languages_cli.command("update")
def update(
    language: Annotated[str, typer.Argument(help="A language code, e.g. fi (new or shipped).")],
) -> None:
    """Write LANGUAGE's catalogue from the sources: add new messages (untranslated), drop gone
    ones, keep translations. Starts the catalogue of a new language."""
    from app.i18n import catalogues
    from app.i18n.extract import update as write_catalogue
    from app.i18n.languages import UnknownLanguage, check_code

    try:
        check_code(language)
    except UnknownLanguage as exc:
        fail(str(exc), code=2)
    total, missing = write_catalogue(language)
    catalogues.ui_languages.cache_clear()
    catalogues.catalogue.cache_clear()
    where = catalogues.path_of(language)
    typer.echo(f"{where}: {total} messages, {missing} to translate")
