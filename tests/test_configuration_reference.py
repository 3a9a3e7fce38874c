"""The configuration reference, docs/configuration.md, is generated from the typed configuration
(``docs/tools/config_reference.py``, a script beside the docs it writes): the committed file must
be the generated text, and every key must have a meaning."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import msgspec
import pytest

from minimize_surprise.config import EvolutionConfig, NetworkConfig

_TOOL = Path(__file__).resolve().parents[1] / "docs" / "tools" / "config_reference.py"
_spec = importlib.util.spec_from_file_location("config_reference", _TOOL)
assert _spec is not None and _spec.loader is not None
ref = importlib.util.module_from_spec(_spec)
sys.modules["config_reference"] = ref  # dataclasses look their module up by name
_spec.loader.exec_module(ref)
DEFAULT_OUTPUT, Document, documents, generate, main = (
    ref.DEFAULT_OUTPUT,
    ref.Document,
    ref.documents,
    ref.generate,
    ref.main,
)


def test_committed_reference_is_current() -> None:
    assert DEFAULT_OUTPUT.read_text(encoding="utf-8") == generate(), (
        "docs/configuration.md is not current: run `python docs/tools/config_reference.py`"
    )


def test_check_mode(tmp_path, capsys) -> None:
    target = tmp_path / "configuration.md"
    assert main(["--check", "--output", str(target)]) == 1  # missing
    assert "not current" in capsys.readouterr().err
    assert main(["--output", str(target)]) == 0
    assert main(["--check", "--output", str(target)]) == 0
    target.write_text(target.read_text(encoding="utf-8") + "edited\n", encoding="utf-8")
    assert main(["--check", "--output", str(target)]) == 1


def _keys(document: Document) -> set[str]:
    return {row.key.strip("`") for row in ref.rows(document)}


def test_every_key_has_a_meaning_type_and_default() -> None:
    for document in documents():
        for row in ref.rows(document):
            assert row.meaning.strip(), row.key
            assert row.type.strip(), row.key
            assert row.default.strip(), row.key


def test_every_field_of_every_file_is_listed() -> None:
    by_anchor = {d.anchor: d for d in documents()}
    agent = _keys(by_anchor["the-agent-file"])
    for key in (
        "robot_id",
        "master.tls.server_hostname",
        "body.thymio.speed_scale",
        "body.light[].mux.channel",
        "body.force.full_scale_volts",
        "loop.read_timeout",
        "reconnect.jitter",
        "safety",
        "telemetry",
    ):
        assert key in agent
    assert "safety.profile" not in agent  # listed once, in the safety section
    experiment = _keys(by_anchor["the-experiment-file"])
    assert {"network", "evolution", "simulation", "safety"} <= experiment
    for cls, prefix in ((NetworkConfig, "network."), (EvolutionConfig, "evolution.")):
        for info in msgspec.structs.fields(cls):
            assert prefix + info.encode_name in experiment
    study = _keys(by_anchor["the-study-file"])
    assert {"groups[].seeds.from", "groups[].seeds.to", "groups[].sweep"} <= study
    telemetry = _keys(by_anchor["the-telemetry-section"])
    assert "telemetry.reconnect.initial" in telemetry


def test_nested_defaults_come_from_the_parent() -> None:
    # TelemetryConfig's reconnect starts at 1 s, not BackoffConfig's 0.5 s.
    telemetry = {d.anchor: d for d in documents()}["the-telemetry-section"]
    row = next(r for r in ref.rows(telemetry) if r.key == "`telemetry.reconnect.initial`")
    assert row.default == "`1.0`"


def test_meanings_come_from_comments_then_the_docstring() -> None:
    class Example(msgspec.Struct):
        """An example. ``b`` is described here."""

        #: the first key,
        #: over two lines
        a: int = 1
        b: int = 2

    assert ref.meanings(Example) == {
        "a": "the first key, over two lines",
        "b": "``b`` is described here.",
    }

    class Silent(msgspec.Struct):
        """Nothing about it."""

        c: int = 3

    with pytest.raises(ValueError, match=r"Silent\.c has no meaning"):
        ref.meanings(Silent)


def test_anchors_match_the_headings() -> None:
    text = generate()
    for document in documents():
        heading = document.title[0].upper() + document.title[1:]
        assert f"\n## {heading}\n" in text
        assert document.anchor == heading.lower().replace(" ", "-")
        assert f"(#{document.anchor})" in text
