"""Business logic: keyword-only, typed functions shared by the web handlers and the CLI.

Functions named as commands (``enroll_participant``, ``create_study`` …) are transaction
boundaries: they validate, change the database, append to the audit log and commit before they
return, so whatever a caller acknowledges is already durable. Helpers they share never commit.
"""
