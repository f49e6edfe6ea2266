"""The docs site in a browser: headless Chromium opens the built site and finds the home
page, the API page and a guide rendered, their formulas typeset by the MathJax served with
the site (docs/mathjax_assets.py), and no error in the browser's console.

The site is ``site/`` when ``make docs`` built it after the last change to its sources (as
``.ci/run`` does), else a fresh ``mkdocs build --strict`` into a temporary folder. It is
served on 127.0.0.1, and Chromium resolves no other host name, so a page that needs the
network (a CDN, web fonts) fails here as it would offline. Outside CI a missing Chromium,
ChromeDriver or selenium skips this module with the reason; with ``CI`` set it fails
(``.ci/run`` installs Debian's ``chromium`` and ``chromium-driver``).
"""

from __future__ import annotations

import functools
import http.server
import os
import pathlib
import shutil
import subprocess
import sys
import threading

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
# Chromium's flags for a root user on a machine without a display or a network; the
# background services would try to reach Google's hosts at every start.
CHROMIUM_FLAGS = (
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-dev-shm-usage",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--window-size=1280,900",
    "--host-resolver-rules=MAP * ~NOTFOUND , EXCLUDE 127.0.0.1",
)
# (path in the site, what the page must show, least number of typeset formulas)
PAGES = {
    "home": ("", "Quick start", 0),
    "api": ("api/optax_bilateral/", "bilateral_adam", 5),
    "guide": ("method/", "The update (supplement eqs. 1–11)", 2),
}
# Inputs of the site: a built site/ older than any of them is rebuilt.
SOURCES = ("mkdocs.yml", "README.md", "CHANGELOG.md", "BENCHMARKS.md", "docs", "optax_bilateral")


def _unavailable() -> str | None:
    try:
        import selenium  # noqa: F401
    except ImportError:
        return "selenium is not installed: pip install -e '.[dev]'"
    missing = [b for b in ("chromium", "chromedriver") if shutil.which(b) is None]
    if missing:
        return f"{' and '.join(missing)} not found: apt-get install chromium chromium-driver"
    return None


REASON = _unavailable()
if REASON is not None and not os.environ.get("CI"):
    pytest.skip(REASON, allow_module_level=True)


def _newest_source() -> float:
    newest = 0.0
    for name in SOURCES:
        path = ROOT / name
        files = path.rglob("*") if path.is_dir() else [path]
        newest = max([newest, *(f.stat().st_mtime for f in files if f.is_file())])
    return newest


@pytest.fixture(scope="module")
def site(tmp_path_factory) -> pathlib.Path:
    built = ROOT / "site"
    index = built / "index.html"
    if index.exists() and index.stat().st_mtime > _newest_source():
        return built
    out = tmp_path_factory.mktemp("site")
    proc = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--quiet", "-d", str(out)],
        cwd=ROOT,
        env={**os.environ, "NO_MKDOCS_2_WARNING": "1"},
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    return out


@pytest.fixture(scope="module")
def base_url(site):
    handler = functools.partial(QuietHandler, directory=str(site))
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), handler)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    yield f"http://127.0.0.1:{server.server_address[1]}/"
    server.shutdown()
    server.server_close()


class QuietHandler(http.server.SimpleHTTPRequestHandler):
    def log_message(self, format, *args):  # the test reports what matters
        pass


@pytest.fixture(scope="module")
def browser(tmp_path_factory):
    if REASON is not None:
        pytest.fail(f"CI must run the browser test: {REASON}", pytrace=False)
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = shutil.which("chromium")
    for flag in CHROMIUM_FLAGS:
        options.add_argument(flag)
    options.add_argument(f"--user-data-dir={tmp_path_factory.mktemp('chromium')}")
    options.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    driver = webdriver.Chrome(service=Service(shutil.which("chromedriver")), options=options)
    driver.set_script_timeout(60)
    driver.set_page_load_timeout(60)
    yield driver
    driver.quit()


# Resolves once MathJax has typeset the page (or says why it cannot).
WAIT_FOR_MATHJAX = """
const done = arguments[arguments.length - 1];
if (!window.MathJax || !MathJax.startup || !MathJax.startup.promise) {
  done("MathJax did not load");
} else {
  MathJax.startup.promise.then(() => done("ok"), (e) => done("MathJax failed: " + e));
}
"""

PAGE_STATE = """
const formulas = Array.from(document.querySelectorAll(".arithmatex"));
return {
  title: document.querySelector("article h1") ? document.querySelector("article h1").innerText : "",
  text: document.querySelector("article") ? document.querySelector("article").innerText : "",
  nav: document.querySelectorAll(".md-nav__link").length,
  formulas: formulas.length,
  typeset: formulas.filter((f) => f.querySelector("mjx-container")).length,
  errors: document.querySelectorAll("mjx-merror").length,
  raw: formulas.filter((f) => /\\\\[([]/.test(f.innerText)).map((f) => f.innerText.slice(0, 80)),
  images: Array.from(document.images).filter((i) => !(i.complete && i.naturalWidth > 0))
    .map((i) => i.src),
  resources: performance.getEntriesByType("resource").map((e) => e.name),
};
"""


@pytest.mark.parametrize("page", PAGES)
def test_page_renders_with_typeset_formulas_and_no_console_error(page, browser, base_url):
    path, heading_or_text, least_formulas = PAGES[page]
    browser.get_log("browser")  # drop what earlier pages logged
    browser.get(base_url + path)
    assert browser.execute_async_script(WAIT_FOR_MATHJAX) == "ok"
    state = browser.execute_script(PAGE_STATE)
    assert state["title"], f"{page}: no heading rendered"
    assert heading_or_text in state["text"], f"{page}: {heading_or_text!r} not on the page"
    assert state["nav"] > 10, f"{page}: the navigation did not render"
    assert state["formulas"] >= least_formulas, state["formulas"]
    assert state["typeset"] == state["formulas"], f"{page}: raw TeX left: {state['raw']}"
    assert state["raw"] == [] and state["errors"] == 0, (state["raw"], state["errors"])
    assert state["images"] == [], f"{page}: images that did not load: {state['images']}"
    outside = [r for r in state["resources"] if not r.startswith(base_url)]
    assert outside == [], f"{page}: requests that leave the site: {outside}"
    errors = [e for e in browser.get_log("browser") if e["level"] == "SEVERE"]
    assert errors == [], f"{page}: console errors: {errors}"
