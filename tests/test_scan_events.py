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


def test_each_frame_gets_its_images_with_heights_while_the_scan_goes_on(tmp_path: Path) -> None:
    # a scan until stopped, frames of three lines: frame 0's images are written (in a child process)
    # and named by its frame event while the scan still runs; the last frame's when the recording
    # closes. Both carry the heights through the scanner's z model (height_model, height_linear)
    # beside z_voltage. Before: one frame event per frame without images, the images (z_voltage
    # only) once, of the whole recording, when it closed.
    import gwyfile
    import numpy as np

    config = config_dir() / "sim-microscope.yaml"
    events: list[ScanEvent] = []
    with RealDaemon(tmp_path, config=config) as daemon:
        subscribed = threading.Event()
        first = threading.Event()
        last = threading.Event()
        stopped = threading.Event()

        def follow() -> None:
            with daemon.client(timeout=60.0) as c:
                for ev in c.events(rate_hz=2.0, scans=True):
                    subscribed.set()
                    if isinstance(ev, ScanEvent):
                        events.append(ev)
                        if ev.kind == "frame" and ev.frame == 0:
                            first.set()
                        # after the stop, a middle frame's "skipped" event may still come (the
                        # images lag under load): the last frame's own event is a written one
                        written = ev.image_error is None or "skipped" not in ev.image_error
                        if ev.kind == "frame" and stopped.is_set() and ev.frame > 0 and written:
                            last.set()
                            return

        t = threading.Thread(target=follow, daemon=True)
        t.start()
        assert subscribed.wait(30 * SLOW)
        with daemon.client() as c:
            c.scan(range_um=10.0, line_rate_hz=5.0, lines=3, frames=0, pixels=64, name="frames")
            assert first.wait(180 * SLOW), f"no frame event for frame 0; events: {events}"
            assert c.status().state == "scanning"  # frame 0's images came during the scan
            stopped.set()
            c.stop()
        assert last.wait(180 * SLOW), f"no frame event after the stop; events: {events}"
        t.join(10)
    frames = [e for e in events if e.kind == "frame"]
    assert [e.frame for e in frames] == sorted(e.frame for e in frames), "frame events out of order"
    # frames that finish faster than their images are written may be skipped (said so); the first
    # and the last never are
    assert all(e.image_error is None or "skipped" in e.image_error for e in frames), frames
    for e in (frames[0], frames[-1]):
        assert e.image_error is None and e.recording == "frames.csv", e
        assert f"frames-f{e.frame}.gwy" in e.images, e.images
        assert f"frames-f{e.frame}-height_model-commanded.png" in e.images, e.images
    obj = gwyfile.load(str(daemon.recordings / "frames-f0.gwy"))
    titles = {str(obj[k]): k.removesuffix("/title") for k in obj if k.endswith("/data/title")}
    assert {"height_model trace (commanded grid)", "height_linear trace (commanded grid)"} <= set(titles)
    data = np.asarray(obj[titles["height_model trace (commanded grid)"]].data)
    # one whole frame of three lines, every pixel filled, the 100 nm lines of the pattern
    assert data.shape == (3, 64) and np.isfinite(data).all()
    assert 0.05e-6 < float(np.ptp(data)) < 1e-6
