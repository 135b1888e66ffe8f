"""What survives a restart: the SQLite database of scenes, jobs, histories and results, the
content-addressed blobs and the checkpoints under --data-dir."""
