"""A run: the run directory, its log and console, signals, then the procedure's solve steps."""
