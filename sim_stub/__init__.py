"""The simulator that stands in for the hardware: a kinematic arena of Thymio II robots.

* :mod:`sim_stub.scenarios` - every world parameter (``WorldConfig``) and the named scenarios of
  the paper (``basic``, ``boxes``, ``gradient``) with overrides: ``scenario_config(name, ...)``;
* :mod:`sim_stub.world` - the vectorised world: motion, contacts, boxes, sensors (``World``);
* :mod:`sim_stub.body` - the drivers' ``Body`` over a shared world, in lockstep or real time
  (``SimSwarm``, ``SimBody``, ``LockstepClock``);
* :mod:`sim_stub.metrics` - the paper's behaviour metrics from recorded poses;
* :mod:`sim_stub.render` - pictures of a world (needs the optional matplotlib);
* :mod:`sim_stub.fake_i2c`, :mod:`sim_stub.fake_medulla` - fake devices behind the real drivers.

Nothing is imported here, so that each part costs only what it uses.
"""
