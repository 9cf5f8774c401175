#!/usr/bin/env python3
"""The web view's screenshot in the README (``make docs-figures``): the README's command
of its block ``<!-- recipe-steps: web -->`` run as written (on a free port), its page opened
in headless chromium (tests/chromium.py) once it shows the targets, their tracks, the truth,
the range profile and the health of every node and has drawn 3 s of frames, then written to
docs/figures/web_view.png.

    .venv/bin/python docs/figures/web_view.py [--out docs/figures/web_view.png]
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import threading
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "tests"))

from chromium import Chromium  # noqa: E402  (tests/ first on the path)

#: the page is ready for its picture when this holds (window.qradarView.stats())
READY = ("(s => s.targetsDrawn >= 2 && s.truthDrawn >= 2 && s.tracksDrawn >= 2 && s.healthRows >= 4 && "
         "s.profilesDrawn > 0 && s.interval.n >= 180)(window.qradarView.stats())")


def readme_command() -> str:
    """The README's web command (its block ``recipe-steps: web``), comment cut."""
    text = (ROOT / "README.md").read_text()
    m = re.search(r"<!-- recipe-steps: web -->\n```sh\n(.*?)```", text, re.S)
    if not m:
        raise SystemExit("README.md has no <!-- recipe-steps: web --> block")
    return re.sub(r"\s+#.*$", "", m.group(1).strip().splitlines()[0]).strip()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "figures" / "web_view.png")
    args = ap.parse_args()
    command = readme_command()
    line = re.sub(r"--web \S+", "--web 0", command) + " --duration 60"
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}"}
    run = subprocess.Popen(["bash", "-c", f"exec {line}"], cwd=ROOT, env=env, stdin=subprocess.DEVNULL,
                           stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        url = None
        for _ in range(200):  # its first lines: the page's URL
            out = run.stdout.readline()
            m = re.search(r"web: page on (\S+)", out)
            if m or not out:
                url = m and m.group(1)
                break
        if url is None:
            raise SystemExit(f"{line!r} printed no page URL: {out!r}")
        threading.Thread(target=run.stdout.read, daemon=True).start()  # drained, never blocks the run
        with Chromium(width=1400, height=900) as browser:
            page = browser.open(url)
            page.wait_for(READY, 40.0, "the page with targets, tracks, truth, profile and health")
            page.screenshot(args.out)
    finally:
        run.terminate()
        run.wait(30)
    print(f"`{command}`: wrote {args.out.relative_to(ROOT) if args.out.is_relative_to(ROOT) else args.out}")


if __name__ == "__main__":
    main()
