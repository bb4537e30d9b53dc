"""report.html in a real browser: headless Chromium (Debian's `chromium` package) opens a small
league's report and a training run's, every <img> must have loaded (its naturalWidth, read by
a script once the page has loaded), and a screenshot of the page must show the figures (the
pixels of a member's colour). Skipped where no Chromium is on PATH, as in CI; `make
report-check` runs it, refuses to skip, and keeps the pages and screenshots under
runs/report-check/."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
from conftest import create_league, quiet_schedule, write_league
from test_report import full_run

BROWSERS = ("chromium", "chromium-browser", "google-chrome")
CHROMIUM = next((found for name in BROWSERS if (found := shutil.which(name))), None)

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(
        CHROMIUM is None,
        reason="no chromium on PATH (Debian: apt-get install chromium), so report.html is not "
        "rendered; `make report-check` needs one",
    ),
]

WINDOW = (1280, 7000)  # pixels: wide as a laptop screen, tall enough for the first figures
# Once the page has loaded, each <img>'s src and natural width (0: it did not load) as JSON.
PROBE = """<script>
window.addEventListener("load", () => {
  const found = Array.from(document.images,
    (image) => ({src: image.getAttribute("src"), width: image.naturalWidth}));
  const out = document.createElement("pre");
  out.id = "image-check";
  out.textContent = JSON.stringify(found);
  document.body.appendChild(out);
});
</script>"""


def chromium(page: Path, *options: str) -> str:
    """Run headless Chromium on `page` with `options`; its standard output."""
    profile = page.parent / ".chromium-profile"  # not the user's: nothing shared or locked
    command = [
        CHROMIUM,
        "--headless",
        "--no-sandbox",
        "--disable-gpu",
        "--hide-scrollbars",
        f"--user-data-dir={profile}",
        *options,
        page.resolve().as_uri(),
    ]
    done = subprocess.run(command, capture_output=True, text=True, timeout=120, check=False)
    shutil.rmtree(profile, ignore_errors=True)
    assert done.returncode == 0, done.stderr[-2000:]
    return done.stdout


def loaded_images(page: Path) -> dict[str, int]:
    """Each <img> of `page` (its src) and its natural width once Chromium has loaded it,
    read from a copy of the page beside it (the same relative links) with PROBE added."""
    probe = page.with_name(f"{page.stem}-probe.html")
    probe.write_text(page.read_text().replace("</body>", f"{PROBE}</body>"))
    dom = chromium(probe, "--dump-dom")
    probe.unlink()
    found = re.search(r'<pre id="image-check">(.*?)</pre>', dom, re.S)
    assert found, "the probe did not run: the page never finished loading"
    return {
        image["src"]: image["width"] for image in json.loads(found.group(1).replace("&quot;", '"'))
    }


def screenshot(page: Path) -> np.ndarray:
    """`page` rendered at WINDOW into <page>.png beside it, as RGB values in [0, 1]."""
    from matplotlib.image import imread

    shot = page.with_suffix(".png")
    chromium(page, f"--window-size={WINDOW[0]},{WINDOW[1]}", f"--screenshot={shot}")
    return imread(shot)[..., :3]


def pixels_of(image: np.ndarray, colour: str) -> int:
    from matplotlib.colors import to_rgb

    return int(np.sum(np.all(np.abs(image - np.array(to_rgb(colour))) < 0.02, axis=-1)))


def check(page: Path, colour: str) -> None:
    """Every figure of `page` loaded in the browser, and its screenshot shows them."""
    sources = re.findall(r'<img src="([^"]+)"', page.read_text())
    images = loaded_images(page)
    assert sources and sorted(images) == sorted(sources)
    unloaded = [src for src, width in images.items() if width <= 0]
    assert not unloaded, f"{page}: figures that did not load: {unloaded}"
    image = screenshot(page)
    assert image.shape[:2] == (WINDOW[1], WINDOW[0])
    assert np.mean(np.all(image > 0.97, axis=-1)) < 0.97  # not a blank page
    assert pixels_of(image, colour) > 500, f"no figure in {colour} on the screenshot of {page}"


def test_the_probe_sees_an_image_that_did_not_load(tmp_path: Path) -> None:
    """The check can fail: a page whose image is missing reports a natural width of 0."""
    page = tmp_path / "broken.html"
    page.write_text('<!DOCTYPE html><html><body><img src="missing.png" alt="x"></body></html>')
    assert loaded_images(page) == {"missing.png": 0}


def test_a_league_report_renders_with_every_figure(tmp_path: Path) -> None:
    from alignrl.league.loop import leaderboard
    from alignrl.league.report import write_league_report
    from alignrl.league.report_data import read_league_run
    from alignrl.league.report_figures import member_colours

    schedule = quiet_schedule(iterations=4, matches=4, snapshot_every=2, evaluate_every=2)
    league = create_league(write_league(tmp_path, schedule=schedule), tmp_path / "runs")
    league.run(progress=False)
    league.test()
    write_league_report(league.run_dir, leaderboard(league))
    champion = json.loads((league.run_dir / "test.json").read_text())["chosen_by"]["member"]
    colours = member_colours(read_league_run(league.run_dir).teams)
    check(league.run_dir / "report.html", colours[champion])


def test_a_training_report_renders_with_every_figure(tmp_path: Path) -> None:
    from alignrl.runs.report import write_run_report

    report = write_run_report(full_run(tmp_path))
    check(report.html, "#1f77b4")  # a training run's curves: matplotlib's first colour
