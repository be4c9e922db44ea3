"""Alembic migrations of the results database (rigctl.recording.results_db); see env.py."""
