"""The rerun family: ``rerun`` (a spawned viewer), ``rerun+grpc://HOST:PORT`` (a running one)
and ``rerun:FILE.rrd``.

rerun.py     the sink: specs, options, what is logged per frame
layout.py    the entities and the default layout (blueprint)
depth.py     the depth image and what is drawn on it
topdown.py   the top-down view (scan, drop-offs, footprint, field of view, memory)
file.py      writing ``.rrd`` files (lock, short writes, a bounded disconnect)
viewer.py    checking that a viewer listens before connecting to it
"""
