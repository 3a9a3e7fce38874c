"""The safety kernel's inputs are named: ``safety_step(params, sensors, inputs, state)``, four
arguments of four kinds, where it used to take eleven positional values (two of them, the front
and rear IR positions, could be swapped and still compile and run). The rules themselves are
tested in test_safety.py through :class:`SafetyLayer`."""

from __future__ import annotations

import ast
import math
import os
from pathlib import Path

import numpy as np
import pytest

from minimize_surprise.jit import JIT
from minimize_surprise.safety import (
    REASON_OF_CODE,
    SafetyConfig,
    SafetyInput,
    SafetyLayer,
    SafetySensors,
    SafetyState,
    safety_step,
)
from minimize_surprise.sensors import ALL_SENSORS

LAYER = SafetyLayer(ALL_SENSORS, SafetyConfig(profile="escape"))


def full(**by_name: float) -> np.ndarray:
    """Sensor values, all zero except the named ones (underscores stand for dots: ir_f0)."""
    values = np.zeros(len(ALL_SENSORS))
    for key, value in by_name.items():
        values[ALL_SENSORS.index(key.replace("_", "."))] = value
    return values


def inputs(values: np.ndarray, left: float, right: float) -> SafetyInput:
    return SafetyInput(values=values, left=left, right=right, fresh=True, age=-math.inf)


def test_the_kernel_decides_as_the_layer_does():
    state = SafetyState(rng=3)
    for values in (full(), full(ir_f2=0.9), full(ir_b0=0.9), full(force=0.9)):
        array = state.to_array()
        left, right, code = safety_step(
            LAYER.params, LAYER.groups, inputs(values, 0.5, -0.2), array
        )
        decision = LAYER.step(state, values, (0.5, -0.2))
        assert ((left, right), REASON_OF_CODE[code]) == (decision.command, decision.reason)
        assert SafetyState.from_array(array) == decision.state
    assert LAYER.groups == SafetySensors(
        front=LAYER.front, rear=LAYER.rear, ground=LAYER.ground, force=LAYER.force
    )


def test_swapped_kernel_arguments_do_not_run():
    if JIT:
        from numba.core.errors import TypingError

        refused: type[Exception] = TypingError
    else:
        refused = AttributeError
    params, groups, array = LAYER.params, LAYER.groups, SafetyState().to_array()
    step = inputs(full(), 0.5, 0.5)
    with pytest.raises(refused):
        safety_step(params, step, groups, array)
    with pytest.raises(refused):
        safety_step(groups, params, step, array)


#: The kernels' named inputs, which are built with every field named.
NAMED = {"SafetyInput", "SafetySensors", "SafetyParams", "SafetyLayers"}


def _sources() -> list[Path]:
    root = Path(__file__).resolve().parents[2]
    found = []
    for directory, subdirectories, files in os.walk(root):
        subdirectories[:] = [d for d in subdirectories if not d.startswith((".", "__"))]
        found += [Path(directory) / f for f in files if f.endswith(".py")]
    return found


def test_every_kernel_input_is_built_with_its_fields_named():
    # A named tuple can still be built from positions; the house's rule is that it never is,
    # so that no two inputs of one type (two floats, two arrays of positions) can be swapped
    # unseen.
    unnamed = []
    for path in _sources():
        text = path.read_text(encoding="utf-8")
        if not any(name in text for name in NAMED):
            continue
        for node in ast.walk(ast.parse(text)):
            if not isinstance(node, ast.Call):
                continue
            func = node.func
            name = func.id if isinstance(func, ast.Name) else getattr(func, "attr", None)
            if name in NAMED and (node.args or any(k.arg is None for k in node.keywords)):
                unnamed.append(f"{path}:{node.lineno}: {name}(...)")
    assert not unnamed, "build these with every field named:\n" + "\n".join(unnamed)
