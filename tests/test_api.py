"""The control API served over real sockets: status codes, socket security, SSE, recordings."""

from __future__ import annotations

import contextlib
import grp
import json
import logging
import os
import re
import signal
import socket
import stat
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest
from fake_engine import FakeEngine, running_api

from piezod.config import ApiConfig
from piezod.errors import ConfigError
from piezod.service.api import EventHub, create_app
from piezod.service.server import ApiServer, parse_api_spec

CSV = "# scanner: fake\nt,voltage,position\n0.0,0.0,0.0\n0.001,1.0,0.2\n"


def http(server: ApiServer, token: str | None = None) -> httpx.Client:
    headers = {"authorization": f"Bearer {token}"} if token else {}
    if server.spec.kind == "unix":
        transport = httpx.HTTPTransport(uds=server.spec.path)
        return httpx.Client(transport=transport, base_url="http://piezod", headers=headers, timeout=10)
    spec = parse_api_spec(server.address)
    return httpx.Client(base_url=f"http://{spec.host}:{spec.port}", headers=headers, timeout=10)


@pytest.fixture(scope="module")
def api(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[FakeEngine, ApiServer, httpx.Client]]:
    rec = tmp_path_factory.mktemp("api")
    (rec / "scan-001.csv").write_text(CSV)
    with running_api(rec) as (engine, server), http(server) as client:
        yield engine, server, client


@pytest.fixture
def fake(api: tuple[FakeEngine, ApiServer, httpx.Client]) -> FakeEngine:
    api[0].reset()
    return api[0]


@pytest.fixture
def client(api: tuple[FakeEngine, ApiServer, httpx.Client], fake: FakeEngine) -> httpx.Client:
    return api[2]


def sse_events(lines: Iterator[str]) -> Iterator[tuple[str, dict[str, object]]]:
    event, data = "", ""
    for line in lines:
        if line.startswith("event: "):
            event = line[7:]
        elif line.startswith("data: "):
            data = line[6:]
        elif line == "" and data:
            yield event, json.loads(data)
            event, data = "", ""


# ---------------------------------------------------------------------------- socket and listener


def test_unix_socket_mode_0660_group_and_removed_at_exit(tmp_path: Path) -> None:
    group = grp.getgrgid(os.getegid()).gr_name
    path = tmp_path / "api.sock"
    with running_api(tmp_path, api_config=ApiConfig(socket_group=group)) as (_, server):
        st = os.lstat(path)
        assert stat.S_ISSOCK(st.st_mode)
        assert stat.S_IMODE(st.st_mode) == 0o660
        assert st.st_gid == os.getegid()
        with http(server) as c:
            assert c.get("/v1/status").json()["state"] == "idle"
    assert not path.exists()


def test_unknown_socket_group_is_a_config_error(tmp_path: Path) -> None:
    app = create_app(FakeEngine(tmp_path))
    with pytest.raises(ConfigError, match=re.escape("api.socket_group: no group named 'no-such-group-xyz'")):
        ApiServer(app, f"unix:{tmp_path / 'a.sock'}", ApiConfig(socket_group="no-such-group-xyz"))


def test_stale_socket_removed_live_socket_and_other_files_refused(tmp_path: Path) -> None:
    path = tmp_path / "api.sock"
    stale = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    stale.bind(str(path))
    stale.close()  # a socket file nobody listens on, as a crashed daemon leaves it
    with running_api(tmp_path) as (_, server):
        second = ApiServer(create_app(FakeEngine(tmp_path)), f"unix:{path}")
        with pytest.raises(ConfigError, match="another server is listening"):
            second.start()
        with http(server) as c:  # the first one is untouched
            assert c.get("/v1/status").status_code == 200
    other = tmp_path / "not-a-socket"
    other.write_text("keep me")
    with pytest.raises(ConfigError, match="is not a socket; refusing"):
        ApiServer(create_app(FakeEngine(tmp_path)), f"unix:{other}").start()
    assert other.read_text() == "keep me"


@pytest.mark.parametrize(
    ("spec", "message"),
    [
        ("http://x", "expected unix:PATH or tcp:HOST:PORT"),
        ("unix:", "empty socket path"),
        ("unix:/" + "a" * 200, "longer than 107 bytes"),
        ("tcp:127.0.0.1", "expected tcp:HOST:PORT"),
        ("tcp:127.0.0.1:http", "port 'http' is not a number"),
        ("tcp:127.0.0.1:70000", "port '70000' is not a number in 0..65535"),
        ("tcp:::1:80", "put IPv6 addresses in brackets"),
        ("tcp:[zz]:80", "'zz' is not an IPv6 address"),
    ],
)
def test_parse_api_spec_errors(spec: str, message: str) -> None:
    with pytest.raises(ConfigError, match=re.escape(message)) as info:
        parse_api_spec(spec)
    assert "\n" not in str(info.value)


def test_parse_api_spec_forms() -> None:
    assert parse_api_spec("unix:/run/piezod/a.sock").path == "/run/piezod/a.sock"
    tcp = parse_api_spec("tcp:127.0.0.1:8765")
    assert (tcp.host, tcp.port, tcp.is_loopback) == ("127.0.0.1", 8765, True)
    v6 = parse_api_spec("tcp:[::1]:0")
    assert (v6.host, v6.is_loopback, str(v6)) == ("::1", True, "tcp:[::1]:0")
    assert not parse_api_spec("tcp:0.0.0.0:80").is_loopback
    assert not parse_api_spec("tcp:192.0.2.7:80").is_loopback


def test_tcp_loopback_needs_a_token_free_port_and_no_signal_handlers(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"a TCP listener needs api\.token_file"):
        ApiServer(create_app(FakeEngine(tmp_path)), "tcp:127.0.0.1:0", ApiConfig())
    token_file = tmp_path / "token"
    token_file.write_text("loopback-token\n")
    before = {sig: signal.getsignal(sig) for sig in (signal.SIGTERM, signal.SIGINT)}
    with running_api(tmp_path, "tcp:127.0.0.1:0", ApiConfig(token_file=str(token_file))) as (_, server):
        assert {sig: signal.getsignal(sig) for sig in before} == before  # the daemon owns them
        spec = parse_api_spec(server.address)
        assert spec.port > 0
        assert server.requires_token
        with http(server) as c:
            assert c.get("/v1/status").status_code == 401
        with http(server, token="loopback-token") as c:
            assert c.get("/v1/status").json()["scanner"] == "fake-stage"


@pytest.mark.parametrize("spec", ["tcp:0.0.0.0:0", "tcp:192.0.2.7:8765", "tcp:[::]:0"])
def test_non_loopback_tcp_refused_without_allow_remote(tmp_path: Path, spec: str) -> None:
    app = create_app(FakeEngine(tmp_path))
    with pytest.raises(ConfigError, match=re.escape("not a loopback address; set api.allow_remote")):
        ApiServer(app, spec, ApiConfig())


def test_token_required_when_allow_remote(tmp_path: Path) -> None:
    token_file = tmp_path / "token"
    token_file.write_text("s3cret-token\n")
    token_file.chmod(0o600)
    cfg = ApiConfig(allow_remote=True, token_file=str(token_file))
    # a non-loopback listener is accepted now, with the token
    assert ApiServer(create_app(FakeEngine(tmp_path)), "tcp:0.0.0.0:0", cfg).requires_token
    with running_api(tmp_path, "tcp:127.0.0.1:0", cfg) as (_, server):
        assert server.requires_token
        with http(server) as c:
            for path in ("/v1/status", "/openapi.json", "/v1/events?limit=1", "/v1/recordings"):
                r = c.get(path)
                assert r.status_code == 401, path
                assert r.headers["www-authenticate"] == "Bearer"
            r = c.post("/v1/stop", headers={"authorization": "Bearer s3cret-tokeN"})
            assert (r.status_code, r.json()["detail"]) == (401, "invalid bearer token")
        with http(server, token="s3cret-token") as c:
            assert c.get("/v1/status").status_code == 200
            assert c.post("/v1/stop").status_code == 200


def test_empty_token_file_refused(tmp_path: Path) -> None:
    token_file = tmp_path / "token"
    token_file.write_text("  \n")
    cfg = ApiConfig(allow_remote=True, token_file=str(token_file))
    with pytest.raises(ConfigError, match="token must be one non-empty word"):
        ApiServer(create_app(FakeEngine(tmp_path)), "tcp:127.0.0.1:0", cfg)


# ---------------------------------------------------------------------------- endpoints


def test_openapi_served(client: httpx.Client) -> None:
    doc = client.get("/openapi.json").json()
    assert doc["info"]["title"] == "piezod control API"
    assert "Unix socket" in doc["info"]["description"]
    paths = doc["paths"]
    assert set(paths) >= {
        "/v1/status",
        "/v1/scan",
        "/v1/stop",
        "/v1/move",
        "/v1/recordings",
        "/v1/recordings/{name}",
        "/v1/events",
    }
    assert set(paths["/v1/scan"]) == {"post", "patch"}
    assert "409" in paths["/v1/scan"]["post"]["responses"]
    assert "text/event-stream" in paths["/v1/events"]["get"]["responses"]["200"]["content"]
    assert "ScanRequest" in doc["components"]["schemas"]
    assert client.get("/docs").status_code == 200


def test_bad_body_is_422_naming_the_field(client: httpx.Client, fake: FakeEngine) -> None:
    r = client.post("/v1/scan", json={"range_um": -1, "line_rate_hz": 2})
    assert r.status_code == 422
    assert [e["loc"] for e in r.json()["detail"]] == [["body", "range_um"]]
    r = client.post("/v1/scan", json={"range_um": 5, "line_rate_hz": 2, "colour": "red"})
    assert r.status_code == 422 and r.json()["detail"][0]["loc"] == ["body", "colour"]
    r = client.post("/v1/scan", content=b"{not json", headers={"content-type": "application/json"})
    assert r.status_code == 422
    r = client.post("/v1/scan", json={"range_um": 5, "line_rate_hz": 2, "name": "../etc"})
    assert r.status_code == 422 and r.json()["detail"][0]["loc"] == ["body", "name"]
    assert not [c for c in fake.calls if c[0] == "start_scan"]


def test_scan_accepted_then_busy_then_changed_then_stopped(client: httpx.Client, fake: FakeEngine) -> None:
    r = client.post("/v1/scan", json={"range_um": 10, "line_rate_hz": 2, "lines": 32, "name": "a"})
    assert r.status_code == 202
    assert r.json()["state"] == "scanning" and r.json()["scan"]["lines"] == 32
    r = client.post("/v1/scan", json={"range_um": 10, "line_rate_hz": 2})
    assert r.status_code == 409
    assert r.json() == {
        "detail": "cannot start a scan: a scan is running; change it with PATCH /v1/scan or stop it first",
        "error": "EngineStateError",
    }
    r = client.patch("/v1/scan", json={"line_rate_hz": 4})
    assert r.status_code == 200 and r.json()["scan"]["line_rate_hz"] == 4
    r = client.patch("/v1/scan", json={"range_um": 500})  # the engine refuses
    assert r.status_code == 422 and r.json()["error"] == "RangeUnreachableError"
    assert client.patch("/v1/scan", json={}).status_code == 422
    assert client.post("/v1/move", json={"x_um": 1}).status_code == 409
    r = client.post("/v1/stop")
    assert r.status_code == 200 and r.json()["state"] == "idle"


def test_scan_out_of_limits_is_422_with_the_engine_reason(client: httpx.Client, fake: FakeEngine) -> None:
    r = client.post("/v1/scan", json={"range_um": 100, "line_rate_hz": 2})
    assert r.status_code == 422
    assert r.json() == {
        "detail": "range 100 um needs +/-250 V on x, beyond voltage_max_v 150 V",
        "error": "RangeUnreachableError",
    }
    assert [c[0] for c in fake.calls] == ["start_scan", "check_scan"] and fake.state == "idle"


def test_change_while_idle_is_409(client: httpx.Client, fake: FakeEngine) -> None:
    r = client.patch("/v1/scan", json={"range_um": 5})
    assert r.status_code == 409
    assert "the engine is idle" in r.json()["detail"]
    assert fake.calls == []


def test_fault_state_is_409_naming_the_fault_until_stop(client: httpx.Client, fake: FakeEngine) -> None:
    fake.inject_fault("underrun", "FIFO ran empty", push=False)
    r = client.post("/v1/scan", json={"range_um": 10, "line_rate_hz": 2})
    assert r.status_code == 409
    assert "in fault (board underrun: FIFO ran empty); POST /v1/stop" in r.json()["detail"]
    client.post("/v1/stop")
    assert client.post("/v1/scan", json={"range_um": 10, "line_rate_hz": 2}).status_code == 202


def test_move_limits_and_empty_move(client: httpx.Client, fake: FakeEngine) -> None:
    r = client.post("/v1/move", json={"x_um": 99})
    assert r.status_code == 422
    assert r.json() == {"detail": "x_um = 99 is outside the limits [-30, 30] um", "error": "SafetyError"}
    assert client.post("/v1/move", json={"speed_um_per_s": 5}).status_code == 422
    r = client.post("/v1/move", json={"x_um": 1.5, "y_um": -2})
    assert r.status_code == 202 and r.json()["position_um"] == {"x": 1.5, "y": -2.0, "z": 0.0}


def test_internal_errors_are_logged_but_not_leaked(
    client: httpx.Client, fake: FakeEngine, caplog: pytest.LogCaptureFixture
) -> None:
    fake.status_error = RuntimeError("secret internal state 0xdeadbeef")
    with caplog.at_level(logging.ERROR, logger="piezod.service.api"):
        r = client.get("/v1/status")
    assert r.status_code == 500
    assert r.json() == {
        "detail": "internal error in status (RuntimeError); see the daemon log",
        "error": "InternalError",
    }
    assert "deadbeef" not in r.text and "Traceback" not in r.text
    logged = [rec for rec in caplog.records if rec.exc_info]
    assert logged and "deadbeef" in str(logged[0].exc_info[1])  # type: ignore[index]


def test_bug_in_a_route_is_a_logged_500_and_the_connection_survives(
    client: httpx.Client, fake: FakeEngine, caplog: pytest.LogCaptureFixture, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(fake, "recordings", lambda: [{"bogus": 1}])  # breaks the response model
    with caplog.at_level(logging.ERROR, logger="piezod.service.api"):
        r = client.get("/v1/recordings")
    assert r.status_code == 500
    assert r.json() == {"detail": "internal error; see the daemon log", "error": "InternalError"}
    assert any(rec.exc_info and "GET /v1/recordings failed" in rec.getMessage() for rec in caplog.records)
    assert client.get("/v1/status").status_code == 200  # same keep-alive connection


@contextlib.contextmanager
def _scan_start_blocked(client: httpx.Client, fake: FakeEngine) -> Iterator[list[int]]:
    """A ``POST /v1/scan`` held inside the engine's ``start_scan`` for the block; its status code
    is in the yielded list afterwards."""
    fake.block_start = threading.Event()
    answer: list[int] = []
    waiter = threading.Thread(
        target=lambda: answer.append(
            client.post("/v1/scan", json={"range_um": 10, "line_rate_hz": 2}).status_code
        )
    )
    waiter.start()
    try:
        deadline = time.monotonic() + 10
        while not any(c[0] == "start_scan" for c in fake.calls) and time.monotonic() < deadline:
            time.sleep(0.005)
        assert waiter.is_alive()  # start_scan is blocked
        yield answer
    finally:
        fake.block_start.set()
        waiter.join(10)


def test_engine_calls_do_not_block_the_event_loop(client: httpx.Client, fake: FakeEngine) -> None:
    with _scan_start_blocked(client, fake) as answer:
        assert client.get("/v1/status").status_code == 200  # the API still answers
    assert answer == [202]


def test_one_scan_check_at_a_time_others_429_then_busy_is_409_without_a_check(
    client: httpx.Client, fake: FakeEngine
) -> None:
    """A scan check renders seconds of samples; concurrent ones are refused at once (429, nothing
    changed, retry), and a scan request while scanning is 409 before any check is computed."""
    with _scan_start_blocked(client, fake) as answer:
        r = client.patch("/v1/scan", json={"line_rate_hz": 4})
        assert r.status_code == 409  # not scanning yet: the state is checked first
        r = client.post("/v1/scan", json={"range_um": 5, "line_rate_hz": 2})
        assert r.status_code == 429 and r.headers["retry-after"] == "1"
        assert r.json()["error"] == "Busy" and "another scan is being checked" in r.json()["detail"]
    assert answer == [202]
    assert [c[1].range_um for c in fake.calls if c[0] == "check_scan"] == [10]
    fake.calls.clear()
    assert client.post("/v1/scan", json={"range_um": 5, "line_rate_hz": 2}).status_code == 409
    assert not fake.calls


# ---------------------------------------------------------------------------- recordings


def test_recordings_list_and_fetch(client: httpx.Client) -> None:
    (listed,) = client.get("/v1/recordings").json()
    assert listed["name"] == "scan-001.csv" and listed["size_bytes"] == len(CSV)
    r = client.get("/v1/recordings/scan-001.csv")
    assert r.status_code == 200
    assert r.text == CSV
    assert r.headers["content-type"].startswith("text/csv")
    assert r.headers["content-disposition"] == 'attachment; filename="scan-001.csv"'


def test_recording_being_written_is_served_in_whole_lines(client: httpx.Client, fake: FakeEngine) -> None:
    path = fake.recording_dir / "growing.csv"
    path.write_text("t,voltage,position\n0,0,0\n0.001,1.0,0.")
    try:
        r = client.get("/v1/recordings/growing.csv")
        assert r.status_code == 200
        assert r.text == "t,voltage,position\n0,0,0\n"
    finally:
        path.unlink()


@pytest.mark.parametrize(
    "name",
    [
        "nope.csv",
        "..%2F..%2Fetc%2Fpasswd",
        "%2E%2E",
        ".secret",
        "sub%2Fx.csv",
        "..",
        "link.csv",
        "a%00b",
    ],
)
def test_unknown_names_and_traversal_are_404(client: httpx.Client, fake: FakeEngine, name: str) -> None:
    outside = fake.recording_dir.parent / "outside-secret.txt"
    outside.write_text("TOP SECRET")
    (fake.recording_dir / ".secret").write_text("TOP SECRET")
    link = fake.recording_dir / "link.csv"
    link.unlink(missing_ok=True)
    link.symlink_to(outside)
    try:
        r = client.get(f"/v1/recordings/{name}")
        assert r.status_code == 404
        assert "TOP SECRET" not in r.text
    finally:
        link.unlink()
        (fake.recording_dir / ".secret").unlink()


# ---------------------------------------------------------------------------- events


def test_sse_delivers_status_events_then_closes(client: httpx.Client) -> None:
    with client.stream("GET", "/v1/events", params={"limit": 3, "rate_hz": 50}) as r:
        assert r.headers["content-type"].startswith("text/event-stream")
        events = list(sse_events(r.iter_lines()))
    assert [e for e, _ in events] == ["status"] * 3
    uptimes = [float(str(d["uptime_s"])) for _, d in events]
    assert uptimes == sorted(uptimes) and uptimes[0] < uptimes[-1]


def test_sse_rate_is_validated(client: httpx.Client) -> None:
    r = client.get("/v1/events", params={"rate_hz": 1000})
    assert r.status_code == 422 and r.json()["detail"][0]["loc"] == ["query", "rate_hz"]


def test_sse_pushed_fault_arrives_before_the_next_status(client: httpx.Client, fake: FakeEngine) -> None:
    with client.stream("GET", "/v1/events", params={"rate_hz": 0.2}) as r:
        events = sse_events(r.iter_lines())
        assert next(events)[0] == "status"
        fake.inject_fault("watchdog", "heartbeat lost")
        kind, data = next(events)  # the next status is 5 s away: only the push can arrive now
        assert kind == "fault"
        assert (data["code"], data["message"]) == ("watchdog", "heartbeat lost")


def test_sse_fault_seen_only_in_status_is_reported_once(client: httpx.Client, fake: FakeEngine) -> None:
    with client.stream("GET", "/v1/events", params={"rate_hz": 50, "limit": 4}) as r:
        events = sse_events(r.iter_lines())
        assert next(events)[0] == "status"
        fake.inject_fault("underrun", "FIFO ran empty", push=False)
        rest = list(events)
    kinds = [k for k, _ in rest]
    assert kinds.count("fault") == 1 and kinds.count("status") == 3
    assert kinds.index("fault") < len(kinds) - 1  # reported with the status that showed it


def test_sse_engine_failure_ends_the_stream_with_an_error_event(
    client: httpx.Client, fake: FakeEngine
) -> None:
    fake.status_error = RuntimeError("boom")
    with client.stream("GET", "/v1/events") as r:
        events = list(sse_events(r.iter_lines()))
    assert events == [("error", {"detail": "engine status failed (RuntimeError)", "error": "InternalError"})]


def test_sse_client_disconnect_ends_the_stream(
    api: tuple[FakeEngine, ApiServer, httpx.Client], fake: FakeEngine
) -> None:
    _, server, client = api
    hub = server._app.state.events  # type: ignore[attr-defined]
    assert isinstance(hub, EventHub)
    with client.stream("GET", "/v1/events", params={"rate_hz": 20}) as r:
        events = sse_events(r.iter_lines())  # kept: dropping it would close the connection early
        next(events)
        assert hub.subscribers == 1
    deadline = time.monotonic() + 10
    while hub.subscribers and time.monotonic() < deadline:
        time.sleep(0.01)
    assert hub.subscribers == 0


def test_server_stop_ends_open_streams(tmp_path: Path) -> None:
    with running_api(tmp_path, rate_hz=20) as (_, server), http(server) as c:
        got: list[str] = []
        opened = threading.Event()

        def follow() -> None:
            with c.stream("GET", "/v1/events") as r:
                for kind, _ in sse_events(r.iter_lines()):
                    got.append(kind)
                    opened.set()

        reader = threading.Thread(target=follow)
        reader.start()
        assert opened.wait(10)
        server.stop()
        reader.join(10)
        assert not reader.is_alive()  # the stream ended, not hung
        assert not server.running
        assert got and set(got) == {"status"}
        assert not (tmp_path / "api.sock").exists()
