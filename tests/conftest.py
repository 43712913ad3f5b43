"""Shared test settings: one on-disk compilation cache for the whole session, and quick
compilation.

Several tests compile the same small training program (in this process, in the other
pytest-xdist worker, and in subprocesses of ``python -m ccrjax.train``); with a shared
cache, the second compilation of a program is a disk read. A cached program is the same
executable, so no result depends on whether it came from the cache.

The tests' programs are small and run for moments, so compiling them is most of the
suite's time: XLA's CPU backend compiles them at its lowest optimisation level
(``--xla_backend_optimization_level=0``, about half the compile time). Every comparison
in the suite is between programs compiled alike or against tolerances, and
``tests/test_world.py`` still matches the maintained MPE to 1e-5.

On a GPU, JAX computes float32 matrix products in TensorFloat32 by default (10-bit
mantissas), which the comparisons against float64 references and their float32
tolerances were never meant to absorb: the suite runs them at full float32 precision, as
the CPU always does (there the setting changes nothing). The experiments keep JAX's default;
``python experiments/ccr_signal.py --matmul tf32`` measures what TensorFloat32 does to
CCR's signal.
"""

from __future__ import annotations

import os
import shutil
import tempfile

import jax
import pytest

_FLAG = "--xla_backend_optimization_level=0"
if _FLAG not in os.environ.get("XLA_FLAGS", ""):
    os.environ["XLA_FLAGS"] = f"{os.environ.get('XLA_FLAGS', '')} {_FLAG}".strip()

# On a GPU each pytest-xdist worker, and each subprocess, would reserve 75% of the device's
# memory as JAX starts, and the second could not start: take memory as it is needed.
os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")

# Full float32 matrix products on a GPU too, here and in subprocesses (see above).
os.environ["JAX_DEFAULT_MATMUL_PRECISION"] = "highest"
jax.config.update("jax_default_matmul_precision", "highest")

# One cache for the whole run, made by the process pytest started in: pytest-xdist's workers
# inherit its environment (they start after this file is read) and use the same folder, and
# that process removes it when the run ends (pytest_unconfigure below), so repeated runs
# leave nothing behind in the temporary folder.
_CACHE_VARIABLE = "CCRJAX_TEST_XLA_CACHE"
_SHARED = os.environ.get(_CACHE_VARIABLE) if "PYTEST_XDIST_WORKER" in os.environ else None
_OWN_CACHE = _SHARED is None or not os.path.isdir(_SHARED)
_CACHE = tempfile.mkdtemp(prefix="ccrjax-test-xla-") if _OWN_CACHE else _SHARED
os.environ[_CACHE_VARIABLE] = _CACHE
jax.config.update("jax_compilation_cache_dir", _CACHE)


def pytest_unconfigure(config: pytest.Config) -> None:
    """Remove the run's compilation cache from the process that made it, after its workers."""
    if _OWN_CACHE:
        shutil.rmtree(_CACHE, ignore_errors=True)


@pytest.fixture(scope="session")
def subprocess_env() -> dict[str, str]:
    """An environment for subprocesses that shares this session's compilation cache."""
    env = dict(os.environ)
    env["JAX_COMPILATION_CACHE_DIR"] = _CACHE
    env["PYTHONUNBUFFERED"] = "1"
    return env



@pytest.fixture
def kill_grid_in_program(monkeypatch: pytest.MonkeyPatch):
    """``arm(n)``: the experiments' grid (:func:`experiments.tables_grid.run_grid`) is killed
    (``KeyboardInterrupt``) as it writes the cells of the ``n``-th program it trains from
    then on, counted over its calls, as a Ctrl-C would be; ``arm(None)`` disarms it."""
    from experiments import tables_grid

    real_cells_of = tables_grid.cells_of

    def arm(n: int | None) -> None:
        calls: list[int] = []

        def cells_of(*args):
            calls.append(1)
            if len(calls) == n:
                raise KeyboardInterrupt
            return real_cells_of(*args)

        monkeypatch.setattr(tables_grid, "cells_of", real_cells_of if n is None else cells_of)

    return arm
