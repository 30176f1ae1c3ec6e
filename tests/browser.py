"""Look at a report the way a person does: load it in headless Chromium.

:func:`check_in_browser` opens an HTML file in Chromium (``--headless``), lets
it load every image, and reports for each ``<img>`` whether it decoded
(``naturalWidth > 0``), plus the number of tables and their rows; it also saves
a screenshot. Nothing is injected into the report itself: a probe copy with one
inline script is written next to it (so relative image links resolve), loaded
with ``--dump-dom``, and deleted.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import tempfile
from dataclasses import dataclass
from pathlib import Path

from dynbtf.errors import InputError
from chromium import CHROMIUM_FLAGS as _LIBRARY_FLAGS
from chromium import find_chromium

__all__ = ["find_chromium", "check_in_browser", "BrowserCheck", "CHROMIUM_FLAGS"]

#: Flags for a quiet, offline, sandbox-free headless run without GPU (each run also gets a fresh profile dir).
CHROMIUM_FLAGS = (*_LIBRARY_FLAGS, "--disable-gpu")

_PROBE = """
<script>
window.addEventListener('load', function () {
  var imgs = Array.prototype.map.call(document.images, function (i) {
    return {src: i.getAttribute('src'), naturalWidth: i.naturalWidth, naturalHeight: i.naturalHeight,
            complete: i.complete};
  });
  var tables = Array.prototype.map.call(document.querySelectorAll('table'), function (t) {
    return {rows: t.rows.length, caption: t.caption ? t.caption.textContent : ''};
  });
  var pre = document.createElement('pre');
  pre.id = 'dynbtf-browser-check';
  pre.textContent = JSON.stringify({images: imgs, tables: tables, title: document.title});
  document.body.appendChild(pre);
});
</script>
"""


@dataclass
class BrowserCheck:
    """What Chromium saw: ``images`` (list of dicts with ``src``, ``naturalWidth``...), ``tables``
    (list of dicts with ``rows``, ``caption``), the page ``title`` and the ``screenshot`` path."""

    images: list
    tables: list
    title: str
    screenshot: Path | None

    @property
    def broken_images(self) -> list[str]:
        """``src`` of every image that did not load (``naturalWidth == 0``)."""
        return [i["src"] for i in self.images if not i.get("naturalWidth")]


def _run(cmd: list[str], timeout: float) -> subprocess.CompletedProcess:
    return subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)


def check_in_browser(html_path, *, screenshot=None, window=(1400, 2400), timeout: float = 120.0,
                     chromium: str | None = None) -> BrowserCheck:
    """Load ``html_path`` in headless Chromium; return what it saw.

    Parameters
    ----------
    html_path : path
        The report.
    screenshot : path, optional
        Where to save a PNG screenshot of the top ``window`` of the page.
    window : (width, height)
        Browser window size in CSS pixels.
    timeout : float
        Seconds allowed per Chromium run.
    chromium : str, optional
        Executable (default: :func:`find_chromium`).
    """
    html_path = Path(html_path).resolve()
    if not html_path.is_file():
        raise InputError(f"{html_path}: report not found")
    exe = chromium or find_chromium()
    if exe is None:
        raise InputError("no Chromium executable found (install Debian's 'chromium' or set DYNBTF_CHROMIUM)")
    text = html_path.read_text(encoding="utf-8")
    probe_text = text.replace("</body>", _PROBE + "</body>") if "</body>" in text else text + _PROBE
    fd, probe = tempfile.mkstemp(prefix=".browser-check-", suffix=".html", dir=html_path.parent)
    os.close(fd)
    probe = Path(probe)
    try:
        probe.write_text(probe_text, encoding="utf-8")
        with tempfile.TemporaryDirectory(prefix="dynbtf-chromium-") as profile:
            flags = [*CHROMIUM_FLAGS, f"--user-data-dir={profile}", f"--window-size={window[0]},{window[1]}",
                     "--virtual-time-budget=20000"]
            done = _run([exe, *flags, "--dump-dom", probe.as_uri()], timeout)
            m = re.search(r'<pre id="dynbtf-browser-check">(.*?)</pre>', done.stdout, re.S)
            if not m:
                raise RuntimeError(f"Chromium did not run the report probe (exit {done.returncode}): "
                                   f"{done.stderr.strip()[-500:]}")
            import html as _html

            seen = json.loads(_html.unescape(m.group(1)))
            shot = None
            if screenshot is not None:
                shot = Path(screenshot).resolve()
                shot.parent.mkdir(parents=True, exist_ok=True)
                _run([exe, *flags, f"--screenshot={shot}", html_path.as_uri()], timeout)
                if not shot.exists():
                    raise RuntimeError(f"Chromium wrote no screenshot to {shot}")
    finally:
        probe.unlink(missing_ok=True)
    return BrowserCheck(images=seen["images"], tables=seen["tables"], title=seen.get("title", ""), screenshot=shot)
