"""Participants and their lifecycle: enrolment and allocation, languages, tablet links, the
questionnaire flow, each participant's record, and the one function that applies a change to a
participant and tells every view."""
