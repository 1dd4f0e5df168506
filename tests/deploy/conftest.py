"""The images every Docker test of this folder runs, built once per session (tests/deploy/docker_stack.py)."""

from __future__ import annotations

import pytest

from tests.deploy.docker_stack import Images, base_image_unavailable_reason, docker_unavailable_reason


@pytest.fixture(scope="session")
def images() -> Images:
    reason = docker_unavailable_reason() or base_image_unavailable_reason()
    if reason:
        pytest.skip(reason)
    built = Images()
    built.build()
    return built
