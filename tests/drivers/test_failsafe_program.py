"""The shipped Aseba failsafe program: well-formed and consistent with the driver's constants."""

from __future__ import annotations

import re
import xml.etree.ElementTree as ET
from importlib import resources

from drivers.thymio import FAILSAFE_PROGRAM, FAILSAFE_TICK, HEARTBEAT, PROGRAM_NODE


def _text() -> str:
    program = resources.files("drivers").joinpath(FAILSAFE_PROGRAM)
    assert program.is_file(), "failsafe.aesl must ship as package data"
    return program.read_text("utf-8")


def test_is_an_aesl_document_for_the_thymio_node():
    text = _text()
    assert text.startswith("<!DOCTYPE aesl-source>")
    root = ET.fromstring(text)
    assert root.tag == "network"
    (node,) = root.findall("node")
    assert node.get("name") == PROGRAM_NODE == "thymio-II"
    assert node.get("nodeId") == "1"


def test_counts_down_the_heartbeat_and_zeroes_the_motors():
    code = ET.fromstring(_text()).find("node").text or ""
    assert re.search(rf"^var {HEARTBEAT} = 0$", code, re.M)
    period = re.search(r"^timer\.period\[0\] = (\d+)$", code, re.M)
    assert period is not None and int(period[1]) / 1000 == FAILSAFE_TICK
    events = re.split(r"^onevent ", code, flags=re.M)
    assert len(events) == 2 and events[1].startswith("timer0")
    handler = events[1]
    assert f"{HEARTBEAT} = {HEARTBEAT} - 1" in handler
    assert re.search(
        rf"if {HEARTBEAT} == 0 then\s+motor\.left\.target = 0\s+motor\.right\.target = 0", handler
    )
