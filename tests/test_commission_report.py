"""The commissioning record a technician hands over: order, identity, units, values to program,
and the page as a real browser (Debian's chromium, headless) renders it.

One commissioning run on ``sim://`` serves every test here. Its drive reports
what a CiA 402 drive with a factor group reports (identity from 0x1018, scale
factors of per-mille torque, rpm and increments in its log metadata), so the
values to program come out in the drive's own units as well.
"""

from __future__ import annotations

import io
import json
import math
import re
import shutil
import subprocess
from html.parser import HTMLParser
from pathlib import Path

import pytest

import servobench.drivers.registry
from servobench.drivers.base import DriveInfo
from servobench.drivers.sim import SimDrive

#: A drive with a rated torque of 640 mN m (0x6076), velocity in rpm (0x60A9 = 0x00B44700)
#: and 131072 increments per revolution (0x608F): SI per drive unit, by CiA 402's definitions.
SCALE_U = 0.640 / 1000  # N m per mille of rated torque
SCALE_V = 2 * math.pi / 60  # rad/s per rpm
SCALE_X = 2 * math.pi / 131072  # rad per increment

CONFIG = """
[identity]
site = "Hall 3"
machine = "Press 7"
axis = "Z"
operator = "A. Technician"

[limits]
max_u = 5.0
max_v = 20.0
xmin = -inf
xmax = inf

[sidbe]
periods = 3
period_s = 1.0
"""


class FactorGroupSim(SimDrive):
    """The simulated drive, telling its identity and scale factors as a CiA 402 driver does."""

    def _info(self) -> DriveInfo:
        return DriveInfo(transport="canopen", vendor="0x0000029C", product="eDrive (product code 0x00000001)",
                         firmware="V2.13", serial_number="SN-4711", state="SWITCH ON DISABLED",
                         units=dict(self.units))  # fmt: skip

    def log_metadata(self) -> dict[str, str]:
        return {
            **super().log_metadata(),
            "scale_u": f"{SCALE_U:.12g}",
            "scale_u_source": "0x6076 rated torque 640 mN m, per mille",
            "scale_v": f"{SCALE_V:.12g}",
            "scale_v_source": "0x60A9 rpm (0x00B44700)",
            "scale_x": f"{SCALE_X:.12g}",
            "scale_x_source": "0x608F 131072 inc / 1 rev",
        }


@pytest.fixture(scope="module")
def record(tmp_path_factory) -> Path:
    from rich.console import Console as RichConsole

    from servobench.bench.commission.config import load_config
    from servobench.bench.commission.sequence import CommissionOptions, commission
    from servobench.bench.commission.ui import Console

    tmp = tmp_path_factory.mktemp("record")
    (tmp / "bench.toml").write_text(CONFIG)
    out = tmp / "rec"
    mp = pytest.MonkeyPatch()
    mp.setattr(servobench.drivers.registry, "open_drive", FactorGroupSim)
    try:
        options = CommissionOptions("sim://?pace=fast", load_config(tmp / "bench.toml"), out,
                                    assume_yes=True)  # fmt: skip
        result = commission(options, Console(RichConsole(file=io.StringIO(), width=200)))
    finally:
        mp.undo()
    assert result.status == "complete"
    return out


class _Text(HTMLParser):
    """Headings, table rows and figure captions of the page, in document order."""

    def __init__(self):
        super().__init__()
        self.items: list[tuple[str, str]] = []
        self._tag, self._buf, self._row = "", [], []

    def handle_starttag(self, tag, attrs):
        if tag in ("h1", "h2", "h3", "figcaption", "td", "th", "p", "div"):
            self._tag, self._buf = tag, []
        if tag == "tr":
            self._row = []

    def handle_data(self, data):
        if self._tag:
            self._buf.append(data)

    def handle_endtag(self, tag):
        if tag == self._tag:
            text = "".join(self._buf).strip()
            if tag in ("td", "th"):
                self._row.append(text)
            else:
                self.items.append((tag, text))
            self._tag = ""
        if tag == "tr":
            self.items.append(("tr", " | ".join(self._row)))

    def index(self, tag: str, text: str) -> int:
        return next(i for i, (t, x) in enumerate(self.items) if t == tag and x == text)

    def rows(self) -> dict[str, list[str]]:
        return {r.split(" | ")[0]: r.split(" | ")[1:] for t, r in self.items if t == "tr"}


def _page(record: Path) -> _Text:
    page = _Text()
    page.feed((record / "report.html").read_text())
    return page


def test_summary_then_values_to_program_then_evidence(record):
    page = _page(record)
    h1 = page.index("h1", "Commissioning record: Press 7 axis Z")
    verdict = next(i for i, (t, x) in enumerate(page.items) if t == "div" and x.startswith("PASS"))
    summary, program = page.index("h2", "Summary"), page.index("h2", "Values to program into the drive")
    evidence = page.index("h2", "Evidence")
    assert h1 < verdict < summary < program < evidence
    for heading in ("Drive and limits", "Bump test", "Excitation", "Velocities", "Frequency response",
                    "Friction-velocity map", "Diagnosis (before / after)",
                    "Friction compensation and velocity-loop PI"):  # fmt: skip
        assert page.index("h3", heading) > evidence
    steps = [x.split(" | ")[:2] for t, x in page.items[summary:program] if t == "tr"]
    assert [s for s, _ in steps[1:8]] == ["Link and drive", "Limits", "Bump test", "Identification (SIDBE)",
                                         "Diagnosis", "Velocity PI design", "Friction compensation (simulation)"]
    assert all(result == "PASS" for _, result in steps[1:8])


def test_identity_from_the_config_and_from_the_drive(record):
    rows = _page(record).rows()
    assert rows["site"] == ["Hall 3"] and rows["machine"] == ["Press 7"] and rows["axis"] == ["Z"]
    assert rows["operator"] == ["A. Technician"]
    assert rows["drive vendor"] == ["0x0000029C"] and rows["firmware"] == ["V2.13"]
    assert rows["serial number"] == ["SN-4711"]
    who = json.loads((record / "model.json").read_text())["identity"]
    assert who["operator"] == "A. Technician" and who["serial_number"] == "SN-4711"


def test_model_and_values_in_units_si_and_the_drives_own(record):
    model = json.loads((record / "model.json").read_text())
    assert model["units"]["M"] == "kg m^2" and model["units"]["coulomb_pos"] == "N m"
    rows = _page(record).rows()
    assert rows["M (inertia)"][1] == "kg m^2" and rows["B (viscous friction)"][1] == "N m s/rad"
    assert rows["Coulomb friction, v > 0"][1] == "N m"
    program = {p["name"]: p for p in model["program"]}
    ff = program["friction feed-forward, positive motion (Coulomb +)"]
    assert ff["value"] == pytest.approx(model["coulomb_pos"]) and ff["unit"] == "N m"
    # per mille of the 640 mN m rated torque: 0.5 N m is 781.25 per mille
    assert ff["drive_value"] == pytest.approx(model["coulomb_pos"] / 0.00064)
    assert model["coulomb_pos"] / 0.00064 == pytest.approx(781.25, rel=0.02)
    viscous = program["viscous feed-forward (B)"]
    # 1 N m s/rad = 0.10472 N m per rpm = 163.6 per mille per rpm
    assert viscous["drive_value"] == pytest.approx(model["B"] * (math.pi / 30) / 0.00064)
    kp = program["velocity PI: proportional gain Kp"]
    assert kp["value"] == pytest.approx(model["velocity_pi"]["kp"]) and kp["unit"] == "N m s/rad"
    assert program["velocity PI: integral gain Ki = Kp/Ti"]["unit"] == "N m/rad"
    assert program["velocity filter"]["note"].startswith("none: no resonance")
    page_rows = rows["friction feed-forward, positive motion (Coulomb +)"]
    assert page_rows[1] == "N m" and page_rows[3] == "drive u unit"
    assert float(page_rows[2]) == pytest.approx(ff["drive_value"], rel=1e-5)
    text = (record / "report.html").read_text()
    assert "1 drive u unit = 0.00064 N m (0x6076 rated torque 640 mN m, per mille)" in text
    assert "1 drive v unit = 0.10472 rad/s (0x60A9 rpm (0x00B44700))" in text


def test_no_engineering_dump_left(record):
    html = (record / "report.html").read_text()
    page = _page(record)
    captions = [x for t, x in page.items if t == "figcaption"]
    assert len(captions) >= 9
    assert all(len(c.split()) >= 6 and not c.endswith(".png") for c in captions)  # sentences, not file names
    assert html.count("auto: joint") + html.count("auto: sidbe") == 1  # the selection sentence once
    # my sections say units, never a bare "units" or "command units"
    mine = html.split('<h3>Diagnosis (before / after)</h3>')[0]
    assert not re.search(r"\[units|units/s|command unit", mine)
    excitation = next(x for t, x in page.items if t == "figcaption" and x.startswith("One excitation period"))
    assert "period 3 of 3" in excitation


#: Appended to a copy of the page: after load, write every image's decoded size into the DOM.
PROBE = (
    '<script>window.addEventListener("load",()=>{const p=document.createElement("pre");p.id="probe";'
    "p.textContent=JSON.stringify([...document.images].map(i=>[i.complete,i.naturalWidth,i.naturalHeight]));"
    "document.body.appendChild(p);});</script>"
)


def _browser_images(page: Path, profile: Path) -> list[list]:
    chromium = shutil.which("chromium")
    if chromium is None:
        pytest.fail("chromium is not installed: the test command installs it as root (tests/peers.py)")
    probe = page.with_name(page.stem + "-probe.html")
    probe.write_text(page.read_text().replace("</body>", PROBE + "</body>"))
    done = subprocess.run(
        [chromium, "--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
         "--disable-component-update", "--disable-sync", "--no-first-run", f"--user-data-dir={profile}",
         "--dump-dom", probe.as_uri()],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr[-2000:]
    found = re.search(r'<pre id="probe">(.*?)</pre>', done.stdout, re.S)
    assert found, "the page did not finish loading in chromium"
    return json.loads(found.group(1))


def test_the_page_loads_with_its_figures_in_a_real_browser(record, tmp_path):
    page = record / "report.html"
    n_img = page.read_text().count("<img ")
    images = _browser_images(page, tmp_path / "profile")
    assert len(images) == n_img >= 10
    assert all(complete and width > 300 and height > 200 for complete, width, height in images)
    # the probe can fail: a figure whose data is cut short does not decode
    broken = tmp_path / "broken.html"
    text = page.read_text()
    start = text.index("base64,") + len("base64,")
    broken.write_text(text[:start] + text[start + 400 :])
    assert _browser_images(broken, tmp_path / "profile")[0][1] == 0
