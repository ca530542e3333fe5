"""Small shared helpers at the bottom of the package: input checks, atomic files, checkpoints, schedules, metric logs."""
