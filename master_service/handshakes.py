"""Which connections still in their handshake the master keeps, and which one gives way.

A peer without the secret can open connections and say nothing. The master keeps at most
``limit`` of them (its ``max_pending_connections``); when a new connection would be one too many,
one connection is closed at once, chosen so that a flood only ever hurts its own source:

- The address holding the most handshakes (the new connection counted) gives one up. A flood
  from one address (a misbehaving script, a scanner) then loses its own connections, never the
  handshake of a robot from another address, however fast it reconnects: in a lab each robot has
  an address of its own. This is the per-address limit, applied when it matters: an address may
  hold any number of handshakes while there is room, and no more than any other once there is
  not. A fixed per-address number below ``limit`` would refuse robots that share an address (a
  simulated swarm on loopback, robots behind a NAT) while there is room, and protect nobody
  more, since every other address gets room anyway.
- When that address is the new connection's own, the new connection is closed if it is silent
  (nothing received yet): beyond the limit, a connection that says nothing costs the master no
  handshake at all, however fast a flood comes. A new connection that has spoken already takes
  the place of its address's oldest silent one instead. A robot sends its Hello the moment it is
  connected, and under a flood the master accepts it after that has arrived: a robot that shares
  its address with a silent flood gets in too. (Speaking needs no secret: this holds against
  silence only; the rule above does not rely on it.) With no silent one there, the new
  connection is closed: robots of one address halfway through their handshakes stay.
- When it is another address, that address's oldest silent connection is closed, or its oldest
  when none is silent.

Pure bookkeeping: the server closes the connection :meth:`HandshakeTable.add` names.
"""

from __future__ import annotations

import ipaddress
import itertools
from typing import Generic, TypeVar

__all__ = ["HandshakeTable", "source_of"]

K = TypeVar("K")


def source_of(peer: object) -> str:
    """The source a peer (``transport.get_extra_info("peername")``) counts against: its address
    (an IPv4 address mapped into IPv6 as the IPv4 one; anything unparsable as text).

    An address, not a network: robots on one IPv6 lab network share its /64, so counting a /64
    as one source would put every robot in with a flood from the same network."""
    host = str(peer[0] if isinstance(peer, tuple) and peer else peer)
    if ":" not in host:
        return host  # IPv4, as the kernel writes it: one spelling per address
    try:
        address = ipaddress.ip_address(host.split("%")[0])
    except ValueError:
        return str(host)
    if isinstance(address, ipaddress.IPv6Address) and address.ipv4_mapped is not None:
        return str(address.ipv4_mapped)
    return str(address)


class _Source(Generic[K]):
    """The handshakes of one source, each with its arrival number, oldest first."""

    __slots__ = ("silent", "spoken")

    def __init__(self) -> None:
        self.silent: dict[K, int] = {}
        self.spoken: dict[K, int] = {}

    def __len__(self) -> int:
        return len(self.silent) + len(self.spoken)

    def first(self) -> tuple[bool, int, K]:
        """The one this source gives up for another source's connection: (has spoken, arrival,
        key) of its oldest silent one, else of its oldest."""
        queue = self.silent or self.spoken
        key, arrival = next(iter(queue.items()))
        return queue is self.spoken, arrival, key


class HandshakeTable(Generic[K]):
    """The connections whose handshake is running, by source (see the module docstring)."""

    def __init__(self, limit: int) -> None:
        self.limit = limit
        self._sources: dict[str, _Source[K]] = {}
        self._source_of: dict[K, str] = {}
        self._arrivals = itertools.count()

    def __len__(self) -> int:
        return len(self._source_of)

    def count(self, source: str) -> int:
        """Handshakes running from ``source``."""
        entries = self._sources.get(source)
        return 0 if entries is None else len(entries)

    def add(self, key: K, source: str, *, spoke: bool = False) -> K | None:
        """Enter a new connection from ``source`` (``spoke``: something was received on it
        already); return the connection to close so that at most ``limit`` remain (``key``
        itself, an older one, or None). That one is out of the table."""
        entries = self._sources.setdefault(source, _Source())
        (entries.spoken if spoke else entries.silent)[key] = next(self._arrivals)
        self._source_of[key] = source
        if len(self._source_of) <= self.limit:
            return None
        victim = self._victim(key, source)
        self.remove(victim)
        return victim

    def spoke(self, key: K) -> None:
        """Something was received on the connection: it no longer counts as silent."""
        source = self._source_of.get(key)
        if source is not None:
            entries = self._sources[source]
            arrival = entries.silent.pop(key, None)
            if arrival is not None:
                entries.spoken[key] = arrival

    def remove(self, key: K) -> None:
        """Take a connection out (its handshake ended, or it was closed); no-op if not in."""
        source = self._source_of.pop(key, None)
        if source is None:
            return
        entries = self._sources[source]
        entries.silent.pop(key, None)
        entries.spoken.pop(key, None)
        if not entries:
            del self._sources[source]

    def _victim(self, new: K, source: str) -> K:
        most = max(len(entries) for entries in self._sources.values())
        own = self._sources[source]
        if len(own) == most:
            if new in own.silent:
                return new
            return next(iter(own.silent), new)
        return min(entries.first() for entries in self._sources.values() if len(entries) == most)[2]
