"""The programs: the command line (``cli``: ``inclinometer-calib``, a module per command group),
the graph launcher and its run summary (``launcher``: ``inclinometer-calib-launch``), the replay
test of a recorded run (``replaytest``), the ROS environment of the processes it starts
(``rosenv``: domain ids, locks) and what the commands share (``common``: the user's input error,
site and record readers).

May import: every other layer (``apps`` is the top; nothing imports it).
"""
