"""Shared fixtures of the engine's tests."""
import os

import pytest


@pytest.fixture
def numba_cache(request, monkeypatch, tmp_path_factory):
    """A private compiled-code cache for the compiled-path tests: pytest's cache directory
    keeps the compiled code between runs; without the cache plugin (-p no:cacheprovider) one
    temporary folder per session still isolates the tests from ~/.cache (generated modules
    are also cached in-process)."""
    store = getattr(request.config, "cache", None)
    folder = store.mkdir("fwdstep-numba") if store is not None else \
        tmp_path_factory.getbasetemp() / "fwdstep-numba"
    os.makedirs(folder, exist_ok=True)
    os.chmod(folder, 0o700)
    monkeypatch.setenv("FWDSTEP_CACHE_DIR", str(folder))
    return folder
