"""The frame loop and what it keeps between frames: the device source with reconnect
(``source``), the mount tracker (``mount_tracker``), the stage tables built off the loop
(``stage_tables``) and the loop itself (``loop``: driver -> pose -> stages -> sinks)."""
