"""Line / frame events on the API and the images the daemon writes per finished frame (real daemon)."""

from __future__ import annotations

import threading
from pathlib import Path

from piezod.config import config_dir
from piezod.service.schemas import ScanEvent
from tests.real_daemon import SLOW, RealDaemon


def test_line_and_frame_events_and_images_beside_the_recording(tmp_path: Path) -> None:
    import gwyfile

    config = config_dir() / "sim-microscope.yaml"
    events: list[ScanEvent] = []
    with RealDaemon(tmp_path, config=config) as daemon:
        subscribed = threading.Event()
        done = threading.Event()

        def follow() -> None:
            with daemon.client(timeout=60.0) as c:
                for ev in c.events(rate_hz=2.0, scans=True):
                    subscribed.set()
                    if isinstance(ev, ScanEvent):
                        events.append(ev)
                        if ev.kind == "frame" and (ev.images or ev.image_error):
                            done.set()
                            return

        t = threading.Thread(target=follow, daemon=True)
        t.start()
        assert subscribed.wait(30 * SLOW)
        with daemon.client() as c:
            c.scan(range_um=10.0, line_rate_hz=5.0, lines=3, pixels=64, name="evscan")
        assert done.wait(120 * SLOW), f"no frame event with images; events: {events}"
        t.join(10)
        faults = [f"{f.code}: {f.message}" for f in daemon.status().faults]
    lines = [e for e in events if e.kind == "line"]
    want = {(i, d) for i in range(3) for d in ("trace", "retrace")}
    assert {(e.line, e.direction) for e in lines} >= want, f"line events {lines}; daemon faults {faults}"
    assert all(e.recording == "evscan.csv" and e.lines == 3 and e.frame == 0 for e in lines)
    frame = events[-1]
    assert frame.kind == "frame" and frame.image_error is None and frame.frame == 0
    assert "evscan.gwy" in frame.images and any(f.endswith(".png") for f in frame.images)
    rec_dir = daemon.recordings
    for name in frame.images:
        assert (rec_dir / name).is_file()
    obj = gwyfile.load(str(rec_dir / "evscan.gwy"))
    assert any(str(obj[k]).startswith("z_voltage trace") for k in obj if k.endswith("/data/title"))
    # line events come in scan order, before the frame's
    order = [(e.line, e.direction == "retrace") for e in lines]
    assert order == sorted(order)
