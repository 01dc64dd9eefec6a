"""PiezodClient and ``piezod ctl`` against a real ApiServer with the fake engine."""

from __future__ import annotations

import json
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from fake_engine import FakeEngine, running_api

from piezod.cli import main
from piezod.client import PiezodClient
from piezod.config import ApiConfig
from piezod.errors import ApiError, ApiUnreachableError, PiezodError
from piezod.service.schemas import FaultInfo, ScanRequest, Status
from piezod.service.server import ApiServer

CSV = "t,voltage,position\n" + "".join(
    f"{i * 1e-4:.4f},{i % 50:.1f},{(i % 50) * 0.2:.3f}\n" for i in range(5000)
)


@pytest.fixture(scope="module")
def served(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[FakeEngine, ApiServer]]:
    rec = tmp_path_factory.mktemp("client")
    (rec / "scan-001.csv").write_text(CSV)
    with running_api(rec) as (engine, server):
        yield engine, server


@pytest.fixture
def fake(served: tuple[FakeEngine, ApiServer]) -> FakeEngine:
    served[0].reset()
    return served[0]


@pytest.fixture
def spec(served: tuple[FakeEngine, ApiServer], fake: FakeEngine) -> str:
    return served[1].address


@pytest.fixture
def client(spec: str) -> Iterator[PiezodClient]:
    with PiezodClient(spec, timeout=10) as c:
        yield c


# ---------------------------------------------------------------------------- client


def test_status_scan_change_move_stop(client: PiezodClient, fake: FakeEngine) -> None:
    status = client.status()
    assert isinstance(status, Status) and status.state == "idle" and status.scanner == "fake-stage"
    status = client.scan(range_um=10, line_rate_hz=2, lines=16, name="s1")
    assert status.state == "scanning" and status.scan is not None and status.scan.lines == 16
    status = client.change(offset_x_um=1.5)
    assert status.scan is not None and status.scan.offset_x_um == 1.5
    assert client.stop().state == "idle"
    assert client.move(x_um=2, y_um=-1).position_um["x"] == 2
    assert client.scan(ScanRequest(range_um=5, line_rate_hz=1), frames=3).scan == ScanRequest(
        range_um=5, line_rate_hz=1, frames=3
    )


def test_scan_out_of_limits_raises_api_error_with_the_engine_reason(client: PiezodClient) -> None:
    with pytest.raises(ApiError) as info:
        client.scan(range_um=100, line_rate_hz=2)
    err = info.value
    assert (err.status_code, err.error) == (422, "RangeUnreachableError")
    assert err.detail == "range 100 um needs +/-250 V on x, beyond voltage_max_v 150 V"
    assert str(err) == f"POST /v1/scan: {err.detail} (HTTP 422)"
    assert isinstance(err, PiezodError)


def test_bad_body_names_the_fields(client: PiezodClient) -> None:
    with pytest.raises(ApiError) as info:
        client.scan(range_um=-3)
    assert info.value.status_code == 422
    assert info.value.detail == ("range_um: Input should be greater than 0; line_rate_hz: Field required")
    assert "\n" not in str(info.value)


def test_change_while_idle_is_409(client: PiezodClient) -> None:
    with pytest.raises(ApiError, match=r"cannot change the scan: the engine is idle \(HTTP 409\)") as info:
        client.change(range_um=5)
    assert info.value.status_code == 409 and info.value.error == "EngineStateError"


def test_recordings_list_fetch_404_and_traversal(client: PiezodClient, tmp_path: Path) -> None:
    (rec,) = client.recordings()
    assert (rec.name, rec.size_bytes, rec.complete) == ("scan-001.csv", len(CSV), True)
    into_dir = client.fetch_recording("scan-001.csv", tmp_path)
    assert into_dir == tmp_path / "scan-001.csv" and into_dir.read_text() == CSV
    named = client.fetch_recording("scan-001.csv", tmp_path / "copy.csv")
    assert named.read_text() == CSV
    for name in ("missing.csv", "../scan-001.csv", "../../etc/passwd", ".."):
        with pytest.raises(ApiError) as info:
            client.fetch_recording(name, tmp_path / "x.csv")
        assert info.value.status_code == 404, name
    assert sorted(p.name for p in tmp_path.iterdir()) == ["copy.csv", "scan-001.csv"]  # no partial files


def test_events_deliver_status_then_close(client: PiezodClient, fake: FakeEngine) -> None:
    events = list(client.events(rate_hz=50, limit=3))
    assert len(events) == 3 and all(isinstance(e, Status) for e in events)


def test_events_deliver_a_fault_at_once(client: PiezodClient, fake: FakeEngine) -> None:
    stream = client.events(rate_hz=0.2)
    first = next(stream)
    assert isinstance(first, Status)
    fake.inject_fault("limit", "sample outside voltage limits")
    second = next(stream)  # the next status is 5 s away
    assert isinstance(second, FaultInfo) and second.code == "limit"
    stream.close()


def test_unreachable_daemon(tmp_path: Path) -> None:
    with PiezodClient(f"unix:{tmp_path / 'none.sock'}") as c, pytest.raises(ApiUnreachableError) as info:
        c.status()
    assert isinstance(info.value, ConnectionError)
    assert str(info.value) == (
        f"GET /v1/status: cannot reach unix:{tmp_path / 'none.sock'}: No such file or directory "
        "(is piezod serve running?)"
    )


def test_token_over_tcp(tmp_path: Path) -> None:
    token_file = tmp_path / "token"
    token_file.write_text("tok-123\n")
    cfg = ApiConfig(allow_remote=True, token_file=str(token_file))
    with running_api(tmp_path, "tcp:127.0.0.1:0", cfg) as (_, server):
        with PiezodClient(server.address) as anonymous, pytest.raises(ApiError) as info:
            anonymous.status()
        assert (info.value.status_code, info.value.detail) == (401, "missing bearer token")
        with PiezodClient(server.address, token="tok-123") as c:
            assert c.status().state == "idle"
            assert c.openapi()["info"]["title"] == "piezod control API"
        rc = main(["ctl", "--api", server.address, "--token-file", str(token_file), "status"])
        assert rc == 0


# ---------------------------------------------------------------------------- piezod ctl


def test_ctl_status_human_and_json(spec: str, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["ctl", "--api", spec, "status"]) == 0
    out = capsys.readouterr().out
    assert out.startswith("fake-stage: idle (uptime ")
    assert "underruns 0" in out
    assert main(["ctl", "--api", spec, "status", "--json", "-"]) == 0
    captured = capsys.readouterr()
    assert json.loads(captured.out)["state"] == "idle"
    assert captured.err.startswith("fake-stage: idle")  # human text moved to stderr


def test_ctl_default_api_from_environment(
    spec: str, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("PIEZOD_API", spec)
    assert main(["ctl", "--json", "-", "status"]) == 0
    assert json.loads(capsys.readouterr().out)["scanner"] == "fake-stage"


def test_ctl_scan_change_move_stop(spec: str, fake: FakeEngine, capsys: pytest.CaptureFixture[str]) -> None:
    args = ["ctl", "--api", spec, "scan", "--range-um", "12", "--line-rate-hz", "3", "--lines", "8"]
    assert main([*args, "--no-correction", "--slow-mode", "ramp", "--name", "run-7"]) == 0
    out = capsys.readouterr().out
    assert "scanning" in out and "12 x 12 um at 3 lines/s, 8 lines" in out and "NO correction" in out
    request = next(c[1] for c in fake.calls if c[0] == "start_scan")
    assert request == ScanRequest(
        range_um=12, line_rate_hz=3, lines=8, correction=False, slow_mode="ramp", name="run-7"
    )
    assert request.model_fields_set == {
        "range_um",
        "line_rate_hz",
        "lines",
        "correction",
        "slow_mode",
        "name",
    }
    assert main(["ctl", "--api", spec, "change", "--rotation-deg", "30"]) == 0
    assert "rotated 30 deg" in capsys.readouterr().out
    assert main(["ctl", "--api", spec, "stop"]) == 0
    assert capsys.readouterr().out.startswith("fake-stage: idle")
    assert main(["ctl", "--api", spec, "move", "--x-um", "3", "--json", "-"]) == 0
    assert json.loads(capsys.readouterr().out)["position_um"]["x"] == 3


def test_ctl_refusal_is_one_line_exit_2(spec: str, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["ctl", "--api", spec, "scan", "--range-um", "100", "--line-rate-hz", "2"]) == 2
    err = capsys.readouterr().err
    assert err == (
        "piezod ctl: error: POST /v1/scan: range 100 um needs +/-250 V on x, "
        "beyond voltage_max_v 150 V (HTTP 422)\n"
    )
    assert main(["ctl", "--api", spec, "move", "--x-um", "1e6"]) == 2
    assert "x_um = 1e+06 is outside the limits" in capsys.readouterr().err


def test_ctl_recordings_and_fetch(spec: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["ctl", "--api", spec, "recordings"]) == 0
    assert capsys.readouterr().out.startswith("scan-001.csv  ")
    assert main(["ctl", "--api", spec, "--json", "-", "recordings"]) == 0
    assert json.loads(capsys.readouterr().out)["recordings"][0]["size_bytes"] == len(CSV)
    target = tmp_path / "got.csv"
    assert main(["ctl", "--api", spec, "fetch", "scan-001.csv", "-o", str(target)]) == 0
    assert target.read_text() == CSV
    assert f"wrote {target} ({len(CSV)} bytes)" in capsys.readouterr().out
    assert main(["ctl", "--api", spec, "fetch", "nope.csv", "-o", str(tmp_path / "n.csv")]) == 2
    assert "no recording named 'nope.csv' (HTTP 404)" in capsys.readouterr().err


def test_ctl_watch(spec: str, fake: FakeEngine, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["ctl", "--api", spec, "watch", "--rate-hz", "50", "--count", "2"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) == 2 and all(" idle " in line for line in lines)
    assert main(["ctl", "--api", spec, "watch", "--rate-hz", "50", "--count", "3", "--json", "-"]) == 0
    records = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    assert [r["event"] for r in records] == ["status"] * 3


# ---------------------------------------------------------------------------- load


def test_status_load_over_unix_socket(spec: str) -> None:
    """2 threads x 200 GET /v1/status over the Unix socket; prints requests per second."""
    threads, per_thread = 2, 200
    errors: list[BaseException] = []
    barrier = threading.Barrier(threads + 1)

    def hammer() -> None:
        try:
            with PiezodClient(spec) as c:
                c.status()  # connect outside the timed part
                barrier.wait()
                for _ in range(per_thread):
                    c.status()
        except BaseException as exc:
            errors.append(exc)
            barrier.abort()

    workers = [threading.Thread(target=hammer) for _ in range(threads)]
    for w in workers:
        w.start()
    barrier.wait()
    t0 = time.perf_counter()
    for w in workers:
        w.join(60)
    elapsed = time.perf_counter() - t0
    assert not errors
    rate = threads * per_thread / elapsed
    print(f"\nGET /v1/status over unix socket: {threads} threads x {per_thread}: {rate:.0f} req/s")
