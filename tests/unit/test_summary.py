"""``summary.json``'s one model (#45): the answer is ``estimate`` as in every record, and a job
folder of an older version, whose answer was ``final``, reads into the same names."""

import pytest
from pydantic import ValidationError

from schemas.summary import Summary

OLD = {"status": "succeeded", "method": "prb", "iterations": 30, "seconds": 1.2, "scalars": ["a.r"], "init": [0.5],
       "final": [0.61], "standard_error": [0.01], "last_iterate": [0.6],
       "estimate": {"kind": "newton", "window": [10, 29], "run_error": [0.008], "floor_error": [0.006]},
       "stopped": {"what": "stop", "value": 30, "reason": "the cap", "iteration": 29}, "target": [0.6],
       "error": None, "field": None, "max_abs_error": 0.01}


def test_an_older_folders_summary_reads_into_the_new_names():
    """Failed before the older names were mapped (``final`` is no field of the model)."""
    summary = Summary.read(OLD)
    assert summary.estimate == [0.61] and summary.target_values == [0.6] and summary.estimate_error == 0.01
    assert summary.estimate_kind == "newton" and summary.estimate_window == [10, 29]
    assert summary.run_error == [0.008] and summary.floor_error == [0.006]


def test_a_summary_round_trips_and_refuses_names_it_does_not_know():
    summary = Summary.read(OLD)
    assert Summary.read(summary.model_dump_json()) == summary
    with pytest.raises(ValidationError, match="answer"):
        Summary.read({**summary.model_dump(), "answer": [0.61]})   # one name per idea: the answer is estimate
