"""A headless Chromium driving the viewer (Selenium and Debian's chromium-driver): what the
browser test and the docs' screenshot use. `make test` installs the browser where it can
(scripts/ensure_browser.sh)."""

from __future__ import annotations

import shutil
import time
from pathlib import Path

BROWSERS = ("chromium", "chromium-browser", "google-chrome")


def find_browser() -> tuple[str, str] | None:
    """(browser, driver) executables, or None when either is missing."""
    browser = next((p for p in map(shutil.which, BROWSERS) if p), None)
    driver = shutil.which("chromedriver")
    return (browser, driver) if browser and driver else None


def missing_browser_reason() -> str | None:
    """Why no browser test can run here, or None when one can."""
    try:
        import selenium  # noqa: F401
    except ImportError:
        return "selenium is not installed (pip install -e '.[dev]')"
    if find_browser() is None:
        return (
            "no chromium and chromedriver on PATH (Debian: apt-get install chromium "
            "chromium-driver; `make test` tries scripts/ensure_browser.sh)"
        )
    return None


def open_browser(url: str, width: int = 1000, height: int = 700):
    """A headless Chromium at `url` with software WebGL (the splats draw without a GPU);
    the caller quits it."""
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    found = find_browser()
    if found is None:
        raise RuntimeError(missing_browser_reason())
    browser, driver = found
    options = webdriver.ChromeOptions()
    options.binary_location = browser
    for flag in (
        "--headless=new",
        "--no-sandbox",
        "--disable-dev-shm-usage",
        "--use-gl=angle",
        "--use-angle=swiftshader",
        "--enable-unsafe-swiftshader",
        "--ignore-gpu-blocklist",
        f"--window-size={width},{height}",
    ):
        options.add_argument(flag)
    options.set_capability("goog:loggingPrefs", {"browser": "ALL"})  # for console_errors
    chrome = webdriver.Chrome(service=Service(driver), options=options)
    chrome.get(url)
    return chrome


# viser's own splat mesh (viser/client/src/Splatting/GaussianSplatsHelpers.ts) gives its quad a
# two-component "position" attribute; three.js reads three for a bounding sphere and logs this on
# every page that draws splats, whatever they are (random finite splats in a bare viser server
# give it too). It is not an error in the data sent; with a NaN sphere the frustum test never
# culls the mesh (every comparison with NaN is false), so the splats always draw.
VISER_OWN = ("computeBoundingSphere(): Computed radius is NaN",)


def console_errors(chrome) -> list[str]:
    """The page's console errors (SEVERE) since the last call, but viser's own (VISER_OWN)."""
    return [
        e["message"]
        for e in chrome.get_log("browser")
        if e["level"] == "SEVERE" and not any(known in e["message"] for known in VISER_OWN)
    ]


def wait_for(condition, timeout: float, what: str, step: float = 0.1):
    """Poll `condition()` until it is truthy (returned) or `timeout` seconds pass."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        value = condition()
        if value:
            return value
        time.sleep(step)
    raise TimeoutError(f"waited {timeout:.0f} s for {what}")


def canvas(chrome):
    """The WebGL canvas the scene is drawn on (the largest canvas of the page)."""
    from selenium.webdriver.common.by import By

    found = chrome.find_elements(By.TAG_NAME, "canvas")
    return max(found, key=lambda c: c.size["width"] * c.size["height"]) if found else None


def click_canvas(chrome, fx: float = 0.5, fy: float = 0.5, shift: bool = False) -> None:
    """A click at the fraction (fx, fy) of the canvas (shift held: a negative click)."""
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.common.keys import Keys

    element = canvas(chrome)
    w, h = element.size["width"], element.size["height"]
    actions = ActionChains(chrome).move_to_element_with_offset(
        element, int((fx - 0.5) * w), int((fy - 0.5) * h)
    )
    held = actions.key_down(Keys.SHIFT).click().key_up(Keys.SHIFT) if shift else None
    (held or actions.click()).perform()


def click_button(chrome, text: str) -> None:
    """Click the GUI button labelled `text`."""
    from selenium.webdriver.common.by import By

    buttons = [b for b in chrome.find_elements(By.TAG_NAME, "button") if b.text.strip() == text]
    if not buttons:
        raise LookupError(f"no button {text!r} on the page")
    buttons[0].click()


def screenshot(chrome, path: Path) -> Path:
    """The page as a PNG at `path`."""
    path.parent.mkdir(parents=True, exist_ok=True)
    chrome.save_screenshot(str(path))
    return path
