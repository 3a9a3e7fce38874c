"""The shared secret at work: mutual proofs in the handshake and the tagging of every frame."""

from __future__ import annotations

import itertools

import pytest

from minimize_surprise.errors import AuthenticationError, ProtocolError
from minimize_surprise.session import (
    NONCE_SIZE,
    PROOF_SIZE,
    TAG_SIZE,
    FrameAuth,
    master_proof,
    new_nonce,
    proof_matches,
    robot_proof,
)

SECRET = b"lab secret"
NR, NM = bytes(range(NONCE_SIZE)), bytes(range(100, 100 + NONCE_SIZE))


def test_nonces_are_fresh_and_fixed_length() -> None:
    nonces = {new_nonce() for _ in range(100)}
    assert len(nonces) == 100 and {len(n) for n in nonces} == {NONCE_SIZE}


@pytest.mark.parametrize("prove", [master_proof, robot_proof])
def test_a_proof_depends_on_the_secret_both_nonces_and_the_robot(prove) -> None:
    proof = prove(SECRET, NR, NM, "thymio-3")
    assert len(proof) == PROOF_SIZE
    assert proof_matches(prove(SECRET, NR, NM, "thymio-3"), proof)
    for other in (
        prove(b"other secret", NR, NM, "thymio-3"),
        prove(SECRET, new_nonce(), NM, "thymio-3"),
        prove(SECRET, NR, new_nonce(), "thymio-3"),
        prove(SECRET, NR, NM, "thymio-4"),
        prove(SECRET, NM, NR, "thymio-3"),  # the nonces swapped
    ):
        assert not proof_matches(other, proof)
    assert not proof_matches(proof[:-1], proof) and not proof_matches(b"", proof)


def test_the_masters_proof_is_no_robots_proof() -> None:
    # A relay that gets the master to prove itself cannot hand that proof back as the robot's.
    assert master_proof(SECRET, NR, NM, "r1") != robot_proof(SECRET, NR, NM, "r1")


def test_nonces_must_have_their_fixed_length() -> None:
    with pytest.raises(ValueError, match="32 bytes"):
        master_proof(SECRET, NR[:-1], NM, "r1")


def pair(robot_id: str = "r1", secret: bytes = SECRET) -> tuple[FrameAuth, FrameAuth]:
    return (
        FrameAuth.for_master(secret, NR, NM, robot_id),
        FrameAuth.for_robot(secret, NR, NM, robot_id),
    )


def test_frames_pass_both_ways_in_order() -> None:
    master, robot = pair()
    for i in range(3):
        sealed = master.seal(b"evaluate %d" % i)
        assert len(sealed) == len(b"evaluate 0") + TAG_SIZE
        assert bytes(robot.open(sealed)) == b"evaluate %d" % i
        assert bytes(master.open(robot.seal(b"result"))) == b"result"
    assert (master.sent, master.received, robot.sent, robot.received) == (3, 3, 3, 3)


def test_a_replayed_frame_fails() -> None:
    master, robot = pair()
    sealed = master.seal(b"evaluate")
    robot.open(sealed)
    with pytest.raises(AuthenticationError, match="frame 1 fails authentication"):
        robot.open(sealed)


def test_reordered_or_dropped_frames_fail() -> None:
    master, robot = pair()
    master.seal(b"one")  # lost on the way, or held back by a relay
    with pytest.raises(AuthenticationError) as info:
        robot.open(master.seal(b"two"))
    assert isinstance(info.value, ProtocolError)  # the connection must be closed


def test_a_frame_sent_back_to_its_sender_fails() -> None:
    # Reflection: the master's own frame, returned as if the robot had sent it.
    master, _ = pair()
    with pytest.raises(AuthenticationError):
        master.open(master.seal(b"ping"))


@pytest.mark.parametrize(
    "other",
    [
        lambda: FrameAuth.for_robot(b"other secret", NR, NM, "r1"),
        lambda: FrameAuth.for_robot(SECRET, new_nonce(), NM, "r1"),  # another session
        lambda: FrameAuth.for_robot(SECRET, NR, NM, "r2"),  # another robot
    ],
)
def test_a_frame_of_another_secret_session_or_robot_fails(other) -> None:
    master, _ = pair()
    with pytest.raises(AuthenticationError):
        other().open(master.seal(b"evaluate"))


def test_a_forged_or_damaged_frame_fails() -> None:
    master, robot = pair()
    sealed = bytearray(master.seal(b"evaluate genome"))
    for i in itertools.islice(range(len(sealed)), 0, None, 3):
        damaged = bytearray(sealed)
        damaged[i] ^= 0x01
        with pytest.raises(AuthenticationError):
            pair()[1].open(damaged)
    assert bytes(robot.open(sealed)) == b"evaluate genome"
    with pytest.raises(AuthenticationError, match="too short"):
        robot.open(bytes(TAG_SIZE))
