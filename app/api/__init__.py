"""The JSON API under /api/v1, documented at /api/v1/openapi.json."""
