"""Configuration of a real robot's body: which parts it has and how each is wired.

Decoded from the agent's YAML with :func:`minimize_surprise.config.decode`; every value that is a
choice (calibration, wiring, timeouts) lives here, not in the drivers (docs/thymio.md,
docs/sensors.md).
"""

from __future__ import annotations

from typing import Annotated, Literal

import msgspec

from minimize_surprise.config import Strict
from minimize_surprise.sensors import FORCE_SENSORS, GROUND_SENSORS, IR_SENSORS, LIGHT_SENSORS

#: Seconds one asebamedulla call may take. ``GetVariable`` waits for the robot's answer, which
#: follows its 10 Hz sensor update (up to 100 ms), so 0.25 s tolerates one late update plus D-Bus
#: latency while bounding how far a control step can overrun when the robot is gone (medulla then
#: never answers at all).
CALL_TIMEOUT = 0.25
#: Seconds to connect and authenticate to the D-Bus daemon; a local socket answers in milliseconds.
CONNECT_TIMEOUT = 2.0
#: Motor units for a normalised speed of 1.0. The Thymio's motor unit is about 0.04 cm/s
#: (docs/thymio.md); the paper's real robots drove at most 10.6 cm/s to spare the motors, which is
#: 265 units (its simulation used 12.6 cm/s, 315 units). Calibrate per robot.
SPEED_SCALE = 265.0
#: The Thymio accepts motor targets of about -500..500 (docs/thymio.md).
MAX_MOTOR_TARGET = 500

#: The node name a Thymio II announces, and the one the packaged Aseba programs are written for.
PROGRAM_NODE = "thymio-II"
#: The directory the agent's unit gives it for copies of the Aseba programs (its
#: ``RuntimeDirectory=``, deploy/systemd/surprise-agent.service): writable under the unit's
#: ``ProtectSystem=strict``, and outside its private /tmp, so medulla, another unit, can read it.
RUNTIME_PROGRAM_DIR = "/run/minimize-surprise"

PositiveSeconds = Annotated[float, msgspec.Meta(gt=0.0, le=60.0)]
BusNumber = Annotated[int, msgspec.Meta(ge=0, le=255)]


class ThymioConfig(Strict, frozen=True):
    """The Thymio II base, reached through asebamedulla on D-Bus (docs/thymio.md).

    ``bus`` is ``"session"``, ``"system"`` or an explicit D-Bus address (``"unix:path=..."``).
    ``speed_scale`` is the motor target for a normalised speed of 1.0 (calibrate per robot);
    targets are clamped to ``±max_target``. With ``failsafe`` the base loads an Aseba program that
    zeroes the motor targets when the host has not commanded the motors for ``failsafe_timeout``
    seconds (see ``drivers/failsafe.aesl``); without it, it loads an empty program, so that no
    program left on the Thymio (an earlier run's failsafe, the Thymio's own behaviours) sets the
    motor targets.

    medulla reads the programs from files: the ones installed with the package, or, for a node
    not named ``thymio-II``, copies written into ``program_dir`` (a directory medulla can read;
    not a private ``/tmp``). ``restart_medulla``: medulla never reconnects to a robot that went
    away, so when the robot cannot be reached through it the agent ends it (SIGTERM) and waits
    for its service to start a fresh one; this needs medulla to run as the agent's user under a
    unit with ``Restart=always`` (deploy/systemd/asebamedulla.service).
    """

    #: the D-Bus bus asebamedulla is on: ``session``, ``system`` or an address such as
    #: ``unix:path=/run/dbus/system_bus_socket``
    bus: str = "session"
    #: the Aseba node name of the Thymio
    node: str = PROGRAM_NODE
    #: seconds one asebamedulla call may take (medulla never answers once the robot is gone)
    timeout: PositiveSeconds = CALL_TIMEOUT
    #: seconds to connect and authenticate to the D-Bus daemon
    connect_timeout: PositiveSeconds = CONNECT_TIMEOUT
    #: the Thymio variable the ground sensors are read from (both 0..1023, normalised by 1023)
    ground: Literal["prox.ground.reflected", "prox.ground.delta"] = "prox.ground.reflected"
    #: motor units for a normalised speed of 1.0 (265: 10.6 cm/s, the paper's real robots);
    #: calibrate per robot
    speed_scale: Annotated[float, msgspec.Meta(gt=0.0, le=MAX_MOTOR_TARGET)] = SPEED_SCALE
    #: the left wheel's real speed per commanded speed, as ``surprise-master calibrate``
    #: measured it (docs/fleet.md): its targets are divided by it, so both wheels drive at
    #: the speed the network asked for
    wheel_left: Annotated[float, msgspec.Meta(gt=0.5, le=2.0)] = 1.0
    #: the right wheel's, likewise
    wheel_right: Annotated[float, msgspec.Meta(gt=0.5, le=2.0)] = 1.0
    #: motor targets are clamped to plus or minus this many units
    max_target: Annotated[int, msgspec.Meta(ge=1, le=MAX_MOTOR_TARGET)] = MAX_MOTOR_TARGET
    #: load the Aseba failsafe program, which stops the motors when the host stops commanding
    #: them; without it an empty program is loaded
    failsafe: bool = False
    # The Aseba program counts 100 ms ticks in an int16; 0.2 s is the shortest sensible window for
    # a 10 Hz host (two missed commands), 300 s keeps the count far from overflow.
    #: seconds without a motor command after which the failsafe program stops the motors
    failsafe_timeout: Annotated[float, msgspec.Meta(ge=0.2, le=300.0)] = 1.0
    #: a directory medulla can read (not a private /tmp) for copies of the Aseba programs,
    #: needed only for a node not named ``thymio-II``; under the deploy/ units
    #: ``/run/minimize-surprise``, the agent's runtime directory
    program_dir: str | None = None
    #: end medulla (SIGTERM) when the robot cannot be reached through it, for its service to
    #: start a fresh one; needs medulla under a unit with ``Restart=always``, as the agent's user
    restart_medulla: bool = True

    def __post_init__(self) -> None:
        if self.bus not in ("session", "system") and ":" not in self.bus:
            raise ValueError(
                "`bus`: expected 'session', 'system' or a D-Bus address such as "
                f"'unix:path=/run/dbus/system_bus_socket', got {self.bus!r}"
            )
        if not self.node:
            raise ValueError("`node`: the Aseba node name must not be empty")
        if self.node != PROGRAM_NODE and self.program_dir is None:
            raise ValueError(
                f"`program_dir`: the Aseba programs are installed for the node {PROGRAM_NODE!r}; "
                f"for node {self.node!r} they are written into program_dir, a directory "
                f"asebamedulla can read (e.g. {RUNTIME_PROGRAM_DIR})"
            )


class MuxConfig(Strict, frozen=True):
    """A TCA9548A I2C multiplexer channel in front of a device (docs/sensors.md)."""

    #: the multiplexer channel the device is on
    channel: Annotated[int, msgspec.Meta(ge=0, le=7)]
    #: the multiplexer's I2C address
    address: Annotated[int, msgspec.Meta(ge=0x70, le=0x77)] = 0x70


class LightSensorConfig(Strict, frozen=True):
    """A TSL45315 ambient light sensor (docs/sensors.md).

    It sits on its own bus (``bus``, e.g. a software bus from the ``i2c-gpio`` overlay) or behind
    a multiplexer channel (``mux``). ``integration_ms`` is 400, 200 or 100; 100 gives a fresh value
    for every step of the 10 Hz loop. The reading is ``lux / max_lux`` clipped to [0, 1].
    """

    #: the I2C bus number (``/dev/i2c-N``)
    bus: BusNumber = 1
    #: the sensor's I2C address
    address: Annotated[int, msgspec.Meta(ge=0x03, le=0x77)] = 0x29
    #: the multiplexer channel in front of the sensor (``null``: none)
    mux: MuxConfig | None = None
    #: integration time in milliseconds: 400, 200 or 100 (a fresh value every 10 Hz step)
    integration_ms: Literal[400, 200, 100] = 100
    # The authors normalised the raw count by 1024 at 400 ms (multiplier 1), i.e. 1024 lux.
    #: the illuminance that reads 1.0; the reading is lux / max_lux clipped to [0, 1]
    max_lux: Annotated[float, msgspec.Meta(gt=0.0)] = 1024.0


#: ADS1115 input multiplexer settings (config bits 14:12), in the datasheet's order.
ADS1115_INPUTS: tuple[str, ...] = (
    "AIN0-AIN1", "AIN0-AIN3", "AIN1-AIN3", "AIN2-AIN3", "AIN0", "AIN1", "AIN2", "AIN3",
)  # fmt: skip
#: ADS1115 programmable-gain full-scale ranges in volts (config bits 11:9, codes 0..5).
ADS1115_RANGES: tuple[float, ...] = (6.144, 4.096, 2.048, 1.024, 0.512, 0.256)

AdsInput = Literal[
    "AIN0-AIN1", "AIN0-AIN3", "AIN1-AIN3", "AIN2-AIN3", "AIN0", "AIN1", "AIN2", "AIN3"
]  # fmt: skip


class ForceSensorConfig(Strict, frozen=True):
    """The blade's force sensor (a bridge) read differentially by an ADS1115 (docs/sensors.md).

    ``inputs`` selects the ADC's input pair, ``pga_range_volts`` its gain (±6.144 .. ±0.256 V),
    ``data_rate`` its samples per second. ``full_scale_volts`` is the bridge voltage that reads
    1.0 (about 86 mV at 7 N and 3.3 V supply); the zero is measured at ``open()`` as the mean of
    ``zero_samples`` conversions, so the blade must be unloaded then. ``invert`` flips the sign
    when the bridge is wired the other way round.
    """

    #: the I2C bus number (``/dev/i2c-N``)
    bus: BusNumber = 1
    #: the ADS1115's I2C address (0x48..0x4B, set by its ADDR pin)
    address: Annotated[int, msgspec.Meta(ge=0x48, le=0x4B)] = 0x48
    #: the multiplexer channel in front of the ADC (``null``: none)
    mux: MuxConfig | None = None
    #: the ADC's input (pair) the bridge is wired to; a pair reads the difference
    inputs: AdsInput = "AIN0-AIN1"
    #: the ADC's full-scale range in volts (its gain): 6.144, 4.096, 2.048, 1.024, 0.512, 0.256
    pga_range_volts: float = 0.256
    # 128 SPS is the chip's default and quieter than the faster rates; its 8 ms conversion is
    # small next to the 100 ms control step.
    #: the ADC's samples per second (one conversion takes 1 / data_rate)
    data_rate: Literal[8, 16, 32, 64, 128, 250, 475, 860] = 128
    #: the bridge voltage above the zero that reads 1.0 (about 86 mV at 7 N and 3.3 V supply)
    full_scale_volts: Annotated[float, msgspec.Meta(gt=0.0)] = 0.086
    #: conversions averaged for the zero when the sensor is opened (the blade must be unloaded)
    zero_samples: Annotated[int, msgspec.Meta(ge=1, le=64)] = 8
    #: flip the sign, for a bridge wired the other way round
    invert: bool = False

    def __post_init__(self) -> None:
        if self.pga_range_volts not in ADS1115_RANGES:
            raise ValueError(
                f"`pga_range_volts`: expected one of {', '.join(map(str, ADS1115_RANGES))}, "
                f"got {self.pga_range_volts}"
            )
        if self.full_scale_volts > self.pga_range_volts:
            raise ValueError(
                f"`full_scale_volts`: {self.full_scale_volts} V exceeds the ADC range "
                f"±{self.pga_range_volts} V"
            )


class BodyConfig(Strict, frozen=True):
    """The parts of one real robot: the Thymio base, up to two light sensors, a force sensor."""

    #: the Thymio II base, through asebamedulla on D-Bus (docs/thymio.md)
    thymio: ThymioConfig = msgspec.field(default_factory=ThymioConfig)
    #: up to two TSL45315 light sensors, reported as ``light.0`` and ``light.1`` in this order
    #: (docs/sensors.md)
    light: list[LightSensorConfig] = msgspec.field(default_factory=list)
    #: the blade's force sensor on an ADS1115, reported as ``force`` (``null``: none;
    #: docs/sensors.md)
    force: ForceSensorConfig | None = None
    # A real robot reads its chips on /dev/i2c-N; a rehearsal's agent reads emulated chips served
    # by surprise-sim-robots, whose readings come from its simulated world.
    #: a rehearsal's stand-in for the I2C buses: the Unix socket of the emulated chips that
    #: ``surprise-sim-robots`` serves (it writes this key); ``null`` on a real robot, which reads
    #: ``/dev/i2c-N`` (docs/separate-processes.md)
    i2c_bridge: str | None = None

    def __post_init__(self) -> None:
        if self.i2c_bridge is not None and not self.i2c_bridge.strip():
            raise ValueError("`i2c_bridge`: expected the bridge's socket path or null, got ''")
        if len(self.light) > len(LIGHT_SENSORS):
            raise ValueError(f"`light`: at most {len(LIGHT_SENSORS)} light sensors are supported")
        seen: dict[tuple[object, ...], int] = {}
        for i, light in enumerate(self.light):
            where = (light.bus, light.mux and (light.mux.address, light.mux.channel), light.address)
            if where in seen:
                raise ValueError(
                    f"`light[{i}]`: same bus, multiplexer channel and address as "
                    f"light[{seen[where]}]"
                )
            seen[where] = i

    def sensor_names(self) -> tuple[str, ...]:
        """The names a body built from this configuration reports, in canonical order."""
        names = IR_SENSORS + GROUND_SENSORS
        if self.force is not None:
            names += FORCE_SENSORS
        return names + LIGHT_SENSORS[: len(self.light)]
