"""Simulated experiments: the master's run on a simulated swarm (``surprise-master sim``).

:mod:`.simulate` runs the real master against simulated robots over loopback TCP or, with the
fast engine, in one process (:mod:`.engine_run`); :mod:`.simulation_setup` builds the world and
the robots from an experiment file; :mod:`.baseline` evaluates fixed genomes for comparison.
"""
