"""Jobs: the job service (submit, list, cancel), the one owner of a job's state, and the
execution of an attempt."""
