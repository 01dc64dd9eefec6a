"""Hostile and malformed API requests against the real daemon (issue #13 items 2, 6, 8).

``piezod serve`` runs on the real simulator over a pty, scanning; a raw HTTP client sends what a
hostile or broken client would. Every refusal is a one-line 4xx, answered without the engine, and
changes nothing: the scan keeps running with no underrun, and the daemon log holds no traceback.
"""

from __future__ import annotations

import json
import os
import secrets
import socket
import stat
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest
import yaml
from real_daemon import RealDaemon

from piezod.config import ApiConfig, default_sim_config_path
from piezod.errors import ConfigError
from piezod.service.api import create_app
from piezod.service.daemon import default_api_spec
from piezod.service.guards import MAX_BODY_BYTES
from piezod.service.server import ApiServer, private_dir


@pytest.fixture(scope="module")
def scanning(tmp_path_factory: pytest.TempPathFactory) -> Iterator[RealDaemon]:
    tmp = tmp_path_factory.mktemp("hostile")
    with RealDaemon(tmp) as d:
        with d.client() as c:
            c.scan(range_um=10.0, line_rate_hz=2.0, lines=64, frames=0, name="steady")
        d.wait_state({"scanning"}, 10.0)
        yield d


def raw(d: RealDaemon) -> httpx.Client:
    return httpx.Client(
        transport=httpx.HTTPTransport(uds=str(d.socket)), base_url="http://piezod", timeout=30.0
    )


def _post(d: RealDaemon, path: str, content: bytes, headers: dict[str, str] | None = None) -> httpx.Response:
    h = {"content-type": "application/json", **(headers or {})}
    with raw(d) as c:
        return c.post(path, content=content, headers=h)


def _unchanged(d: RealDaemon, underruns_before: int) -> None:
    st = d.status()
    assert st.state == "scanning", st.faults[-3:]
    assert st.scan is not None and st.scan.range_um == 10.0 and st.scan.name == "steady"
    assert st.underruns == underruns_before


@pytest.mark.parametrize(
    "body",
    [
        b'{"range_um": NaN, "line_rate_hz": 1}',
        b'{"range_um": Infinity, "line_rate_hz": 1}',
        b'{"range_um": -Infinity}',
        b'{"range_um": 5, "range_um": 500}',
        b'{"range_um": [[[[[[1]]]]]]}',
        b"[" * 5000 + b"]" * 5000,
        b'{"range_um": 5',
        json.dumps({f"k{i}": i for i in range(1000)}).encode(),
    ],
    ids=["nan", "inf", "-inf", "duplicate", "deep", "very-deep", "truncated", "1000-keys"],
)
def test_malformed_json_is_a_one_line_4xx_and_changes_nothing(scanning: RealDaemon, body: bytes) -> None:
    """Tried: API bodies with NaN, ±Infinity, duplicate keys, 1000 keys, 5000-deep nesting, truncated JSON,
    to PATCH/POST scan and move while scanning. Held: 413/422 with one line each; the scan, its settings
    and the underrun count unchanged; no traceback logged.
    """
    before = scanning.status().underruns
    for method, path in (("PATCH", "/v1/scan"), ("POST", "/v1/move"), ("POST", "/v1/scan")):
        with raw(scanning) as c:
            r = c.request(method, path, content=body, headers={"content-type": "application/json"})
        assert 400 <= r.status_code < 500, (path, r.status_code, r.text[:200])
        assert r.status_code in (413, 422)
        assert len(r.content) < 4096
    _unchanged(scanning, before)
    assert "Traceback" not in scanning.log_text()


def test_huge_bodies_are_refused_before_they_are_read(scanning: RealDaemon) -> None:
    """Tried: a 3.4 MB body of 150k unknown keys; a 32 MB chunked body without Content-Length. Held: 413
    before the body is read (16 KiB limit); the scan unchanged, no underrun.
    """
    before = scanning.status().underruns
    many_keys = json.dumps({f"unknown_key_{i}": i for i in range(150_000)}).encode()  # ~3.4 MB
    t0 = time.monotonic()
    r = _post(scanning, "/v1/move", many_keys)
    assert r.status_code == 413 and str(MAX_BODY_BYTES) in r.json()["detail"]

    def chunks() -> Iterator[bytes]:  # no Content-Length: counted as it arrives
        for _ in range(2000):
            yield b" " * 16384

    with raw(scanning) as c:
        r = c.post("/v1/scan", content=chunks(), headers={"content-type": "application/json"})
    assert r.status_code == 413
    assert time.monotonic() - t0 < 30.0  # generous: the point is "not 3 s of parsing per request"
    _unchanged(scanning, before)


def test_cross_site_and_rebinding_requests_are_refused(scanning: RealDaemon) -> None:
    """Tried: a cross-site text/plain POST /v1/stop with Origin evil.example; form and text/plain bodies;
    Host evil.example (DNS rebinding); Origin null. Held: 403/415; the scan keeps running.
    """
    before = scanning.status().underruns
    # a web page's "simple" POST: text/plain, no preflight
    r = _post(scanning, "/v1/stop", b"{}", {"content-type": "text/plain", "origin": "http://evil.example"})
    assert r.status_code == 403
    r = _post(scanning, "/v1/stop", b"x=1", {"content-type": "application/x-www-form-urlencoded"})
    assert r.status_code == 415
    r = _post(scanning, "/v1/stop", b"{}", {"content-type": "text/plain"})
    assert r.status_code == 415
    # DNS rebinding: evil.example resolved to the daemon, the Host header still says evil.example
    for path in ("/v1/status", "/v1/stop"):
        with raw(scanning) as c:
            r = c.request("GET" if "status" in path else "POST", path, headers={"host": "evil.example"})
        assert r.status_code == 403, path
    r = _post(scanning, "/v1/stop", b"", {"origin": "null"})
    assert r.status_code == 403
    _unchanged(scanning, before)


def test_unknown_fields_and_bad_values_are_named(scanning: RealDaemon) -> None:
    """Tried: an unknown field, a negative range. Held: 422 naming the field; nothing changed."""
    before = scanning.status().underruns
    r = _post(scanning, "/v1/move", json.dumps({"x_um": 1, "colour": "red"}).encode())
    assert r.status_code == 422 and r.json()["detail"][0]["loc"] == ["body", "colour"]
    r = _post(scanning, "/v1/scan", json.dumps({"range_um": -1, "line_rate_hz": 1}).encode())
    assert r.status_code == 422 and r.json()["detail"][0]["loc"] == ["body", "range_um"]
    _unchanged(scanning, before)


def test_a_dangling_symlink_in_the_recordings_is_not_listed(scanning: RealDaemon) -> None:
    """Tried: a dangling *.csv symlink in the recording directory. Held: listing answers 200 without it;
    fetching it is 404.
    """
    link = scanning.recordings / "gone.csv"
    link.symlink_to(scanning.recordings / "does-not-exist.csv")
    try:
        with scanning.client() as c:
            names = [r.name for r in c.recordings()]
        assert "gone.csv" not in names and "steady.csv" in names
        with raw(scanning) as c:
            assert c.get("/v1/recordings/gone.csv").status_code == 404
    finally:
        link.unlink()


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def test_tcp_needs_a_token_and_wrong_tokens_are_throttled(tmp_path: Path) -> None:
    """Tried: --api tcp: without a token file; 60 wrong bearer tokens in a row; the right token with Host
    evil.example. Held: exit 2 with one line before the board is touched; failures delayed and then 429,
    at most one log line per 10 s; the right token answered at once; 403 for the foreign Host.
    """
    port = _free_port()
    # without api.token_file the daemon refuses to listen on TCP: one line, exit 2
    proc = subprocess.run(
        [sys.executable, "-m", "piezod", "serve", "--sim", "--api", f"tcp:127.0.0.1:{port}"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 2 and "needs api.token_file" in proc.stderr, proc.stderr
    assert proc.stderr.strip().count("\n") == 0
    token = secrets.token_hex(16)
    (tmp_path / "token").write_text(token + "\n")
    (tmp_path / "token").chmod(0o600)
    cfg = yaml.safe_load(default_sim_config_path().read_text())
    cfg["api"] = {"token_file": str(tmp_path / "token")}
    (tmp_path / "stage.yaml").write_text(yaml.safe_dump(cfg))
    api = f"tcp:127.0.0.1:{port}"
    with RealDaemon(tmp_path, config=tmp_path / "stage.yaml", api=api, token=token) as d:
        base = f"http://127.0.0.1:{port}"
        codes: dict[int, int] = {}
        t0 = time.monotonic()
        with httpx.Client(base_url=base, timeout=30.0) as c:
            assert c.get("/v1/status").status_code == 401
            for i in range(60):
                r = c.post("/v1/stop", headers={"authorization": f"Bearer wrong-{i}"})
                codes[r.status_code] = codes.get(r.status_code, 0) + 1
            elapsed = time.monotonic() - t0
            # the right token is never held back
            r = c.get("/v1/status", headers={"authorization": f"Bearer {token}"})
            assert r.status_code == 200
            # a rebinding page cannot use the listener either
            r = c.get("/v1/status", headers={"authorization": f"Bearer {token}", "host": "evil.example"})
            assert r.status_code == 403
        assert set(codes) <= {401, 429} and codes.get(429, 0) > 0, codes
        assert elapsed > 3.0, f"60 wrong tokens took only {elapsed:.2f} s: not throttled"
        refusals = [line for line in d.log_text().splitlines() if "API request refused" in line]
        assert 1 <= len(refusals) <= 1 + int(elapsed / 10.0) + 1, refusals
        with d.client() as c:
            assert c.status().state == "idle"


def test_the_socket_directory_must_be_ours(tmp_path: Path) -> None:
    """Tried: a socket directory with mode 0777, owned by another user, or a symlink (the /tmp/piezod-<uid>
    fallback included). Held: refused with the owner/mode and what to do; only a 0700 directory of the
    daemon's user is used.
    """
    mine = private_dir(tmp_path / "fresh")
    assert stat.S_IMODE(os.lstat(mine).st_mode) == 0o700
    loose = tmp_path / "loose"
    loose.mkdir()
    loose.chmod(0o777)
    with pytest.raises(ConfigError, match="lets other users in"):
        private_dir(loose)
    other = tmp_path / "other"
    other.mkdir(mode=0o700)
    if os.geteuid() == 0:
        os.chown(other, 65534, 65534)
        with pytest.raises(ConfigError, match="owned by uid 65534"):
            private_dir(other)
    (tmp_path / "target").mkdir(mode=0o700)
    (tmp_path / "sym").symlink_to(tmp_path / "target")
    with pytest.raises(ConfigError, match="not a directory"):
        private_dir(tmp_path / "sym")
    # the daemon's fallback /tmp/piezod-<uid>: an impostor's directory is refused
    impostor = tmp_path / f"piezod-{os.geteuid()}"
    impostor.mkdir()
    impostor.chmod(0o777)
    with pytest.raises(ConfigError, match="lets other users in"):
        default_api_spec("stage", run_dir=tmp_path / "no-run", tmp_root=tmp_path, runtime_dir=None)
    impostor.chmod(0o700)
    assert default_api_spec("stage", run_dir=tmp_path / "no-run", tmp_root=tmp_path, runtime_dir=None) == (
        f"unix:{impostor / 'stage.sock'}"
    )
    with pytest.raises(ConfigError, match=r"needs api\.token_file"):
        ApiServer(create_app(object()), "tcp:127.0.0.1:0", ApiConfig())  # type: ignore[arg-type]
