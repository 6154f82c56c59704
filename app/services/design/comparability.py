"""Whether a live study's protocol may change without splitting the study (issue 50, item 5).

Participants enrolled before and after an amendment must be comparable, and everything stored
must keep its meaning. So a new version may reword what participants see or hear, translate,
add a language, a site or an item, and tune the robot's replies, but it may not change what
defines the experiment or the meaning of an answer already given:

- the conditions (ids and learners) and the learners' settings;
- the categories: their names, questions (the learner's arms, in order) and the preferred one;
- the schedule (sessions, runs, the familiarisation run) and the reward map;
- the allocation (block sizes, strata, dropout replacement: the concealed sequence is computed
  from them);
- a language or a site someone takes part in or at;
- an item already answered: it must stay, with its kind, its scale's range, its reverse keying,
  its instrument's timing, and (a choice) every option already chosen.

What would break one of these belongs in a new study started from the changed protocol (a split).
"""

from __future__ import annotations

from dataclasses import dataclass

from sqlalchemy import select
from sqlalchemy.orm import Session

from app.protocol import ItemSpec, Protocol
from app.tables import Participant, Response, Study


@dataclass(frozen=True)
class InUse:
    """What a study's participants have used so far, which a new version must keep."""

    languages: frozenset[str]
    sites: frozenset[str]
    answered: frozenset[tuple[str, str]]
    """(instrument, item) pairs with at least one stored answer."""
    chosen: frozenset[tuple[str, str, str]]
    """(instrument, item, value) of the choice answers given."""


def in_use(db: Session, study: Study, protocol: Protocol) -> InUse:
    """Read what the study's participants have used (pilots included: their data stay); of the
    answers, only which items were answered and the values of ``protocol``'s choice items (free
    text is never read here)."""
    people = select(Participant.id).where(Participant.study_id == study.id)
    languages = db.scalars(
        select(Participant.language)
        .where(Participant.study_id == study.id, Participant.language.is_not(None))
        .distinct()
    )
    sites = db.scalars(
        select(Participant.site)
        .where(Participant.study_id == study.id, Participant.site.is_not(None))
        .distinct()
    )
    answered = db.execute(
        select(Response.instrument, Response.item)
        .where(Response.participant_id.in_(people))
        .distinct()
    ).all()
    choices = [key for key, (_, item) in _items(protocol).items() if item.kind == "choice"]
    chosen = []
    for instrument, item in choices:
        values = db.scalars(
            select(Response.value)
            .where(
                Response.participant_id.in_(people),
                Response.instrument == instrument,
                Response.item == item,
            )
            .distinct()
        )
        chosen += [(instrument, item, str(value)) for value in values]
    return InUse(
        languages=frozenset(str(code) for code in languages),
        sites=frozenset(str(site) for site in sites),
        answered=frozenset((instrument, item) for instrument, item in answered),
        chosen=frozenset(chosen),
    )


def problems(old: Protocol, new: Protocol, used: InUse) -> list[str]:
    """Why ``new`` cannot replace ``old`` in the same study (empty: it can)."""
    found: list[str] = []
    conditions = [(c.id, c.learner) for c in old.conditions]
    if [(c.id, c.learner) for c in new.conditions] != conditions:
        found.append("conditions: their ids and learners must stay as they are")
    if new.learners != old.learners:
        found.append("learners: the learners' settings must stay as they are")
    categories = [(c.name, list(c.questions), c.preferred) for c in old.categories]
    if [(c.name, list(c.questions), c.preferred) for c in new.categories] != categories:
        found.append(
            "categories: their names, questions (the arms, in order) and preferred question "
            "must stay as they are"
        )
    if new.schedule != old.schedule:
        found.append("schedule: the sessions and runs must stay as they are")
    if new.reward != old.reward:
        found.append("reward: the reward of each answer must stay as it is")
    if new.allocation != old.allocation:
        found.append(
            "allocation: the block sizes, strata and dropout replacement must stay as they are "
            "(the concealed sequence is computed from them)"
        )
    dropped = sorted(used.languages - set(new.study.languages))
    if dropped:
        found.append(f"study.languages: {', '.join(dropped)} must stay (participants use it)")
    new_sites = set(new.sites.names) if new.sites is not None else set()
    gone = sorted(used.sites - new_sites)
    if gone:
        found.append(f"sites: {', '.join(gone)} must stay (participants take part there)")
    found += _answered_items(old, new, used)
    return found


def _items(protocol: Protocol) -> dict[tuple[str, str], tuple[str, ItemSpec]]:
    return {
        (instrument.key, item.key): (instrument.when, item)
        for instrument in protocol.questionnaires.instruments
        for item in instrument.items
    }


def _range(protocol: Protocol, item: ItemSpec) -> tuple[int | None, int | None]:
    if item.scale is None:
        return item.minimum, item.maximum
    try:
        scale = protocol.scale(item.scale)
    except (KeyError, ValueError):
        return None, None
    return scale.minimum, scale.maximum


def _answered_items(old: Protocol, new: Protocol, used: InUse) -> list[str]:
    before, after = _items(old), _items(new)
    found = []
    for key in sorted(used.answered):
        if key not in before:
            continue  # answered under an earlier version's item: already checked then
        name = f"questionnaires.{key[0]}.{key[1]}"
        if key not in after:
            found.append(f"{name}: already answered, so it must stay")
            continue
        (was_when, was), (now_when, now) = before[key], after[key]
        if (now.kind, now.reverse, now_when) != (was.kind, was.reverse, was_when):
            found.append(f"{name}: already answered, so its kind, reverse keying and timing stay")
        if _range(new, now) != _range(old, was):
            found.append(f"{name}: already answered, so its scale's range stays")
        chosen = {value for i, k, value in used.chosen if (i, k) == key}
        missing = sorted(chosen - {option.value for option in now.options})
        if was.kind == "choice" and missing:
            found.append(f"{name}: the options {', '.join(missing)} were chosen, so they stay")
    return found
