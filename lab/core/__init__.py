"""The kernel: what every layer stands on (geometry, rig files and configuration, errors, the
recorder, the executor of studies, the run catalogue, review).  It imports no layer above it."""
