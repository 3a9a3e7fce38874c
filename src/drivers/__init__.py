"""Robot hardware behind one interface, :class:`drivers.body.Body`.

The backends (asebamedulla over D-Bus, I2C sensors) are imported lazily by
:func:`drivers.compose.build_body` so that importing this package needs neither ``dbus-fast`` nor
``smbus2``.
"""

from drivers.body import Body, SensorFrame
from drivers.clock import Clock, MonotonicClock

__all__ = ["Body", "Clock", "MonotonicClock", "SensorFrame"]
