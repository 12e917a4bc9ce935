"""Drive ``hapsim run|play ... --view 0`` in a real headless browser (Debian's chromium and
chromium-driver through selenium): the live view's test (tests/test_view.py) and its
screenshots in the docs, and the loop-disturbance benchmark (tools/view_bench.py).

Usage (the screenshots of docs/view.md)::

    python tools/view_browser.py --shots docs

writes docs/view_wall.png (``hapsim run configs/wall.yaml``), docs/view_pantograph.png
(``hapsim play`` of configs/pantograph_wall.yaml with a listening point, on a JACK dummy
server) and docs/view_membrane.png (``hapsim play configs/membrane.yaml``, idem). The test
writes the same files from its own browser run.
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
#: The chromium flags that work headless in a container (no sandbox, no GPU, nothing
#: fetched from outside the machine).
CHROMIUM_FLAGS = ("--headless", "--no-sandbox", "--disable-gpu", "--disable-quic",
                  "--no-first-run", "--disable-background-networking",
                  "--disable-component-update", "--disable-sync",
                  "--window-size=1280,1000")


def browser_missing() -> str | None:
    """Why no headless browser can run here (None when chromium, its driver and selenium
    are all installed)."""
    for exe, pkg in (("chromium", "chromium"), ("chromedriver", "chromium-driver")):
        if shutil.which(exe) is None:
            return f"{exe} not installed: apt-get install {pkg}"
    try:
        import selenium  # noqa: F401
    except ImportError:
        return "selenium not installed: pip install selenium"
    try:
        import websockets  # noqa: F401
    except ImportError:
        return "websockets not installed: pip install 'hapsim[view]'"
    return None


def open_browser(profile: str):
    """A headless chromium (selenium WebDriver) with a fresh profile in ``profile``."""
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service
    opts = webdriver.ChromeOptions()
    opts.binary_location = shutil.which("chromium")
    for f in CHROMIUM_FLAGS:
        opts.add_argument(f)
    opts.add_argument(f"--user-data-dir={profile}")
    return webdriver.Chrome(service=Service(shutil.which("chromedriver")), options=opts)


class ViewRun:
    """A ``python -m hapsim ... --view 0`` child and its page's address.

    Parameters
    ----------
    argv : list of str
        The command after ``python -m hapsim`` (``--view 0`` is appended).
    env : dict, optional
        The child's environment.
    timeout : float
        Most time to wait for the view's address on stderr [s].
    """

    def __init__(self, argv, env=None, timeout: float = 120.0) -> None:
        self.err = tempfile.TemporaryFile(mode="w+")
        self.proc = subprocess.Popen([sys.executable, "-m", "hapsim", *argv, "--view", "0"],
                                     stdout=subprocess.PIPE, stderr=self.err, text=True,
                                     env=env, cwd=ROOT)
        self.url = None
        end = time.monotonic() + timeout
        while time.monotonic() < end and self.proc.poll() is None:
            m = re.search(r"live view on (http://127\.0\.0\.1:\d+/)", self._stderr())
            if m:
                self.url = m.group(1)
                break
            time.sleep(0.1)
        if self.url is None:
            raise RuntimeError(f"no view address: {self._stderr()[-2000:]}")

    def _stderr(self) -> str:
        """What the child wrote on stderr so far.

        Read with ``pread``, which leaves the file offset alone: the child shares this
        open file (its offset), so a ``seek(0)`` here while it runs made its next line
        overwrite the file from the start (the view's address lost under the start-up
        line, a 120 s wait for an address already given)."""
        fd = self.err.fileno()
        return os.pread(fd, os.fstat(fd).st_size, 0).decode("utf-8", "replace")

    def finish(self, timeout: float = 60.0) -> tuple[int, str, str]:
        """Wait for the child's end; its exit code, stdout and stderr."""
        out, _ = self.proc.communicate(timeout=timeout)
        return self.proc.returncode, out, self._stderr()

    def kill(self) -> None:
        """End the child if it still runs (SIGTERM: its clean stop)."""
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(30)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()


def wait_for(driver, script: str, timeout: float = 30.0, every: float = 0.1):
    """Poll ``return <script>`` in the page until it is truthy; its value (else
    TimeoutError with the script)."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        v = driver.execute_script("return " + script)
        if v:
            return v
        time.sleep(every)
    raise TimeoutError(f"the page never had {script!r} within {timeout:g} s")


def shoot(driver, url: str, path: str, settle: float = 1.5, grid: bool = True,
          points: int = 20) -> None:
    """Load the view, wait until ``points`` trace points are drawn (and the grid, for a 1-D
    loop), and write a screenshot of the page to ``path``. (An n-D play hands one row per
    chunk of its producer over: few points at a low rate.)"""
    driver.get(url)
    wait_for(driver, f"window.hapsimView && window.hapsimView.t.length > {points}", 60)
    if grid:
        wait_for(driver, "window.hapsimView.grid !== null", 60)
    time.sleep(settle)
    driver.save_screenshot(path)


def pantograph_with_listen(directory: str) -> str:
    """configs/pantograph_wall.yaml with a listening point on the handle's y axis (``hapsim
    play`` plays a scene's sound: an n-D scene needs one); the path of the copy."""
    with open(os.path.join(ROOT, "configs", "pantograph_wall.yaml"), encoding="utf-8") as fh:
        text = fh.read()
    text += ("audio:\n  listen:\n    - {mass: hand, axis: y, quantity: velocity, "
             "gain: 1.0}\n")
    path = os.path.join(directory, "pantograph_wall_listen.yaml")
    with open(path, "w", encoding="utf-8") as fh:
        fh.write(text)
    return path


def main(argv=None) -> int:
    """Write the three screenshots of docs/view.md (``--shots DIR``)."""
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--shots", metavar="DIR", required=True, help="where the PNGs go")
    p.add_argument("--jack-server", metavar="NAME", required=True,
                   help="a running JACK server (jackd -n NAME -d dummy -r RATE) at the "
                        "scene's rate for the n-D plays (1000 Hz the pantograph, 44100 Hz "
                        "the membrane: run once with each)")
    a = p.parse_args(argv)
    why = browser_missing()
    if why:
        print(f"view_browser: {why}", file=sys.stderr)
        return 2
    with tempfile.TemporaryDirectory() as tmp:
        drv = open_browser(os.path.join(tmp, "profile"))
        try:
            for name, argv_, grid in (
                    ("wall", ["run", "configs/wall.yaml", "--duration", "0"], True),
                    ("pantograph", ["play", pantograph_with_listen(tmp), "--sound", "jack",
                                    "--jack-server", a.jack_server, "--duration", "60"], False),
                    ("membrane", ["play", "configs/membrane.yaml", "--sound", "jack",
                                  "--jack-server", a.jack_server, "--duration", "60"], False)):
                r = ViewRun(argv_)
                try:
                    shoot(drv, r.url, os.path.join(a.shots, f"view_{name}.png"), grid=grid,
                          points=20 if grid else 2)
                    print(f"view_browser: {a.shots}/view_{name}.png", file=sys.stderr)
                finally:
                    r.kill()
        finally:
            drv.quit()
    return 0


if __name__ == "__main__":
    sys.exit(main())
