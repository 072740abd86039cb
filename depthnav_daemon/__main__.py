"""``python -m depthnav_daemon`` runs the CLI."""

from depthnav_daemon.cli import entry_point

entry_point()
