"""The review page: one static HTML file with a row per take, its flags and relative links that
resolve, nothing fetched from the network; checked with html.parser, and in headless Chromium
(skipped where Debian's `chromium` is not installed)."""

from __future__ import annotations

import shutil
import subprocess
from html.parser import HTMLParser
from pathlib import Path
from urllib.parse import unquote

import pytest
from click.testing import CliRunner

import dualhuman_builder.cli.quality  # noqa: F401  (registers `gates` and `review`)
from dualhuman_builder.cli import main
from dualhuman_builder.quality.gates import check_take
from dualhuman_builder.quality.review import write_review
from quality_ws import qws  # noqa: F401  (a fixture)


class _Page(HTMLParser):
    """Rows of the takes table (their attributes), links per row, and every external reference."""

    def __init__(self):
        super().__init__()
        self.rows: list[dict] = []
        self.links: dict[str, list[tuple[str, str]]] = {}
        self.external: list[str] = []
        self.tags: set[str] = set()
        self._row = None
        self._a = None

    def handle_starttag(self, tag, attrs):
        a = dict(attrs)
        self.tags.add(tag)
        for key in ("src", "href"):
            if key in a and ("//" in (a[key] or "") or tag in ("link", "img", "iframe")):
                self.external.append(a[key])
        if tag == "script" and "src" in a:
            self.external.append(a["src"])
        if tag == "tr" and "data-take" in a:
            self._row = a["data-take"]
            self.rows.append(a)
            self.links[self._row] = []
        if tag == "a" and self._row is not None:
            self.links[self._row].append((a.get("data-kind"), a["href"]))

    def handle_endtag(self, tag):
        if tag == "tr":
            self._row = None


def _parse(text: str) -> _Page:
    p = _Page()
    p.feed(text)
    return p


def _page(ws, tmp_path) -> Path:
    check_take(ws, "BAD")
    check_take(ws, "GOOD")  # RAW is never checked
    (tmp_path / "pages").mkdir(exist_ok=True)
    return write_review(ws, tmp_path / "pages" / "review.html")


def test_the_page_lists_every_take_with_flags_and_links_that_resolve(qws, tmp_path):
    qws.add_take("x<i>&y", actors=["alice", "bob"])  # a name with markup in it is shown as text
    path = _page(qws, tmp_path)
    text = path.read_text(encoding="utf-8")
    page = _parse(text)
    assert [r["data-take"] for r in page.rows] == ["BAD", "GOOD", "RAW", "x<i>&y"]
    assert "<i>" not in text and "x&lt;i&gt;&amp;y" in text
    verdicts = {r["data-take"]: (r["data-verdict"], r["data-gates"]) for r in page.rows}
    assert verdicts == {"BAD": ("flagged", "penetration tracker_loss"), "GOOD": ("clean", ""), "RAW": ("unchecked", ""),
                        "x<i>&y": ("unchecked", "")}
    assert "the bodies overlap by up to 14.0 mm" in text and "1 flagged" in text and "2 not checked" in text
    # relative links to what exists: the fit has no report here, the render's views folder is there
    assert {k for k, _ in page.links["BAD"]} == {"renders"} and page.links["RAW"] == []
    for take, links in page.links.items():
        for _, href in links:
            assert not href.startswith(("/", "file:")) and (path.parent / unquote(href)).exists(), (take, href)
    # self-contained: no external script, stylesheet, image or frame; the script and style are inline
    assert page.external == [] and {"script", "style", "table"} <= page.tags
    # the default place is the workspace folder
    assert write_review(qws) == qws.root / "review.html"


def test_review_command_writes_the_page_read_only(qws, tmp_path):
    res = CliRunner().invoke(main, ["review", str(qws.root), "--out", str(tmp_path / "r.html")])
    assert res.exit_code == 0, res.output
    assert (tmp_path / "r.html").is_file() and len(_parse((tmp_path / "r.html").read_text()).rows) == 3
    res = CliRunner().invoke(main, ["review", str(qws.root), "--out", str(tmp_path / "no" / "such" / "r.html")])
    assert res.exit_code == 2 and "folder does not exist" in res.output


def test_a_fit_report_and_contact_sheet_are_linked_where_they_exist(qws, tmp_path):
    def fit(out):
        from quality_ws import _bodies

        from dualhuman_builder.body.model import get_body_model

        _bodies(out, get_body_model())
        out.path("report.html").write_text("<html>fit report</html>")
        return {"frames": 12, "max_penetration_after_mm": 0.5, "penetrating_share_after": 0.0}

    qws.add_take("REPORTED", actors=["alice", "bob"])
    qws.run_stage("fit", fit, take="REPORTED")
    qws.run_stage("sheet", lambda out: out.path("contact_sheet.png").write_bytes(b"png") and {}, take="REPORTED",
                  depends_on=[("fit", None)])  # fmt: skip
    path = _page(qws, tmp_path)
    links = dict(_parse(path.read_text()).links["REPORTED"])
    assert links == {"fit report": "../ws/artifacts/REPORTED/_take/fit/report.html",
                     "contact sheet": "../ws/artifacts/REPORTED/_take/sheet/contact_sheet.png"}


@pytest.mark.skipif(shutil.which("chromium") is None, reason="Debian's chromium is not installed")
def test_the_page_opens_in_headless_chromium(qws, tmp_path):
    path = _page(qws, tmp_path)
    profile = tmp_path / "chromium-profile"
    cmd = ["chromium", "--headless", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage", "--no-first-run",
           f"--user-data-dir={profile}", "--virtual-time-budget=2000", "--dump-dom", path.resolve().as_uri()]  # fmt: skip
    res = subprocess.run(cmd, check=False, capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr[-2000:]
    page = _parse(res.stdout)
    assert [r["data-take"] for r in page.rows] == ["BAD", "GOOD", "RAW"], res.stdout[:2000]
    assert {k for k, _ in page.links["BAD"]} == {"renders"}
    # the page's script ran in the browser: it counted the rows it shows
    assert '<b id="shown">3</b>' in res.stdout
