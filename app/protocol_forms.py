"""A protocol's sections as forms, for an experimenter who has never seen TOML (issue 50).

The forms hold no second copy of the protocol. A section's fields are built from the protocol's
own models (app.protocol: each field's type, limits and description make its input and its rule)
with the values of the protocol's current text; a submitted form is written back into that text
with tomlkit, and only where a value changed, so comments, layout and the other sections stay
byte for byte. The text is then checked and saved as any text is (app.services.
protocol_versions), so the forms and the TOML view always show one protocol.

A field's name is the key path the problems name (``conditions[0].label``,
``translations.sv.categories.conation.questions``), so each problem is shown beside its field.
Lists of tables (conditions, categories, instruments and their items, the room's zones) render
one group per entry, each with a *remove* box, and an *add* button that draws one empty entry
more; ``<list>#entries`` says how many entries a submitted form holds.
"""

from __future__ import annotations

import enum
import itertools
import re
import tomllib
import types
import typing
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal, Union

import annotated_types
import tomlkit
from pydantic import BaseModel, StringConstraints
from pydantic.fields import FieldInfo
from pydantic_core import PydanticUndefined
from tomlkit.items import AoT, Array, InlineTable, Table

from app.i18n import protocol_texts
from app.i18n.languages import native_name
from app.protocol import Protocol

Kind = Literal[
    "text",
    "long_text",
    "number",
    "checkbox",
    "choice",
    "lines",
    "numbers",
    "pairs",
    "group",
    "list",
]
Location = tuple[str | int, ...]
ENTRIES = "#entries"
"""Suffix of the hidden field saying how many entries of a list a form holds."""
REMOVE = "remove"
"""The name of the check boxes marking list entries to remove (their value: the entry's name)."""
LONG_TEXTS = {"description", "text", "instructions", "citation", "yes", "no", "reprompt", "source"}
"""Text fields drawn as a text area (consent text, instructions, reply lines)."""
PATTERN_RULES = {
    r"^[a-z][a-z0-9_]{0,39}$": "lower-case letters, digits and _, starting with a letter",
    r"^[A-Za-z][A-Za-z0-9_-]{0,31}$": "letters, digits, _ and -, starting with a letter",
    r"^#[0-9a-fA-F]{6}$": "a colour as #rrggbb",
}


@dataclass(frozen=True)
class Section:
    """A page of the designer: a title, what it holds, and the protocol keys it edits."""

    slug: str
    title: str
    summary: str
    paths: tuple[str, ...]
    skip: tuple[str, ...] = ()
    """Key paths of fields another section edits (the languages, in the study section)."""


SECTIONS = (
    Section(
        "study",
        "Study and consent",
        "The title, the rules participants are told, blinding, the schedule, the consent text, "
        "what a withdrawal may do with the data and how long it is kept.",
        ("study", "schedule", "questionnaires.consent", "withdrawal", "retention"),
        skip=("study.languages", "study.language_choice"),
    ),
    Section(
        "conditions",
        "Conditions and learners",
        "The conditions participants are allocated to, each with its learner, and the learners' "
        "settings.",
        ("conditions", "learners"),
    ),
    Section(
        "categories",
        "Categories, questions and arms",
        "Each category's questions (the learner's arms, in order) and the one the rules make "
        "right; the reward each answer gives.",
        ("categories", "reward"),
    ),
    Section(
        "replies",
        "Replies",
        "The robot's line after each answer, per confidence level, and the thresholds between "
        "the levels.",
        ("replies",),
    ),
    Section(
        "speech",
        "Speech",
        "The phrases that count as yes and as no, how long the robot listens and what it says "
        "when it did not catch an answer.",
        ("speech",),
    ),
    Section(
        "room",
        "The room",
        "The escape room's floor plan in metres: its size, start and exit, the robot, the walls "
        "and one trigger zone per category.",
        ("room",),
    ),
    Section(
        "allocation",
        "Allocation and strata",
        "The permuted blocks participants are allocated in, the stratification factors and "
        "their values, and whether a dropout's replacement takes their condition.",
        ("allocation",),
    ),
    Section(
        "sites",
        "Sites",
        "The places a multi-site study runs at (none: a single place).",
        ("sites",),
    ),
    Section(
        "online",
        "Online",
        "Running the study from a public link with no experimenter: the recruitment platform's "
        "parameters, the completion and screen-out links, the time limit, the devices allowed "
        "and the participants wanted per condition (none: in the lab only).",
        ("online",),
    ),
    Section(
        "quality",
        "Data quality",
        "What counts as careless answering (too fast, one answer throughout, away from the page, "
        "failed attention checks) and which of those flags leave a participant out of the "
        "analysis. Attention checks are items given an expected answer under Questionnaires.",
        ("quality",),
    ),
    Section(
        "languages",
        "Languages and translations",
        "The study's languages, and every participant-facing text in each further language "
        "beside the first language's.",
        ("study.languages", "study.language_choice"),
    ),
    Section(
        "questionnaires",
        "Questionnaires",
        "The response scales, the instruments with their items (reverse-keyed ones marked) and "
        "the scores computed from them.",
        ("questionnaires.scales", "questionnaires.instruments", "questionnaires.scores"),
    ),
)
SECTION_SLUGS = {section.slug: section for section in SECTIONS}


@dataclass
class FormField:
    """One input of a section's form (or a group of them: a table, a list, a list's entry)."""

    name: str
    label: str
    kind: Kind
    location: Location
    value: str = ""
    placeholder: str = ""
    rule: str = ""
    choices: tuple[str, ...] = ()
    children: list[FormField] = field(default_factory=list)
    source: str = ""
    """Beside a translation: the text in the protocol's first language."""
    new: bool = False
    """A list entry the form added, not in the protocol yet."""
    removed: bool = False
    problems: list[str] = field(default_factory=list)
    theirs: str | None = None
    """After a refused save: the value someone else saved meanwhile, where this form changed
    the same field (the form's own value is shown)."""
    annotation: Any = None
    optional: bool = True

    @property
    def title(self) -> str:
        """The label as people read it (``language choice`` for ``language_choice``)."""
        return self.label.replace("_", " ")

    @property
    def id(self) -> str:
        """An HTML id for the field (its problems' element is ``problems-`` + this)."""
        return "f-" + re.sub(r"[^A-Za-z0-9_-]", "_", self.name)

    def leaves(self) -> Iterator[FormField]:
        """Every input below (or this one)."""
        if self.kind in ("group", "list"):
            for child in self.children:
                yield from child.leaves()
        else:
            yield self

    def walk(self) -> Iterator[FormField]:
        """This field and everything below it."""
        yield self
        for child in self.children:
            yield from child.walk()


# ---------------------------------------------------------------------------------- types


def _unwrap(annotation: Any) -> tuple[Any, list[Any], bool]:
    """The type without ``Annotated`` and ``| None``: (type, its metadata, whether optional)."""
    metadata: list[Any] = []
    optional = False
    while True:
        origin = typing.get_origin(annotation)
        if origin is typing.Annotated:
            annotation, *extra = typing.get_args(annotation)
            metadata.extend(extra)
        elif origin in (Union, types.UnionType):
            args = [a for a in typing.get_args(annotation) if a is not type(None)]
            optional = optional or len(args) < len(typing.get_args(annotation))
            if len(args) != 1:
                return annotation, metadata, optional
            annotation = args[0]
        else:
            return annotation, metadata, optional


def _is_model(annotation: Any) -> bool:
    return isinstance(annotation, type) and issubclass(annotation, BaseModel)


def _is_number(annotation: Any) -> bool:
    return annotation in (int, float)


def _choices(annotation: Any) -> tuple[str, ...]:
    if typing.get_origin(annotation) is Literal:
        return tuple(str(a) for a in typing.get_args(annotation))
    if isinstance(annotation, type) and issubclass(annotation, enum.Enum):
        return tuple(str(member.value) for member in annotation)
    return ()


def _kind(name: str, annotation: Any) -> Kind | None:
    """How a value of this type is edited (None: only in the TOML view)."""
    if annotation is bool:
        return "checkbox"
    if _is_number(annotation):
        return "number"
    if _choices(annotation):
        return "choice"
    if annotation is str:
        return "long_text" if name in LONG_TEXTS else "text"
    if _is_model(annotation):
        return "group"
    origin = typing.get_origin(annotation)
    if origin is list:
        (inner,) = typing.get_args(annotation)
        inner, _, _ = _unwrap(inner)
        if _is_model(inner):
            return "list"
        return "numbers" if _is_number(inner) else "lines"
    if origin is dict:
        _, value = typing.get_args(annotation)
        value, _, _ = _unwrap(value)
        if value is str or _is_number(value) or typing.get_origin(value) is list:
            return "pairs"
    return None


def _default(info: FieldInfo) -> Any:
    if info.default_factory is not None:
        return info.default_factory()  # type: ignore[call-arg]
    return None if info.default is PydanticUndefined else info.default


def _rule(info: FieldInfo, annotation: Any, metadata: list[Any], required: bool) -> str:
    """What the field takes, in words: its description, limits and default."""
    parts = [info.description.rstrip(".") + "." if info.description else ""]
    limits = []
    for item in [*info.metadata, *metadata]:
        if isinstance(item, annotated_types.Ge):
            limits.append(f"at least {item.ge}")
        elif isinstance(item, annotated_types.Gt):
            limits.append(f"more than {item.gt}")
        elif isinstance(item, annotated_types.Le):
            limits.append(f"at most {item.le}")
        elif isinstance(item, annotated_types.Lt):
            limits.append(f"less than {item.lt}")
        elif isinstance(item, annotated_types.MinLen) and item.min_length > 1:
            limits.append(f"at least {item.min_length} entries")
        elif isinstance(item, annotated_types.MaxLen):
            limits.append(f"at most {item.max_length} entries")
        elif isinstance(item, StringConstraints) and item.pattern:
            limits.append(PATTERN_RULES.get(str(item.pattern), f"matching {item.pattern}"))
    if annotation is int:
        limits.insert(0, "a whole number")
    elif annotation is float:
        limits.insert(0, "a number")
    if limits:
        parts.append(limits[0][0].upper() + ", ".join(limits)[1:] + ".")
    if required:
        parts.append("Required.")
    else:
        default = _default(info)
        if isinstance(default, bool):
            parts.append(f"Default: {'on' if default else 'off'}.")
        elif default not in (None, "", [], {}) and not isinstance(default, BaseModel):
            parts.append(f"Default: {_display(default)}.")
    return " ".join(p for p in parts if p)


def _display(value: Any) -> str:
    """A value as its input shows it."""
    if value is None:
        return ""
    if isinstance(value, bool):
        return "on" if value else ""
    if isinstance(value, list):
        if all(isinstance(v, int | float) and not isinstance(v, bool) for v in value) and value:
            return ", ".join(str(v) for v in value)
        return "\n".join(str(v) for v in value)
    if isinstance(value, dict):
        return "\n".join(
            f"{k} = {', '.join(map(str, v)) if isinstance(v, list) else v}"
            for k, v in value.items()
        )
    return str(value)


# ----------------------------------------------------------------------------------- build


def _get(data: Any, location: Location) -> Any:
    for step in location:
        if isinstance(step, int):
            if not isinstance(data, list) or step >= len(data):
                return None
            data = data[step]
        else:
            if not isinstance(data, dict) or step not in data:
                return None
            data = data[step]
    return data


def _name(location: Location) -> str:
    name = ""
    for step in location:
        name += f"[{step}]" if isinstance(step, int) else (f".{step}" if name else step)
    return name


def _model_at(path: str) -> tuple[FieldInfo, Any]:
    """The model field a dotted top-level path names (``questionnaires.consent``)."""
    model: Any = Protocol
    info: FieldInfo | None = None
    for part in path.split("."):
        info = model.model_fields[part]
        model, _, _ = _unwrap(info.annotation)
    assert info is not None
    return info, info.annotation


def _field(
    label: str, info: FieldInfo, annotation: Any, location: Location, data: Any, counts: Counts
) -> FormField | None:
    inner, metadata, optional = _unwrap(annotation)
    kind = _kind(label, inner)
    if kind is None:
        return None
    required = info.is_required() and not optional
    current = _get(data, location)
    made = FormField(
        name=_name(location),
        label=label,
        kind=kind,
        location=location,
        rule=_rule(info, inner, metadata, required),
        choices=_choices(inner),
        annotation=inner,
        optional=not required,
    )
    if kind == "group":
        made.children = _model_fields(inner, location, data, counts)
    elif kind == "list":
        (entry,) = typing.get_args(inner)
        entry, _, _ = _unwrap(entry)
        stored = len(current) if isinstance(current, list) else 0
        for index in range(counts.get(made.name, stored)):
            at = (*location, index)
            made.children.append(
                FormField(
                    name=_name(at),
                    label=_entry_label(_get(data, at), index),
                    kind="group",
                    location=at,
                    children=_model_fields(entry, at, data, counts),
                    new=index >= stored,
                    annotation=entry,
                )
            )
    elif kind == "checkbox":
        made.value = _display(current if current is not None else _default(info))
    else:
        made.value = _display(current)
        default = None if required else _default(info)
        if default not in (None, "", [], {}) and not isinstance(default, BaseModel):
            made.placeholder = _display(default).replace("\n", ", ")
    return made


def _entry_label(entry: Any, index: int) -> str:
    """What a list entry is called on its group: its key, name, id or category, else its
    number."""
    if isinstance(entry, dict):
        for key in ("key", "name", "id", "category", "value"):
            if isinstance(entry.get(key), str):
                return entry[key]
    return f"#{index + 1}"


Counts = Mapping[str, int]
"""List name → how many entries its form holds (absent: as many as the protocol has)."""


def _model_fields(model: Any, location: Location, data: Any, counts: Counts) -> list[FormField]:
    fields = []
    for name, info in model.model_fields.items():
        if model is Protocol and name == protocol_texts.TRANSLATIONS:
            continue
        made = _field(name, info, info.annotation, (*location, name), data, counts)
        if made is not None:
            fields.append(made)
    return fields


def section_fields(
    section: Section, text: str, counts: Counts | None = None, languages: Sequence[str] = ()
) -> list[FormField]:
    """The section's fields with the values of the protocol ``text``; ``counts``: entries per
    list (a form's, plus one where an entry was added); ``languages``: the languages a form
    declares (the languages section draws a translation column for each)."""
    data = tomllib.loads(text)
    counts = counts or {}
    fields = []
    for path in section.paths:
        info, annotation = _model_at(path)
        location = tuple(path.split("."))
        made = _field(location[-1], info, annotation, location, data, counts)
        if made is not None:
            fields.append(made)
    fields = _without(fields, section.skip)
    if section.slug == "languages":
        fields += _translation_fields(data, languages)
    return fields


def _without(fields: list[FormField], skip: Sequence[str]) -> list[FormField]:
    kept = [made for made in fields if made.name not in skip]
    for made in kept:
        made.children = _without(made.children, skip)
    return kept


def _translation_fields(data: dict[str, Any], languages: Sequence[str]) -> list[FormField]:
    """One group per further language: every participant-facing text beside the first
    language's (app.i18n.protocol_texts names them)."""
    declared = list(languages) or list(data.get("study", {}).get("languages", ["en"]))
    slots = protocol_texts.text_slots(data)
    groups = []
    for language in declared[1:]:
        table = (data.get(protocol_texts.TRANSLATIONS) or {}).get(language) or {}
        given = protocol_texts.flatten(table) if isinstance(table, dict) else {}
        base: Location = (protocol_texts.TRANSLATIONS, language)
        children = [
            FormField(
                name=_name((*base, protocol_texts.SOURCE)),
                label="where the translation comes from",
                kind="long_text",
                location=(*base, protocol_texts.SOURCE),
                value=_display(given.get(protocol_texts.SOURCE)),
                rule="Who made it, or the published versions it uses; the report cites it.",
                annotation=str,
            )
        ]
        for slot in slots:
            at = (*base, *slot.path.split("."))
            children.append(
                FormField(
                    name=f"{_name(base)}.{slot.path}",
                    label=slot.path,
                    kind="long_text" if slot.shape == "text" else "lines",
                    location=at,
                    value=_display(given.get(slot.path)),
                    source=_display(slot.source),
                    rule="One per line, as many as in the first language."
                    if slot.shape == "lines"
                    else ("One per line, any number." if slot.shape == "phrases" else ""),
                    annotation=str if slot.shape == "text" else list[str],
                    optional=False,
                )
            )
        groups.append(
            FormField(
                name=_name(base),
                label=f"{native_name(language)} ({language})",
                kind="group",
                location=base,
                children=children,
            )
        )
    return groups


# ------------------------------------------------------------------------------ submission


def form_counts(form: Mapping[str, Any], add: str = "") -> dict[str, int]:
    """Entries per list as a submitted form holds them, one more where ``add`` names a list."""
    counts = {
        key.removesuffix(ENTRIES): int(value)
        for key, value in form.items()
        if key.endswith(ENTRIES) and str(value).isdigit() and int(value) <= 500
    }
    if add:
        counts[add] = counts.get(add, 0) + 1
    return counts


def form_languages(form: Mapping[str, Any]) -> list[str]:
    """The languages a submitted languages section declares (none: not that section)."""
    return [line.strip() for line in str(form.get("study.languages", "")).splitlines() if line]


def shown_with(
    fields: list[FormField], form: Mapping[str, Any], removed: Sequence[str]
) -> list[FormField]:
    """The fields showing what was submitted (a refused save, an added entry), nothing lost."""
    for top in fields:
        for made in top.walk():
            if made.kind in ("group", "list"):
                made.removed = made.name in removed
                continue
            if made.kind == "checkbox":
                made.value = "on" if made.name in form else ""
            elif made.name in form:
                made.value = _normalised(str(form[made.name]))
    return fields


def _submitted(made: FormField, form: Mapping[str, Any]) -> str | None:
    """What the form says of a field (None: it does not carry it)."""
    if made.kind == "checkbox":
        return "on" if made.name in form else ""
    return _normalised(str(form[made.name])) if made.name in form else None


def rebase_form(
    section: Section, base_text: str, current_text: str, form: Mapping[str, Any]
) -> tuple[list[tuple[str, str]], dict[str, str]]:
    """A form drawn from an earlier version carried over to the current one, after a refused
    save: each field the form changed keeps the form's value, every other field takes the
    current one (so saving it again undoes nobody's change unseen), and entries the form added
    follow the current entries. Also returns, for each field both changed, the current value."""
    languages = form_languages(form) if section.slug == "languages" else []
    base = section_fields(section, base_text, form_counts(form), languages)
    current = section_fields(section, current_text, {}, languages)
    current_leaves = {leaf.name: leaf for top in current for leaf in top.leaves()}
    lists = {made.name: made for top in current for made in top.walk() if made.kind == "list"}
    values = {name: leaf.value for name, leaf in current_leaves.items()}
    added: dict[str, int] = {}
    theirs: dict[str, str] = {}
    for made in (made for top in base for made in top.walk() if made.kind == "list"):
        stored = sum(1 for entry in made.children if not entry.new)
        added[made.name] = len(made.children) - stored
    for leaf in (leaf for top in base for leaf in top.leaves()):
        submitted = _submitted(leaf, form)
        if submitted is None or (submitted == _normalised(leaf.value) and not _is_new(leaf, base)):
            continue
        target = _moved(leaf.name, base, lists)
        mine = current_leaves.get(target)
        if mine is not None and _normalised(mine.value) not in (_normalised(leaf.value), submitted):
            theirs[target] = mine.value
        values[target] = submitted
    pairs = [(name, value) for name, value in values.items() if value or name in current_leaves]
    pairs = [
        (name, value)
        for name, value in pairs
        if not (name in current_leaves and current_leaves[name].kind == "checkbox" and not value)
    ]
    for name, made in lists.items():
        pairs.append((name + ENTRIES, str(len(made.children) + added.get(name, 0))))
    for name, count in added.items():
        if name not in lists and count:
            pairs.append((name + ENTRIES, str(count)))
    pairs += [(REMOVE, str(name)) for name in _getlist(form, REMOVE)]
    return pairs, theirs


def _is_new(leaf: FormField, fields: list[FormField]) -> bool:
    return _inside_new(leaf, fields)


def _moved(name: str, base: list[FormField], current_lists: Mapping[str, FormField]) -> str:
    """The name a field of an entry the form added takes after the current entries."""
    for made in (made for top in base for made in top.walk() if made.kind == "list"):
        stored = sum(1 for entry in made.children if not entry.new)
        found = re.fullmatch(re.escape(made.name) + r"\[(\d+)\](.*)", name)
        if found and int(found.group(1)) >= stored:
            now = len(current_lists[made.name].children) if made.name in current_lists else 0
            return f"{made.name}[{now + int(found.group(1)) - stored}]{found.group(2)}"
    return name


def _normalised(value: str) -> str:
    return "\n".join(line.rstrip() for line in value.replace("\r\n", "\n").split("\n")).strip()


def _parsed(made: FormField, shown: str) -> Any:
    """The submitted value as TOML takes it; what cannot be converted stays text, for the
    protocol's check to name beside the field. None: remove the key."""
    if made.kind == "checkbox":
        return bool(shown)
    if not shown:
        if made.kind in ("lines", "numbers", "pairs") and not made.optional:
            return []
        return None
    if made.kind == "number":
        return _number(shown, made.annotation)
    if made.kind == "lines":
        return [line.strip() for line in shown.split("\n") if line.strip()]
    if made.kind == "numbers":
        inner, _, _ = _unwrap(typing.get_args(made.annotation)[0])
        return [_number(part, inner) for part in re.split(r"[,\s]+", shown) if part]
    if made.kind == "pairs":
        _, value_type = typing.get_args(made.annotation)
        listed = typing.get_origin(_unwrap(value_type)[0]) is list
        pairs: dict[str, Any] = {}
        for line in shown.split("\n"):
            key, _, value = line.partition("=")
            if key.strip():
                value = value.strip()
                pairs[key.strip()] = (
                    [v.strip() for v in value.split(",") if v.strip()] if listed else value
                )
        return pairs
    return shown


def _number(text: str, annotation: Any) -> Any:
    try:
        return int(text) if annotation is int else float(text)
    except ValueError:
        return text


def _toml_value(value: Any) -> Any:
    if isinstance(value, str) and "\n" in value:
        return tomlkit.string(value, multiline=True)
    return value


def _container(doc: Any, location: Location) -> Any:
    """The table or array holding ``location``'s last step, made where missing."""
    here = doc
    for step, following in itertools.pairwise(location):
        if isinstance(step, int):
            here = here[step]
            continue
        if step not in here:
            inline = isinstance(here, InlineTable)
            if isinstance(following, int):
                here[step] = tomlkit.array() if inline else tomlkit.aot()
            else:
                here[step] = tomlkit.inline_table() if inline else tomlkit.table()
        here = here[step]
    return here


def _write(doc: Any, location: Location, value: Any) -> None:
    holder = _container(doc, location)
    last = location[-1]
    if value is None:
        if isinstance(last, str) and last in holder:
            del holder[last]
        return
    holder[last] = _toml_value(value)


def _entry_values(group: FormField, form: Mapping[str, Any]) -> dict[str, Any]:
    """A new list entry's values as a table (empty: nothing was filled in)."""
    values: dict[str, Any] = {}
    for child in group.children:
        if child.kind == "group":
            nested = _entry_values(child, form)
            if nested:
                values[str(child.location[-1])] = nested
            continue
        if child.kind == "list":
            continue  # a new entry's own lists are filled in once it is saved
        shown = _normalised(str(form.get(child.name, "")))
        value = _parsed(child, "on" if child.kind == "checkbox" and child.name in form else shown)
        if value not in (None, [], {}, False):
            values[str(child.location[-1])] = value
    return values


def _append(doc: Any, made: FormField, values: dict[str, Any]) -> None:
    holder = _container(doc, made.location)
    if made.location[-1] not in holder:
        holder[made.location[-1]] = (
            tomlkit.array() if isinstance(holder, InlineTable | Array) else tomlkit.aot()
        )
    target = holder[made.location[-1]]
    if isinstance(target, AoT):
        table = tomlkit.table()
        for key, value in values.items():
            table[key] = _toml_value(value)
        target.append(table)
    else:
        inline = tomlkit.inline_table()
        inline.update(values)
        target.append(inline)


def apply_form(section: Section, text: str, form: Mapping[str, Any]) -> str:
    """The protocol ``text`` with the submitted section ``form`` written into it: changed values
    only, removed entries gone, filled-in new entries appended, and, in the languages section,
    the translations of a language no longer declared dropped."""
    languages = form_languages(form) if section.slug == "languages" else []
    fields = section_fields(section, text, form_counts(form), languages)
    removed = [str(v) for v in _getlist(form, REMOVE)]
    doc = tomlkit.parse(text)
    removals: list[FormField] = []
    for top in fields:
        for made in top.walk():
            if made.kind == "list":
                for entry in made.children:
                    if entry.name in removed and not entry.new:
                        removals.append(entry)
                    elif entry.new and entry.name not in removed:
                        values = _entry_values(entry, form)
                        if values:
                            _append(doc, made, values)
                continue
            if made.kind == "group" or _inside_new(made, fields):
                continue
            shown = "on" if made.kind == "checkbox" and made.name in form else ""
            if made.kind != "checkbox":
                if made.name not in form:
                    continue
                shown = _normalised(str(form[made.name]))
            if shown == _normalised(made.value):
                continue
            _write(doc, made.location, _parsed(made, shown))
    for entry in sorted(removals, key=lambda e: e.location, reverse=True):
        holder = _container(doc, entry.location)
        del holder[entry.location[-1]]
    if section.slug == "languages" and languages:
        table = doc.get(protocol_texts.TRANSLATIONS)
        if isinstance(table, Table):
            for language in [k for k in table if k not in languages[1:]]:
                del table[language]
    return tomlkit.dumps(doc)


def _inside_new(made: FormField, fields: list[FormField]) -> bool:
    """Whether a field belongs to a list entry the form added (written by its entry)."""
    for top in fields:
        for group in top.walk():
            if group.new and made.location[: len(group.location)] == group.location:
                return True
    return False


def _getlist(form: Mapping[str, Any], key: str) -> list[Any]:
    getter = getattr(form, "getlist", None)
    if getter is not None:
        return list(getter(key))
    value = form.get(key)
    return [] if value is None else (value if isinstance(value, list) else [value])


@dataclass(frozen=True)
class Elsewhere:
    """A problem no field of the section holds, and the section that edits its key."""

    text: str
    section: Section | None


def section_of(path: str) -> Section | None:
    """The section whose form edits the key ``path`` (None: the TOML view only)."""
    found = None
    for section in SECTIONS:
        for prefix in section.paths:
            if path == prefix or path.startswith((f"{prefix}.", f"{prefix}[")):
                found = section
    if path.startswith(f"{protocol_texts.TRANSLATIONS}."):
        return SECTION_SLUGS["languages"]
    return found


def place_problems(fields: list[FormField], problems: Sequence[tuple[str, str]]) -> list[Elsewhere]:
    """Put each problem ``(key path, reason)`` beside the field whose name is the longest prefix
    of its path; what no field of the section holds is returned (shown above the form, with
    the section to put it right in)."""
    by_name = {made.name: made for top in fields for made in top.walk() if made.name}
    elsewhere = []
    for path, reason in problems:
        holder = next((by_name[p] for p in _prefixes(path) if p in by_name), None)
        if holder is not None:
            holder.problems.append(reason)
        else:
            text = f"{path}: {reason}" if path else reason
            elsewhere.append(Elsewhere(text, section_of(path) if path else None))
    return elsewhere


def _prefixes(path: str) -> Iterator[str]:
    """``a.b[2].c``, ``a.b[2]``, ``a.b``, ``a``."""
    while path:
        yield path
        shorter = re.sub(r"(\[\d+\]|\.[^.\[]+)$", "", path)
        if shorter == path:
            return
        path = shorter
