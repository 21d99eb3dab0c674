"""A small Python client of the NDRF service (``ndrf submit/watch/fetch/ls --server``).

Standard library only: importable without Mitsuba, torch, numpy or the service's own packages
(an import-linter contract checks it), so a notebook or a CI job can drive a remote server::

    from client import Client

    api = Client("http://gpu-box:8000", api_key="...")        # or Client.from_env()
    job = api.submit_job(json.load(open("job.json")))
    for event in api.events(job["id"]):                       # SSE, reconnecting with Last-Event-ID
        print(event["type"], event.get("iteration"))
    exp = api.submit_experiment({"base": ..., "grid": {"method": ["prb", "ndrf-rhs"]}, "seeds": [0, 1, 2]})
    print(api.results_csv(exp["id"]))
"""

from client.http import ApiError, Client, is_experiment_id, is_job_id
from client.scenes import pack_scene

__all__ = ["ApiError", "Client", "is_experiment_id", "is_job_id", "pack_scene"]
