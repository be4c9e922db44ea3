"""Procedures compiled to steps, and the engine that runs them on the rig's devices."""
