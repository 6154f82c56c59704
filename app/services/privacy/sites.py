"""Sites: several places sharing one server, each seeing only its own participants.

Like REDCap's data access groups:

- a study's protocol may declare its sites (``[sites] names``); every participant of such a study
  is enrolled at one of them (``participant.site``), and with ``[sites] stratify = true`` the site
  is a stratification factor (``site``), so each site's allocation is balanced on its own;
- an experimenter's or analyst's account may be limited to some sites (``user.sites``). For that
  account, a participant anywhere else — and every participant of a study without sites — does not
  exist: lists, counts, the dashboard, analyses and exports leave them out, and naming one (a
  participant page, seating, withdrawal, erasure, the API) answers 404 as for an unknown code;
- admins (the PI) and accounts without a limit see every site.

The limit travels with the :class:`~app.services.audit.Actor` (``actor.sites``), so every service
that shows or changes participants filters with :func:`visible` in SQL or checks with
:func:`require_visible`; pages narrowing a view to one site (the dashboard's and the analysis's
site filter) pass a narrowed actor (:func:`narrowed`). A reader that has no actor to record
(the analysis and its exports, the power planning) takes a :class:`Scope`, a required argument
built from the account by one dependency (``app.deps.ReaderScope``) or, on the command line,
said out loud (:meth:`Scope.every_site`): there is no optional ``sites=`` to forget.

What reaches a limited account is its sites' participants in every form: rows, counts,
estimates, and their activity on the live streams (:func:`event_site`, :func:`reaches`: an
event names the site of the participant it is about, and a limited account's stream passes only
its own sites' events and the study-wide ones). Participant codes are a study's, unique in it,
and in a study with sites each begins with its site's name (:func:`check_code`), so a code typed
at one site can never meet another site's: "already used" is only ever said of a participant
the account can see, and nobody can test whether a code exists elsewhere.

Stations may belong to a site (``station.site``): such a station seats only its site's
participants (:func:`check_seating`) and does not exist for an account limited to other sites
(:func:`station_hidden`, :func:`visible_stations`). A shared station (no site) is seen by every
account, but what its robots did (last heard, connected, notices) tells when another site used
it, so a limited account sees that only from the moment one of its own participants is seated
there (:class:`Contact`), and the robots' live events name the site that may hear them
(:func:`device_event_site`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable
from dataclasses import dataclass
from datetime import datetime

from sqlalchemy import ColumnElement, select, true
from sqlalchemy.orm import Session

from app.errors import Conflict, InvalidInput, NotFound, PermissionDenied
from app.events import Event
from app.protocol import Protocol
from app.services import audit
from app.services.audit import Actor
from app.services.staff import users
from app.services.studies import list_studies, protocol_of
from app.tables import Participant, Role, Station, Study, User


@dataclass(frozen=True)
class Scope:
    """The participants a reader may see: those of ``sites`` (a limited account's, or a page's
    site filter), or of every site (``sites`` None).

    Every query that reads participant data for someone without an :class:`Actor` to record
    takes one, as a required argument: the analysis, its exports and the power planning.
    """

    sites: frozenset[str] | None

    @classmethod
    def of(cls, actor: Actor) -> Scope:
        """What ``actor`` may see (a narrowed actor's site, a limited account's sites)."""
        return cls(actor.sites)

    @classmethod
    def every_site(cls) -> Scope:
        """Every participant: the command line's (whoever holds the server sees every site)."""
        return cls(None)

    @property
    def limited(self) -> bool:
        """Whether some participants are out of sight."""
        return self.sites is not None

    def narrowed(self, site: str, study: Study) -> Scope:
        """This scope seeing only ``site`` (a page's ``?site=`` filter; itself when empty),
        refused as :func:`narrowed` refuses."""
        return Scope(_narrowed(self.sites, site, study))

    def where(self) -> ColumnElement[bool]:
        """A WHERE clause keeping the participants in scope."""
        if self.sites is None:
            return true()
        return Participant.site.in_(sorted(self.sites))

    def sees_site(self, site: str | None) -> bool:
        """Whether a participant of ``site`` (None: of a study without sites) is in scope."""
        return self.sites is None or (site is not None and site in self.sites)


STUDY_WIDE = "*"
"""The ``site`` of a live event about no participant in particular (a new consent version, the
study unblinded, a device key): every reader of the study or station may hear of it."""


def event_site(participant: Participant | None) -> str | None:
    """The ``site`` a live event about ``participant`` carries (None for a study without sites,
    :data:`STUDY_WIDE` for an event about no participant)."""
    return STUDY_WIDE if participant is None else participant.site


def seated_site(db: Session, station_id: int) -> str | None:
    """The ``site`` of a live event about what happens at a station: its seated participant's
    (:func:`event_site`), :data:`STUDY_WIDE` when nobody is seated."""
    seated = db.scalar(
        select(Participant)
        .join(Station, Station.participant_id == Participant.id)
        .where(Station.id == station_id)
    )
    return event_site(seated)


def reaches(scope: Scope, event: Event) -> bool:
    """Whether a live page of a reader with ``scope`` hears ``event``.

    An event reaches a limited account only when it names a site in scope, or
    :data:`STUDY_WIDE`: an event that names no site (a publisher that forgot, or a participant of
    a study without sites) reaches unlimited accounts only, so a forgotten site makes a page
    stale, never leaks a hidden site's activity. ``site`` may be a list (one change touching
    participants of several sites, e.g. retention)."""
    if scope.sites is None or event.topic == "*":
        return True
    site = event.data.get("site")
    if site == STUDY_WIDE:
        return True
    named = site if isinstance(site, list) else [site]
    return any(isinstance(one, str) and one in scope.sites for one in named)


def code_prefix(site: str) -> str:
    """What every participant code at ``site`` begins with (``uppsala-``): automatic codes are
    numbered after it, and a typed one must start with it. Site names have no hyphen, so the
    prefix names one site."""
    return f"{site[:24]}-"


def check_code(code: str, site: str | None, *, study: Study) -> None:
    """Refuse a typed code that does not begin with its site's prefix (a study with sites).

    Codes are unique in a study (the analysis, the exports and every URL name a participant by
    code alone), so a clash is possible only within one prefix, that is within one site: an
    account limited to that site sees whoever holds the code, and "already used" tells it
    nothing about other sites."""
    if site is None:
        return
    prefix = code_prefix(site)
    if not code.startswith(prefix) or len(code) == len(prefix):
        raise InvalidInput(
            f"participant code {code!r}: a code at site {site!r} begins with {prefix!r} "
            f"(e.g. {prefix}017), or leave it out for the next one"
        )


def visible(actor: Actor) -> ColumnElement[bool]:
    """A WHERE clause keeping the participants ``actor`` may see (all when unlimited)."""
    return Scope.of(actor).where()


def sees(actor: Actor, participant: Participant) -> bool:
    """Whether ``actor`` may see this participant."""
    return actor.sites is None or participant.site in actor.sites


def not_found(study: Study, code: str) -> NotFound:
    """The refusal for a participant the caller may not see: the one an unknown code gets."""
    return NotFound(f"study {study.name!r} has no participant {code!r}")


def require_visible(actor: Actor, participant: Participant, study: Study) -> Participant:
    """``participant`` itself, or the NotFound an unknown code gets when ``actor`` may not see
    them."""
    if not sees(actor, participant):
        raise not_found(study, participant.code)
    return participant


def names(protocol: Protocol) -> list[str]:
    """The study's sites in the protocol's order (empty without ``[sites]``)."""
    return list(protocol.sites.names) if protocol.sites is not None else []


def choices(protocol: Protocol, actor: Actor) -> list[tuple[str, str]]:
    """(site, label) the actor may enrol at or filter by, in the protocol's order."""
    if protocol.sites is None:
        return []
    return [
        (name, protocol.sites.label(name))
        for name in protocol.sites.names
        if actor.sites is None or name in actor.sites
    ]


def _limit_words(sites: Iterable[str]) -> str:
    listed = sorted(sites)
    return f"site{'' if len(listed) == 1 else 's'} {', '.join(listed)}"


def enrolment_site(
    protocol: Protocol, site: str | None, *, actor: Actor, study: Study
) -> str | None:
    """The site a new participant is enrolled at, checked: one of the study's sites, and one of
    the actor's. None for a study without sites (only accounts for every site enrol there)."""
    site = (site or "").strip() or None
    declared = names(protocol)
    if not declared:
        if site is not None:
            raise InvalidInput(f"study {study.name!r} has no sites: leave the site out")
        if actor.sites is not None:
            raise PermissionDenied(
                f"your account is limited to {_limit_words(actor.sites)} and study "
                f"{study.name!r} has no sites: an account for every site enrols here"
            )
        return None
    if site is None:
        raise InvalidInput(
            f"study {study.name!r} enrols each participant at a site: give one of "
            f"{', '.join(declared)}"
        )
    if site not in declared:
        raise InvalidInput(
            f"site {site!r} is not a site of study {study.name!r}: {', '.join(declared)}"
        )
    if actor.sites is not None and site not in actor.sites:
        raise PermissionDenied(
            f"your account is limited to {_limit_words(actor.sites)}: it cannot enrol at {site!r}"
        )
    return site


def narrowed(actor: Actor, site: str, study: Study) -> Actor:
    """``actor`` seeing only ``site`` (a page's site filter); ``actor`` itself when ``site`` is
    empty. Refused for a site the study does not declare or the actor may not see."""
    within = _narrowed(actor.sites, site, study)
    return actor if within == actor.sites else dataclasses.replace(actor, sites=within)


def _narrowed(sites: frozenset[str] | None, site: str, study: Study) -> frozenset[str] | None:
    site = site.strip()
    if not site:
        return sites
    declared = names(protocol_of(study))
    if site not in declared:
        offered = ", ".join(declared) if declared else "none: it is a single-site study"
        raise InvalidInput(
            f"site: study {study.name!r} has no site {site!r} (its sites: {offered})"
        )
    if sites is not None and site not in sites:
        raise PermissionDenied(f"your account is limited to {_limit_words(sites)}")
    return frozenset({site})


def station_hidden(db: Session, station: Station, actor: Actor) -> bool:
    """Whether ``station`` is, for ``actor``, as if it did not exist: a station of a site the
    account is not limited to, or one seating a participant it may not see."""
    if actor.sites is None:
        return False
    if station.site is not None and station.site not in actor.sites:
        return True
    if station.participant_id is None:
        return False
    return _seated_participants_site(db, station.participant_id) not in actor.sites


def visible_stations(db: Session, found: list[Station], actor: Actor) -> list[Station]:
    """``found`` without the stations :func:`station_hidden` hides from ``actor``."""
    if actor.sites is None:
        return found
    seated = dict(
        db.execute(
            select(Station.id, Participant.site)
            .join(Participant, Participant.id == Station.participant_id)
            .where(Station.id.in_([station.id for station in found]))
        ).all()
    )
    return [
        s
        for s in found
        if (s.site is None or s.site in actor.sites)
        and (s.id not in seated or seated[s.id] in actor.sites)
    ]


@dataclass(frozen=True)
class Contact:
    """What a reader sees of a station's robots' contact: when each was last heard, whether it is
    connected, its console notice.

    A station of a site is used by that site only, so whoever sees it sees all of it. A shared
    station (no site) is used by every site, and its robots' contact tells when it was last
    used: an account limited to some sites sees it only while one of its own participants is
    seated there, and only from the moment they were seated (``since``); otherwise none of it
    (``withheld``). Unlimited accounts see everything.
    """

    withheld: bool = False
    since: datetime | None = None

    def when(self, moment: datetime | None) -> datetime | None:
        """``moment`` (a last contact, a notice's time) if shown, else None."""
        if moment is None or self.withheld:
            return None
        if self.since is not None and moment < self.since:
            return None
        return moment

    def connected(self, connected: bool) -> bool | None:
        """Whether the robot is connected now (None: withheld)."""
        return None if self.withheld else connected


def contact(station: Station, seated_site: str | None, actor: Actor) -> Contact:
    """What ``actor`` sees of the contact of ``station``'s robots (:class:`Contact`);
    ``seated_site``: the site of the participant seated there (None: nobody, or a participant of
    a study without sites)."""
    if actor.sites is None or station.site is not None:
        return Contact()
    if station.participant_id is not None and seated_site in actor.sites:
        return Contact(since=station.assigned_at)
    return Contact(withheld=True)


def device_event_site(db: Session, station_id: int) -> str | None:
    """The ``site`` of a live event about a station's robot (connected, a notice): the
    station's site, else its seated participant's (None: a free shared station, heard by
    unlimited accounts only, as :class:`Contact` shows it)."""
    station = db.get(Station, station_id)
    if station is None:
        return None
    if station.site is not None:
        return station.site
    if station.participant_id is None:
        return None
    return _seated_participants_site(db, station.participant_id)


def _seated_participants_site(db: Session, participant_id: int) -> str | None:
    return db.scalar(select(Participant.site).where(Participant.id == participant_id))


def station_site(db: Session, site: str | None) -> str | None:
    """A station's site, checked: empty for a shared station, else a site some study declares
    (a typo would hide the station from everyone limited)."""
    site = (site or "").strip() or None
    if site is None:
        return None
    declared = declared_anywhere(db)
    if site not in declared:
        known = ", ".join(declared) if declared else "none yet: create the study first"
        raise InvalidInput(f"site: no study declares site {site!r} (sites declared: {known})")
    return site


def check_seating(station: Station, participant: Participant, site: str | None) -> None:
    """Refuse seating ``participant`` at ``station`` of ``site`` (its own, or the one it is
    about to have) when that is another site: a station of a site seats only its participants."""
    if site is None or participant.site == site:
        return
    theirs = (
        f"is enrolled at {participant.site!r}"
        if participant.site is not None
        else "is of a study without sites"
    )
    raise Conflict(
        f"station {station.name!r} belongs to site {site!r} and seats only its "
        f"participants: {participant.code!r} {theirs}"
    )


def declared_anywhere(db: Session) -> dict[str, list[str]]:
    """Each site any study declares (archived ones too) → the studies declaring it."""
    found: dict[str, list[str]] = {}
    for study in list_studies(db):
        for name in names(protocol_of(study)):
            found.setdefault(name, []).append(study.name)
    return dict(sorted(found.items()))


def set_user_sites(
    db: Session, *, username: str, sites: Iterable[str] | None, actor: Actor
) -> User:
    """Limit an experimenter's or analyst's account to ``sites`` (None: every site); commits.

    Refused for an admin (admins see every site), for an empty list, and for a site no study
    declares: a typo would leave the account seeing nobody, silently.
    """
    user = users.named(db, username, for_update=True)
    clean: list[str] | None = None
    if sites is not None:
        if user.role == Role.ADMIN:
            raise Conflict(
                f"{user.username!r} is an admin and admins see every site: limit an "
                "experimenter's or analyst's account"
            )
        clean = sorted({site.strip() for site in sites if site.strip()})
        if not clean:
            raise InvalidInput("give at least one site (or every site: --all)")
        declared = declared_anywhere(db)
        unknown = [site for site in clean if site not in declared]
        if unknown:
            known = ", ".join(declared) if declared else "none yet: create the study first"
            raise InvalidInput(
                f"no study declares {_limit_words(unknown)} (sites declared: {known})"
            )
    if user.sites == clean:
        raise Conflict(f"{user.username!r} already sees {describe(clean)}")
    before = user.sites
    user.sites = clean
    audit.record(
        db,
        actor=actor,
        action="user.sites_changed",
        subject=user.username,
        details={"from": before, "to": clean},
    )
    db.commit()
    return user


def describe(sites: Iterable[str] | None) -> str:
    """An account's limit in words: ``every site`` or ``sites a, b``."""
    return "every site" if sites is None else _limit_words(sites)
