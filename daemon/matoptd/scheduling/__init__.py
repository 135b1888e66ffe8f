"""Who runs what, and carrying it out: the scheduler (a state machine), job control, one lane
per worker, recovery from lost workers and restarts, and the watchers' events."""
