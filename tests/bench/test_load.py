"""``pbrsr bench load`` on a short run: real API and worker processes on loopback with a
private Redis; zero errors in every phase and every submitted job finished."""

from __future__ import annotations

import json
import time

import pytest

from pbrsr_bench.load import Recorder, big_payload, print_table, run
from tests.service_support import require_redis_server

pytestmark = pytest.mark.slow


def test_recorder_percentiles_and_throughput():
    rec = Recorder()
    for i in range(1, 101):
        rec.ok("get", i / 1000.0)
    rec.error("get", "HTTP 500")
    rec.ok("up", 2.0, nbytes=4 * 1024 * 1024)
    rec.ok("up", 1.0, nbytes=4 * 1024 * 1024)
    s = rec.summary(wall_s=10.0)
    assert s["get"]["requests"] == 101 and s["get"]["errors"] == 1
    assert s["get"]["p50_ms"] == pytest.approx(50.5)
    assert s["get"]["p99_ms"] == pytest.approx(99.01)
    assert s["get"]["per_s"] == pytest.approx(10.1)
    assert s["up"]["mb_per_s_total"] == pytest.approx(0.8)
    assert s["up"]["mb_per_s_each_p50"] == pytest.approx(3.0)


def test_big_payload_is_a_valid_asset_of_the_requested_size(tmp_path):
    from pbrsr_core.asset import load_asset

    name, data = big_payload(tmp_path, 1.5)
    assert 1.4 < len(data) / 2**20 < 1.7
    (tmp_path / "check.glb").write_bytes(data)
    asset = load_asset(tmp_path / "check.glb")
    assert max(im.width for im in asset.images) >= 700


def test_short_load_run_has_no_errors_and_drains_every_job(tmp_path, capsys):
    require_redis_server()
    t0 = time.monotonic()
    result = run(
        tmp_path / "out",
        duration=4,
        baseline=1.5,
        pollers=5,
        uploaders=2,
        upload_mb=1,
        big_uploads=2,
        jobs=6,
        workers=2,
        drain_timeout=90,
    )
    elapsed = time.monotonic() - t0
    assert result["config"]["private_redis"] is True
    mixed = result["mixed"]
    assert mixed["errors"] == 0, mixed["error_samples"]
    for kind in ("get_job", "list_jobs", "healthz", "upload"):
        row = mixed["kinds"][kind]
        assert row["requests"] > 0 and row["errors"] == 0
        assert 0 < row["p50_ms"] <= row["p99_ms"] <= row["max_ms"]
    assert result["poll_only"]["errors"] == 0
    assert set(result["poll_only"]["kinds"]) == {"get_job", "list_jobs", "healthz"}
    # each status read as a multiple of /healthz's p50 in the same phase, with its target
    ratios = {(r["request"], r["phase"]): r for r in result["ratios"]}
    assert set(ratios) == {(k, p) for k in ("get_job", "list_jobs") for p in ("poll_only", "mixed")}
    for (kind, phase), r in ratios.items():
        kinds = result[phase]["kinds"]
        want = kinds[kind]["p50_ms"] / kinds["healthz"]["p50_ms"]
        assert r["ratio"] == pytest.approx(want, rel=0.01, abs=0.006)  # kept to 2 decimals
        assert r["met"] == (r["ratio"] <= r["target"])
    assert result["big"]["errors"] == 0 and result["big"]["kinds"]["big_upload"]["requests"] == 2
    assert result["cleanup"]["errors"] == 0
    drain = result["drain"]
    assert drain["submitted"] == drain["finished"] == 6, drain["states"]
    assert drain["workers_alive"] == 2
    # every job's events on its own stream, the key's stream and by signed webhook
    events = drain["events"]
    assert events["jobs"] == 6 and events["lost"] == 0 and events["bad_signatures"] == 0
    channels = events["channels"]
    assert set(channels) == {"sse_job", "sse_key", "webhook"}
    assert channels["webhook"]["events"] == 6 * 3  # queued, started, succeeded
    assert channels["webhook"]["duplicates"] == 0
    assert channels["sse_key"]["events"] >= 6 * 3 and channels["sse_job"]["events"] >= 6 * 3
    for c in channels.values():
        assert c["lost"] == 0 and c["timed"] > 0
        assert 0 < c["p50_ms"] <= c["p99_ms"] <= c["max_ms"]
    assert channels["sse_key"]["timed"] == channels["sse_key"]["events"]  # open from the start
    assert result["ok"] is True
    saved = json.loads((tmp_path / "out" / "load.json").read_text())
    assert saved["drain"]["finished"] == 6 and saved["ok"] is True
    assert (tmp_path / "out" / "load.png").stat().st_size > 1000
    print_table(result)
    assert "PASS" in capsys.readouterr().out
    assert elapsed < 120
