"""Stand-ins for the lab's hardware: what runs where a robot, its asebamedulla or its I2C chips
would be, in tests, rehearsals and the simulated swarm's separate processes.

* :mod:`standins.fake_medulla` - a fake asebamedulla on a private D-Bus (the real drivers talk to
  it as to the real one);
* :mod:`standins.medulla_model` - a simulated Thymio behind the fake medulla: its sensors read
  from the simulated world, its motors drive it;
* :mod:`standins.fake_i2c` - emulated I2C chips (light sensors, force-sensor ADC, multiplexer);
* :mod:`standins.i2c_bridge` - a served robot's emulated chips, reading its world, on a Unix
  socket for its agent's drivers (the client: :mod:`drivers.i2c_bridge`);
* :mod:`standins.playground` - the real asebamedulla and Aseba Playground, started and stopped
  for a rehearsal;
* :mod:`standins.playground_world` - Playground's world file for an arena (size, carpet, walls,
  boxes, start poses);
* :mod:`standins.serve` - ``surprise-sim-robots``: simulated robots served as separate
  processes behind either medulla;
* :mod:`standins.agent_files` - the agent configurations ``surprise-sim-robots`` writes;
* :mod:`standins.scripted_robots` - robots that speak the protocol over TCP from a script, for
  the master's tests and benchmarks;
* :mod:`standins.overhead_camera` - a synthetic overhead camera filming a simulated
  post-evaluation (corner markers, robots with ArUco markers, boxes, the LED flash), for the
  tracker's tests and benchmark.

Nothing is imported here, so that each part costs only what it uses.
"""
