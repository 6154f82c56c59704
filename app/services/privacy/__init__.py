"""Privacy: consent and its versions, sites (who may see whom), the registry of personal data,
erasure, retention, subject access and pseudonyms."""
