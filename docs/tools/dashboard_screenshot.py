"""The dashboard's picture in the docs, ``docs/images/dashboard.png``, taken from a real page.

::

    python docs/tools/dashboard_screenshot.py                  # simulate a run, then take it
    python docs/tools/dashboard_screenshot.py --run runs/X     # the dashboard of an existing run

Without ``--run`` it simulates a finished run in a temporary directory (the lab setting on the
agents engine, so that the robots' table has every column a real run has: 10 robots,
``--evaluations`` evaluations, seed ``--seed``), serves ``surprise-master dashboard`` for it on a
free port, opens the page in headless chromium (Debian's ``chromium`` and ``chromium-driver``
packages, driven by Selenium with that driver: no download) and saves the window.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Final

#: Where the picture goes: docs/images/ beside this file's folder.
DEFAULT_OUTPUT: Final = Path(__file__).resolve().parents[1] / "images" / "dashboard.png"
#: Seconds the page gets to draw after loading: a poll, the websocket, Bokeh's canvas.
SETTLE: Final = 4.0
#: The browser window: wide enough for the robots' table beside the status, tall enough for
#: the whole page.
WINDOW: Final = "1280,1480"


def _simulate(out: Path, evaluations: int, seed: int) -> None:
    command = [sys.executable, "-m", "master_service", "sim", "--setting", "lab"]
    command += ["--engine", "agents", "--evaluations", str(evaluations), "--seed", str(seed)]
    done = subprocess.run([*command, "--out", str(out)], capture_output=True, text=True)
    if done.returncode:  # its log only when it failed: one line per evaluation
        raise SystemExit(f"the simulated run failed:\n{done.stderr}")


def _screenshot(url: str, output: Path) -> None:
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = "/usr/bin/chromium"
    for argument in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage"):
        options.add_argument(argument)
    options.add_argument(f"--window-size={WINDOW}")
    driver = webdriver.Chrome(
        service=Service(executable_path="/usr/bin/chromedriver"), options=options
    )
    try:
        driver.get(url)
        time.sleep(SETTLE)
        output.parent.mkdir(parents=True, exist_ok=True)
        driver.save_screenshot(str(output))
    finally:
        driver.quit()


def take(run: Path, output: Path) -> None:
    """Serve the dashboard of ``run`` and save a picture of its page to ``output``."""
    command = [sys.executable, "-m", "master_service", "dashboard", str(run), "--port", "0"]
    server = subprocess.Popen(command, stdout=subprocess.PIPE, text=True)
    try:
        assert server.stdout is not None
        line = server.stdout.readline()  # "" when the dashboard ended instead
        if not line.startswith("dashboard: "):
            raise SystemExit(f"the dashboard did not start: {line!r}")
        _screenshot(line.removeprefix("dashboard: ").strip(), output)
    finally:
        server.terminate()
        server.wait()


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point; returns the exit status."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--run", type=Path, help="an existing run directory (default: simulate)")
    parser.add_argument("--evaluations", type=int, default=300, help="of the simulated run")
    parser.add_argument("--seed", type=int, default=3, help="of the simulated run")
    parser.add_argument("--out", type=Path, default=DEFAULT_OUTPUT, help="the PNG to write")
    args = parser.parse_args(argv)
    if args.run is not None:
        take(args.run, args.out)
    else:
        with tempfile.TemporaryDirectory() as directory:
            run = Path(directory) / "lab-sim"
            _simulate(run, args.evaluations, args.seed)
            take(run, args.out)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
