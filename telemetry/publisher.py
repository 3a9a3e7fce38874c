"""The publisher: a bounded queue in front of one MQTT connection, run by one background task.

::

    async with TelemetryPublisher(config, status_suffix="robot/r1/status") as telemetry:
        telemetry.publish_nowait("robot/r1/evaluation", summary, qos=1)   # never waits
        telemetry.publish_nowait("run/status", status, retain=True)       # latest value wins

The caller (the control loop, the master's evolution) never awaits the network:
:meth:`TelemetryPublisher.publish_nowait` is a plain function that appends to a queue and returns.
Two kinds of message wait for the broker:

* events (``retain=False``) in a FIFO :class:`collections.deque` of ``queue_size`` entries; when it
  is full the oldest is dropped and counted in :attr:`TelemetryPublisher.dropped`;
* states (``retain=True``), one slot per topic, latest value wins, never dropped; every state is
  published again after each (re)connection, since a restarted broker may have lost it.

The background task connects, publishes states first and then events, republishes its own status
(``online``, ``dropped``, ``sent``) every :data:`STATUS_INTERVAL` seconds, and reconnects with
capped exponential backoff and jitter when the broker goes away. The first failure after a
success (or at start) is one warning in the log; further attempts log at debug level only.
``aiomqtt`` is imported by that task, so nothing needs it until a broker is configured.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import logging
import random
import uuid
from types import TracebackType
from typing import Any, Final, Self

from minimize_surprise.backoff import Backoff
from telemetry.config import TelemetryConfig
from telemetry.payloads import ClientStatus, Payload, encode_payload, now

__all__ = [
    "BROKER_TIMEOUT",
    "CANCEL_GRACE",
    "CLOSE_TIMEOUT",
    "STATUS_INTERVAL",
    "Backoff",
    "TelemetryPublisher",
]

log = logging.getLogger(__name__)

#: Seconds the broker may take to acknowledge a connection or a QoS 1 message. A broker on the
#: lab network answers within milliseconds; past this it is treated as gone and the client
#: reconnects. (The TCP connect itself is bounded by the MQTT library's own 5 s timeout.)
BROKER_TIMEOUT: Final = 5.0
#: Seconds :meth:`TelemetryPublisher.aclose` waits for the queue to drain and the offline status
#: to go out before it gives up: a shutdown (a robot stopping its motors, a master exiting) must
#: not wait for a slow broker.
CLOSE_TIMEOUT: Final = 1.0
#: Seconds a cancelled publisher task gets to leave cleanly (the MQTT library sends DISCONNECT
#: and waits for the socket to close, milliseconds with a live broker) before it is cancelled
#: again, which cuts that wait short: a stalled broker must not hold up a shutdown.
CANCEL_GRACE: Final = 0.5
#: Seconds between two publications of the client's own status: often enough that a watcher sees
#: the drop counter move, rare enough to be no traffic at all.
STATUS_INTERVAL: Final = 10.0
#: QoS of states (retained) and of the client's own status: they are the current picture and few.
STATE_QOS: Final = 1

# The MQTT library's own messages (a failed socket read, a forced disconnect) repeat what our
# single warning says; they go to a logger of ours, at debug level, so they can still be seen.
_MQTT_LOG = logging.getLogger("telemetry.mqtt")


class _DebugOnly(logging.LoggerAdapter):
    """Passes every record of the MQTT library on at debug level."""

    def log(self, level: int, msg: object, *args: Any, **kwargs: Any) -> None:
        self.logger.log(logging.DEBUG, msg, *args, **kwargs)

    def warning(self, msg: object, *args: Any, **kwargs: Any) -> None:
        self.logger.debug(msg, *args, **kwargs)

    def error(self, msg: object, *args: Any, **kwargs: Any) -> None:
        self.logger.debug(msg, *args, **kwargs)

    def exception(self, msg: object, *args: Any, exc_info: Any = True, **kwargs: Any) -> None:
        self.logger.debug(msg, *args, exc_info=exc_info, **kwargs)


def _abandon(client: Any) -> None:
    """Close the socket of a connection attempt that failed half-way.

    When the TCP connection succeeded but the broker never acknowledged the MQTT CONNECT (a
    wrong service on the port, a hung broker), aiomqtt gives up without closing the socket;
    one leaked per attempt would add up over a long run. Its paho client's ``disconnect()``
    writes a DISCONNECT and then closes the socket (the attribute is aiomqtt's, hence the guard).
    """
    paho = getattr(client, "_client", None)
    if paho is None:
        return
    with contextlib.suppress(Exception):
        paho.disconnect()


class TelemetryPublisher:
    """Publishes payloads to ``<prefix>/<suffix>`` topics on the configured broker, in the
    background; see the module docstring.

    ``status_suffix`` is this client's status topic (it also carries the last will).
    ``client_id`` is used when the configuration names none (default: a random one). Create it
    anywhere; :meth:`start` (or ``async with``) needs a running event loop. Every method is to be
    called from the event loop's thread.
    """

    def __init__(
        self,
        config: TelemetryConfig,
        *,
        status_suffix: str,
        client_id: str | None = None,
        name: str = "telemetry",
        rng: random.Random | None = None,
    ) -> None:
        if not config.enabled:
            raise ValueError("telemetry is off: no broker configured")
        self.config = config
        self.address = config.address
        self.prefix = config.prefix
        self.client_id = config.client_id or client_id or f"surprise-{uuid.uuid4().hex[:12]}"
        self.status_suffix = status_suffix
        self.name = name
        #: events dropped because the queue was full (the oldest goes)
        self.dropped = 0
        #: messages handed to the broker
        self.sent = 0
        #: successful connections so far (1 after the first, +1 per reconnection)
        self.connections = 0
        #: whether a connection to the broker is up now
        self.connected = False
        self._queue: collections.deque[tuple[str, Payload, int]] = collections.deque(
            maxlen=config.queue_size
        )
        self._states: dict[str, Payload] = {}
        # Insertion-ordered set of the states not yet published on this connection.
        self._dirty: dict[str, None] = {}
        self._wakeup = asyncio.Event()
        self._backoff = Backoff(config.reconnect, rng)
        self._task: asyncio.Task[None] | None = None
        self._sending = 0
        self._closing = False
        self._warn_next_failure = True

    # ------------------------------------------------------------------ the caller's side

    def publish_nowait(
        self, topic_suffix: str, payload: Payload, *, retain: bool = False, qos: int = 0
    ) -> None:
        """Queue ``payload`` for ``<prefix>/<topic_suffix>``; returns at once, never raises.

        ``retain=True`` makes it the topic's state (published retained with QoS 1, replacing any
        unsent earlier state of the topic, published again after a reconnection). Otherwise it
        is an event with the given ``qos``; when the queue is full the oldest event is dropped
        and :attr:`dropped` counts it. Encoding happens later, in the background task.
        """
        try:
            if self._closing and self._task is None:
                return  # closed: nobody will ever send it
            if retain:
                self._states[topic_suffix] = payload
                self._dirty[topic_suffix] = None
            else:
                queue = self._queue
                if len(queue) == queue.maxlen:
                    self.dropped += 1  # append() below pushes the oldest out, in O(1)
                queue.append((topic_suffix, payload, qos))
            self._wakeup.set()
        except Exception:  # telemetry must never break its caller
            log.exception("telemetry: could not queue a message for %s", topic_suffix)

    @property
    def pending(self) -> int:
        """Messages not yet handed to the broker: queued events, unsent states and the one
        being sent."""
        return len(self._queue) + len(self._dirty) + self._sending

    def topic(self, topic_suffix: str) -> str:
        """The full topic of ``topic_suffix``."""
        return f"{self.prefix}/{topic_suffix}"

    # ------------------------------------------------------------------ lifecycle

    def start(self) -> None:
        """Start the background task (connecting happens there; this returns at once)."""
        if self._task is not None:
            raise RuntimeError("the publisher was started already")
        self._closing = False
        self._task = asyncio.get_running_loop().create_task(self._run(), name=self.name)

    async def aclose(self, timeout: float = CLOSE_TIMEOUT) -> None:
        """Publish the offline status, let the queue drain for up to ``timeout`` seconds if
        connected, then stop the background task. Safe to call twice or before :meth:`start`."""
        task = self._task
        if task is not None and self.connected and not task.done():
            self.publish_nowait(self.status_suffix, self._status(online=False), retain=True)
        self._task = None
        self._closing = True
        if task is None:
            return
        try:
            if self.connected and not task.done():
                # The task returns once everything is out; a clean DISCONNECT keeps the broker
                # from publishing the will, which says the same anyway.
                await asyncio.wait((task,), timeout=timeout)
        finally:
            # wait(), not await task: a cancellation of the caller must not be swallowed here.
            if not task.done():
                task.cancel()
                await asyncio.wait((task,), timeout=CANCEL_GRACE)
            if not task.done():
                task.cancel()  # interrupts the MQTT library waiting for a stalled broker
                await asyncio.wait((task,))
            if not task.cancelled():
                task.exception()  # retrieved, so asyncio does not warn about it

    async def __aenter__(self) -> Self:
        self.start()
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        await self.aclose()

    # ------------------------------------------------------------------ the background task

    def _status(self, *, online: bool) -> ClientStatus:
        return ClientStatus(online=online, t=now(), dropped=self.dropped, sent=self.sent)

    async def _run(self) -> None:
        while not self._closing:
            try:
                await self._session()
            except asyncio.CancelledError:
                raise
            except Exception as exc:  # MqttError, OSError, a bug: never let the task die
                self._failed(exc)
            finally:
                self.connected = False
            if self._closing:
                return
            await asyncio.sleep(self._backoff.next_delay())

    def _failed(self, exc: Exception) -> None:
        if self._closing:
            return
        text = f"{type(exc).__name__}: {exc}" if str(exc) else type(exc).__name__
        if exc.__cause__ is not None:  # aiomqtt wraps the socket's error; that one says why
            text += f", {exc.__cause__}"
        if self._warn_next_failure:
            self._warn_next_failure = False
            log.warning(
                "telemetry: %s %s (%s); retrying in the background, meanwhile at most %d "
                "messages are kept and the oldest dropped",
                "lost the broker" if self.connections else "cannot reach the broker",
                self.address.url,
                text,
                self.config.queue_size,
            )
        else:
            log.debug("telemetry: attempt to reach %s failed: %s", self.address.url, text)

    async def _session(self) -> None:
        """One connection: publish until closing (returns) or the connection fails (raises)."""
        import aiomqtt  # only here: nothing needs the MQTT client unless a broker is configured

        will = aiomqtt.Will(
            self.topic(self.status_suffix),
            encode_payload(ClientStatus(online=False)),
            qos=STATE_QOS,
            retain=True,
        )
        client = aiomqtt.Client(
            self.address.host,
            self.address.port,
            identifier=self.client_id,
            will=will,
            keepalive=self.config.keepalive,
            timeout=BROKER_TIMEOUT,
            logger=_DebugOnly(_MQTT_LOG, {}),  # type: ignore[arg-type]  # typed Logger; duck-typed
        )
        try:
            async with client:
                await self._serve(client)
        finally:
            if not self.connected:
                _abandon(client)

    async def _serve(self, client: Any) -> None:
        """The connection is up: publish until closing (returns) or it fails (raises)."""
        self.connected = True
        self.connections += 1
        self._backoff.reset()
        self._warn_next_failure = True
        log.info(
            "telemetry: connected to %s as %s%s",
            self.address.url,
            self.client_id,
            " again" if self.connections > 1 else "",
        )
        # A broker restarted without persistence forgot the retained states: send them all.
        self._states[self.status_suffix] = self._status(online=True)
        self._dirty = dict.fromkeys(self._states)
        watcher = asyncio.ensure_future(self._watch(client))
        sender = asyncio.ensure_future(self._send_loop(client))
        try:
            done, _ = await asyncio.wait((watcher, sender), return_when=asyncio.FIRST_COMPLETED)
        finally:
            for task in (watcher, sender):
                task.cancel()
            await asyncio.wait((watcher, sender))
        if sender in done and not sender.cancelled():
            sender.result()  # raises its error; returns when closing
            return
        if not watcher.cancelled():
            watcher.result()  # raises the MqttError of the lost connection
        raise ConnectionError("the connection to the broker ended")

    @staticmethod
    async def _watch(client: Any) -> None:
        # No subscriptions, so no messages: the iteration only ends, with MqttError, when the
        # connection is lost. This notices a lost broker even while nothing is being published.
        async for _ in client.messages:
            pass

    async def _send_loop(self, client: Any) -> None:
        loop = asyncio.get_running_loop()
        status_due = loop.time() + STATUS_INTERVAL
        while True:
            if self._dirty:
                suffix = next(iter(self._dirty))
                del self._dirty[suffix]
                try:
                    await self._send(client, suffix, self._states[suffix], STATE_QOS, True)
                except BaseException:
                    self._dirty.setdefault(suffix, None)  # still unsent: next connection
                    raise
            elif loop.time() >= status_due and not self._closing:
                status_due = loop.time() + STATUS_INTERVAL
                self.publish_nowait(self.status_suffix, self._status(online=True), retain=True)
                continue
            elif self._queue:
                item = self._queue.popleft()
                try:
                    await self._send(client, item[0], item[1], item[2], False)
                except BaseException:
                    # Back to the front for the next connection, unless newer events filled
                    # the queue meanwhile (then it is the oldest and is dropped).
                    if len(self._queue) < (self._queue.maxlen or 0):
                        self._queue.appendleft(item)
                    else:
                        self.dropped += 1
                    raise
            elif self._closing:
                return
            else:
                self._wakeup.clear()
                with contextlib.suppress(TimeoutError):
                    async with asyncio.timeout_at(status_due):
                        await self._wakeup.wait()
                continue
            # A QoS 0 publish completes without suspending: yield after every message so a long
            # queue never holds the event loop (and the control loop in it) for more than one.
            await asyncio.sleep(0)

    async def _send(
        self, client: Any, suffix: str, payload: Payload, qos: int, retain: bool
    ) -> None:
        try:
            data = encode_payload(payload)
        except Exception:  # a bug in a payload: drop that one message, keep the rest flowing
            log.exception("telemetry: cannot encode the message for %s; dropped", suffix)
            return
        self._sending = 1
        try:
            await client.publish(self.topic(suffix), data, qos=qos, retain=retain)
        finally:
            self._sending = 0
        self.sent += 1
