"""The daemon: streaming engine, control API, systemd integration."""
