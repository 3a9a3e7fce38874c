"""The onboard agent of one robot: control loop, safety layer, watchdog and link to the master.

Submodules are imported where they are needed; importing this package loads nothing else.
"""
