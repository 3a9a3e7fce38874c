"""The shared secret at work: both sides prove it in the handshake, then every frame is tagged.

Pure functions and one small class, no I/O; ``docs/protocol.md`` describes the conversation.

Handshake: the robot sends a fresh nonce ``Nr`` in Hello; the master answers with its own fresh
nonce ``Nm`` and :func:`master_proof`; the robot checks it before it sends anything else, then
answers with :func:`robot_proof`. Both proofs are HMAC-SHA256 under the secret over a role label,
both nonces and the robot id, so neither can stand in for the other (reflection), for another
robot, or for another session.

Session: :class:`FrameAuth` derives one key per direction from the secret, both nonces and the
robot id (HMAC-SHA256 with a direction label), and appends to every payload a tag: HMAC-SHA256
under the sender's key over a 64-bit sequence number (counting that direction's frames from 0)
and the payload, truncated to :data:`TAG_SIZE` bytes. A relay that forwarded the handshake can
therefore neither inject a frame (no key), nor replay, reorder or drop one (the sequence number
moves on), nor send a frame back where it came from (the other direction's key).
"""

from __future__ import annotations

import hashlib
import hmac
import secrets
import struct
from typing import Final

from minimize_surprise.errors import AuthenticationError

__all__ = [
    "NONCE_SIZE",
    "PROOF_SIZE",
    "TAG_SIZE",
    "FrameAuth",
    "master_proof",
    "new_nonce",
    "proof_matches",
    "robot_proof",
]

#: Length of a nonce in bytes. Fixed, so that the nonces and the robot id that follow them in an
#: HMAC's input cannot be shifted against each other.
NONCE_SIZE: Final = 32
#: Length of a handshake proof in bytes (a whole HMAC-SHA256).
PROOF_SIZE: Final = 32
#: Length of a frame's tag in bytes: HMAC-SHA256 truncated to 128 bits, far beyond what a forger
#: can guess in a session's lifetime, and only 16 bytes on every frame.
TAG_SIZE: Final = 16

# Role and direction labels: the same secret and nonces give unrelated values for each use.
_MASTER_PROOF: Final = b"minimize-surprise/2 master proof"
_ROBOT_PROOF: Final = b"minimize-surprise/2 robot proof"
_MASTER_TO_ROBOT: Final = b"minimize-surprise/2 key master->robot"
_ROBOT_TO_MASTER: Final = b"minimize-surprise/2 key robot->master"
_SEQUENCE: Final = struct.Struct(">Q")


def new_nonce() -> bytes:
    """A fresh random nonce of :data:`NONCE_SIZE` bytes."""
    return secrets.token_bytes(NONCE_SIZE)


def _mac(
    secret: bytes, label: bytes, robot_nonce: bytes, master_nonce: bytes, robot_id: str
) -> bytes:
    if len(robot_nonce) != NONCE_SIZE or len(master_nonce) != NONCE_SIZE:
        raise ValueError(f"nonces are {NONCE_SIZE} bytes")
    # The label ends at its NUL; the nonces have a fixed length; the robot id takes the rest.
    data = label + b"\0" + robot_nonce + master_nonce + robot_id.encode("utf-8")
    return hmac.digest(secret, data, hashlib.sha256)


def master_proof(secret: bytes, robot_nonce: bytes, master_nonce: bytes, robot_id: str) -> bytes:
    """What the master sends in its Challenge to prove it knows ``secret``."""
    return _mac(secret, _MASTER_PROOF, robot_nonce, master_nonce, robot_id)


def robot_proof(secret: bytes, robot_nonce: bytes, master_nonce: bytes, robot_id: str) -> bytes:
    """What the robot sends in Authenticate to prove it knows ``secret``."""
    return _mac(secret, _ROBOT_PROOF, robot_nonce, master_nonce, robot_id)


def proof_matches(expected: bytes, received: bytes) -> bool:
    """Whether a received proof is the expected one, compared in constant time."""
    return hmac.compare_digest(expected, received)


class FrameAuth:
    """One side's tagging of a session's frames: :meth:`seal` outgoing payloads, :meth:`open`
    incoming ones. Build it with :meth:`for_master` or :meth:`for_robot` once the handshake's
    proofs have been checked.
    """

    def __init__(self, send_key: bytes, receive_key: bytes) -> None:
        # The keyed inner and outer states are computed once; each frame copies them.
        self._send = hmac.new(send_key, digestmod=hashlib.sha256)
        self._receive = hmac.new(receive_key, digestmod=hashlib.sha256)
        #: sequence number of the next frame sent / expected
        self.sent = 0
        self.received = 0

    @classmethod
    def for_master(
        cls, secret: bytes, robot_nonce: bytes, master_nonce: bytes, robot_id: str
    ) -> FrameAuth:
        """The master's side of the session the handshake with ``robot_id`` established."""
        args = (robot_nonce, master_nonce, robot_id)
        return cls(_mac(secret, _MASTER_TO_ROBOT, *args), _mac(secret, _ROBOT_TO_MASTER, *args))

    @classmethod
    def for_robot(
        cls, secret: bytes, robot_nonce: bytes, master_nonce: bytes, robot_id: str
    ) -> FrameAuth:
        """The robot's side of the session the handshake established."""
        args = (robot_nonce, master_nonce, robot_id)
        return cls(_mac(secret, _ROBOT_TO_MASTER, *args), _mac(secret, _MASTER_TO_ROBOT, *args))

    @staticmethod
    def _tag(base: hmac.HMAC, sequence: int, payload: bytes | memoryview) -> bytes:
        mac = base.copy()
        mac.update(_SEQUENCE.pack(sequence))
        mac.update(payload)
        return mac.digest()[:TAG_SIZE]

    def tag(self, payload: bytes | memoryview) -> bytes:
        """The tag of the next frame sent, whose payload is ``payload`` (counts the frame)."""
        tag = self._tag(self._send, self.sent, payload)
        self.sent += 1
        return tag

    def seal(self, payload: bytes) -> bytes:
        """``payload`` followed by its tag, as the next frame sent."""
        return payload + self.tag(payload)

    def open(self, sealed: bytes | bytearray | memoryview) -> memoryview:
        """The payload of the next frame received, after checking its tag.

        Raises :class:`~minimize_surprise.errors.AuthenticationError` if the tag does not verify:
        the frame was forged, replayed, reordered, reflected or damaged. The session cannot recover
        from that; the connection must be closed.
        """
        view = memoryview(sealed)
        if len(view) <= TAG_SIZE:
            raise AuthenticationError(f"frame {self.received} is too short to carry a tag")
        payload, tag = view[:-TAG_SIZE], view[-TAG_SIZE:]
        expected = self._tag(self._receive, self.received, payload)
        if not hmac.compare_digest(expected, tag):
            raise AuthenticationError(
                f"frame {self.received} fails authentication "
                "(forged, replayed, reordered or reflected)"
            )
        self.received += 1
        return payload
