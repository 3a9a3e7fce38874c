"""Reporting: what a person reads from a run's directory or its live telemetry; it reads the
run's files through :mod:`runfiles.schema` and writes nothing into a run's state.

* :mod:`reporting.report` - a run's summary and metrics (``surprise-master report``);
* :mod:`reporting.pictures` - its figures;
* :mod:`reporting.recovery` - fitness around each change of the arena: drop and recovery;
* :mod:`reporting.reality_gap` - a replay beside its source run;
* :mod:`reporting.tracker` - an overhead tracker's positions file, for real runs;
* :mod:`reporting.robot_stats` - the robots' batteries, overruns and failed reads per evaluation;
* :mod:`reporting.status` - ``surprise-master status``;
* :mod:`reporting.dashboard_data`, :mod:`reporting.dashboard_html`, :mod:`reporting.dashboard` -
  ``surprise-master dashboard``;
* :mod:`reporting.watch` - a run's MQTT telemetry (``surprise-master watch``).
"""
