"""Pydantic models shared by the API, the worker and the CLI (no Mitsuba, no torch)."""
