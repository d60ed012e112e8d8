"""Names of the files the bench keeps in each run folder (shared by the runner and the worker,
which must not import each other: the worker runs as ``python -m``)."""

JOB_NAME = "bench_job.yml"
"""The complete TrainerConfig of the run, written by the runner, trained by the worker."""
ERROR_NAME = "error.txt"
"""One line: why the worker failed."""
STATE_NAME = "bench_state.json"
"""{fingerprint, status (running / done / failed), attempts, error}."""
LOG_NAME = "bench.log"
"""The worker's commands, stdout and stderr, appended attempt after attempt."""
METRICS_NAME = "metrics.json"
"""Written by the trainer at the end of a run."""
