"""Headless Chromium for the tests of the live view (Debian's ``chromium`` and ``chromium-driver``).

Without them the browser tests are skipped with the reason, except in CI (``CI=true``), where
they must run: there a missing browser fails the test.
"""
from __future__ import annotations

import contextlib
import os
import shutil
import time

import pytest

CHROMIUM = ("/usr/bin/chromium", "chromium", "chromium-browser")
DRIVER = ("/usr/bin/chromedriver", "chromedriver")
INSTALL = "apt-get install -y chromium chromium-driver"

# The text of the page, through the shadow roots Bokeh renders its widgets in.
DEEP_TEXT = """
function walk(node) {
  let out = "";
  if (node.shadowRoot) out += walk(node.shadowRoot);
  for (const child of node.childNodes) {
    if (child.nodeType === Node.TEXT_NODE) out += child.textContent + " ";
    else if (child.nodeType === Node.ELEMENT_NODE && child.tagName !== "SCRIPT" && child.tagName !== "STYLE")
      out += walk(child);
  }
  return out;
}
return walk(document.body).replace(/\\s+/g, " ");
"""
# The texts of the elements with a class, looked for through the shadow roots, in page order.
CLASS_TEXTS = """
function find(node, cls, out) {
  if (node.classList && node.classList.contains(cls)) out.push(node.textContent);
  const kids = [...(node.shadowRoot ? node.shadowRoot.childNodes : []), ...node.childNodes];
  for (const child of kids) find(child, cls, out);
  return out;
}
return find(document.body, arguments[0], []);
"""


def _which(names) -> str | None:
    for name in names:
        path = shutil.which(name) if not os.path.isabs(name) else (name if os.path.exists(name) else None)
        if path:
            return path
    return None


def require_chromium() -> tuple[str, str]:
    """Paths of Chromium and its driver; skips (fails in CI) when they are missing."""
    browser, driver = _which(CHROMIUM), _which(DRIVER)
    if browser and driver:
        return browser, driver
    missing = "chromium" if not browser else "chromium-driver"
    reason = f"{missing} is not installed (Debian: {INSTALL})"
    if os.environ.get("CI", "").lower() in ("1", "true", "yes"):
        pytest.fail(f"CI must run the browser tests: {reason}")
    pytest.skip(reason)


@contextlib.contextmanager
def chromium(width: int = 1500, height: int = 1400):
    """A headless Chromium driven through Selenium; always quit at the end."""
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    browser, driver = require_chromium()
    options = webdriver.ChromeOptions()
    options.binary_location = browser
    for arg in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage", "--disable-gpu",
                f"--window-size={width},{height}", "--hide-scrollbars"):
        options.add_argument(arg)
    session = webdriver.Chrome(service=Service(executable_path=driver), options=options)
    try:
        session.set_page_load_timeout(30)
        yield session
    finally:
        session.quit()


def text(driver) -> str:
    """Everything the page shows as text."""
    return driver.execute_script(DEEP_TEXT)


def class_texts(driver, cls: str) -> list[str]:
    """The texts of the elements of class ``cls``, in page order."""
    return driver.execute_script(CLASS_TEXTS, cls) or []


def class_text(driver, cls: str) -> str | None:
    """The text of the first element of class ``cls`` (None if there is none)."""
    texts = class_texts(driver, cls)
    return texts[0] if texts else None


def model(driver, name: str, expr: str = "m"):
    """``expr`` evaluated on the Bokeh model called ``name`` in the page (m), e.g. ``m.data.J``."""
    return driver.execute_script(
        "const doc = (window.Bokeh && Bokeh.documents.length) ? Bokeh.documents[0] : null;"
        "if (!doc) return null; const m = doc.get_model_by_name(arguments[0]); if (!m) return null;"
        f"const v = {expr}; return (v && v.constructor && v.constructor.name.endsWith('Array')) ? Array.from(v) : v;",
        name)


def wait_until(predicate, timeout: float, interval: float = 0.1, what: str = "the page"):
    """The first true value of ``predicate()``; fails the test after ``timeout`` seconds."""
    deadline = time.monotonic() + timeout
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() > deadline:
            pytest.fail(f"{what}: not within {timeout} s")
        time.sleep(interval)
