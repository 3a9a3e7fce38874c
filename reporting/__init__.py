"""Reporting: what a person reads from a run's directory or its live telemetry.

:mod:`.report` computes a run's summary and metrics (``surprise-master report``), :mod:`.pictures`
draws its figures and :mod:`.watch` follows a run's MQTT telemetry (``surprise-master watch``).
Nothing here writes into a run's state.
"""
