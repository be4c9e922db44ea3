"""Alembic migrations of the results database (rigctl.results_db); see env.py."""
