"""Settings (validation, env parsing, limits), the settings table in docs/SERVICE.md, and the
deployment files (docker-compose.yml services/profiles/env names against Settings)."""

from __future__ import annotations

import os
import re

import pytest
from pydantic import ValidationError

from pbrsr_core.limits import Limits
from pbrsr_jobs.settings import Settings
from tests.service_support import REPO

ENV_NAMES = {f"PBRSR_{name.upper()}" for name in Settings.model_fields}


def test_defaults_match_limits_and_env_is_read(monkeypatch, tmp_path):
    for key in list(os.environ):
        if key.startswith("PBRSR_"):
            monkeypatch.delenv(key)
    assert Settings().limits() == Limits()  # one set of defaults
    monkeypatch.setenv("PBRSR_API_KEYS", " alpha-0123456789abcdef , ,bravo-0123456789abcdef")
    monkeypatch.setenv("PBRSR_CORS_ORIGINS", "https://a.example,http://b.example:8080")
    monkeypatch.setenv("PBRSR_PRELOAD_PRIORS", "")
    monkeypatch.setenv("PBRSR_DEVICE", "CUDA:1")
    monkeypatch.setenv("PBRSR_MAX_UPLOAD_MB", "1.5")
    monkeypatch.setenv("PBRSR_STORAGE_DIR", str(tmp_path / "s"))
    s = Settings()
    assert s.api_keys == ["alpha-0123456789abcdef", "bravo-0123456789abcdef"]
    assert s.auth_enabled
    assert s.cors_origins == ["https://a.example", "http://b.example:8080"]
    assert s.preload_priors == []
    assert s.device == "cuda:1"
    assert s.limits().max_file_bytes == int(1.5 * 1024 * 1024)
    assert s.prepare_storage() == tmp_path / "s"
    assert (tmp_path / "s" / "jobs").is_dir()


@pytest.mark.parametrize(
    "field, value, words",
    [
        ("device", "tpu", "cuda:N"),
        ("redis_url", "http://localhost:6379", "redis://"),
        ("api_keys", "short", "16 characters"),
        ("cors_origins", "example.com", "http"),
        ("queue", "bad name!", "letters"),
        ("retention_hours", "0", "greater than 0"),
        ("log_level", "chatty", "DEBUG"),
    ],
)
def test_bad_values_are_refused_with_the_reason(monkeypatch, field, value, words):
    monkeypatch.setenv(f"PBRSR_{field.upper()}", value)
    with pytest.raises(ValidationError) as info:
        Settings()
    assert words in str(info.value)


def test_unwritable_storage_is_refused(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    with pytest.raises(ValueError, match="PBRSR_STORAGE_DIR"):
        Settings(storage_dir=blocker / "sub").prepare_storage()


def test_docs_table_lists_every_setting():
    text = (REPO / "docs" / "SERVICE.md").read_text()
    documented = set(re.findall(r"^\| `(PBRSR_[A-Z0-9_]+)` \|", text, flags=re.M))
    assert documented == ENV_NAMES


def test_compose_file_matches_settings():
    yaml = pytest.importorskip("yaml", reason="PyYAML is needed to parse docker-compose.yml")
    doc = yaml.safe_load((REPO / "docker-compose.yml").read_text())
    services = doc["services"]
    assert {"redis", "api", "worker-cpu", "worker-gpu"} <= services.keys()
    assert services["worker-gpu"]["profiles"] == ["gpu"]
    assert "profiles" not in services["worker-cpu"] and "profiles" not in services["api"]
    gpu = services["worker-gpu"]["deploy"]["resources"]["reservations"]["devices"][0]
    assert gpu["driver"] == "nvidia" and "gpu" in gpu["capabilities"]
    assert services["api"]["command"][:2] == ["pbrsr", "serve"]
    for name in ("worker-cpu", "worker-gpu"):
        assert services[name]["command"] == ["pbrsr", "worker"]
    for name in ("api", "worker-cpu", "worker-gpu"):
        env = services[name]["environment"]
        unknown = {k for k in env if k.startswith("PBRSR_")} - ENV_NAMES
        assert not unknown, f"{name}: {unknown} are not Settings fields"
        assert env["PBRSR_REDIS_URL"].startswith("redis://redis:")
        Settings(
            **{
                k[6:].lower(): v
                for k, v in env.items()  # values validate
                if k.startswith("PBRSR_") and "${" not in str(v)
            }
        )
        # all share the storage volume at PBRSR_STORAGE_DIR
        assert f"storage:{env['PBRSR_STORAGE_DIR']}" in services[name]["volumes"]
    assert services["worker-cpu"]["environment"]["PBRSR_DEVICE"] == "cpu"
    assert services["worker-gpu"]["environment"]["PBRSR_DEVICE"].startswith("cuda")
    assert "storage" in doc["volumes"]


def test_compose_s3_override_switches_every_pbrsr_service_to_its_bucket():
    yaml = pytest.importorskip("yaml", reason="PyYAML is needed to parse the compose files")
    base = yaml.safe_load((REPO / "docker-compose.yml").read_text())["services"]
    s3 = yaml.safe_load((REPO / "deploy" / "docker-compose.s3.yml").read_text())["services"]
    bucket = s3["api"]["environment"]["PBRSR_S3_BUCKET"]
    assert s3["minio-init"]["command"][0].endswith(f"mc mb --ignore-existing local/{bucket}")
    for name in ("api", "worker-cpu", "worker-gpu"):
        assert name in base
        env = {**base[name]["environment"], **s3[name]["environment"]}
        assert {k for k in env if k.startswith("PBRSR_")} <= ENV_NAMES
        merged = Settings(
            _env_file=None,
            **{
                k[6:].lower(): v for k, v in env.items() if k.startswith("PBRSR_") and "${" not in v
            },
        )
        assert merged.storage_backend == "s3" and merged.s3_endpoint_url == "http://minio:9000"
        assert s3[name]["depends_on"]["minio-init"]["condition"] == "service_completed_successfully"


def test_dockerfile_has_cpu_default_and_cuda_arg():
    text = (REPO / "deploy" / "Dockerfile").read_text()
    assert re.search(r"^ARG TORCH_INDEX=https://download\.pytorch\.org/whl/cpu$", text, re.M)
    assert "torch==2.13.0" in text  # the version pyproject pins
    assert 'CMD ["pbrsr", "serve"' in text
    assert 'RUN pip install ".[service]"' in text  # the core and the service extra
    for package in ("pbrsr_core", "pbrsr_jobs", "service", "worker"):
        assert f"COPY {package} ./{package}" in text
    env_names = set(re.findall(r"\b(PBRSR_[A-Z_]+)=", text))
    assert env_names <= ENV_NAMES
