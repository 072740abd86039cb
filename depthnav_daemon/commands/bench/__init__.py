"""``depthnav bench``: the stages, the sinks and the whole loop timed against np.copy of a frame.

command.py   the command: arguments, the report and its JSON
stages.py    each stage's timing (interleaved rounds, ratios to np.copy)
sinks.py     each sink's per-frame work
process.py   whole processes: latency, CPU at 30 frames/s, start-up, the loop's cost
rebuild.py   what a large mount change costs the frames
"""
