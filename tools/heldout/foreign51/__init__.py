"""Held-out stage foreign51 (a package only so that mypy tells its stage_server from foreign49's)."""
