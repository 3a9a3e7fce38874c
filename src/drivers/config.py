"""Configuration of a real robot's body: which parts it has and how each is wired.

Decoded from the agent's YAML with :func:`surprise.config.decode`; every value that is a choice
(calibration, wiring, timeouts) lives here, not in the drivers (REFERENCE sections 4 and 6).
"""

from __future__ import annotations

from typing import Annotated, Literal

import msgspec

from surprise.config import Strict
from surprise.sensors import FORCE_SENSORS, GROUND_SENSORS, IR_SENSORS, LIGHT_SENSORS

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

PositiveSeconds = Annotated[float, msgspec.Meta(gt=0.0, le=60.0)]
BusNumber = Annotated[int, msgspec.Meta(ge=0, le=255)]


class ThymioConfig(Strict):
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

    bus: str = "session"
    node: str = PROGRAM_NODE
    timeout: PositiveSeconds = CALL_TIMEOUT
    connect_timeout: PositiveSeconds = CONNECT_TIMEOUT
    ground: Literal["prox.ground.reflected", "prox.ground.delta"] = "prox.ground.reflected"
    speed_scale: Annotated[float, msgspec.Meta(gt=0.0, le=MAX_MOTOR_TARGET)] = SPEED_SCALE
    max_target: Annotated[int, msgspec.Meta(ge=1, le=MAX_MOTOR_TARGET)] = MAX_MOTOR_TARGET
    failsafe: bool = False
    # The Aseba program counts 100 ms ticks in an int16; 0.2 s is the shortest sensible window for
    # a 10 Hz host (two missed commands), 300 s keeps the count far from overflow.
    failsafe_timeout: Annotated[float, msgspec.Meta(ge=0.2, le=300.0)] = 1.0
    program_dir: str | None = None
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
                "asebamedulla can read (e.g. /run/minimize-surprise)"
            )


class MuxConfig(Strict):
    """A TCA9548A I2C multiplexer channel in front of a device (REFERENCE 6)."""

    channel: Annotated[int, msgspec.Meta(ge=0, le=7)]
    address: Annotated[int, msgspec.Meta(ge=0x70, le=0x77)] = 0x70


class LightSensorConfig(Strict):
    """A TSL45315 ambient light sensor (REFERENCE 6).

    It sits on its own bus (``bus``, e.g. a software bus from the ``i2c-gpio`` overlay) or behind
    a multiplexer channel (``mux``). ``integration_ms`` is 400, 200 or 100; 100 gives a fresh value
    for every step of the 10 Hz loop. The reading is ``lux / max_lux`` clipped to [0, 1].
    """

    bus: BusNumber = 1
    address: Annotated[int, msgspec.Meta(ge=0x03, le=0x77)] = 0x29
    mux: MuxConfig | None = None
    integration_ms: Literal[400, 200, 100] = 100
    # The authors normalised the raw count by 1024 at 400 ms (multiplier 1), i.e. 1024 lux.
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


class ForceSensorConfig(Strict):
    """The blade's force sensor (a bridge) read differentially by an ADS1115 (REFERENCE 6).

    ``inputs`` selects the ADC's input pair, ``pga_range_volts`` its gain (±6.144 .. ±0.256 V),
    ``data_rate`` its samples per second. ``full_scale_volts`` is the bridge voltage that reads
    1.0 (about 86 mV at 7 N and 3.3 V supply); the zero is measured at ``open()`` as the mean of
    ``zero_samples`` conversions, so the blade must be unloaded then. ``invert`` flips the sign
    when the bridge is wired the other way round.
    """

    bus: BusNumber = 1
    address: Annotated[int, msgspec.Meta(ge=0x48, le=0x4B)] = 0x48
    mux: MuxConfig | None = None
    inputs: AdsInput = "AIN0-AIN1"
    pga_range_volts: float = 0.256
    # 128 SPS is the chip's default and quieter than the faster rates; its 8 ms conversion is
    # small next to the 100 ms control step.
    data_rate: Literal[8, 16, 32, 64, 128, 250, 475, 860] = 128
    full_scale_volts: Annotated[float, msgspec.Meta(gt=0.0)] = 0.086
    zero_samples: Annotated[int, msgspec.Meta(ge=1, le=64)] = 8
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


class BodyConfig(Strict):
    """The parts of one real robot: the Thymio base, up to two light sensors, a force sensor."""

    thymio: ThymioConfig = msgspec.field(default_factory=ThymioConfig)
    light: list[LightSensorConfig] = msgspec.field(default_factory=list)
    force: ForceSensorConfig | None = None

    def __post_init__(self) -> None:
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
