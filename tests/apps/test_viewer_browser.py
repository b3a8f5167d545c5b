"""In a real browser (headless Chromium): the served page and the exported page (opened from its file) both draw
the splat where and as tacsplat's rasterizer does, over a clean background (not a blank or an error page)."""

from __future__ import annotations

import os
import shutil
import sys
from pathlib import Path

import pytest

from tacsplat.cli import main

sys.path.insert(0, str(Path(__file__).parent))  # pytest's importlib mode does not add test folders
from viewer_browser import browser_missing, expected_view, headless_chromium, wait_for_object, write_splat_run  # noqa: E402
from viewer_client import served  # noqa: E402

pytestmark = [pytest.mark.browser, pytest.mark.skipif(browser_missing() is not None, reason=str(browser_missing()))]


@pytest.fixture(scope="module")
def splat_run(tmp_path_factory):
    return write_splat_run(tmp_path_factory.mktemp("browser") / "run", 3000)


def _keep(picture, tmp_path: Path, name: str) -> None:
    """Save the screenshot beside the test's files, and in $TACSPLAT_SCREENSHOTS when it is set."""
    from PIL import Image

    Image.fromarray(picture).save(tmp_path / name)
    if os.environ.get("TACSPLAT_SCREENSHOTS"):
        shutil.copy(tmp_path / name, Path(os.environ["TACSPLAT_SCREENSHOTS"]) / name)


def test_the_served_page_draws_the_splat(splat_run, tmp_path):
    expected, mask = expected_view(splat_run)
    with served(splat_run) as url, headless_chromium() as page:
        seconds, picture = wait_for_object(page, url, expected, mask)
        title, text = page.evaluate("document.title"), page.evaluate("document.body.innerText")
    _keep(picture, tmp_path, "viewer-served.png")
    assert seconds is not None, f"the splat never covered its pixels in its colours; screenshot in {tmp_path}"
    assert title == "Viser" and "Connected" in text and "mismatch" not in text.lower()


def test_the_exported_page_draws_the_splat_without_python(splat_run, tmp_path):
    page = tmp_path / "view.html"
    assert main(["view", str(splat_run), "--export", str(page), "--quiet"]) == 0
    with headless_chromium() as browser:
        seconds, picture = wait_for_object(browser, page.resolve().as_uri(), *expected_view(splat_run))
    _keep(picture, tmp_path, "viewer-exported.png")
    assert seconds is not None, f"the exported page never drew the splat; screenshot in {tmp_path}"
