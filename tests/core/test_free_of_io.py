"""The method package stays free of I/O: importing every module of ``minimize_surprise`` loads no
networking, event loop or process machinery (the transport lives in the ``transport`` package)."""

from __future__ import annotations

import os
import subprocess
import sys

IO_MODULES = ("asyncio", "socket", "ssl", "selectors", "subprocess")

PROBE = f"""
import importlib, pkgutil, sys
import minimize_surprise
for module in pkgutil.iter_modules(minimize_surprise.__path__):
    importlib.import_module("minimize_surprise." + module.name)
print(",".join(name for name in {IO_MODULES!r} if name in sys.modules))
"""


def test_importing_every_surprise_module_loads_no_io_machinery():
    # A fresh interpreter: this test process has long imported asyncio for other tests. Without
    # numba: the compiler itself imports socket and selectors, which says nothing about our code.
    env = {**os.environ, "SURPRISE_NO_JIT": "1"}
    out = subprocess.run(
        [sys.executable, "-c", PROBE], check=True, capture_output=True, text=True, env=env
    ).stdout.strip()
    assert out == "", f"minimize_surprise imports {out}"
