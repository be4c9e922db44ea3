"""The daemon: job queue, control socket, web page, live feed and notifications."""
