"""Shared fixtures. Random tests are seeded so a failure reproduces."""

from __future__ import annotations

import subprocess
from pathlib import Path

import numpy as np
import pytest

import cochlea

DATA = Path(__file__).parent / "data"
ROOT = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="session")
def program() -> Path:
    """``make embedded``, as a user builds it (up to date: make rebuilds only what changed),
    without a warning: build/cochlea-embedded."""
    done = subprocess.run(["make", "--no-print-directory", "embedded"], cwd=ROOT,
                          capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    assert "warning" not in done.stderr
    return ROOT / "build" / "cochlea-embedded"


@pytest.fixture
def rng():
    return np.random.default_rng(20261122)


@pytest.fixture(scope="session")
def serial_arm1():
    return cochlea.model("serial", arm="arm1")


def random_state(rng, n, scale=2.0):
    """A random (q, qd, qdd) of n joints: angles over the full circle, rates of order one."""
    return (rng.uniform(-np.pi, np.pi, n), rng.uniform(-scale, scale, n),
            rng.uniform(-scale, scale, n))


def ev(f, *args):
    """Evaluate a CasADi Function to a numpy array (vector results flattened)."""
    out = np.array(f(*args))
    return out.ravel() if out.shape[1] == 1 else out


def assert_periods_allocate_nothing(backend, x: np.ndarray, tau: np.ndarray,
                                    warmup: int = 200, periods: int = 5000) -> None:
    """A backend's per-period path (read into ``x``, write ``tau``) makes no buffer, list or
    array: after a warm-up, ``periods`` more periods leave Python's allocated blocks where they
    were (a per-period allocation would add thousands; 50 allows the interpreter's own)."""
    import gc
    import sys

    for _ in range(warmup):
        assert backend.read(x) and backend.write(tau)
    gc.collect()
    before = sys.getallocatedblocks()
    for _ in range(periods):
        backend.read(x)
        backend.write(tau)
    gc.collect()
    assert sys.getallocatedblocks() - before < 50
