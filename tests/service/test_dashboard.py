"""The dashboard in a real headless browser, with the line running and a process drifting.

One ``inspection run`` for the module (small images, one matching pass): the
simulator presses a dent into every part after the baseline at one
comparison point, a little deeper each time, so the control chart's 3-sigma
rule fires. Debian's chromium is driven through Playwright; every request the
pages make is checked to go to the service itself.

The README's pictures of the board and a report come from ``docs/screens.py``,
which runs the line at its full image size.
"""

from __future__ import annotations

import csv
import io
import shutil
import threading
from collections.abc import Callable, Iterator
from pathlib import Path
from urllib.parse import urlsplit

import pytest
import zenoh
from linekit import LINE, PART, client, free_port
from test_line import cli, get_json, line_file, stop

from inspection.rig import Rig
from service import bus
from service.models import Alarm, InspectionResult
from service.protocol import Keys

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
playwright_api = pytest.importorskip(
    "playwright.sync_api", reason="the dashboard's tests need Playwright: pip install playwright"
)
if CHROMIUM is None:
    pytest.skip(
        "the dashboard's tests need a chromium browser: apt-get install chromium "
        "(.ci/run installs it when run as root)",
        allow_module_level=True,
    )

SIZE = (640, 512)
PERIOD_S = 1.0
BASELINE = 8
DRIFT_POINT = "centre"
LAUNCH_ARGS = [
    "--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
    "--disable-component-update", "--disable-sync", "--no-first-run",
]  # fmt: skip


class Bus:
    """What the line publishes, read from zenoh: results and alarms in arrival order."""

    def __init__(self, session: zenoh.Session, keys: Keys) -> None:
        self.results: list[InspectionResult] = []
        self.alarms: list[Alarm] = []
        self._arrived = threading.Condition()
        self._subs = [
            session.declare_subscriber(keys.results(), self._on(self.results, InspectionResult)),
            session.declare_subscriber(keys.alarms(), self._on(self.alarms, Alarm)),
        ]

    def _on(self, into: list, model: type) -> Callable[[zenoh.Sample], None]:
        def on_sample(sample: zenoh.Sample) -> None:
            item = model.model_validate_json(sample.payload.to_bytes())
            with self._arrived:
                into.append(item)
                self._arrived.notify_all()

        return on_sample

    def wait(self, cond: Callable[[], object], timeout_s: float, what: str) -> None:
        with self._arrived:
            if self._arrived.wait_for(cond, timeout_s):
                return
        pytest.fail(f"{what} did not happen within {timeout_s} s")

    def close(self) -> None:
        for s in self._subs:
            s.undeclare()


@pytest.fixture(scope="module")
def line(tmp_path_factory, trees) -> Iterator[dict]:
    tmp = tmp_path_factory.mktemp("dash")
    rig_file = tmp / "rig.toml"
    Rig.default().with_image_size(*SIZE).save(rig_file)
    config = line_file(tmp, trees, period_s=PERIOD_S, queue_size=8)
    text = config.read_text()
    for old, new in [
        ("[station]\n", f'[station]\nrig_calibration = "{rig_file}"\n'),
        ("guided_matching = true", "guided_matching = false"),
        ("defect_rate = 0.1 ", "defect_rate = 0.0 "),
        ('# drift_point = "centre" ', f'drift_point = "{DRIFT_POINT}" '),
        ("drift_after_seq = 120 ", f"drift_after_seq = {BASELINE + 1} "),
        ("drift_mm_per_part = 0.02 ", "drift_mm_per_part = 0.08 "),
        ("baseline_parts = 100 ", f"baseline_parts = {BASELINE} "),
    ]:
        assert old in text, old
        text = text.replace(old, new, 1)
    config.write_text(text)
    port, http_port = free_port(), free_port()
    run = cli("run", "--config", str(config), "--data-dir", str(tmp / "data"),
              "--http-port", str(http_port), "--zenoh-listen", f"tcp/127.0.0.1:{port}")  # fmt: skip
    session = None
    seen = None
    try:
        for out in run.stdout:
            if out.strip().startswith("data:"):
                break
        else:
            pytest.fail(f"the line did not start: {run.stderr.read()[-3000:]}")
        session = bus.open_session(client(port))
        seen = Bus(session, Keys(LINE))
        yield {"base": f"http://127.0.0.1:{http_port}", "bus": seen, "tmp": tmp}
    finally:
        if seen is not None:
            seen.close()
        if session is not None:
            session.close()
        code = stop(run)
    assert code == 0, run.stderr.read()[-3000:]


@pytest.fixture(scope="module")
def browser() -> Iterator[object]:
    with playwright_api.sync_playwright() as pw:
        b = pw.chromium.launch(executable_path=CHROMIUM, args=LAUNCH_ARGS)
        yield b
        b.close()


@pytest.fixture
def page(browser, line):
    """A fresh page whose every request must go to the service: others are refused and fail."""
    own = urlsplit(line["base"]).netloc
    foreign: list[str] = []
    context = browser.new_context(accept_downloads=True)

    def guard(route) -> None:
        url = route.request.url
        if urlsplit(url).scheme in ("data", "blob") or urlsplit(url).netloc == own:
            route.continue_()
        else:
            foreign.append(url)
            route.abort()

    context.route("**/*", guard)
    p = context.new_page()
    errors: list[str] = []
    p.on("pageerror", lambda exc: errors.append(str(exc)))
    yield p
    context.close()
    assert foreign == [], f"requests to other hosts: {foreign}"
    assert errors == [], f"script errors: {errors}"


def expect(locator):
    # A page follows the line's results as they come; on a loaded machine the
    # browser's default of 5 s for each of them is too little.
    playwright_api.expect.set_options(timeout=20_000)
    return playwright_api.expect(locator)


def measured(line) -> InspectionResult:
    """The newest measured result the bus carried."""
    bus_ = line["bus"]
    bus_.wait(lambda: any(r.status.value in ("pass", "fail") for r in bus_.results), 180,
              "a measured part")  # fmt: skip
    return next(r for r in reversed(bus_.results) if r.status.value in ("pass", "fail"))


def test_board_shows_each_new_part_within_seconds(page, line):
    page.goto(line["base"] + "/")
    expect(page.locator("#live")).to_have_text("live", timeout=20_000)
    bus_ = line["bus"]
    before = len(bus_.results)
    bus_.wait(lambda: len(bus_.results) > before, 60, "a new result")
    new = bus_.results[before]
    row = page.locator(f'#latest tr[data-serial="{new.serial}"]')
    expect(row).to_be_visible(timeout=10_000)
    expect(row).to_contain_text(new.status.value)
    assert page.locator("#yield").inner_text().endswith("%")


def test_inspection_page_shows_its_map_and_comparison_table(page, line):
    r = measured(line)
    page.goto(f"{line['base']}/ui/inspections/{r.id}")
    expect(page.locator("#title")).to_contain_text(r.serial)
    img = page.locator("img.map")
    expect(img).to_be_visible(timeout=10_000)
    expect(img).to_have_attribute("data-loaded", "1")
    expect(page.locator("#points tr[data-point]")).to_have_count(len(r.comparison))
    expect(page.locator(f'#points tr[data-point="{DRIFT_POINT}"]')).to_be_visible()
    expect(page.locator("#trace")).to_contain_text(r.tree_hash or "")
    expect(page.locator("#rec")).to_contain_text(".mcap", timeout=10_000)


def test_search_finds_a_serial_and_downloads_its_csv(page, line):
    r = measured(line)
    page.goto(line["base"] + "/ui/search")
    page.fill("input[name=serial]", r.serial)
    page.click("button[type=submit]")
    expect(page.locator("#results tr")).to_have_count(1, timeout=10_000)
    expect(page.locator(f'#results tr[data-serial="{r.serial}"]')).to_be_visible()
    with page.expect_download() as dl:
        page.click("#csv")
    rows = list(csv.DictReader(io.StringIO(Path(dl.value.path()).read_text())))
    assert {row["serial"] for row in rows} == {r.serial}
    assert {row["point"] for row in rows} == {c.name for c in r.comparison}


def test_api_docs_load_offline(page, line):
    page.goto(line["base"] + "/docs")
    expect(page.locator(".swagger-ui .info .title")).to_contain_text("Inspection", timeout=20_000)
    page.goto(line["base"] + "/redoc")
    expect(page.locator("h1").first).to_contain_text("Inspection", timeout=20_000)


def test_drift_fires_the_rule_on_zenoh_rest_the_board_and_the_chart(page, line):
    bus_ = line["bus"]

    def drifted() -> list[Alarm]:
        return [a for a in bus_.alarms if a.kind.value == "spc_rule" and a.feature == DRIFT_POINT]

    bus_.wait(drifted, 240, f"an spc_rule alarm at {DRIFT_POINT} on zenoh")
    alarm = drifted()[0]
    assert alarm.rule == "nelson1" and alarm.part == PART and alarm.value < 0  # a dent
    assert alarm.seq is not None and alarm.seq > BASELINE  # not before the drift began
    code, listed = get_json(line["base"] + "/v1/alarms")
    assert code == 200 and alarm.id in {a["id"] for a in listed}

    page.goto(line["base"] + "/")
    box = page.locator(f'#alarms .alarm[data-id="{alarm.id}"]')
    expect(box).to_contain_text(DRIFT_POINT, timeout=10_000)
    page.on("dialog", lambda d: d.accept("QE Ann"))
    box.locator("button").click()
    expect(page.locator(f'#alarms .alarm.acked[data-id="{alarm.id}"]')).to_contain_text("QE Ann")
    code, acked = get_json(f"{line['base']}/v1/alarms/{alarm.id}")
    assert acked["acknowledged_by"].startswith("QE Ann") and acked["acknowledged_ns"] > 0

    page.goto(f"{line['base']}/ui/trends?part={PART}")
    chart = page.locator(f'section.chart[data-feature="{DRIFT_POINT}"]')
    expect(chart.locator("canvas").first).to_be_visible(timeout=20_000)
    expect(chart).to_contain_text("run rules hold at")
    expect(chart).to_contain_text("nelson1")
    expect(page.locator("section.chart")).to_have_count(len(measured(line).comparison) + 2)
