"""The live view in a real headless Chromium: its script fetches the state and the frame and fills the page.

The evaluation that feeds the view is real (in-process World, rendered frames). Chromium runs the page's
JavaScript (``--virtual-time-budget`` lets its polling timers run); the test reads back the DOM it built
and the screenshot it took. Set ``SWIMM_LIVE_VIEW_SCREENSHOT=docs/live_view.png`` to keep the screenshot
(that is how the one in docs/ was made). Skipped where no Chromium is installed (.ci/run installs it via apt).
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess

import matplotlib.image
import pytest

from eval_service.engine import EvaluationSettings, evaluate
from eval_service.live import LiveFeed, LiveView

pytestmark = pytest.mark.slow

CHROMIUM = next((path for name in ("chromium", "chromium-browser", "google-chrome") if (path := shutil.which(name))),
                None)  # fmt: skip
WINDOW = (980, 520)
CAMERA_BOX = (60, 400, 30, 390)  # rows, then columns, inside the 384x384 camera image at the page's top left


def chromium(url: str, *args: str) -> subprocess.CompletedProcess:
    command = [CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars",
               f"--window-size={WINDOW[0]},{WINDOW[1]}", "--virtual-time-budget=5000", *args, url]  # fmt: skip
    return subprocess.run(command, capture_output=True, text=True, timeout=120, check=True)


def cell(dom: str, ident: str) -> str:
    match = re.search(rf'<td id="{ident}">(.*?)</td>', dom)
    assert match, f"no cell {ident} in the page"
    return re.sub(r"<[^>]+>", "", match.group(1))


@pytest.mark.skipif(CHROMIUM is None, reason="no Chromium here (apt-get install chromium)")
def test_live_view_in_headless_chromium(tmp_path) -> None:
    feed = LiveFeed()
    given = EvaluationSettings(backend="inprocess", obs="state", episodes=1, steps=150, seed=113, progress_bar=False,
                               figures=False)  # fmt: skip
    with LiveView(feed) as view:
        evaluate(given, tmp_path / "eval", feed=feed)
        (source,) = feed.sources()
        state = feed.state(source)
        dom = chromium(view.url, "--dump-dom").stdout
        shot = tmp_path / "live_view.png"
        chromium(view.url, f"--screenshot={shot}")

    step, episode = state["step"], state["episode"]
    assert cell(dom, "where") == f"scripted / 1 / {given.steps}"
    assert cell(dom, "geometry") == f"{step['d']:.2f} / {step['theta']:.1f}"
    for name in ("A", "D", "S_D", "S_A"):  # JavaScript's toExponential(2): three significant digits
        assert float(cell(dom, f"m-{name}")) == pytest.approx(episode[name], rel=6e-3), name
    assert cell(dom, "flags") == " / ".join("yes" if episode[f] else "no" for f in
                                            ("left_view", "distance_exceeded", "collided"))  # fmt: skip
    assert f"frame {given.steps} of {source}" in dom

    pixels = matplotlib.image.imread(shot)
    assert pixels.shape[:2] == (WINDOW[1], WINDOW[0])
    top, bottom, left, right = CAMERA_BOX
    camera = pixels[top:bottom, left:right, :3]
    assert camera.std() > 0.02, "the camera frame did not load into the page"
    if target := os.environ.get("SWIMM_LIVE_VIEW_SCREENSHOT"):
        shutil.copyfile(shot, target)
