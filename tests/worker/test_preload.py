"""The worker preloads the default prior, and a job on the default prior reuses that instance."""

from __future__ import annotations

import re

import torch

from pbrsr_core.device import resolve_device
from pbrsr_core.options import DEFAULT_PRIOR
from pbrsr_core.prior import registry
from pbrsr_core.prior.registry import clear_cache, load_prior
from pbrsr_jobs.settings import Settings
from pbrsr_jobs.store import resolve_options
from tests.service_support import REPO
from worker.runner import _preload


def test_preload_default_is_the_default_prior(monkeypatch):
    monkeypatch.delenv("PBRSR_PRELOAD_PRIORS", raising=False)
    assert Settings(_env_file=None).preload_priors == [DEFAULT_PRIOR]


def test_docs_give_the_default_prior_as_the_preload_default():
    text = (REPO / "docs" / "SERVICE.md").read_text()
    row = re.search(r"^\| `PBRSR_PRELOAD_PRIORS` \| `([^`]*)` \|", text, flags=re.M)
    assert row is not None and row.group(1) == DEFAULT_PRIOR


def test_a_default_prior_job_reuses_the_preloaded_instance(monkeypatch, tmp_path):
    builds: list[str] = []
    build = registry._build

    def counting_build(name: str, device: torch.device):
        builds.append(name)
        return build(name, device)

    reads: list[object] = []
    from pbrsr_core.prior import texture

    load_network = texture.load_network

    def counting_load_network(path):
        reads.append(path)
        return load_network(path)

    monkeypatch.setattr(registry, "_build", counting_build)
    monkeypatch.setattr(texture, "load_network", counting_load_network)
    clear_cache()
    try:
        device = resolve_device("cpu")
        _preload([DEFAULT_PRIOR], device)  # what build_worker does at start-up
        assert builds[0] == DEFAULT_PRIOR and reads
        preloaded = load_prior(DEFAULT_PRIOR, device)
        builds.clear()
        reads.clear()

        # a job with no prior option, as run_job resolves it on this worker
        settings = Settings(_env_file=None, storage_dir=tmp_path, preload_priors=[])
        options = resolve_options({}, settings, device=str(device))
        assert options.prior == DEFAULT_PRIOR
        assert load_prior(options.prior, resolve_device(options.device)) is preloaded
        assert builds == [] and reads == []  # no weights read again
    finally:
        clear_cache()


def test_deployment_files_do_not_preload_another_prior():
    for path in ("docker-compose.yml", "deploy/pbrsr.env.example", "deploy/Dockerfile"):
        text = (REPO / path).read_text()
        values = re.findall(r"^\s*PBRSR_PRELOAD_PRIORS\s*[:=]\s*(\S*)", text, flags=re.M)
        assert all(DEFAULT_PRIOR in v.split(",") for v in values), (path, values)
