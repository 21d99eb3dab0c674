"""One router per resource: jobs, artifacts, events, scenes, health."""
