"""Golden bytes of every wire message, for every protocol version the code speaks.

The other wire tests round-trip messages through the very structs that encode them, so a field
renamed (in Python, or only its name on the wire), retyped, dropped or moved passes all of them and
breaks every deployed robot. Here every message of the ``Message`` union (enumerated from the union:
a new message without a golden fails) is encoded from a fixed instance and compared with bytes
stored in ``tests/core/golden/wire_v<N>.json``, and the stored bytes are decoded back to the equal
struct. Every optional field, nested structs' included, is set in at least one case and every
message with optional fields has a case with all of them unset (checked below, so that a new
optional field needs its case too).

A golden file maps a case's name (``<tag>`` or ``<tag>/<variant>``) to ``hex``, the message's
payload (msgpack, without the frame's length header or the session's tag), and ``msgpack``, the same
bytes as plain data (binary as ``{"bin": hex}``) so that a change reads in a diff; a test checks
that both say the same.

The current version's file holds every message. An older version's file stays for its peers and
holds what the code still exchanges with them (``LEGACY``): the Hello they open with, which must
still decode (so that the master can tell them about the version), and the Refused that tells them,
whose bytes must be exactly those their codec was built to read.

Changing a golden is changing the protocol (docs/protocol.md). Regenerate deliberately, from the
repository's root::

    python -m tests.core.test_wire_golden --write

It rewrites the current version's file only, and refuses a change that a peer of the same version
could not read (a field renamed, retyped or removed, a message removed; adding an optional field is
fine, older peers ignore it): bump ``PROTOCOL_VERSION`` instead, which starts a new file and keeps
the old one for the old peers (then list it in ``LEGACY``). ``--force`` writes anyway, for when
only a case's instance was changed here.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Iterator
from functools import cache
from pathlib import Path
from typing import Any, Final, Literal, get_args

import msgspec
import numpy as np
import pytest

from minimize_surprise.errors import ProtocolError
from minimize_surprise.network import GenomeLayout, NetworkSpec
from minimize_surprise.wire import (
    FEATURE_ESCAPE,
    PROTOCOL_VERSION,
    REFUSED_VERSION_MISMATCH,
    Abort,
    Authenticate,
    Bye,
    Challenge,
    Check,
    CheckReport,
    Error,
    Escape,
    EscapeReply,
    Evaluate,
    EvaluationStats,
    Failed,
    Hello,
    Message,
    PartCheck,
    Ping,
    Pong,
    Refused,
    Result,
    StopAll,
    Stopped,
    Trace,
    Welcome,
    decode_payload,
    encode_payload,
    genome_to_bytes,
)

GOLDEN_DIR: Final = Path(__file__).resolve().parent / "golden"
WRITE_COMMAND: Final = "python -m tests.core.test_wire_golden --write"

# ---------------------------------------------------------------------------------------------
# The cases: fixed instances with every field set to something recognisable

NONCE: Final = bytes(range(32))
PROOF: Final = bytes(range(0xA0, 0xC0))
SENSORS: Final = ("ir.f0", "ir.f2", "ir.f4", "ground.0", "ground.1")
ROBOT: Final = "thymio-07"
VERSION_REFUSAL: Final = "the master speaks protocol version 2, the robot 1"


def _genome(spec: NetworkSpec) -> bytes:
    size = GenomeLayout(spec).size
    # Distinct values with bits all over the mantissa, a negative zero and a subnormal among them.
    values = np.array([(i - size / 2) / 7.0 for i in range(size)], dtype=np.float64)
    values[0], values[-1] = -0.0, 5e-324
    return genome_to_bytes(values)


def _trace(*, poses: bool) -> Trace:
    return Trace.from_arrays(
        sensors=np.array([[0.125, 0.5], [0.25, 1.0]]),
        predictions=np.array([[0.1, 0.6], [0.3, 0.9]]),
        actions=np.array([[1.0, -1.0], [0.5, 0.25]]),
        commands=np.array([[0.0, 0.0], [0.5, 0.25]]),
        safety=["front", ""],
        poses=np.array([[0.1, 0.2, 3.0], [0.11, 0.19, -3.0]]) if poses else None,
    )


def current_cases() -> dict[str, Message]:
    """Every case of the current protocol version, by name."""
    full_spec = NetworkSpec(
        sensors=SENSORS,
        actor_hidden=3,
        predictor_hidden=4,
        predefined={"ground.0": 0.75, "ground.1": 0.25},
        initial_action=-0.5,
    )
    plain_spec = NetworkSpec(sensors=("ir.f0", "ground.0"), actor_hidden=1, predictor_hidden=2)
    full_stats = EvaluationStats(
        steps_run=1000,
        overruns=3,
        interventions={"front": 12, "ground": 4},
        read_failures=2,
        battery_v=3.875,
    )
    plain_stats = EvaluationStats(steps_run=100, overruns=0, interventions={})
    cases: list[tuple[str, Message]] = [
        (
            "hello/all-set",
            Hello(
                robot_id=ROBOT,
                software_version="0.9.1+pi",
                protocol_version=PROTOCOL_VERSION,
                sensors=SENSORS,
                nonce=NONCE,
                features=(FEATURE_ESCAPE,),
                software_commit="3f2a9c4e1b7d8a6f5e4c3b2a1908f7e6d5c4b3a2-dirty",
                thymio_firmware=14,
            ),
        ),
        (
            "hello/defaults",
            Hello(
                robot_id=ROBOT,
                software_version="0.9.1+pi",
                protocol_version=PROTOCOL_VERSION,
                sensors=SENSORS,
            ),
        ),
        ("challenge", Challenge(nonce=NONCE, proof=PROOF)),
        ("auth", Authenticate(proof=PROOF)),
        ("welcome", Welcome(run_id="2026-11-22T10-15-00-basic", heartbeat_interval=1.5)),
        ("refused", Refused(code=REFUSED_VERSION_MISMATCH, reason=VERSION_REFUSAL)),
        (
            "eval/all-set",
            Evaluate(
                evaluation_id=41,
                genome=_genome(full_spec),
                spec=full_spec,
                steps=1000,
                step_period=0.1,
                record=True,
                post_evaluation=True,
            ),
        ),
        (
            "eval/defaults",
            Evaluate(
                evaluation_id=2**40 + 1,
                genome=_genome(plain_spec),
                spec=plain_spec,
                steps=100,
                step_period=0.01,
            ),
        ),
        (
            "result/all-set",
            Result(evaluation_id=41, fitness=0.8125, stats=full_stats, trace=_trace(poses=True)),
        ),
        (
            "result/trace-without-poses",
            Result(evaluation_id=42, fitness=1.0, stats=plain_stats, trace=_trace(poses=False)),
        ),
        ("result/defaults", Result(evaluation_id=43, fitness=0.0, stats=plain_stats)),
        ("failed", Failed(evaluation_id=44, reason="period: 0.05 s is below loop.min_period")),
        ("abort", Abort(evaluation_id=45, reason="the round's deadline passed")),
        ("check", Check(seq=7)),
        (
            "check-report/read",
            CheckReport(
                seq=7,
                time=1795860000.25,
                battery_v=3.95,
                parts=(
                    PartCheck(part="thymio", sensors=("ir.f0", "ground.0"), values=(0.0, 0.625)),
                    PartCheck(part="light", sensors=("light.0",), error="no answer at 0x29"),
                ),
                forward_safety="ground",
                ground_rule="ground >= 0.55",
            ),
        ),
        ("check-report/busy", CheckReport(seq=8, time=1795860001.5, busy=True)),
        ("check-report/defaults", CheckReport(seq=9, time=-0.0)),
        (
            "check-report/throttled",
            CheckReport(seq=10, time=1795860002.0, battery_v=3.7, throttled=0x50005),
        ),
        ("escape", Escape(seq=11)),
        ("escape-reply/accepted", EscapeReply(seq=11, accepted=True, evaluation_id=2**40 + 2)),
        (
            "escape-reply/refused",
            EscapeReply(
                seq=12, accepted=False, reason="profile: the stop profile has no escape behaviour"
            ),
        ),
        ("escape-reply/defaults", EscapeReply(seq=13, accepted=False)),
        ("stop-all", StopAll(seq=14, reason="surprise-master fleet stop")),
        ("stop-all/defaults", StopAll(seq=15)),
        ("stopped/cancelled", Stopped(seq=14, confirmed=True, evaluation_id=2**40 + 3)),
        (
            "stopped/unconfirmed",
            Stopped(seq=16, confirmed=False, detail="the motor stop: no answer within 0.5 s"),
        ),
        ("stopped/defaults", Stopped(seq=15, confirmed=True)),
        ("ping", Ping(seq=2**63 - 1)),
        ("pong", Pong(seq=0)),
        ("error", Error(code="authentication", message="a frame's tag does not verify")),
        ("bye", Bye(reason="the run is over")),
    ]
    named = dict(cases)
    assert len(named) == len(cases), "two cases of one name"
    return named


Direction = Literal["in", "out"]

#: What the code still exchanges with peers of older protocol versions, whose golden files stay:
#: per version, case name -> ("in", a message they send, which must decode to this) or ("out", a
#: message we send them, which must encode to their golden bytes exactly).
LEGACY: Final[dict[int, dict[str, tuple[Direction, Message]]]] = {
    1: {
        # A version-1 Hello has no nonce; it decodes, so the master can refuse it by its version.
        "hello": (
            "in",
            Hello(robot_id=ROBOT, software_version="0.1.0", protocol_version=1, sensors=SENSORS),
        ),
        "refused": ("out", Refused(code=REFUSED_VERSION_MISMATCH, reason=VERSION_REFUSAL)),
    },
}


# ---------------------------------------------------------------------------------------------
# The golden files


def golden_path(version: int) -> Path:
    return GOLDEN_DIR / f"wire_v{version}.json"


def plain_view(data: bytes) -> Any:
    """The payload as plain data for the file's readers: msgpack decoded, binary as hex."""

    def view(value: Any) -> Any:
        if isinstance(value, bytes):
            return {"bin": value.hex()}
        if isinstance(value, dict):
            return {key: view(item) for key, item in value.items()}
        if isinstance(value, list):
            return [view(item) for item in value]
        return value

    return view(msgspec.msgpack.decode(data))


def render(version: int, about: str, payloads: dict[str, bytes]) -> str:
    """A golden file's text (also used once to write an older version's file with its codec)."""
    document = {
        "protocol_version": version,
        "about": about,
        "cases": {
            name: {"hex": data.hex(), "msgpack": plain_view(data)}
            for name, data in sorted(payloads.items())
        },
    }
    return json.dumps(document, indent=2, ensure_ascii=False) + "\n"


@cache
def load(version: int) -> dict[str, dict[str, Any]]:
    """The cases of ``version``'s golden file; fails the test if there is none."""
    path = golden_path(version)
    if not path.exists():
        pytest.fail(f"no golden file {path.name}: write it with `{WRITE_COMMAND}`")
    document = json.loads(path.read_text(encoding="utf-8"))
    assert document["protocol_version"] == version, f"{path.name} says another version"
    cases: dict[str, dict[str, Any]] = document["cases"]
    return cases


def golden(version: int, name: str) -> bytes:
    cases = load(version)
    assert name in cases, f"{golden_path(version).name} has no case {name!r}: `{WRITE_COMMAND}`"
    return bytes.fromhex(cases[name]["hex"])


def _names_on_disk(version: int) -> list[str]:
    """Case names for parametrizing (read without failing at collection when the file is
    missing: the tests of that version then fail with what to do)."""
    path = golden_path(version)
    if not path.exists():
        return ["<missing golden file>"]
    return sorted(json.loads(path.read_text(encoding="utf-8"))["cases"])


# ---------------------------------------------------------------------------------------------
# Which messages and fields the cases cover


def _tag(cls: type) -> str:
    """A message type's tag, its ``type`` on the wire."""
    return str(msgspec.inspect.type_info(cls).tag)  # type: ignore[attr-defined]


def _struct_types(info: msgspec.inspect.Type) -> Iterator[type[msgspec.Struct]]:
    """Every Struct type reachable from ``info``: the message, and the structs it holds."""
    if isinstance(info, msgspec.inspect.StructType):
        yield info.cls
        for field in info.fields:
            yield from _struct_types(field.type)
        return
    for attribute in ("type", "item_type", "key_type", "value_type"):
        inner = getattr(info, attribute, None)
        if isinstance(inner, msgspec.inspect.Type):
            yield from _struct_types(inner)
    for inner in getattr(info, "types", None) or getattr(info, "item_types", None) or ():
        yield from _struct_types(inner)


def _optional_fields(cls: type[msgspec.Struct]) -> list[msgspec.structs.FieldInfo]:
    return [field for field in msgspec.structs.fields(cls) if not field.required]


def _default(field: msgspec.structs.FieldInfo) -> Any:
    if field.default_factory is not msgspec.NODEFAULT:
        return field.default_factory()
    return field.default


def _is_default(value: Any, default: Any) -> bool:
    return type(value) is type(default) and value == default


def _structs_in(value: Any) -> Iterator[msgspec.Struct]:
    if isinstance(value, msgspec.Struct):
        yield value
        for field in msgspec.structs.fields(value):
            yield from _structs_in(getattr(value, field.name))
    elif isinstance(value, list | tuple):
        for item in value:
            yield from _structs_in(item)
    elif isinstance(value, dict):
        for item in value.values():
            yield from _structs_in(item)


def _all_default(message: Message) -> bool:
    """Whether every optional field in ``message``, nested ones included, is unset."""
    return all(
        _is_default(getattr(struct, field.name), _default(field))
        for struct in _structs_in(message)
        for field in _optional_fields(type(struct))
    )


# ---------------------------------------------------------------------------------------------
# Tests


def test_every_message_of_the_union_has_a_case() -> None:
    union = {_tag(cls) for cls in get_args(Message)}
    cases = current_cases()
    covered = {_tag(type(message)) for message in cases.values()}
    assert union == covered, f"messages without a golden case: {sorted(union - covered)}"
    for name, message in cases.items():
        assert name.split("/")[0] == _tag(type(message)), f"case {name!r} is not named by its tag"


def test_every_optional_field_is_set_in_one_case_and_unset_in_another() -> None:
    cases = current_cases()
    seen: dict[tuple[type, str], set[bool]] = {}
    for message in cases.values():
        for struct in _structs_in(message):
            for field in _optional_fields(type(struct)):
                unset = _is_default(getattr(struct, field.name), _default(field))
                seen.setdefault((type(struct), field.name), set()).add(unset)
    missing = []
    for cls in get_args(Message):
        optional = False
        for struct_type in _struct_types(msgspec.inspect.type_info(cls)):
            for field in _optional_fields(struct_type):
                optional = True
                states = seen.get((struct_type, field.name), set())
                for unset, what in ((False, "set"), (True, "unset")):
                    if unset not in states:
                        missing.append(f"{struct_type.__name__}.{field.name} never {what}")
        if optional and not any(type(m) is cls and _all_default(m) for m in cases.values()):
            missing.append(f"{cls.__name__}: no case with every optional field unset")
    assert not missing, "; ".join(sorted(set(missing)))


def test_the_golden_files_are_those_of_the_versions_spoken() -> None:
    on_disk = {int(path.stem.removeprefix("wire_v")) for path in GOLDEN_DIR.glob("wire_v*.json")}
    spoken = {PROTOCOL_VERSION, *LEGACY}
    assert PROTOCOL_VERSION not in LEGACY
    assert on_disk == spoken, (
        f"golden files for versions {sorted(on_disk)}, the code speaks {sorted(spoken)}: "
        f"write the current one with `{WRITE_COMMAND}`; keep an old one and list it in LEGACY"
    )
    assert set(load(PROTOCOL_VERSION)) == set(current_cases()), (
        f"{golden_path(PROTOCOL_VERSION).name} holds other cases than the code: `{WRITE_COMMAND}`"
    )
    for version, cases in LEGACY.items():
        assert set(cases) <= set(load(version)), f"{golden_path(version).name} lacks cases"


@pytest.mark.parametrize("name", _names_on_disk(PROTOCOL_VERSION))
def test_a_message_encodes_to_its_golden_bytes(name: str) -> None:
    data = golden(PROTOCOL_VERSION, name)
    message = current_cases().get(name)
    assert message is not None, f"golden case {name!r} has no message in the code"
    encoded = encode_payload(message)
    assert encoded == data, (
        f"{name}: the bytes changed, which is a protocol change (docs/protocol.md); "
        f"golden {plain_view(data)}, encoded {plain_view(encoded)}"
    )


@pytest.mark.parametrize("name", _names_on_disk(PROTOCOL_VERSION))
def test_golden_bytes_decode_to_the_message(name: str) -> None:
    data = golden(PROTOCOL_VERSION, name)
    message = current_cases().get(name)
    assert message is not None, f"golden case {name!r} has no message in the code"
    decoded = decode_payload(data)
    assert type(decoded) is type(message)
    assert decoded == message
    # Equal is not enough: 0 == 0.0, so a field retyped from int to float would pass.
    assert encode_payload(decoded) == data, f"{name}: decoded as {decoded!r}"


@pytest.mark.parametrize(
    "version, name", [(version, name) for version in sorted(LEGACY) for name in LEGACY[version]]
)
def test_what_the_code_still_exchanges_with_older_peers(version: int, name: str) -> None:
    direction, message = LEGACY[version][name]
    data = golden(version, name)
    if direction == "out":
        assert encode_payload(message) == data, (
            f"a version-{version} peer can no longer read the {name} it is sent"
        )
    decoded = decode_payload(data)
    assert type(decoded) is type(message)
    assert decoded == message


@pytest.mark.parametrize("path", sorted(GOLDEN_DIR.glob("wire_v*.json")), ids=lambda p: p.name)
def test_a_golden_files_plain_view_says_what_its_bytes_say(path: Path) -> None:
    for name, case in json.loads(path.read_text(encoding="utf-8"))["cases"].items():
        assert plain_view(bytes.fromhex(case["hex"])) == case["msgpack"], f"{path.name}: {name}"


# ---------------------------------------------------------------------------------------------
# Regenerating, deliberately


def _readable_by_old_peers(before: bytes, after: bytes) -> bool:
    """Whether a peer built for ``before`` reads ``after`` and we read ``before``: the change only
    adds map entries (fields an older decoder ignores) and keeps every old one as it was."""

    def within(old: Any, new: Any) -> bool:
        if isinstance(old, dict):
            return isinstance(new, dict) and all(
                key in new and within(value, new[key]) for key, value in old.items()
            )
        if isinstance(old, list):
            return (
                isinstance(new, list)
                and len(old) == len(new)
                and all(within(a, b) for a, b in zip(old, new, strict=True))
            )
        return type(old) is type(new) and old == new

    try:
        decode_payload(before)
    except ProtocolError:
        return False
    return within(msgspec.msgpack.decode(before), msgspec.msgpack.decode(after))


def write(*, force: bool) -> int:
    """Rewrite the current version's golden file; see the module's docstring."""
    path = golden_path(PROTOCOL_VERSION)
    payloads = {name: encode_payload(message) for name, message in current_cases().items()}
    old: dict[str, bytes] = {}
    if path.exists():
        cases = json.loads(path.read_text(encoding="utf-8"))["cases"]
        old = {name: bytes.fromhex(case["hex"]) for name, case in cases.items()}
    changed = sorted(name for name in payloads if name in old and payloads[name] != old[name])
    added = sorted(set(payloads) - set(old))
    removed = sorted(set(old) - set(payloads))
    breaking = removed + [n for n in changed if not _readable_by_old_peers(old[n], payloads[n])]
    for label, names in (("changed", changed), ("added", added), ("removed", removed)):
        if names:
            print(f"{path.name}: {label}: {', '.join(names)}")
    if breaking and not force:
        print(
            f"refused: a version-{PROTOCOL_VERSION} peer could not read {', '.join(breaking)}. "
            "That is a protocol change: bump PROTOCOL_VERSION (a new golden file; keep this one "
            "and list it in LEGACY), or pass --force if only a case's instance changed.",
            file=sys.stderr,
        )
        return 1
    about = (
        f"Golden bytes of wire protocol version {PROTOCOL_VERSION}: each case's payload "
        "(msgpack, no frame header, no tag). Checked by tests/core/test_wire_golden.py; written by "
        f"`{WRITE_COMMAND}`. A change here is a protocol change (docs/protocol.md)."
    )
    text = render(PROTOCOL_VERSION, about, payloads)
    if path.exists() and path.read_text(encoding="utf-8") == text:
        print(f"{path.name}: unchanged")
        return 0
    GOLDEN_DIR.mkdir(parents=True, exist_ok=True)
    path.write_text(text, encoding="utf-8")
    print(f"wrote {path}")
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0] if __doc__ else None)
    parser.add_argument("--write", action="store_true", help="rewrite the current version's file")
    parser.add_argument("--force", action="store_true", help="write even a breaking change")
    args = parser.parse_args(argv)
    if not args.write:
        parser.error("nothing to do: pass --write (the checks run under pytest)")
    return write(force=args.force)


if __name__ == "__main__":
    sys.exit(main())
