"""The HTTP API (FastAPI) and the web dashboard. Starts without importing Mitsuba or torch."""
