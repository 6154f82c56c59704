"""Participants' languages: a protocol's texts per language, the interface's message catalogues."""
