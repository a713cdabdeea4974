"""Makes docs/img/live_view.png: a live session in the browser view, shot by headless Chromium.

Run:  python docs/img/live_view_screenshot.py   (needs `chromium` on the PATH and the 'view' extra)

The simulated device drives the main bar of the ``hanging`` scene; after 3 s a websocket
client (tests/support/live_view_client.py, speaking viser's protocol as a browser does) drags the bar
down and sideways, so some strings go slack (orange); 2 s later Chromium (software WebGL)
takes the picture. The top-left corner, where viser warns about software WebGL, is cut off.
"""

from __future__ import annotations

import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import warp as wp

wp.config.log_level = wp.LOG_WARNING

import dmarionette as dm  # noqa: E402
from dmarionette.live.run import run_live  # noqa: E402
from dmarionette.live.view import LiveViewGeometry  # noqa: E402
from dmarionette.live.view_viser import LiveViewServer  # noqa: E402
from dmarionette.marionette.solver import MarionetteModel  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))
from tests.support.live_view_client import ViewClient  # noqa: E402


def main() -> None:
    model = MarionetteModel(dm.load_scene("hanging"), optimization_level=2)
    out = ROOT / "docs" / "img" / "live_view.png"
    with LiveViewServer(LiveViewGeometry.from_model(model, "main"), port=0) as view:
        session = threading.Thread(target=run_live, args=(model,), kwargs={"duration": 12.0, "view": view,
                                                                          "force_scale": 0.3})
        session.start()
        time.sleep(3.0)
        client = ViewClient(view.url)
        time.sleep(0.5)
        client.drag("/drag/main", [0.05, -0.16, 0.0], steps=19, pause=0.03)
        time.sleep(1.0)
        with tempfile.TemporaryDirectory() as tmp:
            raw = Path(tmp) / "shot.png"
            subprocess.run(["chromium", "--headless=new", "--no-sandbox", "--use-angle=swiftshader",
                            "--enable-unsafe-swiftshader", "--window-size=1400,900", "--virtual-time-budget=6000",
                            f"--screenshot={raw}", view.url], check=True, capture_output=True, timeout=120)
            from PIL import Image

            Image.open(raw).crop((330, 0, 1400, 900)).save(out)
        client.close()
        session.join()
    print(out)


if __name__ == "__main__":
    main()
