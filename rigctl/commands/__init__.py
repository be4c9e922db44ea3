"""The CLI's commands (rigctl.cli imports them): parse options, call the application layer, print."""
