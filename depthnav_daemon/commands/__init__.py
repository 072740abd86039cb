"""One module per ``depthnav`` subcommand (``run``, ``calibrate``, ``record``, ``mount``,
``snapshot``, ``info``); ``bench/`` is a package of its own (the command, and what it times:
stages, sinks, whole processes, mount changes). ``common`` holds what several commands share;
``depthnav_daemon.cli`` parses the arguments and dispatches here."""
