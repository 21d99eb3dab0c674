"""Experiments: sweeps over a job's fields, run as ordinary jobs and compared side by side.

``expand`` (field paths, the grid x random x seeds product), ``validate`` (every run is a valid
job, or nothing is queued), ``state`` (the one writer of experiment records), ``service``
(create, cancel, retry, append), ``scheduler`` (admission under ``max_concurrent``, above the
queue), ``results`` (run rows, results.csv, aggregates over seeds, accuracy against time).
"""
