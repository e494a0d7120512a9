"""The names of the files in results folders, named once (each command's docs list what it writes).

A model is always ``MODEL_FILE`` (checkpoint.pt, train and dagger), ``BEST_MODEL_FILE`` or
``FINAL_MODEL_FILE`` (a federation run's cloud models), in learning.checkpoint's format; a federation
run's resumable state is ``STATE_FILE``, never a checkpoint.pt.
"""

SUMMARY_FILE = "summary.json"  # a command's figures: run, drive-bench, dagger, reproduce, report, simulate
CONFIG_JSON_FILE = "config.json"  # a federation run's resolved settings
MODEL_FILE = "checkpoint.pt"  # a trained model (train, dagger); .prev.pt: the epoch before
BEST_MODEL_FILE = "best_model.pt"  # a federation run's best cloud model
FINAL_MODEL_FILE = "final_model.pt"  # a federation run's last cloud model
STATE_FILE = "federation_state.pt"  # a federation run's state, what --resume reads; .prev.pt: the step before
METRICS_LOG_FILE = "metrics.jsonl"  # one line per epoch (train) or per aggregation (run)
DRIVE_METRICS_FILE = "metrics.json"  # one drive's metrics
EPISODES_FILE = "episodes.json"  # a benchmark's episodes, one record each
RESULTS_CSV_FILE = "results.csv"  # a benchmark's, sweep's or study's table
RESULTS_MD_FILE = "results.md"  # the same table for reading
TIMINGS_FILE = "timings.json"  # a reproduction's parts: when each ran and how long
