"""Robot hardware behind one interface, :class:`drivers.body.Body`.

A real robot's body is built by :func:`drivers.compose.build_body` from a
:class:`drivers.config.BodyConfig`. The backend libraries are imported lazily, when a part first
connects (``dbus-fast`` in :mod:`drivers.thymio`, ``smbus2`` in :mod:`drivers.i2c`), so importing
this package needs neither.
"""

from drivers.body import Body, SensorFrame
from drivers.clock import Clock, MonotonicClock

__all__ = ["Body", "Clock", "MonotonicClock", "SensorFrame"]
