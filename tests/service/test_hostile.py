"""Every case of the hostile-input corpus (tests/hostile.py), uploaded through the API: each
gets its typed error as a 4xx problem body, nothing is stored and nothing is queued.
Also: zip uploads that are bombs or escape their folder, and zip entries the asset does not use
(never unpacked)."""

from __future__ import annotations

import io
import zipfile
from pathlib import Path

import pytest
from fastapi.testclient import TestClient
from rq import Queue

from pbrsr_core.limits import Limits
from pbrsr_jobs.store import JobLayout
from service.app import create_app
from tests.hostile import gltf_using, hostile_cases, zip_with_zeros
from tests.service_support import cleanup_redis, make_settings, post_asset, redis_client

MB = 1024 * 1024


def _settings_for(tmp_path: Path, limits: Limits):
    return make_settings(
        tmp_path,
        max_upload_mb=limits.max_file_bytes / MB,
        max_triangles=limits.max_triangles,
        max_texture_dim=limits.max_texture_dim,
        max_output_dim=limits.max_output_dim,
        max_data_uri_mb=limits.max_data_uri_bytes / MB,
        max_zip_entries=limits.max_zip_entries,
        max_unpacked_mb=limits.max_unpacked_bytes / MB,
        max_compression_ratio=limits.max_compression_ratio,
    )


def _payload(path: Path) -> tuple[bytes, str]:
    """The case's file, or a zip of its folder when it has files beside it."""
    files = [p for p in path.parent.rglob("*") if p.is_file()]
    if files == [path]:
        return path.read_bytes(), path.name
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        for p in sorted(files):
            zf.write(p, p.relative_to(path.parent).as_posix())
    return buf.getvalue(), "case.zip"


def _check_problem(resp, status: int, code: str, label: str, storage: Path) -> None:
    assert resp.status_code == status, f"{label}: {resp.status_code} {resp.text}"
    assert resp.headers["content-type"].startswith("application/problem+json"), label
    body = resp.json()
    assert body["code"] == code, f"{label}: {body}"
    # no server paths (a uri the user wrote into their own file may be quoted back)
    assert "Traceback" not in resp.text and str(storage) not in resp.text, label
    assert str(Path(__file__).parents[2]) not in resp.text, label


def test_hostile_corpus_through_the_api(tmp_path):
    cases = hostile_cases(tmp_path / "corpus")
    assert len(cases) >= 20
    by_limits: dict[Limits, list] = {}
    for case in cases:
        by_limits.setdefault(case.limits, []).append(case)
    for n, (limits, group) in enumerate(by_limits.items()):
        settings = _settings_for(tmp_path / f"s{n}", limits)
        try:
            with TestClient(create_app(settings), raise_server_exceptions=False) as c:
                for case in group:
                    data, name = _payload(case.path)
                    options = {"method": "bicubic", "unwrap_missing_uvs": case.unwrap}
                    resp = post_asset(c, data, filename=name, options=options)
                    _check_problem(
                        resp,
                        case.error.http_status,
                        case.error.code,
                        case.name,
                        settings.storage_dir,
                    )
                    if case.says:
                        assert case.says.lower() in resp.json()["detail"].lower(), case.name
            assert list((settings.storage_dir / "jobs").iterdir()) == []
            assert list((settings.storage_dir / "uploads").iterdir()) == []
            assert Queue(settings.queue, connection=redis_client()).count == 0
        finally:
            cleanup_redis(settings)


def _zip(entries: dict[str, bytes], symlink: str | None = None) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as zf:
        for name, data in entries.items():
            zf.writestr(name, data)
        if symlink:
            info = zipfile.ZipInfo(symlink)
            info.external_attr = 0o120777 << 16  # a symlink entry
            zf.writestr(info, "/etc/passwd")
    return buf.getvalue()


@pytest.mark.parametrize(
    "label, entries, symlink, status",
    [
        ("zip slip", {"../evil.gltf": b"{}"}, None, 400),
        ("absolute entry", {"/abs/evil.gltf": b"{}"}, None, 400),
        ("symlink entry", {"a.gltf": b"{}"}, "link.png", 400),
        ("no asset inside", {"readme.txt": b"hello"}, None, 400),
        ("zip bomb", {"a.gltf": gltf_using("pad.bin"), "pad.bin": b"\0" * (3 * MB)}, None, 413),
    ],
)
def test_hostile_zips(tmp_path, label, entries, symlink, status):
    settings = make_settings(tmp_path, max_unpacked_mb=1)
    try:
        with TestClient(create_app(settings), raise_server_exceptions=False) as c:
            resp = post_asset(c, _zip(entries, symlink), filename="x.zip")
            assert resp.status_code == status, f"{label}: {resp.text}"
            assert resp.headers["content-type"].startswith("application/problem+json")
        assert not (tmp_path.parent / "evil.gltf").exists()
        assert list((settings.storage_dir / "jobs").iterdir()) == []
    finally:
        cleanup_redis(settings)


def test_over_long_uri_is_unprocessable(tmp_path):
    case = next(c for c in hostile_cases(tmp_path / "corpus") if c.name == "uri_too_long")
    settings = make_settings(tmp_path)
    try:
        with TestClient(create_app(settings), raise_server_exceptions=False) as c:
            resp = post_asset(c, case.path.read_bytes(), filename="a.gltf")
        _check_problem(resp, 422, "unprocessable-asset", case.name, settings.storage_dir)
        assert "name is too long" in resp.json()["detail"]
        assert len(resp.json()["detail"]) < 300  # the name is cut, its length said
        assert list((settings.storage_dir / "jobs").iterdir()) == []
    finally:
        cleanup_redis(settings)


def test_zip_entry_over_the_compression_ratio_is_413_and_leaves_nothing(tmp_path):
    settings = make_settings(tmp_path)
    try:
        with TestClient(create_app(settings), raise_server_exceptions=False) as c:
            z = zip_with_zeros(tmp_path / "z", 10 * MB, used=True)
            resp = post_asset(c, z.read_bytes(), filename="asset.zip")
        _check_problem(resp, 413, "limit-exceeded", "ratio", settings.storage_dir)
        detail = resp.json()["detail"]
        assert "'model/zeros.bin'" in detail and "the limit is 200:1" in detail, detail
        assert list((settings.storage_dir / "jobs").iterdir()) == []
        assert list((settings.storage_dir / "uploads").iterdir()) == []
        assert Queue(settings.queue, connection=redis_client()).count == 0
    finally:
        cleanup_redis(settings)


def test_zip_entry_the_asset_does_not_use_is_never_unpacked(tmp_path):
    # 64 MiB of zeros that nothing references: accepted under a 1 MiB unpacked limit
    settings = make_settings(tmp_path, max_unpacked_mb=1)
    try:
        with TestClient(create_app(settings), raise_server_exceptions=False) as c:
            z = zip_with_zeros(tmp_path / "z", 64 * MB, used=False)
            options = {"method": "bicubic"}
            resp = post_asset(c, z.read_bytes(), filename="asset.zip", options=options)
        assert resp.status_code == 202, resp.text
        input_dir = JobLayout(settings.storage_dir).job_dir(resp.json()["id"]) / "input"
        stored = sorted(p.relative_to(input_dir).as_posix() for p in input_dir.rglob("*"))
        assert stored == ["model", "model/asset.gltf", "model/base_color.png", "model/quad.bin"]
        assert not list(settings.storage_dir.rglob("zeros.bin"))
    finally:
        cleanup_redis(settings)
