"""One module per ``depthnav`` subcommand; ``depthnav_daemon.cli`` parses the arguments and
dispatches here."""
