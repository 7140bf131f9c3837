"""Shared test setup: every test runs on the CPU device."""

import os

import pytest

os.environ.setdefault("CUDA_VISIBLE_DEVICES", "")


@pytest.fixture(scope="session")
def wp_cpu():
    """Warp, initialized once per session, quiet, with the CPU device as default."""
    import warp as wp

    wp.config.quiet = True
    wp.init()
    wp.set_device("cpu")
    return wp
