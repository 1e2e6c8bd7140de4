"""The documentation site works opened from disk, with no network, in a real browser.

A robot's owner opens ``site/index.html`` from a folder: every link must name an ``.html`` file
(a link to a folder shows a directory listing from ``file://``), no page may load anything from
the internet (fonts, scripts, stylesheets), search must work without a server, and a table's
identifiers must not break mid-word. The site is built here with ``mkdocs build --strict`` and
opened with headless Chromium (the Debian package ``chromium``; ``make test`` installs it when
it runs as root), whose network is cut off: every host name fails to resolve.
"""

from __future__ import annotations

import html.parser
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path
from urllib.parse import unquote, urlsplit

import pytest
import yaml

from support import ROOT, scaled
from test_docs_examples import nav_pages

# The resources a page loads, as (tag, attribute); <a href> is a link, not a resource.
RESOURCES = {("script", "src"), ("img", "src"), ("iframe", "src"), ("source", "src")}
LOADED_LINKS = {"stylesheet", "preconnect", "preload", "modulepreload", "icon", "manifest"}


class Tags(html.parser.HTMLParser):
    """Every start tag of a page, with its attributes."""

    def __init__(self) -> None:
        super().__init__()
        self.tags: list[tuple[str, dict[str, str]]] = []

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        self.tags.append((tag, {name: value or "" for name, value in attrs}))


def tags(page: str) -> list[tuple[str, dict[str, str]]]:
    parser = Tags()
    parser.feed(page)
    return parser.tags


def is_external(url: str) -> bool:
    return urlsplit(url).scheme in {"http", "https"} or url.startswith("//")


def resources(page: str) -> list[str]:
    """The URLs of everything a page loads: scripts, stylesheets, fonts, images, frames."""
    found = []
    for tag, attrs in tags(page):
        if tag == "link" and LOADED_LINKS & set(attrs.get("rel", "").split()):
            found.append(attrs.get("href", ""))
        for name in (attribute for element, attribute in RESOURCES if element == tag):
            if name in attrs:
                found.append(attrs[name])
    found += re.findall(r"url\(\s*['\"]?([^'\")]+)", page)  # in style attributes and elements
    return found


def links(page: str) -> list[str]:
    """The ``<a href>`` targets of a page that stay on the site (not the web, not this page)."""
    return [
        attrs["href"]
        for tag, attrs in tags(page)
        if tag == "a"
        and "href" in attrs
        and not is_external(attrs["href"])
        and urlsplit(attrs["href"]).scheme not in {"mailto"}
        and not attrs["href"].startswith("#")
    ]


def target(page: Path, href: str) -> Path:
    return (page.parent / unquote(urlsplit(href).path)).resolve()


@pytest.fixture(scope="module")
def site(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The site, built as ``make docs`` builds it."""
    folder = tmp_path_factory.mktemp("site")
    result = subprocess.run(
        [sys.executable, "-m", "mkdocs", "build", "--strict", "--quiet", "--site-dir", folder],
        cwd=ROOT,
        env={**os.environ, "NO_MKDOCS_2_WARNING": "1"},
        capture_output=True,
        text=True,
        timeout=scaled(120),
        check=False,
    )
    assert result.returncode == 0, result.stderr
    return folder


def chromium_binary() -> str:
    """Return the Chromium to run, or fail saying how to install it."""
    for name in ("chromium", "chromium-browser"):
        if found := shutil.which(name):
            return found
    pytest.fail(
        "Chromium is not installed: tests/test_docs_site.py opens the docs site in headless "
        "Chromium. Install the Debian package (apt-get install chromium), or run `make test` "
        "as root, which installs it.",
        pytrace=False,
    )


def chromium(url: str, *args: str) -> str:
    """Open ``url`` in headless Chromium without network; return what it prints (the DOM)."""
    with tempfile.TemporaryDirectory(prefix="srvwire-chromium-") as profile:
        result = subprocess.run(
            [
                chromium_binary(),
                "--headless",
                "--no-sandbox",
                "--disable-gpu",
                "--disable-quic",
                "--no-first-run",
                "--disable-background-networking",
                "--disable-component-update",
                "--disable-sync",
                "--disable-dev-shm-usage",  # a container's /dev/shm is often too small
                "--host-resolver-rules=MAP * ~NOTFOUND",  # no host name resolves: offline
                f"--user-data-dir={profile}",
                "--window-size=1280,900",
                "--virtual-time-budget=10000",  # run the page's scripts until they are idle
                *args,
                url,
            ],
            capture_output=True,
            text=True,
            timeout=scaled(60),
            check=False,
        )
    assert result.returncode == 0, result.stderr[-2000:]
    return result.stdout


def rendered(page: Path, query: str = "") -> str:
    """The DOM of a page opened from disk, after its scripts ran."""
    dom = chromium(page.as_uri() + query, "--dump-dom")
    assert "</html>" in dom, dom[-2000:]
    return dom


def pages(site: Path) -> list[Path]:
    """Every page of the site but 404.html, which only a web server shows (its links start with
    ``/``, the root of that server)."""
    found = sorted(set(site.rglob("*.html")) - {site / "404.html"})
    assert len(found) > 10
    return found


# --- what every built page says -------------------------------------------------------------


def test_every_link_names_an_html_file_that_exists(site: Path) -> None:
    broken = [
        f"{page.relative_to(site)}: {href}"
        for page in pages(site)
        for href in links(page.read_text(encoding="utf-8"))
        if not target(page, href).is_file()  # a folder would show a directory listing
    ]
    assert broken == []


def test_no_page_loads_anything_from_the_internet(site: Path) -> None:
    external = [
        f"{path.relative_to(site)}: {url}"
        for path in [*pages(site), *site.rglob("*.css")]
        for url in resources(path.read_text(encoding="utf-8"))
        if is_external(url)
    ]
    assert external == []


def test_the_resource_scanner_sees_fonts_and_scripts() -> None:
    page = (
        '<link rel="preconnect" href="https://fonts.gstatic.com">'
        '<link rel="stylesheet" href="https://fonts.googleapis.com/css?family=Roboto">'
        '<script src="https://unpkg.com/iframe-worker/shim"></script>'
        '<a href="https://example.org/">a link, not a resource</a>'
        "<style>@font-face { src: url('https://example.org/font.woff2') }</style>"
    )
    assert [url for url in resources(page) if is_external(url)] == [
        "https://fonts.gstatic.com",
        "https://fonts.googleapis.com/css?family=Roboto",
        "https://unpkg.com/iframe-worker/shim",
        "https://example.org/font.woff2",
    ]
    assert links('<a href="tutorial.html#x">t</a><a href="#top">t</a>') == ["tutorial.html#x"]


# --- the site opened from disk in Chromium ---------------------------------------------------


@pytest.fixture(scope="module")
def index(site: Path) -> str:
    """The index page's DOM, opened from disk with a search query (``?q=``), which the theme
    runs once it has loaded its search index."""
    return rendered(site / "index.html", "?q=deadline")


def test_the_index_opened_from_disk_reaches_every_page(site: Path, index: str) -> None:
    assert "md-nav" in index  # the theme's navigation, after its scripts ran
    assert [url for url in resources(index) if is_external(url)] == []
    hrefs = links(index)
    assert [href for href in hrefs if not target(site / "index.html", href).is_file()] == []
    reached = {target(site / "index.html", href) for href in hrefs}
    nav = yaml.safe_load((ROOT / "mkdocs.yml").read_text(encoding="utf-8"))["nav"]
    listed = list(nav_pages(nav))
    missing = [page for page in listed if (site / page).with_suffix(".html") not in reached]
    assert missing == []


def test_search_works_from_disk(site: Path, index: str) -> None:
    # From file:// search takes the offline plugin's search_index.js, and
    # docs/javascripts/iframe-worker.js, since a page opened from disk may not start a Worker.
    meta = re.search(r'class="md-search-result__meta">([^<]*)<', index)
    assert meta is not None, "no search results in the page"
    count = re.fullmatch(r"(\d+) matching documents?", meta.group(1))
    assert count is not None and int(count.group(1)) >= 3, meta.group(1)
    results = re.findall(r'<a href="([^"]+)" class="md-search-result__link"', index)
    assert results
    assert [href for href in results if not target(site / "index.html", href).is_file()] == []


# A page beside the site's pages that opens each of them in a frame 1280 pixels wide and lists,
# once all have loaded, the inline code of their tables that the browser laid out on more than one
# line although it holds no space: an identifier broken mid-word. It reads the frames' documents,
# which a page opened from disk may do only with --allow-file-access-from-files.
PROBE = """<!doctype html>
<html><body><script>
const pages = PAGES;
const broken = {};
let left = pages.length;
for (const name of pages) {
  const frame = document.createElement("iframe");
  frame.style.width = "1280px";
  frame.style.height = "900px";
  frame.onload = () => {
    broken[name] = [...frame.contentDocument.querySelectorAll(".md-typeset table code")]
      .filter((code) => !/\\s/.test(code.textContent) && code.getClientRects().length > 1)
      .map((code) => code.textContent);
    if (--left === 0) {
      document.body.setAttribute("data-broken", JSON.stringify(broken));
    }
  };
  frame.src = name;
  document.body.appendChild(frame);
}
</script></body></html>
"""


def test_identifiers_in_tables_stay_whole_at_1280_pixels(site: Path) -> None:
    names = [page.relative_to(site).as_posix() for page in pages(site)]
    probe = site / "srvwire-probe.html"
    probe.write_text(PROBE.replace("PAGES", json.dumps(names)), encoding="utf-8")
    try:
        dom = chromium(probe.as_uri(), "--allow-file-access-from-files", "--dump-dom")
    finally:
        probe.unlink()
    match = re.search(r'data-broken="([^"]*)"', dom)
    assert match is not None, "the probe did not finish"
    broken = json.loads(html.unescape(match.group(1)))
    assert sorted(broken) == sorted(names)
    assert {name: codes for name, codes in broken.items() if codes} == {}
