"""The project's one error tree.

Every error raised on purpose by this project derives from :class:`SurpriseError` and also from the
built-in that matches its meaning, so callers may catch either. Errors carry their data as
attributes, not only in the message.
"""

from __future__ import annotations


class SurpriseError(Exception):
    """Root of every error this project raises on purpose."""


class ConfigError(SurpriseError, ValueError):
    """A configuration file or value is invalid.

    ``file`` is the path of the offending file (or ``None`` for in-memory data), ``key`` the dotted
    path of the offending key (``"evolution.mutation_rate"``; ``None`` when the whole document is
    wrong; a command-line option such as ``"--robots"`` when the value came from there) and
    ``reason`` what was expected.
    """

    def __init__(self, reason: str, *, file: str | None = None, key: str | None = None) -> None:
        self.file = file
        self.key = key
        self.reason = reason
        if file is None and key and key.startswith("--"):
            where = f"option '{key}'"  # a command-line option, not a key of some file
        else:
            where = file or "<config>"
            if key:
                where += f": key '{key}'"
        super().__init__(f"{where}: {reason}")


class ClusterError(SurpriseError, OSError):
    """A compute cluster fails a study: its tools are missing, its controller or scheduler does
    not answer or is lost, or it refuses or ends the workers' jobs (``surprise-study run``)."""


class ClusterTimeoutError(ClusterError, TimeoutError):
    """A cluster did not answer, or start the workers' jobs, within ``timeout`` seconds."""

    def __init__(self, message: str, *, timeout: float) -> None:
        self.timeout = timeout
        super().__init__(message)


class ProtocolError(SurpriseError, ValueError):
    """Bytes or a message on the wire violate the protocol; the connection should be closed."""


class ConnectionClosedError(SurpriseError, ConnectionError):
    """The peer closed the connection; ``mid_frame`` is true if it stopped inside a frame."""

    def __init__(self, message: str = "peer closed the connection", *, mid_frame: bool = False):
        self.mid_frame = mid_frame
        super().__init__(message)


class AuthenticationError(ProtocolError):
    """The peer did not prove it knows the shared secret, or a frame's tag does not verify (it
    was forged, replayed, reordered or reflected); the connection must be closed."""


class FrameTooLargeError(ProtocolError):
    """A frame announces a length above the limit; ``size`` and ``limit`` are in bytes."""

    def __init__(self, size: int, limit: int) -> None:
        self.size = size
        self.limit = limit
        super().__init__(f"frame of {size} bytes exceeds the limit of {limit} bytes")


class GenomeError(SurpriseError, ValueError):
    """A genome does not fit the network layout (wrong length or non-finite values)."""


class HardwareError(SurpriseError, OSError):
    """A robot part failed: a D-Bus call, an I2C transfer, a missing device."""


class DBusReplyError(HardwareError):
    """A D-Bus service (asebamedulla) answered a call with an error; ``name`` is the error's
    D-Bus name, so that callers can tell an unknown variable from a failure."""

    def __init__(self, message: str, name: str) -> None:
        self.name = name
        super().__init__(message)


class HardwareTimeoutError(HardwareError, TimeoutError):
    """A call to a robot part did not answer in time; ``operation`` and ``timeout`` (s) say so."""

    def __init__(self, operation: str, timeout: float) -> None:
        self.operation = operation
        self.timeout = timeout
        super().__init__(f"{operation} did not answer within {timeout:.3f} s")


class RobotUnreachableError(HardwareError):
    """The robot cannot be reached: it is switched off or unplugged, or the software that reaches
    it (asebamedulla) ended or lost it. The body must ``recover()`` before it can drive again."""


class FileWriteError(SurpriseError, OSError):
    """A file could not be written: a full disk, a read-only directory. ``path`` is the file
    meant (not the temporary name an atomic write used); ``errno`` and ``strerror`` are the
    system's reason."""

    def __init__(self, path: str, errno: int | None, strerror: str | None) -> None:
        super().__init__(errno, strerror, path)
        self.path = path

    @classmethod
    def from_os_error(cls, path: str, exc: OSError) -> FileWriteError:
        """The error of writing ``path`` that failed with ``exc``."""
        return cls(path, exc.errno, exc.strerror or str(exc))

    def __str__(self) -> str:
        return f"cannot write {self.path}: {self.strerror}"
