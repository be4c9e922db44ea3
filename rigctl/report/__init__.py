"""Reports and certificates: present results of the application layer (rigctl.analysis)."""
