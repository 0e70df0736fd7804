"""A screenshot of the browser panel after its "symmetric BPH" preset was pressed (the README's docs/img/panel.png).

    .venv/bin/python scripts/panel_screenshot.py --out docs/img/panel.png

Starts ``phantom daemon --sim --http 127.0.0.1:PORT`` (a data directory of its own, so that its tokens are new),
opens the panel in headless Chromium (Debian's ``chromium`` and ``chromium-driver``, with Selenium), presses the
preset, waits for the page to say "reached" and for the plots to fill, and saves the window.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

PHANTOM = Path(sys.executable).with_name("phantom")


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True, help="the PNG to write")
    parser.add_argument("--size", default="1700,1000", help="the window's width,height in pixels")
    parser.add_argument("--settle-s", type=float, default=8.0, help="how long the plots run after reached (s)")
    args = parser.parse_args()
    from selenium import webdriver
    from selenium.webdriver.common.by import By
    from selenium.webdriver.support.ui import WebDriverWait

    with tempfile.TemporaryDirectory(prefix="phantom-panel-") as folder:
        port = free_port()
        environment = {**os.environ, "PHANTOM_DATA_DIR": f"{folder}/data"}
        log = open(f"{folder}/daemon.log", "w")
        daemon = subprocess.Popen([str(PHANTOM), "daemon", "--sim", "--http", f"127.0.0.1:{port}", "--socket",
                                   f"{folder}/phantomd.sock"], stdout=log, stderr=subprocess.STDOUT, env=environment)
        options = webdriver.ChromeOptions()
        for argument in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", f"--window-size={args.size}",
                         "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--hide-scrollbars"):
            options.add_argument(argument)
        options.binary_location = shutil.which("chromium") or ""
        driver = None
        try:
            tokens = Path(f"{folder}/data/panel-tokens.json")
            deadline = time.monotonic() + 120
            while not tokens.exists():
                if daemon.poll() is not None or time.monotonic() > deadline:
                    sys.exit(f"the daemon did not start:\n{Path(log.name).read_text()}")
                time.sleep(0.5)
            driver = webdriver.Chrome(options=options,
                                      service=webdriver.ChromeService(executable_path=shutil.which("chromedriver")))
            wait = WebDriverWait(driver, 120, poll_frequency=0.3)
            control = json.loads(tokens.read_text())["control"]
            while True:  # until the daemon is ready (a preset before then is answered "starting")
                driver.get(f"http://127.0.0.1:{port}/?token={control}")
                wait.until(lambda d: d.find_element(By.TAG_NAME, "body").get_attribute("data-ready") == "true")
                if driver.find_element(By.ID, "control").text != "starting":
                    break
                time.sleep(2)
            time.sleep(args.settle_s)  # a stretch at rest before the preset, in the plots
            driver.find_element(By.CSS_SELECTOR, '.preset[data-name="symmetric BPH"]').click()
            wait.until(lambda d: d.find_element(By.ID, "target-state").text.startswith("reached"))
            time.sleep(args.settle_s)
            args.out.parent.mkdir(parents=True, exist_ok=True)
            driver.save_screenshot(str(args.out))
            print(f"wrote {args.out}")
        finally:
            if driver is not None:
                driver.quit()
            daemon.send_signal(signal.SIGTERM)
            daemon.wait(30)
            log.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
