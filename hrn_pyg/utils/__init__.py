"""Small shared helpers: atomic files, checkpoints, schedules, metric logs."""
