"""Tests of the wire protocol: messages, genomes, framing (:mod:`transport.framing`, tested here
with the messages it carries) and authentication (the TCP stream is tested in tests/transport; every
message's exact bytes are pinned in test_wire_golden.py)."""

from __future__ import annotations

import struct

import msgspec
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from minimize_surprise.config import MAX_RECORDED_STEPS, MAX_STEP_PERIOD
from minimize_surprise.errors import FrameTooLargeError, GenomeError, ProtocolError
from minimize_surprise.network import GenomeLayout, NetworkSpec
from minimize_surprise.sensors import ALL_SENSORS
from minimize_surprise.session import NONCE_SIZE, PROOF_SIZE, TAG_SIZE
from minimize_surprise.wire import (
    FEATURE_ESCAPE,
    HANDSHAKE_MAX_FRAME_SIZE,
    MAX_COMMIT_LENGTH,
    MAX_FEATURES,
    MAX_FIRMWARE,
    MAX_FRAME_SIZE,
    MAX_HEARTBEAT_INTERVAL,
    MAX_NAME_LENGTH,
    MAX_REASON_LENGTH,
    MAX_SENSORS,
    MIN_HEARTBEAT_INTERVAL,
    PROTOCOL_VERSION,
    REFUSED_CODES,
    ROBOT_ID_PATTERN,
    Abort,
    Authenticate,
    Bye,
    Challenge,
    Error,
    Escape,
    EscapeReply,
    Evaluate,
    EvaluationStats,
    Failed,
    Hello,
    Message,
    Ping,
    Pong,
    Refused,
    Result,
    StopAll,
    Stopped,
    Trace,
    Welcome,
    decode_payload,
    genome_from_bytes,
    genome_to_bytes,
    printable,
)
from transport.framing import FrameDecoder, encode

FAST = settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
FEW = settings(max_examples=50, deadline=None, suppress_health_check=[HealthCheck.too_slow])

# ---------------------------------------------------------------------------------------------
# Strategies

finite = st.floats(allow_nan=False, allow_infinity=False)
unit = st.floats(min_value=0.0, max_value=1.0)
periods = st.floats(min_value=0.0, max_value=MAX_STEP_PERIOD, exclude_min=True)
small_text = st.text(max_size=20)
u63 = st.integers(min_value=0, max_value=2**63 - 1)
i64 = st.integers(min_value=-(2**63), max_value=2**63 - 1)

genomes = st.lists(finite, max_size=40).map(lambda xs: np.array(xs, dtype=np.float64))


@st.composite
def network_specs(draw: st.DrawFn) -> NetworkSpec:
    sensors = tuple(draw(st.lists(st.sampled_from(ALL_SENSORS), min_size=1, unique=True)))
    predefined_names = draw(st.lists(st.sampled_from(sensors), unique=True))
    return NetworkSpec(
        sensors=sensors,
        actor_hidden=draw(st.integers(1, 64)),
        predictor_hidden=draw(st.integers(1, 64)),
        predefined={name: draw(unit) for name in predefined_names},
        initial_action=draw(finite),
    )


def rows(width: int, steps: int) -> st.SearchStrategy[np.ndarray]:
    return st.lists(
        st.lists(finite, min_size=width, max_size=width), min_size=steps, max_size=steps
    ).map(lambda r: np.array(r, dtype=np.float64).reshape(steps, width))


@st.composite
def traces(draw: st.DrawFn) -> Trace:
    steps = draw(st.integers(0, 8))
    width = draw(st.integers(1, MAX_SENSORS))
    return Trace.from_arrays(
        sensors=draw(rows(width, steps)),
        predictions=draw(rows(width, steps)),
        actions=draw(rows(2, steps)),
        commands=draw(rows(2, steps)),
        safety=draw(st.lists(small_text, min_size=steps, max_size=steps)),
        poses=draw(st.none() | rows(3, steps)),
    )


stats = st.builds(
    EvaluationStats,
    steps_run=u63,
    overruns=u63,
    interventions=st.dictionaries(small_text, u63, max_size=4),
    read_failures=u63,
)

messages: st.SearchStrategy[Message] = st.one_of(
    st.builds(
        Hello,
        robot_id=st.from_regex(ROBOT_ID_PATTERN, fullmatch=True),
        software_version=small_text,
        protocol_version=i64,
        sensors=st.lists(small_text, max_size=MAX_SENSORS).map(tuple),
        nonce=st.none() | st.binary(min_size=NONCE_SIZE, max_size=NONCE_SIZE),
        features=st.lists(small_text, max_size=MAX_FEATURES).map(tuple),
        software_commit=st.none() | small_text,
        thymio_firmware=st.none() | st.integers(0, MAX_FIRMWARE),
    ),
    st.builds(
        Challenge,
        nonce=st.binary(min_size=NONCE_SIZE, max_size=NONCE_SIZE),
        proof=st.binary(min_size=PROOF_SIZE, max_size=PROOF_SIZE),
    ),
    st.builds(Authenticate, proof=st.binary(min_size=PROOF_SIZE, max_size=PROOF_SIZE)),
    st.builds(
        Welcome,
        run_id=small_text,
        heartbeat_interval=st.floats(
            min_value=MIN_HEARTBEAT_INTERVAL, max_value=MAX_HEARTBEAT_INTERVAL
        ),
    ),
    st.builds(Refused, code=st.sampled_from(sorted(REFUSED_CODES)), reason=small_text),
    st.builds(
        Evaluate,
        evaluation_id=u63,
        genome=genomes.map(genome_to_bytes),
        spec=network_specs(),
        steps=st.integers(1, 2**63 - 1),
        step_period=periods,
        record=st.just(False),
    ),
    st.builds(
        Evaluate,
        evaluation_id=u63,
        genome=genomes.map(genome_to_bytes),
        spec=network_specs(),
        steps=st.integers(1, MAX_RECORDED_STEPS),
        step_period=periods,
        record=st.just(True),
        post_evaluation=st.booleans(),
    ),
    st.builds(
        Result,
        evaluation_id=u63,
        fitness=unit,
        stats=stats,
        trace=st.none() | traces(),
    ),
    st.builds(Failed, evaluation_id=u63, reason=small_text),
    st.builds(Abort, evaluation_id=u63, reason=small_text),
    st.builds(Escape, seq=u63),
    st.builds(
        EscapeReply,
        seq=u63,
        accepted=st.booleans(),
        evaluation_id=st.none() | u63,
        reason=small_text,
    ),
    st.builds(StopAll, seq=u63, reason=small_text),
    st.builds(
        Stopped,
        seq=u63,
        confirmed=st.booleans(),
        evaluation_id=st.none() | u63,
        detail=small_text,
    ),
    st.builds(Ping, seq=u63),
    st.builds(Pong, seq=u63),
    st.builds(Error, code=small_text, message=small_text),
    st.builds(Bye, reason=small_text),
)


def decode_frame(frame: bytes) -> Message:
    decoded = FrameDecoder().feed(frame)
    assert len(decoded) == 1
    return decoded[0]


def frame(payload: bytes) -> bytes:
    return struct.pack(">I", len(payload)) + payload


# ---------------------------------------------------------------------------------------------
# Messages


@FAST
@given(messages)
def test_any_message_round_trips_exactly(msg: Message) -> None:
    data = encode(msg)
    back = decode_frame(data)
    assert type(back) is type(msg)
    assert back == msg
    # Re-encoding gives the same bytes, so floats (incl. -0.0) survive bit for bit.
    assert encode(back) == data


def test_frame_layout_is_big_endian_length_then_msgpack_with_type_tag() -> None:
    data = encode(Ping(seq=7))
    (length,) = struct.unpack(">I", data[:4])
    assert length == len(data) - 4
    assert msgspec.msgpack.decode(data[4:]) == {"type": "ping", "seq": 7}


def test_unknown_fields_are_ignored_for_forward_compatibility() -> None:
    payload = msgspec.msgpack.encode({"type": "ping", "seq": 3, "added_later": [1, 2]})
    assert decode_frame(frame(payload)) == Ping(seq=3)


@pytest.mark.parametrize(
    "payload",
    [
        {"type": "nope", "seq": 1},
        {"seq": 1},
        {"type": "ping"},
        {"type": "ping", "seq": -1},
        {"type": "ping", "seq": "1"},
        {"type": "challenge", "nonce": b"short"},
        {"type": "welcome", "run_id": "r", "heartbeat_interval": 0.0},
        {"type": "result", "evaluation_id": 1, "fitness": float("nan"), "stats": {}},
        [1, 2, 3],
        "ping",
    ],
)
def test_invalid_payloads_are_protocol_errors(payload: object) -> None:
    with pytest.raises(ProtocolError, match="malformed message"):
        decode_payload(msgspec.msgpack.encode(payload))


def test_evaluate_with_malformed_genome_is_rejected_when_decoded() -> None:
    spec = NetworkSpec(sensors=("ir.f0",), actor_hidden=1, predictor_hidden=1)
    message = Evaluate(evaluation_id=0, genome=b"", spec=spec, steps=1, step_period=0.1)
    good = msgspec.msgpack.decode(msgspec.msgpack.encode(message))
    for genome in (b"\x00" * 7, struct.pack("<d", float("inf"))):
        with pytest.raises(ProtocolError, match="malformed message"):
            decode_payload(msgspec.msgpack.encode({**good, "genome": genome}))


def test_trace_arrays_must_have_one_row_per_step() -> None:
    with pytest.raises(ValueError, match="predictions must be shaped"):
        Trace.from_arrays(
            sensors=np.zeros((1, 1)),
            predictions=np.zeros((0, 1)),
            actions=np.zeros((1, 2)),
            commands=np.zeros((1, 2)),
            safety=[""],
        )
    with pytest.raises(ValueError, match="one entry per step"):
        Trace.from_arrays(
            sensors=np.zeros((1, 1)),
            predictions=np.zeros((1, 1)),
            actions=np.zeros((1, 2)),
            commands=np.zeros((1, 2)),
            safety=[],
        )


def test_a_trace_reads_back_as_arrays_bit_for_bit() -> None:
    sensors = np.array([[0.1, -0.0], [5e-324, 1.0]])
    trace = sample_trace(2, 2)
    trace = Trace.from_arrays(
        sensors=sensors,
        predictions=trace.array("predictions"),
        actions=trace.array("actions"),
        commands=trace.array("commands"),
        safety=["", "front"],
    )
    back = decode_frame(encode(Result(evaluation_id=1, fitness=0.5, stats=STATS, trace=trace)))
    assert back.trace.array("sensors").tobytes() == sensors.tobytes()
    assert back.trace.array("sensors").shape == (2, 2) and back.trace.poses is None
    with pytest.raises(ValueError, match="no poses"):
        back.trace.array("poses")


def test_nested_data_too_deep_is_a_protocol_error() -> None:
    # A hostile peer can nest arrays far deeper than the interpreter's recursion limit.
    head = msgspec.msgpack.encode({"type": "ping", "seq": 1, "x": None})[:-1]
    payload = head + b"\x91" * 200_000 + b"\x01"
    with pytest.raises(ProtocolError):
        decode_payload(payload)


def test_encode_refuses_non_messages() -> None:
    with pytest.raises(TypeError):
        encode(EvaluationStats(steps_run=1, overruns=0, interventions={}))  # type: ignore[arg-type]


def test_protocol_version_is_two() -> None:
    # 2: mutual authentication and tagged frames, the step period, packed traces.
    assert PROTOCOL_VERSION == 2


# ---------------------------------------------------------------------------------------------
# Genomes


@FAST
@given(genomes)
def test_genome_bytes_are_bit_exact(genome: np.ndarray) -> None:
    data = genome_to_bytes(genome)
    assert len(data) == 8 * len(genome)
    back = genome_from_bytes(data)
    assert back.dtype == np.float64
    assert back.tobytes() == genome.astype("<f8").tobytes()
    assert np.array_equal(np.signbit(back), np.signbit(genome))


def test_genome_special_values_survive() -> None:
    values = np.array([-0.0, 5e-324, -2.2250738585072014e-308, 1.7976931348623157e308, -1.0])
    back = genome_from_bytes(genome_to_bytes(values))
    assert back.tobytes() == values.tobytes()
    assert np.signbit(back[0])
    back[0] = 1.0  # the caller owns a writable copy


def test_genome_is_little_endian() -> None:
    assert genome_to_bytes(np.array([1.0])) == struct.pack("<d", 1.0)
    assert genome_to_bytes(np.array([1.0], dtype=">f8")) == struct.pack("<d", 1.0)


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), float("-inf")])
def test_non_finite_genome_values_are_rejected(bad: float) -> None:
    with pytest.raises(ProtocolError, match="non-finite"):
        genome_from_bytes(struct.pack("<3d", 0.0, bad, 1.0))
    with pytest.raises(GenomeError):
        genome_to_bytes(np.array([0.0, bad]))


@pytest.mark.parametrize("length", [1, 7, 9, 15])
def test_genome_length_must_be_a_multiple_of_eight(length: int) -> None:
    with pytest.raises(ProtocolError, match="float64"):
        genome_from_bytes(bytes(length))


def test_genome_must_be_flat() -> None:
    with pytest.raises(GenomeError, match="one-dimensional"):
        genome_to_bytes(np.zeros((2, 2)))


# ---------------------------------------------------------------------------------------------
# Framing


@FAST
@given(st.lists(messages, min_size=1, max_size=5), st.data())
def test_any_split_of_a_stream_decodes_to_the_same_messages(
    msgs: list[Message], data: st.DataObject
) -> None:
    stream = b"".join(encode(m) for m in msgs)
    cuts = sorted(data.draw(st.lists(st.integers(0, len(stream)), max_size=10)))
    decoder = FrameDecoder()
    decoded: list[Message] = []
    for start, end in zip([0, *cuts], [*cuts, len(stream)], strict=True):
        decoded.extend(decoder.feed(stream[start:end]))
    assert decoded == msgs
    assert decoder.pending == 0


@FEW
@given(st.lists(messages, min_size=1, max_size=3))
def test_byte_at_a_time_decodes_to_the_same_messages(msgs: list[Message]) -> None:
    stream = b"".join(encode(m) for m in msgs)
    decoder = FrameDecoder()
    decoded: list[Message] = []
    for i in range(len(stream)):
        decoded.extend(decoder.feed(stream[i : i + 1]))
    assert decoded == msgs


def test_pending_counts_buffered_bytes() -> None:
    data = encode(Bye(reason="done"))
    decoder = FrameDecoder()
    assert decoder.feed(data[:3]) == []
    assert decoder.pending == 3
    assert decoder.feed(data[3:-1]) == []
    assert decoder.pending == len(data) - 1
    assert decoder.feed(data[-1:] + data[:2]) == [Bye(reason="done")]
    assert decoder.pending == 2


def test_large_frame_byte_at_a_time_is_linear() -> None:
    # About 0.3 MB fed one byte at a time: quadratic buffering would take minutes.
    msg = Bye(reason="x" * 300_000)
    data = encode(msg)
    decoder = FrameDecoder()
    out: list[Message] = []
    view = memoryview(data)
    for i in range(len(data)):
        out += decoder.feed(view[i : i + 1])
    assert out == [msg]


@FAST
@given(st.binary(max_size=200))
def test_random_bytes_raise_only_protocol_errors(data: bytes) -> None:
    try:
        decoded = FrameDecoder(max_frame_size=1024).feed(data)
    except ProtocolError:
        return
    assert all(isinstance(m, Message) for m in decoded)


@FAST
@given(st.binary(min_size=1, max_size=200))
def test_random_payloads_in_valid_frames_raise_only_protocol_errors(payload: bytes) -> None:
    try:
        decoded = FrameDecoder().feed(frame(payload))
    except ProtocolError as exc:
        assert "malformed message" in str(exc)
        return
    assert len(decoded) == 1
    assert isinstance(decoded[0], Message)


@FAST
@given(messages, st.data())
def test_corrupted_frames_raise_only_protocol_errors(msg: Message, data: st.DataObject) -> None:
    payload = bytearray(encode(msg)[4:])
    for _ in range(data.draw(st.integers(1, 4))):
        i = data.draw(st.integers(0, len(payload) - 1))
        payload[i] = data.draw(st.integers(0, 255))
    try:
        decoded = FrameDecoder().feed(frame(bytes(payload)))
    except ProtocolError:
        return
    assert all(isinstance(m, Message) for m in decoded)


def test_oversized_header_is_rejected_before_the_body_arrives() -> None:
    decoder = FrameDecoder(max_frame_size=100)
    assert decoder.feed(struct.pack(">I", 101)[:3]) == []
    with pytest.raises(FrameTooLargeError) as info:
        decoder.feed(struct.pack(">I", 101)[3:])
    assert (info.value.size, info.value.limit) == (101, 100)
    assert decoder.pending == 0


def test_default_limit_is_eight_mebibytes() -> None:
    assert MAX_FRAME_SIZE == 8 * 1024 * 1024
    assert FrameDecoder().max_frame_size == MAX_FRAME_SIZE
    with pytest.raises(FrameTooLargeError):
        FrameDecoder().feed(struct.pack(">I", MAX_FRAME_SIZE + 1))


def test_frame_at_the_limit_is_accepted() -> None:
    data = encode(Bye(reason="x" * 50))
    limit = len(data) - 4
    assert FrameDecoder(max_frame_size=limit).feed(data) == [Bye(reason="x" * 50)]
    assert encode(Bye(reason="x" * 50), max_frame_size=limit) == data


def test_encode_refuses_oversized_messages() -> None:
    with pytest.raises(FrameTooLargeError) as info:
        encode(Bye(reason="x" * 1000), max_frame_size=999)
    assert info.value.limit == 999
    assert info.value.size > 999


def test_zero_length_frame_is_a_protocol_error() -> None:
    with pytest.raises(ProtocolError, match="empty frame"):
        FrameDecoder().feed(encode(Ping(seq=1)) + bytes(4))


@pytest.mark.parametrize(
    "bad",
    [bytes(4), struct.pack(">I", 1 << 30), frame(b"\xc1"), frame(msgspec.msgpack.encode({}))],
)
def test_decoder_is_poisoned_after_an_error(bad: bytes) -> None:
    decoder = FrameDecoder()
    with pytest.raises(ProtocolError):
        decoder.feed(bad)
    with pytest.raises(ProtocolError, match="earlier error"):
        decoder.feed(encode(Ping(seq=1)))
    with pytest.raises(ProtocolError):
        decoder.feed(b"")


def test_messages_before_a_bad_frame_in_the_same_chunk_are_lost_with_the_connection() -> None:
    # The whole chunk raises: the connection is closed anyway, so nothing is half-delivered.
    decoder = FrameDecoder()
    with pytest.raises(ProtocolError):
        decoder.feed(encode(Ping(seq=1)) + frame(b"\xc1"))


# ---------------------------------------------------------------------------------------------
# What may arrive before authentication is bounded in its type


def hello_payload(**changes: object) -> bytes:
    fields = {
        "type": "hello",
        "robot_id": "thymio-1",
        "software_version": "0.1.0",
        "protocol_version": PROTOCOL_VERSION,
        "sensors": list(ALL_SENSORS),
        "nonce": bytes(NONCE_SIZE),
    }
    fields.update(changes)
    return msgspec.msgpack.encode(fields)


@pytest.mark.parametrize(
    "changes, words",
    [
        # 65,000 empty names once held half a megabyte per connection for the whole handshake.
        ({"sensors": [""] * 65_000}, f"length <= {MAX_SENSORS}"),
        ({"sensors": ["x" * (MAX_NAME_LENGTH + 1)]}, f"length <= {MAX_NAME_LENGTH}"),
        ({"robot_id": "r" * 65}, "robot_id"),
        ({"robot_id": "no spaces"}, "robot_id"),
        ({"software_version": "v" * 65}, "software_version"),
        ({"software_commit": "c" * (MAX_COMMIT_LENGTH + 1)}, "software_commit"),
        ({"thymio_firmware": MAX_FIRMWARE + 1}, "thymio_firmware"),
        ({"thymio_firmware": -1}, "thymio_firmware"),
        ({"nonce": bytes(NONCE_SIZE - 1)}, "nonce"),
        ({"nonce": bytes(NONCE_SIZE + 1)}, "nonce"),
    ],
)
def test_a_hello_out_of_bounds_is_refused_by_decoding(changes, words) -> None:
    with pytest.raises(ProtocolError, match="malformed message") as info:
        decode_payload(hello_payload(**changes))
    assert words in str(info.value)


@pytest.mark.parametrize(
    "payload, words",
    [
        ({"type": "auth", "proof": bytes(PROOF_SIZE + 1)}, "proof"),
        ({"type": "auth", "proof": bytes(300_000)}, "proof"),
        ({"type": "challenge", "nonce": bytes(NONCE_SIZE), "proof": b""}, "proof"),
        ({"type": "refused", "code": "x" * 33, "reason": ""}, "code"),
        ({"type": "refused", "code": "protocol", "reason": "x" * 513}, "reason"),
        ({"type": "welcome", "run_id": "r" * 256, "heartbeat_interval": 1.0}, "run_id"),
        ({"type": "welcome", "run_id": "r", "heartbeat_interval": 1e-6}, "heartbeat_interval"),
        ({"type": "welcome", "run_id": "r", "heartbeat_interval": 1e6}, "heartbeat_interval"),
    ],
)
def test_other_handshake_messages_out_of_bounds_are_refused(payload, words) -> None:
    with pytest.raises(ProtocolError, match="malformed message") as info:
        decode_payload(msgspec.msgpack.encode(payload))
    assert words in str(info.value)


def test_the_largest_handshake_messages_fit_the_small_handshake_frames() -> None:
    largest = [
        Hello(
            robot_id="r" * 64,
            software_version="\u00e9" * 64,
            protocol_version=-(2**63),
            sensors=tuple("\u00e9" * MAX_NAME_LENGTH for _ in range(MAX_SENSORS)),
            nonce=bytes(NONCE_SIZE),
            features=tuple("\u00e9" * MAX_NAME_LENGTH for _ in range(MAX_FEATURES)),
            software_commit="\u00e9" * MAX_COMMIT_LENGTH,
            thymio_firmware=MAX_FIRMWARE,
        ),
        Challenge(nonce=bytes(NONCE_SIZE), proof=bytes(PROOF_SIZE)),
        Authenticate(proof=bytes(PROOF_SIZE)),
        Refused(code="\u00e9" * MAX_NAME_LENGTH, reason="\u00e9" * MAX_REASON_LENGTH),
        Welcome(run_id="\u00e9" * 255, heartbeat_interval=MAX_HEARTBEAT_INTERVAL),
    ]
    for msg in largest:
        # Tagged (Welcome, a late Refused) or not: either way within the limit, and decodable.
        data = encode(msg, max_frame_size=HANDSHAKE_MAX_FRAME_SIZE - TAG_SIZE)
        assert decode_frame(data) == msg


def test_a_hello_of_a_robot_older_than_its_commit_and_firmware_says_neither() -> None:
    # An agent deployed before the fields existed is still accepted: they are unknown.
    msg = decode_payload(hello_payload())
    assert isinstance(msg, Hello)
    assert msg.software_commit is None and msg.thymio_firmware is None


def test_a_hello_of_a_robot_older_than_its_features_offers_none() -> None:
    # A version-2 robot deployed before features existed sends no such field: it offers nothing,
    # so the master never sends it a message it would not decode.
    payload = msgspec.msgpack.decode(hello_payload(protocol_version=PROTOCOL_VERSION))
    payload.pop("features", None)
    msg = decode_payload(msgspec.msgpack.encode(payload))
    assert isinstance(msg, Hello) and msg.features == ()
    offered = Hello(**{**msgspec.structs.asdict(msg), "features": (FEATURE_ESCAPE,)})
    assert decode_payload(msgspec.msgpack.encode(offered)) == offered


def test_a_hello_of_another_version_may_lack_the_nonce() -> None:
    # An older robot is told about the version rather than about a missing field.
    msg = decode_payload(hello_payload(protocol_version=1, nonce=None))
    assert isinstance(msg, Hello) and msg.protocol_version == 1 and msg.nonce is None


@pytest.mark.parametrize(
    "text, limit, expected",
    [
        ("bad secret", 200, "bad secret"),
        ("line\nbreak\x1b[2Jclear\u2028", 200, "line?break?[2Jclear?"),
        ("x" * 300, 200, "x" * 200 + "..."),
        ("\x00" * 10_000_000, 5, "?????..."),
    ],
)
def test_printable_cuts_and_cleans_a_peers_text(text, limit, expected) -> None:
    assert printable(text, limit) == expected


def sample_trace(steps: int, width: int) -> Trace:
    row = [0.123456789 * i for i in range(width)]
    return Trace.from_arrays(
        sensors=np.array([row] * steps).reshape(steps, width),
        predictions=np.array([row] * steps).reshape(steps, width),
        actions=np.array([[0.5, -0.5]] * steps).reshape(steps, 2),
        commands=np.array([[0.5, -0.5]] * steps).reshape(steps, 2),
        safety=[""] * steps,
        poses=np.array([[1.0, 2.0, 3.0]] * steps).reshape(steps, 3),
    )


STATS = EvaluationStats(steps_run=2, overruns=0, interventions={})


def result_with_trace(**changes: object) -> dict:
    """A Result with a 2-step, 2-sensor trace as plain data, with ``changes`` to the trace."""
    good = msgspec.to_builtins(
        Result(evaluation_id=1, fitness=0.5, stats=STATS, trace=sample_trace(2, 2)),
        builtin_types=(bytes,),
    )
    good["trace"].update(changes)
    return good


@pytest.mark.parametrize(
    "field, value, words",
    [
        ("sensors", bytes(3 * 8), "sensors must hold 2 x 2 float64 values"),  # a row short
        ("predictions", bytes(2 * 8), "predictions must hold 2 x 2"),
        ("actions", bytes(2 * 3 * 8), "actions must hold 2 x 2"),  # not two wheel speeds
        ("poses", bytes(2 * 2 * 8), "poses must hold 2 x 3"),  # not (x, y, theta)
        ("safety", ["", "", ""], "one entry per step"),
        ("sensors", [[0.1, 0.2], [0.3, 0.4]], "Expected `bytes`"),  # rows are not accepted
        ("steps", MAX_RECORDED_STEPS + 1, f"<= {MAX_RECORDED_STEPS}"),
        ("width", MAX_SENSORS + 1, f"<= {MAX_SENSORS}"),
        ("width", 0, ">= 1"),
        ("safety", ["x" * (MAX_NAME_LENGTH + 1), ""], f"<= {MAX_NAME_LENGTH}"),
    ],
)
def test_a_trace_of_the_wrong_shape_or_size_is_a_protocol_error(field, value, words) -> None:
    # The master stores a trace as arrays: a malformed one must be refused where it enters, not
    # crash the run when the post-evaluation is written.
    with pytest.raises(ProtocolError, match="malformed message") as info:
        decode_payload(msgspec.msgpack.encode(result_with_trace(**{field: value})))
    assert words in str(info.value)


@pytest.mark.parametrize(
    "field, header",
    [
        ("sensors", b"\xdd"),  # 8 million empty rows where packed bytes belong
        ("safety", b"\xdd"),  # 8 million empty reasons for at most 20,000 steps
        ("sensors", b"\xc6"),  # one 8 MiB array where no trace needs more than 2.5 MB
    ],
)
def test_a_hostile_frame_is_refused_before_it_is_built(field, header) -> None:
    # One 8 MiB frame used to cost the master 600 MB and seconds of decoding: the shape and
    # size are checked as the frame is decoded, so nothing of its size is ever built.
    import tracemalloc

    head = msgspec.msgpack.encode(
        {"type": "result", "evaluation_id": 1, "fitness": 0.5, "stats": msgspec.to_builtins(STATS)}
    )
    prefix = bytes([0x85]) + head[1:] + msgspec.msgpack.encode("trace")
    prefix += bytes([0x81]) + msgspec.msgpack.encode(field)
    count = MAX_FRAME_SIZE - len(prefix) - 5
    filler = b"\x90" if field == "sensors" else b"\xa0"
    body = bytes(count) if header == b"\xc6" else filler * count
    payload = prefix + header + struct.pack(">I", count) + body
    assert len(payload) == MAX_FRAME_SIZE
    frame = struct.pack(">I", len(payload)) + payload
    tracemalloc.start()
    try:
        with pytest.raises(ProtocolError, match="malformed message"):
            FrameDecoder().feed(frame)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    # The frame is buffered (a copy or two of its 8 MiB); decoding adds next to nothing, where
    # a list of rows cost 530 MB of Python objects.
    assert peak < 3 * MAX_FRAME_SIZE


def test_the_largest_trace_fits_one_frame() -> None:
    steps, width = MAX_RECORDED_STEPS, MAX_SENSORS
    trace = Trace.from_arrays(
        sensors=np.zeros((steps, width)),
        predictions=np.zeros((steps, width)),
        actions=np.zeros((steps, 2)),
        commands=np.zeros((steps, 2)),
        safety=["x" * MAX_NAME_LENGTH] * steps,
        poses=np.zeros((steps, 3)),
    )
    result = Result(evaluation_id=2**63 - 1, fitness=1.0, stats=STATS, trace=trace)
    assert decode_frame(encode(result)) == result


@pytest.mark.parametrize("fitness", [1e300, -0.5, 1.0000001, -1e-300, float("inf")])
def test_a_fitness_outside_zero_to_one_is_a_protocol_error(fitness: float) -> None:
    # Surprise fitness lies in [0, 1]: one result of 1e300 once froze the evolution.
    payload = msgspec.to_builtins(Result(evaluation_id=1, fitness=0.5, stats=STATS))
    payload["fitness"] = fitness
    with pytest.raises(ProtocolError, match="fitness"):
        decode_payload(msgspec.msgpack.encode(payload))
    for edge in (0.0, 1.0):
        payload["fitness"] = edge
        assert decode_payload(msgspec.msgpack.encode(payload)).fitness == edge


def test_a_recorded_evaluation_too_long_for_one_frame_is_refused():
    """Its trace could never be sent back: refuse it where it enters, on either side."""
    spec = NetworkSpec(sensors=("ir.f0",), actor_hidden=1, predictor_hidden=1)
    genome = genome_to_bytes(np.zeros(GenomeLayout(spec).size))
    Evaluate(
        evaluation_id=1,
        genome=genome,
        spec=spec,
        steps=MAX_RECORDED_STEPS,
        step_period=0.1,
        record=True,
    )
    Evaluate(
        evaluation_id=1, genome=genome, spec=spec, steps=10 * MAX_RECORDED_STEPS, step_period=0.1
    )
    with pytest.raises(ProtocolError, match="at most"):
        Evaluate(
            evaluation_id=1,
            genome=genome,
            spec=spec,
            steps=MAX_RECORDED_STEPS + 1,
            step_period=0.1,
            record=True,
        )
