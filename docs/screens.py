"""The README's pictures of the dashboard: ``.venv/bin/python docs/screens.py``.

Runs the default line (``configs/line.toml``, full image size) in a scratch
folder with a drifting process (a dent growing part by part at the panel's
centre after the baseline), waits for the control chart's alarm, and saves
the board, the drifting point's control chart and the report of the part
that raised the alarm, as Debian's chromium shows them (Playwright drives it).
Takes a few minutes: the line measures a part every few seconds here.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
import urllib.request
from pathlib import Path

from playwright.sync_api import sync_playwright

ROOT = Path(__file__).resolve().parents[1]
OUT = Path(__file__).parent / "images"
BASELINE = 12
ARGS = [
    "--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
    "--disable-component-update", "--disable-sync", "--no-first-run",
]  # fmt: skip


def _port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _get(url: str) -> object:
    with urllib.request.urlopen(url, timeout=30) as resp:
        return json.loads(resp.read())


def main() -> None:
    browser_path = shutil.which("chromium")
    if browser_path is None:
        sys.exit("needs chromium: apt-get install chromium")
    work = Path(tempfile.mkdtemp(prefix="screens-"))
    text = (ROOT / "configs" / "line.toml").read_text()
    text = text.replace('parts_dir = "parts"', f'parts_dir = "{ROOT / "configs" / "parts"}"')
    text = text.replace("trigger_period_s = 2.0", "trigger_period_s = 3.0")
    text = text.replace('# drift_point = "centre" ', 'drift_point = "centre" ')
    text = text.replace("drift_after_seq = 120 ", f"drift_after_seq = {BASELINE + 2} ")
    text = text.replace("drift_mm_per_part = 0.02 ", "drift_mm_per_part = 0.03 ")
    text = text.replace("baseline_parts = 100 ", f"baseline_parts = {BASELINE} ")
    config = ROOT / "configs" / ".screens-line.toml"  # beside the parts it names
    config.write_text(text)
    http_port, zenoh_port = _port(), _port()
    run = subprocess.Popen(
        [sys.executable, "-m", "service.cli", "run", "--config", str(config), "--data-dir",
         str(work / "data"), "--http-port", str(http_port), "--zenoh-listen",
         f"tcp/127.0.0.1:{zenoh_port}"],
        cwd=ROOT, stdout=subprocess.PIPE, text=True,
        env={**os.environ, "OPENBLAS_NUM_THREADS": "1"},
    )  # fmt: skip
    base = f"http://127.0.0.1:{http_port}"
    try:
        assert run.stdout is not None
        for line in run.stdout:
            if line.strip().startswith("data:"):
                break
        deadline = time.monotonic() + 900
        alarm = None
        while alarm is None and time.monotonic() < deadline:
            found = [a for a in _get(f"{base}/v1/alarms") if a.get("feature") == "centre"]  # type: ignore[union-attr]
            alarm = found[-1] if found else None
            time.sleep(2)  # a part every 3 s: nothing to see sooner
        if alarm is None:
            sys.exit("no alarm within 15 minutes")
        with sync_playwright() as pw:
            browser = pw.chromium.launch(executable_path=browser_path, args=ARGS)
            page = browser.new_page(viewport={"width": 1280, "height": 860})
            page.goto(base + "/")
            page.wait_for_selector("#latest tr")
            page.screenshot(path=str(OUT / "board.png"))
            page.goto(f"{base}/ui/trends?part=demo-panel#centre")
            page.wait_for_selector("section.chart canvas")
            page.locator('section.chart[data-feature="centre"]').screenshot(
                path=str(OUT / "control_chart.png")
            )
            page.set_viewport_size({"width": 900, "height": 1270})
            page.goto(f"{base}/v1/inspections/{alarm['result_id']}/report.html")
            page.screenshot(path=str(OUT / "report.png"))
            browser.close()
    finally:
        run.send_signal(signal.SIGINT)
        run.wait(120)
        config.unlink(missing_ok=True)
        shutil.rmtree(work, ignore_errors=True)
    print(f"wrote {OUT / 'board.png'}, {OUT / 'control_chart.png'}, {OUT / 'report.png'}")


if __name__ == "__main__":
    main()
