"""Designing a study before (and while) it runs: its phases, draft → pilot → live
(study_phases), and the versions of its protocol (protocol_versions)."""
