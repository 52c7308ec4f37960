"""The verdict page (judged in reports/verdict.py, written by reports/verdict_page.py): the writer on small synthetic inputs,
and the HTML page in headless Chromium.

The browser test drives Chromium over the Chrome DevTools Protocol on a pipe
(``--remote-debugging-pipe``: NUL-separated JSON on file descriptors 3 and 4, no port and
no websocket library), presses a key and clicks a tab, and checks that the canvas changed,
that the page decoded the embedded linear data as numpy does, and that a screenshot is not
blank. It is skipped, saying so, where no Chromium or Chrome binary is found
(``scripts/setup-browser.sh`` installs one).
"""

from __future__ import annotations

import base64
import fcntl
import io
import json
import os
import queue
import shutil
import subprocess
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from kdtrace.imageio import png_bytes, rgbe_decode, rgbe_encode
from reports import verdict, verdict_page
from reports.figures import lit_fraction, safe_stem, strip_view
from reports.verdict import Strip, StripImage

HOSTILE = "<script>x</script>&\"'"
#: Binaries tried for the browser test, in order.
BROWSERS = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable", "chrome")


def synthetic_strip(scene: str = "cbox", label: str = "ours", height: int = 24, width: int = 32) -> Strip:
    """A scored strip of small made-up images: a lit gradient reference, a noisy copy, a blurred one, a tinted one."""
    rng = np.random.default_rng(3)
    y, x = np.mgrid[0:height, 0:width] / max(height, width)
    reference = np.stack([0.2 + x, 0.1 + y, 0.3 + 0.5 * x * y], axis=2) * 2.0
    reference[height // 3:height // 2, width // 3:width // 2] = [6.0, 5.0, 4.0]  # a bright patch, above display white
    noisy = reference * rng.gamma(2.0, 0.5, size=reference.shape)
    smooth = (reference + np.roll(reference, 1, axis=1) + np.roll(reference, 1, axis=0)) / 3
    tinted = reference * np.array([1.3, 0.8, 0.6])
    images = [StripImage("noisy", "noisy, 4 spp", "verdict/x/noisy.exr", noisy),
              StripImage("ours", label, "verdict/x/ours.exr", smooth),
              StripImage("oidn", "OIDN", "verdict/x/oidn.exr", tinted),
              StripImage("reference", "reference, 64 spp", "verdict/x/reference.exr", reference)]
    return verdict.score_strip(Strip(scene, "view-0001", "test", "rule", images))


def write_synthetic_page(out_dir: Path, strips: list[Strip], problems: list[str] = ()) -> dict[str, Path]:
    tables = verdict.RunTables(out_dir)
    return verdict_page.write_page(out_dir, "synthetic", verdict.judge(tables), strips, list(problems),
                              verdict.compact_tables(tables))


# ------------------------------------------------------------------ the writer
def test_rgbe_round_trip_within_its_precision():
    rng = np.random.default_rng(0)
    image = rng.lognormal(0.0, 3.0, size=(17, 13, 3))  # about 1e-6 to 1e6
    image[0, 0] = 0.0
    image[0, 1] = [1.0, 0.0, 1e-9]
    image[1, 0] = [-1.0, np.nan, 2.0]  # negative and NaN are 0
    planes = rgbe_encode(image)
    assert planes.shape == (34, 13, 3) and planes.dtype == np.uint8
    decoded = rgbe_decode(planes)
    expected = np.clip(np.nan_to_num(image, nan=0.0), 0.0, None)
    bound = expected.max(axis=2, keepdims=True) / 256  # RGBE: 8 bits of mantissa per channel, shared exponent
    assert np.all(np.abs(decoded - expected) <= bound * (1 + 1e-6))
    assert np.all(decoded[0, 0] == 0)  # black stays black; a zero channel of a lit pixel is half a step
    assert decoded[1, 0, 0] <= 2 / 256 and decoded[1, 0, 2] == pytest.approx(2.0, rel=1 / 256)
    # through PNG bytes and back, as the page embeds it
    from PIL import Image

    again = np.asarray(Image.open(io.BytesIO(png_bytes(planes))))
    assert np.array_equal(again, planes)


def test_compact_tables_have_at_most_eight_columns():
    assert all(len(spec.columns) <= verdict.MAX_COLUMNS == 8 for spec in verdict.TABLES)
    with pytest.raises(ValueError, match="at most 8"):
        verdict.TableSpec("wide", "table2", tuple(verdict.Column(str(i), verdict._get("scene")) for i in range(9)))


def test_names_are_escaped_in_both_pages(tmp_path):
    strip = synthetic_strip(scene=HOSTILE, label=f"plug-in {HOSTILE}")
    written = write_synthetic_page(tmp_path, [strip])
    page = written["html"].read_text()
    assert "<script>x</script>" not in page
    assert page.count("</script>") == 2  # the data block and the viewer's script, nothing from a name
    assert "&lt;script&gt;x&lt;/script&gt;&amp;&quot;&#x27;" in page
    data = page.split('id="verdict-data">')[1].split("</script>")[0]
    assert json.loads(data)[0]["scene"] == HOSTILE  # the JSON still says the name exactly
    markdown = written["markdown"].read_text()
    assert "<script>" not in markdown and "&lt;script&gt;x&lt;/script&gt;&amp;" in markdown
    assert (tmp_path / "verdict" / safe_stem(HOSTILE) / "strip.png").is_file()


def test_missing_images_are_stated_not_drawn(tmp_path):
    from kdtrace.imageio import write_exr

    folder = tmp_path / "verdict" / "cbox"
    strip = synthetic_strip()
    for item in strip.images:
        if item.key != "ours":  # ours.exr is missing
            write_exr(folder / f"{item.key}.exr", item.image)
    entries = [{"key": item.key, "label": item.label, "file": f"{item.key}.exr"} for item in strip.images]
    (folder / "strip.json").write_text(json.dumps({"scene": "cbox", "view": "view-0001", "split": "test", "rule": "r",
                                                   "images": entries}))
    (tmp_path / "verdict" / "broken").mkdir()
    (tmp_path / "verdict" / "broken" / "strip.json").write_text("{not json")
    written = verdict_page.write_verdict(tmp_path, "synthetic")
    page, markdown = written["html"].read_text(), written["markdown"].read_text()
    for text in (page, markdown):
        assert "verdict/cbox/ours.exr is missing" in text
        assert "verdict/broken/strip.json cannot be read" in text
        assert "not measured in this folder" in text  # no table of any part here
    assert "[ours.exr]" not in markdown and "missing" in markdown.split("linear EXR")[1].split("\n")[0]
    viewer = json.loads(page.split('id="verdict-data">')[1].split("</script>")[0])
    assert [image["key"] for image in viewer[0]["images"]] == ["noisy", "oidn", "reference"]

    (folder / "reference.exr").unlink()  # no reference: no strip at all, said so
    page = verdict_page.write_verdict(tmp_path, "synthetic")["html"].read_text()
    assert "the reference image is missing" in page and "no linear images to compare" in page

    empty = tmp_path / "empty"
    empty.mkdir()
    assert "no strip images in" in verdict_page.write_verdict(empty)["markdown"].read_text()
    with pytest.raises(FileNotFoundError):
        verdict_page.write_verdict(tmp_path / "absent")


def test_claims_judged_in_both_spaces_and_changes_listed(tmp_path):
    (tmp_path / "table2.csv").write_text(
        "scene,model,display_psnr,test_psnr,minus_oidn_display,minus_oidn\n"
        f"{HOSTILE},per-scene,24.0,41.0,-6.0,-0.5\ncar,per-scene,26.0,43.0,-4.0,-1.0\ncar,mixed,20.0,39.0,-9.0,-3.0\n")
    findings = dict((claim.evidence + claim.text[:12], finding) for claim, finding in verdict.judge(verdict.RunTables(tmp_path)))
    above = findings["table2.mdThe per-scen"]
    assert above.verdicts == {"display": verdict.NOT_REPRODUCED, "linear": verdict.HOLDS}
    assert "24.00–26.00 dB display-referred" in above.ours
    changed = verdict.changed_by_space(verdict.judge(verdict.RunTables(tmp_path)))
    assert len(changed) == 2 and "Holds by linear radiance, Not reproduced display-referred" in changed[0]
    markdown = write_synthetic_page(tmp_path, [])["markdown"].read_text()
    assert "Verdicts that change with the image space" in markdown and "[table2.md](table2.md)" in markdown


class FakeDataset:
    """The two methods of a dataset :func:`strip_view` uses."""

    root = Path("fake")

    def __init__(self, references: dict[str, np.ndarray]):
        self.references = references

    def views(self, split=None):
        return list(self.references)

    def load_view(self, name):
        return {"reference": self.references[name]}


def test_strip_view_prefers_the_most_lit_reference():
    black = np.zeros((8, 8, 3))
    corner = black.copy()
    corner[:2, :2] = 1.0  # 4 of 64 pixels lit
    lit = np.full((8, 8, 3), 0.5)
    assert lit_fraction(black) == 0.0 and lit_fraction(corner) == pytest.approx(4 / 64) and lit_fraction(lit) == 1.0
    assert strip_view(FakeDataset({"view-0000": black, "view-0003": lit, "view-0001": corner})) == "view-0003"
    assert strip_view(FakeDataset({"view-0002": black, "view-0001": black})) == "view-0001"  # all black: first name


# ------------------------------------------------------------------ the browser
def find_browser() -> str | None:
    """The first Chromium or Chrome binary on PATH (or /usr/bin/chromium)."""
    for name in BROWSERS:
        found = shutil.which(name)
        if found:
            return found
    return "/usr/bin/chromium" if os.access("/usr/bin/chromium", os.X_OK) else None


class BrowserTimeout(AssertionError):
    """Chromium did not answer a DevTools command in time; the message carries its stderr and crash events."""


class DevTools:
    """A minimal Chrome DevTools Protocol client on ``--remote-debugging-pipe`` (requests by id, events kept).

    Chromium's stderr goes to ``profile_dir/stderr.log`` so that a hang can be told apart from a crash.
    """

    def __init__(self, binary: str, profile_dir: Path, extra_flags: tuple[str, ...] = ()):
        profile_dir.mkdir(parents=True, exist_ok=True)
        self.stderr_path = profile_dir / "stderr.log"
        to_browser_read, self._to_browser = os.pipe()
        self._from_browser, from_browser_write = os.pipe()

        def on_fds_3_and_4() -> None:  # in the child: the pipe ends Chromium expects
            reading, writing = (fcntl.fcntl(fd, fcntl.F_DUPFD, 10) for fd in (to_browser_read, from_browser_write))
            os.dup2(reading, 3)
            os.dup2(writing, 4)

        with open(self.stderr_path, "wb") as stderr:
            self.process = subprocess.Popen(
                [binary, "--headless", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
                 "--remote-debugging-pipe", f"--user-data-dir={profile_dir}", "--no-first-run",
                 "--no-default-browser-check", "--disable-extensions", "--window-size=1280,1600", *extra_flags,
                 "about:blank"],
                stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=stderr,
                preexec_fn=on_fds_3_and_4, close_fds=False)  # only 3 and 4 are inheritable: Python's own fds are not
        os.close(to_browser_read)
        os.close(from_browser_write)
        self._next_id = 0
        self._replies: dict[int, queue.Queue] = {}
        self.events: list[dict] = []
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def _read(self) -> None:
        pending = b""
        while True:
            chunk = os.read(self._from_browser, 1 << 16)
            if not chunk:
                return
            pending += chunk
            while b"\0" in pending:
                message, pending = pending.split(b"\0", 1)
                parsed = json.loads(message)
                if "id" in parsed and parsed["id"] in self._replies:
                    self._replies[parsed["id"]].put(parsed)
                else:
                    self.events.append(parsed)

    def diagnosis(self) -> str:
        """What Chromium said: crash events, whether it still runs, and the tail of its stderr."""
        crashes = [event["method"] for event in self.events if "rash" in event.get("method", "")]
        alive = "running" if self.process.poll() is None else f"exited with {self.process.returncode}"
        tail = self.stderr_path.read_text(errors="replace").strip().splitlines()[-15:]
        return f"chromium {alive}; crash events {crashes}; stderr tail:\n" + "\n".join(tail)

    def send(self, method: str, params: dict | None = None, session: str | None = None, timeout: float = 30.0) -> dict:
        """Send one command and wait for its reply's ``result``; an error reply raises, silence raises BrowserTimeout."""
        self._next_id += 1
        message = {"id": self._next_id, "method": method, "params": params or {}}
        if session:
            message["sessionId"] = session
        self._replies[self._next_id] = queue.Queue()
        os.write(self._to_browser, json.dumps(message).encode() + b"\0")
        try:
            reply = self._replies[self._next_id].get(timeout=timeout)
        except queue.Empty:
            raise BrowserTimeout(f"{method}: no reply in {timeout:g} s; {self.diagnosis()}") from None
        if "error" in reply:
            raise RuntimeError(f"{method}: {reply['error']}")
        return reply["result"]

    def wait_for_event(self, method: str, timeout: float) -> dict:
        """The first event named ``method`` (kept since launch), waiting up to ``timeout`` seconds."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            found = next((event for event in self.events if event.get("method") == method), None)
            if found is not None:
                return found
            time.sleep(0.05)
        raise BrowserTimeout(f"no {method} event in {timeout:g} s; {self.diagnosis()}")

    def close(self) -> None:
        try:
            self.send("Browser.close", timeout=5.0)
        except (RuntimeError, BrowserTimeout, OSError):
            pass
        try:
            self.process.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.wait()
        for fd in (self._to_browser, self._from_browser):
            os.close(fd)


def open_blank_page(binary: str, profile_dir: Path) -> tuple[DevTools, str]:
    """A browser with one blank tab whose renderer answers JavaScript; returns it and the tab's session id.

    Some containers start Chromium's browser process but not its renderer processes; there the
    tab is retried once with the renderer inside the browser process (``--single-process``), and
    only if that fails too is the test skipped, with Chromium's own diagnosis. The page under
    test is loaded only after this, so a page that hangs still fails.
    """
    failures = []
    for flags in ((), ("--single-process", "--no-zygote")):
        browser = DevTools(binary, profile_dir / ("default" if not flags else "single-process"), flags)
        try:
            target = browser.send("Target.createTarget", {"url": "about:blank"})["targetId"]
            session = browser.send("Target.attachToTarget", {"targetId": target, "flatten": True})["sessionId"]
            browser.send("Runtime.enable", session=session)
            browser.send("Page.enable", session=session)
            answer = browser.send("Runtime.evaluate", {"expression": "6 * 7", "returnByValue": True}, session=session)
            assert answer["result"]["value"] == 42
            return browser, session
        except BrowserTimeout as error:
            failures.append(f"flags {list(flags)}: {error}")
            browser.close()
    pytest.skip("headless chromium runs here but its renderer never answers:\n" + "\n\n".join(failures))


def test_page_in_headless_chromium(tmp_path):
    from PIL import Image

    binary = find_browser()
    if binary is None:
        pytest.skip("no chromium/chrome binary found (scripts/setup-browser.sh installs Debian's chromium)")
    strip = synthetic_strip(scene=HOSTILE)
    page = write_synthetic_page(tmp_path / "results", [strip, synthetic_strip(scene="second")])["html"]
    browser, session = open_blank_page(binary, tmp_path / "chromium-profile")
    try:
        def evaluate(expression: str):
            result = browser.send("Runtime.evaluate", {"expression": expression, "returnByValue": True,
                                                       "awaitPromise": True}, session=session)
            assert "exceptionDetails" not in result, result["exceptionDetails"]
            return result["result"].get("value")

        browser.events.clear()
        browser.send("Page.navigate", {"url": page.resolve().as_uri()}, session=session)
        browser.wait_for_event("Page.loadEventFired", timeout=60)
        deadline = time.monotonic() + 60
        while not evaluate("!!(window.kdtraceVerdict && window.kdtraceVerdict.ready)"):
            assert time.monotonic() < deadline, f"the page never finished decoding its images; {browser.diagnosis()}"
            time.sleep(0.1)
        assert evaluate("window.kdtraceVerdict.errors") == []
        assert evaluate("document.title") == "Verdict: synthetic profile"
        assert evaluate("document.querySelector('section.viewer h3').textContent").startswith(HOSTILE)

        # the page decodes the embedded RGBE exactly as numpy does
        decoded = np.asarray(evaluate("window.kdtraceVerdict.viewers[0].linear('reference')"), dtype=np.float32)
        expected = rgbe_decode(rgbe_encode(strip.reference.image)).reshape(-1)
        np.testing.assert_allclose(decoded, expected, rtol=1e-6)

        canvas = "document.querySelector('section.viewer canvas.method').toDataURL()"
        state = "window.kdtraceVerdict.viewers[0].state()"
        before = evaluate(canvas)
        assert evaluate(state)["key"] == "noisy"
        for kind in ("keyDown", "keyUp"):  # a real key event: "2" selects the second method
            browser.send("Input.dispatchKeyEvent", {"type": kind, "key": "2", "code": "Digit2", "text": "2",
                                                    "windowsVirtualKeyCode": 50}, session=session)
        assert evaluate(state)["key"] == "ours"
        after_key = evaluate(canvas)
        assert after_key != before

        box = evaluate("(() => { const tab = document.querySelector('section.viewer .tabs button[data-index=\"2\"]');"
                       " tab.scrollIntoView({block: 'center'}); const r = tab.getBoundingClientRect();"
                       " return [r.left + r.width / 2, r.top + r.height / 2]; })()")
        for kind in ("mousePressed", "mouseReleased"):  # a real click on the third tab
            browser.send("Input.dispatchMouseEvent", {"type": kind, "x": box[0], "y": box[1], "button": "left",
                                                      "clickCount": 1}, session=session)
        assert evaluate(state)["key"] == "oidn"
        assert evaluate("document.querySelector('section.viewer .tabs button[data-index=\"2\"]')"
                        ".getAttribute('aria-selected')") == "true"
        assert evaluate(canvas) not in (before, after_key)

        shot = browser.send("Page.captureScreenshot", {"format": "png"}, session=session)["data"]
        picture = np.asarray(Image.open(io.BytesIO(base64.b64decode(shot))).convert("RGB"))
        assert picture.shape[0] > 100 and len(np.unique(picture.reshape(-1, 3), axis=0)) > 16  # not blank
        shown = np.asarray(Image.open(io.BytesIO(base64.b64decode(after_key.split(",", 1)[1]))).convert("RGB"))
        assert len(np.unique(shown.reshape(-1, 3), axis=0)) > 16  # the canvas shows an image, not one colour
        assert evaluate("window.kdtraceVerdict.errors") == []
        assert not [event for event in browser.events if event.get("method") == "Runtime.exceptionThrown"]
    finally:
        browser.close()


def test_index_links_the_verdict_first_once(tmp_path):
    assert not verdict_page.link_from_index(tmp_path)  # no index: nothing to link from
    (tmp_path / "README.md").write_text("# kdtrace report: quick profile\n\nrest\n")
    assert verdict_page.link_from_index(tmp_path) and verdict_page.link_from_index(tmp_path)
    index = (tmp_path / "README.md").read_text()
    assert index.count("](verdict.md)") == 1 and index.index("verdict.md") < index.index("rest")


def test_production_scale_is_shown_beside_the_memory_verdicts_and_not_graded(tmp_path):
    tables = verdict.RunTables(tmp_path)
    assert verdict._at_production_scale(tables, "tree_bytes", "less") == ""  # not run here
    stages = {"scene": {"triangles": 10_114_192},
              "build-naive": {"tree_bytes": 1000, "triangle_references": 400},
              "build-local": {"tree_bytes": 828, "triangle_references": 287}}
    (tmp_path / "table1_production.json").write_text(json.dumps({"stages": stages}))
    tables = verdict.RunTables(tmp_path)
    assert verdict._at_production_scale(tables, "tree_bytes", "less") == \
        "; 17.2% less at 10,114,192 triangles (kdtrace production)"
    assert "28.2% fewer references at 10,114,192" in verdict._at_production_scale(tables, "triangle_references",
                                                                                  "fewer references")
    (tmp_path / "table1_production.json").write_text("{not json")
    assert verdict._at_production_scale(verdict.RunTables(tmp_path), "tree_bytes", "less") == ""
