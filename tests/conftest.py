"""Shared test settings: one on-disk compilation cache for the whole session.

Several tests compile the same small training program (in this process and in
subprocesses of ``python -m ccrjax.train``); with a shared cache, the second
compilation of a program is a disk read. A cached program is the same
executable, so no result depends on whether it came from the cache.
"""

from __future__ import annotations

import os
import tempfile

import jax
import pytest

_CACHE = tempfile.mkdtemp(prefix="ccrjax-test-xla-")
jax.config.update("jax_compilation_cache_dir", _CACHE)


@pytest.fixture(scope="session")
def subprocess_env() -> dict[str, str]:
    """An environment for subprocesses that shares this session's compilation cache."""
    env = dict(os.environ)
    env["JAX_COMPILATION_CACHE_DIR"] = _CACHE
    env["PYTHONUNBUFFERED"] = "1"
    return env
