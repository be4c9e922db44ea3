"""rigctl: test automation for inertial sensor labs."""

__version__ = "0.1.0"
